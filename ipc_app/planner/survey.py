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

At least :data:`MIN_POINTS` points, not all on one line. A point's name is 1..
:data:`MAX_NAME_CHARS` printable characters (no control or format characters: names are
printed); ``face_y_m`` and ``face_z_m`` lie within the configuration's coordinate range
(``CoordM``, -100..100 m), ``x_m``, ``y_m``, ``z_m`` within the range of
``tunnel.alignment``'s points (:data:`MEASURED_RANGE_M`). The file is read by
:func:`read_survey_points` (``wara survey import``, ``wara place plan --survey`` and
``wara ctl survey`` alike): a regular UTF-8 file of at most :data:`MAX_SURVEY_BYTES`.

The fit is the least-squares rigid pose (:func:`~ipc_app.model.placement.fit_pose`) of
the part in its ring's tunnel frame; it is refused when the RMS point residual is above
``placement.survey_max_residual_mm`` (or not a finite number) or the pose is not a
plausible as-built pose of the ring (:func:`as_built_problems`: further from its design
than :data:`PLAUSIBLE_DEVIATION_MM` across, half a ring along or
:data:`PLAUSIBLE_ANGLE_DEG` in an angle, or not finite: a survey of another ring, or
another frame). The same check holds for a pose given instead of a survey (the
acceptance store's, ``wara ctl survey --from-store``, and a cycle's previous part).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from config import numbers, units
from config.files import InputFileError, read_text_file
from config.schema import AlignmentPoint, CoordM, ProjectConfig
from ipc_app.model.placement import (
    Pose,
    compose,
    design_pose,
    deviation,
    face_points,
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
#: ... nor one turned further than this from its design in roll, pitch or yaw (the
#: bound of a deviation as a survey sheet gives it, ``--previous-deviation``).
PLAUSIBLE_ANGLE_DEG = 10.0
#: The longest point name (as the control channel's names).
MAX_NAME_CHARS = 40
#: At most this many bad lines are listed (then how many more there are).
MAX_ERRORS_LISTED = 20


def _field_range(annotated: Any) -> tuple[float, float]:
    """The ``ge``/``le`` bounds a schema type or field states (one source of the ranges)."""
    metadata = getattr(annotated, "metadata", None)
    if metadata is None:  # an Annotated type: its FieldInfo parts
        metadata = [m for f in getattr(annotated, "__metadata__", ()) for m in f.metadata]
    lo = next(m.ge for m in metadata if hasattr(m, "ge"))
    hi = next(m.le for m in metadata if hasattr(m, "le"))
    return float(lo), float(hi)


#: Where a target may sit on the face (part frame, m): the configuration's coordinates.
FACE_RANGE_M = _field_range(CoordM)
#: Where a measured point may lie (project frame, m): ``tunnel.alignment``'s points' range.
MEASURED_RANGE_M: dict[str, tuple[float, float]] = {
    c: _field_range(AlignmentPoint.model_fields[c]) for c in ("x_m", "y_m", "z_m")
}
_RANGES: dict[str, tuple[float, float]] = {
    "face_y_m": FACE_RANGE_M,
    "face_z_m": FACE_RANGE_M,
    **MEASURED_RANGE_M,
}


class SurveyError(Exception):
    """The survey cannot be used: each line of the message is one problem (with the
    file's line number where a row is at fault)."""


def check_name(name: str) -> str:
    """A point's name, or ValueError: a name of 1..MAX_NAME_CHARS characters
    (:func:`config.numbers.check_name`: no control, format or line-break character)."""
    return numbers.check_name(name, "point: name", MAX_NAME_CHARS)


def check_coordinate(column: str, value: float) -> float:
    """A point's coordinate, or ValueError naming the column: finite, in its range."""
    lo, hi = _RANGES[column]
    if not math.isfinite(value):
        raise ValueError(f"{column}: {value!r} is not a finite number")
    if not lo <= value <= hi:
        raise ValueError(f"{column}: {value:g} m is outside {lo:g}..{hi:g} m")
    return value


@dataclass(frozen=True)
class SurveyPoint:
    """One surveyed target; construction checks it (ValueError with the reason): the
    name (:func:`check_name`) and each coordinate (:func:`check_coordinate`)."""

    line: int
    name: str
    face: tuple[float, float]  # part frame y, z (m)
    measured: tuple[float, float, float]  # project frame (m)

    def __post_init__(self) -> None:
        check_name(self.name)
        for column, v in zip(COLUMNS[1:], (*self.face, *self.measured), strict=True):
            check_coordinate(column, v)


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
    """A cell in the one decimal syntax (:func:`config.numbers.parse_decimal`), in range."""
    try:
        v = numbers.parse_decimal(text.strip())
    except ValueError as exc:
        raise ValueError(f"{column}: {exc}") from None
    return check_coordinate(column, v)


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
                check_name(name)
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
    if len(errors) > MAX_ERRORS_LISTED:
        more = len(errors) - MAX_ERRORS_LISTED
        errors = [*errors[:MAX_ERRORS_LISTED], f"{source}: {more} more bad line(s) not listed"]
    if errors:
        raise SurveyError("\n".join(errors))
    if len(points) < MIN_POINTS:
        raise SurveyError(f"{source}: {len(points)} point(s); the fit needs at least {MIN_POINTS}")
    return points


def _brief(v: float) -> str:
    """A figure for a message: whole units, or three digits when it is huge."""
    return f"{v:.0f}" if abs(v) < 1e6 else f"{v:.3g}"


def as_built_problems(cfg: ProjectConfig, ring: int, pose: Pose) -> list[str]:
    """Why ``pose`` (in ring ``ring``'s own tunnel frame) is not a plausible as-built pose
    of that ring's part (empty: it is): not finite, or further from the ring's design
    than :data:`PLAUSIBLE_DEVIATION_MM` across the axis, half a ring along it or
    :data:`PLAUSIBLE_ANGLE_DEG` in roll, pitch or yaw. One check for a fitted survey, a
    pose from the acceptance store and a cycle's previous part."""
    if not all(math.isfinite(v) for v in pose):
        return [f"the pose of ring {ring}'s part is not finite: {pose.to_dict()}"]
    dev = deviation(pose, design_pose(cfg, ring))
    if not all(math.isfinite(v) for v in dev):
        return [f"the pose of ring {ring}'s part is not finite: {pose.to_dict()}"]
    off = units.to_mm(math.hypot(dev.y, dev.z))
    along = abs(dev.x)
    out: list[str] = []
    if off > PLAUSIBLE_DEVIATION_MM or along > cfg.tunnel.ring_width_m / 2.0:
        out.append(
            f"the part is {_brief(off)} mm across and {_brief(units.to_mm(along))} mm along "
            f"the axis off its design position in ring {ring} (limits "
            f"{PLAUSIBLE_DEVIATION_MM:g} mm across, half a ring along: another ring's "
            "survey, or another frame?)"
        )
    angles = {"roll": dev.roll, "pitch": dev.pitch, "yaw": dev.yaw}
    turned = {k: units.to_deg(v) for k, v in angles.items()}
    turned = {k: v for k, v in turned.items() if abs(v) > PLAUSIBLE_ANGLE_DEG}
    if turned:
        out.append(
            "the part is turned "
            + ", ".join(f"{k} {v:+.1f} deg" for k, v in turned.items())
            + f" from its design in ring {ring} (limit {PLAUSIBLE_ANGLE_DEG:g} deg: "
            "another ring's survey, or another frame?)"
        )
    return out


def fit_survey(cfg: ProjectConfig, ring: int, points: list[SurveyPoint]) -> SurveyFit:
    """The as-built pose of ring ``ring``'s part from points on its front joint face
    (each point checked as it is built: :class:`SurveyPoint`)."""
    if cfg.placement is None:
        raise ValueError("the project has no placement section")
    nominal = face_points(cfg, [p.face for p in points])
    world = np.array([p.measured for p in points])
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            local = inverse(tunnel_frame(cfg, ring)).apply(world)
            fit = fit_pose(nominal, local)
    except FloatingPointError as exc:  # not with coordinates in their ranges; if ever
        raise SurveyError(f"survey: the fit failed numerically ({exc})") from None
    except ValueError as exc:
        raise SurveyError(f"survey: {exc} (face_y_m, face_z_m of the points)") from None
    reasons: list[str] = []
    limit = cfg.placement.survey_max_residual_m
    if not fit.rms_residual_m <= limit:  # NaN too
        worst = int(np.nanargmax(fit.residuals_m)) if np.isfinite(fit.residuals_m).any() else 0
        reasons.append(
            f"RMS residual {units.to_mm(fit.rms_residual_m):.2f} mm above "
            f"placement.survey_max_residual_mm {cfg.placement.survey_max_residual_mm:g}; "
            f"worst line {points[worst].line} ({points[worst].name}): "
            f"{units.to_mm(float(fit.residuals_m[worst])):.2f} mm"
        )
    reasons += [f"the fitted pose: {r}" for r in as_built_problems(cfg, ring, fit.pose)]
    return SurveyFit(
        ring,
        fit.pose,
        deviation(fit.pose, design_pose(cfg, ring)),
        tuple(points),
        tuple(float(r) for r in fit.residuals_m),
        fit.rms_residual_m,
        not reasons,
        tuple(reasons),
    )


def read_survey_points(path: str | Path) -> list[SurveyPoint]:
    """The points of the survey file ``path``: the one reader of survey files (``wara
    survey import``, ``wara place plan --survey``, ``wara ctl survey``). The file is
    opened as :func:`config.files.read_text_file` opens it (a regular file, at most
    :data:`MAX_SURVEY_BYTES`, UTF-8: a FIFO, a device or a directory is refused before
    it is read); every problem is a :class:`SurveyError`, one line each."""
    try:
        text = read_text_file(path, MAX_SURVEY_BYTES, hint="export the survey as 'CSV UTF-8'")
    except InputFileError as exc:
        raise SurveyError(str(exc)) from None
    return parse_survey_text(text, str(path))


def read_survey(cfg: ProjectConfig, ring: int, path: str | Path) -> SurveyFit:
    """:func:`read_survey_points` fitted (:func:`fit_survey`)."""
    return fit_survey(cfg, ring, read_survey_points(path))


def format_survey(
    cfg: ProjectConfig, ring: int, pose: Pose, faces: list[tuple[float, float]]
) -> str:
    """A survey CSV of ``faces`` (part-frame y, z) on ring ``ring``'s part at ``pose``
    (the example file, tests and the simulator's survey)."""
    local = pose.apply(face_points(cfg, faces))
    world = compose(tunnel_frame(cfg, ring), Pose()).apply(local)
    out = [",".join(COLUMNS)]
    for i, ((fy, fz), p) in enumerate(zip(faces, world, strict=True), start=1):
        out.append(f"P{i},{fy:.4f},{fz:.4f},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f}")
    return "\n".join(out) + "\n"
