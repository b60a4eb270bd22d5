"""The design axis by chainage (curves.md section 1; docs/curves.md): the horizontal
alignment's point and heading and the vertical alignment's level and grade at a
chainage, the chainage a distance along the axis further, and the invert's rise under
the machine (what the simulator's feet stand on).

:func:`ipc_app.model.placement.axis_pose` is the one place that turns these into the
tunnel frame; this module holds the elements' formulas it uses for an alignment given
by chainage (``tunnel.alignment.horizontal`` and ``vertical``).

Chainage is measured in plan, as the designers' drawings give it: the horizontal
elements' lengths are chainage differences, and a grade ``g`` is ``dz / d(chainage)``.
The axis's own length from chainage ``c_0`` to ``c`` is ``int sqrt(1 + g^2) dc``
(:func:`along_axis_m`); rings are laid along it (:func:`chainage_after`).

Horizontal elements (heading ``theta`` from the project's +x toward +y, curvature
``k = dtheta / ds``, positive turning left):

- straight: ``k = 0``; arc: ``k = 1 / radius_m`` (signed);
- clothoid: ``k`` linear from the element before's curvature to the element after's over
  its length ``A^2 |k_1 - k_0|`` (the schema checks that length); its point is the
  integral of ``(cos theta, sin theta)``, by 16-point Gauss-Legendre quadrature (the
  integrand is smooth: the error is far below a micrometre for any clothoid the
  schema admits).

Vertical elements: a grade ``g``; a vertical curve between grades ``g_0`` and ``g_1``
whose grade changes linearly over its length ``R |g_1 - g_0|``. Before the first element
each alignment goes straight on backwards (the start heading, the first grade); the last
element goes on.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from config.schema import Alignment, AlignmentPoint, HorizontalAlignment, VerticalAlignment

FloatArray = NDArray[np.float64]

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(16)


class PlanPoint(NamedTuple):
    """The axis in plan at a chainage: point (m) and heading (rad)."""

    x: float
    y: float
    heading: float


class Level(NamedTuple):
    """The axis's level (m) and grade (dz / d(chainage)) at a chainage."""

    z: float
    grade: float


def _curvatures(h: HorizontalAlignment) -> list[tuple[float, float]]:
    """Each element's curvature at its start and its end (1/m)."""
    el = h.elements
    out = []
    for i, e in enumerate(el):
        if e.kind == "clothoid":
            out.append((el[i - 1].curvature_per_m, el[i + 1].curvature_per_m))
        else:
            out.append((e.curvature_per_m, e.curvature_per_m))
    return out


def _advance(p: PlanPoint, k0: float, k1: float, length: float, u: float) -> PlanPoint:
    """``u`` along an element of ``length`` whose curvature goes from ``k0`` to ``k1``."""
    if k0 == k1 == 0.0:
        return PlanPoint(p.x + u * math.cos(p.heading), p.y + u * math.sin(p.heading), p.heading)
    if k0 == k1:
        th = p.heading + k0 * u
        return PlanPoint(
            p.x + (math.sin(th) - math.sin(p.heading)) / k0,
            p.y - (math.cos(th) - math.cos(p.heading)) / k0,
            th,
        )
    rate = (k1 - k0) / length

    s = 0.5 * u * (_NODES + 1.0)
    ths = p.heading + k0 * s + 0.5 * rate * s * s
    dx = 0.5 * u * float(np.sum(_WEIGHTS * np.cos(ths)))
    dy = 0.5 * u * float(np.sum(_WEIGHTS * np.sin(ths)))
    return PlanPoint(p.x + dx, p.y + dy, p.heading + k0 * u + 0.5 * rate * u * u)


def plan_point(h: HorizontalAlignment, chainage_m: float) -> PlanPoint:
    """The horizontal alignment's point and heading at ``chainage_m``."""
    el = h.elements
    p = PlanPoint(h.x_m, h.y_m, math.radians(h.heading_deg))
    if chainage_m <= el[0].start_chainage_m:
        return _advance(p, 0.0, 0.0, 1.0, chainage_m - el[0].start_chainage_m)
    ks = _curvatures(h)
    for i, e in enumerate(el):
        last = i == len(el) - 1
        end = math.inf if last else el[i + 1].start_chainage_m
        length = end - e.start_chainage_m
        k0, k1 = ks[i]
        if chainage_m <= end:
            return _advance(p, k0, k1, length, chainage_m - e.start_chainage_m)
        p = _advance(p, k0, k1, length, length)
    raise AssertionError("unreachable: the last element goes on")


def _grades(v: VerticalAlignment) -> list[tuple[float, float]]:
    """Each element's grade at its start and its end (dz / d(chainage))."""
    el = v.elements
    out = []
    for i, e in enumerate(el):
        if e.radius_m is not None:
            g0, g1 = el[i - 1].gradient_percent or 0.0, el[i + 1].gradient_percent or 0.0
            out.append((g0 / 100.0, g1 / 100.0))
        else:
            g = (e.gradient_percent or 0.0) / 100.0
            out.append((g, g))
    return out


def level(v: VerticalAlignment, chainage_m: float) -> Level:
    """The vertical alignment's level and grade at ``chainage_m``."""
    el = v.elements
    gs = _grades(v)
    z = v.z_m
    if chainage_m <= el[0].start_chainage_m:
        g = gs[0][0]
        return Level(z + g * (chainage_m - el[0].start_chainage_m), g)
    for i, e in enumerate(el):
        end = math.inf if i == len(el) - 1 else el[i + 1].start_chainage_m
        g0, g1 = gs[i]
        length = end - e.start_chainage_m
        u = min(chainage_m, end) - e.start_chainage_m
        rate = 0.0 if g0 == g1 else (g1 - g0) / length
        if chainage_m <= end:
            return Level(z + g0 * u + 0.5 * rate * u * u, g0 + rate * u)
        z += g0 * u + 0.5 * rate * u * u
    raise AssertionError("unreachable: the last element goes on")


def along_axis_m(v: VerticalAlignment, c0: float, c1: float) -> float:
    """The axis's length from chainage ``c0`` to ``c1`` (negative if ``c1 < c0``):
    ``int sqrt(1 + g^2) dc``, piece by piece between the vertical elements' starts (the
    grade is linear on each: quadrature is exact to far below a micrometre)."""
    if c1 < c0:
        return -along_axis_m(v, c1, c0)
    cuts = [c0, *(e.start_chainage_m for e in v.elements if c0 < e.start_chainage_m < c1), c1]
    total = 0.0
    for a, b in itertools.pairwise(cuts):
        s = a + 0.5 * (b - a) * (_NODES + 1.0)
        g = np.array([level(v, float(c)).grade for c in s])
        total += 0.5 * (b - a) * float(np.sum(_WEIGHTS * np.sqrt(1.0 + g * g)))
    return total


def chainage_after(v: VerticalAlignment, chainage_m: float, along_m: float) -> float:
    """The chainage ``along_m`` further along the axis (its length, grades included) than
    ``chainage_m``: Newton's method on :func:`along_axis_m` (converges in a few steps:
    ``sqrt(1 + g^2)`` is within 0.5 % of 1 on the grades the schema admits)."""
    c = chainage_m + along_m
    for _ in range(20):
        err = along_m - along_axis_m(v, chainage_m, c)
        if abs(err) < 1e-9:
            break
        g = level(v, c).grade
        c += err / math.sqrt(1.0 + g * g)
    return c


# ------------------------------------------------------ the invert under the machine


def start_chainage_m(alignment: Alignment | None) -> float:
    """M's centre's chainage where the machine starts: ring 1's rear joint face (its
    commissioning place; the walk's steering and the simulator's invert start there), 0
    without an alignment."""
    return 0.0 if alignment is None else alignment.first_ring_chainage_m


def table_segment(points: Sequence[AlignmentPoint], chainage_m: Any) -> tuple[Any, Any]:
    """A design-axis table's segment at ``chainage_m`` (a number or an array): the index
    of its first row and how far along it (0 to 1 within it; beyond the table's ends the
    end segments go on)."""
    ch = np.array([p.chainage_m for p in points])
    i = np.clip(np.searchsorted(ch, chainage_m) - 1, 0, len(ch) - 2)
    return i, (chainage_m - ch[i]) / (ch[i + 1] - ch[i])


def _levels(alignment: Alignment, chainage_m: FloatArray) -> FloatArray:
    """The axis's level (m) at each chainage: the vertical elements', a table's rows'
    (linear between them, the end segments going on), a straight grade's."""
    if alignment.vertical is not None:
        v = alignment.vertical
        return np.array([level(v, float(c)).z for c in chainage_m])
    if alignment.points:
        z = np.array([p.z_m for p in alignment.points])
        i, f = table_segment(alignment.points, chainage_m)
        return np.asarray(z[i] + f * (z[i + 1] - z[i]), dtype=np.float64)
    g = (alignment.gradient_percent or 0.0) / 100.0
    return np.asarray(chainage_m * g, dtype=np.float64)


def invert_rise_m(alignment: Alignment | None, along_m: FloatArray) -> FloatArray:
    """The invert's rise (m, normal to it) at ``along_m`` (m) from the machine's start
    (:func:`start_chainage_m`) along its heading there, above the plane of the axis's
    grade at the start: 0 on a straight grade, ``x^2 / (2 R)`` on a vertical curve of
    radius ``R`` (curves.md section 3: the invert under each frame follows the axis's
    grade at its chainage). First order in the horizontal curve (the machine's few metres
    of a curve of hundreds are taken as along the axis)."""
    x = np.asarray(along_m, dtype=np.float64)
    if alignment is None:
        return np.zeros_like(x)
    c0 = start_chainage_m(alignment)
    eps = 1e-3
    z0, z1 = _levels(alignment, np.array([c0 - eps, c0 + eps]))
    grade = (z1 - z0) / (2.0 * eps)
    cos_a = 1.0 / math.sqrt(1.0 + grade * grade)
    run = x * cos_a  # in plan
    z = _levels(alignment, c0 + run) - _levels(alignment, np.array([c0]))[0]
    return np.asarray((z - grade * run) * cos_a, dtype=np.float64)
