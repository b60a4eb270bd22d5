"""The site's acts on a simulator running in its own process: the crane and the crew.

In one process the HIL driver calls them on the simulator (``wara cycle``:
:meth:`HilSimulator.load_part`, :meth:`HilSimulator.bolt_part`). When the simulator is
a process of its own (``wara hil --site-socket PATH``; the two-process ring cycle of
``wara demo --two-process --rings N``), the same acts come over a local stream socket:
one JSON object per line, each answered with one JSON object on one line. Nothing of it
is on the CAN wire: on site these are people, and the service sees them only in the
pressures, as in one process.

Each act is done by the simulator's own thread between two PLC scans
(:meth:`SiteServer.between_scans`, given to :meth:`HilSimulator.run_realtime`), never
while a scan runs; the socket's thread waits for it (:data:`ACT_TIMEOUT_S`).

Requests (``{"act": NAME, ...}``) and what they do:

- ``part``: nothing; the answer says where the part is;
- ``bolt``: the crew bolts the part to its ring where it is (refused unless it is
  carried): its pose frozen, the simulator's truth from then on;
- ``load`` (``duration_s``, default :data:`HilSimulator.LOAD_DURATION_S`): a crane sets
  the next part down on the platform (refused unless the one before is bolted).

Every answer: ``ok``; ``state`` (``carried``, ``loading``, ``bolted``), ``load_n`` (the
part's weight on the platform, N), ``t_s`` (simulated time), ``r`` (3x3) and ``t`` (m):
the part's pose from its home (:func:`hil_sim.placement.pose_from_home`; bolted: the
pose it was bolted in). A refusal: ``{"ok": false, "error": "one line"}``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil_sim.placement import pose_from_home
from hil_sim.simulator import HilSimulator

#: How long the socket's thread waits for the simulator to do an act, s.
ACT_TIMEOUT_S = 5.0
#: The longest request line, bytes.
MAX_LINE = 4096
#: The acts, and what each does.
ACTS: dict[str, str] = {
    "part": "where the part is",
    "bolt": "the crew bolts the part where it is",
    "load": "a crane sets the next part down on the platform",
}


class _Act:
    """One request handed from the socket's thread to the simulator's."""

    def __init__(self, fn: Callable[[], dict[str, Any]]) -> None:
        self.fn = fn
        self.done = threading.Event()
        self.reply: dict[str, Any] = {}
        #: the asker stopped waiting: not done later behind its back
        self.cancelled = False


class SiteServer:
    """Serves the site's acts on ``sim`` at the Unix socket ``path`` (a stale socket file
    there is replaced). :meth:`start` binds and starts the socket's thread; the
    simulator's thread calls :meth:`between_scans`; :meth:`close` stops it."""

    def __init__(self, sim: HilSimulator, path: str | Path) -> None:
        self.sim = sim
        self.path = Path(path)
        self._acts: queue.SimpleQueue[_Act] = queue.SimpleQueue()
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Bind the socket (mode 0600) and serve; OSError when it cannot be bound."""
        with contextlib.suppress(FileNotFoundError):
            if self.path.is_socket():
                self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(self.path))
            os.chmod(self.path, 0o600)
            sock.listen(2)
        except OSError:
            sock.close()
            raise
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="hil-site", daemon=True)
        self._thread.start()

    def between_scans(self) -> None:
        """Do the acts asked for since the last call (the simulator's thread, between
        two scans)."""
        acts = self._acts
        while not acts.empty():
            act = acts.get_nowait()
            if act.cancelled:
                continue
            try:
                act.reply = act.fn()
            except ValueError as exc:  # the rig's refusal (not carried, not bolted, ...)
                act.reply = {"ok": False, "error": str(exc)}
            act.done.set()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self._sock is not None:
            self._sock.close()
        with contextlib.suppress(OSError):
            self.path.unlink()

    # ----------------------------------------------------------------- the socket

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                self._connection(conn)

    def _connection(self, conn: socket.socket) -> None:
        conn.settimeout(0.5)
        buf = b""
        while not self._stop.is_set():
            try:
                chunk = conn.recv(MAX_LINE)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                out = self.answer(line)
                try:
                    conn.sendall(json.dumps(out).encode() + b"\n")
                except OSError:
                    return
            if len(buf) > MAX_LINE:
                with contextlib.suppress(OSError):
                    msg = {"ok": False, "error": f"request longer than {MAX_LINE} bytes"}
                    conn.sendall(json.dumps(msg).encode() + b"\n")
                return

    def answer(self, line: bytes) -> dict[str, Any]:
        """One request line -> its answer (the act done by the simulator's thread)."""
        try:
            req = json.loads(line)
        except ValueError:
            return {"ok": False, "error": "request is not JSON"}
        name = req.get("act") if isinstance(req, dict) else None
        if name not in ACTS:
            return {"ok": False, "error": f"unknown act {name!r}; expected one of {list(ACTS)}"}
        fn = self._act(name, req)
        if isinstance(fn, str):
            return {"ok": False, "error": fn}
        act = _Act(fn)
        self._acts.put(act)
        if not act.done.wait(ACT_TIMEOUT_S):
            act.cancelled = True
            return {
                "ok": False,
                "error": f"{name}: the simulator did not run it in {ACT_TIMEOUT_S} s",
            }
        return act.reply

    def _act(self, name: str, req: dict[str, Any]) -> Callable[[], dict[str, Any]] | str:
        sim = self.sim
        if name == "part":
            return self._part
        if name == "bolt":

            def bolt() -> dict[str, Any]:
                sim.bolt_part()
                return self._part()

            return bolt
        d = req.get("duration_s", HilSimulator.LOAD_DURATION_S)
        if isinstance(d, bool) or not isinstance(d, int | float) or not 0 < d <= 600:
            return f"load: duration_s must be a number of seconds in (0, 600], got {d!r}"

        def load() -> dict[str, Any]:
            sim.load_part(float(d))
            return self._part()

        return load

    def _part(self) -> dict[str, Any]:
        sim = self.sim
        r, t = pose_from_home(sim.cfg, sim.rig)
        load = sim.rig.part_load_n
        return {
            "ok": True,
            "state": sim.rig.part_state,
            "load_n": load if math.isfinite(load) else None,
            "t_s": sim.t_s,
            "r": r.tolist(),
            "t": t.tolist(),
        }
