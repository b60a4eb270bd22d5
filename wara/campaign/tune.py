"""``wara campaign tune SPEC``: Optuna over the spec's ``tune.parameters`` (the LADRC
bandwidths by default), each trial a campaign on the same engine and the same drawn
runs (the spec's seed), maximising the campaign's percentile figure
(:func:`wara.campaign.report.percentile_figure`; for a lower-is-better figure, its
negative).

The result is a YAML fragment for the project with the best values, and that trial's
verdict.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from wara.campaign.engine import read_results, run_campaign
from wara.campaign.report import percentile_figure, verdict
from wara.campaign.spec import HIGHER_IS_BETTER, Campaign


def tune(
    c: Campaign,
    out: Path,
    *,
    client: Any,
    trials: int | None = None,
    runs: int | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    import optuna

    t = c.spec.tune
    n_runs = runs or t.runs or c.run_count
    n_trials = trials or t.trials
    req = c.spec.requirement
    # each trial: the spec with the trial's run count (its first n_runs runs)
    spec = c.spec.model_copy(update={"requirement": req.model_copy(update={"runs": n_runs})})
    trial_c = Campaign(spec, c.source, Path("."), project=c.project)
    trial_c.project_path = c.project_path
    sign = 1.0 if req.metric == "margin" or req.metric in HIGHER_IS_BETTER else -1.0
    history: list[dict[str, Any]] = []

    def objective(trial: Any) -> float:
        values = {
            path: trial.suggest_float(path, lo, hi, log=t.log)
            for path, (lo, hi) in t.parameters.items()
        }
        d = out / f"trial-{trial.number:04d}"
        run_campaign(trial_c, d, client=client, overrides=values, progress=progress)
        rows = read_results(d)
        fig = percentile_figure(rows, req.metric, req.probability)
        v = verdict(trial_c, rows, n_runs)
        history.append(
            {
                "trial": trial.number,
                "values": values,
                "figure": fig,
                "failures": v["failures"],
                "runs": v["runs"],
            }
        )
        return sign * fig if math.isfinite(fig) else -math.inf

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(seed=c.spec.seed)
    study = optuna.create_study(direction="maximize", sampler=sampler)
    # the shipped values first: the tuning must beat what the project has
    study.enqueue_trial({p: _nominal(c, p) for p in t.parameters})
    study.optimize(objective, n_trials=n_trials)
    best = study.best_trial
    d = out / f"trial-{best.number:04d}"
    rows = read_results(d)
    v = verdict(trial_c, rows, n_runs)
    fragment: dict[str, Any] = {}
    for path, value in best.params.items():
        _nest(fragment, path.split("."), round(float(value), 4))
    return {
        "best_trial": best.number,
        "best_values": dict(best.params),
        "figure": sign * float(best.value or 0.0),
        "metric": req.metric,
        "verdict": v,
        "fragment": yaml.safe_dump(fragment, sort_keys=False),
        "trials": history,
    }


def _nominal(c: Campaign, path: str) -> float:
    """The project's value of ``path``, or (left out of the YAML) the derived one
    (:func:`ipc_app.control.tuning.derived_value`), within the search range."""
    cur: Any = c.project.model_dump(mode="json")
    for p in path.split("."):
        cur = cur[p]
    if cur is None:
        from ipc_app.control.tuning import derived_value

        cur = derived_value(c.project, path)
    lo, hi = c.spec.tune.parameters[path]
    return float(min(max(float(cur), lo), hi))


def _nest(d: dict[str, Any], parts: list[str], value: float) -> None:
    for p in parts[:-1]:
        d = d.setdefault(p, {})
    d[parts[-1]] = value
