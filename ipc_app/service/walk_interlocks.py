"""The walk's interlocks (walking.md section 5): pure checks of one cycle's
:class:`~ipc_app.control.walk.WalkFigures` against the :class:`WalkLimits` of the
configuration. Their specs (config key, when they apply) are data in
:data:`ipc_app.service.interlocks.SPECS`; the phases each one watches are
:data:`PHASES_OF`. Every cause returned here is a stop, latched (ABORTED, valves closed,
load held); the sync band's own reaction (the group holds and goes on) is the
sequencer's, and only a band left for longer than its timeout comes here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from config import units
from config.schema import ProjectConfig
from ipc_app.control.walk import LIFT, LOWER, PRELOAD, TRANSFER, TRAVEL, WalkFigures
from ipc_app.service.interlocks import Cause, Interlock

_ALL = TRAVEL | LOWER | PRELOAD | TRANSFER | LIFT

#: the phases in which each walk check runs (data: the checks below read it)
PHASES_OF: dict[Interlock, frozenset[str]] = {
    Interlock.SYNC_BAND: TRAVEL | LOWER | LIFT,
    Interlock.OVERLOAD: _ALL,
    Interlock.TOUCHDOWN: LOWER,
    Interlock.TRANSFER: PRELOAD | TRANSFER,
    Interlock.STABILITY: _ALL,
    Interlock.SLIP: _ALL,
}


@dataclass(frozen=True)
class WalkLimits:
    """The walk's limits, SI (and the configured figures for the causes' ``limit``)."""

    sync_band_timeout_s: float
    overload_ratio: float
    overload_percent: float
    min_margin_m: float
    share_tolerance: float
    resume_height_m: float
    #: how far a travel rod may stand from where it stopped when the walk resumes: it
    #: coasts on its last command until the PLC closes the valves, at most the travel
    #: speed times ``safety.command_timeout_ms``, plus the height tolerance
    resume_travel_m: float
    resume_force: float
    touchdown_travel_mm: float

    @classmethod
    def from_config(cls, cfg: ProjectConfig) -> WalkLimits:
        w = cfg.walking
        if w is None:
            raise ValueError("the project has no walking section")
        return cls(
            sync_band_timeout_s=w.sync_band_timeout_s,
            overload_ratio=w.overload_percent / 100.0,
            overload_percent=w.overload_percent,
            min_margin_m=w.min_stability_margin_m,
            share_tolerance=w.share_tolerance_percent / 100.0,
            resume_height_m=units.mm(w.resume_height_tolerance_mm),
            resume_travel_m=units.mm(w.resume_height_tolerance_mm)
            + w.travel_speed_m_s * units.ms(cfg.safety.command_timeout_ms),
            resume_force=w.resume_force_tolerance_percent / 100.0,
            touchdown_travel_mm=w.touchdown_travel_mm,
        )


def walk_causes(fig: WalkFigures, leg_ids: Sequence[str], lim: WalkLimits) -> list[Cause]:
    """The walk checks of this cycle (each in the phases of :data:`PHASES_OF`)."""
    out: list[Cause] = []
    ph = fig.phase

    def on(il: Interlock) -> bool:
        return ph in PHASES_OF[il]

    if on(Interlock.SYNC_BAND) and fig.out_of_band_s > lim.sync_band_timeout_s:
        out.append(
            Cause(
                Interlock.SYNC_BAND,
                where=fig.out_of_band,
                value=fig.out_of_band_s,
                limit=lim.sync_band_timeout_s,
                detail=f"out of its band (step {fig.step} phase {ph})",
            )
        )
    if on(Interlock.OVERLOAD) and fig.leg_force_n:
        ratios = fig.force_ratios()
        j = max(range(len(ratios)), key=ratios.__getitem__)
        if ratios[j] > lim.overload_ratio:
            unknown = fig.friction_unknown_n[j] if fig.friction_unknown_n else 0.0
            out.append(
                Cause(
                    Interlock.OVERLOAD,
                    where=leg_ids[j],
                    value=100.0 * ratios[j],
                    limit=lim.overload_percent,
                    detail=f"{fig.leg_force_n[j] / units.KN:.1f} kN, less {unknown / units.KN:.1f} "
                    f"kN its seal may hold, of an expected {fig.expected_n[j] / units.KN:.1f} "
                    f"kN (step {fig.step} phase {ph})",
                )
            )
    if on(Interlock.TOUCHDOWN) and fig.no_touchdown:
        out.append(
            Cause(
                Interlock.TOUCHDOWN,
                where=fig.no_touchdown,
                detail=f"no touch-down within {lim.touchdown_travel_mm:g} mm below the expected "
                f"ground (step {fig.step} phase {ph}): a hole under the foot",
            )
        )
    if on(Interlock.TOUCHDOWN) and fig.obstacle[0]:
        who, height_m = fig.obstacle
        out.append(
            Cause(
                Interlock.TOUCHDOWN,
                where=who,
                value=units.to_mm(height_m),
                limit=lim.touchdown_travel_mm,
                detail=f"the foot met the invert {units.to_mm(height_m):.1f} mm above the "
                f"expected ground, above the touch-down window of {lim.touchdown_travel_mm:g} "
                f"mm (step {fig.step} phase {ph}): an obstacle, or the ground higher than "
                "expected",
            )
        )
    if on(Interlock.TRANSFER) and fig.overdue_s > 0.0:
        who, ratio = fig.share_off
        out.append(
            Cause(
                Interlock.TRANSFER,
                where=who,
                value=fig.overdue_s,
                limit=0.0,
                detail=f"not done in time (step {fig.step} phase {ph}"
                + (f"; {who} at {100 * ratio:.0f} % of its share)" if who else ")"),
            )
        )
    if on(Interlock.STABILITY):
        worst = min(fig.margin_m, fig.margin_ahead_m)
        if worst < lim.min_margin_m:
            ahead = fig.margin_ahead_m < fig.margin_m
            out.append(
                Cause(
                    Interlock.STABILITY,
                    where="ahead" if ahead else "now",
                    value=worst,
                    limit=lim.min_margin_m,
                    detail=f"step {fig.step} phase {ph}"
                    + (" (along the commanded motion)" if ahead else ""),
                )
            )
    if on(Interlock.SLIP) and abs(fig.travel_force_n) > fig.friction_capacity_n:
        out.append(
            Cause(
                Interlock.SLIP,
                where="travel",
                value=abs(fig.travel_force_n) / units.KN,
                limit=fig.friction_capacity_n / units.KN,
                detail=f"above the standing feet's friction (step {fig.step} phase {ph})",
            )
        )
    return out


def walk_resume_cause(
    x_now: Sequence[float],
    x_stop: Sequence[float],
    cylinders: Sequence[int],
    travel: Sequence[int],
    ids: Sequence[str],
    f_now: Sequence[float],
    f_stop: Sequence[float],
    share_n: Sequence[float],
    leg_ids: Sequence[str],
    lim: WalkLimits,
) -> Cause | None:
    """Resume of a stopped walk: every height cylinder (``cylinders``: legs, upper
    platform) within the height tolerance of where it stopped, each travel rod within
    its coasting allowance (:attr:`WalkLimits.resume_travel_m`), every leg's force
    within the force tolerance (of its share); else why not."""
    for group, tol in ((cylinders, lim.resume_height_m), (travel, lim.resume_travel_m)):
        for i in group:
            dev = abs(x_now[i] - x_stop[i])
            if not dev <= tol:  # NaN too
                return Cause(
                    Interlock.WALK_RESUME,
                    where=ids[i],
                    value=units.to_mm(dev),
                    limit=units.to_mm(tol),
                    detail="mm moved since the stop",
                )
    for j, cid in enumerate(leg_ids):
        dev = abs(f_now[j] - f_stop[j])
        if not dev <= lim.resume_force * share_n[j]:
            return Cause(
                Interlock.WALK_RESUME,
                where=cid,
                value=dev / units.KN,
                limit=lim.resume_force * share_n[j] / units.KN,
                detail="kN force change since the stop",
            )
    return None
