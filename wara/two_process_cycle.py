"""The ring cycle across two processes, as on site: ``wara demo --two-process --rings N``.

The simulator (``wara hil``: the PLC and the walking rig) and the service (``wara
serve``) run as two processes on the wall clock with the project's safety timeouts, on
the demo's private bus (:mod:`wara.demo_two_process`). The demo plays the people: the
operator through the service's control socket, as ``wara ctl`` does (``cycle``,
``confirm_fixed``, ``survey``, ``status``), and the crane, the crew and the surveyor
through the simulator's site socket (:mod:`hil_sim.site`). Per ring, the phases of
``wara cycle`` (docs/placement.md):

1. ``cycle``: ring N, the part before it as its deviation (the first ring: the demo's
   6 mm off, :data:`wara.demo.RING_DEMO_DEVIATION`) or as surveyed (the pose the ring
   before recorded in the acceptance store);
2. ``load``: for every ring after the first the crane sets the next part down (site
   ``load``) once the cycle waits for it; the service sees it in the pressures;
3. ``walk``, ``place``: the service's;
4. ``fixing``: ``cycle.fixing_confirm_after_s`` after the placement ended the crew bolts
   the part (site ``bolt``: its pose frozen, the truth the ring is judged on), and the
   operator confirms the part is fixed (``confirm_fixed``, audited as
   :data:`OPERATOR`). The operator and not the HMI: the confirmation is the operator's
   act on the service's own channel, as docs/placement.md has it; the PLC's HMI has no
   such request on the wire;
5. ``release``: the service's;
6. ``survey``: the total station: the bolted part's truth (site ``part``, checked to be
   the pose it was bolted in) plus ``cycle.survey_noise_mm`` per coordinate
   (:func:`wara.cycle.simulated_survey`), sent as ``survey`` points;
7. ``record``, ``walk_back``: the service's; the record goes to ``DIR/acceptance.sqlite``.

Each ring is then judged as in one process (:func:`wara.cycle.ring_row`): the plan read
back from the ring's acceptance record, the part's bolted truth against it. After the
last ring both processes stop; the loop's figures per phase and its overruns come from
the service's run record and its loop reports (:mod:`wara.loop_phases`). The run passes
when every ring passed and the loop's compute p99 (the worst report after start-up)
is under :data:`~wara.demo_two_process.COMPUTE_P99_GOAL_FRACTION` of the period; its
overruns are counted and each explained, not judged (a stop the PLC or the service
takes for a fault fails its ring).
"""

from __future__ import annotations

import json
import math
import os
import socket
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project, units
from config.schema import ProjectConfig
from ipc_app.model.placement import (
    POSE_DICT_KEYS,
    Pose,
    joint_figures,
    sheet_deviation,
    to_ring_frame,
)
from ipc_app.service.cycle import previous_from_deviation
from plc_bridge.busload import bus_load
from wara.cycle import PHASE_ALLOWANCE_S, conclude, render, ring_row, simulated_survey
from wara.demo import DB_NAME, REPORT_SUBDIR, RING_DEMO_DEVIATION, write_ring_report
from wara.demo_two_process import (
    COMPUTE_P99_GOAL_FRACTION,
    DEFAULT_TRANSPORT,
    RUNS_DIR,
    SITE_SOCKET,
    LoopWatch,
    Progress,
    Service,
    TwoProcessError,
    run_in_netns,
    service_and_simulator,
    setting_lines,
    sim_realtime_factor,
)
from wara.harness import ring_pose
from wara.loop_phases import phase_figures, record_times, render_phases
from wara.place import motion_limit_s, placed_against

#: Who confirms the fixing (the service's audit trail).
OPERATOR = "wara demo (operator)"
#: How often the demo reads the service's status, s.
POLL_S = 0.25
#: The first ring the demo builds (ring 1 is the part before it).
FIRST_RING = 2


def run_two_process_cycle(
    config_path: str | None,
    *,
    rings: int,
    out_dir: Path,
    json_out: bool,
    keep_dir: Path | None = None,
    transport: str = DEFAULT_TRANSPORT,
    pin: bool = True,
) -> int:
    """``wara demo --two-process --rings N``: the namespace, and this command again in
    it (:func:`run_inside`); its exit code. Raises
    :class:`~wara.demo_two_process.NetnsUnavailable` when the namespace cannot be made."""
    inner = ["demo", "--two-process", "--rings", str(rings), "--out", str(out_dir.resolve())]
    if json_out:
        inner.append("--json")
    return run_in_netns(inner, config_path, keep_dir=keep_dir, transport=transport, pin=pin)


class SiteClient:
    """The simulator's site socket (:mod:`hil_sim.site`): one act a call."""

    def __init__(self, path: Path, timeout_s: float = 10.0) -> None:
        self.path, self.timeout_s = path, timeout_s

    def act(self, name: str, **args: Any) -> dict[str, Any]:
        """The act's answer; :class:`TwoProcessError` when it is refused or not answered."""
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(self.timeout_s)
                s.connect(str(self.path))
                s.sendall(json.dumps({"act": name, **args}).encode() + b"\n")
                buf = b""
                while not buf.endswith(b"\n"):
                    chunk = s.recv(65536)
                    if not chunk:
                        break
                    buf += chunk
        except OSError as exc:
            raise TwoProcessError(f"the simulator's site socket {self.path}: {exc}") from None
        try:
            out: dict[str, Any] = json.loads(buf)
        except ValueError:
            raise TwoProcessError(f"site {name}: no answer from the simulator") from None
        if not out.get("ok"):
            raise TwoProcessError(f"site {name} refused: {out.get('error')}")
        return out


class RingFailed(Exception):
    """A ring's cycle did not end (the message: why); ``refused``: its target was
    unreachable, nothing of it moved."""

    def __init__(self, msg: str, refused: bool = False) -> None:
        super().__init__(msg)
        self.refused = refused


class _Driver:
    """One ring after another through the two sockets (module docstring)."""

    def __init__(
        self, cfg: ProjectConfig, svc: Service, site: SiteClient, watch: LoopWatch, say: Progress
    ) -> None:
        self.cfg, self.svc, self.site, self.watch, self.say = cfg, svc, site, watch, say
        self.rng = np.random.default_rng(0)  # the survey's noise, as wara cycle's
        self.phase = "start"

    def status(self) -> dict[str, Any]:
        st = self.svc.status()
        self.watch.see(st)
        return st

    def ring(self, ring: int, previous: Sequence[float], first: bool) -> dict[str, Any]:
        """Ring ``ring``'s cycle to its end; what it gave: ``as_built`` (the truth),
        ``phase_times_s``, ``part_load_kn``. ``previous``: the part before as 5 numbers
        (its deviation) or 6 (its surveyed pose, :data:`POSE_DICT_KEYS`)."""
        cfg = self.cfg
        assert cfg.cycle is not None
        key = "previous_deviation" if len(previous) == 5 else "previous_pose"
        reply = self.svc.call("cycle", ring=ring, **{key: list(previous)})
        if not reply.get("ok"):
            raise RingFailed(
                f"cycle refused: {reply.get('error')}", reply.get("code") == "infeasible"
            )
        limit_s = motion_limit_s(cfg) + PHASE_ALLOWANCE_S
        loaded, surveyed = first, False
        fixing_since: float | None = None
        as_built: Pose | None = None
        bolted: dict[str, Any] = {}
        load_kn: dict[str, float] = {}
        since = time.monotonic()
        while True:
            st = self.status()
            cyc = st.get("cycle") or {}
            if cyc.get("ring") == ring:
                phase = str(cyc.get("phase"))
                if phase != self.phase:
                    self.phase, since = phase, time.monotonic()
                    if not cyc.get("done"):  # said once the ring's record is read
                        self.say(f"ring {ring}: {phase}")
                if cyc.get("error"):
                    reasons = "; ".join(st.get("fault_reasons") or [])
                    why = str(cyc["error"]) + (
                        f" (service {st.get('mode')}: {reasons})" if reasons else ""
                    )
                    raise RingFailed(why, "infeasible" in str(cyc["error"]))
                if cyc.get("done"):
                    times = {k: float(v) for k, v in (cyc.get("phase_times_s") or {}).items()}
                    assert as_built is not None
                    return {"as_built": as_built, "phase_times_s": times, "part_load_kn": load_kn}
                if phase == "load" and not loaded:
                    self.site.act("load")  # the crane: the next part onto the platform
                    loaded = True
                elif phase == "fixing" and as_built is None:
                    if fixing_since is None:
                        fixing_since = time.monotonic()
                    elif time.monotonic() - fixing_since >= cfg.cycle.fixing_confirm_after_s:
                        bolted = self.site.act("bolt")  # the crew's bolts
                        as_built = ring_pose(
                            cfg, ring, np.array(bolted["r"]), np.array(bolted["t"])
                        )
                        load_kn["bolted"] = float(bolted["load_n"]) / units.KN
                        out = self.svc.call("confirm_fixed", user=OPERATOR)
                        if not out.get("ok"):
                            raise RingFailed(str(out.get("error")))  # "confirm-fixed refused: why"
                elif phase == "survey" and not surveyed:
                    part = self.site.act("part")  # the total station sees the bolted part
                    if part["r"] != bolted.get("r") or part["t"] != bolted.get("t"):
                        raise RingFailed(f"ring {ring}: the bolted part moved")
                    load_kn["released"] = float(part["load_n"]) / units.KN
                    assert as_built is not None
                    pts = simulated_survey(cfg, ring, as_built, self.rng)
                    rows = [[p.name, *p.face, *p.measured] for p in pts]
                    out = self.svc.call("survey", points=rows)
                    if not out.get("ok"):
                        raise RingFailed(str(out.get("error")))  # "survey refused: why"
                    surveyed = True
            if time.monotonic() - since > limit_s:
                raise RingFailed(f"ring {ring}'s {self.phase} did not end in {limit_s:g} s")
            time.sleep(POLL_S)


def _record(db: Path, ring: int) -> tuple[dict[str, Any], Pose, dict[str, float | None]]:
    """Ring ``ring``'s record as the service wrote it: the plan with the cycle's figures,
    the surveyed pose, the surveyed Table 4 values."""
    from acceptance.store import AcceptanceStore

    with AcceptanceStore.open(db, create=False) as store:
        plan = store.latest_plan(ring)
        recs = store.current(ring, ring)
    if plan is None or not recs or not plan.final_attitude:
        raise RingFailed(f"ring {ring}: no record in {db}")
    surveyed = Pose.from_dict(plan.final_attitude["as_built_pose"])
    return plan.plan, surveyed, dict(recs[-1].measurement.values)


def _row(
    cfg: ProjectConfig,
    ring: int,
    db: Path,
    got: dict[str, Any],
    previous_truth: Pose,
    walks: dict[str, list[dict[str, Any]]],
) -> tuple[dict[str, Any], Pose]:
    """The ring's row, judged on the truth as in one process; and its surveyed pose."""
    attached, surveyed, values = _record(db, ring)
    plan = attached["plan"]
    design, target = Pose.from_dict(plan["design"]), Pose.from_dict(plan["target"])
    prev = Pose.from_dict(plan["previous_as_built"])  # as the plan took it, in ring's T
    gap_m = joint_figures(cfg, prev, target, design).max_gap_m
    prev_truth = to_ring_frame(cfg, previous_truth, ring - 1, ring)
    as_built: Pose = got["as_built"]
    figures = attached.get("cycle") or {}
    row = ring_row(
        cfg, ring, placed_against(cfg, design, target, gap_m, prev_truth, as_built),
        design=design, as_built=as_built, times=got["phase_times_s"],
        surveyed=values, target_deviation=plan.get("target_deviation"),
        survey_rms_residual_mm=figures.get("survey_rms_residual_mm"), place_settled=None,
        release=figures.get("release"), walks=walks,
        platform_part_load_kn=got["part_load_kn"],
    )  # fmt: skip
    return row, surveyed


def _events(run_dir: Path) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    path = run_dir / "events.jsonl"
    if path.exists():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                break  # a half-written last line
    return out


def _walks(events: Sequence[dict[str, Any]]) -> dict[int, dict[str, list[dict[str, Any]]]]:
    """Each ring's walks' steps (``walk``, ``walk_back``) from the ``walk_done`` events."""
    out: dict[int, dict[str, list[dict[str, Any]]]] = {}
    ring, phase = 0, ""
    for ev in events:
        if ev.get("kind") == "cycle_phase":
            ring, phase = int(ev["ring"]), str(ev["phase"])
        elif ev.get("kind") == "walk_done" and ring:
            out.setdefault(ring, {})[phase] = list(ev.get("steps") or [])
    return out


def run_inside(
    workdir: Path,
    config_path: str,
    *,
    rings: int,
    out_dir: Path,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """The ring cycles on the two processes (this namespace); the JSON-ready result."""
    say = progress or (lambda _s: None)
    cfg = load_project(config_path)
    assert cfg.cycle is not None and cfg.placement is not None
    period = cfg.control.period_s
    out_dir = out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    db = out_dir / DB_NAME
    db.unlink(missing_ok=True)  # this run's rings only
    dev = sheet_deviation(*RING_DEMO_DEVIATION)
    load_start = os.getloadavg()
    wall0 = time.perf_counter()
    out: dict[str, Any] = {"mode": "two-process", "passed": False, "refused": None, "error": None}
    out["rings"] = []
    got: list[dict[str, Any]] = []
    watch = LoopWatch()
    codes: dict[str, int] = {}
    driver: _Driver | None = None
    final: dict[str, Any] = {}
    with service_and_simulator(
        workdir, config_path, say, codes, rig="walking", site=True, db=db
    ) as (svc, sim, placement):
        driver = _Driver(cfg, svc, SiteClient(workdir / SITE_SOCKET), watch, say)
        if not watch.wait_reports(svc, 0, 15.0):
            raise TwoProcessError("the service published no loop statistics in 15 s")
        truths = [previous_from_deviation(cfg, FIRST_RING, dev)]
        previous: list[float] = list(RING_DEMO_DEVIATION)
        try:
            for k in range(rings):
                ring = FIRST_RING + k
                res = driver.ring(ring, previous, first=k == 0)
                got.append(res)
                surveyed = _record(db, ring)[1]
                truths.append(res["as_built"])
                previous = [surveyed.to_dict()[key] for key in POSE_DICT_KEYS]
                say(f"ring {ring}: done")
        except RingFailed as exc:
            out["error"] = f"{driver.phase}: {exc}"
            out["refused"] = str(exc) if exc.refused else None
            say(f"stopping: {out['error']}")
        # one report after the last ring, so that its cycles are in the figures
        watch.wait_reports(svc, len(watch.reports) + 1, 10.0)
        final = svc.status()
    load_end = os.getloadavg()
    runs = sorted((workdir / RUNS_DIR).iterdir())
    events = _events(runs[-1]) if runs else []
    walks = _walks(events)
    for k, res in enumerate(got):
        ring = FIRST_RING + k
        row, _ = _row(cfg, ring, db, res, truths[k], walks.get(ring, {}))
        out["rings"].append(row)
    out["db"] = str(db)
    out["wall_time_s"] = time.perf_counter() - wall0
    conclude(cfg, out, dev, rings)
    out["report"] = None
    if out["rings"]:
        out["report"] = str(write_ring_report(config_path, db, out_dir / REPORT_SUBDIR))
    loop = watch.summary(period)
    reports = [r for r in [watch.baseline, *watch.reports] if r]
    t_s = record_times(runs[-1]) if runs else np.zeros(0)
    base = int((watch.baseline or {}).get("cycles", 0))
    phases = phase_figures(t_s, events, reports, period, base)
    frac = loop["compute_p99_fraction"]
    loop_ok = frac is not None and frac < COMPUTE_P99_GOAL_FRACTION
    lo, up = cfg.layers.lower.cylinders, cfg.layers.upper.cylinders
    active = [c.can_index for c in cfg.cylinders if c.id in (*lo, *up)]
    out.update(
        bus=f"{cfg.can.interface} {cfg.can.channel}:{cfg.can.udp_port} (private netns)",
        placement=placement,
        loop=loop,
        loop_goal={
            "compute_p99_fraction_below": COMPUTE_P99_GOAL_FRACTION,
            "overruns": "counted and explained, not judged",
            "passed": loop_ok,
        },
        loop_phases=phases,
        record_cycles=int(t_s.size),
        final_mode=final.get("mode"),
        fault_reasons=list(final.get("fault_reasons") or []),
        faults=list(final.get("faults") or []),  # the same, as data (interlock, where)
        ride_through=final.get("ride_through"),
        exit_codes=codes,
        bus_load_percent=bus_load(cfg, active).load_percent,
        simulator_realtime_factor=sim_realtime_factor(sim.log_path.read_text(errors="replace")),
        load_average={"start": list(load_start), "end": list(load_end)},
        fixing_confirmed_by=OPERATOR,
    )
    if not loop_ok:
        pct = "n/a" if frac is None else f"{100 * frac:.1f} %"
        out["missed"].append(f"loop: compute p99 {pct} of the period (goal < 20 %)")
    out["passed"] = bool(out["passed"] and loop_ok)
    return out


def render_table(out: dict[str, Any]) -> str:
    """Table 4 per ring (the one-process demo's), then the loop: its goal, its figures per
    phase, each overrun, the load and the verdict with its cause."""
    from wara.demo import render_ring_table

    lp, period_ms = out["loop"], float(out["loop"]["period_ms"])
    frac = lp.get("compute_p99_fraction")
    la = out.get("load_average") or {}

    def avg(v: Sequence[float] | None) -> str:
        return "n/a" if not v else " ".join(f"{x:.2f}" for x in v)

    lines = [render_ring_table(out) if out["rings"] else render(out), ""]
    lines += [
        *setting_lines(out),
        f"loop: {period_ms:.1f} ms period, {lp['measured_s']:.1f} s after start-up "
        f"({lp['measured_cycles']} cycles, {lp['reports']} reports); compute p99 (worst "
        f"report) {_ms(lp['compute_p99_ms'])}"
        + ("" if frac is None else f" = {100 * frac:.1f} % of the period")
        + f" (goal < {100 * out['loop_goal']['compute_p99_fraction_below']:.0f} %: "
        + ("met" if out["loop_goal"]["passed"] else "NOT MET")
        + f"); overruns after start-up {lp['overruns']}, suspends "
        + str((out.get("ride_through") or {}).get("suspends", "n/a")),
        "",
        *render_phases(out["loop_phases"], period_ms),
        "",
        f"load average (1, 5, 15 min): {avg(la.get('start'))} at the start, "
        f"{avg(la.get('end'))} at the end; exit codes: "
        + ", ".join(f"{k} {v}" for k, v in (out.get("exit_codes") or {}).items()),
        "PASSED" if out["passed"] else "FAILED: " + "; ".join(out["missed"]),
    ]
    return "\n".join(lines)


def _ms(v: float | None) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.3f} ms"
