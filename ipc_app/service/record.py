"""The per-run record: every cycle's commands and measurements, and the events, on disk.

The loop thread calls :meth:`RunRecorder.sample` (one row per cycle) and
:meth:`RunRecorder.event`; both only append to an in-memory deque (no lock, no syscall,
no allocation beyond the row tuple) and never block. A writer thread drains the deques
every ``flush_every_s``, writes, and ``fsync``-s at most every ``fsync_every_s``; on
:meth:`RunRecorder.stop` it drains everything, fsyncs and writes the summary.

Overflow policy (decision): never block the loop. The queued rows are bounded by
``max_queued_rows`` (default 60 s of a 200 Hz loop); a row that does not fit is *dropped
and counted* (``rows_dropped``), the first drop and then one per second are logged, the
writer records an ``record_overflow`` event with the count, and the summary in
``meta.json`` says how many rows were lost. With a healthy disk the writer keeps the
queue near empty; the bound only matters when the disk stalls. A disk error (full,
read-only) is logged once, counted, and the rows are dropped the same way so memory stays
bounded. Memory: about ``max_queued_rows * (64 + 32 * columns)`` bytes at worst.

Format (decision: plain text a site engineer can open anywhere), one directory per run::

    RUN_DIR/meta.json       columns, units, period, start time (UTC), config path; on stop
                            also rows_written, rows_dropped, events_written, ...
    RUN_DIR/samples.csv     header ``t_s,<column>,...``; one row per cycle; floats repr'd
                            with 9 significant digits (enough for 0.01 mm at 1 m)
    RUN_DIR/events.jsonl    one JSON object per event: {"t_s": ..., "kind": ..., ...}

A crash loses at most the rows since the last fsync; a half-written last line is ignored
by the reader. :func:`read_run` returns numpy arrays for plotting::

    run = read_run("wara-data/runs/2026-05-01T10-00-00Z")
    plt.plot(run.t_s, run["twist_mm"])
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import structlog

log = structlog.get_logger("wara.service.record")

SAMPLES = "samples.csv"
EVENTS = "events.jsonl"
META = "meta.json"
_EVENT_ROW = tuple[float, str, dict[str, Any]]


def new_run_dir(root: str | Path, now: datetime | None = None) -> Path:
    """``root/<UTC timestamp>`` (a fresh directory name; created by the recorder)."""
    stamp = (now or datetime.now(UTC)).strftime("%Y-%m-%dT%H-%M-%S.%fZ")
    return Path(root) / stamp


class RunRecorder:
    """Write one run's samples and events from a background thread.

    ``columns`` name the values of each :meth:`sample` row after the time (units in the
    names: ``d_upper_1_mm``, ``p_cap_3_mpa``); ``units`` is optional documentation kept
    in ``meta.json``.
    """

    def __init__(
        self,
        run_dir: str | Path,
        columns: Sequence[str],
        *,
        meta: Mapping[str, Any] | None = None,
        max_queued_rows: int = 12_000,
        max_queued_events: int = 10_000,
        flush_every_s: float = 0.2,
        fsync_every_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if len(set(columns)) != len(columns) or "t_s" in columns:
            raise ValueError(f"columns must be unique and not 't_s': {list(columns)}")
        bad = [c for c in columns if not c or "," in c or "\n" in c]
        if bad:
            raise ValueError(f"column names must be non-empty without commas: {bad}")
        self.run_dir = Path(run_dir)
        self.columns = tuple(columns)
        self._meta = dict(meta or {})
        self._max_rows = max_queued_rows
        self._max_events = max_queued_events
        self._flush_every_s = flush_every_s
        self._fsync_every_s = fsync_every_s
        self._clock = clock
        self._rows: deque[tuple[float, tuple[float, ...]]] = deque()
        self._events: deque[_EVENT_ROW] = deque()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.rows_written = 0
        self.events_written = 0
        self.io_errors = 0
        self.fsyncs = 0
        # one writer thread per counter: the loop counts overflow, the writer I/O losses
        self._rows_full = 0
        self._events_full = 0
        self._rows_lost = 0
        self._events_lost = 0
        self._dropped_logged_at = -math.inf
        self._full_reported = 0
        self._last_t = math.nan
        self._samples: TextIO | None = None
        self._events_f: TextIO | None = None

    # ------------------------------------------------------------------ loop side
    def sample(self, t_s: float, values: Iterable[float]) -> bool:
        """Queue one row (``len(columns)`` values); False if it was dropped (counted)."""
        if len(self._rows) >= self._max_rows:
            self._rows_full += 1
            self._log_drop()
            return False
        self._rows.append((t_s, tuple(values)))
        return True

    def event(self, t_s: float, kind: str, **fields: Any) -> bool:
        """Queue one event (JSON-ready fields); False if it was dropped (counted)."""
        if len(self._events) >= self._max_events:
            self._events_full += 1
            self._log_drop()
            return False
        self._events.append((t_s, kind, fields))
        return True

    def _log_drop(self) -> None:
        now = self._clock()
        if now - self._dropped_logged_at >= 1.0:
            self._dropped_logged_at = now
            log.warning(
                "record_overflow",
                rows_dropped=self.rows_dropped,
                events_dropped=self.events_dropped,
                run_dir=str(self.run_dir),
            )

    @property
    def rows_dropped(self) -> int:
        """Rows lost: queue full (overflow) plus disk errors."""
        return self._rows_full + self._rows_lost

    @property
    def events_dropped(self) -> int:
        return self._events_full + self._events_lost

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Create the run directory and files, then start the writer thread."""
        self.run_dir.mkdir(parents=True, exist_ok=False)
        meta = {
            "format": "wara-run-1",
            "started_utc": datetime.now(UTC).isoformat(),
            "columns": ["t_s", *self.columns],
            **self._meta,
        }
        (self.run_dir / META).write_text(json.dumps(meta, indent=2) + "\n")
        self._samples = open(self.run_dir / SAMPLES, "w", encoding="utf-8", newline="")  # noqa: SIM115
        self._samples.write(",".join(("t_s", *self.columns)) + "\n")
        self._events_f = open(self.run_dir / EVENTS, "w", encoding="utf-8")  # noqa: SIM115
        self._thread = threading.Thread(target=self._writer, name="wara-record", daemon=True)
        self._thread.start()
        log.info("record_start", run_dir=str(self.run_dir), columns=len(self.columns))

    def stop(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Drain everything, fsync, close, and write the summary; returns the summary."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        summary = self.summary()
        meta_path = self.run_dir / META
        if meta_path.exists():
            meta = json.loads(meta_path.read_text())
            meta.update(summary, stopped_utc=datetime.now(UTC).isoformat())
            tmp = meta_path.with_suffix(".tmp")
            tmp.write_text(json.dumps(meta, indent=2) + "\n")
            os.replace(tmp, meta_path)
        log.info("record_stop", run_dir=str(self.run_dir), **summary)
        return summary

    def summary(self) -> dict[str, int]:
        return {
            "rows_written": self.rows_written,
            "rows_dropped": self.rows_dropped,
            "events_written": self.events_written,
            "events_dropped": self.events_dropped,
            "io_errors": self.io_errors,
        }

    def __enter__(self) -> RunRecorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ writer thread
    def _writer(self) -> None:
        last_fsync = self._clock()
        try:
            while True:
                stopping = self._stop.wait(self._flush_every_s)
                self._drain()
                now = self._clock()
                if stopping or now - last_fsync >= self._fsync_every_s:
                    self._sync()
                    last_fsync = now
                if stopping:
                    self._drain()  # anything queued while syncing
                    self._sync()
                    return
        finally:
            for f in (self._samples, self._events_f):
                if f is not None:
                    f.close()

    def _drain(self) -> None:
        full = self._rows_full
        if full > self._full_reported:
            lost, self._full_reported = full - self._full_reported, full
            self._events.append((self._last_t, "record_overflow", {"rows_dropped": lost}))
        n_cols = len(self.columns)
        lines: list[str] = []
        while self._rows:
            t, values = self._rows.popleft()
            if len(values) != n_cols:
                self._rows_lost += 1
                log.error("record_bad_row", expected=n_cols, got=len(values))
                continue
            lines.append(",".join([f"{t:.9g}", *(f"{v:.9g}" for v in values)]) + "\n")
            self._last_t = t
        events: list[str] = []
        while self._events:
            t, kind, fields = self._events.popleft()
            t_out = None if math.isnan(t) else t
            events.append(json.dumps({"t_s": t_out, "kind": kind, **fields}, default=str) + "\n")
        self._write(self._samples, lines, "rows")
        self._write(self._events_f, events, "events")

    def _write(self, f: TextIO | None, lines: list[str], what: str) -> None:
        if not lines or f is None:
            return
        try:
            f.write("".join(lines))
        except OSError as exc:
            self.io_errors += 1
            if self.io_errors == 1:
                log.error("record_write_failed", run_dir=str(self.run_dir), error=str(exc))
            if what == "rows":
                self._rows_lost += len(lines)
            else:
                self._events_lost += len(lines)
            return
        if what == "rows":
            self.rows_written += len(lines)
        else:
            self.events_written += len(lines)

    def _sync(self) -> None:
        for f in (self._samples, self._events_f):
            if f is None:
                continue
            try:
                f.flush()
                os.fsync(f.fileno())
            except OSError as exc:
                self.io_errors += 1
                if self.io_errors == 1:
                    log.error("record_fsync_failed", run_dir=str(self.run_dir), error=str(exc))
        self.fsyncs += 1


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class RunData:
    """One recorded run: ``t_s`` and each column as numpy arrays, the events, the meta."""

    run_dir: Path
    t_s: np.ndarray
    columns: dict[str, np.ndarray]
    events: list[dict[str, Any]] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "t_s":
            return self.t_s
        try:
            return self.columns[name]
        except KeyError:
            raise KeyError(
                f"{self.run_dir}: no column {name!r}; columns: {sorted(self.columns)}"
            ) from None


def read_run(run_dir: str | Path) -> RunData:
    """Read a run directory; a half-written last line (crash) is ignored."""
    d = Path(run_dir)
    meta = json.loads((d / META).read_text()) if (d / META).exists() else {}
    text = (d / SAMPLES).read_text(encoding="utf-8")
    lines = text.split("\n")
    header = lines[0].split(",")
    body = lines[1:-1]  # the last element is "" after a final newline, or a partial line
    n = len(header)
    rows = [ln.split(",") for ln in body if ln]
    rows = [r for r in rows if len(r) == n]
    data = np.array(rows, dtype=float).reshape(len(rows), n)
    events: list[dict[str, Any]] = []
    if (d / EVENTS).exists():
        for ln in (d / EVENTS).read_text(encoding="utf-8").splitlines():
            try:
                events.append(json.loads(ln))
            except json.JSONDecodeError:
                break  # partial last line
    cols = {name: data[:, i] for i, name in enumerate(header) if name != "t_s"}
    return RunData(d, data[:, 0], cols, events, meta)
