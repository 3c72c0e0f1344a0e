"""A simple combined-slip tire: brush (Fiala) shape with explicit stiffnesses and friction.

The paper paired its lagged slip states with the STI tire model (its ref. 10), a
combined-slip model driven by an explicit cornering stiffness, longitudinal stiffness and
friction coefficient. This model has the same inputs and the same structure: the two
slips are normalised by the friction limit,

    s_x = C_kappa * kappa / (mu Fz),        s_y = C_alpha * tan_alpha / (mu Fz),
    s   = sqrt(s_x^2 + s_y^2),

and the resultant shear force follows the brush model with a parabolic pressure
distribution (Fiala; Pacejka 2012, eq. 3.40 in normalised form)

    f(s) = s - s^2 / 3 + s^3 / 27      for s <= 3,       f(s) = 1 beyond,
    |F|  = mu Fz f(s),  directed along (s_x, -s_y) / s.

so that ``dF/dslip = C`` at zero slip, the force saturates at ``mu Fz`` with zero slope at
``s = 3`` (full sliding) and combined slip shares the friction circle. ``f(s)/s`` is
evaluated as the polynomial ``1 - s/3 + s^2/27``: nothing is divided by the slip.

Stiffnesses scale linearly with load (``C = C_nom Fz / Fz_nom``), so the normalised
slips, and with them the shape of the curves, do not depend on load. The paper's car
(model.md section 5) has ``C_alpha = 51 000 N/rad`` and ``C_kappa = 22 500`` per tire at
``Fz_nom = 5005 N``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.tire_layout import (
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FX,
    OUT_FX_PEAK,
    OUT_FY,
    OUT_FY_PEAK,
    OUT_KAPPA_SLIDE,
    OUT_MY,
    OUT_MZ,
    OUT_TAN_ALPHA_SLIDE,
)

# model-specific slots (offsets into tp[TP_MODEL_BASE:])
SP_C_ALPHA_NOM = 0  # cornering stiffness at Fz_nom (N/rad)
SP_C_KAPPA_NOM = 1  # longitudinal slip stiffness at Fz_nom (N per unit slip)
SP_FZ_NOM = 2  # nominal load (N)
SP_MU = 3  # friction coefficient (peak = sliding in the brush model)
SP_ROLLING_RESISTANCE = 4  # rolling-resistance coefficient f_rr (My = f_rr Fz R)
SP_PNEUMATIC_TRAIL_M = 5  # pneumatic trail at zero slip (m), Mz = -t(s) Fy
SP_RADIUS_M = 6  # rolling radius (m), for My
N_SIMPLE_PARAM = 7

SIMPLE_PARAM_NAMES = (
    "cornering_stiffness_n_per_rad",
    "longitudinal_stiffness_n",
    "nominal_load_n",
    "friction_coefficient",
    "rolling_resistance_coefficient",
    "pneumatic_trail_m",
    "rolling_radius_m",
)
"""Config keys of the model-specific slots, in slot order."""

FULL_SLIDE_S = 3.0
"""Normalised slip at which the brush model slides over the whole contact patch."""
MU_NEGLIGIBLE = 1e-6
"""Below this friction coefficient the surface transmits no shear force."""
S_CLIP = 1e6
"""Normalised slips are scaled down to this (deep in full sliding) to avoid overflow."""


def simple_param_vector(values: dict[str, float]) -> np.ndarray:
    """Pack the model-specific parameters, in the order of ``SIMPLE_PARAM_NAMES``."""
    return np.array([float(values[k]) for k in SIMPLE_PARAM_NAMES], dtype=np.float64)


@nb.njit(cache=True)
def simple_forces(
    p: np.ndarray,
    kappa: float,
    tan_alpha: float,
    gamma_rad: float,
    fz_n: float,
    mu_scale: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Brush-model combined-slip forces; same contract as ``simserver.core.tire.tire_forces``.

    ``p`` holds the ``SP_*`` slots. Camber and speed are not used by this model (the
    STI-class models of the paper's time ignored camber thrust for passenger cars).
    """
    load_ratio = fz_n / p[SP_FZ_NOM]
    c_alpha = p[SP_C_ALPHA_NOM] * load_ratio
    c_kappa = p[SP_C_KAPPA_NOM] * load_ratio
    mu = p[SP_MU] * mu_scale
    f_max = mu * fz_n

    if mu < MU_NEGLIGIBLE:  # no friction: no shear force, and nothing to normalise by
        s_x = 0.0
        s_y = 0.0
    else:
        # Fz cancels in the normalised slips: s = (C_nom / Fz_nom) slip / mu
        s_x = p[SP_C_KAPPA_NOM] * kappa / (mu * p[SP_FZ_NOM])
        s_y = p[SP_C_ALPHA_NOM] * tan_alpha / (mu * p[SP_FZ_NOM])
        big = max(abs(s_x), abs(s_y))
        if big > S_CLIP:  # far into sliding: keep the direction, avoid overflow
            s_x *= S_CLIP / big
            s_y *= S_CLIP / big
    s = np.sqrt(s_x * s_x + s_y * s_y)
    if s < FULL_SLIDE_S:
        f_over_s = 1.0 - s / 3.0 + s * s / 27.0  # f(s)/s, regular at s = 0
    else:
        f_over_s = 1.0 / s
    fx = f_max * f_over_s * s_x
    fy = -f_max * f_over_s * s_y

    # Pneumatic trail shrinks linearly to zero at full sliding (brush model).
    trail = p[SP_PNEUMATIC_TRAIL_M] * max(0.0, 1.0 - s / FULL_SLIDE_S)

    out[OUT_FX] = fx
    out[OUT_FY] = fy
    out[OUT_MZ] = -trail * fy
    out[OUT_MY] = p[SP_ROLLING_RESISTANCE] * fz_n * p[SP_RADIUS_M]
    out[OUT_C_KAPPA] = c_kappa
    out[OUT_C_ALPHA] = c_alpha
    # sliding limits: the slip at s = 3 (load cancels; floored so callers may divide)
    mu_floor = max(mu, MU_NEGLIGIBLE)
    out[OUT_KAPPA_SLIDE] = FULL_SLIDE_S * mu_floor * p[SP_FZ_NOM] / p[SP_C_KAPPA_NOM]
    out[OUT_TAN_ALPHA_SLIDE] = FULL_SLIDE_S * mu_floor * p[SP_FZ_NOM] / p[SP_C_ALPHA_NOM]
    out[OUT_FX_PEAK] = f_max
    out[OUT_FY_PEAK] = f_max
