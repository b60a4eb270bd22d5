"""Queue-based structlog JSON logging: JSON lines, rendered off-thread, drops counted."""

from __future__ import annotations

import io
import json
import logging
import threading
import time
from collections.abc import Iterator

import pytest
import structlog

from ipc_app.service.logs import configure_logging


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    structlog.reset_defaults()
    root.handlers[:] = handlers
    root.setLevel(level)


def test_json_lines_from_structlog_and_stdlib() -> None:
    buf = io.StringIO()
    handle = configure_logging("INFO", stream=buf, cache_loggers=False)
    structlog.get_logger("wara.service.modes").info("mode", mode="FAULT", reason="twist")
    structlog.get_logger("wara.x").debug("hidden")
    logging.getLogger("can.interfaces").warning("bus %s down", "can0")
    handle.stop()
    lines = [json.loads(x) for x in buf.getvalue().splitlines()]
    assert len(lines) == 2
    assert lines[0]["event"] == "mode" and lines[0]["mode"] == "FAULT"
    assert lines[0]["level"] == "info" and lines[0]["logger"] == "wara.service.modes"
    assert lines[0]["timestamp"].endswith("Z")
    assert lines[1]["event"] == "bus can0 down" and lines[1]["level"] == "warning"


class _Gate(io.StringIO):
    """A stream whose writes wait until the test opens the gate (a stuck journal)."""

    def __init__(self) -> None:
        super().__init__()
        self.open = threading.Event()

    def write(self, s: str) -> int:
        self.open.wait(30)
        return super().write(s)


def test_full_queue_drops_and_counts_never_blocks() -> None:
    stream = _Gate()
    handle = configure_logging("INFO", stream=stream, max_queued=5, cache_loggers=False)
    log = structlog.get_logger("wara.test")
    for i in range(50):  # the caller never waits on the stuck stream
        log.info("tick", i=i)
    assert handle.dropped >= 40
    stream.open.set()
    for _ in range(3000):  # let the listener drain (bounded wait, no timing assertion)
        if handle.listener.queue.empty():
            break
        time.sleep(0.01)
    log.info("after")
    handle.stop()
    lines = [json.loads(x) for x in stream.getvalue().splitlines()]
    assert lines[-1]["event"] == "after"
    # every drop is reported, by the next record that made it into the queue
    assert sum(x.get("log_records_dropped", 0) for x in lines) == handle.dropped
    assert len(lines) + handle.dropped == 51
