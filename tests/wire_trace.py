"""Record the CAN wire and the run record of lockstep runs, to show that a refactor of
the service changed neither (docs/service.md, "Motions").

Every frame sent on a :func:`~plc_bridge.lockstep_bus.lockstep_pair` (both ends) is
written as one line ``<simulated time, us> <id, hex> <data, hex>``; the run record's
events (less the keys measured on the wall clock) and samples beside it. The runs are
the service's public requests through :class:`~wara.harness.Harness`, so the same file
runs on any checkout: run it with each checkout's own interpreter and compare::

    (cd OLD && .venv/bin/python NEW/tests/wire_trace.py record /tmp/old)
    (cd NEW && .venv/bin/python tests/wire_trace.py record /tmp/new)
    .venv/bin/python tests/wire_trace.py compare /tmp/old /tmp/new

Lockstep runs are deterministic on one machine; another CPU may round the simulator's
numba kernels differently, so the traces are compared between two checkouts on the
same machine, never against a stored file.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

WALL_CLOCK_KEYS = frozenset(
    {
        "solve_time_s",
        "solve_time_share_of_task_percent",
        "elapsed_s",
        "first_t_s",
        "last_t_s",
        "wall_time_s",
        "db",
        "note",
    }
)


@contextmanager
def recording(out: Path) -> Iterator[list[str]]:
    """Within the block, every frame sent on a lockstep bus goes to ``out`` (gzip); the
    time is the simulator's of the last harness built."""
    import wara.harness as harness_mod
    from plc_bridge import lockstep_bus

    lines: list[str] = []
    current: list[Any] = []
    bus = lockstep_bus.LockstepBus
    send0 = bus.send
    send_all0 = getattr(bus, "send_all", None)  # a batch of frames (the simulator's scans)
    init0 = harness_mod.Harness.__init__

    def write(msg: Any) -> None:
        t = current[-1].sim.t_s if current else -1.0
        lines.append(f"{round(t * 1e6)} {msg.arbitration_id:x} {bytes(msg.data).hex()}")

    def send(self: Any, msg: Any, timeout: float | None = None) -> None:
        write(msg)
        send0(self, msg, timeout)

    def send_all(self: Any, msgs: list[Any]) -> None:
        for msg in msgs:
            write(msg)
        assert send_all0 is not None
        send_all0(self, msgs)

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        current.append(self)
        init0(self, *args, **kwargs)

    bus.send = send  # type: ignore[method-assign]
    if send_all0 is not None:
        bus.send_all = send_all  # type: ignore[method-assign]
    harness_mod.Harness.__init__ = init  # type: ignore[method-assign]
    try:
        yield lines
    finally:
        bus.send = send0  # type: ignore[method-assign]
        if send_all0 is not None:
            bus.send_all = send_all0  # type: ignore[method-assign]
        harness_mod.Harness.__init__ = init0  # type: ignore[method-assign]
        with gzip.open(out, "wt") as f:
            f.write("\n".join(lines) + "\n")


def _recorder(run_dir: Path) -> Any:
    from config import load_project
    from ipc_app.service.core import ServiceCore
    from ipc_app.service.record import RunRecorder

    rec = RunRecorder(run_dir, ServiceCore.record_columns(load_project(None)))
    rec.start()
    return rec


def _harness(rec: Any, **kwargs: Any) -> Any:
    from config import load_project
    from ipc_app.service.modes import Mode
    from wara.harness import Harness

    h = Harness(load_project(None), None, mode="lockstep", record=rec, **kwargs)
    h.start()
    assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
    return h


def attitude(rec: Any, _tmp: Path) -> str:
    """Example 2 of the reference machine (wara demo's second)."""
    from wara.examples import EXAMPLES

    h = _harness(rec)
    try:
        res = h.run_example(*EXAMPLES[1])
        return f"passed {res.passed} duration_s {res.duration_s:.3f}"
    finally:
        h.close()


def walk(rec: Any, _tmp: Path) -> str:
    """One loaded step forward (wara walk --steps 1)."""
    from wara.walk import run_walk

    out = run_walk(None, 1, mode="lockstep", record=rec)
    return f"passed {out['passed']} distance_m {out['distance_m']}"


def place(rec: Any, _tmp: Path) -> str:
    """Ring 5's part placed from a deviation of the part before (wara ctl place)."""
    from ipc_app.model.placement import sheet_deviation
    from ipc_app.service.modes import Mode

    h = _harness(rec)
    try:
        out = h.core.request_place(5, sheet_deviation(6, -6, 0, 0, 0.03))
        assert out["ok"], out
        ok = h.wait_for(Mode.COMPLETE, 60.0)
        h.advance(1.0)
        return f"complete {ok} mode {h.core.modes.mode}"
    finally:
        h.close()


def place_ride_through(rec: Any, _tmp: Path) -> str:
    """A placement through eight short losses of the link (suspend, resume)."""
    from config.hil_scenario import HilScenario
    from ipc_app.model.placement import sheet_deviation
    from ipc_app.service.modes import Mode

    starts = (2.0, 2.3, 2.6, 2.9, 3.2, 3.6, 4.0, 4.5)
    events = [
        {"kind": "wire_stall", "start_s": t, "end_s": t + 0.06, "direction": "both"} for t in starts
    ]
    h = _harness(rec, scenario=HilScenario.model_validate({"events": events}))
    try:
        assert h.core.request_place(3, sheet_deviation(4, -4, 0, 0, 0))["ok"]
        ok = h.wait_for(Mode.COMPLETE, 60.0)
        return f"complete {ok} resumes {h.core.resumes}"
    finally:
        h.close()


def cycle(rec: Any, tmp: Path) -> str:
    """One ring's cycle (wara cycle --rings 1): walk, place, fixing, release, survey,
    record, walk back."""
    from wara.cycle import run_cycle

    out = run_cycle(None, 1, db_path=tmp / "acceptance.db", record=rec)
    return f"passed {out['passed']} error {out['error']}"


def walk_there_and_back(rec: Any, _tmp: Path) -> str:
    """One step forward, then one back (a walk taking over from a walk)."""
    from wara.walk import run_walk

    out = run_walk(None, 1, mode="lockstep", record=rec, directions=("forward", "back"))
    return f"passed {out['passed']} distance_m {out['distance_m']}"


def walk_ride_through(rec: Any, _tmp: Path) -> str:
    """A 60 ms stall of the wire while the travel pair moves (suspend, the walk's
    resume check, resume), then an operator's hold and unhold in a later phase."""
    from config.hil_scenario import HilScenario
    from ipc_app.service.modes import Mode
    from wara.walk import run_walk

    stall = {"kind": "wire_stall", "start_s": 3.0, "end_s": 3.06, "direction": "both"}
    held: list[float] = []

    def on_cycle(h: Any) -> None:
        t, mode = h.sim.t_s, h.core.modes.mode
        if not held and t >= 20.0 and mode == Mode.EXECUTE:
            held.append(t)
            h.core.request_hold()
        elif len(held) == 1 and t >= held[0] + 0.1 and mode == Mode.HELD:
            held.append(t)
            h.core.request_unhold()

    sc = HilScenario.model_validate({"events": [stall]})
    out = run_walk(None, 1, mode="lockstep", record=rec, scenario=sc, on_cycle=on_cycle)
    return f"passed {out['passed']} final {out['final_mode']} held {held}"


def hold_and_jog(rec: Any, _tmp: Path) -> str:
    """An adjustment held and unheld mid-way, then a jog in MANUAL."""
    from config import load_project
    from ipc_app.service.modes import Mode

    cfg = load_project(None)
    h = _harness(rec)
    try:
        assert h.core.request_adjust(2.0, -1.0)["ok"]
        assert h.wait_for(Mode.EXECUTE, 10.0)
        h.advance(3.0)
        h.core.request_hold()
        h.advance(0.1)
        h.core.request_unhold()
        assert h.wait_for(Mode.COMPLETE, 60.0), h.fault_note()
        h.advance(1.0)
        h.core.stop("to jog")
        h.advance(0.1)
        h.core.request_unit_mode("MANUAL")
        h.core.request_jog(cfg.layers.upper.cylinders[1], 2.0)
        ok = h.wait_for(Mode.COMPLETE, 30.0)
        h.advance(1.0)
        return f"jog complete {ok} mode {h.core.modes.mode}"
    finally:
        h.close()


SCENARIOS: dict[str, Callable[[Any, Path], str]] = {
    "walk_there_and_back": walk_there_and_back,
    "walk_ride_through": walk_ride_through,
    "hold_and_jog": hold_and_jog,
    "attitude": attitude,
    "walk": walk,
    "place": place,
    "place_ride_through": place_ride_through,
    "cycle": cycle,
}


def _event_line(line: str) -> str:
    """A run-record event without the keys measured on the wall clock, keys sorted."""
    obj = json.loads(line, object_hook=lambda d: {k: d[k] for k in d if k not in WALL_CLOCK_KEYS})
    return json.dumps(obj, sort_keys=True)


def record(out_dir: Path, names: list[str]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        with tempfile.TemporaryDirectory() as tmp:
            run_dir = Path(tmp) / "run"
            rec = _recorder(run_dir)
            try:
                with recording(out_dir / f"{name}.wire.gz") as lines:
                    note = SCENARIOS[name](rec, Path(tmp))
            finally:
                rec.stop()
            events = [_event_line(line) for line in (run_dir / "events.jsonl").open()]
            (out_dir / f"{name}.events").write_text("\n".join(events) + "\n")
            samples = sorted(run_dir.glob("samples.csv*"))
            data = b"".join(p.read_bytes() for p in samples)
            if samples and samples[0].suffix == ".gz":
                data = gzip.decompress(data)
            (out_dir / f"{name}.samples").write_bytes(data)
        print(f"{name}: {len(lines)} frames, {len(events)} events; {note}", flush=True)


def _first_difference(a: list[str], b: list[str]) -> str | None:
    for k, (x, y) in enumerate(zip(a, b, strict=False)):
        if x != y:
            return f"line {k + 1}: {x[:160]!r} != {y[:160]!r}"
    if len(a) != len(b):
        return f"lengths {len(a)} != {len(b)}"
    return None


def compare(old: Path, new: Path) -> int:
    bad = 0
    for f in sorted(old.iterdir()):
        g = new / f.name
        if not g.exists():
            print(f"{f.name}: missing in {new}")
            bad += 1
            continue
        opener = gzip.open if f.suffix == ".gz" else open
        with opener(f, "rt") as fa, opener(g, "rt") as fb:
            a, b = fa.read().splitlines(), fb.read().splitlines()
        diff = _first_difference(a, b)
        print(f"{f.name}: {len(a)} lines, " + ("identical" if diff is None else f"DIFFERS {diff}"))
        bad += diff is not None
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out_dir", type=Path)
    r.add_argument("names", nargs="*", help=f"of {', '.join(SCENARIOS)} (default: all)")
    c = sub.add_parser("compare")
    c.add_argument("old", type=Path)
    c.add_argument("new", type=Path)
    a = p.parse_args(argv)
    if a.cmd == "record":
        unknown = sorted(set(a.names) - set(SCENARIOS))
        if unknown:
            p.error(f"unknown scenario(s) {unknown}; one of {', '.join(SCENARIOS)}")
        record(a.out_dir, a.names or list(SCENARIOS))
        return 0
    return compare(a.old, a.new)


if __name__ == "__main__":
    sys.exit(main())
