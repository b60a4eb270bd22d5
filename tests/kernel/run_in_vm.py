"""Run a command inside a throw-away Linux VM that has SocketCAN (``vcan0``).

    python3 tests/kernel/run_in_vm.py [--no-install] [--kvm] [--require] [--] [COMMAND ...]

Without COMMAND it runs the kernel tests: ``python -m pytest -m kernel tests/kernel
tests/test_plc_link.py`` (every test marked ``kernel``: tests/kernel/ and the SocketCAN
class of tests/test_plc_link.py).

How: virtme-ng (PyPI ``virtme-ng``) boots Debian's distribution kernel
(``linux-image-amd64``, which ships ``vcan.ko``) in qemu with this machine's root file
system shared read-only (``/etc``, ``/opt``, ``/usr``, ``/var``, ``/tmp`` get a
throw-away overlay) and this repository shared read-write, so the project's venv
resolves inside. The guest loads ``vcan``, brings up ``vcan0``, runs COMMAND as root
in this repository with ``WARA_KERNEL_VM=1`` and powers off; COMMAND's exit code is
this script's.

What it installs where missing (as root; apt-get, then pip into the running
interpreter, or into ``.venv`` of this repository when run from outside a venv):
``qemu-system-x86``, ``linux-image-amd64``, ``can-utils``, ``busybox-static``,
``virtme-ng``.

The accelerator is qemu's TCG (software emulation) unless ``--kvm`` (or
``WARA_VM_KVM=1``): KVM is much faster where nested virtualization works, but where
it does not, qemu can hang at boot instead of failing. Where the VM cannot start
(not Linux on x86-64, packages cannot be installed, no kernel with vcan, qemu fails,
no boot within ``--boot-timeout-s``) the script prints one line,
``kernel tests: skipped: <reason>``, and exits 0 (1 with ``--require``). Once the
guest has booted, every failure is COMMAND's: its exit code, or 1 when the whole run
exceeds ``--timeout-s``. See docs/kernel-tests.md.
"""

from __future__ import annotations

import argparse
import glob
import os
import platform
import shlex
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
APT_PACKAGES = ("qemu-system-x86", "linux-image-amd64", "can-utils", "busybox-static")
#: Every test module with ``kernel`` tests (tests/test_kernel_vm.py keeps it complete);
#: naming them spares the guest importing the whole suite (slow on an emulated CPU).
KERNEL_TEST_PATHS = ("tests/kernel", "tests/test_plc_link.py")
#: The tests' files (logs, candump) stay in out/kernel-tests/ of the repository after
#: the run, for a look at a failure.
#: Without hypothesis' plugin (no kernel test uses it; importing it alone takes minutes on
#: the guest's emulated CPU) and pytest's cache.
DEFAULT_COMMAND = (
    "{python}", "-m", "pytest", "-p", "no:hypothesispytest", "-p", "no:cacheprovider",
    "-m", "kernel", "-rs", "--durations=0", "--basetemp=out/kernel-tests",
    *KERNEL_TEST_PATHS,
)  # fmt: skip
MARKER = "booted"


class CannotStart(Exception):
    """The VM cannot start here; the message is the one-line reason."""


def say(msg: str) -> None:
    print(f"run_in_vm: {msg}", file=sys.stderr, flush=True)


def is_static_elf(path: str) -> bool:
    """True for a 64-bit little-endian ELF without a program interpreter (PT_INTERP)."""
    try:
        with open(path, "rb") as f:
            head = f.read(64)
            if head[:4] != b"\x7fELF" or head[4] != 2 or head[5] != 1:
                return False
            phoff = int.from_bytes(head[32:40], "little")
            phentsize = int.from_bytes(head[54:56], "little")
            phnum = int.from_bytes(head[56:58], "little")
            f.seek(phoff)
            table = f.read(phentsize * phnum)
    except OSError:
        return False
    types = [int.from_bytes(table[i : i + 4], "little") for i in range(0, len(table), phentsize)]
    return 3 not in types  # PT_INTERP


def _static_busybox() -> str | None:
    """virtme-ng builds the guest's initramfs with a statically linked busybox."""
    for name in ("busybox-static", "busybox.static", "busybox"):
        path = shutil.which(name)
        if path is not None and is_static_elf(path):
            return path
    return None


def vcan_kernels() -> list[str]:
    """``/boot/vmlinuz-*`` images whose modules include vcan, newest first."""
    found = []
    for image in glob.glob("/boot/vmlinuz-*"):
        version = image.removeprefix("/boot/vmlinuz-")
        mods = glob.glob(f"/lib/modules/{version}/kernel/drivers/net/can/vcan.ko*")
        if mods and os.access(image, os.R_OK):
            found.append((os.path.getmtime(image), image))
    return [image for _mtime, image in sorted(found, reverse=True)]


def missing_packages() -> list[str]:
    missing = []
    if shutil.which("qemu-system-x86_64") is None:
        missing.append("qemu-system-x86")
    if not vcan_kernels():
        missing.append("linux-image-amd64")
    if shutil.which("candump") is None or shutil.which("cansend") is None:
        missing.append("can-utils")
    if _static_busybox() is None:
        missing.append("busybox-static")
    return missing


def install_packages(pkgs: list[str]) -> None:
    if shutil.which("apt-get") is None:
        raise CannotStart(f"missing {' '.join(pkgs)} and no apt-get to install them")
    if os.geteuid() != 0:
        raise CannotStart(f"missing {' '.join(pkgs)}: run as root or apt-get install them")
    say(f"installing {' '.join(pkgs)} (apt-get)")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    lock = ["-o", "DPkg::Lock::Timeout=600"]
    for cmd in (
        ["apt-get", *lock, "update", "-qq"],
        ["apt-get", *lock, "install", "-y", "-qq", "--no-install-recommends", *pkgs],
    ):
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            last = (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-1:] or ["?"]
            raise CannotStart(f"{' '.join(cmd[:3])} failed: {last[0]}")


def have_virtme() -> bool:
    probe = "import virtme_ng.run"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


def install_virtme() -> None:
    say(f"installing virtme-ng into {sys.prefix} (pip)")
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "virtme-ng"],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0 or not have_virtme():
        last = (proc.stderr.strip() or "import failed").splitlines()[-1]
        raise CannotStart(f"pip install virtme-ng failed: {last}")


#: Host variables the guest gets too (the guest starts with a minimal environment):
#: pip's configuration and proxies, so pip resolves as it does here.
FORWARD_PREFIXES = ("PIP_", "CI", "LANG", "LC_")
FORWARD_NAMES = ("http_proxy", "https_proxy", "no_proxy", "HTTP_PROXY", "HTTPS_PROXY", "NO_PROXY")


def forwarded_env() -> list[str]:
    return [
        f"export {k}={shlex.quote(v)}"
        for k, v in sorted(os.environ.items())
        if (k.startswith(FORWARD_PREFIXES) or k in FORWARD_NAMES) and k.isidentifier()
    ]


def build_wheelhouse(dest: Path) -> None:
    """The project's wheel, built here from this checkout, for install.sh's offline
    install in the guest (``--wheelhouse``; tests/kernel/test_deploy_vcan.py): the guest
    has no network, and building the package there (pip's isolated build environment,
    setuptools' hooks in fresh interpreters) costs minutes on its emulated CPU. Best
    effort: without it the test fails with install.sh's own message."""
    dest.mkdir()
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
         "-w", str(dest), str(REPO)],
        capture_output=True,
        text=True,
        check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        last = (proc.stderr.strip() or "?").splitlines()[-1]
        say(f"no wheel of the project for the guest's install.sh: {last}")


#: Caches the guest reads instead of building them on its emulated CPU, prepared on this
#: machine before the boot (:func:`prewarm`) in this repository's out/ (shared with the
#: guest read-write). numba's cache is keyed by the CPU: both sides compile for the
#: generic x86-64 CPU, so the guest loads what was compiled here.
CACHE_ENV = {
    "NUMBA_CACHE_DIR": str(REPO / "out" / "numba-vm"),
    "NUMBA_CPU_NAME": "generic",
    "MPLCONFIGDIR": str(REPO / "out" / "mplconfig"),
    "MPLBACKEND": "Agg",
}
#: Compiles the simulator's plant as the HIL test runs it (tests/kernel/test_hil_vcan.py:
#: the rigid rig, 0.5 ms step; stepped and its status line printed) and builds
#: matplotlib's font cache where it is installed.
PREWARM = """
import importlib.util
import can
from config import load_project
from config.hil_scenario import HilScenario
from hil_sim.simulator import HilSimulator
scenario = HilScenario.model_validate({"name": "prewarm", "plant": {"step_ms": 0.5}})
with can.Bus(interface="virtual", channel="prewarm") as bus:
    sim = HilSimulator(load_project(), bus, scenario)
    sim.step(0.01)
    sim.status_line()
    sim.close()
if importlib.util.find_spec("matplotlib") is not None:
    import matplotlib.font_manager
"""


def prewarm() -> None:
    """Fill :data:`CACHE_ENV`'s caches here (half a minute the first time, seconds after);
    best effort: where it fails the guest builds them itself, slowly."""
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-c", PREWARM],
        env={**os.environ, **CACHE_ENV},
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        last = (proc.stderr.strip() or "?").splitlines()[-1]
        say(f"prewarming the guest's caches failed: {last}")
    else:
        say(f"guest's caches (numba, matplotlib) ready after {time.monotonic() - t0:.0f} s")


def guest_script(command: list[str], marker: Path, wheelhouse: Path) -> str:
    """What the guest runs: mark the boot, bring up vcan0, run the command in the repo."""
    return "\n".join(
        [
            f"echo ok > {shlex.quote(str(marker))}",
            "modprobe vcan && ip link add dev vcan0 type vcan && ip link set vcan0 up"
            " || { echo 'run_in_vm: cannot bring up vcan0 in the guest' >&2; exit 1; }",
            f"cd {shlex.quote(str(REPO))}",
            *forwarded_env(),
            "export WARA_KERNEL_VM=1 PYTHONUNBUFFERED=1",
            # pytest's plugins installed beside it (hypothesis, xdist): none is used here
            "export PYTEST_DISABLE_PLUGIN_AUTOLOAD=1",
            *(f"export {k}={shlex.quote(v)}" for k, v in CACHE_ENV.items()),
            f"export WARA_VM_WHEELHOUSE={shlex.quote(str(wheelhouse))}",
            f"export PATH={shlex.quote(str(Path(sys.executable).parent))}:$PATH",
            f"exec {shlex.join(command)}",
        ]
    )


def qemu_opts(kvm: bool) -> list[str]:
    """qemu options beyond virtme-ng's: under TCG one host thread per vCPU; and each of
    virtme-ng's virtio-serial devices (the guest's stdin, stdout, ...; one port used) at 2
    ports instead of 31, whose hundreds of event fds qemu's main loop polls on every
    wake-up (it used more CPU than both vCPUs with them)."""
    opts = [] if kvm else ["-accel", "tcg,thread=multi"]
    return [*opts, "-global", "virtio-serial-pci.max_ports=2"]


def _stop(proc: subprocess.Popen[bytes]) -> None:
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=10)
            return
        except subprocess.TimeoutExpired:
            continue


def boot(command: list[str], args: argparse.Namespace) -> int:
    kernels = vcan_kernels()
    if not kernels:
        raise CannotStart(
            "no /boot/vmlinuz-* with a vcan module (apt-get install linux-image-amd64)"
        )
    kernel = kernels[0]
    with tempfile.TemporaryDirectory(prefix="wara-vm-") as tmp:
        marker = Path(tmp) / MARKER
        wheelhouse = Path(tmp) / "wheels"
        build_wheelhouse(wheelhouse)
        prewarm()
        (REPO / "out").mkdir(exist_ok=True)  # pytest's --basetemp needs its parent
        scripts = sysconfig.get_path("scripts")
        env = {**os.environ, "PATH": f"{scripts}:{os.environ.get('PATH', '/usr/bin:/bin')}"}
        vng = [
            sys.executable,
            "-c",
            "import sys; from virtme_ng.run import main; sys.argv[0] = 'vng'; sys.exit(main())",
            "--run",
            kernel,
            "--memory",
            args.memory,
            "--cpus",
            str(args.cpus),
            "--rwdir",
            str(REPO),
            "--rwdir",
            tmp,
            "--cwd",
            str(REPO),
        ]
        if not args.kvm:
            vng.append("--disable-kvm")
        # The script in a file on the shared directory: virtme-ng passes --exec on the
        # kernel's command line, which the kernel cuts at 2 KiB.
        script = Path(tmp) / "guest.sh"
        script.write_text(guest_script(command, marker, wheelhouse) + "\n")
        vng += ["--exec", f"sh {shlex.quote(str(script))}"]
        vng.append(f"--qemu-opts={' '.join(qemu_opts(args.kvm))}")  # greedy: the last option
        accel = "KVM" if args.kvm else "TCG (no KVM)"
        say(f"booting {kernel} in qemu, {accel}, {args.cpus} CPUs, {args.memory}")
        t0 = time.monotonic()
        proc = subprocess.Popen(vng, env=env, stdin=subprocess.DEVNULL, start_new_session=True)
        booted_at: float | None = None
        try:
            while True:
                try:
                    rc = proc.wait(timeout=1.0)
                    break
                except subprocess.TimeoutExpired:
                    pass
                now = time.monotonic() - t0
                if booted_at is None and marker.exists():
                    booted_at = now
                    say(f"guest up after {now:.0f} s")
                if booted_at is None and now > args.boot_timeout_s:
                    raise CannotStart(f"the VM did not boot within {args.boot_timeout_s:g} s")
                if now > args.timeout_s:
                    say(f"FAILED: the run exceeded {args.timeout_s:g} s; stopped")
                    return 1
        finally:  # a timeout, Ctrl-C or SIGTERM: the VM goes with this script
            if proc.poll() is None:
                _stop(proc)
        if booted_at is None and not marker.exists():
            raise CannotStart(f"qemu/virtme-ng exited {rc} before the guest booted (output above)")
        say(f"guest finished after {time.monotonic() - t0:.0f} s, exit {rc}")
        return rc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Run COMMAND (default: the kernel tests) in a VM with SocketCAN (vcan0)."
    )
    ap.add_argument("--no-install", action="store_true", help="install nothing; skip if missing")
    ap.add_argument(
        "--kvm",
        action="store_true",
        default=os.environ.get("WARA_VM_KVM") == "1",
        help="use KVM instead of TCG (where nested virtualization works)",
    )
    ap.add_argument(
        "--require", action="store_true", help="exit 1, not 0, when the VM cannot start"
    )
    ap.add_argument("--memory", default="2G", help="guest memory (qemu -m), default 2G")
    ap.add_argument("--cpus", type=int, default=2, help="guest CPUs, default 2")
    ap.add_argument("--boot-timeout-s", type=float, default=600.0)
    ap.add_argument("--timeout-s", type=float, default=3600.0, help="limit for the whole run")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="command to run in the guest")
    args = ap.parse_args(argv)
    command = [c for c in args.command if c != "--"] if args.command[:1] == ["--"] else args.command
    if not command:
        command = [c.format(python=sys.executable) for c in DEFAULT_COMMAND]
    try:
        if platform.system() != "Linux" or platform.machine() not in ("x86_64", "AMD64"):
            raise CannotStart(
                f"needs Linux on x86-64, this is {platform.system()} {platform.machine()}"
            )
        missing = missing_packages()
        if missing:
            if args.no_install:
                raise CannotStart(f"missing {' '.join(missing)} (--no-install)")
            install_packages(missing)
            still = missing_packages()
            if still:
                raise CannotStart(f"still missing after apt-get: {' '.join(still)}")
        if not have_virtme():
            if args.no_install:
                raise CannotStart("virtme-ng is not installed (--no-install)")
            install_virtme()
        return boot(command, args)
    except CannotStart as exc:
        print(f"kernel tests: skipped: {exc}", flush=True)
        return 1 if args.require else 0


def _reexec_in_repo_venv() -> None:
    """Outside a venv, run under this repository's .venv (pip may not install system-wide)."""
    venv_python = REPO / ".venv" / "bin" / "python"
    if sys.prefix == sys.base_prefix and venv_python.exists():
        os.execv(str(venv_python), [str(venv_python), __file__, *sys.argv[1:]])


def _terminate(_signum: int, _frame: object) -> None:
    raise SystemExit(143)


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, _terminate)
    _reexec_in_repo_venv()
    sys.exit(main())
