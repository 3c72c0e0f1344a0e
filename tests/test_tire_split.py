"""The split tire evaluation: ``tire_prepare`` once per step, ``tire_evaluate`` per stage.

What is checked, for both models (brush; MF 6.1 with the sample file and a variant that
takes the other branches):

- at the prepared load the split is ``tire_forces`` (to 1e-12), for any input;
- at another load ``Fz'`` it returns the prepared outputs scaled by ``Fz' / Fz_c``;
- the error this makes against ``tire_forces`` at ``Fz'`` (the bound below);
- forces go to zero with the load; nothing is allocated or reference-counted;
- the compiled kernels equal their Python source; every output is finite.

Error at another load (derivation). Let ``F(s, Fz)`` be an output of the full model
(``tire_forces``) at slip ``s``, and ``f = F / Fz`` the output per unit load. Prepared
at ``Fz`` (inside the file's FZMIN..FZMAX) and evaluated at ``Fz' = (1 + eps) Fz``, the
split returns ``Fz' f(s, Fz)``, so its error is exactly

    e = F(s, Fz') - Fz' f(s, Fz) = Fz' [f(s, Fz') - f(s, Fz)],

and by the mean value theorem, with ``xi df/dxi = dF/dFz - F / Fz``,

    |e| <= |eps| Fz' sup_{xi in [Fz, Fz']} |dF/dFz - F/Fz|  =:  |eps| Fz' Lambda_F.

The split keeps the part of the load dependence that is proportional to ``Fz`` and
drops only the change of the curve per unit load (friction coefficient, stiffness per
unit load, shape factors, shifts); ``e`` is first order in ``eps``. Closed forms:

- peaks ``D = mu(Fz) Fz`` with ``mu`` linear in ``dfz`` (4.E13, 4.E23): exactly
  ``e = Fz' PDX2 LMUX mu_scale (Fz' - Fz) / Fz0`` (sample file: 0.083 eps Fz' at Fz0);
- stiffnesses: ``e = eps K [d ln(K / Fz) / d ln Fz] + O(eps^2)``, with
  ``d ln(Kxk / Fz) / d ln Fz = (PKX2 / (PKX1 + PKX2 dfz) + PKX3) Fz / Fz0`` (4.E15) and
  ``d ln(Kya / Fz) / d ln Fz = PKY4 a cot(PKY4 atan a) / (1 + a^2) - 1``,
  ``a = Fz / (PKY2 Fz0)`` (4.E25, gamma = 0, nominal pressure);
- forces in the linear range ``e = eps F d ln(K / Fz) / d ln Fz``, in sliding
  ``e = eps F d ln(mu) / d ln Fz``.

For the sample file over 1000 <= Fz <= 9000 N, any slip, |gamma| <= 0.1, friction scale
0.3..1, a search over 4e5 points gives ``Lambda`` = 0.21 (Fx), 0.59 (Fy), 0.029 m (Mz),
3e-4 m (My), 5.2 (C_kappa, per unit load), 8.9 (C_alpha): ``LAMBDA`` below adds margin.
At ``FNOMIN`` = 4000 N they are 0.10, 0.22, 0.011 m: for a 1 % load change within a step,
|dFx| <= 4 N, |dFy| <= 9 N, |dMz| <= 0.45 N m there. The brush model is exactly linear in
load: its split is exact at any load.
"""

from __future__ import annotations

import math
import re

import numba as nb
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from simserver.adapters.config import load_tire
from simserver.core import tire, tire_mf61, tire_simple
from simserver.core.tire import (
    BUILTIN_KERNELS,
    tire_evaluate,
    tire_forces,
    tire_prepare,
)
from simserver.core.tire_layout import (
    N_MF61_COEF,
    N_SIMPLE_COEF,
    N_TIRE_COEF,
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
    TP_MIRRORED,
    TP_MODEL_BASE,
)
from tests.conftest import CONFIGS, mf61_sample_coefficients

C = mf61_sample_coefficients()
VARIANT = mf61_sample_coefficients(variant=True)
MF_SAMPLE, _ = load_tire(CONFIGS / "tires" / "mf61_sample.yaml")
MF_VARIANT = MF_SAMPLE.copy()
MF_VARIANT[TP_MODEL_BASE : TP_MODEL_BASE + tire_mf61.N_MF61_PARAM] = (
    tire_mf61.mf61_param_vector(VARIANT)
)
SIMPLE, _ = load_tire(CONFIGS / "tires" / "paper_sti.yaml")
TIRES = {"mf61": MF_SAMPLE, "mf61_variant": MF_VARIANT, "simple": SIMPLE}
R0 = C["UNLOADED_RADIUS"]

FORCE_SLOTS = [OUT_FX, OUT_FY, OUT_MZ, OUT_MY, OUT_C_KAPPA, OUT_C_ALPHA, OUT_FX_PEAK, OUT_FY_PEAK]
SLIDE_SLOTS = [OUT_KAPPA_SLIDE, OUT_TAN_ALPHA_SLIDE]
LAMBDA = {  # sample file, 1000..9000 N: sup |dF/dFz - F/Fz| with margin (module docstring)
    OUT_FX: 0.25,
    OUT_FY: 0.65,
    OUT_MZ: 0.035,
    OUT_MY: 1e-3,
    OUT_C_KAPPA: 5.5,
    OUT_C_ALPHA: 9.5,
}


def forces(tp, kappa, tan_alpha, gamma, fz, mu, vx) -> np.ndarray:
    """``tire_forces``, ``out`` pre-filled with NaN."""
    out = np.full(N_TIRE_OUT, np.nan)
    tire_forces(BUILTIN_KERNELS, tp, kappa, tan_alpha, gamma, fz, mu, vx, out)
    return out


def split(tp, kappa, tan_alpha, gamma, fz_prepared, fz, mu, vx) -> np.ndarray:
    """``tire_prepare`` at ``fz_prepared``, ``tire_evaluate`` at ``fz`` (NaN-filled)."""
    coef = np.full(N_TIRE_COEF, np.nan)
    tire_prepare(BUILTIN_KERNELS, tp, gamma, fz_prepared, mu, coef)
    out = np.full(N_TIRE_OUT, np.nan)
    tire_evaluate(BUILTIN_KERNELS, tp, coef, kappa, tan_alpha, fz, vx, out)
    return out


def natural_scale(fz: float) -> np.ndarray:
    """Per output: its size at load ``fz`` (forces Fz, moments Fz R0, slips 1)."""
    f = min(max(abs(fz), 1.0), tire_mf61.FZ_INPUT_MAX_N)
    scale = np.ones(N_TIRE_OUT)
    scale[[OUT_FX, OUT_FY, OUT_FX_PEAK, OUT_FY_PEAK]] = f
    scale[[OUT_MZ, OUT_MY]] = f * R0
    scale[[OUT_C_KAPPA, OUT_C_ALPHA]] = 10.0 * f
    return scale


def assert_close(a: np.ndarray, b: np.ndarray, fz: float, rtol: float = 1e-12) -> None:
    """Relative to each output's magnitude, floored at 1e-3 of its natural scale."""
    floor = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1e-3 * natural_scale(fz))
    assert np.all(np.abs(a - b) <= rtol * floor), (a, b, a - b)


finite = st.floats(allow_nan=False, allow_infinity=False)
slip = st.one_of(st.floats(-0.5, 0.5), st.floats(-1e3, 1e3), finite)
load = st.one_of(st.floats(-1e3, 2e4), finite)


# --- layout ---------------------------------------------------------------------------------


def test_coefficient_layout() -> None:
    assert N_TIRE_COEF == max(N_MF61_COEF, N_SIMPLE_COEF)
    names = tire_mf61.MF61_COEF_NAMES
    assert len(set(names)) == len(names) == N_MF61_COEF
    slots = {k: v for k, v in vars(tire_mf61).items() if re.fullmatch(r"C_[A-Z0-9_]+", k)}
    assert len(slots) == N_MF61_COEF
    for const, idx in slots.items():
        assert names[idx] == const[2:], const
    simple = {k: v for k, v in vars(tire_simple).items() if re.fullmatch(r"SC_[A-Z_]+", k)}
    assert sorted(simple.values()) == list(range(N_SIMPLE_COEF))


@pytest.mark.parametrize("name", TIRES)
def test_prepare_writes_every_slot_it_uses(name: str) -> None:
    n_used = N_SIMPLE_COEF if name == "simple" else N_MF61_COEF
    for gamma, fz, mu in ((0.0, 4000.0, 1.0), (0.05, -10.0, 0.3), (-0.1, 3e4, 2.0)):
        coef = np.full(N_TIRE_COEF, np.nan)
        tire_prepare(BUILTIN_KERNELS, TIRES[name], gamma, fz, mu, coef)
        assert np.all(np.isfinite(coef[:n_used])), coef


# --- the split at the prepared load is tire_forces ---------------------------------------


@settings(max_examples=300, deadline=None)
@given(
    name=st.sampled_from(list(TIRES)),
    kappa=slip,
    tan_alpha=slip,
    gamma=st.one_of(st.just(0.0), st.floats(-0.2, 0.2), finite),
    fz=load,
    mu=st.one_of(st.floats(0.0, 2.0), finite),
    vx=st.one_of(st.floats(-50.0, 50.0), finite),
)
def test_split_at_the_prepared_load_is_tire_forces(
    name: str, kappa: float, tan_alpha: float, gamma: float, fz: float, mu: float, vx: float
) -> None:
    tp = TIRES[name]
    whole = forces(tp, kappa, tan_alpha, gamma, fz, mu, vx)
    parts = split(tp, kappa, tan_alpha, gamma, fz, fz, mu, vx)
    assert_close(parts, whole, fz)


@pytest.mark.parametrize("name", TIRES)
def test_no_load(name: str) -> None:
    """At ``fz <= 0``: zeros, stiffnesses and limits 1, whatever was prepared."""
    for fz_prepared in (4000.0, 0.0, -50.0):
        for fz in (0.0, -1.0, -1e9):
            out = split(TIRES[name], 0.1, -0.2, 0.0, fz_prepared, fz, 1.0, 10.0)
            ones = [OUT_C_KAPPA, OUT_C_ALPHA, OUT_KAPPA_SLIDE, OUT_TAN_ALPHA_SLIDE]
            assert np.all(out[ones] == 1.0)
            assert np.all(np.delete(out, ones) == 0.0)


@pytest.mark.parametrize("name", TIRES)
def test_prepared_without_load_then_touching_down(name: str) -> None:
    """Prepared at ``fz <= 0`` (wheel in the air), evaluated with load: the model's own
    linear continuation below its load floor, i.e. ``tire_forces`` at that load."""
    tp = TIRES[name]
    for fz in (1e-6, 0.5, 20.0):
        for kappa, tan_alpha in ((0.0, 0.0), (0.05, -0.03), (-0.4, 0.3)):
            parts = split(tp, kappa, tan_alpha, 0.0, -5.0, fz, 0.9, 12.0)
            whole = forces(tp, kappa, tan_alpha, 0.0, fz, 0.9, 12.0)
            assert_close(parts, whole, fz)


# --- the split at another load ----------------------------------------------------------------


@pytest.mark.parametrize("name", TIRES)
@pytest.mark.parametrize("ratio", [1.01, 0.99, 1.3, 1e-3])
def test_other_load_scales_the_prepared_outputs(name: str, ratio: float) -> None:
    """``evaluate`` at ``Fz'`` = prepared outputs times ``Fz' / Fz`` (Fz in the fitted
    range); the sliding limits are the prepared ones."""
    tp = TIRES[name]
    for fz in (2500.0, 4000.0, 6000.0):
        for kappa, tan_alpha, gamma in ((0.03, 0.02, 0.0), (-0.2, 0.15, 0.04), (2.0, -5.0, 0.0)):
            at_fz = forces(tp, kappa, tan_alpha, gamma, fz, 0.8, 15.0)
            out = split(tp, kappa, tan_alpha, gamma, fz, ratio * fz, 0.8, 15.0)
            expect = at_fz.copy()
            expect[FORCE_SLOTS] *= ratio
            assert_close(out, expect, ratio * fz)
            assert np.array_equal(out[SLIDE_SLOTS], at_fz[SLIDE_SLOTS])


@pytest.mark.parametrize("name", TIRES)
def test_force_goes_to_zero_with_the_load(name: str) -> None:
    tp = TIRES[name]
    at_fz = forces(tp, 0.08, -0.06, 0.0, 4000.0, 1.0, 20.0)
    assert np.all(np.abs(at_fz[[OUT_FX, OUT_FY, OUT_MZ]]) > 1.0)
    for t in (1e-1, 1e-4, 1e-9, 1e-15):
        out = split(tp, 0.08, -0.06, 0.0, 4000.0, t * 4000.0, 1.0, 20.0)
        expect = at_fz.copy()
        expect[FORCE_SLOTS] *= t
        assert_close(out, expect, t * 4000.0)
    out = split(tp, 0.08, -0.06, 0.0, 4000.0, 0.0, 1.0, 20.0)
    assert np.all(out[[OUT_FX, OUT_FY, OUT_MZ, OUT_MY, OUT_FX_PEAK, OUT_FY_PEAK]] == 0.0)


@settings(max_examples=300, deadline=None)
@given(
    kappa=st.floats(-1e3, 1e3),
    tan_alpha=st.floats(-1e3, 1e3),
    fz=st.floats(1.0, 3e4),
    ratio=st.floats(1e-6, 1e6),
    mu=st.floats(0.0, 2.0),
)
def test_brush_split_is_exact_at_any_load(
    kappa: float, tan_alpha: float, fz: float, ratio: float, mu: float
) -> None:
    parts = split(SIMPLE, kappa, tan_alpha, 0.0, fz, ratio * fz, mu, 5.0)
    whole = forces(SIMPLE, kappa, tan_alpha, 0.0, ratio * fz, mu, 5.0)
    assert_close(parts, whole, ratio * fz, rtol=1e-11)


@settings(max_examples=400, deadline=None)
@given(
    kappa=st.one_of(st.floats(-0.3, 0.3), st.floats(-5.0, 5.0)),
    tan_alpha=st.one_of(st.floats(-0.4, 0.4), st.floats(-20.0, 20.0)),
    gamma=st.one_of(st.just(0.0), st.floats(-0.1, 0.1)),
    fz=st.floats(1000.0, 9000.0),
    eps=st.sampled_from([0.01, -0.01]),
    mu=st.floats(0.3, 1.0),
)
def test_mf61_error_at_another_load_is_bounded(
    kappa: float, tan_alpha: float, gamma: float, fz: float, eps: float, mu: float
) -> None:
    """``|e| <= |eps| Fz' Lambda_F`` (module docstring), a 1 % load error."""
    fz_new = (1.0 + eps) * fz
    e = forces(MF_SAMPLE, kappa, tan_alpha, gamma, fz_new, mu, 20.0) - split(
        MF_SAMPLE, kappa, tan_alpha, gamma, fz, fz_new, mu, 20.0
    )
    for slot, lam in LAMBDA.items():
        assert abs(e[slot]) <= abs(eps) * fz_new * lam, (slot, e[slot] / (eps * fz_new))
    # peaks: exactly the change of the friction coefficient (4.E13, 4.E23: linear in dfz)
    fz0 = C["FNOMIN"] * C["LFZO"]
    assert e[OUT_FX_PEAK] == pytest.approx(
        fz_new * C["PDX2"] * C["LMUX"] * mu * (fz_new - fz) / fz0, rel=1e-9, abs=1e-9
    )
    mu_y_change = C["PDY2"] * C["LMUY"] * mu * (fz_new - fz) / fz0
    assert e[OUT_FY_PEAK] == pytest.approx(
        fz_new * mu_y_change * (1.0 - C["PDY3"] * math.sin(gamma) ** 2), rel=1e-9, abs=1e-9
    )


@pytest.mark.parametrize("fz", [1500.0, 4000.0, 6500.0])
@pytest.mark.parametrize("eps", [1e-2, -1e-2, 1e-3])
def test_mf61_stiffness_error_closed_form(fz: float, eps: float) -> None:
    """``e = Fz' (Fz' - Fz) d(K/Fz)/dFz`` at the midpoint load ``+ O(eps^3)``, with the
    closed-form elasticities of (4.E15) and (4.E25) (module docstring)."""
    fz_new = (1.0 + eps) * fz
    fz_mid = 0.5 * (fz + fz_new)
    e = forces(MF_SAMPLE, 0.0, 0.0, 0.0, fz_new, 1.0, 20.0) - split(
        MF_SAMPLE, 0.0, 0.0, 0.0, fz, fz_new, 1.0, 20.0
    )
    at_mid = forces(MF_SAMPLE, 0.0, 0.0, 0.0, fz_mid, 1.0, 20.0)
    fz0 = C["FNOMIN"] * C["LFZO"]
    dfz = (fz_mid - fz0) / fz0
    elasticity_x = (C["PKX2"] / (C["PKX1"] + C["PKX2"] * dfz) + C["PKX3"]) * fz_mid / fz0
    a = fz_mid / (C["PKY2"] * fz0)
    w = C["PKY4"] * math.atan(a)
    elasticity_y = C["PKY4"] * a / (1.0 + a * a) * math.cos(w) / math.sin(w) - 1.0
    for slot, elasticity in ((OUT_C_KAPPA, elasticity_x), (OUT_C_ALPHA, elasticity_y)):
        per_load_slope = at_mid[slot] / fz_mid * elasticity / fz_mid  # d(K/Fz)/dFz
        expect = fz_new * (fz_new - fz) * per_load_slope
        assert e[slot] == pytest.approx(expect, rel=20.0 * eps * eps, abs=1e-9), slot


def test_mf61_error_follows_the_load_sensitivity() -> None:
    """Pointwise: ``e / (eps Fz') -> dF/dFz - F/Fz`` (central differences of the full
    model), the first-order term of the derivation."""
    eps = 1e-3
    for fz in (2000.0, 4000.0, 7000.0):
        for kappa, tan_alpha, gamma in ((0.02, 0.03, 0.0), (-0.1, -0.08, 0.05), (0.5, 0.4, 0.0)):
            h = 1e-4 * fz
            up = forces(MF_SAMPLE, kappa, tan_alpha, gamma, fz + h, 1.0, 20.0)
            down = forces(MF_SAMPLE, kappa, tan_alpha, gamma, fz - h, 1.0, 20.0)
            at_fz = forces(MF_SAMPLE, kappa, tan_alpha, gamma, fz, 1.0, 20.0)
            sensitivity = (up - down) / (2.0 * h) - at_fz / fz
            fz_new = (1.0 + eps) * fz
            e = forces(MF_SAMPLE, kappa, tan_alpha, gamma, fz_new, 1.0, 20.0) - split(
                MF_SAMPLE, kappa, tan_alpha, gamma, fz, fz_new, 1.0, 20.0
            )
            for slot, lam in LAMBDA.items():
                assert e[slot] / (eps * fz_new) == pytest.approx(
                    sensitivity[slot], abs=0.01 * lam
                ), slot


# --- robustness, equivalence, no allocation ----------------------------------------------------


@settings(max_examples=400, deadline=None)
@given(
    name=st.sampled_from(list(TIRES)),
    gamma=finite,
    fz_prepared=finite,
    mu=finite,
    kappa=finite,
    tan_alpha=finite,
    fz=finite,
    vx=finite,
)
def test_finite_for_any_finite_input(
    name: str,
    gamma: float,
    fz_prepared: float,
    mu: float,
    kappa: float,
    tan_alpha: float,
    fz: float,
    vx: float,
) -> None:
    out = split(TIRES[name], kappa, tan_alpha, gamma, fz_prepared, fz, mu, vx)
    assert np.all(np.isfinite(out)), out
    assert out[OUT_KAPPA_SLIDE] > 0.0 and out[OUT_TAN_ALPHA_SLIDE] > 0.0
    assert out[OUT_MY] >= 0.0 and out[OUT_FX_PEAK] >= 0.0 and out[OUT_FY_PEAK] >= 0.0


KERNELS = {  # compiled function, its Python source (helpers compiled), parameter vector
    "mf61": (tire_mf61.mf61_prepare, tire_mf61._mf61_prepare.py_func,
             tire_mf61.mf61_evaluate, tire_mf61._mf61_evaluate.py_func,
             MF_SAMPLE[TP_MODEL_BASE:]),
    "mf61_variant": (tire_mf61.mf61_prepare, tire_mf61._mf61_prepare.py_func,
                     tire_mf61.mf61_evaluate, tire_mf61._mf61_evaluate.py_func,
                     MF_VARIANT[TP_MODEL_BASE:]),
    "simple": (tire_simple.simple_prepare, tire_simple._simple_prepare.py_func,
               tire_simple.simple_evaluate, tire_simple._simple_evaluate.py_func,
               SIMPLE[TP_MODEL_BASE:]),
}  # fmt: skip


@pytest.mark.parametrize("name", KERNELS)
def test_jit_equals_py_func(name: str) -> None:
    """Compiled prepare and evaluate equal their Python source to 1e-12 (coefficients:
    relative, floored at 1e-12 of the largest; outputs: as in ``assert_close``)."""
    prepare, prepare_py, evaluate, evaluate_py, p = KERNELS[name]
    rng = np.random.default_rng(20261123)
    for _ in range(200):
        gamma = rng.choice([0.0, rng.uniform(-0.1, 0.1)])
        fz_prepared = rng.choice([rng.uniform(10.0, 14000.0), -5.0])
        mu = rng.uniform(0.1, 1.5)
        a = np.full(N_TIRE_COEF, np.nan)
        b = np.full(N_TIRE_COEF, np.nan)
        prepare(p, gamma, fz_prepared, mu, a)
        prepare_py(p, gamma, fz_prepared, mu, b)
        n_used = N_SIMPLE_COEF if name == "simple" else N_MF61_COEF
        a, b = a[:n_used], b[:n_used]
        floor = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1e-12 * np.max(np.abs(a)))
        assert np.all(np.abs(a - b) <= 1e-12 * floor), (a - b) / floor
        kappa = rng.choice([rng.uniform(-0.3, 0.3), rng.uniform(-5.0, 5.0)])
        tan_alpha = rng.choice([rng.uniform(-0.3, 0.3), rng.uniform(-20.0, 20.0)])
        fz = abs(fz_prepared) * rng.uniform(0.9, 1.1)
        vx = rng.uniform(-40.0, 40.0)
        out = np.full(N_TIRE_OUT, np.nan)
        ref = np.full(N_TIRE_OUT, np.nan)
        evaluate(p, b, kappa, tan_alpha, fz, vx, out)
        evaluate_py(p, b, kappa, tan_alpha, fz, vx, ref)
        assert_close(out, ref, fz)


def _main_function_ir(fn: nb.core.registry.CPUDispatcher, *calls: tuple) -> str:
    """LLVM IR of ``fn``'s own compiled code (the specialisation the step and the tests
    run, from numba's cache or compiled now) without the Python wrappers, after calling it
    with each argument tuple of ``calls``: they must all dispatch to one specialisation,
    so that this IR is the code every one of them ran.

    The IR is the library's module for linking (``_get_module_for_linking``: the final,
    optimised module, NRT pruning done, that numba stores in its cache beside the object
    code so that other functions can inline it); ``inspect_llvm`` has nothing for a
    specialisation loaded from the cache, and recompiling a copy uncached to get it cost
    minutes of CPU a run (issue 33)."""
    for args in calls:
        fn(*args)
    sigs = {tuple(fn.typeof_pyval(a) for a in args) for args in calls}
    assert len(sigs) == 1, (fn.__name__, sigs)
    (sig,) = sigs
    assert sig in fn.overloads, (fn.__name__, sig, fn.signatures)
    module = str(fn.overloads[sig].library._get_module_for_linking())
    bodies = [b for b in re.split(r"\n(?=define )", module) if b.startswith("define")]
    names = [re.search(r'@"?([\w.$]+)', b.splitlines()[0]).group(1) for b in bodies]
    (body,) = [
        b for b, n in zip(bodies, names, strict=True)
        if fn.__name__ in n and not n.startswith(("_ZN7cpython", "cfunc."))
    ]  # fmt: skip
    return body


def test_dispatchers_neither_allocate_nor_count_references() -> None:
    """No heap allocation in prepare, evaluate (nor tire_forces, whose scratch is on the
    stack); and no reference counting either: the model bodies are inlined, so the
    arrays' NRT increments and decrements are pruned (20 ns a call otherwise).

    Every tire model runs through the same compiled code (the model is chosen at run time
    from ``tp[TP_MODEL]``), so one compile per dispatcher, run with each tire, is checked
    for all of them (``_main_function_ir`` asserts they share the specialisation)."""
    out = np.zeros(N_TIRE_OUT)
    calls: dict = {tire.tire_prepare: [], tire.tire_evaluate: [], tire.tire_forces: []}
    for name in ("mf61", "simple"):
        tp, coef = TIRES[name], np.zeros(N_TIRE_COEF)
        tire_prepare(BUILTIN_KERNELS, tp, 0.0, 4000.0, 1.0, coef)
        calls[tire.tire_prepare].append((BUILTIN_KERNELS, tp, 0.0, 4000.0, 1.0, coef))
        calls[tire.tire_evaluate].append(
            (BUILTIN_KERNELS, tp, coef, 0.01, 0.02, 4000.0, 10.0, out))
        calls[tire.tire_forces].append(
            (BUILTIN_KERNELS, tp, 0.01, 0.02, 0.0, 4000.0, 1.0, 10.0, out))
    for fn, args in calls.items():
        body = _main_function_ir(fn, *args)
        called = set(re.findall(r"call [^@]*@\"?([A-Za-z_][\w.]*)", body))
        assert not {c for c in called if "alloc" in c.lower()}, (fn.__name__, called)
        assert not {c for c in called if c.startswith("NRT")}, (fn.__name__, called)


def four_floats(low: float, high: float) -> st.SearchStrategy:
    """One value per tire of the four-tire calls."""
    return st.lists(st.floats(low, high), min_size=4, max_size=4)


def four_at_once_and_one_at_a_time(
    batched: nb.core.registry.CPUDispatcher, tp: np.ndarray, kappa: list, tan_alpha: list,
    gamma: list, fz: list, vx: list,
) -> tuple[np.ndarray, np.ndarray]:
    """Four tires (rows of ``tp``) prepared one at a time, then evaluated by the step's
    ``batched`` call and by ``tire_evaluate`` tire by tire: both sets of output rows."""
    coef = np.full((4, N_TIRE_COEF), np.nan)
    for w in range(4):
        tire_prepare(BUILTIN_KERNELS, tp[w], gamma[w], max(fz[w], 0.0), 1.0, coef[w])
    out = np.full((4, N_TIRE_OUT), np.nan)
    batched(tp, coef, tuple(kappa), tuple(tan_alpha), tuple(fz), tuple(vx), out)
    ref = np.full((4, N_TIRE_OUT), np.nan)
    for w in range(4):
        tire_evaluate(BUILTIN_KERNELS, tp[w], coef[w], kappa[w], tan_alpha[w], fz[w], vx[w],
                      ref[w])
    return out, ref


@settings(max_examples=60, deadline=None)
@given(kappa=four_floats(-1.5, 1.5), tan_alpha=four_floats(-1.5, 1.5),
       gamma=four_floats(-0.1, 0.1), fz=four_floats(-500.0, 9000.0), vx=four_floats(-40.0, 40.0))
def test_four_mf61_tires_at_once_equal_one_at_a_time(
    kappa: list, tan_alpha: list, gamma: list, fz: list, vx: list
) -> None:
    """The step's batched call for four MF 6.1 tires (``tire_evaluate_mf61_wheels``)
    gives what ``tire_evaluate`` gives each tire: the same equations, the curves computed
    in another loop (so equal to rounding: the 1e-12 of ``assert_close``), with mirrored
    tires, the variant file, camber and wheels off the ground among them."""
    tp = np.stack([MF_SAMPLE, MF_VARIANT, MF_SAMPLE, MF_VARIANT])
    tp[1, TP_MIRRORED] = tp[2, TP_MIRRORED] = 1.0
    out, ref = four_at_once_and_one_at_a_time(tire.tire_evaluate_mf61_wheels, tp, kappa,
                                              tan_alpha, gamma, fz, vx)
    mf61 = tire.TIRE_MODEL_MF61
    assert tire.every_tire_is(tp, mf61)
    assert not tire.every_tire_is(np.stack([MF_SAMPLE] * 3 + [SIMPLE]), mf61)
    for w in range(4):
        assert_close(out[w], ref[w], fz[w])


@settings(max_examples=60, deadline=None)
@given(kappa=four_floats(-1.5, 1.5), tan_alpha=four_floats(-1.5, 1.5),
       fz=four_floats(-500.0, 9000.0), vx=four_floats(-40.0, 40.0))
def test_four_brush_tires_at_once_are_bit_for_bit_one_at_a_time(
    kappa: list, tan_alpha: list, fz: list, vx: list
) -> None:
    """The step's batched call for four brush tires (``tire_evaluate_simple_wheels``) is
    ``tire_evaluate``'s brush branch under its compile options: the same bits (the
    first-release replay depends on it), mirrored tires and wheels off the ground among
    them; a set of tires that is not all brush is not taken for one."""
    tp = np.stack([SIMPLE] * 4)
    tp[1, TP_MIRRORED] = tp[3, TP_MIRRORED] = 1.0
    out, ref = four_at_once_and_one_at_a_time(tire.tire_evaluate_simple_wheels, tp, kappa,
                                              tan_alpha, [0.0] * 4, fz, vx)
    assert tire.every_tire_is(tp, tire.TIRE_MODEL_SIMPLE)
    assert not tire.every_tire_is(np.stack([SIMPLE] * 3 + [MF_SAMPLE]),
                                  tire.TIRE_MODEL_SIMPLE)
    for w in range(4):
        assert out[w].tobytes() == ref[w].tobytes(), (w, out[w], ref[w])
