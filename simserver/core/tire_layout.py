"""Slot layout shared by every tire model: common parameters, coefficients, outputs.

Kept apart from :mod:`simserver.core.tire` so that each model kernel can import it
without importing the dispatcher.

Every model is split in two (see :mod:`simserver.core.tire`): ``prepare`` computes the
load-dependent coefficients into a ``coef`` vector of ``N_TIRE_COEF`` floats (the slots
are named in each model's module), ``evaluate`` the slip-dependent rest from them.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, overload

# --- model ids (tp[TP_MODEL]) -----------------------------------------------------
# The ids of the two built-in models, which the dispatchers of core.tire call directly
# (inlined); every other id is a registered model (simserver.tires.registry), called through
# its kernels. The registry is the one list of models, names and ids.
TIRE_MODEL_SIMPLE = 0  # brush-type (Fiala) combined-slip model, explicit stiffnesses
TIRE_MODEL_MF61 = 1  # Magic Formula 6.1 from a .tir property file

# --- common parameter slots --------------------------------------------------------
TP_MODEL = 0
TP_RADIUS_M = 1  # effective rolling radius R (m)
TP_RELAX_LAT_M = 2  # lateral relaxation length b (m), paper eq. 16
TP_RELAX_LONG_M = 3  # longitudinal relaxation length B (m), paper eq. 26
# 1.0: this corner's tire is the mirror image of the tire its file describes (the file's
# tire is mounted on the other side of the car; MF-Tyre's TYRESIDE), 0.0: as described.
# The dispatchers of core.tire mirror every model alike (slip angle, camber, Fy, Mz).
TP_MIRRORED = 4
TP_MODEL_BASE = 5  # first model-specific slot

# --- outputs ---------------------------------------------------------------------
OUT_FX = 0  # longitudinal force (N), wheel frame
OUT_FY = 1  # lateral force (N), wheel frame
OUT_MZ = 2  # aligning moment (N m)
OUT_MY = 3  # rolling-resistance moment magnitude (N m, >= 0), applied against spin
OUT_C_KAPPA = 4  # longitudinal slip stiffness dFx/dkappa at kappa = 0 (N per unit slip)
OUT_C_ALPHA = 5  # cornering stiffness -dFy/dtan_alpha at 0 (N/rad, > 0)
OUT_KAPPA_SLIDE = 6  # |kappa| at the peak of pure-slip Fx: the sliding limit (> 0)
OUT_TAN_ALPHA_SLIDE = 7  # |tan alpha| at the peak of pure-slip Fy: the sliding limit (> 0)
OUT_FX_PEAK = 8  # peak pure-slip |Fx| at this load and friction (N)
OUT_FY_PEAK = 9  # peak pure-slip |Fy| at this load and friction (N)
N_TIRE_OUT = 10

# --- load-dependent coefficients (prepare -> evaluate) -------------------------------
# Slot names live in the model modules (SC_* in tire_simple, C_* in tire_mf61); each
# checks at import that it uses exactly its count here.
N_SIMPLE_COEF = 10
N_MF61_COEF = 53
N_TIRE_COEF = max(N_SIMPLE_COEF, N_MF61_COEF)

# --- compilation of every tire kernel -------------------------------------------------
# Fused multiply-add allowed (and nothing else of fastmath: NaN and inf keep their IEEE
# meaning); division by zero yields inf instead of raising, which removes a test and a
# branch per division. The model bodies are inlined (numba IR) into the dispatchers of
# simserver.core.tire, and inlined code is compiled with the *caller's* options: every
# function that inlines a model body must use exactly these.
# ``_nrt`` is set explicitly because numba hands an unset one down from the caller being
# compiled, and the integrator's step is compiled without reference counting; the
# kernels that allocate a stack scratch as an array (``coef_scratch`` in tire_forces)
# need it.
TIRE_JIT_OPTIONS = {"cache": True, "fastmath": {"contract"}, "error_model": "numpy",
                    "_nrt": True, "forceinline": False}
# The dispatchers the step calls (core.tire.tire_prepare, tire_evaluate) are compiled
# without reference counting: they allocate nothing and hold only their caller's arrays
# and views of them, which the caller keeps alive, so the counts protect nothing. numba
# did not prune them there (three atomic increments and decrements a call, 20 calls a
# step). Their inlined bodies use no array made inside (the MF 6.1 lanes index a stack
# pointer).
TIRE_DISPATCH_JIT_OPTIONS = dict(TIRE_JIT_OPTIONS, _nrt=False)

# --- the compiled interface of a tire model --------------------------------------------
# A model is two functions compiled with these explicit signatures (first-class function
# pointers: a tuple of them is a cacheable argument of a compiled function):
#   prepare(tp, gamma_rad, fz_n, mu_scale, coef)
#   evaluate(tp, coef, kappa, tan_alpha, fz_n, vx_mps, out)
# with ``tp`` the packed tire vector (N_TIRE_PARAM floats: the common TP_* slots, then the
# model's own from TP_MODEL_BASE), ``coef`` N_TIRE_COEF floats, ``out`` N_TIRE_OUT floats
# (core.tire describes the arguments).
_VEC = types.float64[::1]
_F64 = types.float64
PREPARE_SIGNATURE = types.void(_VEC, _F64, _F64, _F64, _VEC)
EVALUATE_SIGNATURE = types.void(_VEC, _VEC, _F64, _F64, _F64, _F64, _VEC)


class TireKernels(NamedTuple):
    """The registered models' compiled functions, indexed by model id (``tp[TP_MODEL]``)."""

    prepare: tuple  # of PREPARE_SIGNATURE functions
    evaluate: tuple  # of EVALUATE_SIGNATURE functions


# --- input ranges shared by the models (outputs stay finite for any finite input) ----
FZ_INPUT_MAX_N = 1.0e9  # fz_n is clamped to this
SLIP_INPUT_MAX = 1.0e6  # |kappa|, |tan_alpha| clamped to this (the curves are flat there)
MU_SCALE_MAX = 10.0  # mu_scale clamped to at most this


@intrinsic
def _stack_coef(typingctx: object) -> tuple:
    """Pointer to ``N_TIRE_COEF`` float64 on the stack of the compiled caller (an alloca)."""
    sig = types.CPointer(types.float64)()

    def codegen(context: object, builder: object, signature: object, args: object) -> object:
        return cgutils.alloca_once(builder, context.get_value_type(types.float64), size=N_TIRE_COEF)

    return sig, codegen


def coef_scratch() -> np.ndarray:
    """A ``float64[N_TIRE_COEF]`` scratch vector for ``prepare`` followed by ``evaluate``.

    In compiled code it lives on the caller's stack (no heap allocation: the call is
    inlined into the caller, see the overload below); called from Python it is a new
    array. Its content is undefined until a ``prepare`` writes it.
    """
    return np.empty(N_TIRE_COEF, dtype=np.float64)


@overload(coef_scratch, inline="always")
def _coef_scratch_compiled() -> object:
    def impl() -> np.ndarray:
        return nb.carray(_stack_coef(), (N_TIRE_COEF,))

    return impl
