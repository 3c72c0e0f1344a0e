"""One interface for every tire force model.

The lagged slip states of SAE 950311 (see :mod:`simserver.core.slip`) "can be paired
with any semi-empirical tire model". Every model here is a compiled kernel split in
two with the signatures of ``tire_layout.PREPARE_SIGNATURE`` and ``EVALUATE_SIGNATURE``
(below), listed in the tire-model registry (``simserver.tires.registry``: id, name,
parameter loader, kernels, stiffness report). The dispatchers here take the registered
kernels (``TireKernels``, indexed by model id) and the tire's packed parameters:

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

Sign convention (``docs/model.md`` section 2): ``Fx > 0`` for ``kappa > 0`` and
``Fy < 0`` for ``tan_alpha > 0``.

Split evaluation. Within one integrator step the load, camber and friction hardly move
(the suspension's 1-2 Hz against a 1 kHz step), while the slips do. Every model is
therefore also split in two, and :func:`tire_forces` is exactly the one after the other
at the same load:

- ``tire_prepare(tp, gamma_rad, fz_n, mu_scale, coef)``: everything that depends on
  load, camber, friction (and pressure) but not on slip, into ``coef``
  (``N_TIRE_COEF`` floats; slot names in the model modules); once per step and wheel;
- ``tire_evaluate(tp, coef, kappa, tan_alpha, fz_n, vx_mps, out)``: the slip-dependent
  rest at the *current* load ``fz_n``: forces, moments, stiffnesses and peaks are those
  at the prepared load ``Fz_p`` times ``fz_n / Fz_p`` (so zero load gives zero force and
  the leading-order load dependence stays exact); the sliding limits are taken as
  prepared. For the brush model this is exact at any load; for MF 6.1 the only error is
  the change of the normalised curve ``F / Fz`` (friction, stiffness per unit load,
  shape) between the two loads, first order in ``fz_n / Fz_p - 1``
  (``tests/test_tire_split.py`` states and checks the bound).

Where to prepare. Prepared at the start-of-step load and used for all four stages of an
RK4 step, the coefficients lag the load by up to ``h`` in stage 4, which makes the
load-dependent part of the right-hand side first order in ``h``. Prepared instead at
the load expected at mid-step (e.g. ``Fz + (Fz - Fz_previous_step) / 2``), the lag is
``-h/2`` at stage 1, zero at stages 2 and 3 and ``+h/2`` at stage 4: RK4's symmetric
weights cancel it to first order, at no cost. Measured on the mf_hatchback driving
cycle (10 s) against unsplit RK4: start-of-step preparation moved the lateral
position by 4e-4 m and the wheel spin by 5e-2 rad/s (RK4's own 1 ms vs 0.5 ms error
there: 4e-5 m, 3e-3 rad/s); mid-step preparation by 8e-7 m and 5e-4 rad/s.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import types
from numba.extending import overload

from simserver.core.tire_layout import (
    N_TIRE_OUT,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FY,
    OUT_KAPPA_SLIDE,
    OUT_MZ,
    OUT_TAN_ALPHA_SLIDE,
    TIRE_DISPATCH_JIT_OPTIONS,
    TIRE_JIT_OPTIONS,
    TIRE_MODEL_MF61,
    TIRE_MODEL_SIMPLE,
    TP_MIRRORED,
    TP_MODEL,
    TP_MODEL_BASE,
    TireKernels,
    coef_scratch,
)
from simserver.core.tire_mf61 import (
    N_MF61_PARAM,
    N_WHEEL_TIRES,
    _mf61_evaluate,
    _mf61_evaluate_wheels,
    _mf61_prepare,
)
from simserver.core.tire_simple import N_SIMPLE_PARAM, _simple_evaluate, _simple_prepare

N_TIRE_PARAM = TP_MODEL_BASE + max(N_SIMPLE_PARAM, N_MF61_PARAM)

BUILTIN_KERNELS = TireKernels((), ())
"""The ``kernels`` argument when only the built-in models are used (they are called
directly); ``simserver.tires.registry.tire_kernels()`` adds every other registered model's."""


# Mirroring (``tp[TP_MIRRORED] = 1``): a tire used on the side opposite to the one its file
# describes (MF-Tyre's TYRESIDE) is the mirror image in the vehicle's x-z plane. Every
# dispatcher evaluates the model at the mirrored slip angle and camber and mirrors its side
# force and aligning moment back (``side = 1 - 2 tp[TP_MIRRORED]``, -1 or +1), so every
# lateral asymmetry (the shifts SHy, SVy, the camber terms, conicity, ply steer) changes
# side while Fx, My and the stiffnesses do not. For an unmirrored tire the factor is
# exactly 1.0 and the results are bit-identical. (Written out in each dispatcher: a helper
# function there kept numba from pruning the reference counts of tire_forces.)


@nb.njit(**TIRE_JIT_OPTIONS)
def _no_load(out: np.ndarray) -> None:
    """Outputs of a wheel without load: all zero, stiffnesses and limits 1."""
    for i in range(N_TIRE_OUT):
        out[i] = 0.0
    # stiffnesses and limits stay positive so that callers never divide by zero
    out[OUT_C_KAPPA] = 1.0
    out[OUT_C_ALPHA] = 1.0
    out[OUT_KAPPA_SLIDE] = 1.0
    out[OUT_TAN_ALPHA_SLIDE] = 1.0


# The built-in models are called directly, their bodies inlined (a call through a function
# pointer costs 2-4 ns and stops inlining; 20 calls a step). Every other registered model
# is called through its kernels, which ``kernels`` holds in id order from
# N_BUILTIN_TIRE_MODELS on. With no other model registered ``kernels`` holds empty tuples
# and the indirect call is not even compiled (the two functions below are resolved on the
# tuples' type): the default step carries no function-pointer machinery (measured: about
# +0.3 us a step when it did). The registry checks the ids before anything is compiled
# (``simserver.sim.simulation.check_model``); an id that got past it anyway yields NaN, which
# every check downstream reports, never another model's forces. (Not an exception: its
# exit path would keep numba from pruning the reference counts of the dispatchers' views.)
N_BUILTIN_TIRE_MODELS = 2


def _registered_prepare(kernels: TireKernels, model: int, tp: np.ndarray, gamma_rad: float,
                        fz_n: float, mu_scale: float, coef: np.ndarray) -> None:
    """The prepare kernel of registered model ``model`` (compiled code only)."""
    raise NotImplementedError


def _registered_evaluate(kernels: TireKernels, model: int, tp: np.ndarray, coef: np.ndarray,
                         kappa: float, tan_alpha: float, fz_n: float, vx_mps: float,
                         out: np.ndarray) -> None:
    """The evaluate kernel of registered model ``model`` (compiled code only)."""
    raise NotImplementedError


def _no_kernels(kernels: types.Type) -> bool:
    return kernels.types[0].count == 0


@overload(_registered_prepare, inline="always", jit_options=TIRE_JIT_OPTIONS)
def _registered_prepare_compiled(kernels, model, tp, gamma_rad, fz_n, mu_scale, coef):  # noqa: ANN001, ANN202
    if _no_kernels(kernels):
        def impl(kernels, model, tp, gamma_rad, fz_n, mu_scale, coef):  # noqa: ANN001, ANN202
            for k in range(coef.size):
                coef[k] = np.nan
    else:
        def impl(kernels, model, tp, gamma_rad, fz_n, mu_scale, coef):  # noqa: ANN001, ANN202
            kernels.prepare[model - N_BUILTIN_TIRE_MODELS](tp, gamma_rad, fz_n, mu_scale, coef)
    return impl


@overload(_registered_evaluate, inline="always", jit_options=TIRE_JIT_OPTIONS)
def _registered_evaluate_compiled(kernels, model, tp, coef, kappa, tan_alpha, fz_n,  # noqa: ANN001, ANN202
                                  vx_mps, out):
    if _no_kernels(kernels):
        def impl(kernels, model, tp, coef, kappa, tan_alpha, fz_n, vx_mps, out):  # noqa: ANN001, ANN202
            for k in range(out.size):
                out[k] = np.nan
    else:
        def impl(kernels, model, tp, coef, kappa, tan_alpha, fz_n, vx_mps, out):  # noqa: ANN001, ANN202
            kernels.evaluate[model - N_BUILTIN_TIRE_MODELS](tp, coef, kappa, tan_alpha, fz_n,
                                                            vx_mps, out)
    return impl


@nb.njit(**TIRE_DISPATCH_JIT_OPTIONS)
def tire_prepare(
    kernels: TireKernels,
    tp: np.ndarray,
    gamma_rad: float,
    fz_n: float,
    mu_scale: float,
    coef: np.ndarray,
) -> None:
    """Load-dependent coefficients of the tire model selected by ``tp[TP_MODEL]``.

    Parameters
    ----------
    kernels : TireKernels
        The registered models' kernels (``simserver.tires.registry.tire_kernels()``).
    tp : float64[N_TIRE_PARAM]
        Packed tire parameters.
    gamma_rad, fz_n, mu_scale : float
        Camber, normal load, road friction scale. Any ``fz_n`` is accepted: at
        ``fz_n <= 0`` the models prepare at a positive reference load (MF 6.1: the floor
        of its load range; brush: 0.1 % of its nominal load, exact anyway), from which
        :func:`tire_evaluate` scales linearly, so a wheel that touches down later in the
        step gets force.
    coef : float64[N_TIRE_COEF]
        Written (every slot the model uses).
    """
    model = int(tp[TP_MODEL])
    # a mirrored tire sees the mirrored camber
    gamma_rad = gamma_rad * (1.0 - 2.0 * tp[TP_MIRRORED])
    if model == TIRE_MODEL_MF61:
        _mf61_prepare(tp[TP_MODEL_BASE:], gamma_rad, fz_n, mu_scale, coef)
    elif model == TIRE_MODEL_SIMPLE:
        _simple_prepare(tp[TP_MODEL_BASE:], gamma_rad, fz_n, mu_scale, coef)
    else:
        _registered_prepare(kernels, model, tp, gamma_rad, fz_n, mu_scale, coef)


@nb.njit(**TIRE_DISPATCH_JIT_OPTIONS)
def tire_evaluate(
    kernels: TireKernels,
    tp: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Forces of the tire model selected by ``tp[TP_MODEL]`` from prepared coefficients.

    Parameters
    ----------
    kernels : TireKernels
        The registered models' kernels.
    tp : float64[N_TIRE_PARAM]
        Packed tire parameters (the same as given to :func:`tire_prepare`).
    coef : float64[N_TIRE_COEF]
        Written by :func:`tire_prepare`; read only.
    kappa, tan_alpha : float
        Slip inputs (the lagged states ``k'`` and ``tan a'``).
    fz_n : float
        Current normal load: outputs scale with ``fz_n / Fz_prepared``; at ``fz_n <= 0``
        every output is zero except the stiffnesses and sliding limits, which are 1.
    vx_mps : float
        Hub longitudinal speed.
    out : float64[N_TIRE_OUT]
        Written in place, every ``OUT_*`` slot.
    """
    model = int(tp[TP_MODEL])
    side = 1.0 - 2.0 * tp[TP_MIRRORED]
    tan_alpha = tan_alpha * side
    if not fz_n > 0.0:
        _no_load(out)
    elif model == TIRE_MODEL_MF61:
        _mf61_evaluate(tp[TP_MODEL_BASE:], coef, kappa, tan_alpha, fz_n, vx_mps, out)
    elif model == TIRE_MODEL_SIMPLE:
        _simple_evaluate(tp[TP_MODEL_BASE:], coef, kappa, tan_alpha, fz_n, vx_mps, out)
    else:
        _registered_evaluate(kernels, model, tp, coef, kappa, tan_alpha, fz_n, vx_mps, out)
    out[OUT_FY] *= side
    out[OUT_MZ] *= side


@nb.njit(**TIRE_DISPATCH_JIT_OPTIONS)
def tire_evaluate_mf61_wheels(
    tp: np.ndarray,
    coef: np.ndarray,
    kappa: tuple[float, ...],
    tan_alpha: tuple[float, ...],
    fz_n: tuple[float, ...],
    vx_mps: tuple[float, ...],
    out: np.ndarray,
) -> None:
    """:func:`tire_evaluate` of ``N_WHEEL_TIRES`` MF 6.1 tires in one call (the step's
    call when every wheel has an MF 6.1 tire: the tires' Magic Formula curves are then
    one vectorised loop, ``tire_mf61._mf61_evaluate_wheels``).

    Parameters
    ----------
    tp : float64[N_WHEEL_TIRES, N_TIRE_PARAM]
        Packed tire parameters, every ``tp[w, TP_MODEL] == TIRE_MODEL_MF61`` (the caller
        checks: :func:`every_tire_is`).
    coef : float64[N_WHEEL_TIRES, N_TIRE_COEF]
        Written by :func:`tire_prepare`; read only.
    kappa, tan_alpha, fz_n, vx_mps : tuples of N_WHEEL_TIRES floats
        Per tire, as the arguments of :func:`tire_evaluate`.
    out : float64[N_WHEEL_TIRES, N_TIRE_OUT]
        Row ``w`` written as :func:`tire_evaluate` writes ``out`` for tire ``w``.
    """
    _mf61_evaluate_wheels(tp, coef, kappa, tan_alpha, fz_n, vx_mps, out)


@nb.njit(**TIRE_DISPATCH_JIT_OPTIONS)
def tire_evaluate_simple_wheels(
    tp: np.ndarray,
    coef: np.ndarray,
    kappa: tuple[float, ...],
    tan_alpha: tuple[float, ...],
    fz_n: tuple[float, ...],
    vx_mps: tuple[float, ...],
    out: np.ndarray,
) -> None:
    """:func:`tire_evaluate` of ``N_WHEEL_TIRES`` brush tires in one call (the step's call
    when every wheel has a brush tire): :func:`tire_evaluate`'s brush branch, with its
    mirroring, under its compile options, so the same bits; one call a Runge-Kutta stage
    instead of four (each call passing its arrays cost about 45 instructions, 16 a step).
    Arguments as :func:`tire_evaluate_mf61_wheels`'s, every ``tp[w, TP_MODEL] ==
    TIRE_MODEL_SIMPLE`` (the caller checks: :func:`every_tire_is`).
    """
    for w in range(N_WHEEL_TIRES):
        out_w = out[w]
        side = 1.0 - 2.0 * tp[w, TP_MIRRORED]
        if not fz_n[w] > 0.0:
            _no_load(out_w)
        else:
            _simple_evaluate(tp[w, TP_MODEL_BASE:], coef[w], kappa[w], tan_alpha[w] * side,
                             fz_n[w], vx_mps[w], out_w)
        out_w[OUT_FY] *= side
        out_w[OUT_MZ] *= side


@nb.njit(inline="always", **TIRE_JIT_OPTIONS)
def every_tire_is(tp: np.ndarray, model: int) -> bool:
    """Whether ``tp`` holds ``N_WHEEL_TIRES`` packed tires, every one of model ``model``."""
    every = tp.shape[0] == N_WHEEL_TIRES
    for w in range(tp.shape[0]):
        every = every and int(tp[w, TP_MODEL]) == model
    return every


@nb.njit(**TIRE_JIT_OPTIONS)
def tire_forces(
    kernels: TireKernels,
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

    :func:`tire_prepare` then :func:`tire_evaluate`, both at ``fz_n`` (the
    coefficients live on the stack; nothing is allocated).

    Parameters
    ----------
    kernels : TireKernels
        The registered models' kernels.
    tp : float64[N_TIRE_PARAM]
        Packed tire parameters.
    kappa, tan_alpha : float
        Slip inputs (the lagged states ``k'`` and ``tan a'``).
    gamma_rad, fz_n, mu_scale, vx_mps : float
        Camber, normal load, road friction scale, hub longitudinal speed.
    out : float64[N_TIRE_OUT]
        Written in place.
    """
    if not fz_n > 0.0:
        _no_load(out)
        return
    coef = coef_scratch()
    # the model kernels are inlined here (no call, so the view tp[TP_MODEL_BASE:] costs
    # no reference counting); the same as tire_prepare then tire_evaluate. The mirroring
    # of the outputs is repeated in each branch: after the branches' merge it kept numba
    # from pruning the views' reference counts.
    model = int(tp[TP_MODEL])
    side = 1.0 - 2.0 * tp[TP_MIRRORED]
    tan_alpha = tan_alpha * side
    gamma_rad = gamma_rad * side
    if model == TIRE_MODEL_MF61:
        _mf61_prepare(tp[TP_MODEL_BASE:], gamma_rad, fz_n, mu_scale, coef)
        _mf61_evaluate(tp[TP_MODEL_BASE:], coef, kappa, tan_alpha, fz_n, vx_mps, out)
        out[OUT_FY] *= side
        out[OUT_MZ] *= side
    elif model == TIRE_MODEL_SIMPLE:
        _simple_prepare(tp[TP_MODEL_BASE:], gamma_rad, fz_n, mu_scale, coef)
        _simple_evaluate(tp[TP_MODEL_BASE:], coef, kappa, tan_alpha, fz_n, vx_mps, out)
        out[OUT_FY] *= side
        out[OUT_MZ] *= side
    else:
        _registered_prepare(kernels, model, tp, gamma_rad, fz_n, mu_scale, coef)
        _registered_evaluate(kernels, model, tp, coef, kappa, tan_alpha, fz_n, vx_mps, out)
        out[OUT_FY] *= side
        out[OUT_MZ] *= side
