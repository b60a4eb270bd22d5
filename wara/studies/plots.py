"""The dual-cylinder study's figure: what a controls engineer looks at, side by side."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from config import units
from config.scenario import DualCylinderScenario
from wara.studies.dual_cylinder import StudyRun

_TITLES = {"ladrc": "LADRC + dual-error sync", "pid": "PID + dual-error sync"}


def plot_runs(runs: dict[str, StudyRun], scenario: DualCylinderScenario, path: str | Path) -> Path:
    """Positions and reference, synchronization error, valve commands and chamber
    pressures, one column per controller; written to ``path`` (PNG, 150 dpi)."""
    names = list(runs)
    fig, axes = plt.subplots(
        4, len(names), figsize=(6.5 * len(names), 11), sharex=True, squeeze=False
    )
    mm = 1.0 / units.mm(1.0)
    goal = scenario.goals.sync_error_max_mm
    sync_peak = max(float(r.sync_error_m.max()) * mm for r in runs.values())
    ids = [c.cylinder.id for c in scenario.cylinders]
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
    for col, name in enumerate(names):
        run = runs[name]
        step = max(len(run.t_s) // 20000, 1)
        t = run.t_s[::step]
        ax = axes[0][col]
        ax.plot(t, run.reference_m[::step, 0] * mm, "k--", lw=1.0, label="reference")
        for i, cid in enumerate(ids):
            ax.plot(t, run.position_m[::step, i] * mm, color=colors[i], lw=1.0, label=cid)
        ax.set_ylabel("rod position [mm]")
        ax.set_title(_TITLES.get(name, name))
        ax.legend(loc="upper right", fontsize=8)

        ax = axes[1][col]
        sync = (run.position_m[:, 0] - run.position_m[:, 1]) * mm
        ax.plot(run.t_s, sync, color="tab:purple", lw=0.6, label=f"{ids[0]} - {ids[1]}")
        ax.axhline(goal, color="tab:red", ls=":", lw=1.0, label=f"+-{goal} mm (paper)")
        ax.axhline(-goal, color="tab:red", ls=":", lw=1.0)
        ax.axvspan(0, scenario.transient_s, color="0.9", label="initial transient")
        ax.set_ylim(-1.15 * max(sync_peak, goal), 1.15 * max(sync_peak, goal))
        ax.set_ylabel("sync error [mm]")
        ax.legend(loc="lower left", fontsize=8, ncol=3)

        ax = axes[2][col]
        for i, cid in enumerate(ids):
            ax.plot(t, run.command[::step, i], color=colors[i], lw=0.8, label=cid)
        ax.set_ylabel("valve command u [-]")
        ax.legend(loc="upper right", fontsize=8)

        ax = axes[3][col]
        for i, cid in enumerate(ids):
            ax.plot(t, units.to_mpa(1.0) * run.p_a_pa[::step, i], color=colors[i], lw=0.8,
                    label=f"{cid} cap side p_A")  # fmt: skip
            ax.plot(t, units.to_mpa(1.0) * run.p_b_pa[::step, i], color=colors[i], lw=0.8,
                    ls="--", label=f"{cid} rod side p_B")  # fmt: skip
        ax.set_ylabel("chamber pressure [MPa]")
        ax.set_xlabel("time [s]")
        ax.legend(loc="upper right", fontsize=7, ncol=2)

        if scenario.noise is not None:
            for row in axes:
                row[col].axvline(scenario.noise.start_s, color="0.4", ls="-.", lw=0.8)
            axes[1][col].text(
                scenario.noise.start_s, 0.95 * axes[1][col].get_ylim()[1], " load noise on",
                fontsize=8, color="0.3", va="top",
            )  # fmt: skip
        for row in axes:
            row[col].grid(True, alpha=0.3)
    fig.suptitle(
        f"{scenario.name}: {run.duration_s:.0f} s, control at {scenario.control.rate_hz:.0f} Hz"
    )
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=150)
    plt.close(fig)
    return out
