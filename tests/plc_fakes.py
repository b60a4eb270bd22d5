"""Deterministic helpers for the plc_bridge tests (cantools style: a queue-backed bus)."""

from __future__ import annotations

import collections
from collections.abc import Callable
from typing import Any

import can

from config import ProjectConfig


class QueueBus(can.BusABC):
    """A fake bus: frames to receive are injected, sent frames are kept; no thread."""

    def __init__(self, channel: str = "fake", **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self.rx: collections.deque[can.Message] = collections.deque()
        self.sent: list[can.Message] = []
        self.send_error: Callable[[], Exception] | None = None
        self.recv_error: Callable[[], Exception] | None = None

    def inject(self, msg: can.Message) -> None:
        self.rx.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.recv_error is not None:
            raise self.recv_error()
        return (self.rx.popleft() if self.rx else None), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        assert timeout == 0.0, "the links must never block on send"
        if self.send_error is not None:
            raise self.send_error()
        self.sent.append(msg)


class Clock:
    """A settable clock for the links (seconds)."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += dt
        return self.t


def frame(frame_id: int, data: bytes, **kw: Any) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, **kw)


def with_can(cfg: ProjectConfig, **changes: Any) -> ProjectConfig:
    """A copy of ``cfg`` with ``can`` fields changed (validated again)."""
    data = cfg.model_dump()
    data["can"].update(changes)
    return ProjectConfig.model_validate(data)
