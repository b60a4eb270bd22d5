"""The campaign report: ``wara campaign report DIR``.

The verdict is a one-sided lower confidence bound on the probability that a run passes:
with no failure in n runs it is the order-statistics bound (1 - confidence)**(1/n);
with f failures, Clopper-Pearson's, the ``1 - confidence`` quantile of
Beta(n - f, f + 1). The requirement is shown when that bound reaches its probability
with every planned run done.
"""

from __future__ import annotations

import base64
import html
import io
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from wara.campaign.engine import campaign_of_dir, read_manifest, read_results
from wara.campaign.spec import HIGHER_IS_BETTER, Campaign


def lower_bound(n: int, failures: int, confidence: float) -> float:
    """One-sided lower bound on the pass probability at ``confidence``."""
    if n <= 0:
        return 0.0
    if failures == 0:
        return float((1.0 - confidence) ** (1.0 / n))
    if failures >= n:
        return 0.0
    from scipy.stats import beta

    return float(beta.ppf(1.0 - confidence, n - failures, failures + 1))


def percentile_figure(rows: list[dict[str, Any]], metric: str, probability: float) -> float:
    """The campaign's figure: for ``margin`` and the figures of
    :data:`~wara.campaign.spec.HIGHER_IS_BETTER` their (1 - probability) quantile, else
    the figure's ``probability`` quantile (lower is better). A run that did not finish
    counts as the worst value (margin -1, a figure -inf or +inf). The quantile is an
    order statistic, on the safe side (no interpolation)."""
    if not rows:
        return math.nan
    v = np.array([r[metric] for r in rows], dtype=float)
    if metric == "margin":
        return float(np.quantile(np.nan_to_num(v, nan=-1.0), 1.0 - probability, method="lower"))
    if metric in HIGHER_IS_BETTER:
        v[np.isnan(v)] = -np.inf
        return float(np.quantile(v, 1.0 - probability, method="lower"))
    v[np.isnan(v)] = np.inf
    return float(np.quantile(v, probability, method="higher"))


def _higher_is_better(name: str) -> bool:
    return name == "margin" or name in HIGHER_IS_BETTER


def verdict(c: Campaign, rows: list[dict[str, Any]], planned: int) -> dict[str, Any]:
    req = c.spec.requirement
    n = len(rows)
    f = sum(not r["passed"] for r in rows)
    bound = lower_bound(n, f, req.confidence)
    complete = n >= planned
    shown = complete and bound >= req.probability
    return {
        "runs": n,
        "planned": planned,
        "failures": f,
        "probability": req.probability,
        "confidence": req.confidence,
        "lower_bound": bound,
        "method": "order statistics (zero failures)" if f == 0 else "Clopper-Pearson",
        "complete": complete,
        "shown": shown,
        "metric": req.metric,
        "percentile_figure": percentile_figure(rows, req.metric, req.probability),
        "limits": dict(c.limits),
    }


def param_columns(rows: list[dict[str, Any]]) -> list[str]:
    return [k for k in rows[0] if k.startswith("p.")] if rows else []


#: A random event's drawn start (NaN in the runs where it did not happen).
EVENT_START = re.compile(r"^p\.(event\d+_\w+?)_start_s$")


def _driver_columns(rows: list[dict[str, Any]]) -> list[tuple[str, np.ndarray]]:
    """Each drawn parameter's values over the runs, and for each random event whether it
    happened at all (1/0: its start drawn or NaN), as ``"eventJ_kind happened"``."""
    out = []
    for col in param_columns(rows):
        x = np.array([r[col] for r in rows], dtype=float)
        out.append((col[2:], x))
        m = EVENT_START.match(col)
        if m is not None:
            out.append((f"{m.group(1)} happened", np.isfinite(x).astype(float)))
    return out


def drivers(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Spearman rank correlation of each drawn parameter with the margin and with
    failure (runs where the parameter was drawn; constant ones left out), and of
    whether each random event happened at all, strongest first."""
    from scipy.stats import spearmanr

    out = []
    margin = np.array([r["margin"] for r in rows], dtype=float)
    failed = np.array([not r["passed"] for r in rows], dtype=float)
    for name, x in _driver_columns(rows):
        ok = np.isfinite(x) & np.isfinite(margin)
        if ok.sum() < 3 or np.ptp(x[ok]) == 0:
            continue
        entry: dict[str, Any] = {"parameter": name, "runs": int(ok.sum())}
        entry["rho_margin"] = _rho(spearmanr, x[ok], margin[ok])
        entry["rho_failure"] = _rho(spearmanr, x[ok], failed[ok])
        out.append(entry)

    def strength(e: dict[str, Any]) -> float:
        vals = [abs(v) for v in (e["rho_failure"], e["rho_margin"]) if v is not None]
        return max(vals, default=0.0)

    return sorted(out, key=strength, reverse=True)


def _rho(fn: Any, x: np.ndarray, y: np.ndarray) -> float | None:
    if np.ptp(y) == 0:
        return None
    r = float(fn(x, y).statistic)
    return None if math.isnan(r) else r


def worst_runs(rows: list[dict[str, Any]], k: int = 5) -> list[dict[str, Any]]:
    """The ``k`` runs with the smallest margin (failures first), with their parameters."""
    order = sorted(rows, key=lambda r: (r["passed"], r["margin"]))
    keep = ["run", "status", "margin", "note", "fault_reasons", "seed"]
    return [
        {**{c: r[c] for c in keep}, "params": {p[2:]: r[p] for p in param_columns(rows)}}
        for r in order[:k]
    ]


def summary(out: Path) -> dict[str, Any]:
    c = campaign_of_dir(out)
    manifest = read_manifest(out)
    rows = read_results(out)
    return {
        "name": manifest["name"],
        "directory": str(out),
        "verdict": verdict(c, rows, int(manifest["runs"])),
        "worst_runs": worst_runs(rows),
        "drivers": drivers(rows)[:10],
        "figures": _figure_stats(c, rows),
        "status_counts": _counts(rows),
    }


def _counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in rows:
        out[r["status"]] = out.get(r["status"], 0) + 1
    return out


def _figure_stats(c: Campaign, rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    req = c.spec.requirement
    out = {}
    for name in [*c.limits, "margin"]:
        v = np.array([r[name] for r in rows], dtype=float)
        v = v[np.isfinite(v)]
        if not len(v):
            continue
        out[name] = {
            "median": float(np.median(v)),
            "p_requirement": percentile_figure(rows, name, req.probability),
            "worst": float(v.min() if _higher_is_better(name) else v.max()),
            "limit": float(c.limits.get(name, 0.0)),
        }
    return out


# --------------------------------------------------------------------------- text / HTML


def render_text(s: dict[str, Any]) -> str:
    v = s["verdict"]
    lines = [
        f"campaign {s['name']}: {v['runs']} of {v['planned']} runs, {v['failures']} failed",
        f"pass probability >= {v['lower_bound']:.5f} at {v['confidence']:.0%} confidence "
        f"({v['method']}); required {v['probability']}",
        f"{v['metric']} at the requirement's percentile: {v['percentile_figure']:.4g}",
        "VERDICT: "
        + (
            "requirement shown"
            if v["shown"]
            else ("incomplete campaign" if not v["complete"] else "requirement NOT shown")
        ),
        "",
        f"{'figure':<33}median      percentile  worst       limit",
    ]
    for name, f in s["figures"].items():
        lim = f"{f['limit']:.4g}" + (" (>=)" if name in HIGHER_IS_BETTER else "")
        lim = lim if name != "margin" else "0 (>)"
        lines.append(
            f"{name:<32} {f['median']:<11.4g} {f['p_requirement']:<11.4g} {f['worst']:<11.4g} {lim}"
        )
    lines += ["", "worst runs:"]
    for w in s["worst_runs"]:
        note = w["note"] or "-"
        lines.append(f"  run {w['run']}: {w['status']}, margin {w['margin']:.4g}: {note}")
    lines += ["", "drivers (Spearman rho with margin / with failure):"]
    for d in s["drivers"][:5]:
        lines.append(f"  {d['parameter']}: {_fmt(d['rho_margin'])} / {_fmt(d['rho_failure'])}")
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:+.3f}"


def plots(c: Campaign, rows: list[dict[str, Any]], s: dict[str, Any]) -> list[tuple[str, bytes]]:
    """PNG images: a histogram of each limited figure and of the margin, with the limit;
    a scatter of the leading parameter against the margin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = []
    passed = np.array([r["passed"] for r in rows], dtype=bool)
    for name in [*c.limits, "margin"]:
        v = np.array([r[name] for r in rows], dtype=float)
        v = v[np.isfinite(v)]
        limit = 0.0 if name == "margin" else c.limits[name]
        fig, ax = plt.subplots(figsize=(6, 3.6))
        histogram(ax, v, limit)
        ax.axvline(limit, color="r", ls="--", label="limit")
        ax.set_xlabel(name)
        ax.set_ylabel("runs")
        worst = f", largest {v.max():.3g}" if v.size and name != "margin" else ""
        ax.set_title(f"{name} over {len(rows)} runs{worst}")
        ax.legend()
        images.append((f"hist_{name}", _png(fig, plt)))
    if s["drivers"]:
        lead = s["drivers"][0]["parameter"]
        x = dict(_driver_columns(rows))[lead]
        m = np.array([r["margin"] for r in rows], dtype=float)
        fig, ax = plt.subplots(figsize=(6, 3.6))
        ax.scatter(x[passed], m[passed], s=10, label="passed")
        ax.scatter(x[~passed], m[~passed], s=14, color="r", label="failed")
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xlabel(lead)
        ax.set_ylabel("margin")
        ax.set_title(f"margin vs {lead} (leading parameter)")
        ax.legend()
        images.append(("scatter_lead", _png(fig, plt)))
    return images


#: Values spanning less than this share of the axis (which reaches the limit) get an
#: inset of their own, its axis scaled to them.
INSET_SHARE = 0.1


def histogram(ax: Any, v: np.ndarray, limit: float) -> Any:
    """``v``'s histogram on ``ax``, its 30 bins spanning the values and the limit (values
    far below the limit, 1e-5 on a 0-0.01 axis, are one visible bar beside the limit's
    line); when the values span less than :data:`INSET_SHARE` of that axis, an inset with
    their own 30 bins on an axis scaled to them (returned; else None)."""
    lo, hi = min([limit, *v]), max([limit, *v])
    ax.hist(v, bins=30, range=(lo, hi) if hi > lo else None, color="#4a78b0")
    if not v.size or hi <= lo or np.ptp(v) >= INSET_SHARE * (hi - lo):
        return None
    inset = ax.inset_axes((0.45, 0.45, 0.5, 0.45))
    inset.hist(v, bins=30, color="#4a78b0")
    inset.set_title("the values alone", fontsize=8)
    inset.tick_params(labelsize=7)
    return inset


def _png(fig: Any, plt: Any) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return buf.getvalue()


def write_html(out: Path, dest: Path | None = None) -> Path:
    """One self-contained page (images inline as base64): ``DIR/report.html``."""
    c = campaign_of_dir(out)
    rows = read_results(out)
    s = summary(out)
    imgs = plots(c, rows, s)
    e = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>Campaign {e(s['name'])}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;"
        "font-size:13px}</style></head><body>",
        f"<h1>Campaign {e(s['name'])}</h1>",
        f"<pre>{e(render_text(s))}</pre>",
        "<h2>Plots</h2>",
    ]
    for name, png in imgs:
        b64 = base64.b64encode(png).decode()
        parts.append(f"<img alt='{e(name)}' src='data:image/png;base64,{b64}'>")
    parts.append(
        "<h2>Worst runs</h2><table><tr><th>run</th><th>status</th><th>margin</th>"
        "<th>note</th><th>parameters</th></tr>"
    )
    for w in s["worst_runs"]:
        params = ", ".join(f"{k}={v:.4g}" for k, v in w["params"].items() if v == v)
        parts.append(
            f"<tr><td>{w['run']}</td><td>{e(w['status'])}</td><td>{w['margin']:.4g}</td>"
            f"<td>{e(w['note'] or w['fault_reasons'])}</td><td>{e(params)}</td></tr>"
        )
    parts.append(
        "</table><p>Replay one: <code>wara campaign replay DIR RUN --plot OUT</code>"
        "</p></body></html>"
    )
    path = dest or out / "report.html"
    path.write_text("\n".join(parts))
    return path
