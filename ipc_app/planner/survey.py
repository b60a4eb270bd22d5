"""The as-built pose of a part from a survey of its front joint face (placement.md
section 3; docs/placement.md, "The survey file").

Format: UTF-8 CSV, one header row naming the columns (any order, case-insensitive),
blank lines and lines starting with ``#`` ignored, one point per line (a field may not
run over a line break):

- ``point``: the target's name on the face (unique in the file);
- ``face_y_m``, ``face_z_m``: where the target sits on the front joint face, in the
  part frame (y along the part's length from its centre, z up from its bottom face);
- ``x_m``, ``y_m``, ``z_m``: the point as the total station or laser tracker measured
  it, in the project frame of ``tunnel.alignment``.

At least :data:`MIN_POINTS` points, not all on one line. The fit is the least-squares
rigid pose (:func:`~ipc_app.model.placement.fit_pose`) of the part in its ring's tunnel
frame; it is refused when the RMS point residual is above
``placement.survey_max_residual_mm`` or the part lies further from its design pose than
:data:`PLAUSIBLE_DEVIATION_MM` (a survey of another ring, or another frame).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from config import units
from config.files import read_text_file
from config.schema import ProjectConfig
from ipc_app.model.placement import (
    Pose,
    compose,
    design_pose,
    deviation,
    fit_pose,
    inverse,
    tunnel_frame,
)

COLUMNS: tuple[str, ...] = ("point", "face_y_m", "face_z_m", "x_m", "y_m", "z_m")
MIN_POINTS = 4
#: Largest survey file read.
MAX_SURVEY_BYTES = 1024 * 1024
#: A fitted part further than this from its design across the axis (y, z), or more than
#: half a ring width along it, is not this ring's.
PLAUSIBLE_DEVIATION_MM = 50.0


class SurveyError(Exception):
    """The survey cannot be used: each line of the message is one problem (with the
    file's line number where a row is at fault)."""


@dataclass(frozen=True)
class SurveyPoint:
    line: int
    name: str
    face: tuple[float, float]  # part frame y, z (m)
    measured: tuple[float, float, float]  # project frame (m)


@dataclass(frozen=True)
class SurveyFit:
    ring: int
    pose: Pose  # in the ring's own tunnel frame
    deviation: Pose  # from the ring's design pose
    points: tuple[SurveyPoint, ...]
    residuals_m: tuple[float, ...]
    rms_residual_m: float
    accepted: bool
    reasons: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "ring": self.ring,
            "accepted": self.accepted,
            "as_built_pose": self.pose.to_dict(),
            "deviation": self.deviation.to_dict(),
            "points": len(self.points),
            "rms_residual_mm": units.to_mm(self.rms_residual_m),
            "max_residual_mm": units.to_mm(max(self.residuals_m)),
            "residuals_mm": {
                f"line {p.line} ({p.name})": units.to_mm(r)
                for p, r in zip(self.points, self.residuals_m, strict=True)
            },
            "reasons": list(self.reasons),
        }


def _number(text: str, column: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{column}: {text.strip()!r} is not a number") from None
    if not math.isfinite(v) or "_" in text:
        raise ValueError(f"{column}: {text.strip()!r} is not a finite number")
    return v


def parse_survey_text(text: str, source: str = "<survey>") -> list[SurveyPoint]:
    """The points of a survey CSV; SurveyError lists every bad line."""
    rows = csv.reader(io.StringIO(text.lstrip("\ufeff"), newline=""))
    header: list[str] | None = None
    points: list[SurveyPoint] = []
    errors: list[str] = []
    seen: dict[str, int] = {}
    prev_end = 0
    try:
        for cells in rows:
            line = rows.line_num
            start, prev_end = prev_end + 1, line
            if any("\n" in c or "\r" in c for c in cells):
                errors.append(
                    f"{source}: line {start}: a field runs over a line break (a quote left open?)"
                )
                continue
            if not cells or all(not c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
                continue
            if header is None:
                header = [c.strip().lower() for c in cells]
                bad = [n for n in header if n not in COLUMNS]
                missing = [c for c in COLUMNS if c not in header]
                twice = sorted({n for n in header if header.count(n) > 1})
                probs = []
                if bad:
                    probs.append(f"unknown column(s) {', '.join(map(repr, bad))}")
                if missing:
                    probs.append(f"missing column(s) {', '.join(missing)}")
                if twice:
                    probs.append(f"column(s) named twice: {', '.join(twice)}")
                if probs:
                    raise SurveyError(
                        f"{source}: header on line {line}: {'; '.join(probs)} "
                        f"(expected columns: {', '.join(COLUMNS)})"
                    )
                continue
            if len(cells) != len(header):
                errors.append(f"{source}: line {line}: {len(cells)} cells, expected {len(header)}")
                continue
            row = dict(zip(header, cells, strict=True))
            name = row["point"].strip()
            try:
                if not name:
                    raise ValueError("point: empty name")
                vals = {c: _number(row[c], c) for c in COLUMNS[1:]}
            except ValueError as exc:
                errors.append(f"{source}: line {line}: {exc}")
                continue
            if name in seen:
                errors.append(
                    f"{source}: line {line}: point {name!r} again (first on line {seen[name]})"
                )
                continue
            seen[name] = line
            points.append(
                SurveyPoint(
                    line,
                    name,
                    (vals["face_y_m"], vals["face_z_m"]),
                    (vals["x_m"], vals["y_m"], vals["z_m"]),
                )
            )
    except csv.Error as exc:
        errors.append(f"{source}: line {rows.line_num}: {exc}")
    if header is None and not errors:
        raise SurveyError(f"{source}: no header row (expected columns: {', '.join(COLUMNS)})")
    if errors:
        raise SurveyError("\n".join(errors))
    if len(points) < MIN_POINTS:
        raise SurveyError(f"{source}: {len(points)} point(s); the fit needs at least {MIN_POINTS}")
    return points


def fit_survey(cfg: ProjectConfig, ring: int, points: list[SurveyPoint]) -> SurveyFit:
    """The as-built pose of ring ``ring``'s part from points on its front joint face."""
    if cfg.placement is None:
        raise ValueError("the project has no placement section")
    half = cfg.workpiece.width_m / 2.0
    nominal = np.array([[half, p.face[0], p.face[1]] for p in points])
    world = np.array([p.measured for p in points])
    local = inverse(tunnel_frame(cfg, ring)).apply(world)
    try:
        fit = fit_pose(nominal, local)
    except ValueError as exc:
        raise SurveyError(f"survey: {exc} (face_y_m, face_z_m of the points)") from None
    dev = deviation(fit.pose, design_pose(cfg, ring))
    reasons: list[str] = []
    limit = cfg.placement.survey_max_residual_m
    if fit.rms_residual_m > limit:
        worst = int(np.argmax(fit.residuals_m))
        reasons.append(
            f"RMS residual {units.to_mm(fit.rms_residual_m):.2f} mm above "
            f"placement.survey_max_residual_mm {cfg.placement.survey_max_residual_mm:g}; "
            f"worst line {points[worst].line} ({points[worst].name}): "
            f"{units.to_mm(float(fit.residuals_m[worst])):.2f} mm"
        )
    off = units.to_mm(math.hypot(dev.y, dev.z))
    along = abs(dev.x)
    if off > PLAUSIBLE_DEVIATION_MM or along > cfg.tunnel.ring_width_m / 2.0:
        reasons.append(
            f"the fitted part is {off:.0f} mm across and {units.to_mm(along):.0f} mm along "
            f"the axis off its design position in ring {ring} (limits "
            f"{PLAUSIBLE_DEVIATION_MM:g} mm across, half a ring along: another ring's "
            "survey, or another frame?)"
        )
    return SurveyFit(
        ring,
        fit.pose,
        dev,
        tuple(points),
        tuple(float(r) for r in fit.residuals_m),
        fit.rms_residual_m,
        not reasons,
        tuple(reasons),
    )


def read_survey(cfg: ProjectConfig, ring: int, path: str | Path) -> SurveyFit:
    text = read_text_file(path, MAX_SURVEY_BYTES)
    return fit_survey(cfg, ring, parse_survey_text(text, str(path)))


def format_survey(
    cfg: ProjectConfig, ring: int, pose: Pose, faces: list[tuple[float, float]]
) -> str:
    """A survey CSV of ``faces`` (part-frame y, z) on ring ``ring``'s part at ``pose``
    (the example file, tests and the simulator's survey)."""
    half = cfg.workpiece.width_m / 2.0
    local = pose.apply(np.array([[half, fy, fz] for fy, fz in faces]))
    world = compose(tunnel_frame(cfg, ring), Pose()).apply(local)
    out = [",".join(COLUMNS)]
    for i, ((fy, fz), p) in enumerate(zip(faces, world, strict=True), start=1):
        out.append(f"P{i},{fy:.4f},{fz:.4f},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f}")
    return "\n".join(out) + "\n"
