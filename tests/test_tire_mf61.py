"""Tests of the compiled Magic Formula 6.1 kernel against the sample .tir file.

Reference values are computed here, independently of the kernel, from the file's
coefficients and Pacejka (2012) eqs. (4.E1)-(4.E30); the kernel is imported directly
(not through the dispatcher :mod:`simserver.core.tire`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from simserver.core import tire_mf61 as mf
from simserver.core.tire_layout import (
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
)
from tests.conftest import SAMPLE_TIR, mf61_sample_coefficients

SAMPLE = SAMPLE_TIR
# the sample, and a variant that takes the other branches (conftest)
C = mf61_sample_coefficients()
P = mf.mf61_param_vector(C)
VARIANT = mf61_sample_coefficients(variant=True)


def run(
    kappa: float,
    tan_alpha: float,
    gamma: float = 0.0,
    fz: float = 4000.0,
    mu: float = 1.0,
    vx: float = 20.0,
    p: np.ndarray = P,
) -> np.ndarray:
    """Outputs of the compiled kernel, ``out`` pre-filled with NaN."""
    out = np.full(N_TIRE_OUT, np.nan)
    mf.mf61_forces(p, kappa, tan_alpha, gamma, fz, mu, vx, out)
    return out


# --- independent closed forms (Pacejka 2012, 4.E1-4.E30; ISO signs as in the file) ------


def dfz_of(fz: float) -> float:
    fz0 = C["FNOMIN"] * C["LFZO"]
    return (fz - fz0) / fz0  # (4.E2a)


def kxk_ref(fz: float) -> float:
    """Longitudinal slip stiffness (4.E15) at nominal pressure."""
    d = dfz_of(fz)
    return fz * (C["PKX1"] + C["PKX2"] * d) * math.exp(C["PKX3"] * d) * C["LKX"]


def kya_ref(fz: float, gamma: float) -> float:
    """Cornering stiffness (4.E25) at nominal pressure (negative for this file)."""
    fz0 = C["FNOMIN"] * C["LFZO"]
    gs = math.sin(gamma)
    return (
        C["PKY1"] * fz0 * (1.0 - C["PKY3"] * abs(gs))
        * math.sin(C["PKY4"] * math.atan(fz / fz0 / (C["PKY2"] + C["PKY5"] * gs * gs)))
        * C["LKY"]
    )  # fmt: skip


def shx_ref(fz: float) -> float:
    return (C["PHX1"] + C["PHX2"] * dfz_of(fz)) * C["LHX"]  # (4.E17)


def shy_ref(fz: float, gamma: float, mu: float = 1.0) -> float:
    """Horizontal shift of Fy0 (4.E27) with (4.E28), (4.E30)."""
    d = dfz_of(fz)
    gs = math.sin(gamma)
    kyg0 = fz * (C["PKY6"] + C["PKY7"] * d) * C["LKYC"]
    svyg = fz * (C["PVY3"] + C["PVY4"] * d) * gs * C["LKYC"] * C["LMUY"] * mu
    return (C["PHY1"] + C["PHY2"] * d) * C["LHY"] + (kyg0 * gs - svyg) / kya_ref(fz, gamma)


def mux_ref(fz: float) -> float:
    return (C["PDX1"] + C["PDX2"] * dfz_of(fz)) * C["LMUX"]  # (4.E13)


def muy_ref(fz: float) -> float:
    return (C["PDY1"] + C["PDY2"] * dfz_of(fz)) * C["LMUY"]  # (4.E23)


def peak_u_ref(c: float, e: float) -> float:
    """Root of u - E (u - atan u) = tan(pi / (2 C)) by bisection (C > 1, E < 1)."""
    target = math.tan(0.5 * math.pi / c)
    lo, hi = 0.0, 1e6
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if (1.0 - e) * mid + e * math.atan(mid) > target:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


# --- layout -------------------------------------------------------------------------------


def test_param_layout_single_source() -> None:
    names = mf.MF61_PARAM_NAMES
    assert len(set(names)) == len(names) == mf.N_MF61_FILE_PARAM
    slots = {k: v for k, v in vars(mf).items() if k.startswith("P_") and isinstance(v, int)}
    assert slots, "no P_* constants"
    for const, idx in slots.items():
        assert names[idx] == const[2:], const
    # the derived slots follow the file's keys, one D_* constant each
    derived = mf.MF61_DERIVED_NAMES
    assert mf.N_MF61_PARAM == len(names) + len(derived)
    d_slots = {k: v for k, v in vars(mf).items() if k.startswith("D_") and isinstance(v, int)}
    assert sorted(d_slots.values()) == list(range(len(names), mf.N_MF61_PARAM))
    for const, idx in d_slots.items():
        assert derived[idx - len(names)] == const[2:], const
    vec = mf.mf61_param_vector(C)
    assert vec.dtype == np.float64 and vec.shape == (mf.N_MF61_PARAM,)
    assert vec[mf.P_PKY1] == -15.324


def test_derived_slots_are_their_definitions() -> None:
    """The packed load-free quantities equal their definitions from the file's keys."""
    vec = mf.mf61_param_vector(C)
    assert vec[mf.D_PEAK_TARGET_X] == mf._peak_target(C["PCX1"] * C["LCX"])
    assert vec[mf.D_PEAK_TARGET_Y] == mf._peak_target(C["PCY1"] * C["LCY"])
    cx = C["PCX1"] * C["LCX"]
    assert vec[mf.D_PEAK_TARGET_X] == pytest.approx(math.tan(0.5 * math.pi / cx), rel=1e-14)
    assert vec[mf.D_INV_FZ0] == 1.0 / (C["FNOMIN"] * C["LFZO"])
    assert vec[mf.D_INV_FNOMIN] == 1.0 / C["FNOMIN"]


def test_param_vector_rejects_bad_input() -> None:
    bad = dict(C)
    del bad["QSY8"]
    with pytest.raises(ValueError, match="QSY8"):
        mf.mf61_param_vector(bad)
    bad = dict(C, PKY1=float("nan"))
    with pytest.raises(ValueError, match="PKY1"):
        mf.mf61_param_vector(bad)
    bad = dict(C, PKY1="x")
    with pytest.raises(ValueError, match="PKY1"):
        mf.mf61_param_vector(bad)


# --- signs and the sample's reference point -------------------------------------------------


def test_sample_reference_point() -> None:
    """The file's own convention: Fy = -2300 N at tan(alpha) = +0.05, Fz = 4000 N."""
    out = run(0.0, 0.05)
    assert out[OUT_FY] == pytest.approx(-2300.0, rel=0.01)
    assert np.all(np.isfinite(out))


def test_iso_signs() -> None:
    assert run(0.1, 0.0)[OUT_FX] > 0.0
    assert run(-0.1, 0.0)[OUT_FX] < 0.0
    assert run(0.0, 0.1)[OUT_FY] < 0.0
    assert run(0.0, -0.1)[OUT_FY] > 0.0
    # the aligning moment turns the wheel towards the slide: Mz > 0 for small alpha > 0
    assert run(0.0, 0.03)[OUT_MZ] > 0.0
    assert run(0.0, -0.03)[OUT_MZ] < 0.0


def test_no_load() -> None:
    for fz in (0.0, -100.0):
        out = run(0.1, 0.1, fz=fz)
        assert out[OUT_FX] == out[OUT_FY] == out[OUT_MZ] == out[OUT_MY] == 0.0
        assert out[OUT_FX_PEAK] == out[OUT_FY_PEAK] == 0.0
        assert out[OUT_C_KAPPA] == out[OUT_C_ALPHA] == 1.0
        assert out[OUT_KAPPA_SLIDE] == out[OUT_TAN_ALPHA_SLIDE] == 1.0


# --- stiffnesses ------------------------------------------------------------------------------

LOAD_CAMBER = [(4000.0, 0.0), (6500.0, 0.0), (2000.0, 0.0), (4000.0, 0.05), (5500.0, -0.08)]


@pytest.mark.parametrize(("fz", "gamma"), LOAD_CAMBER)
def test_stiffness_closed_form(fz: float, gamma: float) -> None:
    for mu in (1.0, 0.6):
        out = run(0.02, 0.03, gamma=gamma, fz=fz, mu=mu)
        assert out[OUT_C_KAPPA] == pytest.approx(kxk_ref(fz), rel=1e-9)
        assert out[OUT_C_ALPHA] == pytest.approx(abs(kya_ref(fz, gamma)), rel=1e-9)
        assert out[OUT_C_ALPHA] > 0.0


@pytest.mark.parametrize(("fz", "gamma"), LOAD_CAMBER)
def test_stiffness_is_the_slope_of_the_curve(fz: float, gamma: float) -> None:
    """Central differences at the curves' own origins (kappa = -SHx, tan_alpha = -SHy)."""
    h = 1e-6
    k0 = -shx_ref(fz)
    slope_x = (run(k0 + h, 0.0, gamma, fz)[OUT_FX] - run(k0 - h, 0.0, gamma, fz)[OUT_FX]) / (2 * h)
    assert slope_x == pytest.approx(run(k0, 0.0, gamma, fz)[OUT_C_KAPPA], rel=1e-4)
    a0 = -shy_ref(fz, gamma)
    slope_y = (run(0.0, a0 + h, gamma, fz)[OUT_FY] - run(0.0, a0 - h, gamma, fz)[OUT_FY]) / (2 * h)
    assert -slope_y == pytest.approx(run(0.0, a0, gamma, fz)[OUT_C_ALPHA], rel=1e-4)


def test_stiffness_vs_slope_at_zero_slip() -> None:
    """At zero slip the slope differs from Kxk, Kya only by O((B SH)^2) (documented)."""
    h = 1e-6
    out = run(0.0, 0.0)
    slope_x = (run(h, 0.0)[OUT_FX] - run(-h, 0.0)[OUT_FX]) / (2 * h)
    slope_y = (run(0.0, h)[OUT_FY] - run(0.0, -h)[OUT_FY]) / (2 * h)
    assert slope_x == pytest.approx(out[OUT_C_KAPPA], rel=1e-4)
    assert -slope_y == pytest.approx(out[OUT_C_ALPHA], rel=2e-3)


def test_pressure_scales_stiffness(tmp_path: Path) -> None:
    """INFLPRES != NOMPRES: Kxk gets (1 + PPX1 dpi + PPX2 dpi^2) (4.E15)."""
    coeffs = dict(C, INFLPRES=1.1 * C["NOMPRES"])
    out = run(0.0, 0.0, p=mf.mf61_param_vector(coeffs))
    dpi = 0.1
    factor = 1.0 + C["PPX1"] * dpi + C["PPX2"] * dpi * dpi
    assert out[OUT_C_KAPPA] == pytest.approx(kxk_ref(4000.0) * factor, rel=1e-9)
    ky = kya_ref(4000.0, 0.0)  # (4.E25) with PPY1, PPY2
    ky_p = (
        C["PKY1"] * C["FNOMIN"] * (1.0 + C["PPY1"] * dpi)
        * math.sin(C["PKY4"] * math.atan(1.0 / (C["PKY2"] * (1.0 + C["PPY2"] * dpi))))
    )  # fmt: skip
    assert out[OUT_C_ALPHA] == pytest.approx(abs(ky_p), rel=1e-9)
    assert abs(ky_p) != pytest.approx(abs(ky), rel=1e-3)


# --- peaks and sliding limits -------------------------------------------------------------------


@pytest.mark.parametrize("fz", [2500.0, 4000.0, 6500.0])
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_peak_force_and_location_longitudinal(fz: float, side: float) -> None:
    step = 2e-5
    kappas = side * np.arange(0.0, 0.4, step)
    fx = np.array([run(k, 0.0, fz=fz)[OUT_FX] for k in kappas])
    i = int(np.argmax(np.abs(fx)))
    out = run(side * 0.01, 0.0, fz=fz)
    assert np.max(np.abs(fx)) == pytest.approx(mux_ref(fz) * fz, rel=0.02)
    assert out[OUT_FX_PEAK] == pytest.approx(mux_ref(fz) * fz, rel=1e-12)
    assert abs(kappas[i]) == pytest.approx(out[OUT_KAPPA_SLIDE], abs=1.5 * step)


@pytest.mark.parametrize("fz", [2500.0, 4000.0, 6500.0])
@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize("gamma", [0.0, 0.04])
def test_peak_force_and_location_lateral(fz: float, side: float, gamma: float) -> None:
    step = 5e-5
    alphas = side * np.arange(0.0, 0.6, step)
    fy = np.array([run(0.0, a, gamma=gamma, fz=fz)[OUT_FY] for a in alphas])
    i = int(np.argmax(np.abs(fy)))
    out = run(0.0, side * 0.01, gamma=gamma, fz=fz)
    mu_y = muy_ref(fz) * (1.0 - C["PDY3"] * math.sin(gamma) ** 2)
    assert np.max(np.abs(fy)) == pytest.approx(mu_y * fz, rel=0.03)
    assert out[OUT_FY_PEAK] == pytest.approx(mu_y * fz, rel=1e-12)
    assert abs(alphas[i]) == pytest.approx(out[OUT_TAN_ALPHA_SLIDE], abs=1.5 * step)


@pytest.mark.parametrize("fz", [2500.0, 4000.0, 6500.0])
def test_sliding_limit_solves_the_peak_equation(fz: float) -> None:
    """OUT_KAPPA_SLIDE = u*/Bx - SHx with u* the bisection root, to 1e-8."""
    d = dfz_of(fz)
    cx = C["PCX1"] * C["LCX"]
    dx = mux_ref(fz) * fz
    bx = kxk_ref(fz) / (cx * dx)
    ex = (C["PEX1"] + C["PEX2"] * d + C["PEX3"] * d * d) * (1.0 - C["PEX4"]) * C["LEX"]
    expect = peak_u_ref(cx, ex) / bx - shx_ref(fz)
    assert run(0.05, 0.0, fz=fz)[OUT_KAPPA_SLIDE] == pytest.approx(expect, rel=1e-8)


def _solve_peak(c: float, e: float, steps: int) -> float:
    target = mf._peak_target(c)
    u = mf._peak_start(target, e)
    for _ in range(steps):
        u = mf._peak_step(u, math.atan(u), e, target)
    return u


def test_peak_solver_over_shapes() -> None:
    """Two Halley steps from the bracketing start: 1e-5 for C in [1.05, 2.5], E in [-3, 0.8]."""
    for c in (1.05, 1.1, 1.2, 1.3, 1.45, 1.55, 1.6, 1.8, 2.0, 2.5):
        assert mf._peak_target(c) == pytest.approx(math.tan(0.5 * math.pi / c), rel=1e-14)
        for e in (-3.0, -2.0, -1.0, -0.5, 0.0, 0.3, 0.6, 0.8):
            assert _solve_peak(c, e, 2) == pytest.approx(peak_u_ref(c, e), rel=1e-5), (c, e)


def test_no_peak_fallback() -> None:
    """C <= 1: the slip where the curve reaches 99 % of its asymptote D sin(C pi / 2)."""
    for c, e in ((1.0, 0.0), (0.8, -0.5), (0.6, 0.4)):
        u = _solve_peak(c, e, 6)
        y = math.sin(c * math.atan((1.0 - e) * u + e * math.atan(u)))
        assert y == pytest.approx(0.99 * math.sin(0.5 * math.pi * c), rel=1e-9)


def test_mu_scale_halves_the_peaks() -> None:
    kappas = np.arange(0.0, 0.4, 1e-4)
    alphas = np.arange(0.0, 0.6, 1e-4)
    for mu in (1.0, 0.5):
        fx_max = max(abs(run(k, 0.0, mu=mu)[OUT_FX]) for k in kappas)
        fy_max = max(abs(run(0.0, a, mu=mu)[OUT_FY]) for a in alphas)
        if mu == 1.0:
            fx_full, fy_full = fx_max, fy_max
    assert fx_max == pytest.approx(0.5 * fx_full, rel=1e-3)
    assert fy_max == pytest.approx(0.5 * fy_full, rel=1e-3)
    full, half = run(0.05, 0.05), run(0.05, 0.05, mu=0.5)
    assert half[OUT_FX_PEAK] == pytest.approx(0.5 * full[OUT_FX_PEAK], rel=1e-12)
    assert half[OUT_FY_PEAK] == pytest.approx(0.5 * full[OUT_FY_PEAK], rel=1e-12)
    assert half[OUT_C_KAPPA] == pytest.approx(full[OUT_C_KAPPA], rel=1e-12)
    assert half[OUT_C_ALPHA] == pytest.approx(full[OUT_C_ALPHA], rel=1e-12)


# --- combined slip ------------------------------------------------------------------------------


KAPPAS = [0.02, 0.05, 0.1, 0.3, -0.03, -0.1, -0.5]
ALPHAS = [0.02, 0.05, 0.12, -0.03, -0.1, -0.4]
P_NO_SVYK = mf.mf61_param_vector(dict(C, RVY1=0.0, RVY2=0.0, RVY3=0.0))  # D_Vyk = 0 (4.E67)


@pytest.mark.parametrize("kappa", KAPPAS)
@pytest.mark.parametrize("tan_alpha", ALPHAS)
def test_combined_slip_reduces_each_force(kappa: float, tan_alpha: float) -> None:
    """|Fx(k, a)| < |Fx(k, 0)| always; |Fy(k, a)| < |Fy(0, a)| through G_yk (4.E59).

    The kappa-induced side force S_Vyk (4.E66) is additive, so the lateral check is made
    without it; with it, see :func:`test_kappa_induced_side_force`.
    """
    both = run(kappa, tan_alpha)
    assert abs(both[OUT_FX]) < abs(run(kappa, 0.0)[OUT_FX])
    both = run(kappa, tan_alpha, p=P_NO_SVYK)
    assert abs(both[OUT_FY]) < abs(run(0.0, tan_alpha, p=P_NO_SVYK)[OUT_FY])


@pytest.mark.parametrize("kappa", KAPPAS)
@pytest.mark.parametrize("tan_alpha", [0.05, 0.12, -0.1, -0.4])
def test_combined_slip_reduces_fy_of_the_sample(kappa: float, tan_alpha: float) -> None:
    assert abs(run(kappa, tan_alpha)[OUT_FY]) < abs(run(0.0, tan_alpha)[OUT_FY])


def test_kappa_induced_side_force() -> None:
    """The sample's RVY terms: braking at a small slip angle adds side force.

    At kappa = -0.03, tan_alpha = 0.02, G_yk removes 2 % of Fy0 but S_Vyk adds about
    -78 N: |Fy| grows by 6 %. This is the file's data, not a defect.
    """
    alone, braking = run(0.0, 0.02)[OUT_FY], run(-0.03, 0.02)[OUT_FY]
    assert braking < alone < 0.0
    assert braking / alone == pytest.approx(1.06, abs=0.01)


# --- load range, rolling resistance ---------------------------------------------------------------


def test_load_beyond_the_fitted_range_is_linear() -> None:
    fzmax, fzmin = C["FZMAX"], C["FZMIN"]
    at_max, at_2max = run(0.05, 0.04, fz=fzmax), run(0.05, 0.04, fz=2.0 * fzmax)
    np.testing.assert_allclose(at_2max[:6], 2.0 * at_max[:6], rtol=1e-12)
    np.testing.assert_allclose(at_2max[8:], 2.0 * at_max[8:], rtol=1e-12)
    assert at_2max[OUT_KAPPA_SLIDE] == at_max[OUT_KAPPA_SLIDE]
    at_min, at_half = run(0.05, 0.04, fz=fzmin), run(0.05, 0.04, fz=0.5 * fzmin)
    np.testing.assert_allclose(at_half[:6], 0.5 * at_min[:6], rtol=1e-12)
    # continuous across the limits
    below = run(0.05, 0.04, fz=fzmax * (1.0 - 1e-9))
    np.testing.assert_allclose(below, at_max, rtol=1e-6)


def test_rolling_resistance_closed_form() -> None:
    """(4.E70) with Fz0 = FNOMIN in front, nominal pressure, QSY2 = 0 in this file."""
    for vx, fz, gamma in ((0.0, 4000.0, 0.0), (16.7, 4000.0, 0.0), (-30.0, 6000.0, 0.05)):
        vr = abs(vx) / C["LONGVL"]
        expect = (
            C["UNLOADED_RADIUS"] * C["FNOMIN"] * C["LMY"]
            * (C["QSY1"] + C["QSY3"] * vr + C["QSY4"] * vr**4
               + (C["QSY5"] + C["QSY6"] * fz / C["FNOMIN"]) * gamma**2)
            * (fz / C["FNOMIN"]) ** C["QSY7"]
        )  # fmt: skip
        out = run(0.0, 0.0, gamma=gamma, fz=fz, vx=vx)
        assert out[OUT_MY] == pytest.approx(expect, rel=1e-12)
        assert out[OUT_MY] > 0.0
    # inflation pressure: (p / p0)^QSY8; Fz0 in (4.E70) is FNOMIN, not LFZO FNOMIN
    v = VARIANT
    fz = 5000.0
    expect = (
        v["UNLOADED_RADIUS"] * v["FNOMIN"] * v["LMY"] * v["QSY1"]
        * (fz / v["FNOMIN"]) ** v["QSY7"] * (v["INFLPRES"] / v["NOMPRES"]) ** v["QSY8"]
    )  # fmt: skip
    out = run(0.0, 0.0, fz=fz, vx=0.0, p=mf.mf61_param_vector(v))
    assert out[OUT_MY] == pytest.approx(expect, rel=1e-12)


# --- robustness and equivalence ----------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=400, deadline=None)
@given(
    kappa=st.one_of(finite, st.floats(-60.0, 60.0)),
    tan_alpha=st.one_of(finite, st.floats(-2e3, 2e3)),
    gamma=st.one_of(finite, st.floats(-0.5, 0.5)),
    fz=st.one_of(finite, st.floats(-1e3, 3e4)),
    mu=st.one_of(finite, st.floats(0.0, 2.0)),
    vx=finite,
)
def test_outputs_finite_for_wild_inputs(
    kappa: float, tan_alpha: float, gamma: float, fz: float, mu: float, vx: float
) -> None:
    out = run(kappa, tan_alpha, gamma, fz, mu, vx)
    assert np.all(np.isfinite(out)), out
    assert out[OUT_MY] >= 0.0 and out[OUT_FX_PEAK] >= 0.0 and out[OUT_FY_PEAK] >= 0.0
    assert out[OUT_KAPPA_SLIDE] > 0.0 and out[OUT_TAN_ALPHA_SLIDE] > 0.0
    if fz > 0.0:
        assert out[OUT_C_KAPPA] >= 0.0 and out[OUT_C_ALPHA] >= 0.0


@pytest.mark.parametrize(("kappa", "tan_alpha"), [(50.0, 1e3), (-50.0, -1e3), (-1.0, 1e3)])
def test_huge_slips(kappa: float, tan_alpha: float) -> None:
    out = run(kappa, tan_alpha, gamma=0.05)
    assert np.all(np.isfinite(out))
    assert abs(out[OUT_FX]) <= out[OUT_FX_PEAK] * 1.05
    assert abs(out[OUT_FY]) <= out[OUT_FY_PEAK] * 1.05


@pytest.mark.parametrize("coeffs", [C, VARIANT], ids=["sample", "variant"])
def test_jit_equals_py_func(coeffs: dict[str, float]) -> None:
    """The compiled kernel equals its Python source (helpers compiled) to 1e-12.

    Relative to each output's magnitude, floored at 1e-3 of its natural scale (forces:
    Fz, moments: Fz R0) for outputs that cross zero.
    """
    p = mf.mf61_param_vector(coeffs)
    rng = np.random.default_rng(20261122)
    py = mf.mf61_forces.py_func
    scale = np.ones(N_TIRE_OUT)
    for _ in range(300):
        kappa = rng.choice([rng.uniform(-0.3, 0.3), rng.uniform(-5.0, 5.0)])
        tan_alpha = rng.choice([rng.uniform(-0.3, 0.3), rng.uniform(-20.0, 20.0)])
        gamma = rng.choice([0.0, rng.uniform(-0.1, 0.1)])
        fz = rng.uniform(10.0, 14000.0)
        mu = rng.uniform(0.1, 1.5)
        vx = rng.uniform(-40.0, 40.0)
        a = run(kappa, tan_alpha, gamma, fz, mu, vx, p=p)
        b = np.full(N_TIRE_OUT, np.nan)
        py(p, kappa, tan_alpha, gamma, fz, mu, vx, b)
        scale[[OUT_FX, OUT_FY, OUT_FX_PEAK, OUT_FY_PEAK]] = fz
        scale[[OUT_MZ, OUT_MY]] = fz * coeffs["UNLOADED_RADIUS"]
        floor = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1e-3 * scale)
        assert np.all(np.abs(a - b) <= 1e-12 * floor), (kappa, tan_alpha, gamma, fz, a - b)


def test_variant_stiffness_closed_form() -> None:
    """(4.E25) with PKY5, pressure and LFZO: Kya = PKY1 F'z0 (1 + PPY1 dpi) (1 - PKY3 |g*|)
    sin(PKY4 atan(Fz / F'z0 / ((PKY2 + PKY5 g*^2)(1 + PPY2 dpi)))) LKY."""
    v = VARIANT
    p = mf.mf61_param_vector(v)
    dpi = v["INFLPRES"] / v["NOMPRES"] - 1.0
    fz0 = v["FNOMIN"] * v["LFZO"]
    for fz, gamma in ((4000.0, 0.0), (6000.0, 0.06), (11000.0, -0.03)):
        gs = math.sin(gamma)
        kya = (
            v["PKY1"] * fz0 * (1.0 + v["PPY1"] * dpi) * (1.0 - v["PKY3"] * abs(gs))
            * math.sin(v["PKY4"] * math.atan(
                fz / fz0 / ((v["PKY2"] + v["PKY5"] * gs * gs) * (1.0 + v["PPY2"] * dpi))))
        )  # fmt: skip
        d = (fz - fz0) / fz0
        kxk = (
            fz * (v["PKX1"] + v["PKX2"] * d) * math.exp(v["PKX3"] * d)
            * (1.0 + v["PPX1"] * dpi + v["PPX2"] * dpi * dpi)
        )  # fmt: skip
        out = run(0.01, 0.02, gamma=gamma, fz=fz, p=p)
        assert out[OUT_C_ALPHA] == pytest.approx(abs(kya), rel=1e-9)
        assert out[OUT_C_KAPPA] == pytest.approx(kxk, rel=1e-9)
        assert np.all(np.isfinite(out))


# --- the inlined elementary functions -----------------------------------------------------------


def test_atan_accuracy() -> None:
    rng = np.random.default_rng(1)
    xs = np.concatenate(
        [
            np.linspace(-3.0, 3.0, 20001),
            rng.uniform(-1.0, 1.0, 5000),
            10.0 ** rng.uniform(-12.0, 12.0, 5000) * rng.choice([-1.0, 1.0], 5000),
            [0.0, -0.0, 0.4375, 0.6875, 1.1875, 2.4375, 1e300, -1e300],
        ]
    )
    for x in xs:
        ref = math.atan(x)
        assert abs(mf._atan(x) - ref) <= 3e-16 * abs(ref), x


def test_sin_accuracy() -> None:
    xs = np.concatenate([np.linspace(-20.0, 20.0, 40001), [0.0, math.pi, -math.pi, 1e6]])
    for x in xs:
        assert abs(mf._sin(x) - math.sin(x)) <= 1e-15 * max(1.0, abs(x) / math.pi), x
    for y in np.linspace(-0.5 * math.pi, 0.5 * math.pi, 10001):
        assert abs(mf._sin_core(y) - math.sin(y)) <= 2.3e-16, y


def test_mf_lanes_against_math() -> None:
    """Each lane: theta = atan(y - E (y - atan y)), s = sin(C theta + K)."""
    rng = np.random.default_rng(7)
    for _ in range(500):
        y = tuple(float(v) for v in rng.choice([1e-3, 1.0, 30.0, 1e4]) * rng.normal(size=8))
        e = tuple(float(v) for v in rng.uniform(-3.0, 1.0, 8))
        c = tuple(float(v) for v in rng.uniform(0.0, 2.6, 8))
        k = tuple(float(v) for v in rng.choice([0.0, 0.5 * math.pi, 1.0], 8))
        theta, s = mf._mf_lanes(y, e, c, k)
        for i in range(mf.N_LANES):
            th_ref = math.atan((1.0 - e[i]) * y[i] + e[i] * math.atan(y[i]))
            assert theta[i] == pytest.approx(th_ref, rel=1e-14, abs=1e-300)
            assert s[i] == pytest.approx(math.sin(c[i] * th_ref + k[i]), abs=1e-15)


def test_atan_flat_equals_atan() -> None:
    """The branch-free variant (used where numba's reference-count pruning needs few
    branch paths) is the same function to the last bit, and as accurate."""
    rng = np.random.default_rng(2)
    xs = np.concatenate(
        [
            np.linspace(-3.0, 3.0, 20001),
            10.0 ** rng.uniform(-12.0, 12.0, 5000) * rng.choice([-1.0, 1.0], 5000),
            [0.0, -0.0, 0.4375, 0.6875, 1.1875, 2.4375, 1e300, -1e300],
        ]
    )
    for x in xs:
        assert mf._atan_flat(x) == mf._atan(x), x
        assert abs(mf._atan_flat(x) - math.atan(x)) <= 3e-16 * abs(math.atan(x)), x
    for x in (1e308, -1e308, math.inf, -math.inf):
        assert mf._atan_flat(x) == math.copysign(0.5 * math.pi, x)


def test_atan_sin_lanes_against_math() -> None:
    """Each lane: theta = atan(y), s = sin(C theta) (K_ya and the peak searches)."""
    rng = np.random.default_rng(8)
    for _ in range(500):
        y = tuple(float(v) for v in rng.choice([1e-3, 1.0, 30.0, 1e4]) * rng.normal(size=8))
        c = tuple(float(v) for v in rng.uniform(0.0, 2.6, 8))
        theta, s = mf._atan_sin_lanes(y, c)
        for i in range(mf.N_LANES):
            assert theta[i] == pytest.approx(math.atan(y[i]), rel=1e-15, abs=1e-300)
            assert s[i] == pytest.approx(math.sin(c[i] * math.atan(y[i])), abs=2e-15)
