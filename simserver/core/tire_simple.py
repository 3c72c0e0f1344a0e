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
slips, and with them the shape of the curves, do not depend on load: every output is
``Fz`` times a function of slip and friction. The split of :mod:`simserver.core.tire`
(``simple_prepare`` once per step, ``simple_evaluate`` per stage, scaled by
``Fz / Fz_prepared``) is therefore exact at any load. The paper's car
(docs/model.md section 5) has ``C_alpha = 51 000 N/rad`` and ``C_kappa = 22 500`` per tire at
``Fz_nom = 5005 N``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.tire_layout import (
    FZ_INPUT_MAX_N,
    MU_SCALE_MAX,
    N_SIMPLE_COEF,
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
    SLIP_INPUT_MAX,
    TIRE_JIT_OPTIONS,
    TP_MODEL_BASE,
    coef_scratch,
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

# load-dependent coefficients (slots of coef, written by simple_prepare)
SC_FZ_PREP = 0  # load the coefficients below were computed at (N, > 0)
SC_F_MAX = 1  # friction limit mu Fz at that load (N)
SC_SX_PER_KAPPA = 2  # s_x / kappa = C_kappa / (mu Fz): independent of load (0 if mu ~ 0)
SC_SY_PER_TAN_ALPHA = 3  # s_y / tan_alpha = C_alpha / (mu Fz)
SC_C_KAPPA = 4  # C_kappa at that load (N per unit slip)
SC_C_ALPHA = 5  # C_alpha at that load (N/rad)
SC_MY = 6  # rolling-resistance moment at that load (N m)
SC_KAPPA_SLIDE = 7  # sliding limits (s = 3), independent of load
SC_TAN_ALPHA_SLIDE = 8
SC_TRAIL_M = 9  # pneumatic trail at zero slip (m)
if SC_TRAIL_M + 1 != N_SIMPLE_COEF:
    raise ImportError("simserver.core.tire_layout.N_SIMPLE_COEF is out of date")

FULL_SLIDE_S = 3.0
"""Normalised slip at which the brush model slides over the whole contact patch."""
MU_NEGLIGIBLE = 1e-6
"""Below this friction coefficient the surface transmits no shear force."""
S_CLIP = 1e6
"""Normalised slips are scaled down to this (deep in full sliding) to avoid overflow."""
FZ_FLOOR_FRAC = 1e-3
"""Coefficients are prepared at no less than this fraction of ``Fz_nom``."""


def simple_param_vector(values: dict[str, float]) -> np.ndarray:
    """Pack the model-specific parameters, in the order of ``SIMPLE_PARAM_NAMES``."""
    return np.array([float(values[k]) for k in SIMPLE_PARAM_NAMES], dtype=np.float64)


@nb.njit(inline="always", **TIRE_JIT_OPTIONS)
def _simple_prepare(
    p: np.ndarray, gamma_rad: float, fz_n: float, mu_scale: float, coef: np.ndarray
) -> None:
    """Load- and friction-dependent coefficients of the brush model.

    Parameters
    ----------
    p : float64[N_SIMPLE_PARAM]
        The ``SP_*`` slots.
    gamma_rad : float
        Camber; not used by this model (the STI-class models of the paper's time ignored
        camber thrust for passenger cars).
    fz_n : float
        Normal load (N). The model is exactly linear in load, so the coefficients may be
        computed at any positive load: at ``fz_n``, floored at ``FZ_FLOOR_FRAC Fz_nom``
        (``fz_n <= 0`` included) and capped at ``FZ_INPUT_MAX_N``; evaluated at any load
        they give the same result (to rounding).
    mu_scale : float
        Road friction scale, clamped to ``[0, MU_SCALE_MAX]``.
    coef : float64[N_TIRE_COEF]
        Written: the ``SC_*`` slots.

    Notes
    -----
    Inlined into its caller (numba IR), which must be compiled with
    ``TIRE_JIT_OPTIONS``; :func:`simple_prepare` is the same compiled on its own.
    """
    # any positive reference load gives the same forces; floored so that the scale
    # fz_n / Fz_prepared of simple_evaluate stays finite
    fz = min(max(fz_n, FZ_FLOOR_FRAC * p[SP_FZ_NOM]), FZ_INPUT_MAX_N)
    load_ratio = fz / p[SP_FZ_NOM]
    mu = p[SP_MU] * min(max(mu_scale, 0.0), MU_SCALE_MAX)
    coef[SC_FZ_PREP] = fz
    coef[SC_F_MAX] = mu * fz
    if mu < MU_NEGLIGIBLE:  # no friction: no shear force, and nothing to normalise by
        coef[SC_SX_PER_KAPPA] = 0.0
        coef[SC_SY_PER_TAN_ALPHA] = 0.0
    else:
        # Fz cancels in the normalised slips: s = (C_nom / Fz_nom) slip / mu
        coef[SC_SX_PER_KAPPA] = p[SP_C_KAPPA_NOM] / (mu * p[SP_FZ_NOM])
        coef[SC_SY_PER_TAN_ALPHA] = p[SP_C_ALPHA_NOM] / (mu * p[SP_FZ_NOM])
    coef[SC_C_KAPPA] = p[SP_C_KAPPA_NOM] * load_ratio
    coef[SC_C_ALPHA] = p[SP_C_ALPHA_NOM] * load_ratio
    coef[SC_MY] = p[SP_ROLLING_RESISTANCE] * fz * p[SP_RADIUS_M]
    # sliding limits: the slip at s = 3 (load cancels; floored so callers may divide)
    mu_floor = max(mu, MU_NEGLIGIBLE)
    coef[SC_KAPPA_SLIDE] = FULL_SLIDE_S * mu_floor * p[SP_FZ_NOM] / p[SP_C_KAPPA_NOM]
    coef[SC_TAN_ALPHA_SLIDE] = FULL_SLIDE_S * mu_floor * p[SP_FZ_NOM] / p[SP_C_ALPHA_NOM]
    coef[SC_TRAIL_M] = p[SP_PNEUMATIC_TRAIL_M]


@nb.njit(inline="always", **TIRE_JIT_OPTIONS)
def _simple_evaluate(
    p: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Brush-model combined-slip forces from prepared coefficients.

    Parameters
    ----------
    p : float64[N_SIMPLE_PARAM]
        The ``SP_*`` slots (not read: everything is in ``coef``).
    coef : float64[N_TIRE_COEF]
        Written by :func:`simple_prepare`.
    kappa, tan_alpha : float
        Slips, clamped to ``|.| <= SLIP_INPUT_MAX``.
    fz_n : float
        Current normal load (N); every force, moment and stiffness is scaled by
        ``fz_n / coef[SC_FZ_PREP]``, which is exact for this model. ``fz_n <= 0`` gives
        zeros (the dispatcher handles that case before calling).
    vx_mps : float
        Not used by this model.
    out : float64[N_TIRE_OUT]
        Written, every ``OUT_*`` slot (contract of ``simserver.core.tire.tire_forces``).

    Notes
    -----
    Inlined into its caller (numba IR), which must be compiled with
    ``TIRE_JIT_OPTIONS``; :func:`simple_evaluate` is the same compiled on its own.
    """
    scale = max(min(fz_n, FZ_INPUT_MAX_N), 0.0) / coef[SC_FZ_PREP]
    f_max = coef[SC_F_MAX] * scale
    kappa = min(max(kappa, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
    tan_alpha = min(max(tan_alpha, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
    s_x = coef[SC_SX_PER_KAPPA] * kappa
    s_y = coef[SC_SY_PER_TAN_ALPHA] * tan_alpha
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
    trail = coef[SC_TRAIL_M] * max(0.0, 1.0 - s / FULL_SLIDE_S)

    out[OUT_FX] = fx
    out[OUT_FY] = fy
    out[OUT_MZ] = -trail * fy
    out[OUT_MY] = coef[SC_MY] * scale
    out[OUT_C_KAPPA] = coef[SC_C_KAPPA] * scale
    out[OUT_C_ALPHA] = coef[SC_C_ALPHA] * scale
    out[OUT_KAPPA_SLIDE] = coef[SC_KAPPA_SLIDE]
    out[OUT_TAN_ALPHA_SLIDE] = coef[SC_TAN_ALPHA_SLIDE]
    out[OUT_FX_PEAK] = f_max
    out[OUT_FY_PEAK] = f_max


@nb.njit(**TIRE_JIT_OPTIONS)
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

    ``p`` holds the ``SP_*`` slots. :func:`simple_prepare` at ``fz_n``, then
    :func:`simple_evaluate` at ``fz_n`` (the coefficients live on the stack).
    """
    coef = coef_scratch()
    _simple_prepare(p, gamma_rad, fz_n, mu_scale, coef)
    _simple_evaluate(p, coef, kappa, tan_alpha, fz_n, vx_mps, out)


@nb.njit(**TIRE_JIT_OPTIONS)
def simple_prepare(
    p: np.ndarray, gamma_rad: float, fz_n: float, mu_scale: float, coef: np.ndarray
) -> None:
    """Load-dependent coefficients of the brush model: :func:`_simple_prepare`.

    Compiled on its own, so it may be called from code compiled with any options.
    """
    _simple_prepare(p, gamma_rad, fz_n, mu_scale, coef)


@nb.njit(**TIRE_JIT_OPTIONS)
def simple_evaluate(
    p: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Brush-model forces from prepared coefficients: :func:`_simple_evaluate`.

    Compiled on its own, so it may be called from code compiled with any options.
    """
    _simple_evaluate(p, coef, kappa, tan_alpha, fz_n, vx_mps, out)


# ---- the kernels registered for this model (simserver.tires.registry): the packed tire vector
# in full (core.tire_layout.PREPARE_SIGNATURE, EVALUATE_SIGNATURE), the body inlined.
# Compiled on first use, not at import: the step inlines the body itself (core.tire)


@nb.njit(**TIRE_JIT_OPTIONS)
def simple_prepare_kernel(
    tp: np.ndarray, gamma_rad: float, fz_n: float, mu_scale: float, coef: np.ndarray
) -> None:
    """:func:`_simple_prepare` on the model slots of the packed tire vector ``tp``."""
    _simple_prepare(tp[TP_MODEL_BASE:], gamma_rad, fz_n, mu_scale, coef)


@nb.njit(**TIRE_JIT_OPTIONS)
def simple_evaluate_kernel(
    tp: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """:func:`_simple_evaluate` on the model slots of the packed tire vector ``tp``."""
    _simple_evaluate(tp[TP_MODEL_BASE:], coef, kappa, tan_alpha, fz_n, vx_mps, out)
