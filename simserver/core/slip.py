"""Slip states of one wheel: the lagged formulation of SAE 950311 and its variants.

Bernard & Clover make the slip angle and the longitudinal slip *state variables* with a
first-order lag whose time constant is relaxation length / |u| (docs/model.md section 3):

    b d(tan a')/dt + |u| tan a' = v                      (paper eq. 16)
    B d(k')/dt     + |u| k'     = R Omega - u            (paper eq. 26, in the k' form)

Nothing is divided by the hub's longitudinal speed ``u``: the equations are regular at
``u = 0`` and for ``u < 0``. In steady state they give the classic definitions
``tan a' = v/|u|`` and ``k' = (R Omega - u)/|u|``; at ``u = 0`` they integrate the
contact-patch displacement (``tan a' = y/b``, ``k' = -x/B`` with a locked wheel).

Three slip models are selectable (``SLIP_*``):

- ``SLIP_LAGGED_PASSIVE`` (default): the equations above, with the states held within the
  tire's sliding limit (:func:`project_to_sliding_limit`, docs/model.md section 4b item 1).
  A real contact patch slides once the deflection reaches the friction limit instead of
  deflecting further; the paper's plain form keeps integrating displacement, stores
  energy that sliding should have dissipated, and gives it back when the slide reverses
  (a braked, nearly stopped car is pushed back up to speed). With the projection the
  elastic energy a tire can store is bounded by what its deflection at the sliding limit
  holds, so the tire never feeds a braked car energy it did not give it.
- ``SLIP_LAGGED_PAPER``: the paper's plain form, kept to reproduce its examples.
- ``SLIP_KINEMATIC``: the classic algebraic slip with the paper's eq. (1) style patch,
  ``u`` replaced by ``max(|u|, u_min)``: the baseline the paper argues against.

The states are integrated by the vehicle integrator; this module provides the pieces.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.variants import Variant, VariantRegistry

SLIP_LAGGED_PASSIVE = 0
SLIP_LAGGED_PAPER = 1
SLIP_KINEMATIC = 2
SLIP_MODELS = VariantRegistry("slip model", (
    Variant(SLIP_LAGGED_PASSIVE, "lagged_passive",
            "lagged slip states held within the tire's sliding limit (default)"),
    Variant(SLIP_LAGGED_PAPER, "lagged_paper", "the paper's plain lagged slip states"),
    Variant(SLIP_KINEMATIC, "kinematic",
            "classic algebraic slip with the paper's eq. (1) u_min patch (baseline)"),
))
SLIP_MODEL_NAMES = SLIP_MODELS.names


@nb.njit(cache=True)
def lagged_slip_rates(
    tan_alpha_lag: float,
    kappa_lag: float,
    u_mps: float,
    v_mps: float,
    omega_radps: float,
    radius_m: float,
    relax_lat_m: float,
    relax_long_m: float,
) -> tuple[float, float]:
    """Time derivatives of ``tan a'`` and ``k'`` (paper eqs. 16 and 26).

    Parameters
    ----------
    tan_alpha_lag, kappa_lag : float
        Current states ``tan a'`` and ``k'``.
    u_mps, v_mps : float
        Hub velocity in the wheel's heading frame (any sign, including 0).
    omega_radps : float
        Wheel spin rate, positive rolling forward.
    radius_m : float
        Effective rolling radius R.
    relax_lat_m, relax_long_m : float
        Relaxation lengths b and B (> 0).

    Returns
    -------
    (d tan a'/dt, d k'/dt) in 1/s.
    """
    speed = abs(u_mps)
    d_tan_alpha = (v_mps - speed * tan_alpha_lag) / relax_lat_m
    d_kappa = (radius_m * omega_radps - u_mps - speed * kappa_lag) / relax_long_m
    return d_tan_alpha, d_kappa


@nb.njit(cache=True)
def kinematic_slip(
    u_mps: float, v_mps: float, omega_radps: float, radius_m: float, u_min_mps: float
) -> tuple[float, float]:
    """Classic slip with the paper's eq. (1) patch: ``u`` replaced by ``max(|u|, u_min)``.

    Returns ``(tan_alpha, kappa)`` in the same convention as the lagged states
    (``tan_alpha = v/|u|``, ``kappa = (R Omega - u)/|u|``), so the two feed the tire
    model identically at speed.
    """
    u_ref = max(abs(u_mps), u_min_mps)
    return v_mps / u_ref, (radius_m * omega_radps - u_mps) / u_ref


@nb.njit(cache=True)
def sliding_ratio_squared(tan_alpha_lag: float, kappa_lag: float, tan_alpha_slide: float,
                          kappa_slide: float) -> float:
    """``rho^2`` of :func:`project_to_sliding_limit`: the squared combined slip state
    against the tire's sliding limit (1: at the limit)."""
    x = kappa_lag / kappa_slide
    y = tan_alpha_lag / tan_alpha_slide
    return x * x + y * y


@nb.njit(cache=True)
def project_to_sliding_limit(
    tan_alpha_lag: float,
    kappa_lag: float,
    tan_alpha_slide: float,
    kappa_slide: float,
    hub_speed_mps: float,
    widen_speed_mps: float,
) -> tuple[float, float]:
    """Hold the slip states within the tire's sliding limit (the passive variant).

    The combined normalised state ``rho = |(k'/k_slide, tan a'/tan_slide)|`` measures the
    contact-patch deflection against the deflection at which the patch slides (the peak of
    the force curves, reported by the tire model at the current load). Beyond the limit
    the patch slides instead of deflecting further, so the state is scaled back radially
    onto the limit ``rho_max``.

    At speed the steady states are the kinematic slips, which legitimately exceed the
    peak (a locked wheel has ``k' = -1``); those are slip, not stored deflection, and the
    relaxation term ``|u| k'`` dissipates them. So the limit widens with hub speed,
    ``rho_max = max(1, |V| / widen_speed)``: at standstill it is the sliding limit itself,
    and from ``|V| = widen_speed * rho_kin`` up the classic high-speed solution is
    untouched. Because ``rho_max`` shrinks continuously as the car slows, the excess is
    removed (dissipated) continuously, never returned.

    Returns the projected ``(tan a', k')``.
    """
    rho2 = sliding_ratio_squared(tan_alpha_lag, kappa_lag, tan_alpha_slide, kappa_slide)
    rho_max = max(1.0, hub_speed_mps / widen_speed_mps)
    if rho2 <= rho_max * rho_max:
        return tan_alpha_lag, kappa_lag
    scale = rho_max / np.sqrt(rho2)
    return tan_alpha_lag * scale, kappa_lag * scale


@nb.njit(cache=True)
def phi1(z: float) -> float:
    """``(1 - exp(-z)) / z``, regular at ``z = 0`` (the exponential integrator's weight)."""
    if abs(z) < 1e-5:
        return 1.0 - 0.5 * z + z * z / 6.0
    return -np.expm1(-z) / z
