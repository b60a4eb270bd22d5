"""``wara bench wire --baseline DIR``: the lockstep CAN wire of this checkout against
DIR's, frame for frame.

A change that is meant to be only faster (the codec, the supervision, the simulator's
scan) must leave every frame on the wire as it was. This records, through
:class:`wara.harness.Harness` in lockstep, every frame either node puts on the bus (its
simulated time, its sender, its id and data) for two runs: Example 1 (roll 2, pitch
1 deg) from the level start, and a walk of one step; then the same in DIR's checkout
with DIR's own interpreter (``DIR/.venv/bin/python`` where there is one), and compares.
The result: per run the frame count on each side and whether they are identical, with
the first frame that differs.

``--quick``: the attitude example only. Without ``--baseline``: this checkout's
records only (counts and a digest).

This file also runs as a script (``python wire.py OUT [--quick]``, in the checkout to
record: its packages first on the path), so it only imports what every revision of the
harness has.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

RUNS = ("attitude", "walk")


def record(out: Path, quick: bool) -> None:
    """Record the runs' frames into ``out`` (a JSON object: run -> list of frames)."""
    import wara.harness as harness_mod
    from config import load_project
    from ipc_app.service.logs import configure_logging
    from ipc_app.service.modes import Mode
    from plc_bridge.lockstep_bus import LockstepBus

    harnesses: list[Any] = []
    frames: list[str] = []
    init = harness_mod.Harness.__init__

    def tracking_init(self: Any, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        harnesses.append(self)

    send = LockstepBus.send
    send_all = getattr(LockstepBus, "send_all", None)  # (a batch: newer revisions)

    def record(bus: LockstepBus, msg: Any) -> None:
        h = harnesses[-1] if harnesses else None
        t = h.sim.t_s if h is not None else float("nan")
        side = "plc" if h is not None and bus is h.sim.wire.inner else "ipc"
        err = "E" if msg.is_error_frame else ""
        frames.append(f"{t:.6f} {side} {msg.arbitration_id:03X}{err} {bytes(msg.data).hex()}")

    def recording_send(self: LockstepBus, msg: Any, timeout: float | None = None) -> None:
        record(self, msg)
        send(self, msg, timeout)

    def recording_send_all(self: LockstepBus, msgs: list[Any]) -> None:
        for msg in msgs:
            record(self, msg)
        assert send_all is not None
        send_all(self, msgs)

    harness_mod.Harness.__init__ = tracking_init  # type: ignore[method-assign]
    LockstepBus.send = recording_send  # type: ignore[method-assign]
    if send_all is not None:
        LockstepBus.send_all = recording_send_all  # type: ignore[method-assign]
    logs = configure_logging("ERROR")
    result: dict[str, Any] = {}
    try:
        cfg = load_project(None)
        h = harness_mod.Harness(cfg, None, mode="lockstep", trace=False)
        try:
            h.wait_for(Mode.IDLE, 20.0)
            res = h.run_example(2.0, 1.0)
        finally:
            h.close()
        result["attitude"] = {"passed": bool(res.passed), "frames": frames[:]}
        if not quick:
            from wara.walk import run_walk

            frames.clear()
            walked = run_walk(None, 1)
            result["walk"] = {"passed": bool(walked.get("passed")), "frames": frames[:]}
    finally:
        logs.stop()
        harness_mod.Harness.__init__ = init  # type: ignore[method-assign]
        LockstepBus.send = send  # type: ignore[method-assign]
        if send_all is not None:
            LockstepBus.send_all = send_all  # type: ignore[method-assign]
    out.write_text(json.dumps(result), encoding="utf-8")


def _record_in(checkout: Path, quick: bool) -> dict[str, Any]:
    """Run :func:`record` in ``checkout`` with its own interpreter (its ``.venv`` if it
    has one, else this one with the checkout first on the path)."""
    checkout = checkout.resolve()
    venv = checkout / ".venv" / "bin" / "python"
    python = str(venv) if venv.is_file() else sys.executable
    with tempfile.TemporaryDirectory(prefix="wara-bench-wire-") as tmp:
        out = Path(tmp) / "frames.json"
        # a copy run from the temporary directory: run from here, its own directory
        # (wara/benches, with a can.py) would come first on the path
        script = Path(tmp) / "wara_wire_record.py"
        script.write_text(Path(__file__).read_text(encoding="utf-8"), encoding="utf-8")
        cmd = [python, str(script), str(out)]
        if quick:
            cmd.append("--quick")
        env = dict(os.environ, PYTHONPATH=str(checkout))
        done = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            tail = done.stderr.strip().splitlines()[-3:] or ["no output"]
            raise RuntimeError(f"recording the wire in {checkout} failed: {' | '.join(tail)}")
        result: dict[str, Any] = json.loads(out.read_text(encoding="utf-8"))
        return result


def _summary(run: dict[str, Any]) -> dict[str, Any]:
    frames: list[str] = run["frames"]
    sides = [f.split(" ", 2)[1] for f in frames]
    digest = hashlib.sha256("\n".join(frames).encode()).hexdigest()[:16]
    return {
        "passed": run["passed"],
        "frames": len(frames),
        "plc_frames": sides.count("plc"),
        "ipc_frames": sides.count("ipc"),
        "last_t_s": float(frames[-1].split(" ", 1)[0]) if frames else None,
        "sha256_16": digest,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    quick = bool(getattr(args, "quick", False))
    here = Path(__file__).resolve().parents[2]
    if (
        getattr(args, "baseline", None) is not None
        and not (Path(args.baseline) / "wara" / "harness.py").is_file()
    ):
        from wara.cli import UsageError

        raise UsageError(f"--baseline {args.baseline}: not a checkout with wara/harness.py")
    this = _record_in(here, quick)
    out: dict[str, Any] = {"bench": "wire", "this": {k: _summary(v) for k, v in this.items()}}
    if getattr(args, "baseline", None) is None:
        return out
    base_dir = Path(args.baseline)
    base = _record_in(base_dir, quick)
    out["against"] = str(base_dir)
    out["baseline"] = {k: _summary(v) for k, v in base.items()}
    out["identical"] = {}
    out["first_difference"] = {}
    for name in this:
        a, b = this[name]["frames"], base[name]["frames"]
        out["identical"][name] = a == b
        if a != b:
            k = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), None)
            k = min(len(a), len(b)) if k is None else k
            out["first_difference"][name] = {
                "index": k,
                "this": a[k] if k < len(a) else None,
                "baseline": b[k] if k < len(b) else None,
            }
    return out


if __name__ == "__main__":
    record(Path(sys.argv[1]), "--quick" in sys.argv[2:])
