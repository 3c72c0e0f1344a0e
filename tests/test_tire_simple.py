"""The brush-type combined-slip tire of the paper's car."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from simserver.core.tire import BUILTIN_KERNELS, tire_forces
from simserver.core.tire_layout import (
    N_TIRE_OUT,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FX,
    OUT_FX_PEAK,
    OUT_FY,
    OUT_KAPPA_SLIDE,
    OUT_TAN_ALPHA_SLIDE,
    TP_MODEL_BASE,
)
from simserver.core.tire_simple import simple_forces

FZ_NOM = 5005.0


def forces(tp, kappa, tan_alpha, fz=FZ_NOM, mu=1.0):
    out = np.zeros(N_TIRE_OUT)
    tire_forces(BUILTIN_KERNELS, tp, kappa, tan_alpha, 0.0, fz, mu, 10.0, out)
    return out


def test_stiffnesses_are_the_papers(paper_tire):
    out = forces(paper_tire, 0.0, 0.0)
    assert out[OUT_C_ALPHA] == 51000.0
    assert out[OUT_C_KAPPA] == 22500.0
    h = 1e-7
    dfx = (forces(paper_tire, h, 0.0)[OUT_FX] - forces(paper_tire, -h, 0.0)[OUT_FX]) / (2 * h)
    dfy = (forces(paper_tire, 0.0, h)[OUT_FY] - forces(paper_tire, 0.0, -h)[OUT_FY]) / (2 * h)
    assert math.isclose(dfx, 22500.0, rel_tol=1e-5)
    assert math.isclose(-dfy, 51000.0, rel_tol=1e-5)
    # linear in load
    assert math.isclose(forces(paper_tire, 0, 0, fz=2 * FZ_NOM)[OUT_C_ALPHA], 102000.0)


def test_signs_follow_iso(paper_tire):
    assert forces(paper_tire, 0.05, 0.0)[OUT_FX] > 0
    assert forces(paper_tire, -0.05, 0.0)[OUT_FX] < 0
    assert forces(paper_tire, 0.0, 0.05)[OUT_FY] < 0  # Fy opposes a slide to +y


def test_saturates_at_mu_fz_at_the_reported_slide_slip(paper_tire):
    mu = 0.9  # configs/tires/paper_sti.yaml
    out = forces(paper_tire, 0.0, 0.0)
    k_slide = out[OUT_KAPPA_SLIDE]
    kappas = np.linspace(0, 2 * k_slide, 2001)
    fx = np.array([forces(paper_tire, k, 0.0)[OUT_FX] for k in kappas])
    assert math.isclose(fx.max(), mu * FZ_NOM, rel_tol=1e-9)
    first_peak = kappas[np.argmax(fx >= mu * FZ_NOM * (1 - 1e-12))]
    assert abs(first_peak - k_slide) <= 2 * (kappas[1] - kappas[0])
    assert math.isclose(out[OUT_FX_PEAK], mu * FZ_NOM)
    t_slide = out[OUT_TAN_ALPHA_SLIDE]
    assert math.isclose(-forces(paper_tire, 0.0, t_slide)[OUT_FY], mu * FZ_NOM, rel_tol=1e-12)
    # road friction scale halves the peak
    assert math.isclose(forces(paper_tire, 5.0, 0.0, mu=0.5)[OUT_FX], 0.5 * mu * FZ_NOM)


def test_combined_slip_shares_the_friction_circle(paper_tire):
    for kappa, tan_a in ((0.05, 0.05), (0.3, 0.1), (-0.2, -0.3), (1.0, 1.0)):
        both = forces(paper_tire, kappa, tan_a)
        assert abs(both[OUT_FX]) < abs(forces(paper_tire, kappa, 0.0)[OUT_FX])
        assert abs(both[OUT_FY]) < abs(forces(paper_tire, 0.0, tan_a)[OUT_FY])
        assert math.hypot(both[OUT_FX], both[OUT_FY]) <= 0.9 * FZ_NOM * (1 + 1e-12)


@settings(max_examples=200, deadline=None)
@given(kappa=st.floats(-1e3, 1e3), tan_a=st.floats(-1e3, 1e3), fz=st.floats(-1e4, 3e4),
       mu=st.floats(0.0, 2.0))
def test_finite_and_equal_to_python_reference(paper_tire, kappa, tan_a, fz, mu):
    out = np.full(N_TIRE_OUT, np.inf)
    tire_forces(BUILTIN_KERNELS, paper_tire, kappa, tan_a, 0.0, fz, mu, 3.0, out)
    assert np.all(np.isfinite(out))
    if fz > 0.0:  # the pure-Python model (uncompiled) is the reference
        ref = np.full(N_TIRE_OUT, np.inf)
        simple_forces.py_func(paper_tire[TP_MODEL_BASE:], kappa, tan_a, 0.0, fz, mu, 3.0, ref)
        np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-9)
