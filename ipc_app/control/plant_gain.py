"""The LADRC input gain ``b0`` of a valve-controlled cylinder, from the configuration.

First order (``x' = f + b0 u``, the command sets the rod speed):
``b0 = K_q / A_A`` with ``K_q = C_d w x_v,max sqrt((p_s - p_T) / rho)`` the valve's
flow per unit normalized command at the no-load pressure drop
(:func:`config.derived.valve_flow_gain_m3_s`) and ``A_A`` the cap area; in m/s per
unit command. Loads, leakage, the other edge's pressure drop and the rod-side area on
retraction make the true gain differ; the observer takes the difference as part of
the total disturbance.

Second order (``x'' = f + b0 u``): the hydraulic mode ``1 / (s^2/w_h^2 + 2 zeta s/w_h + 1)``
between command and speed is reduced to its low-frequency lag ``1 / (1 + 2 zeta s / w_h)``,
giving ``b0 = (K_q / A_A) w_h / (2 zeta)`` with ``w_h`` at mid-stroke
(:func:`config.derived.hydraulic_natural_frequency_rad_s`).
"""

from __future__ import annotations

from config.derived import hydraulic_natural_frequency_rad_s, valve_flow_gain_m3_s
from config.schema import Cylinder, CylinderPlant, Hydraulics


def cylinder_b0(
    cylinder: Cylinder,
    hydraulics: Hydraulics,
    plant: CylinderPlant | None = None,
    order: int = 1,
) -> float:
    """``b0`` for a LADRC of ``order`` 1 or 2 on this cylinder (see the module doc).

    ``plant`` defaults to the cylinder's own, else the hydraulics' ``cylinder_defaults``.
    """
    p = plant or cylinder.plant or hydraulics.cylinder_defaults
    b1 = valve_flow_gain_m3_s(hydraulics, p) / cylinder.cap_area_m2
    if order == 1:
        return b1
    if order == 2:
        w_h = hydraulic_natural_frequency_rad_s(cylinder, p, hydraulics)
        return b1 * w_h / (2.0 * max(p.damping_ratio, 1e-3))
    raise ValueError(f"order must be 1 or 2, got {order}")
