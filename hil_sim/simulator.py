"""The HIL simulator: the rig (:mod:`hil_sim.rig`) behind an emulated PLC on the CAN bus.

One :class:`HilSimulator` owns the plant, the transducers, the PLC's side of the DBC
(``plc_bridge.PlcLink``) and a :class:`~hil_sim.wire.FaultyWire` between that link
and the bus. Time is simulated: ``sim.clock()`` is the PLC's clock, and
:meth:`HilSimulator.step` advances plant and PLC in lockstep, so a controller in the
same process (on the same python-can ``virtual`` channel, with ``clock=sim.clock``)
can take its own step between two of ours and the run is bit-for-bit reproducible
from the seed. :meth:`HilSimulator.run_realtime` paces the same steps by the wall
clock for a controller in another process (``udp_multicast``).

One PLC scan (``plant.plc_cycle_ms``):

1. switch scenario events on/off at the scan time;
2. sample the transducers (at their sample times), apply sensor faults, hand
   positions, pressures and limit switches to the link;
3. ``poll``: read IPC frames, supervise, send what is due (status, sensors, HMI);
4. PLC logic: mode handshake (WALK refused by a rig that cannot walk), E-stop,
   command timeout, latched faults, drives; valve commands applied only with the
   drives on, never further into a limit switch;
5. integrate the plant over the scan with commands held.

Over 500 lines because the emulated PLC's scan (frames in, interlocks, frames out) and
the scenario events it plays are one sequence.
"""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np
from numpy.typing import NDArray

from config import units
from config.hil_scenario import (
    BusOff,
    CorruptCrc,
    DelayFrames,
    DropFrames,
    EStop,
    FootSlip,
    FreezeCounter,
    GroundOffset,
    HilScenario,
    HmiTargetEvent,
    HoldingValveLeak,
    IgnoreCommands,
    Leakage,
    LoadStep,
    PlcSilent,
    PlcStall,
    SensorFault,
    StuckValve,
    WireStall,
)
from config.schema import N_CYLINDERS, ProjectConfig
from config.stall import StallTrace
from hil_sim.placement import bolt_part
from hil_sim.plc_fast import FastPlc, limit_switch_bits
from hil_sim.rig import LayerTruth, Rig
from hil_sim.sensors import PositionTransducer, PressureTransducer
from hil_sim.walking import WalkingRig, WalkTruth
from hil_sim.wire import PLC_TO_IPC, FaultyWire, WireFault, match_messages
from plc_bridge import (
    ControlWord,
    Fault,
    HmiTarget,
    Mode,
    PlcLink,
    PlcStatus,
    TargetAck,
    TargetRequest,
    load_catalog,
    open_bus,
)
from plc_bridge.catalog import Catalog

FloatArray = NDArray[np.float64]

#: Modes in which the PLC lets the valves move.
MOTION_MODES = frozenset({Mode.MANUAL, Mode.ATTITUDE_ADJUST, Mode.WALK, Mode.HOMING})
_WIRE_KINDS = {
    "drop",
    "delay",
    "bad_crc",
    "frozen_counter",
    "bus_off",
    "plc_silent",
    "wire_stall",
}
_QUANTITY_COLUMN = {"cap_pressure": 0, "rod_pressure": 1}


@dataclass(frozen=True)
class Truth:
    """What the plant and the PLC really are at ``t_s`` (for tests and plots)."""

    t_s: float
    lower: LayerTruth
    upper: LayerTruth
    workpiece_roll_rad: float
    workpiece_pitch_rad: float
    rod_positions_m: FloatArray
    rod_velocities_m_s: FloatArray
    hydraulic_forces_n: FloatArray
    pressures_pa: FloatArray
    spool_m: FloatArray
    applied_command: FloatArray
    status: PlcStatus
    faults_active: tuple[str, ...] = field(default=())
    #: the arc part: ``carried``, ``loading``, ``bolted`` (:meth:`HilSimulator.bolt_part`)
    part_state: str = "carried"
    #: how much of the part's weight the upper platform carries, N (bolted: its pads)
    part_load_n: float = 0.0
    #: the walking rig's frames (``plant.contact``): world x, headings, S's yaw in M, plan
    #: positions, slip; None on the attitude rig
    walk: WalkTruth | None = None


class HilSimulator:
    """The rig and its PLC on a CAN bus.

    ``bus``: the bus the PLC is on (e.g. ``can.Bus(interface="virtual", channel=...)``);
    ``None`` opens ``cfg.can``. ``scenario``: events and settings (default: none,
    :class:`HilScenario` defaults). ``seed``: overrides ``scenario.seed``.
    """

    def __init__(
        self,
        cfg: ProjectConfig,
        bus: can.BusABC | None = None,
        scenario: HilScenario | None = None,
        seed: int | None = None,
        *,
        catalog: Catalog | None = None,
    ) -> None:
        self.cfg = cfg
        self.scenario = scenario if scenario is not None else HilScenario()
        self.seed = self.scenario.seed if seed is None else int(seed)
        plant = self.scenario.plant
        self.cycle_s = plant.plc_cycle_s
        self.steps_per_cycle = round(plant.plc_cycle_ms / plant.step_ms)
        self.rig = (WalkingRig if plant.contact else Rig)(
            cfg,
            step_s=plant.step_s,
            rod_mass_kg=plant.rod_mass_for(cfg),
            load_holding_valves=plant.load_holding_valves,
        )
        self.catalog = catalog if catalog is not None else load_catalog()
        self._k = 0
        self.t_s = 0.0
        inner = bus if bus is not None else open_bus(cfg.can)
        ss = np.random.SeedSequence(self.seed)
        s_wire, s_pos, s_press, s_fault = (int(s.generate_state(1)[0]) for s in ss.spawn(4))
        self.wire = FaultyWire(inner, self.catalog, self.clock, seed=s_wire)
        #: the compiled scans (hil_sim.plc_fast), set at the end when they can run here
        self._fast: FastPlc | None = None
        self._plc = PlcLink(cfg, self.wire, catalog=self.catalog, clock=self.clock)
        sens = self.scenario.sensors
        self._pos_sensor = PositionTransducer(
            N_CYLINDERS,
            units.um(sens.position.resolution_um),
            units.um(sens.position.noise_um),
            s_pos,
        )
        self._press_sensor = PressureTransducer(
            2 * N_CYLINDERS,
            units.kpa(sens.pressure.resolution_kpa),
            units.kpa(sens.pressure.noise_kpa),
            s_press,
        )
        self._pos_every = max(1, round(units.ms(sens.position.sample_ms) / self.cycle_s))
        self._press_every = max(1, round(units.ms(sens.pressure.sample_ms) / self.cycle_s))
        self._fault_rng = np.random.default_rng(s_fault)
        # Both transducers sample every scan and no event ever reads or changes a
        # reading: each scan's readings are taken only when a frame needs them
        # (PlcLink.defer_readings), within that scan; the noise streams move on anyway.
        self._deferred_readings = (
            self._pos_every == 1
            and self._press_every == 1
            and not any(isinstance(ev, SensorFault) for ev in self.scenario.events)
        )
        self._stroke = self.rig.params.stroke_m.copy()
        self._limit_m = plant.limit_switch_m
        self._extended_at = self._stroke - self._limit_m
        self._index = {cid: i for i, cid in enumerate(self.rig.cylinder_ids)}
        self._check_events()
        # PLC state
        self._active: set[int] = set()
        self._held: dict[int, float] = {}
        self._hmi_seq = 0
        self._hmi_issued: set[int] = set()  # hmi_target events sent (each once)
        #: TargetSeq values issued so far (one per hmi_target event)
        self.hmi_issued: list[int] = []
        self._engaged = False  # drives were on at the last scan with fresh commands
        self._hmi_ack: tuple[int, TargetAck] | None = None
        self._latched = Fault.NONE
        self._drives = False
        self._applied = np.zeros(N_CYLINDERS)
        #: the rig can walk (the walking rig): the PLC says so in its status and refuses
        #: WALK otherwise (``WalkAvailable``)
        self.walk_available = isinstance(self.rig, WalkingRig)
        self._status = PlcStatus(
            supply_pressure_pa=cfg.hydraulics.supply_pressure_pa,
            walk_available=self.walk_available,
        )
        self._pos_reading = self.rig.rod_positions_m
        self._press_reading = self.rig.pressures_pa
        self._wall_s = 0.0
        self._ctl: ControlWord | None = None
        self._cmd = np.zeros(N_CYLINDERS)
        self._fresh_scan = True
        self._status_key: tuple[Any, ...] = ()
        self._sensor_fault = False
        #: the limit switches as (retracted, extended) bit masks by can_index
        self._limits: tuple[int, int] = (-1, -1)
        self._bit = np.arange(N_CYLINDERS)
        self._stalled = False
        self._retracted = np.zeros(N_CYLINDERS, dtype=bool)
        self._extended = np.zeros(N_CYLINDERS, dtype=bool)
        # what the active events mean for each scan (kept by _derive_active)
        self._sensor_faults: list[int] = []
        self._stuck: list[tuple[int, int]] = []  # (cylinder, event)
        self._estop = self._dead = self._ignore = False
        self._active_version = 0
        self._cmd_version = 0
        self._u_key: tuple[Any, ...] = ()
        self._u = np.zeros(N_CYLINDERS)
        self._logic_inputs: tuple[Any, ...] = ()
        if FastPlc.available(self):
            self._fast = FastPlc(self)

    # ----------------------------------------------------------------- the PLC's outputs

    @property
    def plc(self) -> PlcLink:
        """The PLC's side of the link (its state up to date: the compiled scans hand it
        back to the Python objects first, and take it again at the next step)."""
        if self._fast is not None:
            self._fast.export()
        return self._plc

    @property
    def status(self) -> PlcStatus:
        """The PLC's status word, as its logic last set it."""
        if self._fast is not None:
            self._fast.sync_outputs()
        return self._status

    @property
    def applied_command(self) -> FloatArray:
        """The spool commands the PLC applies (by ``can_index``): the IPC's, or 0 where
        the drives are off, a limit switch stops the rod or a spool is stuck."""
        if self._fast is not None:
            self._fast.sync_outputs()
        return self._applied

    @property
    def hmi_ack(self) -> tuple[int, TargetAck] | None:
        """The IPC's last answer to an HMI request: (TargetSeq, status), None before one."""
        if self._fast is not None:
            self._fast.sync_outputs()
        return self._hmi_ack

    # ----------------------------------------------------------------- set-up

    def _cyl(self, cid: str, where: str) -> int:
        if cid not in self._index:
            raise ValueError(
                f"{where}: unknown cylinder {cid!r}; cylinders are {', '.join(self._index)}"
            )
        return self._index[cid]

    def _check_events(self) -> None:
        self._wire_faults: dict[int, WireFault] = {}
        self._cyl_of: dict[int, int] = {}
        for k, ev in enumerate(self.scenario.events):
            where = f"events[{k}] ({ev.kind})"
            if isinstance(ev, DropFrames | DelayFrames | CorruptCrc | FreezeCounter):
                if isinstance(ev, DelayFrames | FreezeCounter) and ev.direction != PLC_TO_IPC:
                    raise ValueError(f"{where}: direction must be plc_to_ipc for {ev.kind}")
                ids = match_messages(self.catalog, ev.messages, where)
                self._wire_faults[k] = WireFault(
                    kind=ev.kind,
                    frame_ids=ids,
                    direction=ev.direction,
                    rate=getattr(ev, "rate", 1.0),
                    max_burst=getattr(ev, "max_burst", None) or 0,
                    delay_s=ev.delay_s if isinstance(ev, DelayFrames) else 0.0,
                    key=k,
                )
            elif isinstance(ev, BusOff | PlcSilent):
                self._wire_faults[k] = WireFault(kind=ev.kind, key=k)
            elif isinstance(ev, WireStall):
                assert ev.end_s is not None  # the schema requires it
                self._wire_faults[k] = WireFault(
                    kind=ev.kind,
                    frame_ids=match_messages(self.catalog, ev.messages, where),
                    direction=ev.direction,
                    until_s=ev.end_s,
                    key=k,
                )
            elif (
                isinstance(ev, SensorFault | Leakage | StuckValve | LoadStep | HoldingValveLeak)
                and ev.cylinder is not None
            ):
                self._cyl_of[k] = self._cyl(ev.cylinder, where)
            if isinstance(ev, GroundOffset | FootSlip) and not isinstance(self.rig, WalkingRig):
                raise ValueError(f"{where}: needs plant.contact: true (the walking rig)")

    # ----------------------------------------------------------------- time

    def clock(self) -> float:
        """Simulated time (s): the PLC's clock; give it to a controller in lockstep."""
        return self.t_s

    def step(self, dt_s: float) -> None:
        """Advance plant and PLC by ``dt_s`` (a whole number of PLC scans)."""
        n = round(dt_s / self.cycle_s)
        if n < 1 or abs(n * self.cycle_s - dt_s) > 1e-9:
            raise ValueError(
                f"dt_s ({dt_s}) must be a whole number of PLC scans of {self.cycle_s} s"
            )
        t0 = time.perf_counter()
        fast = self._fast
        if fast is None:
            for _ in range(n):
                self._scan()
        else:
            done = 0
            while done < n:
                m = fast.scans_allowed(n - done)
                if m:
                    fast.run(m)
                    done += m
                else:
                    fast.export()
                    self._scan()
                    done += 1
        self._wall_s += time.perf_counter() - t0

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall-clock second spent in :meth:`step` so far."""
        return self.t_s / self._wall_s if self._wall_s > 0 else math.nan

    def run_realtime(
        self,
        duration_s: float | None = None,
        on_status: Callable[[HilSimulator], None] | None = None,
        status_interval_s: float = 0.5,
        should_stop: Callable[[], bool] | None = None,
        between_scans: Callable[[], None] | None = None,
    ) -> dict[str, Any]:
        """Run PLC scans paced by the wall clock until ``duration_s`` or ``should_stop()``;
        ``between_scans()`` after each scan (the site's acts from another thread:
        :class:`hil_sim.site.SiteServer`).

        Behind schedule, scans run back to back to catch up; more than 0.1 s behind,
        the schedule is reset and counted in ``overruns`` (the plant never skips time).
        Each scan sees only the frames that had arrived by its due time
        (:meth:`FaultyWire.set_arrival_horizon`), so catching up does not starve it.

        What is allocated before the first scan (the modules, the compiled plant, the
        rig) is moved out of the collector's reach (:func:`gc.freeze`): a full
        collection over it takes 50-60 ms, ten scans the PLC would not make; frozen, a
        collection walks only what the run has allocated since.
        """
        gc.freeze()
        start = time.monotonic()
        to_epoch = time.time() - start
        t_start = self.t_s
        next_status = start
        overruns = 0
        k = 0
        # WARA_STALL_TRACE_MS: the stacks of a scan that stalls (config.stall)
        with StallTrace() as stall:
            while duration_s is None or self.t_s - t_start < duration_s - 1e-12:
                if should_stop is not None and should_stop():
                    break
                due = start + k * self.cycle_s
                now = time.monotonic()
                if due - now > 0:
                    time.sleep(due - now)
                elif now - due > 0.1:
                    overruns += 1
                    start = now - k * self.cycle_s
                self.wire.set_arrival_horizon(start + to_epoch + k * self.cycle_s)
                stall.arm()
                self.step(self.cycle_s)
                if between_scans is not None:
                    between_scans()
                k += 1
                if on_status is not None and time.monotonic() >= next_status:
                    on_status(self)
                    next_status += status_interval_s
        self.wire.set_arrival_horizon(None)
        wall = time.monotonic() - start
        return {
            "simulated_s": self.t_s - t_start,
            "wall_s": wall,
            "overruns": overruns,
            "compute_realtime_factor": self.realtime_factor,
        }

    # ----------------------------------------------------------------- one scan

    def _scan(self) -> None:
        t = self.t_s
        self._switch_events(t)
        if self._stalled:
            # no scan: nothing sampled, read or sent; the output card's watchdog has the
            # spools centred and the load-holding valves closed; the plant goes on
            self._applied = np.zeros(N_CYLINDERS)
            self.rig.command[:] = 0.0
            if self.rig.load_holding_valves:
                self.rig.ports_open[:] = 0.0
            self.rig.advance(self.steps_per_cycle)
            self._k += 1
            self.t_s = self._k * self.cycle_s
            return
        self._sample(self._k)
        self.wire.release_due(t)
        frames = 0
        faults = self.wire.faults
        if not faults or not any(f.kind == "plc_silent" for f in faults):
            # on bus-off the PLC still runs (its frames are lost), when silent it is dead
            frames = self._plc.poll(t)
        self._logic(t, frames)
        if self._deferred_readings:
            self._plc.defer_readings(None, None)  # this scan's readings, or none
        self.rig.advance(self.steps_per_cycle)
        self._k += 1
        self.t_s = self._k * self.cycle_s

    def _switch_events(self, t: float) -> None:
        events = self.scenario.events
        if not events:
            return
        now_active = self._now_active(t)
        started = now_active - self._active
        ended = self._active - now_active
        if not started and not ended:
            return
        for k in sorted(started):
            ev = events[k]
            if isinstance(ev, HmiTargetEvent):  # one new TargetSeq, once
                self._hmi_issued.add(k)
                self._hmi_seq = (self._hmi_seq % 255) + 1
                self.hmi_issued.append(self._hmi_seq)
                req = {"cancel": TargetRequest.CANCEL, "walk": TargetRequest.WALK}.get(
                    ev.request, TargetRequest.NEW_TARGET
                )
                self._plc.set_hmi_target(
                    HmiTarget(
                        units.deg(ev.roll_deg),
                        units.deg(ev.pitch_deg),
                        req,
                        self._hmi_seq,
                        walk_steps=ev.walk_steps,
                    )
                )
            elif isinstance(ev, StuckValve):
                i = self._cyl_of[k]
                opening = ev.opening
                if opening is None:
                    opening = float(self.rig.spool_m[i] / self.rig.params.spool_max_m[i])
                self._held[k] = opening
            elif isinstance(ev, SensorFault) and ev.mode == "stuck":
                i = self._cyl_of[k]
                if ev.quantity == "position":
                    self._held[k] = float(self._pos_reading[i])
                else:
                    self._held[k] = float(self._press_reading[i, _QUANTITY_COLUMN[ev.quantity]])
        self._active = {k for k in now_active if not isinstance(events[k], HmiTargetEvent)}
        self._derive_active()
        for k in ended:
            self._held.pop(k, None)
        # state-like faults: recomputed from everything active
        for i in range(N_CYLINDERS):
            self.rig.set_internal_leakage(i, None)
        self.rig.external_force_n[:] = 0.0
        self.rig.valve_leak[:] = 0.0
        ground: list[tuple[float, float, float, float, float]] = []
        if isinstance(self.rig, WalkingRig):
            self.rig.set_friction(0, None)
            self.rig.set_friction(1, None)
        extra: dict[str, list[tuple[float, tuple[float, float, float]]]] = {
            "lower": [],
            "upper": [],
        }
        for k in sorted(self._active):
            ev = events[k]
            if isinstance(ev, Leakage):
                self.rig.set_internal_leakage(self._cyl_of[k], ev.internal_leakage_m3_s_pa)
            elif isinstance(ev, HoldingValveLeak):
                self.rig.valve_leak[self._cyl_of[k]] += ev.leakage_m3_s_pa
            elif isinstance(ev, GroundOffset):
                ground.append(ev.row)
            elif isinstance(ev, FootSlip) and isinstance(self.rig, WalkingRig):
                self.rig.set_friction(0 if ev.frame == "main" else 1, ev.friction_coefficient)
            elif isinstance(ev, LoadStep):
                if ev.cylinder is not None:
                    self.rig.external_force_n[self._cyl_of[k]] -= ev.force_n
                elif ev.layer is not None:
                    extra[ev.layer].append((ev.mass_kg, ev.cog_m))
        for layer, items in extra.items():
            m = sum(mi for mi, _ in items)
            cog = (
                tuple(sum(mi * c[a] for mi, c in items) / m for a in range(3))
                if m > 0
                else (0.0, 0.0, 0.0)
            )
            self.rig.set_platform_load(layer, m, cog)
        if isinstance(self.rig, WalkingRig):
            self.rig.set_ground(ground)
        self.wire.set_faults(
            self._wire_faults[k] for k in sorted(self._active) if k in self._wire_faults
        )

    def _now_active(self, t: float) -> set[int]:
        """The events in force at ``t`` (an HMI target event once: not after it was sent);
        :meth:`_switch_events` acts when they differ from :attr:`_active`."""
        return {
            k
            for k, ev in enumerate(self.scenario.events)
            if k not in self._hmi_issued and _is_active(ev, t)
        }

    def _derive_active(self) -> None:
        """What the active events mean for every scan until the set changes."""
        events = self.scenario.events
        order = sorted(self._active)
        self._stalled = any(isinstance(events[k], PlcStall) for k in order)
        self._sensor_faults = [k for k in order if isinstance(events[k], SensorFault)]
        self._stuck = [(self._cyl_of[k], k) for k in order if isinstance(events[k], StuckValve)]
        self._estop = any(isinstance(events[k], EStop) for k in order)
        self._dead = any(isinstance(events[k], PlcSilent) for k in order)
        self._ignore = any(isinstance(events[k], IgnoreCommands) for k in order)
        self._active_version += 1

    def _sample(self, k: int) -> None:
        rig = self.rig
        if self._deferred_readings:
            self._pos_sensor.skip()  # the noise only if a frame takes the reading
            self._press_sensor.skip()
            self._plc.defer_readings(self._take_positions, self._take_pressures)
        else:
            faults = self._sensor_faults
            new_pos = k % self._pos_every == 0
            new_press = k % self._press_every == 0
            if new_pos:
                self._pos_reading = self._pos_sensor.read(rig.x_view)
            if new_press:
                p = rig.pressure_view
                self._press_reading = self._press_sensor.read(p).reshape(2, N_CYLINDERS).T
            if faults or new_pos or new_press or self._sensor_fault:
                self._hand_over(faults)
        bits = limit_switch_bits(rig.x_view, self._limit_m, self._extended_at)
        if bits != self._limits:
            self._limits = bits
            self._retracted = (bits[0] >> self._bit) & 1 == 1
            self._extended = (bits[1] >> self._bit) & 1 == 1
            self._plc.set_limit_switches(self._retracted, self._extended)

    def _take_positions(self) -> None:
        """This scan's positions, deferred by :meth:`_sample` until a frame needs them."""
        sensor = self._pos_sensor
        self._pos_reading = sensor.quantize(self.rig.x_view, sensor.last_noise())
        self._plc.set_positions_m(self._pos_reading)

    def _take_pressures(self) -> None:
        """This scan's pressures, deferred by :meth:`_sample` until a frame needs them."""
        sensor = self._press_sensor
        press = sensor.quantize(self.rig.pressure_view, sensor.last_noise())
        self._press_reading = press.reshape(2, N_CYLINDERS).T
        self._plc.set_pressures_pa(self._press_reading)

    def _hand_over(self, faults: list[int]) -> None:
        """Readings with the sensor faults applied, to the link."""
        if not faults:  # the link keeps its own copy
            self._sensor_fault = False
            self._plc.set_positions_m(self._pos_reading)
            self._plc.set_pressures_pa(self._press_reading)
            return
        events = self.scenario.events
        pos = self._pos_reading.copy()
        press = self._press_reading.copy()
        sensor_fault = False
        for k_ev in faults:
            ev = events[k_ev]
            assert isinstance(ev, SensorFault)
            i = self._cyl_of[k_ev]
            arr = pos if ev.quantity == "position" else press
            scale = units.MM if ev.quantity == "position" else units.MPA
            idx = i if ev.quantity == "position" else (i, _QUANTITY_COLUMN[ev.quantity])
            if ev.mode == "stuck":
                arr[idx] = self._held[k_ev]
            elif ev.mode == "noisy":
                arr[idx] += self._fault_rng.standard_normal() * ev.noise * scale
            elif ev.mode == "jump":
                arr[idx] += ev.offset * scale
            else:
                arr[idx] = math.nan
                sensor_fault = True
        self._sensor_fault = sensor_fault
        self._plc.set_positions_m(pos)
        self._plc.set_pressures_pa(press)

    def _logic(self, t: float, frames: int) -> None:
        estop, dead, ignore = self._estop, self._dead, self._ignore
        plc = self._plc
        # Stale commands: spools centred at once; the fault is latched only when the
        # loss lasts longer than safety.command_timeout_ms (fresh before: drive again).
        timeout = True if dead else plc.command_timeout(t)
        lost = dead or plc.ipc_timeout(t)
        # the control word and the valve commands change only when frames arrive
        if dead:
            self._ctl = None
        elif frames or timeout or self._fresh_scan:
            self._ctl = plc.control(t)
            cmd = plc.valve_commands(t).value
            self._cmd = np.where(np.isnan(cmd), 0.0, cmd)
            self._cmd_version += 1
        self._fresh_scan = timeout
        ctl = self._ctl
        # The rest is a function of these inputs and of the latched fault and the
        # engaged flag it updates: with all of them as at the last scan it would give
        # the same outputs and state again (most scans: no frame, no timeout edge).
        inputs = (
            ctl,
            timeout,
            lost,
            estop,
            ignore,
            self._cmd_version,
            self._limits,
            self._active_version,
            self._sensor_fault,
            self._latched,
            self._engaged,
        )
        if inputs == self._logic_inputs:
            return
        self._logic_inputs = inputs
        if estop:
            self._latched = Fault.ESTOP
        elif self._engaged and lost:
            self._latched = Fault.IPC_TIMEOUT
        if (
            self._latched is not Fault.NONE
            and ctl is not None
            and ctl.fault_reset
            and not estop
            and not timeout
        ):
            self._latched = Fault.NONE
        mode = ctl.mode if ctl is not None and self._latched is Fault.NONE else Mode.IDLE
        if mode is Mode.WALK and not self.walk_available:
            mode = Mode.IDLE  # WALK refused: not echoed, the drives stay off
        drives = (
            ctl is not None
            and ctl.enable
            and not ctl.stop
            and mode in MOTION_MODES
            and not timeout
            and not estop
            and self._latched is Fault.NONE
        )
        # the commands applied change only with fresh commands, the drives, the limit
        # switches or the events: the same array until one of them does
        move = drives and not ignore
        u_key = (move, self._cmd_version, self._limits, self._active_version)
        if u_key == self._u_key:
            u = self._u
        else:
            u = np.zeros(N_CYLINDERS)
            if move:
                u = self._cmd.copy()
                u[self._extended & (u > 0)] = 0.0
                u[self._retracted & (u < 0)] = 0.0
            for i, k in self._stuck:
                u[i] = self._held[k]
            self._u_key, self._u = u_key, u
        self._drives = drives
        if not timeout:
            self._engaged = drives
        self._applied = u
        self.rig.command[:] = u
        if self.rig.load_holding_valves:
            self.rig.ports_open[:] = 1.0 if drives else 0.0
        if ctl is not None and ctl.ack_status is not TargetAck.NONE and ctl.ack_seq:
            self._hmi_ack = (ctl.ack_seq, ctl.ack_status)
        fault = self._latched
        if fault is Fault.NONE and self._sensor_fault:
            fault = Fault.SENSOR_FAULT
        key = (mode, estop, drives, timeout, int(fault))
        if key != self._status_key:
            self._status_key = key
            self._status = PlcStatus(
                mode=mode,
                estop=estop,
                pump_running=not estop,
                drives_enabled=drives,
                command_timeout=timeout,
                fault=fault,
                supply_pressure_pa=self.cfg.hydraulics.supply_pressure_pa,
                walk_available=self.walk_available,
            )
            plc.set_status(self._status)

    # ----------------------------------------------------------------- the part

    #: How long the crane takes to set a new part down on the platform, s
    LOAD_DURATION_S = 5.0

    def bolt_part(self) -> tuple[FloatArray, FloatArray]:
        """The site crew bolts the part to its ring where it is now (the operator's
        fixing confirmation): its pose is frozen, the simulator's truth from now on
        (:func:`hil_sim.placement.pose_from_home`), and it rests on the upper platform
        through its pads until the platform lowers off it (docs/hil.md, "The part").
        Returns the frozen pose ``(R, t)`` from home."""
        return bolt_part(self.cfg, self.rig)

    def load_part(self, duration_s: float = LOAD_DURATION_S) -> None:
        """A crane sets a new part down on the upper platform at its home position, its
        weight ramped on over ``duration_s``; the part bolted before stays in its ring."""
        self.rig.load_part(duration_s)

    # ----------------------------------------------------------------- truth

    def active_faults(self) -> tuple[str, ...]:
        """Kinds of the scenario events in force now (``sensor:upper_1``, ``drop`` ...)."""
        out = []
        for k in sorted(self._active):
            ev = self.scenario.events[k]
            cyl = getattr(ev, "cylinder", None)
            out.append(f"{ev.kind}:{cyl}" if cyl else ev.kind)
        return tuple(out)

    def truth(self) -> Truth:
        rig = self.rig
        roll, pitch = rig.workpiece_attitude_rad()
        return Truth(
            t_s=self.t_s,
            lower=rig.layer("lower"),
            upper=rig.layer("upper"),
            workpiece_roll_rad=roll,
            workpiece_pitch_rad=pitch,
            rod_positions_m=rig.rod_positions_m,
            rod_velocities_m_s=rig.rod_velocities_m_s,
            hydraulic_forces_n=rig.hydraulic_forces_n,
            pressures_pa=rig.pressures_pa,
            spool_m=rig.spool_m,
            applied_command=self.applied_command.copy(),
            status=self.status,
            faults_active=self.active_faults(),
            part_state=rig.part_state,
            part_load_n=rig.part_load_n,
            walk=rig.walk_truth() if isinstance(rig, WalkingRig) else None,
        )

    def status_line(self) -> str:
        """One line: simulated time, realtime factor, PLC state, faults active."""
        s = self.status
        faults = ", ".join(self.active_faults()) or "none"
        rtf = self.realtime_factor
        up = self.rig.layer("upper")
        return (
            f"t={self.t_s:9.3f} s  rtf={rtf:6.2f}x  mode={s.mode.name} "
            f"drives={'on' if s.drives_enabled else 'off'} fault={Fault(s.fault).name}  "
            f"upper twist force={up.twist_force_n / units.KN:+.2f} kN  faults: {faults}"
        )

    def close(self) -> None:
        self._plc.close()


def _is_active(ev: Any, t: float) -> bool:
    if isinstance(ev, HmiTargetEvent):
        return t >= ev.at_s - 1e-12
    return bool(ev.active(t))
