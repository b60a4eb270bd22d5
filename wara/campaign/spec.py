"""The campaign spec (``wara campaign run SPEC``): YAML validated like a project.

A spec names the project, what each run does, what is dispersed and how, the
requirement the campaign must show, and the seed. Everything drawn for run ``i`` comes
from its own generator, ``SeedSequence(seed, spawn_key=(i,))``: a run's parameters do
not depend on how many runs there are, on the number of workers, or on the order in
which runs finish.

Dispersions by YAML key path (``hydraulics.bulk_modulus_mpa``,
``layers.upper.bodies[0].mass_kg``, ``cylinders[*].plant.coulomb_friction_n`` with
``[*]`` drawn for each element on its own; a cylinder without its own ``plant`` starts
from the run's drawn ``hydraulics.cylinder_defaults``) change the simulated machine only: the
service runs on the project as written, as on site, where the real machine differs from
its YAML. ``simulator`` key paths go into the HIL scenario (sensor noise, plant
settings); ``events`` are scenario events at random times.
"""

from __future__ import annotations

import copy
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Discriminator, Field, Tag, model_validator

from config import ConfigError, load_project
from config.hil_scenario import EVENT_KINDS, HilScenario
from config.loader import default_project_path, read_yaml, validate_data
from config.schema import Finite, ProjectConfig, Strict
from ipc_app.service.cycle import RECORD_KEYS
from wara.campaign.kinds import check_nominal
from wara.goals import ATTITUDE_GOALS, HIGHER_IS_BETTER, limits, ring_goals, walk_step_goals

#: Per-run figures a requirement may limit, by run kind: the worst over the run's
#: targets, steps or rings. Lower is better, except those of :data:`HIGHER_IS_BETTER`.
FIGURES_OF: dict[str, tuple[str, ...]] = {
    "attitude_targets": (
        "attitude_error_deg",
        "max_twist_mm",
        "sync_error_mm",
        "max_sync_error_mm",
    ),
    "walk": (
        "distance_error_mm",
        "max_leg_sync_error_mm",
        "max_travel_sync_error_mm",
        "max_transfer_attitude_change_deg",
        "max_leg_force_ratio",
        "min_stability_margin_m",
        "max_step_duration_s",
    ),
    "ring_cycle": (
        *RECORD_KEYS,  # Table 4, absolute values (the acceptance record's keys)
        "min_gap_mm",  # the joint's smallest gap (>= 0: no overlap)
        "position_error_mm",
        "angle_error_deg",
        "gap_error_mm",
        "cycle_time_s",
    ),
}
#: The attitude targets' figures (the demo's examples).
FIGURES = FIGURES_OF["attitude_targets"]

#: The demo's tolerances: the default limits of attitude targets.
DEMO_LIMITS: dict[str, float] = limits(ATTITUDE_GOALS)


def figure_margin(name: str, value: float, limit: float) -> float:
    """How far ``value`` is inside ``limit``, relative: 0 at the limit, below 0 beyond it
    (NaN for a NaN value). A limit of 0 (no overlap: ``min_gap_mm``) has no relative
    margin: the value itself is it (in the figure's unit)."""
    if limit == 0.0:
        return value if name in HIGHER_IS_BETTER else -value
    return value / limit - 1.0 if name in HIGHER_IS_BETTER else 1.0 - value / limit


#: A bounded draw is drawn again while outside its min/max, at most this often ...
MAX_REDRAWS = 1000
#: ... so min/max must keep at least this share of the raw draws (checked at load).
MIN_KEPT_SHARE = 0.02


class Distribution(Strict):
    """One random value. ``normal`` (``mean``, ``std``), ``uniform`` (``low``,
    ``high``), ``triangular`` (``low``, ``mode``, ``high``), ``lognormal`` (``mean``
    and ``std`` of the log), ``choice`` (``values``). ``min``/``max`` bound a draw
    (redrawn until inside, at most MAX_REDRAWS times; bounds that keep less than
    MIN_KEPT_SHARE of the draws are refused at load). ``factor: true``: the draw multiplies
    the project's nominal value instead of replacing it."""

    dist: Literal["normal", "uniform", "triangular", "lognormal", "choice"]
    mean: Finite | None = None
    std: Annotated[Finite, Field(ge=0)] | None = None
    low: Finite | None = None
    high: Finite | None = None
    mode: Finite | None = None
    values: tuple[Finite, ...] = ()
    min: Finite | None = None
    max: Finite | None = None
    factor: bool = False

    @model_validator(mode="after")
    def _params(self) -> Distribution:
        need = {
            "normal": ("mean", "std"),
            "lognormal": ("mean", "std"),
            "uniform": ("low", "high"),
            "triangular": ("low", "mode", "high"),
            "choice": (),
        }[self.dist]
        missing = [k for k in need if getattr(self, k) is None]
        if missing:
            raise ValueError(f"{self.dist} needs {', '.join(missing)}")
        given = {
            k
            for k in ("mean", "std", "low", "high", "mode")
            if getattr(self, k) is not None and k not in need
        }
        if given:
            raise ValueError(f"{self.dist} takes no {', '.join(sorted(given))}")
        if self.dist == "choice" and not self.values:
            raise ValueError("choice needs values (a non-empty list)")
        if self.dist != "choice" and self.values:
            raise ValueError(f"{self.dist} takes no values")
        if self.low is not None and self.high is not None and not self.low < self.high:
            raise ValueError(f"low ({self.low}) must be below high ({self.high})")
        if self.mode is not None and not (self.low or 0) <= self.mode <= (self.high or 0):
            raise ValueError("mode must lie between low and high")
        if self.min is not None and self.max is not None and not self.min < self.max:
            raise ValueError(f"min ({self.min}) must be below max ({self.max})")
        kept = self.kept_share()
        if kept < MIN_KEPT_SHARE:
            raise ValueError(
                f"min/max keep {kept:.2%} of the {self.dist} draws ({self._shape()}); at "
                f"least {MIN_KEPT_SHARE:.0%} are needed (a draw outside is drawn again, at "
                f"most {MAX_REDRAWS} times): widen min/max or move the distribution"
            )
        return self

    def _shape(self) -> str:
        keys = {"normal": "mean std", "lognormal": "mean std", "uniform": "low high",
                "triangular": "low mode high", "choice": "values"}[self.dist]  # fmt: skip
        return ", ".join(f"{k} {getattr(self, k)}" for k in keys.split())

    def kept_share(self) -> float:
        """The share of raw draws inside min/max (1.0 without bounds)."""
        lo = -math.inf if self.min is None else self.min
        hi = math.inf if self.max is None else self.max
        if self.dist == "choice":
            vals: list[float] = list(self.values or [])
            return sum(lo <= v <= hi for v in vals) / max(1, len(vals))
        from scipy import stats

        frozen = {
            "normal": lambda: stats.norm(self.mean, self.std),
            "lognormal": lambda: stats.lognorm(s=self.std, scale=math.exp(self.mean or 0.0)),
            "uniform": lambda: stats.uniform(self.low, (self.high or 0) - (self.low or 0)),
            "triangular": lambda: stats.triang(
                ((self.mode or 0) - (self.low or 0)) / ((self.high or 0) - (self.low or 0)),
                loc=self.low,
                scale=(self.high or 0) - (self.low or 0),
            ),
        }[self.dist]()
        return float(frozen.cdf(hi) - frozen.cdf(lo))

    def draw(self, rng: np.random.Generator) -> float:
        for _ in range(MAX_REDRAWS):
            v = self._draw_once(rng)
            if (self.min is None or v >= self.min) and (self.max is None or v <= self.max):
                return v
        raise ConfigError(  # (1 - MIN_KEPT_SHARE) ** MAX_REDRAWS: about 2e-9
            f"a {self.dist} draw ({self._shape()}) fell outside min {self.min} / max "
            f"{self.max} {MAX_REDRAWS} times"
        )

    def _draw_once(self, rng: np.random.Generator) -> float:
        # the validator made sure the parameters of ``dist`` are set
        mean, std = self.mean or 0.0, self.std or 0.0
        low, high, mode = self.low or 0.0, self.high or 0.0, self.mode or 0.0
        if self.dist == "normal":
            return float(rng.normal(mean, std))
        if self.dist == "lognormal":
            return float(rng.lognormal(mean, std))
        if self.dist == "uniform":
            return float(rng.uniform(low, high))
        if self.dist == "triangular":
            return float(rng.triangular(low, mode, high))
        return float(self.values[int(rng.integers(len(self.values)))])


def _check_ranges(run: Strict, names: tuple[str, ...], bound: float, unit: str) -> None:
    """Each ``[low, high]`` of ``names`` in order and within +-``bound``."""
    for name in names:
        lo, hi = getattr(run, name)
        if not lo <= hi:
            raise ValueError(f"{name}: [{lo}, {hi}] must be [low, high]")
        if max(abs(lo), abs(hi)) > bound:
            raise ValueError(f"{name}: within +-{bound:g} {unit}")


class AttitudeTargets(Strict):
    """Each run: ``targets`` attitude adjustments one after another from the level
    start at mid-stroke, each drawn uniformly in the roll/pitch box, each held and
    judged as a demo example."""

    kind: Literal["attitude_targets"] = "attitude_targets"
    targets: Annotated[int, Field(ge=1, le=20)] = 1
    roll_deg: tuple[Finite, Finite] = (-5.0, 5.0)
    pitch_deg: tuple[Finite, Finite] = (-2.0, 2.0)

    @model_validator(mode="after")
    def _box(self) -> AttitudeTargets:
        _check_ranges(self, ("roll_deg", "pitch_deg"), 45.0, "deg")
        return self


class WalkRun(Strict):
    """Each run: ``wara walk --steps N`` in lockstep (the walking rig, the service's
    step sequencer), ``direction``, and with ``and_back`` the same steps back; judged
    per step as ``wara walk`` judges it (docs/walking.md)."""

    kind: Literal["walk"]
    steps: Annotated[int, Field(ge=1, le=3)] = 1
    direction: Literal["forward", "back"] = "forward"
    and_back: bool = False


class RingCycleRun(Strict):
    """Each run: ``wara cycle --rings N`` in lockstep from ring 2 (the project's
    ``cycle`` section: walk, place, fixing, release, survey, record, walk back), the
    part before it off its design by ``previous_y_mm`` / ``previous_z_mm`` (each drawn
    uniformly in its ``[low, high]``); judged per ring on the simulator's truth as
    ``wara cycle`` judges it (docs/placement.md)."""

    kind: Literal["ring_cycle"]
    rings: Annotated[int, Field(ge=1, le=5)] = 1
    previous_y_mm: tuple[Finite, Finite] = (0.0, 0.0)
    previous_z_mm: tuple[Finite, Finite] = (0.0, 0.0)

    @model_validator(mode="after")
    def _box(self) -> RingCycleRun:
        _check_ranges(self, ("previous_y_mm", "previous_z_mm"), 50.0, "mm")
        return self


def _run_kind(v: Any) -> str:
    """The ``run`` section's kind (left out: attitude targets)."""
    kind = v.get("kind", "attitude_targets") if isinstance(v, dict) else getattr(v, "kind", None)
    return str(kind)


RunSpec = Annotated[
    Annotated[AttitudeTargets, Tag("attitude_targets")]
    | Annotated[WalkRun, Tag("walk")]
    | Annotated[RingCycleRun, Tag("ring_cycle")],
    Discriminator(
        _run_kind,
        custom_error_type="run_kind",
        custom_error_message="run.kind must be attitude_targets, walk or ring_cycle",
    ),
]


class RandomEvent(Strict):
    """A HIL scenario event (``event``: as in a scenario's ``events``, without its
    times) that happens in a run with ``probability``, starting at ``start_s`` and
    lasting ``duration_s`` (left out: to the end of the run); ``fields`` draws other
    keys of the event (``rate``, ``delay_ms``, ...)."""

    event: dict[str, Any]
    probability: Annotated[Finite, Field(ge=0, le=1)] = 1.0
    start_s: Distribution
    duration_s: Distribution | None = None
    fields: dict[str, Distribution] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _kind(self) -> RandomEvent:
        kind = self.event.get("kind")
        if kind not in EVENT_KINDS:
            raise ValueError(f"event.kind must be one of {', '.join(EVENT_KINDS)}; got {kind!r}")
        if kind == "hmi_target":
            raise ValueError("hmi_target is not a dispersion (targets come from run)")
        for key in ("start_s", "end_s", "at_s"):
            if key in self.event:
                raise ValueError(f"event.{key}: the times are drawn (start_s, duration_s)")
        return self


class Requirement(Strict):
    """What the campaign must show: with ``confidence``, a run meets every ``limits``
    (figure -> limit) and ends holding its targets with no latched fault, with
    probability at least ``probability``. ``runs`` null: the zero-failure run count
    (order statistics). ``metric``: the figure whose ``probability`` percentile the
    report and ``wara campaign tune`` give; ``margin`` is the smallest relative margin
    of a run over its limits (1 - value / limit; below 0 when a limit is broken, -1
    when the run did not finish)."""

    #: figure -> limit; null: the run kind's goals (:func:`default_limits`)
    limits: dict[str, Annotated[Finite, Field(gt=0)]] | None = None
    metric: str = "margin"
    probability: Annotated[Finite, Field(gt=0, lt=1)] = 0.99
    confidence: Annotated[Finite, Field(gt=0, lt=1)] = 0.95
    runs: Annotated[int, Field(ge=1, le=1_000_000)] | None = None

    def check_names(self, kind: str) -> None:
        """The figures named are ``kind``'s (ValueError otherwise)."""
        figures = FIGURES_OF[kind]
        bad = [k for k in self.limits or () if k not in figures]
        if bad:
            raise ValueError(
                f"limits: unknown figure {bad[0]!r} of a {kind} run; one of {', '.join(figures)}"
            )
        if self.limits is not None and not self.limits:
            raise ValueError("limits: name at least one figure")
        if self.metric != "margin" and self.metric not in figures:
            raise ValueError(f"metric must be margin or one of {', '.join(figures)}")

    @property
    def run_count(self) -> int:
        return (
            self.runs
            if self.runs is not None
            else zero_failure_runs(self.probability, self.confidence)
        )


class Tune(Strict):
    """``wara campaign tune``: Optuna over these project key paths (each a
    ``[low, high]`` range; ``log: true`` samples on a log scale), ``trials`` trials,
    each a campaign of ``runs`` runs (default: the requirement's)."""

    parameters: dict[str, tuple[Finite, Finite]] = Field(
        default_factory=lambda: {
            "control.ladrc.wc_rad_s": (3.0, 12.0),
            "control.ladrc.wo_rad_s": (6.0, 30.0),
        }
    )
    log: bool = True
    trials: Annotated[int, Field(ge=1, le=10_000)] = 20
    runs: Annotated[int, Field(ge=1, le=100_000)] | None = None


class CampaignSpec(Strict):
    name: str = "campaign"
    #: nominal: dispersions within the specification, judged on the run's goals; fault:
    #: the faults, judged on the reaction (:mod:`wara.campaign.kinds`)
    kind: Literal["nominal", "fault"]
    #: the project YAML, relative to the spec file (null: the shipped project)
    project: str | None = None
    seed: Annotated[int, Field(ge=0)] = 0
    run: RunSpec = AttitudeTargets()
    #: project key path -> distribution (the simulated machine only)
    dispersions: dict[str, Distribution] = Field(default_factory=dict)
    #: HIL scenario key path -> distribution (sensors.position.noise_um, plant.rod_mass_kg)
    simulator: dict[str, Distribution] = Field(default_factory=dict)
    events: tuple[RandomEvent, ...] = ()
    requirement: Requirement = Requirement()
    tune: Tune = Tune()

    @model_validator(mode="after")
    def _figures_of_the_kind(self) -> CampaignSpec:
        try:
            self.requirement.check_names(self.run.kind)
        except ValueError as exc:
            raise ValueError(f"requirement.{exc}") from None
        return self


def default_limits(kind: str, project: ProjectConfig) -> dict[str, float]:
    """The goals a run of ``kind`` is judged against when the spec sets no limits, read
    from ``project`` (:mod:`wara.goals`): the attitude examples' goals, a walk's step
    goals (``wara walk``'s), a ring cycle's (``wara cycle``'s: Table 4 of the project's
    ``acceptance``, the placement goals, ``cycle.max_cycle_time_min``)."""
    if kind == "attitude_targets":
        return dict(DEMO_LIMITS)
    if kind == "walk":
        return limits(walk_step_goals(project))
    return limits(ring_goals(project))


# --------------------------------------------------------------------------- loading


class Campaign:
    """A loaded spec: the spec, the project (nominal), the expanded key paths."""

    def __init__(
        self,
        spec: CampaignSpec,
        source: str,
        base_dir: Path,
        project: ProjectConfig | None = None,
    ) -> None:
        """``project``: the project itself (a worker that got it with the task); else
        ``spec.project`` is read."""
        self.spec = spec
        self.source = source
        self.project_path: str | None = (
            None if spec.project is None else str((base_dir / spec.project).resolve())
        )
        self.project = load_project(self.project_path) if project is None else project
        kind = spec.run.kind
        if kind == "walk" and self.project.walking is None:
            raise ConfigError(f"{source}: run.kind: walk: the project has no walking section")
        if kind == "ring_cycle" and (self.project.cycle is None or self.project.placement is None):
            raise ConfigError(
                f"{source}: run.kind: ring_cycle: the project has no cycle or placement section"
            )
        if spec.kind == "nominal":
            try:
                check_nominal(spec.events, self.project)
            except ValueError as exc:
                raise ConfigError(f"{source}: kind: nominal: {exc}") from None
        #: figure -> limit: the spec's, or the run kind's goals
        self.limits: dict[str, float] = (
            dict(spec.requirement.limits)
            if spec.requirement.limits is not None
            else default_limits(kind, self.project)
        )
        nominal = self.project.model_dump(mode="json")
        expanded = _expand(_with_plants(nominal), spec.dispersions, source, "dispersions")
        # a cylinder's own plant last: it starts from the run's drawn defaults
        self.dispersions = dict(
            sorted(expanded.items(), key=lambda kv: _is_cylinder_plant(kv[1][0]))
        )
        scen = HilScenario().model_dump(mode="json")
        # the simulated rod mass defaults to the machine's: a dispersion draws around it
        scen["plant"]["rod_mass_kg"] = HilScenario().plant.rod_mass_for(self.project)
        self.simulator = _expand(scen, spec.simulator, source, "simulator")
        self._nominal = nominal
        self._scenario_nominal = scen
        for path, (lo, hi) in spec.tune.parameters.items():
            where = f"{source}: tune.parameters.{path}"
            if not path.startswith("control."):
                raise ConfigError(
                    f"{where}: only control.* keys are tuned (the service's own; the "
                    "planner and the machine read the project file)"
                )
            try:
                _get(nominal, _parse(path), where)
            except ValueError as exc:
                raise ConfigError(f"{where}: {exc}") from None
            if not 0 < lo < hi:
                raise ConfigError(f"{where}: [{lo}, {hi}] must be 0 < low < high")
        # one draw now, so that a path whose value the schema refuses fails at load
        self.draw(0)

    @property
    def project_file(self) -> str:
        return self.project_path or str(default_project_path())

    @property
    def run_count(self) -> int:
        return self.spec.requirement.run_count

    def draw(self, index: int) -> Draw:
        """Everything random about run ``index``."""
        return Draw.make(self, index)


class Draw:
    """Run ``index``'s parameters: the simulated machine's project, the scenario, the
    targets, the simulator's seed; ``params`` the drawn values by column name."""

    def __init__(
        self,
        index: int,
        params: dict[str, float],
        targets: list[tuple[float, float]],
        sim_project: ProjectConfig,
        scenario: HilScenario,
        sim_seed: int,
        previous_mm: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """``targets``: the attitude targets (roll, pitch deg); ``previous_mm``: a ring
        cycle's previous part's (y, z) deviation from its design, mm."""
        self.index = index
        self.params = params
        self.targets = targets
        self.previous_mm = previous_mm
        self.sim_project = sim_project
        self.scenario = scenario
        self.sim_seed = sim_seed

    @classmethod
    def make(cls, c: Campaign, index: int) -> Draw:
        spec = c.spec
        rng = np.random.default_rng(np.random.SeedSequence(spec.seed, spawn_key=(index,)))
        sim_seed = int(rng.integers(2**31))
        run = spec.run
        targets: list[tuple[float, float]] = []
        previous = (0.0, 0.0)
        params: dict[str, float] = {}
        if isinstance(run, AttitudeTargets):
            targets = [
                (float(rng.uniform(*run.roll_deg)), float(rng.uniform(*run.pitch_deg)))
                for _ in range(run.targets)
            ]
            for i, (roll, pitch) in enumerate(targets):
                params[f"target{i}_roll_deg"] = roll
                params[f"target{i}_pitch_deg"] = pitch
        elif isinstance(run, RingCycleRun):
            previous = (
                float(rng.uniform(*run.previous_y_mm)),
                float(rng.uniform(*run.previous_z_mm)),
            )
            params["previous_y_mm"], params["previous_z_mm"] = previous
        proj = copy.deepcopy(c._nominal)
        for name, (path, dist) in c.dispersions.items():
            if _is_cylinder_plant(path):
                _materialise_plant(proj, path)
            params[name] = _set_drawn(proj, path, dist, rng)
        scen = copy.deepcopy(c._scenario_nominal)
        for name, (path, dist) in c.simulator.items():
            params["sim." + name] = _set_drawn(scen, path, dist, rng)
        events: list[dict[str, Any]] = []
        for j, ev in enumerate(spec.events):
            kind = ev.event["kind"]
            tag = f"event{j}_{kind}"
            # every draw is made whether the event happens or not: the stream stays aligned
            happens = float(rng.random()) < ev.probability
            start = max(0.0, ev.start_s.draw(rng))
            dur = None if ev.duration_s is None else max(1e-3, ev.duration_s.draw(rng))
            extra = {k: d.draw(rng) for k, d in sorted(ev.fields.items())}
            params[f"{tag}_start_s"] = start if happens else math.nan
            if dur is not None:
                params[f"{tag}_duration_s"] = dur if happens else math.nan
            for k, v in extra.items():
                params[f"{tag}_{k}"] = v if happens else math.nan
            if happens:
                e = dict(ev.event, start_s=start, **extra)
                if dur is not None:
                    e["end_s"] = start + dur
                events.append(e)
        scen["events"] = events
        scen["seed"] = sim_seed
        where = f"{c.source}: run {index}"
        return cls(
            index,
            params,
            targets,
            validate_data(ProjectConfig, proj, f"{where}: drawn project"),
            validate_data(HilScenario, scen, f"{where}: drawn scenario"),
            sim_seed,
            previous,
        )


def load_campaign(path: str | Path) -> Campaign:
    p = Path(path)
    spec = validate_data(CampaignSpec, read_yaml(p), str(p))
    return Campaign(spec, str(p), p.parent)


def campaign_from_data(data: dict[str, Any], source: str, base_dir: Path) -> Campaign:
    return Campaign(validate_data(CampaignSpec, data, source), source, base_dir)


def zero_failure_runs(probability: float, confidence: float) -> int:
    """Runs that, all passing, show ``probability`` at ``confidence``: the smallest n with
    probability**n <= 1 - confidence (299 for 0.99 at 0.95, 852 for 0.9973 at 0.90)."""
    n = math.log(1.0 - confidence) / math.log(probability)
    return max(1, math.ceil(n - 1e-9))


# --------------------------------------------------------------------------- key paths

_PART = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[(?:\d+|\*)\])*)$")


def _parse(path: str) -> list[str | int]:
    """``a.b[0].c`` -> ['a', 'b', 0, 'c']; ``[*]`` -> '*'."""
    out: list[str | int] = []
    for part in path.split("."):
        m = _PART.match(part)
        if not m:
            raise ValueError(f"bad key path {path!r} (at {part!r})")
        out.append(m.group(1))
        for idx in re.findall(r"\[(\d+|\*)\]", m.group(2)):
            out.append("*" if idx == "*" else int(idx))
    return out


def _get(data: Any, parts: list[str | int], where: str) -> Any:
    cur = data
    for i, p in enumerate(parts):
        here = _show(parts[: i + 1])
        if isinstance(p, int):
            if not isinstance(cur, list) or not -len(cur) <= p < len(cur):
                raise ConfigError(f"{where}: {here}: no such element in the project")
            cur = cur[p]
        else:
            if not isinstance(cur, dict) or p not in cur:
                raise ConfigError(f"{where}: {here}: no such key")
            cur = cur[p]
            if cur is None and i < len(parts) - 1:
                raise ConfigError(f"{where}: {here}: is null (not set), nothing to disperse")
    return cur


def _is_cylinder_plant(parts: list[str | int]) -> bool:
    return len(parts) > 2 and parts[0] == "cylinders" and parts[2] == "plant"


def _materialise_plant(data: dict[str, Any], parts: list[str | int]) -> None:
    """A cylinder whose ``plant`` is null has the defaults' (``ProjectConfig.plant_of``):
    set them, as drawn for this run, so that its own can be drawn."""
    cyl = data["cylinders"][parts[1]]
    if cyl.get("plant") is None:
        cyl["plant"] = copy.deepcopy(data["hydraulics"]["cylinder_defaults"])


def _with_plants(data: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(data)
    for i in range(len(out.get("cylinders", []))):
        _materialise_plant(out, ["cylinders", i, "plant"])
    return out


def _show(parts: list[str | int]) -> str:
    s = ""
    for p in parts:
        s += f"[{p}]" if isinstance(p, int) or p == "*" else ("." if s else "") + p
    return s


def _expand(
    data: dict[str, Any], given: dict[str, Distribution], source: str, section: str
) -> dict[str, tuple[list[str | int], Distribution]]:
    """Column name -> (concrete path, distribution), ``[*]`` expanded per element;
    each path checked to name a number."""
    out: dict[str, tuple[list[str | int], Distribution]] = {}
    for key, dist in given.items():
        where = f"{source}: {section}.{key}"
        try:
            parts = _parse(key)
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        concrete: list[list[str | int]] = [[]]
        for p in parts:
            if p == "*":
                grown = []
                for c in concrete:
                    seq = _get(data, c, where)
                    if not isinstance(seq, list):
                        raise ConfigError(f"{where}: {_show(c)}: [*] needs a list")
                    grown += [[*c, i] for i in range(len(seq))]
                concrete = grown
            else:
                concrete = [[*c, p] for c in concrete]
        for c in concrete:
            value = _get(data, c, where)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(f"{where}: {_show(c)}: is {value!r}, not a number")
            if dist.factor and value == 0:
                raise ConfigError(f"{where}: factor: true on a nominal value of 0")
            out[_show(c)] = (c, dist)
    return out


def _set_drawn(
    data: dict[str, Any], parts: list[str | int], dist: Distribution, rng: np.random.Generator
) -> float:
    parent = _get(data, parts[:-1], "key path")
    last = parts[-1]
    nominal = parent[last]
    v = dist.draw(rng)
    value = nominal * v if dist.factor else v
    if isinstance(nominal, int) and not isinstance(nominal, bool) and not dist.factor:
        value = round(value)
    parent[last] = value
    return float(value)


def set_path(data: dict[str, Any], path: str, value: float) -> None:
    """Set one concrete key path in a dumped model (``wara campaign tune``)."""
    parts = _parse(path)
    parent = _get(data, parts[:-1], "key path")
    parent[parts[-1]] = value
