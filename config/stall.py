"""A stall watchdog for the fixed-rate loops of both processes (diagnostics).

``WARA_STALL_TRACE_MS=N`` in the environment of ``wara serve``, ``wara hil`` or a demo:
each cycle of the service's loop and of the simulator's PLC scan re-arms
:func:`faulthandler.dump_traceback_later`; a cycle that has not come round again within
N ms dumps every thread's Python stack to stderr (the process's log). The watchdog is a
C thread, so it fires even while another thread holds the GIL or the process is stuck
in a system call, which is what tells a stall's cause. Unset or 0: off, nothing armed.

Both processes use it; it lives here because ``config`` is the one package besides the
CAN messages that the service and the simulator share.
"""

from __future__ import annotations

import faulthandler
import math
import os
import sys

ENV = "WARA_STALL_TRACE_MS"


class StallTrace:
    """Re-arm per cycle with :meth:`arm`; :meth:`close` (or leaving the ``with``) cancels."""

    def __init__(self, timeout_ms: float | None = None) -> None:
        if timeout_ms is None:
            raw = os.environ.get(ENV, "").strip()
            try:
                timeout_ms = float(raw) if raw else 0.0
            except ValueError:
                raise ValueError(f"{ENV}={raw!r}: expected a number of milliseconds") from None
        if not math.isfinite(timeout_ms) or timeout_ms < 0:
            raise ValueError(f"{ENV}: {timeout_ms!r} ms: expected a finite number >= 0")
        self.timeout_s = timeout_ms / 1000.0
        self.enabled = self.timeout_s > 0

    def arm(self) -> None:
        if self.enabled:
            faulthandler.dump_traceback_later(self.timeout_s, file=sys.stderr)

    def close(self) -> None:
        if self.enabled:
            faulthandler.cancel_dump_traceback_later()

    def __enter__(self) -> StallTrace:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
