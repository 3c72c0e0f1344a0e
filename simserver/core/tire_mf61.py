"""Magic Formula 6.1 tire model (MF-Tyre 6.1 property files), compiled.

Equations: H. B. Pacejka, *Tire and Vehicle Dynamics*, 3rd ed. (2012), section 4.3.2,
"full set of equations" (4.E1) to (4.E78), in the ISO sign convention of MF-Tyre property
files (``docs/model.md`` section 2). Equation numbers are quoted in the comments.
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

Split (see :mod:`simserver.core.tire`): :func:`mf61_prepare` computes everything that
depends on load, camber, friction and pressure but not on slip (``B, C, D, E``, the
shifts, ``Kxk``, ``Kya``, the slip-free factors of the combined-slip weights, the
aligning-moment and rolling-resistance coefficients, both sides of the sliding limits)
at ``Fz_c``; :func:`mf61_evaluate` the slip-dependent rest, scaled by
``Fz / Fz_c`` for the current ``Fz``. At the prepared load the two are
:func:`mf61_forces` exactly; at another load they keep the prepared load's curve per
unit load ``F / Fz``, whose change with load is the only error.

Speed: the model needs about forty atan / sin, each a 10-20 ns libm call that cannot be
vectorised. Here they are branch-free polynomials (about 1 ulp), evaluated eight at a
time in loops the compiler turns into SIMD code, their scratch on the stack. Per
evaluation, one round of :func:`_mf_lanes` holds the eight slip-dependent curves
(``G_xa`` and its value at zero slip, the same for ``G_yk``, ``Fx0``, ``Fy0``, the
trail, ``S_Vyk``), after one scalar ``atan`` for ``E_t``; a non-zero camber adds the
camber-free ``Fy0`` of (4.E74) as a scalar curve. Per preparation, two rounds of
:func:`_atan_sin_lanes` hold ``Kya``'s ``sin(atan)`` and the four peak searches. The
bodies are inlined (numba IR) into their callers; the dispatchers of
:mod:`simserver.core.tire` are compiled with the same options
(``tire_layout.TIRE_JIT_OPTIONS``).

Low speed: below ``VXLOW`` the shifts SHx, SVx, SHy, SVy fade to zero at standstill
(:func:`_low_speed_factor`), so that a car at rest with relaxed slip states stays at rest.

Not modelled: turn slip and spin (zeta = 1), speed-dependent friction ``LMUV``,
overturning moment ``Mx``, low-speed smoothing of ``My`` (the caller applies ``My``
against wheel spin), transient (relaxation) behaviour, which the lagged slip states of
SAE 950311 provide.
"""

from __future__ import annotations

import math
from types import FunctionType

import numba as nb
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from simserver.core.tire_layout import (
    FZ_INPUT_MAX_N,
    MU_SCALE_MAX,
    N_MF61_COEF,
    N_TIRE_OUT,
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
    TIRE_DISPATCH_JIT_OPTIONS,
    TIRE_JIT_OPTIONS,
    TP_MIRRORED,
    TP_MODEL_BASE,
    coef_scratch,
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
    # low-speed reduction of the shifts (MF-Tyre's VXLOW, see _low_speed_factor)
    "VXLOW",
)  # fmt: skip
# Derived slots, after the file's keys: load-, camber- and friction-free quantities that
# mf61_prepare would otherwise compute again for every tire and step, computed once by
# mf61_param_vector from the keys (change a key: pack again).
MF61_DERIVED_NAMES: tuple[str, ...] = (
    "PEAK_TARGET_X",  # _peak_target(PCX1 LCX): T of the Fx0 curve's peak search (4.E11)
    "PEAK_TARGET_Y",  # _peak_target(PCY1 LCY): the same for Fy0 (4.E21)
    "INV_FZ0",  # 1 / F'z0 = 1 / (FNOMIN LFZO) (4.E1)
    "INV_FNOMIN",  # 1 / FNOMIN (4.E70)
)
N_MF61_FILE_PARAM = len(MF61_PARAM_NAMES)
N_MF61_PARAM = N_MF61_FILE_PARAM + len(MF61_DERIVED_NAMES)  # packed length


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
P_VXLOW = _slot("VXLOW")
D_PEAK_TARGET_X = N_MF61_FILE_PARAM + MF61_DERIVED_NAMES.index("PEAK_TARGET_X")
D_PEAK_TARGET_Y = N_MF61_FILE_PARAM + MF61_DERIVED_NAMES.index("PEAK_TARGET_Y")
D_INV_FZ0 = N_MF61_FILE_PARAM + MF61_DERIVED_NAMES.index("INV_FZ0")
D_INV_FNOMIN = N_MF61_FILE_PARAM + MF61_DERIVED_NAMES.index("INV_FNOMIN")

# --- load-dependent coefficients: the slots of coef (mf61_prepare -> mf61_evaluate) -------
# Everything that depends only on Fz, gamma, mu_scale and pressure, at the clamped load
# Fz_c. Where the book's quantity depends on the sign of a slip, both sides are kept.
MF61_COEF_NAMES: tuple[str, ...] = (
    "FZ_PREP",  # Fz_c: the load the coefficients were computed at (N, > 0)
    # pure longitudinal slip (4.E10)-(4.E18)
    "SHX", "BX", "CX", "DX", "SVX", "EX_POS", "EX_NEG",  # E_x for kappa_x >= 0, < 0
    # pure lateral slip (4.E19)-(4.E30)
    "SHY", "BY", "CY", "DY", "SVY", "EY_POS", "EY_NEG",  # E_y for alpha_y >= 0, < 0
    # the same at gamma = 0, for F'y (4.E74); CAMBER = 0 when gamma* = 0 (then equal)
    "CAMBER", "SHY_G0", "BY_G0", "DY_G0", "SVY_G0", "EY_G0_POS", "EY_G0_NEG",
    # combined slip (4.E54)-(4.E57), (4.E62)-(4.E67) without their slip factors
    "BXA0", "EXA", "BYK0", "EYK", "SHYK", "DVYK0",
    # aligning moment (4.E35)-(4.E47), (4.E72)-(4.E78)
    "SHT", "BT", "BT_CT", "ET_LOAD", "ET_GAMMA", "DT", "DR0", "BR",
    "SVY_KYA",  # S_Vy / K'_ya (4.E38)
    "KXK_KYA",  # K_xk / K'_ya (4.E77)
    "S_GAMMA", "INV_FZ0",
    # rolling resistance (4.E70)
    "MY_SCALE", "MY_GAMMA", "MY_PRESSURE", "INV_V0", "INV_FNOMIN",
    # load-only outputs: stiffnesses, peaks, sliding limits on either side
    "KXK", "KYA_ABS", "DX_ABS", "DY_ABS",
    "KAPPA_SLIDE_POS", "KAPPA_SLIDE_NEG", "TAN_ALPHA_SLIDE_POS", "TAN_ALPHA_SLIDE_NEG",
)  # fmt: skip
if len(MF61_COEF_NAMES) != N_MF61_COEF:
    raise ImportError("simserver.core.tire_layout.N_MF61_COEF is out of date")


def _coef_slot(name: str) -> int:
    return MF61_COEF_NAMES.index(name)


C_FZ_PREP = _coef_slot("FZ_PREP")
C_SHX = _coef_slot("SHX")
C_BX = _coef_slot("BX")
C_CX = _coef_slot("CX")
C_DX = _coef_slot("DX")
C_SVX = _coef_slot("SVX")
C_EX_POS = _coef_slot("EX_POS")
C_EX_NEG = _coef_slot("EX_NEG")
C_SHY = _coef_slot("SHY")
C_BY = _coef_slot("BY")
C_CY = _coef_slot("CY")
C_DY = _coef_slot("DY")
C_SVY = _coef_slot("SVY")
C_EY_POS = _coef_slot("EY_POS")
C_EY_NEG = _coef_slot("EY_NEG")
C_CAMBER = _coef_slot("CAMBER")
C_SHY_G0 = _coef_slot("SHY_G0")
C_BY_G0 = _coef_slot("BY_G0")
C_DY_G0 = _coef_slot("DY_G0")
C_SVY_G0 = _coef_slot("SVY_G0")
C_EY_G0_POS = _coef_slot("EY_G0_POS")
C_EY_G0_NEG = _coef_slot("EY_G0_NEG")
C_BXA0 = _coef_slot("BXA0")
C_EXA = _coef_slot("EXA")
C_BYK0 = _coef_slot("BYK0")
C_EYK = _coef_slot("EYK")
C_SHYK = _coef_slot("SHYK")
C_DVYK0 = _coef_slot("DVYK0")
C_SHT = _coef_slot("SHT")
C_BT = _coef_slot("BT")
C_BT_CT = _coef_slot("BT_CT")
C_ET_LOAD = _coef_slot("ET_LOAD")
C_ET_GAMMA = _coef_slot("ET_GAMMA")
C_DT = _coef_slot("DT")
C_DR0 = _coef_slot("DR0")
C_BR = _coef_slot("BR")
C_SVY_KYA = _coef_slot("SVY_KYA")
C_KXK_KYA = _coef_slot("KXK_KYA")
C_S_GAMMA = _coef_slot("S_GAMMA")
C_INV_FZ0 = _coef_slot("INV_FZ0")
C_MY_SCALE = _coef_slot("MY_SCALE")
C_MY_GAMMA = _coef_slot("MY_GAMMA")
C_MY_PRESSURE = _coef_slot("MY_PRESSURE")
C_INV_V0 = _coef_slot("INV_V0")
C_INV_FNOMIN = _coef_slot("INV_FNOMIN")
C_KXK = _coef_slot("KXK")
C_KYA_ABS = _coef_slot("KYA_ABS")
C_DX_ABS = _coef_slot("DX_ABS")
C_DY_ABS = _coef_slot("DY_ABS")
C_KAPPA_SLIDE_POS = _coef_slot("KAPPA_SLIDE_POS")
C_KAPPA_SLIDE_NEG = _coef_slot("KAPPA_SLIDE_NEG")
C_TAN_ALPHA_SLIDE_POS = _coef_slot("TAN_ALPHA_SLIDE_POS")
C_TAN_ALPHA_SLIDE_NEG = _coef_slot("TAN_ALPHA_SLIDE_NEG")

# --- input ranges and numerical guards (compile-time constants) ---------------------------
# (FZ_INPUT_MAX_N, SLIP_INPUT_MAX, MU_SCALE_MAX: simserver.core.tire_layout)
FZ_FLOOR_FRAC = 0.01  # coefficients are never evaluated below 1 % of FNOMIN
GAMMA_INPUT_MAX_RAD = 0.5 * math.pi  # |gamma| clamped to this
MU_SCALE_MIN = 1e-6  # mu_scale clamped to [MU_SCALE_MIN, MU_SCALE_MAX]: lambda_mu divides
# Bt and Br (4.E40, 4.E45), so it may not reach zero
VX_MY_MAX_MPS = 1000.0  # |vx| cap in the (Vx/V0)^4 rolling-resistance term
SLIDE_MAX = 1.0e6  # cap of OUT_KAPPA_SLIDE / OUT_TAN_ALPHA_SLIDE (curve without peak)
SLIDE_FRACTION_NO_PEAK = 0.99  # C <= 1: "sliding" where the curve reaches 99 % of its limit
_TINY = 1e-9  # floor of C*D (N), |K_ya| (N/rad), G0: never reached with a sane file

# Compilation: tire_layout.TIRE_JIT_OPTIONS (FMA, division by zero gives inf; every
# division here has a non-zero denominator anyway).
_JIT_OPTIONS = TIRE_JIT_OPTIONS

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
def _atan_flat(x: float) -> float:
    """:func:`_atan` without a conditional expression (the same value for ``|x| <= 1e300``).

    The interval flags are 0/1 factors and the blends are exact, so nothing branches even
    before LLVM's optimisations: numba's reference-count pruning, which runs early, gives
    up on functions with too many branch paths (see :func:`_mf_curve`).
    """
    ax = min(abs(x), 1e300)  # atan(1e300) = pi/2 in double; keeps c * ax finite
    f1 = 1.0 * (ax >= 0.4375)
    f2 = 1.0 * (ax >= 0.6875)
    f3 = 1.0 * (ax >= 1.1875)
    f4 = 1.0 * (ax >= 2.4375)
    c = 0.5 * (f1 + f2 + f3)  # centre, exact
    num = (ax - c) * (1.0 - f4) - f4  # -1 beyond 39/16
    den = ax * f4 + (1.0 + c * ax) * (1.0 - f4)
    base = max(f1 * _ATAN_HALF, f2 * _PI_4, f3 * _ATAN_3HALF, f4 * _PI_2)
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
def _sin_branch_free(x: float) -> float:
    """``sin(x)`` to about 1 ulp (absolute) for ``|x| < 2^20``, without a branch."""
    n = (x * _INV_TWO_PI + _ROUND_MAGIC) - _ROUND_MAGIC  # nearest integer
    r = (x - n * _TWO_PI_HI) - n * _TWO_PI_LO  # |r| <= pi
    ar = abs(r)
    return math.copysign(_sin_core(min(ar, (_PI_HI - ar) + _PI_LO)), r)  # sin(pi - a) = sin a


@nb.njit(inline="always", **_JIT_OPTIONS)
def _sin(x: float) -> float:
    """``sin(x)`` to about 1 ulp (absolute) for ``|x| < 2^20``; libm beyond (never here)."""
    if not abs(x) < 1048576.0:
        return math.sin(x)
    return _sin_branch_free(x)


# --- the Magic Formula, eight curves at a time ----------------------------------------------
N_LANES = 8


def _stack_scratch(size: int) -> object:
    """An intrinsic giving a pointer to ``size`` float64 on the stack of the compiled
    caller (an alloca).

    Stack scratch, not a heap allocation: it lets the compiler vectorise the lane loop of
    :func:`_mf_lanes` (numba has no other allocation-free local array). Indexed as a raw
    pointer, not wrapped in ``nb.carray``: an array made in a function needs numba's
    reference counting, which the dispatchers that inline these bodies are compiled
    without (``tire_layout.TIRE_DISPATCH_JIT_OPTIONS``).
    """

    @intrinsic
    def stack(typingctx: object) -> tuple:
        sig = types.CPointer(types.float64)()

        def codegen(context: object, builder: object, signature: object, args: object) -> object:
            return cgutils.alloca_once(builder, context.get_value_type(types.float64),
                                       size=size)

        return sig, codegen

    return stack


_stack_lanes = _stack_scratch(N_LANES)


@nb.njit(inline="always", **_JIT_OPTIONS)
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

    Notes
    -----
    Inlined into its caller (numba IR), so that the lanes' scratch is on the caller's
    stack, the tuples are not passed through memory, and no call between the caller's
    array arguments lets their reference counting survive (an out-of-line call here
    costs three atomic increments and decrements of ``p``, ``coef``, ``out``).
    """
    yb = _stack_lanes()
    eb = _stack_lanes()
    cb = _stack_lanes()
    kb = _stack_lanes()
    tb = _stack_lanes()
    sb = _stack_lanes()
    for i in range(N_LANES):
        yb[i] = y[i]
        eb[i] = e[i]
        cb[i] = c[i]
        kb[i] = k[i]
    for i in range(N_LANES):  # branch-free body: the compiler makes it one vector loop
        yi = yb[i]
        ei = eb[i]
        theta = _atan((1.0 - ei) * yi + ei * _atan(yi))
        tb[i] = theta
        sb[i] = _sin_branch_free(cb[i] * theta + kb[i])
    return (
        (tb[0], tb[1], tb[2], tb[3], tb[4], tb[5], tb[6], tb[7]),
        (sb[0], sb[1], sb[2], sb[3], sb[4], sb[5], sb[6], sb[7]),
    )


@nb.njit(inline="always", **_JIT_OPTIONS)
def _atan_sin_lanes(
    y: tuple[float, ...], c: tuple[float, ...]
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Eight ``theta_i = atan(y_i)``, ``s_i = sin(C_i theta_i)`` in one vectorised loop.

    The load-only curves: ``sin(PKY4 atan(.))`` of ``K_ya`` (4.E25) and the ``atan`` of
    the peak searches (:func:`_peak_step`); one ``atan`` per lane where
    :func:`_mf_lanes` takes two. Inlined like :func:`_mf_lanes`.
    """
    yb = _stack_lanes()
    cb = _stack_lanes()
    tb = _stack_lanes()
    sb = _stack_lanes()
    for i in range(N_LANES):
        yb[i] = y[i]
        cb[i] = c[i]
    for i in range(N_LANES):  # branch-free body: one vector loop
        theta = _atan(yb[i])
        tb[i] = theta
        sb[i] = _sin_branch_free(cb[i] * theta)
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
    ``D sin(C pi / 2)``. ``C`` does not depend on the load: evaluated once per tire when
    it is packed (slots ``D_PEAK_TARGET_X``, ``D_PEAK_TARGET_Y``, :func:`_pack_derived`).
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


@nb.njit(inline="always", **_JIT_OPTIONS)
def _mf_curve(y: float, e: float, c: float) -> float:
    """One Magic Formula ``sin[C atan{y - E (y - atan y)}]``, scalar; as a lane of _mf_lanes.

    Used in a branch of :func:`_mf61_evaluate` (camber not zero). Without calls and
    without conditional expressions (:func:`_atan_flat`, and no libm fallback of
    :func:`_sin`: the argument is at most ``|C| pi / 2``), so that the branch does not
    keep numba from pruning the reference counting of the arrays of the dispatchers of
    :mod:`simserver.core.tire` (checked in ``tests/test_tire_split.py``; 20 ns a call).
    """
    return _sin_branch_free(c * _atan_flat((1.0 - e) * y + e * _atan_flat(y)))


@nb.njit(inline="always", **_JIT_OPTIONS)
def _mf61_prepare(
    p: np.ndarray, gamma_rad: float, fz_n: float, mu_scale: float, coef: np.ndarray
) -> None:
    """Load-dependent part of Magic Formula 6.1: every coefficient that needs no slip.

    Parameters
    ----------
    p : float64[N_MF61_PARAM]
        Coefficients packed by :func:`mf61_param_vector` (slots ``P_*``).
    gamma_rad : float
        Inclination angle (rad); ``gamma* = sin(gamma)`` (4.E4).
    fz_n : float
        Normal load (N). The coefficients are computed at the clamped load
        ``Fz_c = clamp(fz_n, max(FZMIN, 0.01 FNOMIN), FZMAX)``, stored in ``C_FZ_PREP``;
        so ``fz_n <= 0`` prepares at the floor, from which :func:`mf61_evaluate` scales
        linearly (as :func:`mf61_forces` does below the floor).
    mu_scale : float
        Road friction scale, multiplies ``LMUX`` and ``LMUY``.
    coef : float64[N_TIRE_COEF]
        Written: every ``C_*`` slot (:data:`MF61_COEF_NAMES`).

    Notes
    -----
    Computes (4.E1)-(4.E8) the operating point; (4.E11)-(4.E18) ``Cx, Dx, Kxk, Bx, SHx,
    SVx`` and ``Ex`` for both signs of ``kappa_x``; (4.E21)-(4.E30) ``Cy, Dy, Kya, By,
    SHy, SVy`` and ``Ey`` for both signs of ``alpha_y``, with their ``gamma = 0``
    counterparts for (4.E74); the slip-free factors of the combined-slip weights
    (4.E54)-(4.E57), (4.E62)-(4.E67); the aligning-moment coefficients (4.E35), (4.E40)-
    (4.E47), (4.E45); the rolling-resistance factors of (4.E70); and the sliding limits:
    the slip at the peak of each pure-slip curve on either side (two Halley steps from
    a bracketing start, :func:`_peak_step`). Four peak searches and ``Kya``'s
    ``sin(atan)`` are the two rounds of :func:`_atan_sin_lanes` here.

    Inlined into its caller (numba IR), which must be compiled with ``_JIT_OPTIONS``;
    :func:`mf61_prepare` is the same compiled on its own.
    """
    gamma = min(max(gamma_rad, -GAMMA_INPUT_MAX_RAD), GAMMA_INPUT_MAX_RAD)
    mu = min(max(mu_scale, MU_SCALE_MIN), MU_SCALE_MAX)

    # --- operating point (4.E1)-(4.E8) ---------------------------------------------------
    fnomin = p[P_FNOMIN]
    r0 = p[P_UNLOADED_RADIUS]
    fz0 = fnomin * p[P_LFZO]  # F'z0 (4.E1)
    fz_lo = max(p[P_FZMIN], FZ_FLOOR_FRAC * fnomin)
    fz = min(max(fz_n, fz_lo), max(p[P_FZMAX], fz_lo))  # load the coefficients see
    inv_fz0 = p[D_INV_FZ0]
    inv_fnomin = p[D_INV_FNOMIN]
    dfz = (fz - fz0) * inv_fz0  # (4.E2a)
    dfz2 = dfz * dfz
    fz_ratio = fz * inv_fnomin
    p_nom = p[P_NOMPRES]
    p_infl = p[P_INFLPRES]
    dpi = (p_infl - p_nom) / p_nom if p_nom > 0.0 and p_infl > 0.0 else 0.0  # (4.E2b)
    dpi2 = dpi * dpi
    pow_load = math.pow(fz_ratio, p[P_QSY7])  # (Fz / Fz0)^QSY7 (4.E70)
    exp_kx = math.exp(p[P_PKX3] * dfz)  # (4.E15)
    lmux = p[P_LMUX] * mu  # lambda*_mux = lambda'_mux (4.E7, 4.E8: LMUV = 0, A_mu = 1)
    lmuy = max(p[P_LMUY] * mu, _TINY)
    inv_lmuy = 1.0 / lmuy  # Bt, Br (4.E40, 4.E45)
    gs = _sin(gamma) if gamma != 0.0 else 0.0  # gamma* (4.E4)
    gs2 = gs * gs
    gs_abs = abs(gs)

    # --- longitudinal (4.E11)-(4.E18) -----------------------------------------------------
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
    ex0 = (p[P_PEX1] + p[P_PEX2] * dfz + p[P_PEX3] * dfz2) * p[P_LEX]
    ex_pos = min(ex0 * (1.0 - p[P_PEX4]), 1.0)  # (4.E14), kappa_x >= 0
    ex_neg = min(ex0 * (1.0 + p[P_PEX4]), 1.0)  # kappa_x < 0

    # --- lateral, the parts that need no stiffness (4.E21)-(4.E30) ------------------------
    cy = p[P_PCY1] * p[P_LCY]  # (4.E21)
    muy_g0 = (p[P_PDY1] + p[P_PDY2] * dfz) * (1.0 + p[P_PPY3] * dpi + p[P_PPY4] * dpi2) * lmuy
    muy = muy_g0 * (1.0 - p[P_PDY3] * gs2)  # (4.E23)
    dy = muy * fz  # (4.E22)
    dy_g0 = muy_g0 * fz
    ey0 = (p[P_PEY1] + p[P_PEY2] * dfz) * p[P_LEY]
    ey_cam = 1.0 + p[P_PEY5] * gs2
    ey_sgn = p[P_PEY3] + p[P_PEY4] * gs
    ey_pos = min(ey0 * (ey_cam - ey_sgn), 1.0)  # (4.E24), alpha_y >= 0
    ey_neg = min(ey0 * (ey_cam + ey_sgn), 1.0)  # alpha_y < 0
    ey_g0_pos = min(ey0 * (1.0 - p[P_PEY3]), 1.0)
    ey_g0_neg = min(ey0 * (1.0 + p[P_PEY3]), 1.0)
    ppy1 = 1.0 + p[P_PPY1] * dpi
    ppy2 = 1.0 + p[P_PPY2] * dpi
    kyg0 = fz * (p[P_PKY6] + p[P_PKY7] * dfz) * (1.0 + p[P_PPY5] * dpi) * p[P_LKYC]  # (4.E30)
    svyg = fz * (p[P_PVY3] + p[P_PVY4] * dfz) * gs * p[P_LKYC] * lmuy  # (4.E28)
    svy_g0 = fz * (p[P_PVY1] + p[P_PVY2] * dfz) * p[P_LVY] * lmuy
    svy = svy_g0 + svyg  # (4.E29)
    shy_g0 = (p[P_PHY1] + p[P_PHY2] * dfz) * p[P_LHY]
    kya_arg = fz * inv_fz0 / max((p[P_PKY2] + p[P_PKY5] * gs2) * ppy2, _TINY)
    kya_g0_arg = fz * inv_fz0 / max(p[P_PKY2] * ppy2, _TINY)

    # --- aligning moment (4.E35)-(4.E47) ----------------------------------------------------
    sht = p[P_QHZ1] + p[P_QHZ2] * dfz + (p[P_QHZ3] + p[P_QHZ4] * dfz) * gs  # (4.E35)
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
    dr0 = (
        fz * r0
        * ((p[P_QDZ6] + p[P_QDZ7] * dfz) * p[P_LRES]
           + ((p[P_QDZ8] + p[P_QDZ9] * dfz) * (1.0 + p[P_PPZ2] * dpi)
              + (p[P_QDZ10] + p[P_QDZ11] * dfz) * gs_abs) * gs * p[P_LKZC])
        * lmuy
    )  # (4.E47) without cos'alpha; sgn(Vcx) cancels that of cos'alpha  # fmt: skip

    # --- sliding limits: start of the four peak searches (both sides of both curves) -----
    tx = p[D_PEAK_TARGET_X]  # _peak_target(cx), load-free: packed once
    ty = p[D_PEAK_TARGET_Y]
    ux_pos = _peak_start(tx, ex_pos)
    ux_neg = _peak_start(tx, ex_neg)
    uy_pos = _peak_start(ty, ey_pos)
    uy_neg = _peak_start(ty, ey_neg)

    # --- round 1: K_ya (4.E25) and at gamma = 0, first peak steps ------------------------
    th1, s1 = _atan_sin_lanes(
        (kya_arg, kya_g0_arg, ux_pos, ux_neg, uy_pos, uy_neg, 0.0, 0.0),
        (p[P_PKY4], p[P_PKY4], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    )  # fmt: skip
    kya_front = p[P_PKY1] * fz0 * ppy1 * p[P_LKY]
    kya_g0 = kya_front * s1[0]
    kya = kya_g0 * (1.0 - p[P_PKY3] * gs_abs)  # (4.E25)
    if p[P_PKY5] != 0.0 and gs != 0.0:  # K_ya at gamma = 0 for F'y (4.E74)
        kya_g0 = kya_front * s1[1]
    ux_pos = _peak_step(ux_pos, th1[2], ex_pos, tx)
    ux_neg = _peak_step(ux_neg, th1[3], ex_neg, tx)
    uy_pos = _peak_step(uy_pos, th1[4], ey_pos, ty)
    uy_neg = _peak_step(uy_neg, th1[5], ey_neg, ty)

    # --- stiffness-dependent quantities (4.E26), (4.E27), (4.E38), (4.E39), (4.E45) -------
    kya_safe = kya if abs(kya) > _TINY else math.copysign(_TINY, p[P_PKY1])  # K'ya (4.E39)
    inv_kya = 1.0 / kya_safe
    shy = shy_g0 + (kyg0 * gs - svyg) * inv_kya  # (4.E27)
    by = kya / max(cy * dy, _TINY)  # (4.E26)
    by_g0 = kya_g0 / max(cy * dy_g0, _TINY)
    br = p[P_QBZ9] * p[P_LKY] * inv_lmuy + p[P_QBZ10] * by * cy  # (4.E45)

    # --- round 2: second peak steps ----------------------------------------------------
    th2, _ = _atan_sin_lanes(
        (ux_pos, ux_neg, uy_pos, uy_neg, 0.0, 0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    )  # fmt: skip
    ux_pos = _peak_step(ux_pos, th2[0], ex_pos, tx)
    ux_neg = _peak_step(ux_neg, th2[1], ex_neg, tx)
    uy_pos = _peak_step(uy_pos, th2[2], ey_pos, ty)
    uy_neg = _peak_step(uy_neg, th2[3], ey_neg, ty)
    # the peak at B |x| = u, shifted back by SH
    inv_bx = 1.0 / max(abs(bx), _TINY)
    inv_by = 1.0 / max(abs(by), _TINY)

    # --- rolling resistance (4.E70, with Fz0 = FNOMIN in front) -------------------------
    v0 = p[P_LONGVL]

    coef[C_FZ_PREP] = fz
    coef[C_SHX] = shx
    coef[C_BX] = bx
    coef[C_CX] = cx
    coef[C_DX] = dx
    coef[C_SVX] = svx
    coef[C_EX_POS] = ex_pos
    coef[C_EX_NEG] = ex_neg
    coef[C_SHY] = shy
    coef[C_BY] = by
    coef[C_CY] = cy
    coef[C_DY] = dy
    coef[C_SVY] = svy
    coef[C_EY_POS] = ey_pos
    coef[C_EY_NEG] = ey_neg
    coef[C_CAMBER] = 1.0 if gs != 0.0 else 0.0
    coef[C_SHY_G0] = shy_g0
    coef[C_BY_G0] = by_g0
    coef[C_DY_G0] = dy_g0
    coef[C_SVY_G0] = svy_g0
    coef[C_EY_G0_POS] = ey_g0_pos
    coef[C_EY_G0_NEG] = ey_g0_neg
    coef[C_BXA0] = (p[P_RBX1] + p[P_RBX3] * gs2) * p[P_LXAL]  # (4.E54) / cos(atan(RBX2 k))
    coef[C_EXA] = min(p[P_REX1] + p[P_REX2] * dfz, 1.0)  # (4.E56)
    coef[C_BYK0] = (p[P_RBY1] + p[P_RBY4] * gs2) * p[P_LYKA]  # (4.E62) / cos(atan(.))
    coef[C_EYK] = min(p[P_REY1] + p[P_REY2] * dfz, 1.0)  # (4.E64)
    coef[C_SHYK] = p[P_RHY1] + p[P_RHY2] * dfz  # (4.E65)
    coef[C_DVYK0] = muy * fz * (p[P_RVY1] + p[P_RVY2] * dfz + p[P_RVY3] * gs)  # (4.E67)
    coef[C_SHT] = sht
    coef[C_BT] = bt
    coef[C_BT_CT] = bt * ct
    coef[C_ET_LOAD] = p[P_QEZ1] + p[P_QEZ2] * dfz + p[P_QEZ3] * dfz2  # (4.E44)
    coef[C_ET_GAMMA] = (p[P_QEZ4] + p[P_QEZ5] * gs) * (2.0 / math.pi)
    coef[C_DT] = dt
    coef[C_DR0] = dr0
    coef[C_BR] = br
    coef[C_SVY_KYA] = svy * inv_kya
    coef[C_KXK_KYA] = kxk * inv_kya
    coef[C_S_GAMMA] = (p[P_SSZ3] + p[P_SSZ4] * dfz) * gs  # (4.E76)
    coef[C_INV_FZ0] = inv_fz0
    coef[C_MY_SCALE] = r0 * fnomin * p[P_LMY] * pow_load
    coef[C_MY_GAMMA] = (p[P_QSY5] + p[P_QSY6] * fz_ratio) * gamma * gamma
    coef[C_MY_PRESSURE] = math.pow(1.0 + dpi, p[P_QSY8]) if dpi != 0.0 else 1.0
    coef[C_INV_V0] = 1.0 / v0 if v0 > 0.0 else 0.0
    coef[C_INV_FNOMIN] = inv_fnomin
    coef[C_KXK] = kxk
    coef[C_KYA_ABS] = abs(kya)
    coef[C_DX_ABS] = abs(dx)
    coef[C_DY_ABS] = abs(dy)
    coef[C_KAPPA_SLIDE_POS] = min(max(abs(ux_pos * inv_bx - shx), _TINY), SLIDE_MAX)
    coef[C_KAPPA_SLIDE_NEG] = min(max(abs(-ux_neg * inv_bx - shx), _TINY), SLIDE_MAX)
    coef[C_TAN_ALPHA_SLIDE_POS] = min(max(abs(uy_pos * inv_by - shy), _TINY), SLIDE_MAX)
    coef[C_TAN_ALPHA_SLIDE_NEG] = min(max(abs(-uy_neg * inv_by - shy), _TINY), SLIDE_MAX)


@nb.njit(inline="always", **_JIT_OPTIONS)
def _low_speed_factor(vx_mps: float, vxlow_mps: float) -> float:
    """The factor on the Magic Formula shifts SHx, SVx, SHy, SVy at hub speed ``vx_mps``.

    The shifts are offsets of the steady-state curves: at zero slip they give a force
    (the sample tire: 18.8 N forward, 69.9 N sideways) that, at standstill, would push a
    stopped car with nothing to balance it. As MF-Tyre does below ``VXLOW``, they are
    reduced smoothly to zero at standstill: ``s^2 (3 - 2 s)`` with ``s = |vx| / VXLOW``
    below ``VXLOW`` (value and slope continuous at both ends, like MF-Tyre's cosine form
    ``0.5 (1 - cos(pi s))``, which it follows within 0.01, without a libm call), exactly 1
    above it, so the forces at speed are unchanged to the bit. At rest the lagged slip
    states (SAE 950311) are then the only source of shear force. ``VXLOW = 0`` switches
    the reduction off.
    """
    s = min(abs(vx_mps) / vxlow_mps, 1.0) if vxlow_mps > 0.0 else 1.0
    return s * s * (3.0 - 2.0 * s)


@nb.njit(inline="always", **_JIT_OPTIONS)
def _mf61_evaluate(
    p: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """Slip-dependent part of Magic Formula 6.1, from coefficients of :func:`mf61_prepare`.

    Parameters
    ----------
    p : float64[N_MF61_PARAM]
        Coefficients packed by :func:`mf61_param_vector` (slots ``P_*``).
    coef : float64[N_TIRE_COEF]
        Written by :func:`mf61_prepare` (at the load ``coef[C_FZ_PREP]``).
    kappa : float
        Longitudinal slip, positive when driving.
    tan_alpha : float
        ``alpha* = tan(alpha) sgn(Vcx)`` (4.E3), positive when the hub slides to +y.
    fz_n : float
        Current normal load (N). Forces, moments, stiffnesses and peaks are those at the
        prepared load times ``fz_n / coef[C_FZ_PREP]`` (``fz_n`` clamped to
        ``[0, FZ_INPUT_MAX_N]``): exact at the prepared load, and proportional to the
        load around it. The sliding limits are taken as prepared.
    vx_mps : float
        Hub longitudinal speed, used only as ``|vx|`` in the rolling resistance.
    out : float64[N_TIRE_OUT]
        Written in place, every ``OUT_*`` slot of :mod:`simserver.core.tire_layout` (see
        :func:`mf61_forces`).

    Notes
    -----
    What is left per call: the pure-slip curves (4.E9), (4.E19) (and (4.E19) at
    ``gamma = 0`` for (4.E74) when the camber is not zero), the combined-slip weights
    (4.E51), (4.E52), (4.E59), (4.E60) with their slip factors (4.E54), (4.E62), (4.E67),
    the kappa-induced side force (4.E66), the trail (4.E73) with ``E_t`` (4.E44), the
    residual torque (4.E75), the arm ``s`` (4.E76) and ``My`` (4.E70). The eight Magic
    Formula curves are one round of :func:`_mf_lanes`; the ``atan`` of ``E_t``, which
    one of them needs, is computed before it.

    Inlined into its caller (numba IR), which must be compiled with ``_JIT_OPTIONS``;
    :func:`mf61_evaluate` is the same compiled on its own. Allocates nothing.
    """
    kappa = min(max(kappa, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
    tan_alpha = min(max(tan_alpha, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
    scale = max(min(fz_n, FZ_INPUT_MAX_N), 0.0) / coef[C_FZ_PREP]
    cos_a = 1.0 / math.sqrt(1.0 + tan_alpha * tan_alpha)  # |cos'alpha| (4.E6)

    # --- combined-slip weights: slip factors (4.E53), (4.E54), (4.E61), (4.E62), (4.E67) --
    rbx2k = p[P_RBX2] * kappa
    bxa = coef[C_BXA0] / math.sqrt(1.0 + rbx2k * rbx2k)  # (4.E54)
    exa = coef[C_EXA]
    cxa = p[P_RCX1]  # (4.E55)
    shxa = p[P_RHX1]  # (4.E57); alpha_s = tan_alpha + SHxa (4.E53)
    rby2a = p[P_RBY2] * (tan_alpha - p[P_RBY3])
    byk = coef[C_BYK0] / math.sqrt(1.0 + rby2a * rby2a)  # (4.E62)
    eyk = coef[C_EYK]
    cyk = p[P_RCY1]  # (4.E63)
    shyk = coef[C_SHYK]  # kappa_s = kappa + SHyk (4.E61)
    rvy4a = p[P_RVY4] * tan_alpha
    dvyk = coef[C_DVYK0] / math.sqrt(1.0 + rvy4a * rvy4a)  # (4.E67)

    # --- pure-slip arguments (4.E10), (4.E14), (4.E20), (4.E24) --------------------------
    low = _low_speed_factor(vx_mps, p[P_VXLOW])  # on SHx, SVx, SHy, SVy; 1 at speed
    kappa_x = kappa + coef[C_SHX] * low  # (4.E10)
    ex = coef[C_EX_POS] if kappa_x >= 0.0 else coef[C_EX_NEG]  # (4.E14)
    shy = coef[C_SHY] * low
    alpha_y = tan_alpha + shy  # (4.E20)
    ey = coef[C_EY_POS] if alpha_y >= 0.0 else coef[C_EY_NEG]  # (4.E24)

    # --- trail and residual torque arguments (4.E34), (4.E37), (4.E44), (4.E77), (4.E78) ---
    alpha_t = tan_alpha + coef[C_SHT]  # (4.E34)
    et = min(coef[C_ET_LOAD] * (1.0 + coef[C_ET_GAMMA] * _atan(coef[C_BT_CT] * alpha_t)), 1.0)
    ct = p[P_QCZ1]  # (4.E41)
    alpha_r = tan_alpha + shy + coef[C_SVY_KYA] * low  # (4.E37), (4.E38)
    # (4.E77), (4.E78): sgn(alpha) dropped, t and Mzr are even in alpha_eq
    kk = coef[C_KXK_KYA] * kappa
    alpha_t_eq = math.sqrt(alpha_t * alpha_t + kk * kk)
    alpha_r_eq = math.sqrt(alpha_r * alpha_r + kk * kk)

    # --- the eight curves: G_xa (4.E51)-(4.E52), G_yk (4.E59)-(4.E60), Fx0 (4.E9),
    # Fy0 (4.E19), trail (4.E73), S_Vyk (4.E66) --------------------------------------------
    _, s = _mf_lanes(
        (bxa * shxa, bxa * (tan_alpha + shxa), byk * shyk, byk * (kappa + shyk),
         coef[C_BX] * kappa_x, coef[C_BY] * alpha_y, coef[C_BT] * alpha_t_eq,
         p[P_RVY6] * kappa),
        (exa, exa, eyk, eyk, ex, ey, et, 0.0),
        (cxa, cxa, cyk, cyk, coef[C_CX], coef[C_CY], ct, p[P_RVY5]),
        (_PI_2, _PI_2, _PI_2, _PI_2, 0.0, 0.0, _PI_2, 0.0),
    )  # fmt: skip
    gxa = max(s[1] / max(s[0], _TINY), 0.0)  # (4.E51), (4.E52), > 0
    gyk = max(s[3] / max(s[2], _TINY), 0.0)  # (4.E59), (4.E60), > 0
    fx0 = coef[C_DX] * s[4] + coef[C_SVX] * low  # (4.E9)
    fy0 = coef[C_DY] * s[5] + coef[C_SVY] * low  # (4.E19)
    t = coef[C_DT] * s[6] * cos_a  # (4.E73)
    svyk = dvyk * s[7] * p[P_LVYKA]  # (4.E66)
    if coef[C_CAMBER] != 0.0:  # Fy0 at gamma = 0 for F'y (4.E74): the curve without camber
        alpha_y0 = tan_alpha + coef[C_SHY_G0] * low
        ey_g0 = coef[C_EY_G0_POS] if alpha_y0 >= 0.0 else coef[C_EY_G0_NEG]
        s_g0 = _mf_curve(coef[C_BY_G0] * alpha_y0, ey_g0, coef[C_CY])
        fy0_g0 = coef[C_DY_G0] * s_g0 + coef[C_SVY_G0] * low
    else:  # gamma* = 0: every camber term vanishes and the two curves are the same
        fy0_g0 = fy0

    # --- combined forces (4.E50), (4.E58) and aligning moment (4.E71)-(4.E76) ------------
    fx = gxa * fx0  # (4.E50)
    fy = gyk * fy0 + svyk  # (4.E58)
    fy_prime = gyk * fy0_g0  # (4.E74)
    br_ar = coef[C_BR] * alpha_r_eq
    dr = coef[C_DR0] * cos_a  # (4.E47)
    mzr = dr / math.sqrt(1.0 + br_ar * br_ar)  # (4.E75), C_r = 1: cos(atan x) = 1/sqrt(1+x^2)
    r0 = p[P_UNLOADED_RADIUS]
    arm = r0 * (p[P_SSZ1] + p[P_SSZ2] * fy * coef[C_INV_FZ0] + coef[C_S_GAMMA]) * p[P_LS]
    mz = -t * fy_prime + mzr + arm * fx  # (4.E71), (4.E72), (4.E76)

    # --- rolling resistance (4.E70, with Fz0 = FNOMIN in front) -------------------------
    vr = min(abs(vx_mps), VX_MY_MAX_MPS) * coef[C_INV_V0]
    vr2 = vr * vr
    my = (
        coef[C_MY_SCALE]
        * (p[P_QSY1] + p[P_QSY2] * fx * coef[C_INV_FNOMIN] + p[P_QSY3] * vr
           + p[P_QSY4] * vr2 * vr2 + coef[C_MY_GAMMA])
        * coef[C_MY_PRESSURE]
    )  # fmt: skip

    out[OUT_FX] = fx * scale
    out[OUT_FY] = fy * scale
    out[OUT_MZ] = mz * scale
    out[OUT_MY] = max(my, 0.0) * scale
    out[OUT_C_KAPPA] = coef[C_KXK] * scale
    out[OUT_C_ALPHA] = coef[C_KYA_ABS] * scale
    out[OUT_KAPPA_SLIDE] = coef[C_KAPPA_SLIDE_POS] if kappa >= 0.0 else coef[C_KAPPA_SLIDE_NEG]
    out[OUT_TAN_ALPHA_SLIDE] = (
        coef[C_TAN_ALPHA_SLIDE_POS] if tan_alpha >= 0.0 else coef[C_TAN_ALPHA_SLIDE_NEG]
    )
    out[OUT_FX_PEAK] = coef[C_DX_ABS] * scale
    out[OUT_FY_PEAK] = coef[C_DY_ABS] * scale


# --- four tires at once: the step's call -------------------------------------------------
N_WHEEL_TIRES = 4  # tires evaluated together by _mf61_evaluate_wheels (core.layout.N_WHEELS)
N_WHEEL_CURVES = 9  # Magic Formula curves per tire there: _mf61_evaluate's eight + Fy0(gamma=0)
N_WHEEL_LANES = N_WHEEL_TIRES * N_WHEEL_CURVES
# The curve loop runs over a whole number of N_LANES-wide vectors: the 36 lanes padded to
# 40 with zero lanes (sin(0 atan 0) = 0, unused). Unpadded, the compiler made the last 4
# lanes a scalar remainder loop with a branching atan, which cost more than a fifth
# vector: 45 ns more per call (of 300), measured by CPU time in a compiled loop.
N_WHEEL_LANES_PADDED = -(-N_WHEEL_LANES // N_LANES) * N_LANES
# The lanes of the curves whose E may be non-zero: all but the last, S_Vyk's (4.E66);
# a whole number of vectors.
N_WHEEL_E_LANES = (N_WHEEL_CURVES - 1) * N_WHEEL_TIRES
if N_WHEEL_E_LANES % N_LANES:
    raise ImportError("N_WHEEL_E_LANES must be a multiple of N_LANES")


_stack_wheel_lanes = _stack_scratch(N_WHEEL_LANES_PADDED)
_stack_wheel_tires = _stack_scratch(N_WHEEL_TIRES)
_stack_wheel_outs = _stack_scratch(N_TIRE_OUT * N_WHEEL_TIRES)


# The four-tire evaluation's scalar helpers, inlined by LLVM, not by numba
# (``core.layout.STEP_JIT_OPTIONS`` says why): numba re-translated and re-typed each inlined
# copy (about two thirds of ``tire_evaluate_mf61_wheels``'s cold compile). Compiled with the
# dispatchers' options, so the same arithmetic and the same bits. Only here: in the
# single-tire bodies, which ``tire.tire_forces`` inlines with reference counting on, a
# call (even one LLVM inlines) kept numba from pruning the counts of its views of ``tp``
# (tests/test_tire_split.py).
_LEAF_JIT_OPTIONS = dict(TIRE_DISPATCH_JIT_OPTIONS, forceinline=True)


def _llvm_inlined(helper: object) -> object:
    """``helper``'s Python function compiled with ``_LEAF_JIT_OPTIONS``, under a name of
    its own (numba's cache files are named by the function's qualified name: the two
    compiled forms must not share one)."""
    py = helper.py_func
    twin = FunctionType(py.__code__, py.__globals__, py.__name__ + "_llvm", py.__defaults__,
                        py.__closure__)
    twin.__qualname__ = py.__qualname__ + "_llvm"
    twin.__doc__ = py.__doc__
    return nb.njit(**_LEAF_JIT_OPTIONS)(twin)


_atan_llvm = _llvm_inlined(_atan)
_low_speed_factor_llvm = _llvm_inlined(_low_speed_factor)
_sin_branch_free_llvm = _llvm_inlined(_sin_branch_free)


@nb.njit(inline="always", **_JIT_OPTIONS)
def _mf61_evaluate_wheels(
    tp: np.ndarray,
    coef: np.ndarray,
    kappa_in: tuple[float, ...],
    tan_alpha_in: tuple[float, ...],
    fz_in: tuple[float, ...],
    vx_in: tuple[float, ...],
    out: np.ndarray,
) -> None:
    """:func:`_mf61_evaluate` of ``N_WHEEL_TIRES`` MF 6.1 tires in one pass, with the
    dispatcher's mirroring and no-load rule (``core.tire.tire_evaluate``) for each.

    Parameters
    ----------
    tp : float64[N_WHEEL_TIRES, N_TIRE_PARAM]
        Packed tire vectors (every one an MF 6.1 tire, ``tp[w, TP_MODEL_BASE:]`` its
        ``P_*`` slots, ``tp[w, TP_MIRRORED]`` its side).
    coef : float64[N_WHEEL_TIRES, N_TIRE_COEF]
        Written by :func:`mf61_prepare`; read only.
    kappa_in, tan_alpha_in, fz_in, vx_in : tuples of N_WHEEL_TIRES floats
        Per tire, as the arguments of :func:`_mf61_evaluate` (``tan_alpha`` unmirrored).
    out : float64[N_WHEEL_TIRES, N_TIRE_OUT]
        Written, row ``w`` as ``tire_evaluate`` writes ``out`` for tire ``w``.

    Notes
    -----
    The same equations as :func:`_mf61_evaluate`, in branch-free loops that the compiler
    vectorises: the work before the curves, across the tires; the ``N_WHEEL_TIRES x
    N_WHEEL_CURVES`` Magic Formula curves (lane ``j N_WHEEL_TIRES + w``: curve ``j`` of
    tire ``w``; curve 7 is ``Fy0`` at ``gamma = 0`` for (4.E74), evaluated always and
    used where the camber is not zero; curve 8, with ``E = 0``, is ``S_Vyk``'s (4.E66));
    the work after them, across the tires. Equal to :func:`_mf61_evaluate` to rounding
    (checked in tests/test_tire_mf61.py).
    """
    nt = N_WHEEL_TIRES
    yb = _stack_wheel_lanes()
    eb = _stack_wheel_lanes()
    cb = _stack_wheel_lanes()
    kb = _stack_wheel_lanes()
    sb = _stack_wheel_lanes()
    xb = _stack_wheel_lanes()
    kappa_b = _stack_wheel_tires()
    tan_b = _stack_wheel_tires()
    fz_b = _stack_wheel_tires()
    vx_b = _stack_wheel_tires()
    low_b = _stack_wheel_tires()
    cos_b = _stack_wheel_tires()
    dvyk_b = _stack_wheel_tires()
    ar_b = _stack_wheel_tires()
    fz_prep_b = _stack_wheel_tires()
    scale_b = _stack_wheel_tires()
    ob = _stack_wheel_outs()
    for w in range(nt):
        kappa_b[w] = kappa_in[w]
        tan_b[w] = tan_alpha_in[w]
        fz_b[w] = fz_in[w]
        vx_b[w] = vx_in[w]
        # read here, not in the lane loops below: a read of a row's first slot there
        # makes the compiler want a run-time check of coef's row stride, which it does
        # not do for a loop of N_WHEEL_TIRES iterations, so it leaves the loop scalar
        fz_prep_b[w] = coef[w, C_FZ_PREP]

    # --- before the curves: as _mf61_evaluate --------------------------------------------
    for w in range(nt):
        p = tp[w, TP_MODEL_BASE:]
        c = coef[w]
        side = 1.0 - 2.0 * tp[w, TP_MIRRORED]
        kappa = min(max(kappa_b[w], -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
        tan_alpha = min(max(tan_b[w] * side, -SLIP_INPUT_MAX), SLIP_INPUT_MAX)
        kappa_b[w] = kappa
        tan_b[w] = tan_alpha
        cos_b[w] = 1.0 / math.sqrt(1.0 + tan_alpha * tan_alpha)  # (4.E6)
        rbx2k = p[P_RBX2] * kappa
        bxa = c[C_BXA0] / math.sqrt(1.0 + rbx2k * rbx2k)  # (4.E54)
        exa = c[C_EXA]
        cxa = p[P_RCX1]  # (4.E55)
        shxa = p[P_RHX1]  # (4.E57)
        rby2a = p[P_RBY2] * (tan_alpha - p[P_RBY3])
        byk = c[C_BYK0] / math.sqrt(1.0 + rby2a * rby2a)  # (4.E62)
        eyk = c[C_EYK]
        cyk = p[P_RCY1]  # (4.E63)
        shyk = c[C_SHYK]  # (4.E61)
        rvy4a = p[P_RVY4] * tan_alpha
        dvyk_b[w] = c[C_DVYK0] / math.sqrt(1.0 + rvy4a * rvy4a)  # (4.E67)
        low = _low_speed_factor_llvm(vx_b[w], p[P_VXLOW])
        low_b[w] = low
        kappa_x = kappa + c[C_SHX] * low  # (4.E10)
        ex = c[C_EX_POS] if kappa_x >= 0.0 else c[C_EX_NEG]  # (4.E14)
        shy = c[C_SHY] * low
        alpha_y = tan_alpha + shy  # (4.E20)
        ey = c[C_EY_POS] if alpha_y >= 0.0 else c[C_EY_NEG]  # (4.E24)
        alpha_t = tan_alpha + c[C_SHT]  # (4.E34)
        et = min(c[C_ET_LOAD] * (1.0 + c[C_ET_GAMMA] * _atan_llvm(c[C_BT_CT] * alpha_t)), 1.0)
        alpha_r = tan_alpha + shy + c[C_SVY_KYA] * low  # (4.E37), (4.E38)
        kk = c[C_KXK_KYA] * kappa  # (4.E77), (4.E78)
        alpha_t_eq = math.sqrt(alpha_t * alpha_t + kk * kk)
        ar_b[w] = math.sqrt(alpha_r * alpha_r + kk * kk)
        alpha_y0 = tan_alpha + c[C_SHY_G0] * low  # (4.E74)'s Fy0 at gamma = 0
        ey_g0 = c[C_EY_G0_POS] if alpha_y0 >= 0.0 else c[C_EY_G0_NEG]
        # the lanes: (y, E, C, K) as in _mf61_evaluate's call of _mf_lanes, then the ninth
        yb[w], eb[w], cb[w], kb[w] = bxa * shxa, exa, cxa, _PI_2
        yb[nt + w], eb[nt + w], cb[nt + w], kb[nt + w] = bxa * (tan_alpha + shxa), exa, cxa, _PI_2
        yb[2 * nt + w], eb[2 * nt + w], cb[2 * nt + w], kb[2 * nt + w] = byk * shyk, eyk, cyk, _PI_2
        yb[3 * nt + w], eb[3 * nt + w], cb[3 * nt + w], kb[3 * nt + w] = (
            byk * (kappa + shyk), eyk, cyk, _PI_2)
        yb[4 * nt + w], eb[4 * nt + w], cb[4 * nt + w], kb[4 * nt + w] = (
            c[C_BX] * kappa_x, ex, c[C_CX], 0.0)
        yb[5 * nt + w], eb[5 * nt + w], cb[5 * nt + w], kb[5 * nt + w] = (
            c[C_BY] * alpha_y, ey, c[C_CY], 0.0)
        yb[6 * nt + w], eb[6 * nt + w], cb[6 * nt + w], kb[6 * nt + w] = (
            c[C_BT] * alpha_t_eq, et, p[P_QCZ1], _PI_2)
        yb[7 * nt + w], eb[7 * nt + w], cb[7 * nt + w], kb[7 * nt + w] = (
            c[C_BY_G0] * alpha_y0, ey_g0, c[C_CY], 0.0)
        yb[8 * nt + w], eb[8 * nt + w], cb[8 * nt + w], kb[8 * nt + w] = (
            p[P_RVY6] * kappa, 0.0, p[P_RVY5], 0.0)  # E = 0: last (see N_WHEEL_E_LANES)

    # --- the curves: branch-free loops, vectorised (as _mf_lanes) -------------------------
    for i in range(N_WHEEL_LANES, N_WHEEL_LANES_PADDED):
        yb[i] = eb[i] = cb[i] = kb[i] = 0.0
    # in three loops, each with fewer constants live than the 32 vector registers hold
    # (one loop kept about 30 of them on the stack and loaded them again every vector);
    # the inner atan only where E may be non-zero (where E = 0 the argument is y)
    for i in range(N_WHEEL_E_LANES):
        yi = yb[i]
        ei = eb[i]
        yb[i] = (1.0 - ei) * yi + ei * _atan_llvm(yi)
    for i in range(N_WHEEL_LANES_PADDED):
        xb[i] = cb[i] * _atan_llvm(yb[i]) + kb[i]
    for i in range(N_WHEEL_LANES_PADDED):
        sb[i] = _sin_branch_free_llvm(xb[i])

    # --- after the curves: as _mf61_evaluate, the tires side by side -------------------
    # Branch-free, writing only the stack lanes ob (force or moment k of tire w at k
    # N_WHEEL_TIRES + w) and reading no first slot of a row (see fz_prep_b): the compiler
    # then vectorises the loop across the tires (its four divisions and square root are
    # one vector instruction each, not four). Then, per tire, the rows of out: the forces
    # from ob, the load-only outputs from coef (scalar reads: as vector lanes each of
    # them costs a gather, which made the whole 4 % slower).
    pb = TP_MODEL_BASE  # tp[w, pb + P_*]: the P_* slots of tire w
    for w in range(nt):
        c = coef[w]
        side = 1.0 - 2.0 * tp[w, TP_MIRRORED]
        kappa = kappa_b[w]
        tan_alpha = tan_b[w]
        fz_n = fz_b[w]
        low = low_b[w]
        cos_a = cos_b[w]
        scale = max(min(fz_n, FZ_INPUT_MAX_N), 0.0) / fz_prep_b[w]
        gxa = max(sb[nt + w] / max(sb[w], _TINY), 0.0)  # (4.E51), (4.E52)
        gyk = max(sb[3 * nt + w] / max(sb[2 * nt + w], _TINY), 0.0)  # (4.E59), (4.E60)
        fx0 = c[C_DX] * sb[4 * nt + w] + c[C_SVX] * low  # (4.E9)
        fy0 = c[C_DY] * sb[5 * nt + w] + c[C_SVY] * low  # (4.E19)
        t = c[C_DT] * sb[6 * nt + w] * cos_a  # (4.E73)
        svyk = dvyk_b[w] * sb[8 * nt + w] * tp[w, pb + P_LVYKA]  # (4.E66)
        fy0_cam = c[C_DY_G0] * sb[7 * nt + w] + c[C_SVY_G0] * low
        camber = 1.0 * (c[C_CAMBER] != 0.0)  # gamma* = 0: the same curve, fy0
        fy0_g0 = fy0_cam * camber + fy0 * (1.0 - camber)
        fx = gxa * fx0  # (4.E50)
        fy = gyk * fy0 + svyk  # (4.E58)
        fy_prime = gyk * fy0_g0  # (4.E74)
        br_ar = c[C_BR] * ar_b[w]
        dr = c[C_DR0] * cos_a  # (4.E47)
        mzr = dr / math.sqrt(1.0 + br_ar * br_ar)  # (4.E75)
        r0 = tp[w, pb + P_UNLOADED_RADIUS]
        arm = (r0 * (tp[w, pb + P_SSZ1] + tp[w, pb + P_SSZ2] * fy * c[C_INV_FZ0] + c[C_S_GAMMA])
               * tp[w, pb + P_LS])
        mz = -t * fy_prime + mzr + arm * fx  # (4.E71), (4.E72), (4.E76)
        vr = min(abs(vx_b[w]), VX_MY_MAX_MPS) * c[C_INV_V0]
        vr2 = vr * vr
        my = (
            c[C_MY_SCALE]
            * (tp[w, pb + P_QSY1] + tp[w, pb + P_QSY2] * fx * c[C_INV_FNOMIN]
               + tp[w, pb + P_QSY3] * vr + tp[w, pb + P_QSY4] * vr2 * vr2 + c[C_MY_GAMMA])
            * c[C_MY_PRESSURE]
        )  # (4.E70)  # fmt: skip
        # without load, as core.tire._no_load: forces zero, stiffnesses and limits 1.
        # A 0/1 factor, not a conditional expression: the loop stays branch-free.
        loaded = 1.0 * (fz_n > 0.0)
        scale_b[w] = scale * loaded
        ob[OUT_FX * nt + w] = fx * scale * loaded
        ob[OUT_FY * nt + w] = fy * scale * side * loaded
        ob[OUT_MZ * nt + w] = mz * scale * side * loaded
        ob[OUT_MY * nt + w] = max(my, 0.0) * scale * loaded
    for w in range(nt):
        c = coef[w]
        o = out[w]
        scale = scale_b[w]
        loaded = fz_b[w] > 0.0
        o[OUT_FX] = ob[OUT_FX * nt + w]
        o[OUT_FY] = ob[OUT_FY * nt + w]
        o[OUT_MZ] = ob[OUT_MZ * nt + w]
        o[OUT_MY] = ob[OUT_MY * nt + w]
        o[OUT_C_KAPPA] = c[C_KXK] * scale if loaded else 1.0
        o[OUT_C_ALPHA] = c[C_KYA_ABS] * scale if loaded else 1.0
        kappa_slide = c[C_KAPPA_SLIDE_POS] if kappa_b[w] >= 0.0 else c[C_KAPPA_SLIDE_NEG]
        o[OUT_KAPPA_SLIDE] = kappa_slide if loaded else 1.0
        tan_alpha_slide = (
            c[C_TAN_ALPHA_SLIDE_POS] if tan_b[w] >= 0.0 else c[C_TAN_ALPHA_SLIDE_NEG]
        )
        o[OUT_TAN_ALPHA_SLIDE] = tan_alpha_slide if loaded else 1.0
        o[OUT_FX_PEAK] = c[C_DX_ABS] * scale
        o[OUT_FY_PEAK] = c[C_DY_ABS] * scale


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

    :func:`mf61_prepare` at ``fz_n``, then :func:`mf61_evaluate` at ``fz_n`` (the
    coefficients live on the stack).

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
    """
    if not fz_n > 0.0:
        for i in range(out.shape[0]):
            out[i] = 0.0
        out[OUT_C_KAPPA] = 1.0
        out[OUT_C_ALPHA] = 1.0
        out[OUT_KAPPA_SLIDE] = 1.0
        out[OUT_TAN_ALPHA_SLIDE] = 1.0
        return
    coef = coef_scratch()
    _mf61_prepare(p, gamma_rad, fz_n, mu_scale, coef)
    _mf61_evaluate(p, coef, kappa, tan_alpha, fz_n, vx_mps, out)


@nb.njit(**_JIT_OPTIONS)
def mf61_prepare(
    p: np.ndarray, gamma_rad: float, fz_n: float, mu_scale: float, coef: np.ndarray
) -> None:
    """Load-dependent coefficients of MF 6.1 into ``coef``: :func:`_mf61_prepare`.

    Compiled on its own, so it may be called from code compiled with any options.
    """
    _mf61_prepare(p, gamma_rad, fz_n, mu_scale, coef)


@nb.njit(**_JIT_OPTIONS)
def mf61_evaluate(
    p: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """MF 6.1 forces from prepared coefficients at the load ``fz_n``: :func:`_mf61_evaluate`.

    Compiled on its own, so it may be called from code compiled with any options.
    """
    _mf61_evaluate(p, coef, kappa, tan_alpha, fz_n, vx_mps, out)


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
    _pack_derived(vec)
    return vec


def _pack_derived(vec: np.ndarray) -> None:
    """Fill the derived slots (:data:`MF61_DERIVED_NAMES`) of ``vec`` from its keys, as
    :func:`_mf61_prepare` computed them per call before (the same expressions)."""
    vec[D_PEAK_TARGET_X] = _peak_target(vec[P_PCX1] * vec[P_LCX])
    vec[D_PEAK_TARGET_Y] = _peak_target(vec[P_PCY1] * vec[P_LCY])
    vec[D_INV_FZ0] = 1.0 / (vec[P_FNOMIN] * vec[P_LFZO])
    vec[D_INV_FNOMIN] = 1.0 / vec[P_FNOMIN]


# ---- the kernels registered for this model (simserver.tires.registry): the packed tire vector
# in full (core.tire_layout.PREPARE_SIGNATURE, EVALUATE_SIGNATURE), the body inlined.
# Compiled on first use, not at import: the step inlines the body itself (core.tire)


@nb.njit(**_JIT_OPTIONS)
def mf61_prepare_kernel(
    tp: np.ndarray, gamma_rad: float, fz_n: float, mu_scale: float, coef: np.ndarray
) -> None:
    """:func:`_mf61_prepare` on the model slots of the packed tire vector ``tp``."""
    _mf61_prepare(tp[TP_MODEL_BASE:], gamma_rad, fz_n, mu_scale, coef)


@nb.njit(**_JIT_OPTIONS)
def mf61_evaluate_kernel(
    tp: np.ndarray,
    coef: np.ndarray,
    kappa: float,
    tan_alpha: float,
    fz_n: float,
    vx_mps: float,
    out: np.ndarray,
) -> None:
    """:func:`_mf61_evaluate` on the model slots of the packed tire vector ``tp``."""
    _mf61_evaluate(tp[TP_MODEL_BASE:], coef, kappa, tan_alpha, fz_n, vx_mps, out)
