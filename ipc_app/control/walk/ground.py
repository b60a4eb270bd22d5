"""Where a lowering foot should meet the invert (docs/walking.md, "The expected ground").

A frame's feet leave the invert when it lifts and meet it again some 2 m further on,
after the other frame carried the machine alone through a travel. Meanwhile the body
moves against the invert: the standing legs' oil columns and the invert under them give
as the load moves over them (the COG travels with the advancing frame), and the body
heaves and tilts by millimetres at the feet. The lowering frame's window
(``walking.touchdown_travel_mm``) is meant for the invert's own steps (Table 4's 8 mm),
not for that; so the expected ground follows the body.

The invert is a plane in the lower platform's frame, measured by the standing frame's
four feet: each foot's tip is ``-(L + x)`` below the body (``x`` its rod, ``L`` the leg's
length at zero extension, the same for the four legs of a frame), and the invert's
surface lies ``F / k`` above the tip (``F`` its force, ``k`` the invert's stiffness,
``walking.contact.stiffness_n_m``). The plane's change between a frame's lift and its
lowering, at a lowering foot, moves that foot's expected touch from where it left the
invert (its rod then, less its own ``F / k``); ``L`` cancels. A standing frame does not
move over the invert, so the same four feet measure both planes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def invert_plane(points_xy: FloatArray, surface_z_m: FloatArray) -> FloatArray:
    """``(c, a, b)`` of the least-squares plane ``z = c + a x + b y`` through four feet
    (their twist, which a plane cannot follow, left out)."""
    a = np.column_stack([np.ones(len(points_xy)), points_xy])
    coef, *_ = np.linalg.lstsq(a, surface_z_m, rcond=None)
    return np.asarray(coef, dtype=np.float64)


def surface_z_m(rods_m: FloatArray, forces_n: FloatArray, stiffness_n_m: float) -> FloatArray:
    """The invert's surface under standing feet in the body's z, less the legs' common
    length: ``-x + F / k``."""
    return -np.asarray(rods_m, dtype=float) + np.asarray(forces_n, dtype=float) / stiffness_n_m


@dataclass(frozen=True)
class LiftMark:
    """A frame's lift: the invert's plane then, and where its feet left it."""

    #: the plane ``(c, a, b)`` the standing frame measured at the lift
    plane: FloatArray
    #: the lifting legs' rods at the lift's start less their feet's ``F / k``, m: each
    #: rod where its foot meets the unloaded invert
    touch_rods_m: FloatArray

    def touch_rods_now(
        self, standing_xy: FloatArray, surface_now_z_m: FloatArray, lowering_xy: FloatArray
    ) -> FloatArray:
        """The lowering legs' rods, m, where their feet meet the invert now: where they
        left it, less the plane's rise under them since (a rise meets the foot sooner)."""
        now = invert_plane(standing_xy, surface_now_z_m)
        basis = np.column_stack([np.ones(len(lowering_xy)), lowering_xy])
        rise = basis @ (now - self.plane)
        return np.asarray(self.touch_rods_m - rise, dtype=np.float64)
