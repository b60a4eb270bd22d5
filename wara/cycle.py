"""The ring cycle: ``wara cycle`` (placement.md section 4; docs/placement.md).

The HIL simulator and the IPC service on one in-process bus (:class:`~wara.harness.Harness`);
per ring, the service's ring cycle (:class:`~ipc_app.service.cycle.RingCycle`, the
request ``wara ctl cycle`` makes), ticked here between the simulated periods, with the
operator's part played here (the fixing confirmed, the survey simulated). Each phase
shows in the service's status (``cycle``), run record (``cycle_phase`` events) and log:

1. ``load``: the part on the platform at the loading point. The first ring's is there
   from the start; before each later ring a crane (played here:
   :meth:`HilSimulator.load_part`) sets a new one down, its weight ramped on over
   :attr:`HilSimulator.LOAD_DURATION_S`, and the service waits for its pressures;
2. ``walk``: ``cycle.walk_steps`` steps to the ring (0: the machine stands at it);
3. ``place``: the target planned from the previous part's as-built pose (the survey of
   the ring before; for the first ring, the given deviation) and moved to
   (:meth:`ServiceCore.request_place_plan`);
4. ``fixing``: the pose held until the operator confirms the part is fixed; here the
   crew bolts it (:meth:`HilSimulator.bolt_part`: its pose frozen, the simulator's
   truth from then on) and confirms after ``cycle.fixing_confirm_after_s`` of machine
   time;
5. ``release``: the upper platform lowers off the bolted part until its pressures are
   the empty platform's, then clear of it (:meth:`ServiceCore.request_release`), and
   stops (valves closed);
6. ``survey``: ``cycle.survey_points`` points on the part's front joint face, the
   frozen truth plus ``cycle.survey_noise_mm`` of noise per coordinate, fitted as
   ``wara survey import`` fits a file (:func:`~ipc_app.planner.survey.fit_survey`);
   when the cycle walks, the machine too (:func:`simulated_machine_survey`: M's truth
   against the axis plus the survey's noise), given to the service as ``wara ctl
   locate`` gives it before the part's survey (the walk back is planned from it) where
   it disagrees with the service's estimate beyond its noise (:data:`LOCATE_GATE_SIGMA`);
7. ``record``: the ring's acceptance record (the surveyed Table 4 items) and, attached,
   the plan, the cycle's figures and the surveyed pose (where the next ring's plan and
   ``wara place plan --from-store`` find it);
8. ``walk_back``: the same steps back, unloaded (the part stays bolted in its ring).

A stop at any point (``wara ctl stop``; a latched fault) leaves the service holding
safely (valves closed) and ends the cycle with the phase it was in.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project, units
from config.hil_scenario import HilScenario
from config.schema import ProjectConfig
from ipc_app.model.placement import Pose, deviation, face_points, to_ring_frame, tunnel_frame
from ipc_app.planner.steering import OnAxis, on_axis_at_start
from ipc_app.planner.survey import SurveyPoint
from ipc_app.service.cycle import previous_from_deviation
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PlannerWorker
from wara.goals import POSITION_TOL_MM, judge, ring_figures, ring_goals
from wara.harness import Harness
from wara.place import motion_limit_s, placed_figures
from wara.ring_records import StoreRecords
from wara.walk import against_axis, walk_scenario

#: The allowance over the project's bound on a motion (``cycle.max_motion_min``) for a
#: phase that waits on the machine or the operator before its motion, s: past it the
#: driver gives up on the phase.
PHASE_ALLOWANCE_S = 5.0


class CycleRefused(Exception):
    """A ring's target is unreachable (the plan's binding limit): nothing of it moved."""


def survey_faces(cfg: ProjectConfig, n: int) -> list[tuple[float, float]]:
    """``n`` points (part-frame y, z) spread over the front joint face: two rows near
    its bottom and top edges, along the part's length, 0.5 m in from its ends."""
    half = cfg.workpiece.length_m / 2.0 - 0.5
    top = cfg.workpiece.height_m - 0.2
    rows = (0.2, top)
    per = [(n + 1) // 2, n // 2]
    out: list[tuple[float, float]] = []
    for z, m in zip(rows, per, strict=True):
        ys = np.linspace(-half, half, m) if m > 1 else np.array([0.0])
        out.extend((float(y), z) for y in ys)
    return out


def simulated_survey(
    cfg: ProjectConfig, ring: int, truth: Pose, rng: np.random.Generator
) -> list[SurveyPoint]:
    """The face points of ``truth`` (ring ``ring``'s T) in the project frame, each
    coordinate with the survey's noise: what a total station would export."""
    assert cfg.cycle is not None
    faces = survey_faces(cfg, cfg.cycle.survey_points)
    local = truth.apply(face_points(cfg, faces))
    world = tunnel_frame(cfg, ring).apply(local)
    world = world + rng.normal(0.0, cfg.cycle.survey_noise_m, world.shape)
    return [
        SurveyPoint(k + 1, f"P{k}", (fy, fz), (float(p[0]), float(p[1]), float(p[2])))
        for k, ((fy, fz), p) in enumerate(zip(faces, world, strict=True), start=1)
    ]


def simulated_machine_survey(cfg: ProjectConfig, truth: OnAxis, rng: np.random.Generator) -> OnAxis:
    """Where the machine stands as a total station surveys it: ``truth`` (M against the
    axis, :func:`machine_truth`) seen through two prisms on M at its front and rear leg
    lines (``+-a_M`` along M's x, the lower layer's ``half_span_x_m``), each coordinate
    with ``cycle.survey_noise_mm`` of noise. Across the axis that is the heading's error
    the difference of the two prisms' lateral errors over the ``2 a_M`` between them, and
    the offset's their mean; along the axis and in height the noise changes neither (to
    first order), and the chainage is the truth's (the walk's, as the service counts it)."""
    assert cfg.cycle is not None
    front, rear = rng.normal(0.0, cfg.cycle.survey_noise_m, 2)
    baseline_m = 2.0 * cfg.layers.lower.a_m
    return OnAxis(
        truth.chainage_m,
        truth.heading_error_rad + (front - rear) / baseline_m,
        truth.lateral_m + (front + rear) / 2,
    )


def machine_truth(
    cfg: ProjectConfig, chainage_m: float, xy: tuple[float, float], heading_rad: float
) -> OnAxis:
    """M's centre ``xy`` and its heading (the simulator's truth, in the walk's base frame)
    against the axis at ``chainage_m`` (:func:`~wara.walk.against_axis`)."""
    return OnAxis(chainage_m, *against_axis(cfg, chainage_m, xy, heading_rad))


#: The surveyor corrects the service's estimate of where the machine stands only where
#: the survey disagrees with it by more than this many of its own standard deviations: a
#: survey within its noise of the estimate tells it nothing it could steer on.
LOCATE_GATE_SIGMA = 3.0


def machine_survey_sigma(cfg: ProjectConfig) -> tuple[float, float]:
    """The standard deviations of :func:`simulated_machine_survey`'s heading (rad) and
    offset (m): two prisms ``2 a_M`` apart, ``cycle.survey_noise_mm`` each."""
    assert cfg.cycle is not None
    sigma = cfg.cycle.survey_noise_m
    return math.sqrt(2.0) * sigma / (2.0 * cfg.layers.lower.a_m), sigma / math.sqrt(2.0)


class _Cycle:
    def __init__(
        self,
        cfg: ProjectConfig,
        h: Harness,
        db_path: Path,
        rng: np.random.Generator,
        say: Callable[[str], None],
        on_cycle: Callable[[Harness, str], None] | None,
    ) -> None:
        self.cfg, self.h, self.db_path, self.rng, self.say = cfg, h, db_path, rng, say
        self.on_cycle = on_cycle
        self.phase = ""
        self.dt = h.period if h.mode == "lockstep" else 0.05

    def advance(self, seconds: float) -> None:
        self.h.advance(seconds)
        if self.on_cycle is not None:
            self.on_cycle(self.h, self.phase)

    def ring(self, ring: int, previous: Pose, previous_truth: Pose) -> dict[str, Any]:
        """One ring's cycle, asked of the service as ``wara ctl cycle`` asks for it
        (:class:`~ipc_app.service.cycle.RingCycle`), ticked here between the simulated
        periods; the operator's part is played here: the fixing confirmed after
        ``cycle.fixing_confirm_after_s``, the survey simulated from the truth.
        ``previous`` / ``previous_truth``: the part before, as surveyed and as built,
        in its own ring's T."""
        cfg, core = self.cfg, self.h.core
        assert cfg.cycle is not None
        records = StoreRecords(
            self.db_path, operator="wara cycle",
            remarks="simulated survey (HIL truth plus survey noise)",
        )  # fmt: skip
        sim = self.h.sim
        res = core.request_cycle(ring, previous, records, drive=False, say=self.say)
        if not res.get("ok"):
            raise RuntimeError(f"cycle refused: {res.get('error')}")
        cyc = core.ring_cycle
        assert cyc is not None
        as_built: Pose | None = None
        fixing_since: float | None = None
        settled: Any = None
        waited = 0.0
        phase_limit_s = motion_limit_s(cfg) + PHASE_ALLOWANCE_S
        part_load_kn: dict[str, float] = {}
        located: dict[str, Any] | None = None
        while cyc.active:
            if cyc.phase != self.phase:
                self.phase, waited = cyc.phase, 0.0
            cyc.tick()
            if not cyc.active:
                break
            if cyc.phase == "load" and sim.rig.part_state == "bolted":
                sim.load_part()  # the crane sets the next part down at the loading point
            elif cyc.phase == "fixing":
                if fixing_since is None:  # the placement just ended: how it settled
                    placer = core.placer
                    settled = placer.settled if placer is not None else None
                    fixing_since = sim.t_s
                if sim.t_s - fixing_since >= cfg.cycle.fixing_confirm_after_s - 1e-9:
                    sim.bolt_part()  # the crew's bolts: from now the ring holds the part
                    as_built = self.h.part_pose(ring)
                    part_load_kn["bolted"] = sim.rig.part_load_n / units.KN
                    core.confirm_fixed("wara cycle (automatic confirmation)")
                    continue
            elif cyc.phase == "survey":
                # the part where the bolts hold it, the platform lowered away from it
                truth = self.h.part_pose(ring)
                if truth != as_built:
                    raise RuntimeError(f"ring {ring}: the bolted part moved: {truth} != {as_built}")
                part_load_kn["released"] = sim.rig.part_load_n / units.KN
                pts = simulated_survey(cfg, ring, truth, self.rng)
                if cyc.walk_steps > 0:  # before the part's: the walk back follows it
                    located = self._locate(ring)
                out = core.submit_survey(points=pts)
                if not out.get("ok"):
                    raise RuntimeError(f"ring {ring}: {out.get('error')}")
                continue
            if waited > phase_limit_s:
                raise RuntimeError(f"ring {ring}'s {cyc.phase} did not end in {phase_limit_s:g} s")
            self.advance(self.dt)
            waited += self.dt
        self.phase = cyc.stopped_in_phase or cyc.phase
        if cyc.error is not None:
            if cyc.refused:
                raise CycleRefused(cyc.error)
            raise RuntimeError(cyc.error)
        assert cyc.plan is not None and cyc.surveyed is not None and as_built is not None
        plan, fit = cyc.plan, cyc.fit
        prev_t = to_ring_frame(cfg, previous_truth, ring - 1, ring)
        row = ring_row(
            cfg, ring, placed_figures(cfg, plan, prev_t, as_built),
            design=plan.design, as_built=as_built,
            surveyed=dict(cyc.table4),  # what the service recorded from the survey
            target_deviation=plan.to_dict()["target_deviation"],
            survey_rms_residual_mm=units.to_mm(fit.rms_residual_m) if fit else None,
            times=dict(cyc.phase_times_s), place_settled=settled,
            release=cyc.release_figures, walks=cyc.walk_figures,
            platform_part_load_kn=part_load_kn, machine_survey=located,
        )  # fmt: skip
        self._surveyed, self._truth = cyc.surveyed, as_built
        return row

    def _locate(self, ring: int) -> dict[str, Any] | None:
        """The machine surveyed (:func:`simulated_machine_survey`) at the chainage the
        service counts, given to it as ``wara ctl locate`` gives it; the reply with the
        truth it was surveyed from (None: the rig does not walk)."""
        cfg, core = self.cfg, self.h.core
        walk = self.h.sim.truth().walk
        if walk is None:
            return None
        here = core.on_axis or on_axis_at_start(cfg)
        xy = (float(walk.plan_xy_m[0, 0]), float(walk.plan_xy_m[0, 1]))
        m_truth = machine_truth(cfg, here.chainage_m, xy, float(walk.heading_rad[0]))
        surveyed = simulated_machine_survey(cfg, m_truth, self.rng)
        truth = m_truth.to_dict()
        sigma_heading, sigma_lateral = machine_survey_sigma(cfg)
        if (
            abs(surveyed.heading_error_rad - here.heading_error_rad)
            <= LOCATE_GATE_SIGMA * sigma_heading
            and abs(surveyed.lateral_m - here.lateral_m) <= LOCATE_GATE_SIGMA * sigma_lateral
        ):  # within the survey's noise of the estimate: kept
            return {"surveyed": surveyed.to_dict(), "kept": here.to_dict(), "truth": truth}
        out = core.locate(surveyed)
        if not out.get("ok"):
            raise RuntimeError(f"ring {ring}: {out.get('error')}")
        return {k: out[k] for k in ("on_axis", "replaced")} | {"truth": truth}


def ring_row(
    cfg: ProjectConfig,
    ring: int,
    placed: dict[str, Any],
    *,
    design: Pose,
    as_built: Pose,
    times: dict[str, float],
    **figures: Any,
) -> dict[str, Any]:
    """One ring's row of the cycle's result, judged: the placed part's figures on the
    truth (:func:`~wara.place.placed_figures`), its deviation from ``design``, the machine
    time (``times`` less the fixing hold) and ``figures`` (``surveyed``,
    ``target_deviation``, ``survey_rms_residual_mm``, ``place_settled``, ``release``,
    ``walks``, ``platform_part_load_kn``; in one process ``machine_survey``: the
    service's ``locate`` reply, ``on_axis`` and ``replaced``, with the ``truth``), as the
    one-process and the two-process forms give them."""
    truth_dev = deviation(as_built, design)
    row: dict[str, Any] = {
        "ring": ring,
        **placed,
        "as_built_deviation": {"y_mm": units.to_mm(truth_dev.y), "z_mm": units.to_mm(truth_dev.z)},
        "cycle_time_s": sum(v for k, v in times.items() if k != "fixing"),
        "fixing_hold_s": times.get("fixing"),
        "phase_times_s": times,
        **figures,
    }
    row.update(judge(ring_goals(cfg), ring_figures(row)).to_dict())
    return row


def run_cycle(
    config_path: str | None,
    rings: int,
    *,
    first_ring: int = 2,
    previous_deviation: Pose | None = None,
    db_path: Path,
    mode: str = "lockstep",
    seed: int = 0,
    record: RunRecorder | None = None,
    progress: Callable[[str], None] | None = None,
    on_cycle: Callable[[Harness, str], None] | None = None,
    cfg: ProjectConfig | None = None,
    sim_cfg: ProjectConfig | None = None,
    planner: PlannerWorker | None = None,
    scenario: HilScenario | None = None,
) -> dict[str, Any]:
    """``rings`` ring cycles from ring ``first_ring``; the part before it (ring
    ``first_ring - 1``) lies ``previous_deviation`` from its design. The JSON-ready
    result: ``passed``, ``refused``, ``rings`` (one object per ring), ``steering``.
    ``cfg``: the project as loaded from ``config_path`` (tests: a changed one).
    ``sim_cfg``, ``planner``, ``scenario``: the simulated machine when it differs from the
    project, a running planner worker to share, the HIL scenario (its events, sensors;
    a campaign's run; :class:`~wara.harness.Harness`)."""
    if cfg is None:
        cfg = load_project(config_path)
    if cfg.cycle is None:
        raise ValueError("the project has no cycle section")
    say = progress or (lambda _s: None)
    wall0 = time.perf_counter()
    if first_ring < 2:
        raise ValueError(
            f"the first ring of a cycle is 2 or later (a part before it), got {first_ring}"
        )
    dev = previous_deviation or Pose()
    previous = previous_from_deviation(cfg, first_ring, dev)
    out: dict[str, Any] = {"passed": False, "refused": None, "error": None, "rings": []}
    # the walking rig (feet on the invert) only when the cycle walks
    if cfg.cycle.walk_steps > 0:
        scenario = walk_scenario(scenario)
    h = Harness(
        cfg, config_path, mode=mode, record=record, seed=seed, scenario=scenario,
        sim_cfg=sim_cfg, planner=planner, trace=False,
    )  # fmt: skip
    rng = np.random.default_rng(seed)
    cyc: _Cycle | None = None
    try:
        h.start()
        up = h.wait_for(Mode.IDLE, 20.0)
        if not (up and (cfg.cycle.walk_steps == 0 or h.wait_walk_ready())):
            raise RuntimeError(f"service did not come up: {h.fault_note()}")
        cyc = _Cycle(cfg, h, db_path, rng, say, on_cycle)
        truth_prev = previous
        for ring in range(first_ring, first_ring + rings):
            row = cyc.ring(ring, previous, truth_prev)
            out["rings"].append(row)
            previous, truth_prev = cyc._surveyed, cyc._truth
    except CycleRefused as exc:
        out["refused"] = str(exc)
        out["error"] = str(exc)
    except RuntimeError as exc:
        out["error"] = f"{cyc.phase if cyc else 'start'}: {exc}"
    finally:
        out.update(h.run_figures())  # final_mode, fault_reasons, loop, ride_through, ...
        out["valves_enabled"] = h.core.modes.valves_enabled
        out["stopped_in_phase"] = cyc.phase if (cyc and out["error"]) else None
        h.close()
    out["db"] = str(db_path)
    out["wall_time_s"] = time.perf_counter() - wall0
    return conclude(cfg, out, dev, rings)


def conclude(cfg: ProjectConfig, out: dict[str, Any], dev: Pose, rings: int) -> dict[str, Any]:
    """``out`` (``rings``: the rows built, ``error``) with the steering back from
    ``dev`` (the first ring's previous part off its design), ``passed`` (every one of the
    ``rings`` built and passed, no error) and ``missed`` (why not)."""
    rows = out["rings"]
    last = [units.to_mm(dev.y), units.to_mm(dev.z)]
    corrections: list[float] = []
    for r in rows:
        now = [r["as_built_deviation"]["y_mm"], r["as_built_deviation"]["z_mm"]]
        corrections.append(max(abs(a - b) for a, b in zip(now, last, strict=True)))
        last = now
    assert cfg.placement is not None
    out["steering"] = {
        "start_deviation_mm": [units.to_mm(dev.y), units.to_mm(dev.z)],
        "max_correction_per_ring_mm": cfg.placement.max_correction_per_ring_mm,
        "correction_per_ring_mm": corrections,
        "last_as_built_deviation_mm": last,
        "returned_within_1_mm": bool(rows) and max(abs(v) for v in last) <= POSITION_TOL_MM,
    }
    out["passed"] = bool(
        out["error"] is None and len(rows) == rings and all(r["passed"] for r in rows)
    )
    out["missed"] = [out["error"]] if out["error"] else []
    out["missed"] += [f"ring {r['ring']}: {n}" for r in rows for n in r["missed"]]
    if not (out["passed"] or out["missed"]):
        out["missed"] = [f"{len(rows)} of {rings} rings built"]
    return out


def render(out: dict[str, Any]) -> str:
    """Table 4 on the simulator's truth per ring, the cycle time and the verdict."""
    head = (
        "| ring | vertical mm | horizontal mm | gap mm | centreline x / y mm | pitch / tilt / "
        "rotation deg | cycle s | passed |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for r in out["rings"]:
        lines.append(
            f"| {r['ring']} | {r['vertical_misalignment_mm']:+.3f} | "
            f"{r['horizontal_misalignment_mm']:+.3f} | {r['max_gap_mm']:.3f} | "
            f"{r['centreline_deviation_x_mm']:+.3f} / {r['centreline_deviation_y_mm']:+.3f} | "
            f"{r['pitch_angle_deg']:+.4f} / {r['tilt_angle_deg']:+.4f} / "
            f"{r['rotation_angle_deg']:+.4f} | "
            f"{r['cycle_time_s']:.1f} | {'yes' if r['passed'] else 'NO'} |"
        )
    lines.append(
        f"acceptance records: {out['db']}; "
        f"{'PASSED' if out['passed'] else 'FAILED'} ({out['wall_time_s']:.1f} s wall)"
    )
    return "\n".join(lines)
