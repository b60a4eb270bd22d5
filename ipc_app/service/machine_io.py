"""What the control step reads and writes, and the handshake with the PLC.

:class:`ServiceCore.step <ipc_app.service.core.ServiceCore.step>` is read -> update ->
write: :func:`read` takes one frozen :class:`MachineInputs` from the link (every value
the cycle's checks and controllers use, at one time), the update works on it and the
mode machine only, and :func:`write` sends one :class:`MachineOutputs`. The interlock
checks (:mod:`ipc_app.service.interlocks`) are pure functions of the inputs, so they are
tested from a :class:`MachineInputs` built by hand, without a bus.

:class:`Handshake` owns the two exchanges with the PLC that span cycles: the HMI request
being served (its TargetSeq, answered in the control word) and the fault-reset pulse.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from plc_bridge.link import (
    ControlWord,
    HmiTarget,
    IpcLink,
    LimitSwitches,
    PlcStatus,
    Reading,
    TargetAck,
)
from plc_bridge.link import Mode as PlcMode
from plc_bridge.supervision import LinkState


@dataclass(frozen=True, slots=True)
class MachineInputs:
    """One cycle's view of the machine, taken by :func:`read` at time :attr:`t`."""

    #: the cycle's time [s]
    t: float
    #: rod positions from fully retracted [m] by ``can_index`` (NaN where not valid)
    positions: Reading
    #: chamber pressures [Pa], shape (19, 2): cap side, rod side
    pressures: Reading
    #: every active cylinder's position valid
    positions_valid: bool
    #: active cylinders whose frame is fresh but whose sensor reports a fault (read
    #: only when :attr:`positions_valid` is False, else empty)
    failed_sensors: frozenset[int]
    #: the PLC status word, None when lost (heartbeat timeout)
    status: PlcStatus | None
    #: time since the last valid PLC status [s] (inf: never)
    status_age_s: float
    #: the status older than the link's short-loss limit (``can.stale_cycles``)
    status_stale: bool
    #: the IPC's bus can send (not off or down)
    bus_ok: bool
    #: per active cylinder (in :attr:`ServiceCore.active` order): at a limit switch;
    #: None when the limit-switch frame is stale, or not read (``read(limits=False)``:
    #: in the modes where no check uses it)
    at_limit: Sequence[bool] | None
    #: a new HMI request (a TargetSeq not seen before), or None
    hmi: HmiTarget | None
    #: the link supervision's verdict
    link_state: LinkState


@dataclass(frozen=True, slots=True)
class MachineOutputs:
    """One cycle's commands: the control words in the order they are to go on the wire
    (each edit of the cycle that changed the word: an ack, a reset pulse, then the mode;
    the last one stands), and the spool commands by ``can_index``."""

    words: tuple[ControlWord, ...]
    valves: np.ndarray
    t: float


class Reader:
    """Takes :class:`MachineInputs` from an :class:`IpcLink` for the active cylinders.
    Keeps the per-active-cylinder limit-switch mask of the last received word (it is
    worked out once per word, not per cycle)."""

    def __init__(self, link: IpcLink, active: Sequence[int]) -> None:
        self.link = link
        self.active = tuple(active)
        self._active_arr = np.array(self.active, dtype=np.intp)
        self._limits_of: tuple[LimitSwitches | None, Sequence[bool] | None] = (None, None)

    def read(self, now: float, limits_needed: bool = True) -> MachineInputs:
        """The cycle's inputs; the limit switches only when ``limits_needed`` (their
        frame is decoded per word: the loop asks only in the modes that check them)."""
        link = self.link
        link.poll(now)
        pos = link.positions_m(now)
        valid = bool(pos.valid[self._active_arr].all())
        limits = link.limit_switches(now) if limits_needed else None
        if limits is not self._limits_of[0]:
            at = None
            if limits is not None:
                a = self._active_arr
                at = tuple((limits.retracted[a] | limits.extended[a]).tolist())
            self._limits_of = (limits, at)
        age = link.status_age_s(now)
        return MachineInputs(
            t=now,
            positions=pos,
            pressures=link.pressures_pa(now),
            positions_valid=valid,
            failed_sensors=(
                frozenset() if valid else frozenset(link.failed_positions(self.active, now))
            ),
            status=link.status(now),
            status_age_s=age,
            status_stale=age > link.status_stale_s,
            bus_ok=link.bus_health.can_send(),
            at_limit=self._limits_of[1] if limits_needed else None,
            hmi=link.new_hmi_request(now),
            link_state=link.state(now),
        )


def write(link: IpcLink, out: MachineOutputs) -> None:
    """Send the cycle's control words (a changed word goes at once) and spool commands."""
    for w in out.words:
        link.set_control(w)
    link.send_valve_commands(out.valves, out.t)


class Handshake:
    """The HMI request being served and the fault-reset pulse, as control-word edits.

    Each cycle starts from the standing word (:meth:`begin`), collects the edits in
    order (:meth:`ack`, the reset pulse in :meth:`reset_step`) and ends with the mode
    and enable of the cycle (:meth:`finish`), which returns the words for
    :class:`MachineOutputs`. :meth:`request_reset` may be called from any thread.
    """

    #: How long ``fault_reset`` is held in the control word for the PLC to clear a fault.
    RESET_PULSE_S = 0.5

    def __init__(self, word: ControlWord | None = None) -> None:
        self.word = word if word is not None else ControlWord()
        #: TargetSeq of the HMI request being planned or run (0: a local request, none)
        self.seq = 0
        self._words: list[ControlWord] = []
        self._lock = threading.Lock()
        self._reset_requested = False
        self._reset_until: float | None = None

    def begin(self) -> None:
        self._words = []

    def _edit(self, **changes: object) -> None:
        w = self.word
        for k, v in changes.items():
            if getattr(w, k) != v:
                break
        else:
            return  # every field already so (mode and enable are set every cycle)
        new = replace(w, **changes)  # type: ignore[arg-type]
        self.word = new
        self._words.append(new)

    def serve(self, seq: int) -> None:
        """A request was accepted: ``seq`` (0 for a local one) is the one now served."""
        self.seq = seq

    def ack(self, status: TargetAck, seq: int | None = None) -> None:
        """Answer an HMI request (the PLC shows it to the operator): ``seq``, else the
        request being served; a local request (seq 0) is not answered."""
        seq = self.seq if seq is None else seq
        if seq:
            self._edit(ack_seq=seq, ack_status=status)

    def request_reset(self) -> None:
        with self._lock:
            self._reset_requested = True

    @property
    def resetting(self) -> bool:
        return self._reset_requested or self._reset_until is not None

    def reset_step(self, now: float, plc_fault: bool) -> bool:
        """Drive a requested reset: ``fault_reset`` on for up to :attr:`RESET_PULSE_S`,
        off once the PLC reports no fault (or the pulse ends). True: reset the modes now."""
        with self._lock:
            start = self._reset_requested and self._reset_until is None
            if start:
                self._reset_requested = False
        if start:
            self._reset_until = now + self.RESET_PULSE_S
            self._edit(fault_reset=True)
        if self._reset_until is None:
            return False
        if not plc_fault or now >= self._reset_until:
            self._edit(fault_reset=False)
            self._reset_until = None
            return True
        return False

    def cleared(self) -> None:
        """The modes were reset: no request is served any more."""
        self.seq = 0

    def finish(
        self, mode: PlcMode, enable: bool, state: int = 0, unit_mode: int = 0
    ) -> tuple[ControlWord, ...]:
        """The cycle's last edit: the PLC mode and enable, the service's PackML state
        and unit mode numbers. Returns the words to send, in order."""
        self._edit(mode=mode, enable=enable, state=state, unit_mode=unit_mode)
        return tuple(self._words)
