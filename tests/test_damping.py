"""Appendix A damping: coefficients at the paper's numbers, trigger and release rules."""

from __future__ import annotations

import math

import numpy as np

from simserver.core.damping import (
    PAPER_DAMPING_RATIO,
    PAPER_TRIGGER_LATERAL_SPEED_MPS,
    damping_coefficients,
    low_speed_fade,
    paper_release,
    paper_trigger,
)
from simserver.core.tire import BUILTIN_KERNELS, tire_forces
from simserver.core.tire_layout import (
    N_TIRE_OUT,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)


def test_coefficients_at_the_reference_car(paper_tire):
    """docs/model.md section 4: c_x = 15.7 kN s/m, c_y = 7.49 kN s/m per wheel at Fz = 5005 N.

    Independent check: c = 2 zeta m w with m = Fz/g, w^2 = (C/relaxation length)/m.
    """
    fz, g = 5005.0, 9.81
    out = np.zeros(N_TIRE_OUT)
    tire_forces(BUILTIN_KERNELS, paper_tire, 0.0, 0.0, 0.0, fz, 1.0, 0.0, out)
    c_x, c_y = damping_coefficients(fz, out[OUT_C_KAPPA], out[OUT_C_ALPHA],
                                    paper_tire[TP_RELAX_LONG_M], paper_tire[TP_RELAX_LAT_M],
                                    PAPER_DAMPING_RATIO, g)
    assert abs(c_x / 15.7e3 - 1.0) < 0.01
    assert abs(c_y / 7.49e3 - 1.0) < 0.01
    m = fz / g
    assert math.isclose(c_x, 2 * 0.7 * m * math.sqrt(22500 / 0.091 / m), rel_tol=1e-12)
    # sum over four wheels = 0.7 of critical for the whole car on its four tire springs
    mass = 4 * m
    critical = 2 * math.sqrt(4 * 22500 / 0.091 * mass)
    assert math.isclose(4 * c_x / critical, 0.7, rel_tol=1e-12)


def test_trigger_needs_a_sign_change_of_u_and_small_v():
    eps = PAPER_TRIGGER_LATERAL_SPEED_MPS
    assert paper_trigger(0.01, -0.01, 0.0, eps)
    assert paper_trigger(-0.01, 0.01, 0.1, eps)
    assert paper_trigger(0.01, 0.0, 0.0, eps)
    assert not paper_trigger(0.01, 0.005, 0.0, eps)  # slowing, no crossing
    assert not paper_trigger(-0.02, -0.01, 0.0, eps)
    assert not paper_trigger(0.01, -0.01, 0.2, eps)  # sliding sideways: not a stop
    assert not paper_trigger(0.0, 0.0, 0.0, eps)  # at rest, nothing crossed


def test_release_rule():
    assert not paper_release(0.5, 0.0, 0.0)  # braking: stays on
    assert not paper_release(0.0, 1.0, 0.0)  # parking brake: stays on
    assert paper_release(0.0, 0.0, 0.0)  # driver let go of the brake
    assert paper_release(0.5, 0.0, 0.3)  # throttle: driving away


def test_fade_is_smooth_and_bounded():
    v = np.linspace(0, 2.0, 2001)
    f = np.array([low_speed_fade(s, 1.0) for s in v])
    assert f[0] == 1.0 and np.all(f[v >= 1.0] == 0.0)
    assert np.all(np.diff(f) <= 0.0)
    assert np.max(np.abs(np.diff(f))) < 2e-3  # continuous: no step anywhere
