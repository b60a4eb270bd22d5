"""The quality report: one PNG per control item and one self-contained HTML page.

Each plot is drawn like paper Figure 14: the value per ring with the tolerance band
shaded and the limits dashed; rings over the limit are marked red and labelled. The HTML
page embeds the same PNGs as base64 and carries the tables, so it can be mailed to the
client as one file. ``summary.json`` holds the same numbers for machines.

Matplotlib is used through :class:`matplotlib.figure.Figure` directly (no pyplot, no
global state, no display needed). It is an optional dependency (the ``plot`` extra):
imported only when a plot is drawn, so the rest of the package works without it.
"""

from __future__ import annotations

import base64
import html
import io
import json
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from acceptance.judge import ItemSummary, RingVerdict, Status, Summary

HTML_NAME = "report.html"
JSON_NAME = "summary.json"

_PASS_COLOUR = "#1f5fa8"
_FAIL_COLOUR = "#c0262d"
_BAND_COLOUR = "#2e8b57"


@dataclass(frozen=True)
class ReportMeta:
    """Where the numbers came from, printed at the top of the report."""

    project: str = ""
    config_source: str = ""
    database: str = ""
    generated_at: str = field(
        default_factory=lambda: datetime.now(UTC).isoformat(timespec="seconds")
    )

    def to_dict(self) -> dict[str, str]:
        return {
            "project": self.project,
            "config_source": self.config_source,
            "database": self.database,
            "generated_at": self.generated_at,
        }


@dataclass(frozen=True)
class ReportFiles:
    html: Path
    summary_json: Path
    plots: dict[str, Path]


def _pct(rate: float | None) -> str:
    return "–" if rate is None else f"{100.0 * rate:.1f} %"


def _num(v: float | None) -> str:
    return "" if v is None else f"{v:g}"


def plot_item(summary: Summary, item: ItemSummary) -> bytes:
    """The Figure-14-style plot of one item as PNG bytes (needs matplotlib)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    key, unit, limit = item.item.key, item.item.unit, item.limit
    points = [
        (r.ring, r.record.measurement.values[key], r.statuses[key])
        for r in summary.rings
        if r.record.measurement.values[key] is not None
    ]
    fig = Figure(figsize=(8.0, 3.9), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    rings = [p[0] for p in points]
    values = [float(p[1]) for p in points if p[1] is not None]
    ax.plot(
        rings,
        values,
        color=_PASS_COLOUR,
        linewidth=1.0,
        marker="o",
        markersize=3.5,
        label="measured",
    )
    lo_lim = -limit if (limit is not None and item.item.signed) else 0.0
    if limit is not None:
        ax.axhspan(lo_lim, limit, color=_BAND_COLOUR, alpha=0.12, label="tolerance band")
        ax.axhline(limit, color=_BAND_COLOUR, linestyle="--", linewidth=1.2)
        if item.item.signed:
            ax.axhline(-limit, color=_BAND_COLOUR, linestyle="--", linewidth=1.2)
        fails = [(g, v) for g, v, s in points if s is Status.FAIL and v is not None]
        if fails:
            ax.scatter(
                [f[0] for f in fails],
                [f[1] for f in fails],
                s=46,
                color=_FAIL_COLOUR,
                zorder=3,
                label="over the limit",
            )
            for g, v in fails:
                ax.annotate(
                    f"ring {g}: {v:g}",
                    (g, v),
                    textcoords="offset points",
                    xytext=(6, 6 if v >= 0 else -14),
                    fontsize=8,
                    color=_FAIL_COLOUR,
                )
        pm = "±" if item.item.signed else "≤ "
        verdict = (
            f"{item.passed}/{item.judged} pass ({_pct(item.pass_rate)}), limit {pm}{limit:g} {unit}"
        )
        span = max([limit, *(abs(v) for v in values)]) * 1.25
        ax.set_ylim(-span if item.item.signed else 0.0, span)
    else:
        verdict = "no limit set in the project: recorded, not judged"
    if not item.item.signed:
        ax.set_ylim(bottom=0.0)
    ax.set_title(f"{item.item.label}: {verdict}", fontsize=10)
    ax.set_xlabel("ring number")
    ax.set_ylabel(f"{item.item.label.split(' (')[0].lower()} ({unit})")
    ax.grid(True, alpha=0.3)
    if summary.rings:
        ax.set_xlim(summary.rings[0].ring - 1, summary.rings[-1].ring + 1)
    fig.legend(loc="outside lower center", ncols=3, fontsize=8, frameon=False)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


#: The report pages' style sheet (this report and ``wara commission``'s dossier).
PAGE_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;
max-width:1100px;color:#1d1d1d;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.5em 0}
th,td{border:1px solid #c8c8c8;padding:.25em .55em;text-align:right}
th{background:#f0f0f0}td.l,th.l{text-align:left}
.pass{background:#e4f4e8}.fail{background:#fbd9d9;font-weight:600}
.nolimit{color:#666}.nm{color:#999;font-style:italic}
.incomplete{background:#fff3cd}
.meta{color:#555;font-size:.9em}.big{font-size:1.15em}
figure{margin:1em 0}img{max-width:100%;height:auto;border:1px solid #ddd}
.rules{font-size:.9em;color:#333}.wide{overflow-x:auto}
"""

# Marks the page as checked once every embedded plot decoded (used by the test suite's
# headless-browser check; harmless for a reader); the dossier of ``wara commission`` too.
PAGE_SCRIPT = """
window.addEventListener("load", function () {
  var bad = 0;
  for (var i = 0; i < document.images.length; i++) {
    var im = document.images[i];
    if (!(im.complete && im.naturalWidth > 0)) { bad++; }
  }
  document.body.setAttribute("data-report-check", bad === 0 ? "ok" : "broken-images:" + bad);
});
"""

_STATUS_CLASS = {
    Status.PASS: "pass",
    Status.FAIL: "fail",
    Status.NO_LIMIT: "nolimit",
    Status.NOT_MEASURED: "nm",
}


def render_html(summary: Summary, plots: dict[str, bytes], meta: ReportMeta) -> str:
    """The self-contained report page (plots embedded as base64 PNG)."""
    e = html.escape
    ov = summary.overall_dict()
    rng = f"rings {ov['first_ring']}–{ov['last_ring']}" if summary.rings else "no rings"
    parts: list[str] = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>Ring acceptance report: {e(meta.project)} ({e(rng)})</title>",
        f"<style>{PAGE_CSS}</style><script>{PAGE_SCRIPT}</script></head><body>",
        f"<h1>Ring acceptance report: {e(meta.project)}</h1>",
        f'<p class="meta">{e(rng)} · tolerances from {e(meta.config_source)} · '
        f"database {e(meta.database)} · generated {e(meta.generated_at)}</p>",
        "<h2>Overall</h2>",
        '<p class="big">'
        f"<strong>{ov['rings_passed']} of {ov['rings']} rings pass "
        f"({_pct(ov['ring_pass_rate'])})</strong>; "
        f"{ov['rings_failed']} fail"
        + (f" (rings {', '.join(map(str, ov['failed_rings']))})" if ov["failed_rings"] else "")
        + f"; {ov['rings_incomplete']} incomplete. "
        f"Item checks: {ov['checks_passed']} of {ov['checks_judged']} pass "
        f"({_pct(ov['check_pass_rate'])}).</p>",
        "<h2>Per control item</h2>",
        "<table><thead><tr><th class=l>control item</th><th>limit</th><th>judged</th>"
        "<th>pass</th><th>fail</th><th>not measured</th><th>pass rate</th>"
        "<th>max |value|</th><th class=l>rings over the limit</th></tr></thead><tbody>",
    ]
    for it in summary.items:
        unit = it.item.unit
        if it.limit is None:
            limit_cell = '<td class="nolimit">no limit set</td>'
            counts = '<td class="nolimit" colspan="4">not judged</td>'
            rate = '<td class="nolimit">–</td>'
        else:
            limit_cell = f"<td>{it.limit:g} {e(unit)}</td>"
            counts = (
                f"<td>{it.judged}</td><td>{it.passed}</td>"
                f'<td class="{"fail" if it.failed else ""}">{it.failed}</td>'
                f"<td>{it.not_measured}</td>"
            )
            rate = f"<td>{_pct(it.pass_rate)}</td>"
        max_abs = "" if it.max_abs is None else f"{it.max_abs:g} {unit}"
        parts.append(
            f"<tr><td class=l>{e(it.item.label)}</td>{limit_cell}{counts}{rate}"
            f"<td>{e(max_abs)}</td>"
            f"<td class=l>{e(', '.join(map(str, it.failed_rings)))}</td></tr>"
        )
    parts.append("</tbody></table>")
    parts.append("<h2>Plots</h2>")
    for it in summary.items:
        png = plots.get(it.item.key)
        if png is None:
            parts.append(f"<p class=nm>{e(it.item.label)}: no values recorded in this range.</p>")
            continue
        b64 = base64.b64encode(png).decode("ascii")
        parts.append(
            f'<figure id="plot-{e(it.item.key)}"><img alt="{e(it.item.label)} per ring" '
            f'src="data:image/png;base64,{b64}"></figure>'
        )
    parts.append("<h2>Per ring</h2>")
    head = "".join(f"<th>{e(it.item.label)}<br>({e(it.item.unit)})</th>" for it in summary.items)
    parts.append(
        '<div class="wide"><table><thead><tr><th>ring</th><th class=l>measured at</th>'
        f"{head}<th>verdict</th><th>plan</th><th class=l>operator</th>"
        "<th class=l>remarks</th></tr></thead><tbody>"
    )
    for r in summary.rings:
        m = r.record.measurement
        cells = []
        for it in summary.items:
            st = r.statuses[it.item.key]
            v = m.values[it.item.key]
            text = "–" if v is None else _num(v)
            cells.append(f'<td class="{_STATUS_CLASS[st]}" title="{e(str(st))}">{e(text)}</td>')
        vclass = {RingVerdict.PASS: "pass", RingVerdict.FAIL: "fail"}.get(r.verdict, "incomplete")
        parts.append(
            f"<tr><td>{r.ring}</td><td class=l>{e(m.measured_at)}</td>{''.join(cells)}"
            f'<td class="{vclass}">{e(str(r.verdict))}</td>'
            f"<td>{'yes' if r.has_plan else ''}</td>"
            f"<td class=l>{e(m.operator)}</td><td class=l>{e(m.remarks)}</td></tr>"
        )
    parts.append("</tbody></table></div>")
    parts.append(
        '<h2>How items are judged</h2><ul class="rules">'
        "<li>An item passes when |value| ≤ limit: a value exactly on the limit passes. "
        "Misalignments, centreline deviations and angles are signed and judged by "
        "magnitude; the gap between blocks is never negative.</li>"
        "<li>Items without a limit in the project configuration are recorded and "
        "shown as <span class=nolimit>no limit set</span>; they are never counted as "
        "passes and are left out of every pass rate.</li>"
        "<li>A ring passes when every item with a limit passes; a ring with an item "
        "over the limit fails; a ring missing a value for an item with a limit is "
        "incomplete.</li>"
        "<li>Each ring is judged on its current record (the last one recorded); "
        "earlier records stay in the database: <code>wara acceptance history RING</code>."
        "</li></ul>"
    )
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def report_dict(summary: Summary, meta: ReportMeta) -> dict[str, Any]:
    """The JSON summary: provenance, limits, overall, per item and per ring."""
    return {"meta": meta.to_dict(), **summary.to_dict()}


def write_report(summary: Summary, out_dir: str | Path, meta: ReportMeta) -> ReportFiles:
    """Write ``<item>.png`` per item with values, ``report.html`` and ``summary.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pngs: dict[str, bytes] = {}
    paths: dict[str, Path] = {}
    for it in summary.items:
        if it.measured == 0:
            continue
        pngs[it.item.key] = plot_item(summary, it)
        paths[it.item.key] = out / f"{it.item.key}.png"
        paths[it.item.key].write_bytes(pngs[it.item.key])
    html_path = out / HTML_NAME
    html_path.write_text(render_html(summary, pngs, meta), encoding="utf-8")
    json_path = out / JSON_NAME
    json_path.write_text(json.dumps(report_dict(summary, meta), indent=2) + "\n", "utf-8")
    return ReportFiles(html_path, json_path, paths)
