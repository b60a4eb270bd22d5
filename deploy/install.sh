#!/usr/bin/env bash
# Install the W-ARa IPC service on an industrial PC (Debian/Ubuntu with systemd).
#
#   sudo deploy/install.sh [--config PROJECT.yaml] [--prefix /opt/wara] [--vcan]
#                          [--extras sim,plot,opcua] [--wheelhouse DIR] [--no-start]
#                          [--dry-run]
#
# Steps (each printed as "+ command"; --dry-run prints them and changes nothing):
#   1. system user and group "wara" (no login shell, home /var/lib/wara)
#   2. a virtualenv under PREFIX/venv with this source tree installed (pip): the service
#      alone; --extras adds optional parts (plot: matplotlib for the acceptance report,
#      sim: numba for the HIL simulator, opcua: the OPC UA server; with opcua the
#      server certificate is created under /var/lib/wara/opcua/pki, owned by wara);
#      --wheelhouse DIR installs offline: the package and every dependency as wheels from
#      DIR only (made where there is network: pip wheel -w DIR '.[EXTRAS]')
#   3. /etc/wara/project.yaml (kept if it exists; --config replaces it), validated
#   4. systemd-networkd files for can0 (BitRate from the project's can.bitrate),
#      and vcan0 with --vcan
#   5. /etc/systemd/system/wara-ipc.service (ExecStart under PREFIX), daemon-reload,
#      enable systemd-networkd and wara-ipc, start (unless --no-start)
# See docs/deploy.md.
set -euo pipefail

SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PREFIX=/opt/wara
CONFIG=""
VCAN=0
EXTRAS=""
WHEELHOUSE=""
START=1
DRY=0
ETC=/etc/wara
NETDIR=/etc/systemd/network
UNITDIR=/etc/systemd/system
USER_NAME=wara

usage() { sed -n '2,21p' "$0" | sed 's/^# \{0,1\}//'; }

while [ $# -gt 0 ]; do
  case "$1" in
    --prefix) PREFIX="$2"; shift 2 ;;
    --config) CONFIG="$2"; shift 2 ;;
    --vcan) VCAN=1; shift ;;
    --extras) EXTRAS="${2:-}"; shift 2 ;;
    --wheelhouse) WHEELHOUSE="${2:-}"; shift 2 ;;
    --no-start) START=0; shift ;;
    --dry-run) DRY=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) echo "install.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

run() {
  echo "+ $*"
  if [ "$DRY" -eq 0 ]; then "$@"; fi
}

if [ "$DRY" -eq 0 ] && [ "$(id -u)" -ne 0 ]; then
  echo "install.sh: run as root (sudo), or with --dry-run to see the steps" >&2
  exit 2
fi
case ",$EXTRAS," in
  *,,*) [ -z "$EXTRAS" ] || { echo "install.sh: --extras $EXTRAS: an empty name (use e.g. sim,plot)" >&2; exit 2; } ;;
esac
for extra in ${EXTRAS//,/ }; do
  case "$extra" in
    sim|plot|opcua) ;;
    *) echo "install.sh: --extras: unknown extra '$extra' (known: sim, plot, opcua)" >&2; exit 2 ;;
  esac
done
if [ -n "$WHEELHOUSE" ] && ! compgen -G "$WHEELHOUSE/wara_control-*.whl" >/dev/null; then
  echo "install.sh: --wheelhouse $WHEELHOUSE: no wara_control-*.whl there (pip wheel -w DIR .)" >&2
  exit 2
fi
if [ -n "$CONFIG" ] && [ ! -f "$CONFIG" ]; then
  echo "install.sh: --config $CONFIG: file not found" >&2
  exit 2
fi

echo "# 1. user"
if getent passwd "$USER_NAME" >/dev/null; then
  echo "# user $USER_NAME exists"
else
  run useradd --system --user-group --home-dir /var/lib/wara --no-create-home \
    --shell /usr/sbin/nologin --comment "W-ARa IPC service" "$USER_NAME"
fi

echo "# 2. virtualenv"
run install -d -m 0755 "$PREFIX"
run python3 -m venv "$PREFIX/venv"
if [ -n "$WHEELHOUSE" ]; then
  run "$PREFIX/venv/bin/pip" install --quiet --upgrade --no-index --find-links "$WHEELHOUSE" \
    "wara-control${EXTRAS:+[$EXTRAS]}"
else
  run "$PREFIX/venv/bin/pip" install --quiet --upgrade "$SRC${EXTRAS:+[$EXTRAS]}"
fi

echo "# 3. project configuration"
run install -d -m 0755 "$ETC"
if [ -n "$CONFIG" ]; then
  run install -m 0644 "$CONFIG" "$ETC/project.yaml"
elif [ -e "$ETC/project.yaml" ]; then
  echo "# keeping $ETC/project.yaml"
else
  run install -m 0644 "$SRC/config/projects/shanghai_airport_link.yaml" "$ETC/project.yaml"
fi
run "$PREFIX/venv/bin/wara" config validate "$ETC/project.yaml"

case ",$EXTRAS," in
  *,opcua,*)
    # The OPC UA server's certificate (kept if present), in the service's state directory,
    # where the project's relative opcua.pki_dir points (WorkingDirectory=%S/wara).
    echo "# 3b. OPC UA server certificate"
    run install -d -m 0700 -o "$USER_NAME" -g "$USER_NAME" /var/lib/wara /var/lib/wara/opcua
    run runuser -u "$USER_NAME" -- "$PREFIX/venv/bin/wara" opcua cert \
      --pki-dir /var/lib/wara/opcua/pki
    echo "# add users: sudo -u $USER_NAME $PREFIX/venv/bin/wara opcua adduser NAME --role operator --users-file /var/lib/wara/opcua/users.json"
    ;;
esac

# The CAN bit rate comes from the project (can.bitrate); read it with the installed
# package, or from the file to install when nothing is installed yet (dry run).
bitrate_of() {
  local py="$PREFIX/venv/bin/python"
  [ -x "$py" ] || py=python3
  PYTHONPATH="$SRC" "$py" - "$1" <<'PY' 2>/dev/null
import sys, yaml
print(int(((yaml.safe_load(open(sys.argv[1])) or {}).get("can") or {}).get("bitrate", 500000)))
PY
}
PROJECT_FILE="$ETC/project.yaml"
[ -n "$CONFIG" ] && PROJECT_FILE="$CONFIG"
[ -e "$PROJECT_FILE" ] || PROJECT_FILE="$SRC/config/projects/shanghai_airport_link.yaml"
BITRATE="$(bitrate_of "$PROJECT_FILE" || true)"
if ! [[ "$BITRATE" =~ ^[0-9]+$ ]]; then  # no python with PyYAML yet: read the key
  BITRATE="$(awk '/^can:/{c=1; next} c && /^[^ #]/{c=0} c && $1=="bitrate:"{print $2}' \
    "$PROJECT_FILE" | head -n1)"
fi
if ! [[ "$BITRATE" =~ ^[0-9]+$ ]]; then
  echo "install.sh: cannot read can.bitrate from $PROJECT_FILE" >&2
  exit 2
fi

echo "# 4. CAN network (systemd-networkd), can0 at $BITRATE bit/s"
run install -d -m 0755 "$NETDIR"
echo "+ sed 's/^BitRate=.*/BitRate=$BITRATE/' > $NETDIR/80-wara-can0.network"
if [ "$DRY" -eq 0 ]; then
  sed "s/^BitRate=.*/BitRate=$BITRATE/" "$SRC/deploy/network/80-wara-can0.network" \
    > "$NETDIR/80-wara-can0.network"
  chmod 0644 "$NETDIR/80-wara-can0.network"
fi
if [ "$VCAN" -eq 1 ]; then
  run install -m 0644 "$SRC/deploy/network/80-wara-vcan0.netdev" "$NETDIR/"
  run install -m 0644 "$SRC/deploy/network/80-wara-vcan0.network" "$NETDIR/"
  echo "+ echo vcan > /etc/modules-load.d/wara-vcan.conf"
  [ "$DRY" -eq 1 ] || echo vcan > /etc/modules-load.d/wara-vcan.conf
fi

echo "# 5. service"
echo "+ sed 's#/opt/wara/#$PREFIX/#' > $UNITDIR/wara-ipc.service"
if [ "$DRY" -eq 0 ]; then
  sed "s#/opt/wara/#$PREFIX/#" "$SRC/deploy/wara-ipc.service" > "$UNITDIR/wara-ipc.service"
  chmod 0644 "$UNITDIR/wara-ipc.service"
fi
run systemctl daemon-reload
run systemctl enable --now systemd-networkd
if [ "$START" -eq 1 ]; then
  run systemctl enable --now wara-ipc.service
else
  run systemctl enable wara-ipc.service
fi
echo "# done: systemctl status wara-ipc; journalctl -u wara-ipc -f; sudo -u wara $PREFIX/venv/bin/wara ctl status"
