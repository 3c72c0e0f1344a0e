"""The road plane: its axes in world frame and gravity resolved into them.

The road is the plane ``Z = (grade/100) X + (cross/100) Y`` (a grade of p % rises p m per
100 m, docs/model.md section 4b). ``e1`` is the world X axis projected onto the plane,
``n`` the plane's upward normal, ``e2 = n x e1``:

    e1 = (1, 0, s_x) / |.|,   n = (-s_x, -s_y, 1) / |.|,   e2 = (-s_x s_y, 1 + s_x^2, s_y) / |.|

with ``s_x = grade/100``, ``s_y = cross/100``. This module is the one place that maths is
written: the integrator's gravity components (``set_road``) and the world pose
(``road_axes``, ``core.pose``) both come from ``road_frame``.

The road belongs to the world, not to a car: its parameters are the terrain's
(``core.terrain.Terrain.road``, slots ``core.params.ROAD_*``), shared by every car on it.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.params import (
    ROAD_CROSS_SLOPE_PCT,
    ROAD_FRICTION_SCALE,
    ROAD_GRADE_PCT,
    ROAD_GRAVITY_E1_MPS2,
    ROAD_GRAVITY_E2_MPS2,
    ROAD_GRAVITY_N_MPS2,
)

E1, E2, NORMAL = 0, 1, 2  # rows of the axes array


@nb.njit(cache=True, inline="always")  # once a step on a terrain (core.terrain)
def road_frame(grade_pct: float, cross_slope_pct: float, axes: np.ndarray) -> None:
    """Write the world-frame unit vectors ``e1``, ``e2``, ``n`` of the plane as rows of
    ``axes`` (float64[3, 3])."""
    s_x = grade_pct / 100.0
    s_y = cross_slope_pct / 100.0
    e1_norm = np.sqrt(1.0 + s_x * s_x)
    e2_norm = np.sqrt((s_x * s_y) ** 2 + (1.0 + s_x * s_x) ** 2 + s_y * s_y)
    n_norm = np.sqrt(1.0 + s_x * s_x + s_y * s_y)
    axes[E1, 0] = 1.0 / e1_norm
    axes[E1, 1] = 0.0
    axes[E1, 2] = s_x / e1_norm
    axes[E2, 0] = -s_x * s_y / e2_norm
    axes[E2, 1] = (1.0 + s_x * s_x) / e2_norm
    axes[E2, 2] = s_y / e2_norm
    axes[NORMAL, 0] = -s_x / n_norm
    axes[NORMAL, 1] = -s_y / n_norm
    axes[NORMAL, 2] = 1.0 / n_norm


def road_axes(grade_pct: float, cross_slope_pct: float) -> np.ndarray:
    """World-frame unit vectors ``(e1, e2, n)`` of the road plane, as rows of a 3x3 array."""
    axes = np.empty((3, 3))
    road_frame(float(grade_pct), float(cross_slope_pct), axes)
    return axes


@nb.njit(cache=True)
def set_road(road: np.ndarray, grade_pct: float, cross_slope_pct: float,
             friction_scale: float, gravity_mps2: float) -> None:
    """Write a terrain's road (``road``: float64[N_ROAD], ``core.params.ROAD_*``) and
    resolve gravity ``gravity_mps2`` into the plane's axes.

    Gravity ``(0, 0, -g)`` resolves to ``g_e1 e1 + g_e2 e2 - g_n n``: the components are
    ``-g`` times the world Z components of ``e1`` and ``e2``, and ``g`` times that of ``n``.
    """
    axes = np.empty((3, 3))
    road_frame(grade_pct, cross_slope_pct, axes)
    g = gravity_mps2
    road[ROAD_GRADE_PCT] = grade_pct
    road[ROAD_CROSS_SLOPE_PCT] = cross_slope_pct
    road[ROAD_FRICTION_SCALE] = friction_scale
    road[ROAD_GRAVITY_E1_MPS2] = -g * axes[E1, 2]
    road[ROAD_GRAVITY_E2_MPS2] = -g * axes[E2, 2]
    road[ROAD_GRAVITY_N_MPS2] = g * axes[NORMAL, 2]
