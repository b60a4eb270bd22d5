"""The one-line progress display on stderr of the long commands: ``wara campaign run``
(runs done of total, ETA, failures) and ``wara commission`` (items done of total, the
item running, its time so far, the items not fit).

On a terminal the line is redrawn in place; otherwise (a log file, a pipe) a line is
printed at most every ``every_s`` seconds and at the end, so a log stays readable.
"""

from __future__ import annotations

import math
import sys
import time


class Progress:
    """One line on stderr: done of total, ETA (or the time so far), failures so far, and
    ``note`` (what is running now) when set."""

    def __init__(
        self,
        total: int,
        done: int,
        failures: int,
        enabled: bool = True,
        *,
        failed_word: str = "failures",
        eta: bool = True,
        every_s: float = 10.0,
    ) -> None:
        self.total, self.done, self.failures = total, done, failures
        self.start_done = done
        self.t0 = time.monotonic()
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.failed_word = failed_word
        self.eta = eta
        self.every_s = every_s
        self.note = ""
        self._last = 0.0

    def update(self, failed: bool) -> None:
        self.done += 1
        self.failures += int(failed)
        self.tick(force=self.done == self.total)

    def tick(self, force: bool = False) -> None:
        """Show the line if it is time to (always on a terminal)."""
        now = time.monotonic()
        if self.tty or force or now - self._last > self.every_s:
            self._last = now
            self.show()

    def show(self) -> None:
        if not self.enabled:
            return
        new = self.done - self.start_done
        el = time.monotonic() - self.t0
        width = 30
        filled = int(width * self.done / max(1, self.total))
        if self.eta:
            rate = new / el if el > 0 and new else 0.0
            eta = (self.total - self.done) / rate if rate else math.nan
            when = f"ETA {'--' if math.isnan(eta) else hms(eta)}"
        else:
            when = f"elapsed {hms(el)}"
        line = (
            f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} "
            f"{when}, {self.failed_word} {self.failures}"
        )
        if self.note:
            line += f"; {self.note}"
        if self.tty:
            line = "\r" + line[:160] + "\x1b[K"  # the rest of a longer line before cleared
        print(line, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def finish(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr, flush=True)


def hms(s: float) -> str:
    """``1m05s``, ``2h03m``."""
    s = round(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"
