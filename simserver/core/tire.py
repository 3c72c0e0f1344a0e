"""One interface for every tire force model.

The lagged slip states of SAE 950311 (see :mod:`simserver.core.slip`) "can be paired
with any semi-empirical tire model". Every model here is a compiled kernel with the
same signature::

    model_forces(tp, kappa, tan_alpha, gamma_rad, fz_n, mu_scale, vx_mps, out)

- ``tp``: the tire's packed parameter vector (``N_TIRE_PARAM`` floats). ``tp[TP_MODEL]``
  selects the model; ``TP_*`` slots below ``TP_MODEL_BASE`` are common to all models.
- ``kappa``: longitudinal slip (positive when driving, ISO 8855).
- ``tan_alpha``: tangent of the slip angle, positive when the hub slides to +y
  (MF-Tyre's ``alpha* = tan(alpha) sgn(Vcx)``; the lagged state ``tan a'`` is exactly this).
- ``gamma_rad``: inclination (camber) angle.
- ``fz_n``: normal load (N); at ``fz_n <= 0`` every output is zero.
- ``mu_scale``: road friction scale (1 = the surface the tire was measured on).
- ``vx_mps``: hub longitudinal speed, used only by speed-dependent terms (rolling
  resistance); never divided by.
- ``out``: ``N_TIRE_OUT`` floats, written with the ``OUT_*`` slots below.

Sign convention (``../shared/docs/model.md`` section 2): ``Fx > 0`` for ``kappa > 0`` and
``Fy < 0`` for ``tan_alpha > 0``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.tire_layout import (
    N_TIRE_OUT,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_KAPPA_SLIDE,
    OUT_TAN_ALPHA_SLIDE,
    TIRE_MODEL_MF61,
    TP_MODEL,
    TP_MODEL_BASE,
)
from simserver.core.tire_mf61 import N_MF61_PARAM, mf61_forces
from simserver.core.tire_simple import N_SIMPLE_PARAM, simple_forces

N_TIRE_PARAM = TP_MODEL_BASE + max(N_SIMPLE_PARAM, N_MF61_PARAM)

@nb.njit(cache=True)
def tire_forces(
    tp: np.ndarray,
    kappa: float,
    tan_alpha: float,
    gamma_rad: float,
    fz_n: float,
    mu_scale: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Evaluate the tire model selected by ``tp[TP_MODEL]`` into ``out``.

    Parameters
    ----------
    tp : float64[N_TIRE_PARAM]
        Packed tire parameters.
    kappa, tan_alpha : float
        Slip inputs (the lagged states ``k'`` and ``tan a'``).
    gamma_rad, fz_n, mu_scale, vx_mps : float
        Camber, normal load, road friction scale, hub longitudinal speed.
    out : float64[N_TIRE_OUT]
        Written in place.
    """
    model = int(tp[TP_MODEL])
    if fz_n <= 0.0:
        for i in range(N_TIRE_OUT):
            out[i] = 0.0
        # stiffnesses and limits stay positive so that callers never divide by zero
        out[OUT_C_KAPPA] = 1.0
        out[OUT_C_ALPHA] = 1.0
        out[OUT_KAPPA_SLIDE] = 1.0
        out[OUT_TAN_ALPHA_SLIDE] = 1.0
        return
    if model == TIRE_MODEL_MF61:
        mf61_forces(tp[TP_MODEL_BASE:], kappa, tan_alpha, gamma_rad, fz_n, mu_scale, vx_mps, out)
    else:
        simple_forces(tp[TP_MODEL_BASE:], kappa, tan_alpha, gamma_rad, fz_n, mu_scale, vx_mps, out)
