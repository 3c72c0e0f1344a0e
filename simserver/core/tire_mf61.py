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

The book's forms are kept for (4.E43) (``QDZ3 |gamma*|``; MFeval reads a signed gamma
there) and (4.E77)-(4.E78) (``alpha_eq = sqrt(alpha^2 + (Kxk/Kya)^2 kappa^2)`` on the
tangents, as everywhere in MF 6.1). ``gamma* = sin(gamma)`` throughout, except the
``gamma^2`` of (4.E13) and (4.E70), which MF-Tyre takes on the angle itself.

Inputs follow :mod:`simserver.core.tire`: ``tan_alpha`` is MF's ``alpha*`` (4.E3), so
``sgn(Vcx)`` never appears again; in (4.E42) and (4.E47) it multiplies ``cos'alpha``
(4.E6), which carries the same sign, and the two cancel. ``cos'alpha`` is therefore
``1 / sqrt(1 + tan_alpha^2)``.

Load range: the coefficient polynomials in ``dfz`` are a fit over the file's
``FZMIN..FZMAX``. Outside it (or below ``0.01 FNOMIN``) the model is evaluated at the
clamped load ``Fz_c`` and every force, moment, stiffness and peak is multiplied by
``Fz / Fz_c``: linear in load beyond the fitted range, and going to zero with ``Fz``.
Inside the range this is exactly MF 6.1.

Speed: the kernel evaluates about forty atan / sin, each a 10-20 ns libm call that
cannot be vectorised. Here they are branch-free polynomials (about 1 ulp), and the
sixteen Magic Formula curves of one call are evaluated eight at a time in a loop the
compiler turns into SIMD code (:func:`_mf_lanes`; its scratch is on the stack).

Not modelled: turn slip and spin (zeta = 1), speed-dependent friction ``LMUV``,
overturning moment ``Mx``, low-speed smoothing of ``My`` (the caller applies ``My``
against wheel spin), transient (relaxation) behaviour, which the lagged slip states of
SAE 950311 provide.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

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
_TINY = 1e-9  # floor of C*D (N), |K_ya| (N/rad), G0: never reached with a sane file

# Compilation: fused multiply-add allowed (and nothing else of fastmath: NaN and inf keep
# their IEEE meaning); division by zero yields inf instead of raising, which removes a
# test and a branch per division (every division here has a non-zero denominator).
_JIT_OPTIONS = {"cache": True, "fastmath": {"contract"}, "error_model": "numpy"}

# --- elementary functions ----------------------------------------------------------------
# libm calls are not inlined, clobber every vector register and cost 10-20 ns each, and
# they cannot be vectorised; the kernel needs about 35 of them. These replacements are
# accurate to about 1 ulp (tested in tests/test_tire_mf61.py against math.atan / math.sin)
# and branch-free, so that the compiler vectorises them (see _mf_lanes).
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
# absolute error 1.3e-18 before rounding. Other arguments are reduced by 2 pi (a 33-bit
# head, exact for |n| < 2^20, and a tail) and folded with pi = _PI_HI + _PI_LO.
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
_TWO_PI_HI = 6.2831853069365025
_TWO_PI_LO = 2.430840202602477e-10
_INV_TWO_PI = 0.15915494309189535
_ROUND_MAGIC = 6755399441055744.0  # 1.5 * 2^52: (x + M) - M rounds x to an integer


@nb.njit(inline="always", **_JIT_OPTIONS)
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


@nb.njit(inline="always", **_JIT_OPTIONS)
def _sin_core(y: float) -> float:
    """``sin(y)`` for ``|y| <= pi/2``."""
    z = y * y
    z2 = z * z
    z4 = z2 * z2
    poly = ((_SN0 + _SN1 * z) + (_SN2 + _SN3 * z) * z2) + (
        (_SN4 + _SN5 * z) + (_SN6 + _SN7 * z) * z2
    ) * z4
    return y + y * z * poly


@nb.njit(inline="always", **_JIT_OPTIONS)
def _sin(x: float) -> float:
    """``sin(x)`` to about 1 ulp (absolute) for ``|x| < 2^20``; libm beyond (never here)."""
    if not abs(x) < 1048576.0:
        return math.sin(x)
    n = (x * _INV_TWO_PI + _ROUND_MAGIC) - _ROUND_MAGIC  # nearest integer
    r = (x - n * _TWO_PI_HI) - n * _TWO_PI_LO  # |r| <= pi
    ar = abs(r)
    return math.copysign(_sin_core(min(ar, (_PI_HI - ar) + _PI_LO)), r)  # sin(pi - a) = sin a


# --- the Magic Formula, eight curves at a time ----------------------------------------------
N_LANES = 8


@intrinsic
def _stack_lanes(typingctx: object) -> tuple:
    """Pointer to ``N_LANES`` float64 on the stack of the compiled caller (an alloca).

    Stack scratch, not a heap allocation: it lets the compiler vectorise the lane loop of
    :func:`_mf_lanes` (numba has no other allocation-free local array).
    """
    sig = types.CPointer(types.float64)()

    def codegen(context: object, builder: object, signature: object, args: object) -> object:
        return cgutils.alloca_once(builder, context.get_value_type(types.float64), size=N_LANES)

    return sig, codegen


@nb.njit(**_JIT_OPTIONS)
def _mf_lanes(
    y: tuple[float, ...], e: tuple[float, ...], c: tuple[float, ...], k: tuple[float, ...]
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Eight Magic Formula evaluations in one vectorised loop.

    For each lane ``i``: ``theta_i = atan{y_i - E_i (y_i - atan y_i)}`` (the argument of
    (4.E9), (4.E19), (4.E51), (4.E59), (4.E73)) and ``s_i = sin(C_i theta_i + K_i)``: the
    Magic Formula for ``K = 0``, its cosine version for ``K = pi/2``. ``E = 0`` gives a
    plain ``theta = atan(y)``.

    Parameters
    ----------
    y, e, c, k : tuple of N_LANES floats
        ``B x``, ``E``, ``C``, ``K`` per lane.

    Returns
    -------
    theta, s : tuple of N_LANES floats
    """
    yb = nb.carray(_stack_lanes(), (N_LANES,))
    eb = nb.carray(_stack_lanes(), (N_LANES,))
    cb = nb.carray(_stack_lanes(), (N_LANES,))
    kb = nb.carray(_stack_lanes(), (N_LANES,))
    tb = nb.carray(_stack_lanes(), (N_LANES,))
    sb = nb.carray(_stack_lanes(), (N_LANES,))
    for i in range(N_LANES):
        yb[i] = y[i]
        eb[i] = e[i]
        cb[i] = c[i]
        kb[i] = k[i]
    for i in range(N_LANES):  # branch-free body: the compiler makes it one vector loop
        yi = yb[i]
        ei = eb[i]
        theta = _atan((1.0 - ei) * yi + ei * _atan(yi))
        w = cb[i] * theta + kb[i]
        n = (w * _INV_TWO_PI + _ROUND_MAGIC) - _ROUND_MAGIC
        r = (w - n * _TWO_PI_HI) - n * _TWO_PI_LO  # |r| <= pi
        ar = abs(r)
        tb[i] = theta
        sb[i] = math.copysign(_sin_core(min(ar, (_PI_HI - ar) + _PI_LO)), r)
    return (
        (tb[0], tb[1], tb[2], tb[3], tb[4], tb[5], tb[6], tb[7]),
        (sb[0], sb[1], sb[2], sb[3], sb[4], sb[5], sb[6], sb[7]),
    )


# --- peak of a Magic Formula curve ------------------------------------------------------------


@nb.njit(inline="always", **_JIT_OPTIONS)
def _peak_target(c: float) -> float:
    """``T``: the curve ``D sin[C atan{u - E (u - atan u)}]`` peaks where ``atan{.} = T``.

    ``T = tan(pi / (2 C))`` for ``C > 1``. For ``C <= 1`` there is no interior peak; ``T``
    is then where the curve reaches ``SLIDE_FRACTION_NO_PEAK`` of its asymptote
    ``D sin(C pi / 2)``.
    """
    c = max(c, 1e-3)
    if c > 1.0:
        a = 0.5 * math.pi / c
    else:
        a = math.asin(SLIDE_FRACTION_NO_PEAK * math.sin(0.5 * math.pi * c)) / c
    return _sin_core(a) / _sin_core((_PI_2 - a) + _PI_2_LO)  # 0 < a < pi/2


@nb.njit(inline="always", **_JIT_OPTIONS)
def _peak_start(target: float, e: float) -> float:
    """Start of the search for the root of ``g(u) = (1 - E) u + E atan(u) - T``.

    ``g`` is strictly increasing for ``E < 1``; ``T`` and ``(T - E pi / 2) / (1 - E)`` both
    bound the root from below if ``E > 0`` and from above if ``E < 0``: the tighter one.
    """
    u_bound = (target - e * _PI_2) / max(1.0 - e, 1e-12)
    u0 = max(target, u_bound) if e > 0.0 else min(target, u_bound)
    return min(max(u0, 1e-12), SLIDE_MAX)


@nb.njit(inline="always", **_JIT_OPTIONS)
def _peak_step(u: float, atan_u: float, e: float, target: float) -> float:
    """One Halley step on ``g(u) = (1 - E) u + E atan(u) - T`` (``atan_u = atan(u)``).

    With ``n = g' (1 + u^2) = (1 - E)(1 + u^2) + E`` and ``g'' = -2 E u / (1 + u^2)^2``
    the step ``2 g g' / (2 g'^2 - g g'')`` is ``g n (1 + u^2) / (n^2 + E g u)``: one
    division. Convergence is cubic: from :func:`_peak_start`, two steps leave a relative
    error below 1e-5 for C in [1.05, 2.5] and E in [-3, 0.8], about 1e-8 for the sample
    file's curves (checked in the tests).
    """
    one_minus_e = max(1.0 - e, 1e-12)
    den = 1.0 + u * u
    g = one_minus_e * u + e * atan_u - target
    n = one_minus_e * den + e
    return min(max(u - g * n * den / max(n * n + e * g * u, _TINY), 0.5 * u), SLIDE_MAX)


@nb.njit(**_JIT_OPTIONS)
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
    ``O((B SH)^2)`` (6e-4 for ``Fy`` of the sample file at ``FNOMIN``).

    The Magic Formula curves (and the atan of the peak searches) are evaluated eight at a
    time by :func:`_mf_lanes`, in two rounds: what needs no stiffness, then what does.
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
    inv_fz0 = 1.0 / fz0
    inv_fnomin = 1.0 / fnomin
    dfz = (fz - fz0) * inv_fz0  # (4.E2a)
    dfz2 = dfz * dfz
    fz_ratio = fz * inv_fnomin
    p_nom = p[P_NOMPRES]
    p_infl = p[P_INFLPRES]
    dpi = (p_infl - p_nom) / p_nom if p_nom > 0.0 and p_infl > 0.0 else 0.0  # (4.E2b)
    dpi2 = dpi * dpi
    # the two libm calls early, while few values are live across them
    pow_load = math.pow(fz_ratio, p[P_QSY7])  # (Fz / Fz0)^QSY7 (4.E70)
    exp_kx = math.exp(p[P_PKX3] * dfz)  # (4.E15)
    lmux = p[P_LMUX] * mu  # lambda*_mux = lambda'_mux (4.E7, 4.E8: LMUV = 0, A_mu = 1)
    lmuy = max(p[P_LMUY] * mu, _TINY)
    inv_lmuy = 1.0 / lmuy  # Bt, Br (4.E40, 4.E45)
    gs = _sin(gamma) if gamma != 0.0 else 0.0  # gamma* (4.E4)
    gs2 = gs * gs
    gs_abs = abs(gs)
    cos_a = 1.0 / math.sqrt(1.0 + tan_alpha * tan_alpha)  # |cos'alpha| (4.E6)

    # --- longitudinal coefficients (4.E10)-(4.E18) ---------------------------------------
    cx = p[P_PCX1] * p[P_LCX]  # (4.E11)
    mux = (
        (p[P_PDX1] + p[P_PDX2] * dfz)
        * (1.0 + p[P_PPX3] * dpi + p[P_PPX4] * dpi2)
        * (1.0 - p[P_PDX3] * gamma * gamma)
        * lmux
    )  # (4.E13)
    dx = mux * fz  # (4.E12)
    ppx = 1.0 + p[P_PPX1] * dpi + p[P_PPX2] * dpi2
    kxk = fz * (p[P_PKX1] + p[P_PKX2] * dfz) * exp_kx * ppx * p[P_LKX]  # (4.E15)
    bx = kxk / max(cx * dx, _TINY)  # (4.E16)
    shx = (p[P_PHX1] + p[P_PHX2] * dfz) * p[P_LHX]  # (4.E17)
    svx = fz * (p[P_PVX1] + p[P_PVX2] * dfz) * p[P_LVX] * lmux  # (4.E18)
    kappa_x = kappa + shx  # (4.E10)
    ex0 = (p[P_PEX1] + p[P_PEX2] * dfz + p[P_PEX3] * dfz2) * p[P_LEX]
    ex = min(ex0 * (1.0 - p[P_PEX4] * (1.0 if kappa_x >= 0.0 else -1.0)), 1.0)  # (4.E14)

    # --- lateral coefficients that need no stiffness (4.E20)-(4.E30) ----------------------
    cy = p[P_PCY1] * p[P_LCY]  # (4.E21)
    muy_g0 = (p[P_PDY1] + p[P_PDY2] * dfz) * (1.0 + p[P_PPY3] * dpi + p[P_PPY4] * dpi2) * lmuy
    muy = muy_g0 * (1.0 - p[P_PDY3] * gs2)  # (4.E23)
    dy = muy * fz  # (4.E22)
    dy_g0 = muy_g0 * fz
    ey0 = (p[P_PEY1] + p[P_PEY2] * dfz) * p[P_LEY]
    ppy1 = 1.0 + p[P_PPY1] * dpi
    ppy2 = 1.0 + p[P_PPY2] * dpi
    kyg0 = fz * (p[P_PKY6] + p[P_PKY7] * dfz) * (1.0 + p[P_PPY5] * dpi) * p[P_LKYC]  # (4.E30)
    svyg = fz * (p[P_PVY3] + p[P_PVY4] * dfz) * gs * p[P_LKYC] * lmuy  # (4.E28)
    svy_g0 = fz * (p[P_PVY1] + p[P_PVY2] * dfz) * p[P_LVY] * lmuy
    svy = svy_g0 + svyg  # (4.E29)
    shy_g0 = (p[P_PHY1] + p[P_PHY2] * dfz) * p[P_LHY]
    kya_arg = fz * inv_fz0 / max((p[P_PKY2] + p[P_PKY5] * gs2) * ppy2, _TINY)

    # --- combined-slip weights (4.E51)-(4.E57), (4.E59)-(4.E67) ---------------------------
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
    rvy4a = p[P_RVY4] * tan_alpha
    dvyk_num = muy * fz * (p[P_RVY1] + p[P_RVY2] * dfz + p[P_RVY3] * gs)
    dvyk = dvyk_num / math.sqrt(1.0 + rvy4a * rvy4a)  # (4.E67)

    # --- aligning-moment coefficients that need no stiffness (4.E34)-(4.E47) --------------
    sht = p[P_QHZ1] + p[P_QHZ2] * dfz + (p[P_QHZ3] + p[P_QHZ4] * dfz) * gs  # (4.E35)
    alpha_t = tan_alpha + sht  # (4.E34)
    bt = (
        (p[P_QBZ1] + p[P_QBZ2] * dfz + p[P_QBZ3] * dfz2)
        * (1.0 + p[P_QBZ4] * gs + p[P_QBZ5] * gs_abs)
        * p[P_LKY]
        * inv_lmuy
    )  # (4.E40)
    ct = p[P_QCZ1]  # (4.E41)
    dt = (
        fz * r0 * inv_fz0 * (p[P_QDZ1] + p[P_QDZ2] * dfz) * (1.0 - p[P_PPZ1] * dpi) * p[P_LTR]
        * (1.0 + p[P_QDZ3] * gs_abs + p[P_QDZ4] * gs2)
    )  # (4.E42), (4.E43); their sgn(Vcx) cancels that of cos'alpha  # fmt: skip
    et_load = p[P_QEZ1] + p[P_QEZ2] * dfz + p[P_QEZ3] * dfz2
    dr = (
        fz * r0
        * ((p[P_QDZ6] + p[P_QDZ7] * dfz) * p[P_LRES]
           + ((p[P_QDZ8] + p[P_QDZ9] * dfz) * (1.0 + p[P_PPZ2] * dpi)
              + (p[P_QDZ10] + p[P_QDZ11] * dfz) * gs_abs) * gs * p[P_LKZC])
        * lmuy * cos_a
    )  # (4.E47); sgn(Vcx) cancels that of cos'alpha  # fmt: skip

    # --- sliding limits: start of the two peak searches ---------------------------------
    side_x = 1.0 if kappa >= 0.0 else -1.0
    side_y = 1.0 if tan_alpha >= 0.0 else -1.0
    ex_side = min(ex0 * (1.0 - p[P_PEX4] * side_x), 1.0)
    ey_side = min(ey0 * (1.0 + p[P_PEY5] * gs2 - (p[P_PEY3] + p[P_PEY4] * gs) * side_y), 1.0)
    tx = _peak_target(cx)
    ty = _peak_target(cy)
    ux = _peak_start(tx, ex_side)
    uy = _peak_start(ty, ey_side)

    # --- round 1: weights, K_ya, E_t, first peak steps ------------------------------------
    th1, s1 = _mf_lanes(
        (bxa * shxa, bxa * (tan_alpha + shxa), byk * shyk, byk * (kappa + shyk),
         kya_arg, bt * ct * alpha_t, ux, uy),
        (exa, exa, eyk, eyk, 0.0, 0.0, 0.0, 0.0),
        (cxa, cxa, cyk, cyk, p[P_PKY4], 0.0, 0.0, 0.0),
        (_PI_2, _PI_2, _PI_2, _PI_2, 0.0, 0.0, 0.0, 0.0),
    )  # fmt: skip
    gxa = max(s1[1] / max(s1[0], _TINY), 0.0)  # (4.E51), (4.E52), > 0
    gyk = max(s1[3] / max(s1[2], _TINY), 0.0)  # (4.E59), (4.E60), > 0
    kya_g0 = p[P_PKY1] * fz0 * ppy1 * p[P_LKY] * s1[4]
    kya = kya_g0 * (1.0 - p[P_PKY3] * gs_abs)  # (4.E25)
    if p[P_PKY5] != 0.0 and gs != 0.0:  # K_ya at gamma = 0 for F'y (4.E74)
        kya_g0 = (
            p[P_PKY1] * fz0 * ppy1 * p[P_LKY]
            * _sin(p[P_PKY4] * _atan(fz * inv_fz0 / max(p[P_PKY2] * ppy2, _TINY)))
        )  # fmt: skip
    et_gamma = (p[P_QEZ4] + p[P_QEZ5] * gs) * (2.0 / math.pi)
    et = min(et_load * (1.0 + et_gamma * th1[5]), 1.0)  # (4.E44)
    ux = _peak_step(ux, th1[6], ex_side, tx)
    uy = _peak_step(uy, th1[7], ey_side, ty)

    # --- stiffness-dependent quantities (4.E16), (4.E20)-(4.E27), (4.E37)-(4.E39) ---------
    kya_safe = kya if abs(kya) > _TINY else math.copysign(_TINY, p[P_PKY1])  # K'ya (4.E39)
    inv_kya = 1.0 / kya_safe
    shy = shy_g0 + (kyg0 * gs - svyg) * inv_kya  # (4.E27)
    alpha_y = tan_alpha + shy  # (4.E20)
    sgn_ay = 1.0 if alpha_y >= 0.0 else -1.0
    ey = min(ey0 * (1.0 + p[P_PEY5] * gs2 - (p[P_PEY3] + p[P_PEY4] * gs) * sgn_ay), 1.0)  # (4.E24)
    by = kya / max(cy * dy, _TINY)  # (4.E26)
    # Fy0 at gamma = 0 for F'y (4.E74): the same curve without the camber terms
    alpha_y0 = tan_alpha + shy_g0
    ey_g0 = min(ey0 * (1.0 - p[P_PEY3] * (1.0 if alpha_y0 >= 0.0 else -1.0)), 1.0)
    by_g0 = kya_g0 / max(cy * dy_g0, _TINY)
    alpha_r = tan_alpha + shy + svy * inv_kya  # (4.E37), (4.E38)
    # (4.E77), (4.E78): sgn(alpha) dropped, t and Mzr are even in alpha_eq
    kk = kxk * inv_kya * kappa
    alpha_t_eq = math.sqrt(alpha_t * alpha_t + kk * kk)
    alpha_r_eq = math.sqrt(alpha_r * alpha_r + kk * kk)

    # --- round 2: pure-slip curves (4.E9), (4.E19), trail (4.E73), S_Vyk, peak steps ----
    th2, s2 = _mf_lanes(
        (bx * kappa_x, by * alpha_y, by_g0 * alpha_y0, bt * alpha_t_eq, p[P_RVY6] * kappa,
         ux, uy, 0.0),
        (ex, ey, ey_g0, et, 0.0, 0.0, 0.0, 0.0),
        (cx, cy, cy, ct, p[P_RVY5], 0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0, _PI_2, 0.0, 0.0, 0.0, 0.0),
    )  # fmt: skip
    fx0 = dx * s2[0] + svx  # (4.E9)
    fy0 = dy * s2[1] + svy  # (4.E19)
    fy0_g0 = dy_g0 * s2[2] + svy_g0  # equals fy0 when gamma = 0
    t = dt * s2[3] * cos_a  # (4.E73)
    svyk = dvyk * s2[4] * p[P_LVYKA]  # (4.E66)
    ux = _peak_step(ux, th2[5], ex_side, tx)
    uy = _peak_step(uy, th2[6], ey_side, ty)

    # --- combined forces (4.E50), (4.E58) and aligning moment (4.E71)-(4.E76) ------------
    fx = gxa * fx0  # (4.E50)
    fy = gyk * fy0 + svyk  # (4.E58)
    fy_prime = gyk * fy0_g0  # (4.E74)
    br = p[P_QBZ9] * p[P_LKY] * inv_lmuy + p[P_QBZ10] * by * cy  # (4.E45)
    br_ar = br * alpha_r_eq
    mzr = dr / math.sqrt(1.0 + br_ar * br_ar)  # (4.E75), C_r = 1: cos(atan x) = 1/sqrt(1+x^2)
    s_gamma = (p[P_SSZ3] + p[P_SSZ4] * dfz) * gs
    s = r0 * (p[P_SSZ1] + p[P_SSZ2] * fy * inv_fz0 + s_gamma) * p[P_LS]  # (4.E76)
    mz = -t * fy_prime + mzr + s * fx  # (4.E71), (4.E72)

    # --- rolling resistance (4.E70, with Fz0 = FNOMIN in front) -------------------------
    v0 = p[P_LONGVL]
    vr = min(abs(vx_mps), VX_MY_MAX_MPS) / v0 if v0 > 0.0 else 0.0
    vr2 = vr * vr
    my = (
        r0 * fnomin * p[P_LMY] * pow_load
        * (p[P_QSY1] + p[P_QSY2] * fx * inv_fnomin + p[P_QSY3] * vr + p[P_QSY4] * vr2 * vr2
           + (p[P_QSY5] + p[P_QSY6] * fz_ratio) * gamma * gamma)
    )  # fmt: skip
    if dpi != 0.0:
        my *= math.pow(1.0 + dpi, p[P_QSY8])

    # --- sliding limits: the peak at B |x| = u, shifted back by SH -----------------------
    kappa_slide = abs(side_x * ux / max(abs(bx), _TINY) - shx)
    tan_alpha_slide = abs(side_y * uy / max(abs(by), _TINY) - shy)

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
