"""Non-blocking structlog JSON logging for the service.

Every ``structlog.get_logger(...)`` call site builds its event dict in the calling thread
(level, UTC timestamp, logger name) and hands the *unrendered* record to a bounded
:class:`queue.Queue` through a :class:`logging.handlers.QueueHandler`; a
:class:`logging.handlers.QueueListener` thread renders JSON and writes it (stderr by
default: under systemd that is the journal, ``journalctl -u wara-ipc -o cat``).

So the loop thread never formats JSON and never waits on a pipe or a disk: a log call
costs a dict and a ``put_nowait``. When the queue is full (the writer is stuck) the record
is dropped and counted (:attr:`LoggingHandle.dropped`), never waited for; the next record
that fits reports the count (``log_records_dropped``).

One JSON object per line, e.g.::

    {"event": "mode", "from_mode": "IDLE", "mode": "STARTING", "reason": "adjust to ...",
     "level": "info", "logger": "wara.service.modes", "timestamp": "2026-...Z"}

Usage (once, at service start; :meth:`LoggingHandle.stop` flushes at shutdown)::

    handle = configure_logging("INFO")
    ...
    handle.stop()
"""

from __future__ import annotations

import logging
import logging.handlers
import queue
import sys
from dataclasses import dataclass
from typing import TextIO

import structlog

_PRE_CHAIN: list[structlog.types.Processor] = [
    structlog.stdlib.add_log_level,
    structlog.stdlib.add_logger_name,
    structlog.processors.TimeStamper(fmt="iso", utc=True),
]


class _DroppingQueueHandler(logging.handlers.QueueHandler):
    """Enqueue the record as is (rendered later, in the listener); drop when full."""

    def __init__(self, q: queue.Queue[logging.LogRecord]) -> None:
        super().__init__(q)
        self.dropped = 0
        self._reported = 0

    def prepare(self, record: logging.LogRecord) -> logging.LogRecord:
        # The stdlib version formats here, in the caller's thread; the listener does it.
        return record

    def enqueue(self, record: logging.LogRecord) -> None:
        pending = self.dropped - self._reported
        if pending and isinstance(record.msg, dict):
            record.msg = {**record.msg, "log_records_dropped": pending}
        else:
            pending = 0
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self.dropped += 1
            return
        self._reported += pending


@dataclass
class LoggingHandle:
    listener: logging.handlers.QueueListener
    handler: _DroppingQueueHandler

    @property
    def dropped(self) -> int:
        return self.handler.dropped

    def stop(self) -> None:
        """Write what is queued and stop the listener thread."""
        self.listener.stop()
        logging.getLogger().removeHandler(self.handler)


def configure_logging(
    level: str | int = "INFO",
    *,
    stream: TextIO | None = None,
    max_queued: int = 10_000,
    cache_loggers: bool = True,
) -> LoggingHandle:
    """Route structlog and stdlib logging through a queue to JSON lines on ``stream``.

    ``cache_loggers=False`` keeps loggers re-configurable (tests reset structlog after).
    """
    q: queue.Queue[logging.LogRecord] = queue.Queue(maxsize=max_queued)
    out = logging.StreamHandler(stream if stream is not None else sys.stderr)
    out.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            processor=structlog.processors.JSONRenderer(sort_keys=False),
            foreign_pre_chain=_PRE_CHAIN,
        )
    )
    listener = logging.handlers.QueueListener(q, out, respect_handler_level=False)
    handler = _DroppingQueueHandler(q)
    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, _DroppingQueueHandler):
            root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level)
    structlog.configure(
        processors=[
            structlog.stdlib.filter_by_level,
            *_PRE_CHAIN,
            structlog.processors.StackInfoRenderer(),
            structlog.processors.format_exc_info,
            structlog.stdlib.ProcessorFormatter.wrap_for_formatter,
        ],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=cache_loggers,
    )
    listener.start()
    return LoggingHandle(listener, handler)
