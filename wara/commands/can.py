"""``wara can busload|dump|record``: the IPC <-> PLC CAN link from the command line.

Examples::

    wara can busload --json                  # load of the default configuration
    wara can dump --count 20                 # decode live traffic with names and units
    wara can record run.blf --duration 10    # python-can log; replay: python -m can.player
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import can

from config import load_project
from config.numbers import decimal, integer, integers
from plc_bridge import BusOpenError, FrameCodec, bus_load, load_catalog, open_bus
from wara.cli import EXIT_FAILED, EXIT_OK, UsageError

#: Log formats ``wara can record`` writes (python-can picks the writer by suffix).
RECORD_SUFFIXES = (".blf", ".asc", ".log")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("can", help="CAN link to the PLC: bus load, live decode, recording")
    verbs = p.add_subparsers(dest="can_command", metavar="VERB")
    verbs.required = True

    b = verbs.add_parser("busload", help="bus load from the DBC and the configured rates")
    b.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    b.add_argument("--json", action="store_true", help="print JSON")
    b.add_argument(
        "--active",
        type=integers(),
        default=None,
        help="comma-separated can_index list of the active group (default: can.active_groups)",
    )
    b.add_argument(
        "--walk",
        action="store_true",
        help="the load of each walk phase's active group (it changes with the phase)",
    )
    b.set_defaults(func=_busload)

    d = verbs.add_parser("dump", help="decode live traffic with names, units and E2E status")
    d.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    d.add_argument("--count", type=integer, default=None, help="stop after N frames")
    d.add_argument("--duration", type=decimal, default=None, help="stop after S seconds")
    d.add_argument("--json", action="store_true", help="one JSON object per frame")
    d.set_defaults(func=_dump)

    r = verbs.add_parser("record", help="write live traffic to a python-can log (.blf/.asc/.log)")
    r.add_argument("file", help="output file; the suffix picks the format")
    r.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    r.add_argument("--count", type=integer, default=None, help="stop after N frames")
    r.add_argument("--duration", type=decimal, default=None, help="stop after S seconds")
    r.set_defaults(func=_record)


def _busload(args: argparse.Namespace) -> int:
    # This command reports the bus-load rule itself (the table, OVER BUDGET, exit 1);
    # every other cross-check refuses the project as everywhere (config.crosscheck).
    cfg = load_project(args.config, skip=("bus-load-within-budget",))
    active = None if args.active is None else list(args.active)
    if args.walk:
        return _walk_busload(cfg, args.json)
    load = bus_load(cfg, active)
    if args.json:
        print(json.dumps(load.as_dict(), indent=2))
    else:
        head = ("message", "id", "dlc", "bits", "cycle ms", "fps", "load %")
        print("{:<18} {:>5} {:>3} {:>4} {:>8} {:>7} {:>7}".format(*head))
        for m in load.messages:
            star = "*" if m.active else " "
            print(
                f"{m.name:<18} {m.frame_id:>5} {m.dlc:>3} {m.bits_per_frame:>4} "
                f"{m.cycle_ms:>7.1f}{star} {m.frames_per_s:>7.1f} {m.load_percent:>7.3f}"
            )
        verdict = "OK" if load.ok else "OVER BUDGET"
        print(
            f"total: {load.frames_per_s:.0f} frames/s, {load.bits_per_s:.0f} bit/s = "
            f"{load.load_percent:.2f} % of {load.bitrate} bit/s "
            f"(budget {load.max_load_percent} %: {verdict}); * = active group "
            f"{list(load.active_cylinders)} at {load.loop_rate_hz:g} Hz"
        )
    return EXIT_OK if load.ok else EXIT_FAILED


def _walk_busload(cfg: Any, as_json: bool) -> int:
    """Each walk phase's active group and its bus load."""
    from ipc_app.control.walk import walk_active_group
    from ipc_app.planner.walk import PHASES

    if cfg.walking is None:
        raise UsageError("the project has no frames and walking sections: it cannot walk")
    rows = []
    for key, name in PHASES.items():
        group = walk_active_group(cfg, key)
        load = bus_load(cfg, group)
        rows.append(
            {
                "phase": key,
                "name": name,
                "active_cylinders": sorted(group),
                "load_percent": round(load.load_percent, 2),
                "max_load_percent": load.max_load_percent,
                "ok": load.ok,
            }
        )
    ok = all(r["ok"] for r in rows)
    if as_json:
        print(json.dumps({"bitrate": cfg.can.bitrate, "ok": ok, "phases": rows}, indent=2))
    else:
        for r in rows:
            print(
                f"phase {r['phase']:<3} {r['name']:<14} {r['load_percent']:6.2f} %  "
                f"active {r['active_cylinders']}"
            )
        print(f"every phase within {rows[0]['max_load_percent']} %: {'OK' if ok else 'NO'}")
    return EXIT_OK if ok else EXIT_FAILED


def _open_observer(config: str | None) -> can.BusABC:
    cfg = load_project(config)
    try:
        return open_bus(cfg.can)  # no filter: an observer sees everything
    except BusOpenError as exc:
        raise UsageError(str(exc)) from None


def _frames(bus: can.BusABC, count: int | None, duration: float | None) -> Any:
    """Received frames until ``count`` or ``duration`` (or forever)."""
    t_end = None if duration is None else time.monotonic() + duration
    n = 0
    while count is None or n < count:
        timeout = 0.2 if t_end is None else min(0.2, t_end - time.monotonic())
        if timeout <= 0:
            return
        msg = bus.recv(timeout)
        if msg is not None:
            n += 1
            yield msg


def describe(msg: can.Message, codecs: dict[int, FrameCodec], db: Any) -> dict[str, Any]:
    """Decode one frame with cantools (names, units, value tables) plus its E2E status."""
    out: dict[str, Any] = {
        "t": round(msg.timestamp, 6),
        "id": f"0x{msg.arbitration_id:03X}",
        "data": bytes(msg.data).hex(" ").upper(),
    }
    if msg.is_error_frame:
        out["name"] = "ERROR_FRAME"
        return out
    codec = codecs.get(msg.arbitration_id)
    if codec is None or msg.is_extended_id:
        out["name"] = "?"
        return out
    out["name"] = codec.name
    data = bytes(msg.data)
    out["e2e"] = {
        "crc_ok": codec.check_crc(data),
        "counter": data[1] & 0x0F if len(data) > 1 else None,
    }
    try:
        decoded = db.decode_message(msg.arbitration_id, data, decode_choices=True)
    except Exception as exc:  # a wrong-length frame: show why, keep dumping
        out["error"] = str(exc)
        return out
    msg_def = db.get_message_by_frame_id(msg.arbitration_id)
    signals = {}
    for sig in msg_def.signals[2:]:
        v = decoded[sig.name]
        signals[sig.name] = f"{v} {sig.unit}".strip() if not isinstance(v, str) else str(v)
    out["signals"] = signals
    return out


def _dump(args: argparse.Namespace) -> int:
    cat = load_catalog()
    codecs = {m.frame_id: FrameCodec(m) for m in cat.messages}
    bus = _open_observer(args.config)
    try:
        for msg in _frames(bus, args.count, args.duration):
            d = describe(msg, codecs, cat.database)
            if args.json:
                print(json.dumps(d), flush=True)
                continue
            e2e = d.get("e2e")
            tag = ""
            if e2e is not None:
                tag = f"[crc {'ok' if e2e['crc_ok'] else 'BAD'} ctr {e2e['counter']}] "
            sigs = " ".join(f"{k}={v}" for k, v in d.get("signals", {}).items())
            extra = d.get("error", "")
            print(f"{d['t']:.6f} {d['id']} {d['name']:<16} {tag}{sigs}{extra}", flush=True)
    finally:
        bus.shutdown()
    return EXIT_OK


def _record(args: argparse.Namespace) -> int:
    path = Path(args.file)
    if path.suffix.lower() not in RECORD_SUFFIXES:
        raise UsageError(
            f"{path}: unknown log format {path.suffix!r}; use one of {', '.join(RECORD_SUFFIXES)}"
        )
    bus = _open_observer(args.config)
    n = 0
    try:
        with can.Logger(str(path)) as logger:
            for msg in _frames(bus, args.count, args.duration):
                # Log formats number their channels (BLF: 16-bit, 1-based) and python-can
                # derives the number from the name's trailing digits, so a bus channel
                # such as "vcan0" or a multicast group would be written wrongly or not
                # at all: the log has one channel, 1.
                msg.channel = 1
                logger.on_message_received(msg)
                n += 1
    finally:
        bus.shutdown()
        print(f"wara can record: {n} frames written to {path}", file=sys.stderr)
    return EXIT_OK
