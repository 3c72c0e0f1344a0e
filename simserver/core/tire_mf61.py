"""Magic Formula 6.1 tire model (MF-Tyre 6.1 property files), compiled.

Equations: H. B. Pacejka, *Tire and Vehicle Dynamics*, 3rd ed. (2012), section 4.3.2,
"full set of equations" (4.E1) to (4.E78), in the ISO sign convention of MF-Tyre property
files (``../shared/docs/model.md`` section 2). Equation numbers are quoted in the comments.
No turn slip: every zeta factor is 1 (zeta0 = 1 as well, the pure camber path).

Where the book and the MF-Tyre implementation differ, this module follows the latter, as
established by the public MFeval implementation that was checked against TNO's MF-Tyre:

- digressive friction factor ``A_mu = 1`` in (4.E8), so ``lambda'_mu = lambda*_mu``: the
  road friction scale then multiplies the friction-proportional vertical shifts exactly
  as it multiplies the peak, and ``mu_scale = 0.5`` halves every peak force;
- (4.E40) uses ``(1 + QBZ4 gamma* + QBZ5 |gamma*|)`` (the book's QBZ6 is not a .tir key);
- (4.E70) rolling resistance is ``R0 Fz0 (...) (Fz/Fz0)^QSY7 (p/p0)^QSY8`` with the
  unprimed nominal load ``Fz0 = FNOMIN`` (the book prints ``Fz`` in front);
- (4.E74) ``F'y = G_yk Fy0(gamma = 0)``: the pneumatic trail acts on the camber-free
  side force; the camber moment is carried by the residual torque (QDZ8..QDZ11).

Inputs follow :mod:`simserver.core.tire`: ``tan_alpha`` is MF's ``alpha*`` (4.E3), so
``sgn(Vcx)`` never appears again; in (4.E42) and (4.E47) it multiplies ``cos'alpha``
(4.E6), which carries the same sign, and the two cancel. ``cos'alpha`` is therefore
``1 / sqrt(1 + tan_alpha^2)``.

Load range: the coefficient polynomials in ``dfz`` are a fit over the file's
``FZMIN..FZMAX``. Outside it (or below ``0.01 FNOMIN``) the model is evaluated at the
clamped load ``Fz_c`` and every force, moment, stiffness and peak is multiplied by
``Fz / Fz_c``: linear in load beyond the fitted range, and going to zero with ``Fz``.
Inside the range this is exactly MF 6.1.

Not modelled: turn slip and spin (zeta = 1), speed-dependent friction ``LMUV``,
overturning moment ``Mx``, low-speed smoothing of ``My`` (the caller applies ``My``
against wheel spin), transient (relaxation) behaviour, which the lagged slip states of
SAE 950311 provide.
"""

from __future__ import annotations

import math

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

# --- packed parameters: one source of truth ------------------------------------------
MF61_PARAM_NAMES: tuple[str, ...] = (
    # operating point, dimensions, validity range
    "FNOMIN", "UNLOADED_RADIUS", "LONGVL", "INFLPRES", "NOMPRES", "FZMIN", "FZMAX",
    # scaling factors (lambda)
    "LFZO", "LCX", "LMUX", "LEX", "LKX", "LHX", "LVX", "LXAL",
    "LCY", "LMUY", "LEY", "LKY", "LKYC", "LKZC", "LHY", "LVY", "LYKA", "LVYKA",
    "LTR", "LRES", "LS", "LMY",
    # longitudinal: pure slip (4.E9-4.E18), combined (4.E50-4.E57)
    "PCX1", "PDX1", "PDX2", "PDX3", "PEX1", "PEX2", "PEX3", "PEX4",
    "PKX1", "PKX2", "PKX3", "PHX1", "PHX2", "PVX1", "PVX2",
    "PPX1", "PPX2", "PPX3", "PPX4",
    "RBX1", "RBX2", "RBX3", "RCX1", "REX1", "REX2", "RHX1",
    # lateral: pure slip (4.E19-4.E30), combined (4.E58-4.E67)
    "PCY1", "PDY1", "PDY2", "PDY3", "PEY1", "PEY2", "PEY3", "PEY4", "PEY5",
    "PKY1", "PKY2", "PKY3", "PKY4", "PKY5", "PKY6", "PKY7",
    "PHY1", "PHY2", "PVY1", "PVY2", "PVY3", "PVY4",
    "PPY1", "PPY2", "PPY3", "PPY4", "PPY5",
    "RBY1", "RBY2", "RBY3", "RBY4", "RCY1", "REY1", "REY2", "RHY1", "RHY2",
    "RVY1", "RVY2", "RVY3", "RVY4", "RVY5", "RVY6",
    # aligning moment (4.E31-4.E49, 4.E71-4.E78)
    "QBZ1", "QBZ2", "QBZ3", "QBZ4", "QBZ5", "QBZ9", "QBZ10", "QCZ1",
    "QDZ1", "QDZ2", "QDZ3", "QDZ4", "QDZ6", "QDZ7", "QDZ8", "QDZ9", "QDZ10", "QDZ11",
    "QEZ1", "QEZ2", "QEZ3", "QEZ4", "QEZ5", "QHZ1", "QHZ2", "QHZ3", "QHZ4",
    "SSZ1", "SSZ2", "SSZ3", "SSZ4", "PPZ1", "PPZ2",
    # rolling resistance (4.E70)
    "QSY1", "QSY2", "QSY3", "QSY4", "QSY5", "QSY6", "QSY7", "QSY8",
)  # fmt: skip
N_MF61_PARAM = len(MF61_PARAM_NAMES)


def _slot(name: str) -> int:
    return MF61_PARAM_NAMES.index(name)


P_FNOMIN = _slot("FNOMIN")
P_UNLOADED_RADIUS = _slot("UNLOADED_RADIUS")
P_LONGVL = _slot("LONGVL")
P_INFLPRES = _slot("INFLPRES")
P_NOMPRES = _slot("NOMPRES")
P_FZMIN = _slot("FZMIN")
P_FZMAX = _slot("FZMAX")
P_LFZO = _slot("LFZO")
P_LCX = _slot("LCX")
P_LMUX = _slot("LMUX")
P_LEX = _slot("LEX")
P_LKX = _slot("LKX")
P_LHX = _slot("LHX")
P_LVX = _slot("LVX")
P_LXAL = _slot("LXAL")
P_LCY = _slot("LCY")
P_LMUY = _slot("LMUY")
P_LEY = _slot("LEY")
P_LKY = _slot("LKY")
P_LKYC = _slot("LKYC")
P_LKZC = _slot("LKZC")
P_LHY = _slot("LHY")
P_LVY = _slot("LVY")
P_LYKA = _slot("LYKA")
P_LVYKA = _slot("LVYKA")
P_LTR = _slot("LTR")
P_LRES = _slot("LRES")
P_LS = _slot("LS")
P_LMY = _slot("LMY")
P_PCX1 = _slot("PCX1")
P_PDX1 = _slot("PDX1")
P_PDX2 = _slot("PDX2")
P_PDX3 = _slot("PDX3")
P_PEX1 = _slot("PEX1")
P_PEX2 = _slot("PEX2")
P_PEX3 = _slot("PEX3")
P_PEX4 = _slot("PEX4")
P_PKX1 = _slot("PKX1")
P_PKX2 = _slot("PKX2")
P_PKX3 = _slot("PKX3")
P_PHX1 = _slot("PHX1")
P_PHX2 = _slot("PHX2")
P_PVX1 = _slot("PVX1")
P_PVX2 = _slot("PVX2")
P_PPX1 = _slot("PPX1")
P_PPX2 = _slot("PPX2")
P_PPX3 = _slot("PPX3")
P_PPX4 = _slot("PPX4")
P_RBX1 = _slot("RBX1")
P_RBX2 = _slot("RBX2")
P_RBX3 = _slot("RBX3")
P_RCX1 = _slot("RCX1")
P_REX1 = _slot("REX1")
P_REX2 = _slot("REX2")
P_RHX1 = _slot("RHX1")
P_PCY1 = _slot("PCY1")
P_PDY1 = _slot("PDY1")
P_PDY2 = _slot("PDY2")
P_PDY3 = _slot("PDY3")
P_PEY1 = _slot("PEY1")
P_PEY2 = _slot("PEY2")
P_PEY3 = _slot("PEY3")
P_PEY4 = _slot("PEY4")
P_PEY5 = _slot("PEY5")
P_PKY1 = _slot("PKY1")
P_PKY2 = _slot("PKY2")
P_PKY3 = _slot("PKY3")
P_PKY4 = _slot("PKY4")
P_PKY5 = _slot("PKY5")
P_PKY6 = _slot("PKY6")
P_PKY7 = _slot("PKY7")
P_PHY1 = _slot("PHY1")
P_PHY2 = _slot("PHY2")
P_PVY1 = _slot("PVY1")
P_PVY2 = _slot("PVY2")
P_PVY3 = _slot("PVY3")
P_PVY4 = _slot("PVY4")
P_PPY1 = _slot("PPY1")
P_PPY2 = _slot("PPY2")
P_PPY3 = _slot("PPY3")
P_PPY4 = _slot("PPY4")
P_PPY5 = _slot("PPY5")
P_RBY1 = _slot("RBY1")
P_RBY2 = _slot("RBY2")
P_RBY3 = _slot("RBY3")
P_RBY4 = _slot("RBY4")
P_RCY1 = _slot("RCY1")
P_REY1 = _slot("REY1")
P_REY2 = _slot("REY2")
P_RHY1 = _slot("RHY1")
P_RHY2 = _slot("RHY2")
P_RVY1 = _slot("RVY1")
P_RVY2 = _slot("RVY2")
P_RVY3 = _slot("RVY3")
P_RVY4 = _slot("RVY4")
P_RVY5 = _slot("RVY5")
P_RVY6 = _slot("RVY6")
P_QBZ1 = _slot("QBZ1")
P_QBZ2 = _slot("QBZ2")
P_QBZ3 = _slot("QBZ3")
P_QBZ4 = _slot("QBZ4")
P_QBZ5 = _slot("QBZ5")
P_QBZ9 = _slot("QBZ9")
P_QBZ10 = _slot("QBZ10")
P_QCZ1 = _slot("QCZ1")
P_QDZ1 = _slot("QDZ1")
P_QDZ2 = _slot("QDZ2")
P_QDZ3 = _slot("QDZ3")
P_QDZ4 = _slot("QDZ4")
P_QDZ6 = _slot("QDZ6")
P_QDZ7 = _slot("QDZ7")
P_QDZ8 = _slot("QDZ8")
P_QDZ9 = _slot("QDZ9")
P_QDZ10 = _slot("QDZ10")
P_QDZ11 = _slot("QDZ11")
P_QEZ1 = _slot("QEZ1")
P_QEZ2 = _slot("QEZ2")
P_QEZ3 = _slot("QEZ3")
P_QEZ4 = _slot("QEZ4")
P_QEZ5 = _slot("QEZ5")
P_QHZ1 = _slot("QHZ1")
P_QHZ2 = _slot("QHZ2")
P_QHZ3 = _slot("QHZ3")
P_QHZ4 = _slot("QHZ4")
P_SSZ1 = _slot("SSZ1")
P_SSZ2 = _slot("SSZ2")
P_SSZ3 = _slot("SSZ3")
P_SSZ4 = _slot("SSZ4")
P_PPZ1 = _slot("PPZ1")
P_PPZ2 = _slot("PPZ2")
P_QSY1 = _slot("QSY1")
P_QSY2 = _slot("QSY2")
P_QSY3 = _slot("QSY3")
P_QSY4 = _slot("QSY4")
P_QSY5 = _slot("QSY5")
P_QSY6 = _slot("QSY6")
P_QSY7 = _slot("QSY7")
P_QSY8 = _slot("QSY8")

# --- input ranges and numerical guards (compile-time constants) ---------------------------
FZ_FLOOR_FRAC = 0.01  # coefficients are never evaluated below 1 % of FNOMIN
FZ_INPUT_MAX_N = 1.0e9  # fz_n is clamped to this (forces stay finite)
SLIP_INPUT_MAX = 1.0e6  # |kappa|, |tan_alpha| clamped to this (the curves are flat there)
GAMMA_INPUT_MAX_RAD = 0.5 * math.pi  # |gamma| clamped to this
MU_SCALE_MIN = 1e-6  # mu_scale clamped to [MU_SCALE_MIN, MU_SCALE_MAX]: lambda_mu divides
MU_SCALE_MAX = 10.0  # Bt and Br (4.E40, 4.E45), so it may not reach zero
VX_MY_MAX_MPS = 1000.0  # |vx| cap in the (Vx/V0)^4 rolling-resistance term
SLIDE_MAX = 1.0e6  # cap of OUT_KAPPA_SLIDE / OUT_TAN_ALPHA_SLIDE (curve without peak)
SLIDE_FRACTION_NO_PEAK = 0.99  # C <= 1: "sliding" where the curve reaches 99 % of its limit
SERIES_MAX_ARG = 2e-3  # below this |B x| the cosine weighting uses its Taylor series
_TINY = 1e-9  # floor of C*D (N), |K_ya| (N/rad), G0: never reached with a sane file

# --- elementary functions, inlined ------------------------------------------------------
# libm calls are not inlined, clobber every vector register and cost 10-20 ns each; the
# kernel needs about 35 of them. These replacements are accurate to about 1 ulp (tested in
# tests/test_tire_mf61.py against math.atan / math.sin / math.cos) and branch-free.
#
# atan: argument reduction at the centres 0, 1/2, 1, 3/2, inf (one division), then
# atan(u) = u + u z P(z), z = u^2, |u| <= 7/16, P of degree 10: Chebyshev interpolation of
# (atan(u) - u) / (u z) on z in [0, (7/16)^2] at 11 nodes in 60-digit arithmetic (mpmath),
# relative error 1.7e-17 before rounding.
_AT0 = -0.33333333333333323666
_AT1 = 0.19999999999987767999
_AT2 = -0.14285714283148639559
_AT3 = 0.1111111090056047561
_AT4 = -0.090909001955601480029
_AT5 = 0.076920873487671681887
_AT6 = -0.066632392991071364433
_AT7 = 0.058477247206451062769
_AT8 = -0.050339427764858483166
_AT9 = 0.03782521866106712056
_AT10 = -0.017547235157290004725
_ATAN_HALF = 0.4636476090008061  # atan(1/2)
_ATAN_3HALF = 0.982793723247329  # atan(3/2)
_PI_4 = 0.7853981633974483
_PI_2 = 1.5707963267948966
# sin on [-pi/2, pi/2]: x + x z Q(z), Q of degree 7 fitted the same way on [0, (pi/2)^2],
# absolute error 1.3e-18 before rounding. |x| <= pi is folded with pi = _PI_HI + _PI_LO
# (cos with pi/2 = _PI_2 + _PI_2_LO); larger |x| (never in the model) goes to libm.
_SN0 = -0.16666666666666666633
_SN1 = 0.0083333333333333158688
_SN2 = -0.00019841269841254973769
_SN3 = 2.7557319219163233416e-6
_SN4 = -2.5052107616996182891e-8
_SN5 = 1.6058977312464087621e-10
_SN6 = -7.6439702967985720524e-13
_SN7 = 2.7314447669863993424e-15
_PI_HI = 3.141592653589793
_PI_LO = 1.2246467991473532e-16
_PI_2_LO = 6.123233995736766e-17


@nb.njit(cache=True, inline="always")
def _atan(x: float) -> float:
    """``atan(x)`` to about 1 ulp, branch-free (see the constants above)."""
    ax = abs(x)
    # interval of ax: [0, 7/16), [7/16, 11/16), [11/16, 19/16), [19/16, 39/16), [39/16, inf)
    i1 = ax >= 0.4375
    i2 = ax >= 0.6875
    i3 = ax >= 1.1875
    i4 = ax >= 2.4375
    c = (0.5 if i1 else 0.0) + (0.5 if i2 else 0.0) + (0.5 if i3 else 0.0)  # centre, exact
    num = -1.0 if i4 else ax - c
    den = ax if i4 else 1.0 + c * ax
    base = _PI_2 if i4 else (_ATAN_3HALF if i3 else (_PI_4 if i2 else (_ATAN_HALF if i1 else 0.0)))
    u = num / den  # atan(ax) = base + atan(u), |u| <= 7/16
    z = u * u
    z2 = z * z
    z4 = z2 * z2
    q0 = (_AT0 + _AT1 * z) + (_AT2 + _AT3 * z) * z2
    q1 = (_AT4 + _AT5 * z) + (_AT6 + _AT7 * z) * z2
    q2 = (_AT8 + _AT9 * z) + _AT10 * z2
    poly = q0 + (q1 + q2 * z4) * z4
    return math.copysign(base + (u + u * z * poly), x)


@nb.njit(cache=True, inline="always")
def _sin_core(y: float) -> float:
    """``sin(y)`` for ``|y| <= pi/2``."""
    z = y * y
    z2 = z * z
    z4 = z2 * z2
    poly = ((_SN0 + _SN1 * z) + (_SN2 + _SN3 * z) * z2) + (
        (_SN4 + _SN5 * z) + (_SN6 + _SN7 * z) * z2
    ) * z4
    return y + y * z * poly


@nb.njit(cache=True, inline="always")
def _sin(x: float) -> float:
    """``sin(x)`` to about 1 ulp (absolute) for ``|x| <= pi``; libm beyond."""
    ax = abs(x)
    if not ax <= _PI_HI:
        return math.sin(x)
    folded = min(ax, (_PI_HI - ax) + _PI_LO)  # sin(pi - a) = sin(a)
    return math.copysign(_sin_core(folded), x)


@nb.njit(cache=True, inline="always")
def _cos(x: float) -> float:
    """``cos(x) = sin(pi/2 - |x|)`` to about 1 ulp (absolute) for ``|x| <= pi``."""
    ax = abs(x)
    if not ax <= _PI_HI:
        return math.cos(x)
    return _sin_core((_PI_2 - ax) + _PI_2_LO)


@nb.njit(cache=True, inline="always")
def _mf_arg(y: float, e: float) -> float:
    """Inner Magic Formula argument ``y - E (y - atan y)`` (4.E9)."""
    return (1.0 - e) * y + e * _atan(y)


@nb.njit(cache=True, inline="always")
def _mf_sin(b: float, c: float, e: float, x: float) -> float:
    """``sin[C atan{B x - E (B x - atan(B x))}]``, the Magic Formula (4.E9, 4.E19)."""
    return _sin(c * _atan(_mf_arg(b * x, e)))


@nb.njit(cache=True, inline="always")
def _mf_cos(b: float, c: float, e: float, x: float) -> float:
    """``cos[C atan{B x - E (B x - atan(B x))}]``, the cosine version (4.E51, 4.E73).

    For ``|B x| <= SERIES_MAX_ARG`` (the normalising weights (4.E52) of files with a tiny
    RHX1) its Taylor series in ``y = B x`` is used:
    ``atan(y - E (y - atan y)) = y - (1 + E) y^3 / 3 + (3 + 8 E) y^5 / 15 + O(y^7)``,
    then ``cos w = 1 - w^2/2 + w^4/24 - w^6/720``; the error is below 1e-19.
    """
    y = b * x
    if abs(y) <= SERIES_MAX_ARG:
        y2 = y * y
        w = c * y * (1.0 - y2 * ((1.0 + e) / 3.0 - y2 * ((3.0 + 8.0 * e) / 15.0)))
        w2 = w * w
        return 1.0 - w2 * (0.5 - w2 * (1.0 / 24.0 - w2 * (1.0 / 720.0)))
    return _cos(c * _atan(_mf_arg(y, e)))


@nb.njit(cache=True, inline="always")
def _peak_start(c: float, e: float) -> tuple[float, float]:
    """Target ``T`` and start ``u0`` of the peak search, see :func:`_peak_step`.

    For ``C > 1`` the curve ``D sin[C atan{u - E (u - atan u)}]`` peaks where the
    ``atan`` argument equals ``T = tan(pi / (2 C))``. For ``C <= 1`` it has no interior
    peak; ``T`` is then where it reaches ``SLIDE_FRACTION_NO_PEAK`` of its asymptote
    ``D sin(C pi / 2)``. ``g(u) = (1 - E) u + E atan(u) - T`` is strictly increasing for
    ``E < 1``; ``T`` and ``(T - E pi / 2) / (1 - E)`` both bound its root from below if
    ``E > 0`` and from above if ``E < 0``: the tighter one is the start.
    """
    c = max(c, 1e-3)
    if c > 1.0:
        a = 0.5 * math.pi / c
    else:
        a = math.asin(SLIDE_FRACTION_NO_PEAK * math.sin(0.5 * math.pi * c)) / c
    target = _sin(a) / _cos(a)
    u_bound = (target - e * _PI_2) / max(1.0 - e, 1e-12)
    u0 = max(target, u_bound) if e > 0.0 else min(target, u_bound)
    return target, min(max(u0, 1e-12), SLIDE_MAX)


@nb.njit(cache=True, inline="always")
def _peak_step(u: float, e: float, target: float) -> float:
    """One Halley step on ``g(u) = (1 - E) u + E atan(u) - T``.

    With ``n = g' (1 + u^2) = (1 - E)(1 + u^2) + E`` and ``g'' = -2 E u / (1 + u^2)^2``
    the step ``2 g g' / (2 g'^2 - g g'')`` is ``g n (1 + u^2) / (n^2 + E g u)``: one
    division. Convergence is cubic: from :func:`_peak_start`, two steps leave a relative
    error below 1e-9 for the (C, E) of real files (checked in the tests).
    """
    one_minus_e = max(1.0 - e, 1e-12)
    den = 1.0 + u * u
    g = one_minus_e * u + e * _atan(u) - target
    n = one_minus_e * den + e
    return min(max(u - g * n * den / (n * n + e * g * u), 0.5 * u), SLIDE_MAX)


@nb.njit(cache=True)
def mf61_forces(
    p: np.ndarray,
    kappa: float,
    tan_alpha: float,
    gamma_rad: float,
    fz_n: float,
    mu_scale: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Magic Formula 6.1 combined-slip forces and moments of one tire.

    Parameters
    ----------
    p : float64[N_MF61_PARAM]
        Coefficients packed by :func:`mf61_param_vector` (slots ``P_*``).
    kappa : float
        Longitudinal slip, positive when driving.
    tan_alpha : float
        ``alpha* = tan(alpha) sgn(Vcx)`` (4.E3), positive when the hub slides to +y.
    gamma_rad : float
        Inclination angle (rad); ``gamma* = sin(gamma)`` (4.E4).
    fz_n : float
        Normal load (N). At ``fz_n <= 0`` every output is 0 except the stiffness and
        sliding-limit slots, which are 1 (as in the dispatcher).
    mu_scale : float
        Road friction scale, multiplies ``LMUX`` and ``LMUY``.
    vx_mps : float
        Hub longitudinal speed, used only as ``|vx|`` in the rolling resistance.
    out : float64[N_TIRE_OUT]
        Written in place, every ``OUT_*`` slot of :mod:`simserver.core.tire_layout`:

        - ``OUT_FX``, ``OUT_FY``, ``OUT_MZ``: combined-slip forces and aligning moment
          (4.E50, 4.E58, 4.E71) in the file's own sign convention (a negative ``PKY1``
          gives ``Fy < 0`` for ``tan_alpha > 0``);
        - ``OUT_MY``: rolling-resistance moment magnitude (4.E70), >= 0;
        - ``OUT_C_KAPPA = Kxk`` (4.E15), ``OUT_C_ALPHA = |Kya|`` (4.E25);
        - ``OUT_KAPPA_SLIDE``, ``OUT_TAN_ALPHA_SLIDE``: slip magnitude at the peak of the
          pure-slip curve, on the side of the current slip's sign (+ at 0);
        - ``OUT_FX_PEAK = |Dx|``, ``OUT_FY_PEAK = |Dy|`` (4.E12, 4.E22).

    Notes
    -----
    Inputs are clamped to ``|kappa|, |tan_alpha| <= SLIP_INPUT_MAX``,
    ``|gamma| <= GAMMA_INPUT_MAX_RAD``, ``fz_n <= FZ_INPUT_MAX_N`` and
    ``MU_SCALE_MIN <= mu_scale <= MU_SCALE_MAX``, so that every output is finite for any
    finite input. ``Kxk`` and ``Kya`` are the slopes at the curves' own origins
    ``kappa = -SHx`` and ``tan_alpha = -SHy``; the slope at zero slip differs by
    ``O((B SH)^2)`` (6e-4 for ``Fy`` of the sample file at ``FNOMIN``). The code is
    ordered so that independent chains (the normalised weights, the two curves, the two
    peak searches) sit next to each other for the out-of-order core.
    """
    if not fz_n > 0.0:
        for i in range(out.shape[0]):
            out[i] = 0.0
        out[OUT_C_KAPPA] = 1.0
        out[OUT_C_ALPHA] = 1.0
        out[OUT_KAPPA_SLIDE] = 1.0
        out[OUT_TAN_ALPHA_SLIDE] = 1.0
        return
    kappa = min(max(kappa, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
    tan_alpha = min(max(tan_alpha, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
    gamma = min(max(gamma_rad, -GAMMA_INPUT_MAX_RAD), GAMMA_INPUT_MAX_RAD)
    mu = min(max(mu_scale, MU_SCALE_MIN), MU_SCALE_MAX)

    # --- operating point (4.E1)-(4.E8) ---------------------------------------------------
    fnomin = p[P_FNOMIN]
    r0 = p[P_UNLOADED_RADIUS]
    fz0 = fnomin * p[P_LFZO]  # F'z0 (4.E1)
    fz_lo = max(p[P_FZMIN], FZ_FLOOR_FRAC * fnomin)
    fz = min(max(fz_n, fz_lo), max(p[P_FZMAX], fz_lo))  # load the coefficients see
    load_scale = min(fz_n, FZ_INPUT_MAX_N) / fz  # 1 inside FZMIN..FZMAX
    dfz = (fz - fz0) / fz0  # (4.E2a)
    dfz2 = dfz * dfz
    fz_ratio = fz / fnomin
    p_nom = p[P_NOMPRES]
    p_infl = p[P_INFLPRES]
    dpi = (p_infl - p_nom) / p_nom if p_nom > 0.0 and p_infl > 0.0 else 0.0  # (4.E2b)
    dpi2 = dpi * dpi
    # the two libm calls first, while few values are live across them
    pow_load = math.pow(fz_ratio, p[P_QSY7])  # (4.E70)
    exp_kx = math.exp(p[P_PKX3] * dfz)  # (4.E15)
    lmux = p[P_LMUX] * mu  # lambda*_mux = lambda'_mux (4.E7, 4.E8: LMUV = 0, A_mu = 1)
    lmuy = p[P_LMUY] * mu
    gs = _sin(gamma)  # gamma* (4.E4)
    gs2 = gs * gs
    gs_abs = abs(gs)
    cos_a = 1.0 / math.sqrt(1.0 + tan_alpha * tan_alpha)  # |cos'alpha| (4.E6)

    # --- coefficients that need no stiffness ----------------------------------------------
    cx = p[P_PCX1] * p[P_LCX]  # (4.E11)
    mux = (
        (p[P_PDX1] + p[P_PDX2] * dfz)
        * (1.0 + p[P_PPX3] * dpi + p[P_PPX4] * dpi2)
        * (1.0 - p[P_PDX3] * gamma * gamma)
        * lmux
    )  # (4.E13)
    dx = mux * fz  # (4.E12)
    shx = (p[P_PHX1] + p[P_PHX2] * dfz) * p[P_LHX]  # (4.E17)
    svx = fz * (p[P_PVX1] + p[P_PVX2] * dfz) * p[P_LVX] * lmux  # (4.E18)
    kappa_x = kappa + shx  # (4.E10)
    ex0 = (p[P_PEX1] + p[P_PEX2] * dfz + p[P_PEX3] * dfz2) * p[P_LEX]
    ex = min(ex0 * (1.0 - p[P_PEX4] * (1.0 if kappa_x >= 0.0 else -1.0)), 1.0)  # (4.E14)

    cy = p[P_PCY1] * p[P_LCY]  # (4.E21)
    muy_g0 = (p[P_PDY1] + p[P_PDY2] * dfz) * (1.0 + p[P_PPY3] * dpi + p[P_PPY4] * dpi2) * lmuy
    muy = muy_g0 * (1.0 - p[P_PDY3] * gs2)  # (4.E23)
    dy = muy * fz  # (4.E22)
    ey0 = (p[P_PEY1] + p[P_PEY2] * dfz) * p[P_LEY]
    ppy1 = 1.0 + p[P_PPY1] * dpi
    ppy2 = 1.0 + p[P_PPY2] * dpi
    kyg0 = fz * (p[P_PKY6] + p[P_PKY7] * dfz) * (1.0 + p[P_PPY5] * dpi) * p[P_LKYC]  # (4.E30)
    svyg = fz * (p[P_PVY3] + p[P_PVY4] * dfz) * gs * p[P_LKYC] * lmuy  # (4.E28)
    svy_g0 = fz * (p[P_PVY1] + p[P_PVY2] * dfz) * p[P_LVY] * lmuy
    svy = svy_g0 + svyg  # (4.E29)
    shy_g0 = (p[P_PHY1] + p[P_PHY2] * dfz) * p[P_LHY]

    # combined-slip weights (4.E51)-(4.E57), (4.E59)-(4.E65): need no stiffness
    rbx2k = p[P_RBX2] * kappa
    bxa = (p[P_RBX1] + p[P_RBX3] * gs2) * p[P_LXAL] / math.sqrt(1.0 + rbx2k * rbx2k)  # (4.E54)
    cxa = p[P_RCX1]  # (4.E55)
    exa = min(p[P_REX1] + p[P_REX2] * dfz, 1.0)  # (4.E56)
    shxa = p[P_RHX1]  # (4.E57); alpha_s = tan_alpha + SHxa (4.E53)
    rby2a = p[P_RBY2] * (tan_alpha - p[P_RBY3])
    byk = (p[P_RBY1] + p[P_RBY4] * gs2) * p[P_LYKA] / math.sqrt(1.0 + rby2a * rby2a)  # (4.E62)
    cyk = p[P_RCY1]  # (4.E63)
    eyk = min(p[P_REY1] + p[P_REY2] * dfz, 1.0)  # (4.E64)
    shyk = p[P_RHY1] + p[P_RHY2] * dfz  # (4.E65); kappa_s = kappa + SHyk (4.E61)
    gxa0 = _mf_cos(bxa, cxa, exa, shxa)  # (4.E52)
    gyk0 = _mf_cos(byk, cyk, eyk, shyk)  # (4.E60)
    gxa_num = _mf_cos(bxa, cxa, exa, tan_alpha + shxa)
    gyk_num = _mf_cos(byk, cyk, eyk, kappa + shyk)
    gxa = max(gxa_num / max(gxa0, _TINY), 0.0)  # (4.E51), > 0
    gyk = max(gyk_num / max(gyk0, _TINY), 0.0)  # (4.E59), > 0
    rvy4a = p[P_RVY4] * tan_alpha
    dvyk = muy * fz * (p[P_RVY1] + p[P_RVY2] * dfz + p[P_RVY3] * gs) / math.sqrt(1.0 + rvy4a * rvy4a)  # (4.E67)  # noqa: E501
    svyk = dvyk * _sin(p[P_RVY5] * _atan(p[P_RVY6] * kappa)) * p[P_LVYKA]  # (4.E66)

    # --- stiffnesses (4.E15), (4.E25) ---------------------------------------------------
    kxk = fz * (p[P_PKX1] + p[P_PKX2] * dfz) * exp_kx * (1.0 + p[P_PPX1] * dpi + p[P_PPX2] * dpi2) * p[P_LKX]  # noqa: E501
    kya_g0 = (
        p[P_PKY1] * fz0 * ppy1 * p[P_LKY]
        * _sin(p[P_PKY4] * _atan(fz / fz0 / max((p[P_PKY2] + p[P_PKY5] * gs2) * ppy2, _TINY)))
    )  # fmt: skip
    kya = kya_g0 * (1.0 - p[P_PKY3] * gs_abs)  # (4.E25)
    if p[P_PKY5] != 0.0 and gs != 0.0:  # K_ya at gamma = 0 for F'y (4.E74)
        kya_g0 = (
            p[P_PKY1] * fz0 * ppy1 * p[P_LKY]
            * _sin(p[P_PKY4] * _atan(fz / fz0 / max(p[P_PKY2] * ppy2, _TINY)))
        )  # fmt: skip
    kya_safe = kya if abs(kya) > _TINY else math.copysign(_TINY, p[P_PKY1])  # K'ya (4.E39)
    shy = shy_g0 + (kyg0 * gs - svyg) / kya_safe  # (4.E27)
    alpha_y = tan_alpha + shy  # (4.E20)
    ey = min(
        ey0 * (1.0 + p[P_PEY5] * gs2 - (p[P_PEY3] + p[P_PEY4] * gs) * (1.0 if alpha_y >= 0.0 else -1.0)),  # noqa: E501
        1.0,
    )  # (4.E24)
    bx = kxk / max(cx * dx, _TINY)  # (4.E16)
    by = kya / max(cy * dy, _TINY)  # (4.E26)

    # --- pure slip (4.E9), (4.E19) and combined slip (4.E50), (4.E58) ---------------------
    fx0 = dx * _mf_sin(bx, cx, ex, kappa_x) + svx  # (4.E9)
    fy0 = dy * _mf_sin(by, cy, ey, alpha_y) + svy  # (4.E19)
    fx = gxa * fx0  # (4.E50)
    fy = gyk * fy0 + svyk  # (4.E58)

    # --- sliding limits: the two peak searches side by side -----------------------------
    side_x = 1.0 if kappa >= 0.0 else -1.0
    side_y = 1.0 if tan_alpha >= 0.0 else -1.0
    ex_side = min(ex0 * (1.0 - p[P_PEX4] * side_x), 1.0)
    ey_side = min(ey0 * (1.0 + p[P_PEY5] * gs2 - (p[P_PEY3] + p[P_PEY4] * gs) * side_y), 1.0)
    tx, ux = _peak_start(cx, ex_side)
    ty, uy = _peak_start(cy, ey_side)
    ux = _peak_step(ux, ex_side, tx)
    uy = _peak_step(uy, ey_side, ty)
    ux = _peak_step(ux, ex_side, tx)
    uy = _peak_step(uy, ey_side, ty)
    kappa_slide = abs(side_x * ux / max(abs(bx), _TINY) - shx)  # peak at B |kappa_x| = u
    tan_alpha_slide = abs(side_y * uy / max(abs(by), _TINY) - shy)

    # --- aligning moment (4.E31)-(4.E47), (4.E71)-(4.E78) --------------------------------
    if gs == 0.0:
        fy0_g0 = fy0
    else:  # Fy0 at gamma = 0 for F'y (4.E74): (4.E19)-(4.E29) without the camber terms
        alpha_y0 = tan_alpha + shy_g0
        dy0 = muy_g0 * fz
        ey_g0 = min(ey0 * (1.0 - p[P_PEY3] * (1.0 if alpha_y0 >= 0.0 else -1.0)), 1.0)
        by_g0 = kya_g0 / max(cy * dy0, _TINY)
        fy0_g0 = dy0 * _mf_sin(by_g0, cy, ey_g0, alpha_y0) + svy_g0
    fy_prime = gyk * fy0_g0  # (4.E74)
    sht = p[P_QHZ1] + p[P_QHZ2] * dfz + (p[P_QHZ3] + p[P_QHZ4] * dfz) * gs  # (4.E35)
    alpha_t = tan_alpha + sht  # (4.E34)
    alpha_r = tan_alpha + shy + svy / kya_safe  # (4.E37), (4.E38)
    bt = (
        (p[P_QBZ1] + p[P_QBZ2] * dfz + p[P_QBZ3] * dfz2)
        * (1.0 + p[P_QBZ4] * gs + p[P_QBZ5] * gs_abs)
        * p[P_LKY]
        / lmuy
    )  # (4.E40)
    ct = p[P_QCZ1]  # (4.E41)
    dt = (
        fz * (r0 / fz0) * (p[P_QDZ1] + p[P_QDZ2] * dfz) * (1.0 - p[P_PPZ1] * dpi) * p[P_LTR]
        * (1.0 + p[P_QDZ3] * gs_abs + p[P_QDZ4] * gs2)
    )  # (4.E42), (4.E43); their sgn(Vcx) cancels that of cos'alpha  # fmt: skip
    et = min(
        (p[P_QEZ1] + p[P_QEZ2] * dfz + p[P_QEZ3] * dfz2)
        * (1.0 + (p[P_QEZ4] + p[P_QEZ5] * gs) * (2.0 / math.pi) * _atan(bt * ct * alpha_t)),
        1.0,
    )  # (4.E44)
    br = p[P_QBZ9] * p[P_LKY] / lmuy + p[P_QBZ10] * by * cy  # (4.E45)
    dr = (
        fz * r0
        * ((p[P_QDZ6] + p[P_QDZ7] * dfz) * p[P_LRES]
           + ((p[P_QDZ8] + p[P_QDZ9] * dfz) * (1.0 + p[P_PPZ2] * dpi)
              + (p[P_QDZ10] + p[P_QDZ11] * dfz) * gs_abs) * gs * p[P_LKZC])
        * lmuy * cos_a
    )  # (4.E47); sgn(Vcx) cancels that of cos'alpha  # fmt: skip
    # (4.E77), (4.E78): sgn(alpha) dropped, t and Mzr are even in alpha_eq
    kk = kxk / kya_safe * kappa
    alpha_t_eq = math.sqrt(alpha_t * alpha_t + kk * kk)
    alpha_r_eq = math.sqrt(alpha_r * alpha_r + kk * kk)
    t = dt * _mf_cos(bt, ct, et, alpha_t_eq) * cos_a  # (4.E73)
    br_ar = br * alpha_r_eq
    mzr = dr / math.sqrt(1.0 + br_ar * br_ar)  # (4.E75), C_r = 1: cos(atan x) = 1/sqrt(1+x^2)
    s = r0 * (p[P_SSZ1] + p[P_SSZ2] * fy / fz0 + (p[P_SSZ3] + p[P_SSZ4] * dfz) * gs) * p[P_LS]  # (4.E76)  # noqa: E501
    mz = -t * fy_prime + mzr + s * fx  # (4.E71), (4.E72)

    # --- rolling resistance (4.E70, with Fz0 = FNOMIN in front) -------------------------
    v0 = p[P_LONGVL]
    vr = min(abs(vx_mps), VX_MY_MAX_MPS) / v0 if v0 > 0.0 else 0.0
    vr2 = vr * vr
    my = (
        r0 * fnomin * p[P_LMY] * pow_load
        * (p[P_QSY1] + p[P_QSY2] * fx / fnomin + p[P_QSY3] * vr + p[P_QSY4] * vr2 * vr2
           + (p[P_QSY5] + p[P_QSY6] * fz_ratio) * gamma * gamma)
    )  # fmt: skip
    if dpi != 0.0:
        my *= math.pow(1.0 + dpi, p[P_QSY8])

    out[OUT_FX] = fx * load_scale
    out[OUT_FY] = fy * load_scale
    out[OUT_MZ] = mz * load_scale
    out[OUT_MY] = max(my, 0.0) * load_scale
    out[OUT_C_KAPPA] = kxk * load_scale
    out[OUT_C_ALPHA] = abs(kya) * load_scale
    out[OUT_KAPPA_SLIDE] = min(max(kappa_slide, _TINY), SLIDE_MAX)
    out[OUT_TAN_ALPHA_SLIDE] = min(max(tan_alpha_slide, _TINY), SLIDE_MAX)
    out[OUT_FX_PEAK] = abs(dx) * load_scale
    out[OUT_FY_PEAK] = abs(dy) * load_scale


def mf61_param_vector(coeffs: dict[str, float]) -> np.ndarray:
    """Pack MF 6.1 coefficients into the kernel's parameter vector.

    Parameters
    ----------
    coeffs : dict[str, float]
        Every name of :data:`MF61_PARAM_NAMES` (upper case), for example the result of
        :func:`simserver.adapters.tir_file.mf61_coefficients`. Extra keys are ignored.

    Returns
    -------
    numpy.ndarray
        float64, length :data:`N_MF61_PARAM`, slot ``P_<NAME>`` holding ``coeffs[NAME]``.

    Raises
    ------
    ValueError
        If a name is missing or a value is not a finite real number.
    """
    missing = [name for name in MF61_PARAM_NAMES if name not in coeffs]
    if missing:
        raise ValueError(f"MF 6.1 coefficients missing: {', '.join(missing)}")
    vec = np.empty(N_MF61_PARAM, dtype=np.float64)
    for i, name in enumerate(MF61_PARAM_NAMES):
        value = coeffs[name]
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise ValueError(f"MF 6.1 coefficient {name} is not a number: {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"MF 6.1 coefficient {name} is not finite: {value!r}")
        vec[i] = float(value)
    return vec
