"""The ground under each wheel: terrain kinds and the contact query (docs/model.md section 11).

A terrain is a ``Terrain`` tuple of arrays, the same types for every kind, so the compiled
step takes any of them without recompiling:

- ``TERRAIN_PLANE``: the inclined plane of ``core.road``, with its own parameters in the
  terrain's ``road`` (grade, cross-slope, friction scale, and gravity resolved into the
  plane: ``core.road.set_road``). The grid arrays are placeholders; the step does exactly
  what it did before terrains existed.
- ``TERRAIN_OPENDRIVE``: an OpenDRIVE road, rasterised when loaded into the grid of a
  height map (``simserver.adapters.opendrive.rasterise``); the step treats it as one.
- ``TERRAIN_HEIGHTMAP``: a regular grid of heights ``heights[j, i]`` at
  ``(x0 + i dx, y0 + j dy)``, interpolated by a tensor-product Catmull-Rom spline (C1: the
  height and its gradient, hence the surface normal, are continuous), with a friction
  scale per grid point (bilinear). Off the grid the query is clamped to the grid's edge:
  the edge heights extend flat, never NaN.

Every kind carries ``road`` (``core.params.ROAD_*``): the road's friction scale multiplies
a height map's too. A terrain is the world's: one is shared by every car of a world
(``core.world``); the ``road`` array is the only part written while a world runs.

The chassis keeps its planar formulation on a *reference plane* fitted under the four
contact points once per step (``fit_reference_plane``, ``rebase_reference_plane``): on
the plane kind the reference plane is the road itself; on a height map the states are
re-expressed on the new plane each step so that the body's world position, velocity and
attitude are unchanged, and what the plane misses under each wheel (``surface_at``)
enters the wheel's suspension and its own contact frame (``core.chassis``).
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

import numba as nb
import numpy as np

from simserver.core.layout import (
    HEAVE_M,
    HEAVE_RATE_MPS,
    PITCH_RAD,
    REF_CROSS_SLOPE_PCT,
    REF_GRADE_PCT,
    REF_HEIGHT_M,
    ROLL_RAD,
    STEP_JIT_OPTIONS,
    U_MPS,
    V_MPS,
    X_M,
    Y_M,
    YAW_RAD,
)
from simserver.core.params import MODEL_OPTIONS, N_ROAD, ROAD
from simserver.core.road import road_frame, set_road
from simserver.core.variants import Variant, VariantRegistry

TERRAIN_PLANE = 0
TERRAIN_HEIGHTMAP = 1
TERRAIN_OPENDRIVE = 2  # an OpenDRIVE road rasterised into a height grid at load time
TERRAIN_KINDS = VariantRegistry("terrain kind", (
    Variant(TERRAIN_PLANE, "plane",
            "one inclined plane: the road's grade, cross-slope and friction"),
    Variant(TERRAIN_HEIGHTMAP, "heightmap",
            "a regular grid of heights (.npy, .npz, 16-bit PNG), C1 Catmull-Rom, "
            "optional friction map"),
    Variant(TERRAIN_OPENDRIVE, "opendrive",
            "an ASAM OpenDRIVE road (.xodr), rasterised into a height grid when loaded "
            "(simserver.adapters.opendrive); stepped as a height map"),
))

# slots of Terrain.grid
GRID_X0_M, GRID_Y0_M, GRID_DX_M, GRID_DY_M = 0, 1, 2, 3
GRID_KEY = 4  # a 48-bit hash of the grid's contents: the key of the per-wheel cell memo
# N_ROAD slots from GRID_ROAD: the terrain's road (core.params.ROAD_*, ``Terrain.road``).
# They sit in ``grid`` rather than in an array of their own so that the Terrain tuple keeps
# four fields: the step passes the model (terrain included) to each stage it does not
# inline, by value, array by array, and a fifth array cost the brush step 6 % (issue 29).
GRID_ROAD = 5
N_GRID = GRID_ROAD + N_ROAD

# slots of the per-wheel cell memo (``Workspace.cells[i, CELL_*]``, ``surface_under_wheel``):
# the cell of the grid the wheel was last in and the power-basis coefficients of the
# surface there, keyed by the terrain's GRID_KEY and the cell's indices (a pure function
# of the three, so a memo shared between states or carried across a terrain change is
# never wrong). A wheel moves a centimetre a step: it stays in its cell for tens to
# hundreds of steps on a 0.25 to 1 m grid.
CELL_KEY = 0  # the terrain's GRID_KEY (NaN: empty)
CELL_I = 1  # the cell's column and row (float)
CELL_J = 2
CELL_H = 3  # 16 slots: c[m, p] of height = sum c[m, p] tx^m ty^p at CELL_H + 4 p + m
CELL_MU = 19  # 4 slots: mu = m0 + m1 tx + m2 ty + m3 tx ty (the bilinear friction)
N_CELL = 23


def empty_cell_memo(n_wheels: int) -> np.ndarray:
    """An empty cell memo per wheel (``CELL_*``): float64[n_wheels, N_CELL]."""
    memo = np.zeros((n_wheels, N_CELL))
    memo[:, CELL_KEY] = np.nan
    return memo


class Terrain(NamedTuple):
    """The ground, as the compiled step takes it (module docstring)."""

    kind: int  # TERRAIN_* id
    heights: np.ndarray  # float64[ny, nx], m (a 1x1 placeholder on the plane)
    friction: np.ndarray  # float64[ny, nx], friction scale per grid point
    grid: np.ndarray  # float64[N_GRID]: origin and spacing, the road (GRID_*)

    @property
    def road(self) -> np.ndarray:
        """The road (``core.params.ROAD_*``): a view of ``grid`` from ``GRID_ROAD``, which
        ``core.road.set_road`` writes (compiled code: ``terrain_road``)."""
        return self.grid[GRID_ROAD:]


@nb.njit(cache=True, inline="always")
def terrain_road(terrain: Terrain) -> np.ndarray:
    """``Terrain.road`` in compiled code (a numba tuple has no properties)."""
    return terrain.grid[GRID_ROAD:]


def default_road() -> np.ndarray:
    """A road at the ``road:`` section's defaults (flat, friction scale 1) with gravity
    at the ``model:`` section's default: float64[N_ROAD]."""
    road = np.zeros(N_ROAD)
    d = ROAD.defaults
    set_road(road, d["grade_pct"], d["cross_slope_pct"], d["friction_scale"],
             MODEL_OPTIONS.defaults["gravity_mps2"])
    return road


def plane_terrain() -> Terrain:
    """The plane kind: the road of ``core.road`` (the grid arrays are placeholders)."""
    grid = np.zeros(N_GRID)
    grid[GRID_DX_M] = grid[GRID_DY_M] = 1.0
    grid[GRID_KEY] = -1.0  # never a hash (those are >= 0): the plane has no cells
    grid[GRID_ROAD:] = default_road()
    return Terrain(TERRAIN_PLANE, np.zeros((1, 1)), np.ones((1, 1)), grid)


# Bounds of a height map (docs/model.md section 11), checked when it is made: with them
# every product of the step stays far inside float64 (positions <= 1e7 m, heights
# <= 1e5 m, slopes <= 1e3: the plane fit's sums of squares stay under 1e15, a gap rate
# (slope x speed) under 1e6 m/s, the contact normal's tilt sqrt(1 + s^2) under 1.5e3),
# so a finite file cannot overflow the step (issue 34: a map of 1e308 did).
HEIGHT_ABS_MAX_M = 1e5  # |height|: 100 km, ten times the deepest trench or highest peak
SLOPE_MAX = 1e3  # |rise| between neighbouring samples per metre of spacing: 89.94 deg,
# a wall for any tire (a 10 m step on a 1 cm grid); the C1 spline keeps its gradient
# within 1.25 x the steepest neighbouring difference
FRICTION_SCALE_MAX = 3.0  # as the road's friction_scale (core.params)
EXTENT_ABS_MAX_M = 1e7  # every grid point within this of the world origin on x and y
SPACING_MIN_M = 1e-3
SPACING_MAX_M = 1e4


def _first_bad(bad: np.ndarray) -> tuple[int, int]:
    j, i = np.argwhere(bad)[0]
    return int(j), int(i)


def with_own_road(terrain: Terrain) -> Terrain:
    """``terrain`` with a copy of its road (``grid``, which holds it; the heights and
    friction shared: they are never written), so that ``set_road`` on the copy leaves the
    original as it was."""
    return terrain._replace(grid=terrain.grid.copy())


def heightmap_terrain(heights: np.ndarray, dx_m: float, dy_m: float, x0_m: float = 0.0,
                      y0_m: float = 0.0, friction: np.ndarray | None = None) -> Terrain:
    """A height-map terrain; ``heights[j, i]`` is at ``(x0 + i dx, y0 + j dy)``.

    Raises ``ValueError`` (naming the row and column of the first bad sample) for a grid
    smaller than 2x2, a height that is not finite or beyond ``HEIGHT_ABS_MAX_M``, a rise
    between neighbouring samples steeper than ``SLOPE_MAX``, a friction scale not finite or
    outside 0 .. ``FRICTION_SCALE_MAX`` or of another shape, a spacing outside
    ``SPACING_MIN_M`` .. ``SPACING_MAX_M`` or a grid reaching beyond
    ``EXTENT_ABS_MAX_M``: the bounds that keep every product of the step finite."""
    h = np.ascontiguousarray(heights, dtype=np.float64)
    if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
        raise ValueError(f"heights: expected a 2-D grid of at least 2x2, got shape {h.shape}")
    if not np.all(np.isfinite(h)):
        j, i = _first_bad(~np.isfinite(h))
        raise ValueError(f"heights: non-finite value at row {j}, column {i}")
    if np.abs(h).max() > HEIGHT_ABS_MAX_M:
        j, i = _first_bad(np.abs(h) > HEIGHT_ABS_MAX_M)
        raise ValueError(f"heights: {h[j, i]:.6g} m at row {j}, column {i} is beyond "
                         f"+-{HEIGHT_ABS_MAX_M:g} m")
    if not (SPACING_MIN_M <= dx_m <= SPACING_MAX_M and SPACING_MIN_M <= dy_m <= SPACING_MAX_M):
        raise ValueError(f"grid spacing must be within {SPACING_MIN_M:g} .. {SPACING_MAX_M:g} m, "
                         f"got dx={dx_m}, dy={dy_m}")
    ny, nx = h.shape
    for name, lo, hi in (("x", x0_m, x0_m + (nx - 1) * dx_m), ("y", y0_m, y0_m + (ny - 1) * dy_m)):
        if not (abs(lo) <= EXTENT_ABS_MAX_M and abs(hi) <= EXTENT_ABS_MAX_M):
            raise ValueError(f"the grid spans {name} = {lo:.6g} .. {hi:.6g} m, beyond "
                             f"+-{EXTENT_ABS_MAX_M:g} m")
    for axis, spacing in ((1, dx_m), (0, dy_m)):
        rise = np.abs(np.diff(h, axis=axis))
        if rise.max() > SLOPE_MAX * spacing:
            j, i = _first_bad(rise > SLOPE_MAX * spacing)
            along = "column" if axis == 1 else "row"
            raise ValueError(f"heights: a rise of {rise[j, i]:.6g} m over {spacing:g} m at row "
                             f"{j}, column {i} (to the next {along}) is steeper than "
                             f"{SLOPE_MAX:g} m/m")
    if friction is None:
        mu = np.ones_like(h)
    else:
        mu = np.ascontiguousarray(friction, dtype=np.float64)
        if mu.shape != h.shape:
            raise ValueError(f"friction: shape {mu.shape} differs from the heights' {h.shape}")
        bad = ~(np.isfinite(mu) & (mu >= 0.0) & (mu <= FRICTION_SCALE_MAX))
        if bad.any():
            j, i = _first_bad(bad)
            raise ValueError(f"friction: {mu[j, i]:.6g} at row {j}, column {i}: every value "
                             f"must be finite and within 0 .. {FRICTION_SCALE_MAX:g}")
    grid = np.zeros(N_GRID)
    grid[[GRID_X0_M, GRID_Y0_M, GRID_DX_M, GRID_DY_M]] = x0_m, y0_m, dx_m, dy_m
    digest = hashlib.blake2b(digest_size=6)
    for part in (h, mu, grid[:GRID_KEY], np.array(h.shape, dtype=np.int64)):
        digest.update(part.tobytes())
    grid[GRID_KEY] = float(int.from_bytes(digest.digest(), "little"))  # < 2^48: exact
    grid[GRID_ROAD:] = default_road()
    return Terrain(TERRAIN_HEIGHTMAP, h, mu, grid)


@nb.njit(cache=True, inline="always")
def _catmull_rom(t: float) -> tuple[float, float, float, float, float, float, float, float]:
    """Catmull-Rom weights of the four samples around ``t`` in [0, 1] and their
    derivatives in ``t``."""
    t2 = t * t
    t3 = t2 * t
    return (0.5 * (-t + 2.0 * t2 - t3), 0.5 * (2.0 - 5.0 * t2 + 3.0 * t3),
            0.5 * (t + 4.0 * t2 - 3.0 * t3), 0.5 * (-t2 + t3),
            0.5 * (-1.0 + 4.0 * t - 3.0 * t2), 0.5 * (-10.0 * t + 9.0 * t2),
            0.5 * (1.0 + 8.0 * t - 9.0 * t2), 0.5 * (-2.0 * t + 3.0 * t2))


@nb.njit(cache=True, inline="always")
def _cell(pos: float, origin: float, spacing: float, n: int) -> tuple[int, float, bool]:
    """Grid cell index and fraction of a position, clamped to the grid, and whether the
    position is strictly inside the grid."""
    f = (pos - origin) / spacing
    if not f > 0.0:  # also NaN: the grid's first cell
        return 0, 0.0, False
    if f >= n - 1:
        return n - 2, 1.0, False
    i = int(f)
    return i, f - i, True


@nb.njit(cache=True, inline="always")
def _row(h: np.ndarray, jj: int, i0: int, i: int, i3: int, wx0: float, wx1: float,
         wx2: float, wx3: float, dwx0: float, dwx1: float, dwx2: float, dwx3: float
         ) -> tuple[float, float]:
    """One grid row's Catmull-Rom value and x-derivative (``surface_at``)."""
    h0 = h[jj, i0]
    h1 = h[jj, i]
    h2 = h[jj, i + 1]
    h3 = h[jj, i3]
    return (wx0 * h0 + wx1 * h1 + wx2 * h2 + wx3 * h3,
            dwx0 * h0 + dwx1 * h1 + dwx2 * h2 + dwx3 * h3)


@nb.njit(**STEP_JIT_OPTIONS)
def surface_at(terrain: Terrain, wx: float, wy: float) -> tuple[float, float, float, float]:
    """Height (m), gradient ``(dh/dx, dh/dy)`` and friction scale of a height map at the
    world point ``(wx, wy)``. Catmull-Rom in each axis (C1); the samples beyond the edge
    are the edge's own (clamped indices); off the grid the point is clamped to the edge.
    The four rows are written out (no loop, no per-row branch): it runs four times a
    step."""
    h = terrain.heights
    grid = terrain.grid
    ny, nx = h.shape
    dx = grid[GRID_DX_M]
    dy = grid[GRID_DY_M]
    i, tx, inside_x = _cell(wx, grid[GRID_X0_M], dx, nx)
    j, ty, inside_y = _cell(wy, grid[GRID_Y0_M], dy, ny)
    wx0, wx1, wx2, wx3, dwx0, dwx1, dwx2, dwx3 = _catmull_rom(tx)
    wy0, wy1, wy2, wy3, dwy0, dwy1, dwy2, dwy3 = _catmull_rom(ty)
    i0 = max(i - 1, 0)
    i3 = min(i + 2, nx - 1)
    v0, d0 = _row(h, max(j - 1, 0), i0, i, i3, wx0, wx1, wx2, wx3, dwx0, dwx1, dwx2, dwx3)
    v1, d1 = _row(h, j, i0, i, i3, wx0, wx1, wx2, wx3, dwx0, dwx1, dwx2, dwx3)
    v2, d2 = _row(h, j + 1, i0, i, i3, wx0, wx1, wx2, wx3, dwx0, dwx1, dwx2, dwx3)
    v3, d3 = _row(h, min(j + 2, ny - 1), i0, i, i3, wx0, wx1, wx2, wx3, dwx0, dwx1, dwx2,
                  dwx3)
    height = wy0 * v0 + wy1 * v1 + wy2 * v2 + wy3 * v3
    grad_x = wy0 * d0 + wy1 * d1 + wy2 * d2 + wy3 * d3
    grad_y = dwy0 * v0 + dwy1 * v1 + dwy2 * v2 + dwy3 * v3
    mu_map = terrain.friction
    mu = ((1.0 - ty) * ((1.0 - tx) * mu_map[j, i] + tx * mu_map[j, i + 1])
          + ty * ((1.0 - tx) * mu_map[j + 1, i] + tx * mu_map[j + 1, i + 1]))
    # clamped outside the grid: flat there
    if not inside_x:
        grad_x = 0.0
    if not inside_y:
        grad_y = 0.0
    return height, grad_x / dx, grad_y / dy, mu


@nb.njit(cache=True, inline="always")
def _spline_coefficients(h0: float, h1: float, h2: float, h3: float
                         ) -> tuple[float, float, float, float]:
    """Power-basis coefficients ``(a0, a1, a2, a3)`` of the Catmull-Rom segment through
    four samples (``_catmull_rom``'s weights collected by powers of ``t``)."""
    return (h1, 0.5 * (h2 - h0), h0 - 2.5 * h1 + 2.0 * h2 - 0.5 * h3,
            0.5 * (3.0 * (h1 - h2) + h3 - h0))


@nb.njit(**STEP_JIT_OPTIONS)
def _fill_cell(terrain: Terrain, memo: np.ndarray, i: int, j: int) -> None:
    """Write the memo of cell ``(i, j)`` (``CELL_*``): the bicubic's 16 power-basis
    coefficients (the same Catmull-Rom surface as ``surface_at``, clamped samples beyond
    the edge) and the bilinear friction's 4. Once per cell a wheel enters."""
    h = terrain.heights
    ny, nx = h.shape
    i0 = max(i - 1, 0)
    i3 = min(i + 2, nx - 1)
    j0 = max(j - 1, 0)
    j3 = min(j + 2, ny - 1)
    # x-coefficients of each row, then each x-coefficient's y-coefficients
    row0 = _spline_coefficients(h[j0, i0], h[j0, i], h[j0, i + 1], h[j0, i3])
    row1 = _spline_coefficients(h[j, i0], h[j, i], h[j, i + 1], h[j, i3])
    row2 = _spline_coefficients(h[j + 1, i0], h[j + 1, i], h[j + 1, i + 1], h[j + 1, i3])
    row3 = _spline_coefficients(h[j3, i0], h[j3, i], h[j3, i + 1], h[j3, i3])
    for m in range(4):
        c0, c1, c2, c3 = _spline_coefficients(row0[m], row1[m], row2[m], row3[m])
        memo[CELL_H + m] = c0
        memo[CELL_H + 4 + m] = c1
        memo[CELL_H + 8 + m] = c2
        memo[CELL_H + 12 + m] = c3
    mu = terrain.friction
    m00 = mu[j, i]
    memo[CELL_MU] = m00
    memo[CELL_MU + 1] = mu[j, i + 1] - m00
    memo[CELL_MU + 2] = mu[j + 1, i] - m00
    memo[CELL_MU + 3] = mu[j + 1, i + 1] - mu[j + 1, i] - mu[j, i + 1] + m00
    memo[CELL_I] = i
    memo[CELL_J] = j
    memo[CELL_KEY] = terrain.grid[GRID_KEY]


@nb.njit(**STEP_JIT_OPTIONS)
def surface_under_wheel(terrain: Terrain, memo: np.ndarray, wx: float, wy: float
                        ) -> tuple[float, float, float, float]:
    """``surface_at`` for a wheel, through its cell memo ``memo`` (float64[N_CELL],
    ``CELL_*``): the same surface, equal to rounding, evaluated from the cell's
    power-basis coefficients (15 multiply-adds for the height, 15 for the gradient)
    instead of the 16 samples and the spline weights. Off the grid (clamped, flat) it is
    ``surface_at`` itself."""
    grid = terrain.grid
    dx = grid[GRID_DX_M]
    dy = grid[GRID_DY_M]
    fx = (wx - grid[GRID_X0_M]) / dx
    fy = (wy - grid[GRID_Y0_M]) / dy
    tx = fx - memo[CELL_I]
    ty = fy - memo[CELL_J]
    if not (memo[CELL_KEY] == grid[GRID_KEY] and 0.0 <= tx <= 1.0 and 0.0 <= ty <= 1.0):
        ny, nx = terrain.heights.shape
        if not (fx > 0.0 and fy > 0.0 and fx < nx - 1 and fy < ny - 1):
            return surface_at(terrain, wx, wy)
        i = int(fx)
        j = int(fy)
        _fill_cell(terrain, memo, i, j)
        tx = fx - i
        ty = fy - j
    # per power p of ty: the x-polynomial r_p(tx) and its derivative
    r0 = ((memo[CELL_H + 3] * tx + memo[CELL_H + 2]) * tx + memo[CELL_H + 1]) * tx + memo[CELL_H]
    r1 = (((memo[CELL_H + 7] * tx + memo[CELL_H + 6]) * tx + memo[CELL_H + 5]) * tx
          + memo[CELL_H + 4])
    r2 = (((memo[CELL_H + 11] * tx + memo[CELL_H + 10]) * tx + memo[CELL_H + 9]) * tx
          + memo[CELL_H + 8])
    r3 = (((memo[CELL_H + 15] * tx + memo[CELL_H + 14]) * tx + memo[CELL_H + 13]) * tx
          + memo[CELL_H + 12])
    d0 = (3.0 * memo[CELL_H + 3] * tx + 2.0 * memo[CELL_H + 2]) * tx + memo[CELL_H + 1]
    d1 = (3.0 * memo[CELL_H + 7] * tx + 2.0 * memo[CELL_H + 6]) * tx + memo[CELL_H + 5]
    d2 = (3.0 * memo[CELL_H + 11] * tx + 2.0 * memo[CELL_H + 10]) * tx + memo[CELL_H + 9]
    d3 = (3.0 * memo[CELL_H + 15] * tx + 2.0 * memo[CELL_H + 14]) * tx + memo[CELL_H + 13]
    height = ((r3 * ty + r2) * ty + r1) * ty + r0
    grad_x = ((d3 * ty + d2) * ty + d1) * ty + d0
    grad_y = (3.0 * r3 * ty + 2.0 * r2) * ty + r1
    mu = memo[CELL_MU] + memo[CELL_MU + 1] * tx + (memo[CELL_MU + 2] + memo[CELL_MU + 3] * tx) * ty
    return height, grad_x / dx, grad_y / dy, mu


@nb.njit(cache=True, inline="always")
def fit_plane(px: np.ndarray, py: np.ndarray, pz: np.ndarray) -> tuple[float, float, float]:
    """Least-squares plane ``Z = a X + b Y + c`` through the points; ``(a, b, c)``."""
    n = px.size
    mx = 0.0
    my = 0.0
    mz = 0.0
    for k in range(n):
        mx += px[k]
        my += py[k]
        mz += pz[k]
    mx /= n
    my /= n
    mz /= n
    sxx = 0.0
    sxy = 0.0
    syy = 0.0
    sxz = 0.0
    syz = 0.0
    for k in range(n):
        ddx = px[k] - mx
        ddy = py[k] - my
        ddz = pz[k] - mz
        sxx += ddx * ddx
        sxy += ddx * ddy
        syy += ddy * ddy
        sxz += ddx * ddz
        syz += ddy * ddz
    det = sxx * syy - sxy * sxy
    a = (sxz * syy - syz * sxy) / det
    b = (syz * sxx - sxz * sxy) / det
    return a, b, mz - a * mx - b * my


@nb.njit(**STEP_JIT_OPTIONS)
def rebase_reference_plane(x: np.ndarray, grade_pct: float, cross_slope_pct: float,
                           height_m: float, cg_height_m: float, axes_old: np.ndarray,
                           axes_new: np.ndarray, c: float, s: float) -> tuple[float, float]:
    """Re-express the body's planar states on another reference plane
    ``Z = grade/100 X + cross/100 Y + height``, keeping its world CG position, velocity and
    attitude (docs/model.md section 11); the plane's slots of ``x`` are set to it.

    Roll and pitch change by the tilt between the planes (small-angle: the plane moves by
    micro-radians a step); the angular rates are unchanged. ``axes_old`` holds the axes of
    the plane ``x`` is on (``core.road.road_frame``), ``c``, ``s`` the cosine and sine of
    its yaw (the caller has them); ``axes_new`` (float64[3, 3]) is written with the new
    plane's. Returns the cosine and sine of the new yaw."""
    road_frame(grade_pct, cross_slope_pct, axes_new)
    lift = cg_height_m + x[HEAVE_M]
    psi = x[YAW_RAD]
    a = x[U_MPS] * c - x[V_MPS] * s
    b = x[U_MPS] * s + x[V_MPS] * c
    dz0 = x[REF_HEIGHT_M] - height_m
    new_pos0 = 0.0
    new_pos1 = 0.0
    new_pos2 = 0.0
    vel0 = 0.0
    vel1 = 0.0
    vel2 = 0.0
    head_e1 = 0.0
    head_e2 = 0.0
    head_n = 0.0
    left_n = 0.0
    for k in range(3):
        cg_k = x[X_M] * axes_old[0, k] + x[Y_M] * axes_old[1, k] + lift * axes_old[2, k]
        if k == 2:
            cg_k += dz0
        vel_k = a * axes_old[0, k] + b * axes_old[1, k] + x[HEAVE_RATE_MPS] * axes_old[2, k]
        head_k = c * axes_old[0, k] + s * axes_old[1, k]
        left_k = -s * axes_old[0, k] + c * axes_old[1, k]
        new_pos0 += cg_k * axes_new[0, k]
        new_pos1 += cg_k * axes_new[1, k]
        new_pos2 += cg_k * axes_new[2, k]
        vel0 += vel_k * axes_new[0, k]
        vel1 += vel_k * axes_new[1, k]
        vel2 += vel_k * axes_new[2, k]
        head_e1 += head_k * axes_new[0, k]
        head_e2 += head_k * axes_new[1, k]
        head_n += head_k * axes_new[2, k]
        left_n += left_k * axes_new[2, k]
    # the heading on the new plane, normalised, is (cos, sin) of the new yaw; the yaw
    # moves by the (small) angle between the two headings
    head_norm = np.sqrt(head_e1 * head_e1 + head_e2 * head_e2)
    c_new = head_e1 / head_norm
    s_new = head_e2 / head_norm
    psi_new = psi + np.arctan2(s_new * c - c_new * s, c_new * c + s_new * s)
    c = c_new
    s = s_new
    x[X_M] = new_pos0
    x[Y_M] = new_pos1
    x[HEAVE_M] = new_pos2 - cg_height_m
    x[YAW_RAD] = psi_new
    x[U_MPS] = vel0 * c + vel1 * s
    x[V_MPS] = -vel0 * s + vel1 * c
    x[HEAVE_RATE_MPS] = vel2
    x[PITCH_RAD] -= head_n
    x[ROLL_RAD] += left_n
    x[REF_GRADE_PCT] = grade_pct
    x[REF_CROSS_SLOPE_PCT] = cross_slope_pct
    x[REF_HEIGHT_M] = height_m
    return c, s
