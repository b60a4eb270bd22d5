"""The dossier of ``wara commission`` as one self-contained HTML page.

The acceptance report's style sheet and load check (:mod:`acceptance.report`), plots as
base64 PNG inline (the campaign's own from :func:`wara.campaign.report.plots`, the
capacity's and the goals' drawn here with :class:`matplotlib.figure.Figure`, no pyplot);
no external ``src`` or ``href``: the page can be mailed as one file.
"""

from __future__ import annotations

import base64
import html
import io
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from acceptance.report import PAGE_CSS, PAGE_SCRIPT
from wara.commission import FIT, NOT_FIT, Item

HTML_NAME = "commission.html"
JSON_NAME = "commission.json"

_CLASS = {FIT: "pass", NOT_FIT: "fail"}


def share_plot(title: str, bars: Sequence[tuple[str, float]]) -> bytes | None:
    """A horizontal bar per ``(label, value / limit)``, the limit at 1 (PNG; ``None``
    without matplotlib or bars)."""
    bars = [(k, v) for k, v in bars if v == v]  # NaN: nothing to draw
    if not bars:
        return None
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return None
    fig = Figure(figsize=(7.5, 0.6 + 0.32 * len(bars)))
    ax = fig.add_subplot()
    labels = [k for k, _ in bars]
    values = [v for _, v in bars]
    colours = ["#c0262d" if v > 1.0 else "#1f5fa8" for v in values]
    ax.barh(range(len(bars)), values, color=colours)
    ax.set_yticks(range(len(bars)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.axvline(1.0, color="k", ls="--", lw=1)
    ax.set_xlabel("share of the limit (1: on the limit)")
    ax.set_title(title, fontsize=9)
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()


def add_plots(items: Sequence[Item]) -> None:
    """The capacity's peak pressures and the walk's and cycle's worst goals, each as a
    share of its limit."""
    for it in items:
        png: bytes | None = None
        if it.name == "capacity" and it.rows:
            bars = [
                (f"{r['plan']} [{r['case'].split(' (')[0]}]", r["peak_mpa"] / r["limit_mpa"])
                for r in it.rows
                if r["limit_mpa"]
            ]
            png = share_plot("peak pressure over what the supply gives", bars)
        elif it.name in ("walk", "cycle") and it.rows:
            bars = []
            for r in it.rows:
                if not r["limit"]:
                    continue
                share = abs(r["worst"]) / r["limit"]
                if r["figure"] == "min_stability_margin_m":  # a lower bound
                    share = r["limit"] / r["worst"] if r["worst"] > 0 else float("inf")
                bars.append((r["figure"], share))
            png = share_plot(f"{it.name}: the worst of each goal", bars)
        if png is not None:
            it.images.insert(0, (f"{it.name}_limits", png))


def _cell(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list | dict):
        return html.escape(json.dumps(v))
    return html.escape(str(v))


def _table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return ""
    cols = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th class=l>{html.escape(c)}</th>" for c in cols)
    body = []
    for r in rows:
        bad = any(r.get(k) is False for k in ("feasible", "kept", "met", "stable"))
        bad = bad or bool(r.get("breaks"))
        cells = "".join(f"<td class=l>{_cell(r.get(c))}</td>" for c in cols)
        body.append(f"<tr class='{'fail' if bad else ''}'>{cells}</tr>")
    return f"<div class=wide><table><tr>{head}</tr>{''.join(body)}</table></div>"


def render_html(items: Sequence[Item], summary: dict[str, Any]) -> str:
    e = html.escape
    fit = summary["fit"]
    verdict = "FIT to commission" if fit else "NOT fit to commission"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>Commissioning dossier: {e(summary['project'])}</title>",
        f"<style>{PAGE_CSS}</style><script>{PAGE_SCRIPT}</script></head><body>",
        f"<h1>Commissioning dossier: {e(summary['project'])}</h1>",
        f'<p class="meta">{e(summary["section"])} · {e(summary["file"])} · generated '
        f"{e(summary['generated_at'])} in {summary['wall_s']:.0f} s on "
        f"{summary['cpus']} CPU(s) · settings {e(json.dumps(summary['settings']))}</p>",
        f'<p class="big {"pass" if fit else "fail"}"><strong>{verdict}</strong></p>',
    ]
    if summary["not_fit"]:
        parts.append("<h2>Why not</h2><ul>")
        parts += [f"<li>{e(r)}</li>" for r in summary["not_fit"]]
        parts.append("</ul>")
    parts.append("<h2>Items</h2><table><tr><th class=l>item</th><th class=l>verdict</th>"
                 "<th class=l>first reason</th><th>wall s</th></tr>")  # fmt: skip
    for it in items:
        cls = _CLASS.get(it.status, "nolimit")
        first = it.reasons[0] if it.reasons else ""
        parts.append(
            f"<tr><td class=l><a href='#{e(it.name)}'>{e(it.title)}</a></td>"
            f"<td class='l {cls}'>{e(it.status)}</td><td class=l>{e(first)}</td>"
            f"<td>{it.wall_s:.1f}</td></tr>"
        )
    parts.append("</table>")
    for it in items:
        cls = _CLASS.get(it.status, "nolimit")
        parts.append(f"<h2 id='{e(it.name)}'>{e(it.title)}: <span class='{cls}'>"
                     f"{e(it.status)}</span></h2>")  # fmt: skip
        if it.reasons:
            parts.append("<ul>" + "".join(f"<li>{e(r)}</li>" for r in it.reasons) + "</ul>")
        for n in it.notes:
            parts.append(f"<pre class=rules>{e(n)}</pre>" if "\n" in n else f"<p class=rules>"
                         f"{e(n)}</p>")  # fmt: skip
        parts.append(_table(it.rows))
        for name, png in it.images:
            b64 = base64.b64encode(png).decode("ascii")
            parts.append(f"<figure><img alt='{e(name)}' src='data:image/png;base64,{b64}'>"
                         "</figure>")  # fmt: skip
    parts.append(
        "<h2>What fit means</h2><p class=rules>Every item fit, skipped or not applicable: "
        "an item is not fit when its check finds the project short of its own limits, "
        "or when it could not run (docs/commissioning.md, decision 0027).</p>"
    )
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write(items: Sequence[Item], summary: dict[str, Any], out: Path) -> tuple[Path, Path]:
    """``OUT/commission.html`` and ``OUT/commission.json``."""
    add_plots(items)
    page = out / HTML_NAME
    page.write_text(render_html(items, summary), encoding="utf-8")
    js = out / JSON_NAME
    js.write_text(json.dumps(_plain(summary), indent=2, default=str) + "\n", encoding="utf-8")
    return page, js


def _plain(v: Any) -> Any:
    """``v`` with every NaN or infinity ``None`` (JSON has neither)."""
    if isinstance(v, float):
        return v if v - v == 0.0 else None
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    return v
