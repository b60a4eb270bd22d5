"""The emulated PLC's scans in machine code, for lockstep runs: :class:`FastPlc`.

:meth:`HilSimulator._scan <hil_sim.simulator.HilSimulator._scan>` is the PLC's scan in
Python over ``plc_bridge``'s :class:`~plc_bridge.link.PlcLink`: the reference. In a
lockstep run most scans are alike (the IPC's frames of the period read, timeouts
supervised, the frames that are due sent, the interlocks evaluated, the plant
integrated), and their Python (some 35 % of a run) is what the scans cost. So while the
run is in that ordinary state the same scans run in :func:`run_scans`, compiled by
numba, on the same state held in arrays; the first scan that needs anything else
(a scenario event switching, a stalled or silent PLC, a sensor fault, a part being
loaded, an error frame on the bus) hands the state back to the Python objects
(:meth:`FastPlc.export`) and runs as Python, and the compiled scans take over again at
the next step where they can (:meth:`FastPlc.take_over`).

What stays Python: the wire (:class:`~hil_sim.wire.FaultyWire`: the frames received are
drained through it before the compiled scans, the frames they send go through it after,
scan by scan, at their scan's time), the scenario's events, the logs (the compiled
scans report what to log). The frame path itself (:mod:`hil_sim.plc_frames`) runs on
tables generated from the codecs; the rest mirrors ``PlcLink``, ``RxRecord`` and the
simulator's ``_logic`` statement for statement, and ``tests/test_plc_fast.py`` runs the
same scenarios both ways, comparing every frame on the wire and the state after.

Only on a :class:`~plc_bridge.lockstep_bus.LockstepBus` (one thread drives both nodes:
nothing arrives during a step), with numba (``HAVE_NUMBA``); else every scan is Python.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import TYPE_CHECKING, Any

import can
import numpy as np
from numpy.typing import NDArray

from config import units
from config.schema import N_CYLINDERS
from hil_sim._jit import HAVE_NUMBA, jit
from hil_sim.plc_frames import (
    ACCEPTED,
    CRC_ERROR,
    ENCODE_OVERFLOW,
    NOT_CLASSIC,
    OWN_ECHO,
    TIMEOUTS,
    UNKNOWN_ID,
    VALUE_ERROR,
    FrameTables,
    check_frame,
    counter_table,
    encode_frame,
)
from hil_sim.rig import Rig, _advance
from plc_bridge.link import FAULT_HOLD_S, Fault, Mode, PlcStatus, TargetAck
from plc_bridge.link.side import TxFrame, indices_of
from plc_bridge.lockstep_bus import LockstepBus
from plc_bridge.supervision import RX_OUTCOMES, BusState

if TYPE_CHECKING:
    from hil_sim.simulator import HilSimulator

log = logging.getLogger("plc_bridge")

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# -- the state in arrays (columns) ------------------------------------------------------
# received messages (RxRecord), ints
RI_LAST_COUNTER, RI_HAS_RX, RI_LOST, RI_WAS_FRESH, RI_HAS_VALUES = 0, 1, 2, 3, 4
RI_SLOTMASK, RI_CAN_BE_FAST, RI_LOOP, RI_LO, RI_HI, RI_COMMAND = 5, 6, 7, 8, 9, 10
# floats
RF_LAST_RX, RF_TIMEOUT, RF_GRACE_TIMEOUT, RF_GRACE_UNTIL, RF_LOGGED_AT = 0, 1, 2, 3, 4
RF_TIMEOUT_ACTIVE, RF_TIMEOUT_INACTIVE = 5, 6
# sent messages, ints and floats
TI_COUNTER, TI_KIND, TI_LO, TI_HI, TI_SLOTMASK, TI_CAN_BE_FAST = 0, 1, 2, 3, 4, 5
TF_PERIOD, TF_NEXT_DUE, TF_PERIOD_ACTIVE, TF_PERIOD_INACTIVE = 0, 1, 2, 3
# what a sent message carries (PlcLink.tx_kind)
KIND_POSITIONS, KIND_PRESSURES, KIND_STATUS, KIND_LIMITS, KIND_HMI = 0, 1, 2, 3, 4
_KINDS = {
    "positions": KIND_POSITIONS,
    "pressures": KIND_PRESSURES,
    "status": KIND_STATUS,
    "limits": KIND_LIMITS,
    "hmi": KIND_HMI,
}
# the status word's signals (PlcLink._status_values) and the limit switches' by number
_STATUS_SOURCES = (
    "ModeActual",
    "EStop",
    "PumpRunning",
    "DrivesEnabled",
    "CommandTimeout",
    "FaultCode",
    "SupplyPressure",
    "WalkAvailable",
)
_LIMIT_SOURCES = ("LimitRetractedMask", "LimitExtendedMask")
# the control word's signals (plc_bridge.link.plc._control_word)
_CONTROL_SIGNALS = (
    "ModeRequest",
    "EnableRequest",
    "StopRequest",
    "FaultReset",
    "TargetAckSeq",
    "TargetAckStatus",
    "FastCylinderMask",
)
# constants, ints: the control word's record and its signals' positions, ...
C_CTL, C_MODE, C_ENABLE, C_STOP, C_RESET, C_ACK_SEQ, C_ACK_STATUS, C_MASK = range(8)
C_HOLDING, C_N_STUCK, C_ESTOP, C_IGNORE, C_PLANT, C_WALK = 8, 9, 10, 11, 12, 13
N_CI = 14
# constants, floats
CF_CYCLE, CF_IPC_TIMEOUT, CF_SUPPLY_MPA, CF_POS_RES, CF_POS_INV = 0, 1, 2, 3, 4
CF_PRESS_RES, CF_PRESS_INV, CF_LIMIT_M, CF_MM, CF_MPA, CF_FAULT_HOLD = 5, 6, 7, 8, 9, 10
N_CF = 11
# the scan's state, ints
S_K, S_ACTIVE, S_LATCHED, S_ENGAGED, S_DRIVES = 0, 1, 2, 3, 4
S_ACK_HAS, S_ACK_SEQ, S_ACK_STATUS, S_ACK_VERSION = 5, 6, 7, 8
S_KEY_SET, S_KEY_MODE, S_KEY_ESTOP, S_KEY_DRIVES, S_KEY_TIMEOUT, S_KEY_FAULT = 9, 10, 11, 12, 13, 14
S_ST_MODE, S_ST_ESTOP, S_ST_PUMP, S_ST_DRIVES, S_ST_TIMEOUT, S_ST_FAULT = 15, 16, 17, 18, 19, 20
S_ST_VERSION, S_LIM_RET, S_LIM_EXT, S_PLC_RET, S_PLC_EXT = 21, 22, 23, 24, 25
S_POS_NEXT, S_PRESS_NEXT, S_OUT_N, S_EV_N, S_IN_AT, S_U_VERSION, S_LIM_VERSION = range(26, 33)
N_SI = 33
# the scan's state, floats
SF_LAST_FAULT, SF_ST_SUPPLY = 0, 1
N_SF = 2
# what the compiled scans ask the caller to log: (kind, record, t, a, b)
EV_FAULT, EV_STALE, EV_AGAIN, EV_ACTIVE = 0, 1, 2, 3
MAX_EVENTS = 256
#: frames a scan takes from the bus at most (PlcLink.poll's ``max_frames``)
MAX_FRAMES = 1000
#: a frame in and out of the compiled scans: id, a flag (in: classic; out: the scan),
#: length, payload (cut or padded to 8 bytes)
FRAME = struct.Struct("<IHBx8s")
#: what :func:`run_scans` returns when a transducer's noise block has no row left
NOISE_EXHAUSTED = -2
_NO_FRAMES = np.frombuffer(b"", dtype=np.uint8).reshape(0, FRAME.size)

_MOTION = (int(Mode.MANUAL), int(Mode.ATTITUDE_ADJUST), int(Mode.WALK), int(Mode.HOMING))
if (
    set(_MOTION) != {1, 2, 3, 4}
    or _MOTION[2] != 3
    or int(Fault.IPC_TIMEOUT) != 6
    or int(Fault.ESTOP) != 1
):
    raise ImportError("hil_sim.plc_fast: the DBC's modes or faults changed; renumber them")


@jit
def limit_switch_bits(
    x: FloatArray, retracted_at: float, extended_at: FloatArray
) -> tuple[int, int]:
    """The rods at their retracted and at their extended limit switches, as bit masks
    (bit i: ``can_index`` i): ``x <= retracted_at``, ``x >= extended_at``. Compiled: the
    PLC reads its switches every scan, and they change a few times in a run."""
    retracted = 0
    extended = 0
    for i in range(x.shape[0]):
        if x[i] <= retracted_at:
            retracted |= 1 << i
        if x[i] >= extended_at[i]:
            extended |= 1 << i
    return retracted, extended


@jit
def _fresh(rx_i: IntArray, rx_f: FloatArray, r: int, now: float) -> bool:
    """``RxRecord.fresh``."""
    if not rx_i[r, RI_HAS_RX]:
        return False
    grace = now < rx_f[r, RF_GRACE_UNTIL]
    return now - rx_f[r, RF_LAST_RX] <= rx_f[r, RF_GRACE_TIMEOUT if grace else RF_TIMEOUT]


@jit
def _event(
    events: FloatArray, st_i: IntArray, kind: int, r: int, t: float, a: float, b: float
) -> None:
    n = st_i[S_EV_N]
    if n < events.shape[0]:
        events[n, 0] = kind
        events[n, 1] = r
        events[n, 2] = t
        events[n, 3] = a
        events[n, 4] = b
        st_i[S_EV_N] = n + 1


@jit
def _apply_active(mask, now, rx_i, rx_f, tx_i, tx_f):
    """``LinkSide._apply_active``: the receive timeouts (``RxRecord.set_timeout``, a
    shorter one after one old timeout of grace) and the send periods of ``mask``."""
    for r in range(rx_i.shape[0]):
        active = rx_i[r, RI_CAN_BE_FAST] and (rx_i[r, RI_SLOTMASK] & mask) != 0
        new = rx_f[r, RF_TIMEOUT_ACTIVE] if active else rx_f[r, RF_TIMEOUT_INACTIVE]
        if new < rx_f[r, RF_TIMEOUT] and rx_i[r, RI_HAS_RX]:
            rx_f[r, RF_GRACE_TIMEOUT] = rx_f[r, RF_TIMEOUT]
            rx_f[r, RF_GRACE_UNTIL] = now + rx_f[r, RF_TIMEOUT]
        rx_f[r, RF_TIMEOUT] = new
    for m in range(tx_i.shape[0]):
        active = tx_i[m, TI_CAN_BE_FAST] and (tx_i[m, TI_SLOTMASK] & mask) != 0
        tx_f[m, TF_PERIOD] = tx_f[m, TF_PERIOD_ACTIVE] if active else tx_f[m, TF_PERIOD_INACTIVE]


@jit
def run_scans(
    n_scans, in_frames, pos_block, press_block, p_view, plant_args,
    rx_msg, rx_fi, rx_ff, counters, lookup, rx_i, rx_f, rx_vals, rx_counts, scratch,
    tx_msg, tx_fi, tx_ff, tx_src, tx_i, tx_f, link_counts,
    cfg_i, cfg_f, st_i, st_f,
    u, command, ports, x_view, extended_at, pos_read,
    press_read, pos_mm, press_mpa, stuck_idx, stuck_open, hmi_vals, values,
    out_frames, events,
):  # fmt: skip
    """``n_scans`` PLC scans from scan ``st_i[S_K]``; the frames received
    (``in_frames``, as drained from the bus, one :data:`FRAME` a row, its flag: a
    classic frame) are read from the first scan on (at most :data:`MAX_FRAMES` a
    scan), the frames sent go to ``out_frames`` (its flag: the scan, 0-based), what to
    log to ``events``. Returns (0 or :data:`~hil_sim.plc_frames.ENCODE_OVERFLOW`, the
    frames sent, the events). With ``cfg_i[C_PLANT]`` the plant is
    integrated here after each scan (the rig's own kernel with ``plant_args``:
    :meth:`~hil_sim.rig.Rig.kernel_call`);
    else ``n_scans`` is 1 and the caller advances it."""
    cycle = cfg_f[CF_CYCLE]
    in_n = in_frames.shape[0]
    st_i[S_OUT_N] = 0
    st_i[S_EV_N] = 0
    st_i[S_IN_AT] = 0
    n_rx = rx_i.shape[0]
    n_tx = tx_i.shape[0]
    n = N_CYLINDERS
    for j in range(n_scans):
        k = st_i[S_K]
        t = k * cycle
        # -- _sample: the transducers' noise streams move on; the readings are taken
        # only when a frame needs them (PlcLink.defer_readings); the limit switches
        if st_i[S_POS_NEXT] >= pos_block.shape[0] or st_i[S_PRESS_NEXT] >= press_block.shape[0]:
            return NOISE_EXHAUSTED, st_i[S_OUT_N], st_i[S_EV_N]  # (scans_allowed keeps clear)
        st_i[S_POS_NEXT] += 1
        st_i[S_PRESS_NEXT] += 1
        pos_taken = False
        press_taken = False
        ret, ext = limit_switch_bits(x_view, cfg_f[CF_LIMIT_M], extended_at)
        if ret != st_i[S_LIM_RET] or ext != st_i[S_LIM_EXT]:
            st_i[S_LIM_RET] = ret
            st_i[S_LIM_EXT] = ext
            st_i[S_PLC_RET] = ret
            st_i[S_PLC_EXT] = ext
            st_i[S_LIM_VERSION] += 1
        # -- poll: the frames received (LinkSide.on_message / RxRecord.on_frame)
        if st_i[S_IN_AT] < in_n:
            taken = 0
            while st_i[S_IN_AT] < in_n and taken < MAX_FRAMES:
                i = st_i[S_IN_AT]
                st_i[S_IN_AT] = i + 1
                taken += 1
                f = in_frames[i]
                fid = np.int64(f[0]) | np.int64(f[1]) << 8 | np.int64(f[2]) << 16
                fid |= np.int64(f[3]) << 24
                if not f[4]:  # the flag: classic
                    outcome = NOT_CLASSIC
                else:
                    r = lookup[fid] if 0 <= fid < lookup.shape[0] else -1
                    if r == -1:
                        outcome = UNKNOWN_ID
                    elif r == -2:
                        outcome = OWN_ECHO
                    else:
                        outcome, lost = check_frame(
                            rx_msg, rx_fi, rx_ff, counters, r, f[8:16], int(f[6]),
                            rx_i[r, RI_LAST_COUNTER : RI_LAST_COUNTER + 1], rx_vals[r], scratch,
                        )  # fmt: skip
                        if outcome == ACCEPTED:
                            rx_f[r, RF_LAST_RX] = t
                            rx_i[r, RI_HAS_RX] = 1
                            rx_i[r, RI_HAS_VALUES] = 1
                            rx_i[r, RI_LOST] += lost
                            if lost != 0:
                                st_f[SF_LAST_FAULT] = t
                            if r == cfg_i[C_CTL]:  # PlcLink._on_accepted
                                mask = np.int64(rx_vals[r, cfg_i[C_MASK]])
                                if mask != st_i[S_ACTIVE]:
                                    _event(events, st_i, EV_ACTIVE, r, t, float(mask), 0.0)
                                    st_i[S_ACTIVE] = mask
                                    _apply_active(mask, t, rx_i, rx_f, tx_i, tx_f)
                        elif CRC_ERROR <= outcome <= VALUE_ERROR:  # RX_FAULTS
                            st_f[SF_LAST_FAULT] = t
                            if t - rx_f[r, RF_LOGGED_AT] > cfg_f[CF_FAULT_HOLD]:
                                _event(events, st_i, EV_FAULT, r, t, float(outcome), 0.0)
                            rx_f[r, RF_LOGGED_AT] = t
                        rx_counts[r, outcome] += 1
                link_counts[outcome] += 1
        # -- poll: timeouts (LinkSide._check_timeouts, RxRecord.check_timeout)
        for r in range(n_rx):
            was = rx_i[r, RI_WAS_FRESH]
            fresh = _fresh(rx_i, rx_f, r, t)
            if was and not fresh:
                rx_counts[r, TIMEOUTS] += 1
                rx_i[r, RI_LAST_COUNTER] = -1
                rx_i[r, RI_HAS_VALUES] = 0
                st_f[SF_LAST_FAULT] = t
                _event(events, st_i, EV_STALE, r, t, t - rx_f[r, RF_LAST_RX], rx_f[r, RF_TIMEOUT])
            elif fresh and not was:
                _event(events, st_i, EV_AGAIN, r, t, float(rx_counts[r, TIMEOUTS]), 0.0)
            rx_i[r, RI_WAS_FRESH] = fresh
        # the command timeouts (PlcLink.command_timeout, ipc_timeout)
        timeout = False
        lost_ipc = False
        for r in range(n_rx):
            if not rx_i[r, RI_COMMAND]:
                continue
            if not _fresh(rx_i, rx_f, r, t):
                timeout = True
            if not rx_i[r, RI_HAS_RX] or t - rx_f[r, RF_LAST_RX] > cfg_f[CF_IPC_TIMEOUT]:
                lost_ipc = True
        # -- poll: the frames due (LinkSide._send_due, PlcLink._values_for)
        for m in range(n_tx):
            period = tx_f[m, TF_PERIOD]
            if t < tx_f[m, TF_NEXT_DUE] - 0.25 * period:
                continue
            kind = tx_i[m, TI_KIND]
            lo = tx_i[m, TI_LO]
            hi = tx_i[m, TI_HI]
            if kind == KIND_POSITIONS:
                if not pos_taken:
                    row = st_i[S_POS_NEXT] - 1
                    for c in range(n):
                        v = x_view[c] + pos_block[row, c]
                        if cfg_f[CF_POS_RES] > 0:
                            v = np.rint(v * cfg_f[CF_POS_INV]) * cfg_f[CF_POS_RES]
                        pos_read[c] = v
                        pos_mm[c] = v / cfg_f[CF_MM]
                    pos_taken = True
                for c in range(lo, hi):
                    values[c - lo] = pos_mm[c]
            elif kind == KIND_PRESSURES:
                if not press_taken:
                    row = st_i[S_PRESS_NEXT] - 1
                    for c in range(2 * n):
                        v = p_view[c] + press_block[row, c]
                        if cfg_f[CF_PRESS_RES] > 0:
                            v = np.rint(v * cfg_f[CF_PRESS_INV]) * cfg_f[CF_PRESS_RES]
                        press_read[c] = v
                    for c in range(n):  # (19, 2) by rows: cap, rod of each can_index
                        press_mpa[2 * c] = press_read[c] / cfg_f[CF_MPA]
                        press_mpa[2 * c + 1] = press_read[n + c] / cfg_f[CF_MPA]
                    press_taken = True
                for c in range(2 * lo, 2 * hi):
                    values[c - 2 * lo] = press_mpa[c]
            elif kind == KIND_STATUS:
                for f in range(tx_msg[m, 3]):
                    src = tx_src[m, f]
                    if src == 0:
                        values[f] = st_i[S_ST_MODE]
                    elif src == 1:
                        values[f] = st_i[S_ST_ESTOP]
                    elif src == 2:
                        values[f] = st_i[S_ST_PUMP]
                    elif src == 3:
                        values[f] = st_i[S_ST_DRIVES]
                    elif src == 4:
                        values[f] = 1 if (st_i[S_ST_TIMEOUT] or timeout) else 0
                    elif src == 5:
                        values[f] = st_i[S_ST_FAULT]
                    elif src == 6:
                        values[f] = st_f[SF_ST_SUPPLY]
                    else:
                        values[f] = cfg_i[C_WALK]
            elif kind == KIND_LIMITS:
                for f in range(tx_msg[m, 3]):
                    values[f] = st_i[S_PLC_RET] if tx_src[m, f] == 0 else st_i[S_PLC_EXT]
            else:
                for f in range(tx_msg[m, 3]):
                    values[f] = hmi_vals[f]
            # LinkSide._send: the bus health is ACTIVE throughout (FastPlc.usable)
            counter = tx_i[m, TI_COUNTER]
            tx_i[m, TI_COUNTER] = (counter + 1) % 15
            o = st_i[S_OUT_N]
            row = out_frames[o]
            dlc = encode_frame(tx_msg, tx_fi, tx_ff, m, counter, values, row[8:16])
            if dlc == ENCODE_OVERFLOW:
                return ENCODE_OVERFLOW, st_i[S_OUT_N], st_i[S_EV_N]
            fid = tx_msg[m, 0]
            for b in range(4):
                row[b] = (fid >> (8 * b)) & 0xFF
            row[4] = j & 0xFF
            row[5] = (j >> 8) & 0xFF
            row[6] = dlc
            st_i[S_OUT_N] = o + 1
            link_counts[TIMEOUTS] += 1  # tx_frames
            nd = tx_f[m, TF_NEXT_DUE] + period
            if nd <= t:
                if nd + period <= t:
                    link_counts[TIMEOUTS + 1] += 1  # tx_overruns
                nd = t + period
            tx_f[m, TF_NEXT_DUE] = nd
        # -- _logic (HilSimulator._logic with no silent PLC and no sensor fault)
        c = cfg_i[C_CTL]
        have_ctl = _fresh(rx_i, rx_f, c, t) and rx_i[c, RI_HAS_VALUES] != 0
        estop = cfg_i[C_ESTOP] != 0
        if estop:
            st_i[S_LATCHED] = 1  # Fault.ESTOP
        elif st_i[S_ENGAGED] and lost_ipc:
            st_i[S_LATCHED] = 6  # Fault.IPC_TIMEOUT
        if (
            st_i[S_LATCHED] != 0
            and have_ctl
            and rx_vals[c, cfg_i[C_RESET]] != 0
            and not estop
            and not timeout
        ):
            st_i[S_LATCHED] = 0
        mode = np.int64(0)
        if have_ctl and st_i[S_LATCHED] == 0:
            mode = np.int64(rx_vals[c, cfg_i[C_MODE]])
        if mode == 3 and not cfg_i[C_WALK]:  # WALK refused: not echoed, the drives stay off
            mode = np.int64(0)
        drives = (
            have_ctl
            and rx_vals[c, cfg_i[C_ENABLE]] != 0
            and rx_vals[c, cfg_i[C_STOP]] == 0
            and 1 <= mode <= 4  # MOTION_MODES
            and not timeout
            and not estop
            and st_i[S_LATCHED] == 0
        )
        move = drives and not cfg_i[C_IGNORE]
        # the valve commands (PlcLink.valve_commands; NaN, stale: 0), limits, stuck spools
        for i in range(n):
            u[i] = 0.0
        if move:
            for r in range(n_rx):
                if not rx_i[r, RI_LOOP] or not rx_i[r, RI_HAS_RX]:
                    continue
                if not rx_i[r, RI_HAS_VALUES] or not _fresh(rx_i, rx_f, r, t):
                    continue
                for i in range(rx_i[r, RI_LO], rx_i[r, RI_HI]):
                    v = rx_vals[r, i - rx_i[r, RI_LO]]
                    u[i] = 0.0 if v != v else v
            for i in range(n):
                if (u[i] > 0 and (st_i[S_LIM_EXT] >> i) & 1) or (
                    u[i] < 0 and (st_i[S_LIM_RET] >> i) & 1
                ):
                    u[i] = 0.0
        for s in range(cfg_i[C_N_STUCK]):
            u[stuck_idx[s]] = stuck_open[s]
        st_i[S_DRIVES] = drives
        if not timeout:
            st_i[S_ENGAGED] = drives
        for i in range(n):
            command[i] = u[i]
        if cfg_i[C_HOLDING]:
            for i in range(n):
                ports[i] = 1.0 if drives else 0.0
        if have_ctl:
            ack_status = np.int64(rx_vals[c, cfg_i[C_ACK_STATUS]])
            ack_seq = np.int64(rx_vals[c, cfg_i[C_ACK_SEQ]])
            if ack_status != 0 and ack_seq != 0:
                if (
                    not st_i[S_ACK_HAS]
                    or st_i[S_ACK_SEQ] != ack_seq
                    or st_i[S_ACK_STATUS] != ack_status
                ):
                    st_i[S_ACK_VERSION] += 1
                st_i[S_ACK_HAS] = 1
                st_i[S_ACK_SEQ] = ack_seq
                st_i[S_ACK_STATUS] = ack_status
        fault = st_i[S_LATCHED]
        if (
            not st_i[S_KEY_SET]
            or st_i[S_KEY_MODE] != mode
            or st_i[S_KEY_ESTOP] != estop
            or st_i[S_KEY_DRIVES] != drives
            or st_i[S_KEY_TIMEOUT] != timeout
            or st_i[S_KEY_FAULT] != fault
        ):
            st_i[S_KEY_SET] = 1
            st_i[S_KEY_MODE] = mode
            st_i[S_KEY_ESTOP] = estop
            st_i[S_KEY_DRIVES] = drives
            st_i[S_KEY_TIMEOUT] = timeout
            st_i[S_KEY_FAULT] = fault
            st_i[S_ST_MODE] = mode
            st_i[S_ST_ESTOP] = estop
            st_i[S_ST_PUMP] = not estop
            st_i[S_ST_DRIVES] = drives
            st_i[S_ST_TIMEOUT] = timeout
            st_i[S_ST_FAULT] = fault
            st_f[SF_ST_SUPPLY] = cfg_f[CF_SUPPLY_MPA]
            st_i[S_ST_VERSION] += 1
        # -- the plant over the scan, commands held (Rig.advance; the caller keeps its
        # time)
        if cfg_i[C_PLANT]:
            _advance(*plant_args)
        st_i[S_K] = k + 1
    return 0, st_i[S_OUT_N], st_i[S_EV_N]


class FastPlc:
    """The compiled scans of one :class:`~hil_sim.simulator.HilSimulator` (module
    docstring): the state in arrays, taken over from the Python objects and handed back.
    """

    def __init__(self, sim: HilSimulator) -> None:
        self.sim = sim
        bus = sim.wire.inner
        assert isinstance(bus, LockstepBus)  # FastPlc.available
        self._bus = bus
        plc = sim._plc
        self.owner = False  #: the arrays hold the state (the Python objects are stale)
        rx_specs = plc.rx_specs
        tx_specs = plc.tx_specs
        codec = plc._codec_by_name
        self.rx_recs = tuple(plc._rx[s.frame_id] for s in rx_specs)
        self.rx = FrameTables([codec[s.name] for s in rx_specs])
        self.tx = FrameTables([codec[s.name] for s in tx_specs])
        self.tx_specs = tx_specs
        self.counters = counter_table(self.rx_recs[0])
        if any(not np.array_equal(counter_table(r), self.counters) for r in self.rx_recs):
            raise ValueError("FastPlc: every received message needs the same counter check")
        self.lookup = np.full(2048, -1, dtype=np.int64)
        for fid in plc._tx_ids:
            self.lookup[fid] = -2
        for r, s in enumerate(rx_specs):
            self.lookup[s.frame_id] = r
        n_rx, n_tx = len(rx_specs), len(tx_specs)
        self.rx_i = np.zeros((n_rx, 11), dtype=np.int64)
        self.rx_f = np.zeros((n_rx, 7))
        width = self.rx.fields_i.shape[1]
        self.rx_vals = np.zeros((n_rx, width))
        self.rx_counts = np.zeros((n_rx, TIMEOUTS + 1), dtype=np.int64)
        self.scratch = np.zeros(width)
        loop = {rec.name: slots for rec, slots in plc._loop_rows}
        all_slots = frozenset(range(N_CYLINDERS))
        for r, s in enumerate(rx_specs):
            self.rx_i[r, RI_SLOTMASK] = sum(1 << i for i in s.slots)
            self.rx_i[r, RI_CAN_BE_FAST] = int(s.can_be_fast)
            if s.name in loop:
                slots = loop[s.name]
                self.rx_i[r, RI_LOOP] = 1
                self.rx_i[r, RI_LO], self.rx_i[r, RI_HI] = slots[0], slots[-1] + 1
            self.rx_i[r, RI_COMMAND] = any(rec is self.rx_recs[r] for rec in plc._command_recs)
            self.rx_f[r, RF_TIMEOUT_ACTIVE] = plc._timeout_for(s, all_slots)
            self.rx_f[r, RF_TIMEOUT_INACTIVE] = plc._timeout_for(s, frozenset())
        self.tx_i = np.zeros((n_tx, 6), dtype=np.int64)
        self.tx_f = np.zeros((n_tx, 4))
        self.tx_src = np.zeros((n_tx, max(width, self.tx.fields_i.shape[1])), dtype=np.int64)
        for m, s in enumerate(tx_specs):
            kind = _KINDS[plc.tx_kind(s)]
            self.tx_i[m, TI_KIND] = kind
            if kind in (KIND_POSITIONS, KIND_PRESSURES):
                self.tx_i[m, TI_LO], self.tx_i[m, TI_HI] = s.slots[0], s.slots[-1] + 1
            names = codec[s.name].signal_names
            if kind == KIND_STATUS:
                self.tx_src[m, : len(names)] = [_STATUS_SOURCES.index(x) for x in names]
            elif kind == KIND_LIMITS:
                self.tx_src[m, : len(names)] = [_LIMIT_SOURCES.index(x) for x in names]
            self.tx_i[m, TI_SLOTMASK] = sum(1 << i for i in s.slots)
            self.tx_i[m, TI_CAN_BE_FAST] = int(s.can_be_fast)
            period = plc._loop_period_s
            self.tx_f[m, TF_PERIOD_ACTIVE] = s.cycle_in_force_s(s.can_be_fast, period)
            self.tx_f[m, TF_PERIOD_INACTIVE] = s.cycle_in_force_s(False, period)
        self.link_counts = np.zeros(TIMEOUTS + 2, dtype=np.int64)  # outcomes, tx, overruns
        ctl = plc._ctl_rec.codec
        self.cfg_i = np.zeros(N_CI, dtype=np.int64)
        self.cfg_i[C_CTL] = rx_specs.index(ctl.spec)
        self.cfg_i[C_MODE] = ctl.signal_names.index("ModeRequest")
        self.cfg_i[C_ENABLE] = ctl.signal_names.index("EnableRequest")
        self.cfg_i[C_STOP] = ctl.signal_names.index("StopRequest")
        self.cfg_i[C_RESET] = ctl.signal_names.index("FaultReset")
        self.cfg_i[C_ACK_SEQ] = ctl.signal_names.index("TargetAckSeq")
        self.cfg_i[C_ACK_STATUS] = ctl.signal_names.index("TargetAckStatus")
        self.cfg_i[C_MASK] = ctl.signal_names.index("FastCylinderMask")
        self.cfg_i[C_HOLDING] = int(sim.rig.load_holding_valves)
        # the plant in line where the rig's advance is its kernel's call (rig.Rig's)
        self._plant_inline = type(sim.rig) is Rig and sim.rig.kernel_call(1)[0] is _advance
        self.cfg_i[C_PLANT] = int(self._plant_inline)
        self.cfg_i[C_WALK] = int(sim.walk_available)
        self._rows_left = 0
        self.cfg_f = np.zeros(N_CF)
        self.cfg_f[CF_CYCLE] = sim.cycle_s
        self.cfg_f[CF_IPC_TIMEOUT] = plc._ipc_timeout_s
        self.cfg_f[CF_SUPPLY_MPA] = units.to_mpa(sim.cfg.hydraulics.supply_pressure_pa)
        pos, press = sim._pos_sensor, sim._press_sensor
        self.cfg_f[CF_POS_RES], self.cfg_f[CF_POS_INV] = pos.resolution, pos._inv_res
        self.cfg_f[CF_PRESS_RES], self.cfg_f[CF_PRESS_INV] = press.resolution, press._inv_res
        self.cfg_f[CF_LIMIT_M] = sim._limit_m
        self.cfg_f[CF_MM], self.cfg_f[CF_MPA] = units.MM, units.MPA
        self.cfg_f[CF_FAULT_HOLD] = FAULT_HOLD_S
        self.st_i = np.zeros(N_SI, dtype=np.int64)
        self.st_f = np.zeros(N_SF)
        self.u = np.zeros(N_CYLINDERS)
        self.pos_read = np.zeros(N_CYLINDERS)
        self.press_read = np.zeros(2 * N_CYLINDERS)
        self.pos_mm = np.zeros(N_CYLINDERS)
        self.press_mpa = np.zeros(2 * N_CYLINDERS)
        self.stuck_idx = np.zeros(N_CYLINDERS, dtype=np.int64)
        self.stuck_open = np.zeros(N_CYLINDERS)
        self.hmi_vals = np.zeros(max(width, self.tx.fields_i.shape[1]))
        self.values = np.zeros(self.hmi_vals.shape[0])
        self._out_cap = 64
        self._alloc_out(self._out_cap)
        self._rig_arrays: tuple[Any, ...] = ()
        self._static: tuple[Any, ...] = ()
        self.events = np.zeros((MAX_EVENTS, 5))
        #: the Python objects' figures when the arrays took over (counts are added)
        self._status_version = 0
        self._ack_version = 0
        self._u_version = 0

    def _alloc_out(self, cap: int) -> None:
        self._out_cap = cap
        self.out_frames = np.zeros((cap, FRAME.size), dtype=np.uint8)

    # ----------------------------------------------------------------- when

    @staticmethod
    def available(sim: HilSimulator) -> bool:
        """Compiled scans for this simulator at all: numba, and a lockstep bus."""
        return HAVE_NUMBA and isinstance(sim.wire.inner, LockstepBus)

    def scans_allowed(self, limit: int) -> int:
        """How many of the next ``limit`` scans may run compiled (0: the next one runs
        as Python)."""
        sim = self.sim
        if sim._stalled or sim._dead or not sim._deferred_readings or sim._sensor_fault:
            return 0
        if sim.rig.part_state == "loading" or not sim.wire.receives_all:
            return 0
        if self._bus.has_error_frame():
            return 0
        if not self.owner:
            health = sim._plc.bus_health
            if (
                health.state is not BusState.ACTIVE
                or health.backoff_s != health.backoff_initial_s
                or health.tx_error_active
            ):
                return 0
        if self.owner:
            rows = self._rows_left
        else:
            pos, press = sim._pos_sensor, sim._press_sensor
            rows = min(pos._block_len - pos._next, press._block_len - press._next)
        if rows < limit:
            limit = rows
        if sim.scenario.events:
            k = sim._k
            for j in range(limit):
                if sim._now_active((k + j) * sim.cycle_s) != sim._active:
                    return j
        if not self._plant_inline and limit > 1:
            limit = 1
        return max(limit, 0)

    # ----------------------------------------------------------------- the state

    def take_over(self) -> None:
        """The Python objects' state into the arrays (from now on the arrays hold it)."""
        sim, plc = self.sim, self.sim._plc
        for r, rec in enumerate(self.rx_recs):
            self.rx_i[r, RI_LAST_COUNTER] = -1 if rec.last_counter is None else rec.last_counter
            self.rx_i[r, RI_HAS_RX] = rec.last_rx is not None
            self.rx_f[r, RF_LAST_RX] = 0.0 if rec.last_rx is None else rec.last_rx
            self.rx_i[r, RI_LOST] = rec.lost_frames
            self.rx_i[r, RI_WAS_FRESH] = rec.was_fresh
            self.rx_i[r, RI_HAS_VALUES] = rec.values is not None
            if rec.values is not None:
                self.rx_vals[r, : len(rec.values)] = rec.values
            self.rx_f[r, RF_TIMEOUT] = rec.timeout_s
            self.rx_f[r, RF_GRACE_TIMEOUT] = rec.grace_timeout_s
            self.rx_f[r, RF_GRACE_UNTIL] = rec.grace_until
            self.rx_f[r, RF_LOGGED_AT] = plc._fault_logged_at.get(rec.name, -math.inf)
        self.rx_counts[:] = 0
        self.link_counts[:] = 0
        for m, s in enumerate(self.tx_specs):
            self.tx_i[m, TI_COUNTER] = plc._tx_counter[s.frame_id]
            self.tx_f[m, TF_PERIOD] = plc._period[s.frame_id]
            self.tx_f[m, TF_NEXT_DUE] = plc._next_due[s.frame_id]
        st, sf = self.st_i, self.st_f
        st[S_K] = sim._k
        st[S_ACTIVE] = sum(1 << i for i in plc._active)
        st[S_LATCHED] = int(sim._latched)
        st[S_ENGAGED] = sim._engaged
        st[S_DRIVES] = sim._drives
        ack = sim._hmi_ack
        st[S_ACK_HAS] = ack is not None
        st[S_ACK_SEQ], st[S_ACK_STATUS] = (0, 0) if ack is None else (ack[0], int(ack[1]))
        key = sim._status_key
        st[S_KEY_SET] = bool(key)
        if key:
            st[S_KEY_MODE : S_KEY_FAULT + 1] = [int(key[0]), key[1], key[2], key[3], key[4]]
        word = plc._status
        st[S_ST_MODE], st[S_ST_ESTOP], st[S_ST_PUMP] = int(word.mode), word.estop, word.pump_running
        st[S_ST_DRIVES], st[S_ST_TIMEOUT] = word.drives_enabled, word.command_timeout
        st[S_ST_FAULT] = int(word.fault)
        sf[SF_ST_SUPPLY] = units.to_mpa(word.supply_pressure_pa)
        st[S_LIM_RET], st[S_LIM_EXT] = sim._limits
        st[S_PLC_RET], st[S_PLC_EXT] = plc._limits
        pos, press = sim._pos_sensor, sim._press_sensor
        st[S_POS_NEXT], st[S_PRESS_NEXT] = pos._next, press._next
        #: scans left before a transducer's noise block runs out (scans_allowed)
        self._rows_left = min(pos._block_len - pos._next, press._block_len - press._next)
        sf[SF_LAST_FAULT] = plc._last_fault
        self.u[:] = sim._applied
        self.pos_read[:] = sim._pos_reading
        self.press_read[:] = np.ascontiguousarray(sim._press_reading.T).ravel()
        stuck = sim._stuck
        self.cfg_i[C_N_STUCK] = len(stuck)
        for s_i, (i, k) in enumerate(stuck):
            self.stuck_idx[s_i] = i
            self.stuck_open[s_i] = sim._held[k]
        self.cfg_i[C_ESTOP] = sim._estop
        self.cfg_i[C_IGNORE] = sim._ignore
        names = plc._codec_by_name
        for m, spec in enumerate(self.tx_specs):
            if self.tx_i[m, TI_KIND] == KIND_HMI:
                vals = plc._hmi_values(names[spec.name].signal_names)
                self.hmi_vals[: len(vals)] = vals
        self._status_version = int(st[S_ST_VERSION])
        self._ack_version = int(st[S_ACK_VERSION])
        self.owner = True

    def export(self) -> None:
        """The arrays' state back into the Python objects (they hold it from now on)."""
        if not self.owner:
            return
        sim, plc = self.sim, self.sim._plc
        self.owner = False
        st, sf = self.st_i, self.st_f
        for r, rec in enumerate(self.rx_recs):
            last = int(self.rx_i[r, RI_LAST_COUNTER])
            rec.last_counter = None if last < 0 else last
            rec.last_rx = float(self.rx_f[r, RF_LAST_RX]) if self.rx_i[r, RI_HAS_RX] else None
            rec.lost_frames = int(self.rx_i[r, RI_LOST])
            rec.was_fresh = bool(self.rx_i[r, RI_WAS_FRESH])
            nf = len(rec.codec.signal_names)
            rec.values = (
                tuple(self.rx_vals[r, :nf].tolist()) if self.rx_i[r, RI_HAS_VALUES] else None
            )
            rec.timeout_s = float(self.rx_f[r, RF_TIMEOUT])
            rec.grace_timeout_s = float(self.rx_f[r, RF_GRACE_TIMEOUT])
            rec.grace_until = float(self.rx_f[r, RF_GRACE_UNTIL])
            logged = float(self.rx_f[r, RF_LOGGED_AT])
            if logged != -math.inf:
                plc._fault_logged_at[rec.name] = logged
            for o in np.flatnonzero(self.rx_counts[r]):
                name = "timeouts" if o == TIMEOUTS else RX_OUTCOMES[o]
                rec.counters[name] += int(self.rx_counts[r, o])
        for o in np.flatnonzero(self.link_counts[:TIMEOUTS]):
            plc.rx_outcomes[RX_OUTCOMES[o]] += int(self.link_counts[o])
        if self.link_counts[TIMEOUTS]:
            plc.tx_counts["tx_frames"] += int(self.link_counts[TIMEOUTS])
        if self.link_counts[TIMEOUTS + 1]:
            plc.tx_counts["tx_overruns"] += int(self.link_counts[TIMEOUTS + 1])
        for m, s in enumerate(self.tx_specs):
            plc._tx_counter[s.frame_id] = int(self.tx_i[m, TI_COUNTER])
            plc._period[s.frame_id] = float(self.tx_f[m, TF_PERIOD])
            plc._next_due[s.frame_id] = float(self.tx_f[m, TF_NEXT_DUE])
        plc._records_set()
        plc._commands_fresh_until = -math.inf
        plc._ipc_seen_until = -math.inf
        plc._last_fault = float(sf[SF_LAST_FAULT])
        plc._set_active_group(indices_of(int(st[S_ACTIVE])))
        sim._k = int(st[S_K])
        sim.t_s = sim._k * sim.cycle_s
        sim._latched = Fault(int(st[S_LATCHED]))
        sim._engaged = bool(st[S_ENGAGED])
        sim._drives = bool(st[S_DRIVES])
        self._sync_outputs()
        sim._status_key = (
            (
                Mode(int(st[S_KEY_MODE])),
                bool(st[S_KEY_ESTOP]),
                bool(st[S_KEY_DRIVES]),
                bool(st[S_KEY_TIMEOUT]),
                int(st[S_KEY_FAULT]),
            )
            if st[S_KEY_SET]
            else ()
        )
        bits = (int(st[S_LIM_RET]), int(st[S_LIM_EXT]))
        if bits != sim._limits:
            sim._limits = bits
            sim._retracted = (bits[0] >> sim._bit) & 1 == 1
            sim._extended = (bits[1] >> sim._bit) & 1 == 1
        plc._limits = (int(st[S_PLC_RET]), int(st[S_PLC_EXT]))
        sim._pos_sensor._next = int(st[S_POS_NEXT])
        sim._press_sensor._next = int(st[S_PRESS_NEXT])
        sim._pos_reading = self.pos_read.copy()
        sim._press_reading = self.press_read.reshape(2, N_CYLINDERS).T.copy()
        plc._pos_m, plc._pos_mm = sim._pos_reading.copy(), None
        plc._press_pa, plc._press_mpa = sim._press_reading.copy(), None
        # the caches of the Python scan: worked out anew at its first logic
        sim._ctl = None
        sim._fresh_scan = True
        sim._logic_inputs = ()
        sim._u_key = ()

    def _sync_outputs(self) -> None:
        """The status word, the HMI acknowledgement and the spool commands the arrays
        hold, as the simulator's and the link's objects (each made anew only when it
        changed)."""
        sim, plc = self.sim, self.sim._plc
        st = self.st_i
        if st[S_ST_VERSION] != self._status_version:
            self._status_version = int(st[S_ST_VERSION])
            status = PlcStatus(
                mode=Mode(int(st[S_ST_MODE])),
                estop=bool(st[S_ST_ESTOP]),
                pump_running=bool(st[S_ST_PUMP]),
                drives_enabled=bool(st[S_ST_DRIVES]),
                command_timeout=bool(st[S_ST_TIMEOUT]),
                fault=Fault(int(st[S_ST_FAULT])),
                supply_pressure_pa=sim.cfg.hydraulics.supply_pressure_pa,
                walk_available=sim.walk_available,
            )
            sim._status = status
            plc._status = status
        if st[S_ACK_VERSION] != self._ack_version:
            self._ack_version = int(st[S_ACK_VERSION])
            sim._hmi_ack = (int(st[S_ACK_SEQ]), TargetAck(int(st[S_ACK_STATUS])))
        if not np.array_equal(sim._applied, self.u):
            sim._applied = self.u.copy()
            sim._u = sim._applied

    def sync_outputs(self) -> None:
        """:meth:`_sync_outputs` while the arrays hold the state (the simulator's
        ``status``, ``hmi_ack`` and ``applied_command`` read through this)."""
        if self.owner:
            self._sync_outputs()

    # ----------------------------------------------------------------- running

    def run(self, n_scans: int) -> None:
        """``n_scans`` compiled scans (``n_scans`` from :meth:`scans_allowed`)."""
        sim = self.sim
        if not self.owner:
            self.take_over()
        rig = sim.rig
        if (rig.command, rig.ports_open, rig.x_view) != self._rig_arrays:
            self._rig_arrays = (rig.command, rig.ports_open, rig.x_view)
            self._static = self._static_args()
        msgs = sim.wire.recv_all(MAX_FRAMES)
        if msgs:
            pack = FRAME.pack
            frames = np.frombuffer(
                b"".join(
                    [
                        pack(
                            m.arbitration_id,
                            not (m.is_remote_frame or m.is_extended_id or m.is_fd),
                            len(m.data),
                            m.data,
                        )
                        for m in msgs
                    ]
                ),
                dtype=np.uint8,
            ).reshape(len(msgs), FRAME.size)
            if len(msgs) == MAX_FRAMES:
                n_scans = 1  # the next scan takes the rest from the bus
        else:
            frames = _NO_FRAMES
        if n_scans * len(self.tx_specs) > self._out_cap:
            self._alloc_out(n_scans * len(self.tx_specs))
            self._static = self._static_args()
        k0 = sim._k
        spc = sim.steps_per_cycle
        # (the walking rig's advance does more than the kernel: its arguments are only
        # there for the types, and the caller advances it)
        _, plant_args = Rig.kernel_call(rig, spc)
        status, n_out, n_events = run_scans(
            n_scans,
            frames,
            sim._pos_sensor._block,
            sim._press_sensor._block,
            rig.pressure_view,
            plant_args,
            *self._static,
        )
        if status == ENCODE_OVERFLOW:
            raise OverflowError("cannot convert float infinity to integer")
        if status == NOISE_EXHAUSTED:
            raise RuntimeError("FastPlc.run: more scans than the noise blocks hold")
        if n_out or sim.wire.has_delayed:
            self._send_out(k0, n_scans, n_out)
        if n_events:
            self._log_events()
        sim._k = k = k0 + n_scans
        sim.t_s = k * sim.cycle_s
        self._rows_left -= n_scans
        if self._plant_inline:
            step = spc * rig.step_s
            for _ in range(n_scans):  # the sum Rig.advance makes, scan by scan
                rig.t_s += step
        else:
            rig.advance(spc)

    def _static_args(self) -> tuple[Any, ...]:
        """:func:`run_scans`' arguments after the per-call ones: arrays kept from call to
        call (made anew when one of them is)."""
        sim = self.sim
        command, ports, x_view = self._rig_arrays
        return (
            self.rx.msg, self.rx.fields_i, self.rx.fields_f, self.counters, self.lookup,
            self.rx_i, self.rx_f, self.rx_vals, self.rx_counts, self.scratch,
            self.tx.msg, self.tx.fields_i, self.tx.fields_f, self.tx_src, self.tx_i, self.tx_f,
            self.link_counts, self.cfg_i, self.cfg_f, self.st_i, self.st_f,
            self.u, command, ports, x_view, sim._extended_at,
            self.pos_read, self.press_read, self.pos_mm, self.press_mpa, self.stuck_idx,
            self.stuck_open, self.hmi_vals, self.values,
            self.out_frames, self.events,
        )  # fmt: skip

    def _send_out(self, k0: int, n_scans: int, n_out: int) -> None:
        """The scans' frames through the wire, each scan's at its time (the wire's
        delays and its clock: frames it delayed go on the bus at each scan's start), as
        the Python scans send them."""
        sim = self.sim
        wire = sim.wire
        cycle = sim.cycle_s
        groups: list[tuple[int, list[can.Message]]] = []
        for fid, j, dlc, data in FRAME.iter_unpack(self.out_frames[:n_out].tobytes()):
            if not groups or groups[-1][0] != j:
                groups.append((j, []))
            groups[-1][1].append(TxFrame(fid, data[:dlc]))

        def at(j: int) -> None:
            """The simulator's clock (the wire's) at scan ``j``, the frames it delayed
            until then released, as at the start of each Python scan."""
            sim._k = k0 + j
            sim.t_s = sim._k * cycle
            wire.release_due(sim.t_s)

        first = 0  # the first scan not yet gone through
        if wire.quiet:  # no fault, nothing delayed: only the clock to keep (observers)
            for j, group in groups:
                sim._k = k0 + j
                sim.t_s = sim._k * cycle
                wire.send_all(group)
            return
        for j, group in groups:
            if wire.has_delayed:
                for between in range(first, j):
                    at(between)
            at(j)
            wire.send_all(group)
            first = j + 1
        if wire.has_delayed:
            for between in range(first, n_scans):
                at(between)

    def _log_events(self) -> None:
        """What the compiled scans asked to log, as ``LinkSide`` and ``PlcLink`` log it."""
        plc = self.sim._plc
        node = plc.role.node
        for kind, r, _t, a, b in self.events[: int(self.st_i[S_EV_N])].tolist():
            rec = self.rx_recs[int(r)]
            if kind == EV_FAULT:
                log.warning(
                    "%s: %s (0x%03X) rejected: %s (repeats are counted, not logged)",
                    node,
                    rec.name,
                    rec.codec.frame_id,
                    RX_OUTCOMES[int(a)],
                )
            elif kind == EV_STALE:
                log.warning(
                    "%s: %s (0x%03X) stale: no valid frame for %.0f ms (timeout %.0f ms)",
                    node,
                    rec.name,
                    rec.codec.frame_id,
                    units.to_ms(a),
                    units.to_ms(b),
                )
            elif kind == EV_AGAIN:
                if rec.counters["timeouts"] or a:  # the Python scans' timeouts, these
                    log.info("%s: %s receiving again", node, rec.name)
            elif kind == EV_ACTIVE:
                log.info("PLC: active group now %s", sorted(indices_of(int(a))))
