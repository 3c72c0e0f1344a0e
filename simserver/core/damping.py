"""Auxiliary damping of the tire forces near zero speed (paper, Appendix A).

Without it a stopped car oscillates, lightly damped, on its tire springs (the paper's
Example 1: about 3.5 Hz fore-aft). Two forms are selectable (``DAMPING_*``):

``DAMPING_PAPER`` -- exactly Appendix A (docs/model.md section 4). Per wheel, triggered when the
hub's longitudinal speed ``u`` changes sign while ``|v| < eps`` (0.15 m/s). The wheel is
treated as a one-degree-of-freedom system of mass ``m_i = Fz_i / g`` on the tire spring
(stiffness ``C_kappa/B`` fore-aft, ``C_alpha/b`` sideways), critically damped to
``zeta`` (0.7): ``c_x = 2 zeta m_i w_x`` with ``w_x = sqrt(C_kappa / (B m_i))``, likewise
``c_y``; the forces become ``Fx -= c_x u``, ``Fy -= c_y v``.
Release rule (the paper gives none; docs/model.md section 4b item 3): the damping of a wheel
ends when the driver stops braking (brake pedal below ``PEDAL_RELEASED`` and parking
brake off) or presses the throttle above ``PEDAL_RELEASED``. Left on it would hold a
restart back (c_x is about 15.7 kN s/m per wheel on the paper's car); a car that is not
being braked has no business being held by a hub damper.

``DAMPING_PATCH`` (default) -- the same coefficients applied to the rate of the
contact-patch deflection instead of the hub velocity: ``Fx += c_x B dk'/dt``,
``Fy -= c_y b d(tan a')/dt``. At standstill (``Omega = 0``, small ``u``) this equals the
paper's ``-c_x u``, ``-c_y v``; in steady rolling the deflection rate is zero, so it never
drags on a car that is driving away and needs no trigger or release rule. Because the
deflection rate contains ``R Omega`` it also damps the wheel-spin / tire mode that rings
when the brakes let go at standstill (docs/model.md section 4b item 2). It fades out with hub
speed as MF-Tyre's low-speed damping does (cosine over ``0 .. v_fade``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.variants import Variant, VariantRegistry

DAMPING_OFF = 0
DAMPING_PAPER = 1
DAMPING_PATCH = 2
DAMPING_MODELS = VariantRegistry("damping model", (
    Variant(DAMPING_OFF, "off", "no auxiliary low-speed damping"),
    Variant(DAMPING_PAPER, "paper",
            "Appendix A: hub-velocity damping, latched on a sign change of u"),
    Variant(DAMPING_PATCH, "patch",
            "the same coefficients on the contact-patch deflection rate, fading with speed "
            "(default)"),
))
DAMPING_MODEL_NAMES = DAMPING_MODELS.names

PAPER_TRIGGER_LATERAL_SPEED_MPS = 0.15
"""eps of Appendix A: the trigger needs |v| below this."""
PAPER_DAMPING_RATIO = 0.7
"""zeta of Appendix A."""
PEDAL_RELEASED = 0.02
"""A pedal below this counts as released (sensor noise of a real pedal is about 1 %)."""


@nb.njit(cache=True)
def damping_coefficients(
    fz_n: float,
    c_kappa: float,
    c_alpha: float,
    relax_long_m: float,
    relax_lat_m: float,
    zeta: float,
    gravity_mps2: float,
) -> tuple[float, float]:
    """Appendix A coefficients ``(c_x, c_y)`` in N s/m for one wheel.

    ``c = 2 zeta m w = 2 zeta sqrt(m k)`` with ``m = Fz/g`` and ``k = C/relaxation
    length`` (the stopped tire's spring stiffness, docs/model.md section 3 property 3).
    """
    if fz_n <= 0.0:
        return 0.0, 0.0
    mass = fz_n / gravity_mps2
    c_x = 2.0 * zeta * np.sqrt(mass * c_kappa / relax_long_m)
    c_y = 2.0 * zeta * np.sqrt(mass * c_alpha / relax_lat_m)
    return c_x, c_y


@nb.njit(cache=True)
def paper_trigger(u_prev_mps: float, u_mps: float, v_mps: float, eps_mps: float) -> bool:
    """Appendix A trigger: ``u`` changed sign over the last step while ``|v| < eps``."""
    crossed = (u_prev_mps > 0.0 and u_mps <= 0.0) or (u_prev_mps < 0.0 and u_mps >= 0.0)
    return crossed and abs(v_mps) < eps_mps


@nb.njit(cache=True)
def paper_release(brake_pedal: float, parking_brake: float, throttle: float) -> bool:
    """The release rule of this project (see the module docstring)."""
    not_braking = brake_pedal < PEDAL_RELEASED and parking_brake < 0.5
    return not_braking or throttle > PEDAL_RELEASED


@nb.njit(cache=True)
def low_speed_fade(hub_speed_mps: float, fade_speed_mps: float) -> float:
    """1 at standstill, 0 from ``fade_speed`` up, a half cosine between (C1 at both ends)."""
    if hub_speed_mps >= fade_speed_mps:
        return 0.0
    return 0.5 * (1.0 + np.cos(np.pi * hub_speed_mps / fade_speed_mps))
