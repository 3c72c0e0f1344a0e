"""The terrain in the Rerun scene: the ground as a mesh, an OpenDRIVE road's lanes and marks.

Logged once per recording, static (``log_terrain``), by the headless ``run-scenario
--rrd`` path and by the live viewer alike (``rerun_scene``). Entity paths::

    world/terrain/ground    the height grid the step queries (``core.terrain``: a height
                            map, or the OpenDRIVE road rasterised), a triangle mesh through
                            its samples, decimated to at most ``MAX_GROUND_VERTICES``
                            vertices (every ``ground_stride``-th row and column, the last
                            ones always kept); coloured by the friction scale (grey at 1,
                            blue toward 0), ``GROUND_OFFSET_M`` below the surface
    world/terrain/lanes     OpenDRIVE only: every lane between its borders, sampled every
                            ``LANE_STEP_M`` along the road, coloured by lane type
    world/terrain/borders   OpenDRIVE only: every lane's outer border (thin grey strips)
    world/terrain/marks     OpenDRIVE only: the road marks the file gives (``<roadMark>``
                            on the lane's outer border): solid, or broken as
                            ``DASH_M`` dashes every ``DASH_PERIOD_M``; white or yellow,
                            as wide as the file says

A lane's surface point at ``(s, t)`` is the one ``adapters.opendrive`` rasterises: the
reference line's point moved ``t cos(roll)`` across it and ``t sin(roll)`` up from the
elevation (roll: the superelevation; ASAM OpenDRIVE 1.6 section 8.4.1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from simserver.adapters.opendrive import (
    OpenDrive,
    Road,
    load_opendrive,
    profile_values,
    reference_points,
)
from simserver.core.terrain import (
    GRID_DX_M,
    GRID_DY_M,
    GRID_X0_M,
    GRID_Y0_M,
    TERRAIN_OPENDRIVE,
    TERRAIN_PLANE,
    Terrain,
)

TERRAIN = "world/terrain"
GROUND = "world/terrain/ground"
LANES = "world/terrain/lanes"
BORDERS = "world/terrain/borders"
MARKS = "world/terrain/marks"
TERRAIN_ENTITY_PATHS = (GROUND, LANES, BORDERS, MARKS)
"""What ``log_terrain`` writes (the last three for an OpenDRIVE road only)."""

MAX_GROUND_VERTICES = 250_000
"""Most vertices of the ground mesh (about 10 MB in the recording)."""
LANE_STEP_M = 1.0
"""Lanes, borders and marks are sampled this often along the road (and at every section
start and end): a third of a dash."""
GROUND_OFFSET_M = -0.02  # the ground sits just below the contact surface (as the plane)
LANE_OFFSET_M = -0.005  # the lanes just above the ground: the road covers its raster
MARK_OFFSET_M = 0.01
DASH_M = 3.0
DASH_PERIOD_M = 9.0
BORDER_RADIUS_M = 0.03

GROUND_RGB = np.array([150.0, 158.0, 142.0])
ICE_RGB = np.array([90.0, 150.0, 230.0])
LANE_COLORS = {"driving": (72, 74, 80), "parking": (92, 92, 110), "biking": (140, 84, 72),
               "sidewalk": (182, 176, 166), "border": (160, 158, 150),
               "shoulder": (140, 138, 128), "curb": (200, 200, 200)}
OTHER_LANE_COLOR = (118, 118, 112)
MARK_COLORS = {"yellow": (240, 200, 40), "red": (220, 50, 40), "blue": (50, 90, 220),
               "green": (50, 170, 70)}
WHITE = (240, 240, 240)


# ------------------------------------------------------------------------- ground
def ground_stride(ny: int, nx: int, max_vertices: int = MAX_GROUND_VERTICES) -> int:
    """Rows and columns kept: every ``stride``-th, the smallest stride for which the mesh
    (``_kept(n, stride)`` per axis) has at most ``max_vertices`` vertices."""
    stride = max(1, math.ceil(math.sqrt(ny * nx / max_vertices)))
    while _kept(ny, stride).size * _kept(nx, stride).size > max_vertices:
        stride += 1
    return stride


def _kept(n: int, stride: int) -> np.ndarray:
    idx = np.arange(0, n, stride)
    return idx if idx[-1] == n - 1 else np.append(idx, n - 1)


def ground_mesh(terrain: Terrain, max_vertices: int = MAX_GROUND_VERTICES
                ) -> dict[str, np.ndarray]:
    """The ground grid as ``Mesh3D`` fields: positions, triangles, normals, colours.

    The vertices are grid samples (the Catmull-Rom surface passes through them), the
    normals the grid's central-difference gradient, the colour the friction scale.
    """
    h = terrain.heights
    grid = terrain.grid
    ny, nx = h.shape
    stride = ground_stride(ny, nx, max_vertices)
    rows, cols = _kept(ny, stride), _kept(nx, stride)
    sub = h[np.ix_(rows, cols)]
    xs = grid[GRID_X0_M] + cols * grid[GRID_DX_M]
    ys = grid[GRID_Y0_M] + rows * grid[GRID_DY_M]
    xx, yy = np.meshgrid(xs, ys)
    positions = np.stack([xx, yy, sub + GROUND_OFFSET_M], axis=-1).reshape(-1, 3)
    grad_y, grad_x = np.gradient(sub, ys, xs) if min(sub.shape) > 1 else (
        np.zeros_like(sub), np.zeros_like(sub))
    normals = np.stack([-grad_x, -grad_y, np.ones_like(sub)], axis=-1).reshape(-1, 3)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    mu = np.clip(terrain.friction[np.ix_(rows, cols)].reshape(-1, 1), 0.0, 1.0)
    rgb = ICE_RGB + (GROUND_RGB - ICE_RGB) * mu
    colors = np.concatenate([np.round(rgb), np.full((rgb.shape[0], 1), 255.0)], axis=1)
    n_r, n_c = rows.size, cols.size
    k = (np.arange(n_r - 1)[:, None] * n_c + np.arange(n_c - 1)[None, :]).ravel()
    triangles = np.concatenate([np.stack([k, k + 1, k + n_c + 1], axis=1),
                                np.stack([k, k + n_c + 1, k + n_c], axis=1)])
    return {"vertex_positions": positions.astype(np.float32),
            "triangle_indices": triangles.astype(np.uint32),
            "vertex_normals": normals.astype(np.float32),
            "vertex_colors": colors.astype(np.uint8)}


# -------------------------------------------------------------------------- lanes
def _reference(road: Road, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World ``x, y, heading`` of the reference line at every ``s``."""
    return reference_points(road, s)  # the rasteriser's own (adapters.opendrive)


def _section_samples(s0: float, s1: float, step_m: float) -> np.ndarray:
    n = max(1, math.ceil((s1 - s0) / step_m))
    return np.linspace(s0, s1, n + 1)


def lane_surfaces(od: OpenDrive, step_m: float = LANE_STEP_M) -> list[dict[str, Any]]:
    """Every lane of every section of every road: its id and type, the section-relative
    ``s`` samples and its inner and outer border points ``(m, 3)`` on the road surface,
    and its road marks (``Lane.marks``)."""
    lanes: list[dict[str, Any]] = []
    for road in od.roads:
        for k, sec in enumerate(road.lane_sections):
            s1 = road.lane_sections[k + 1].s if k + 1 < len(road.lane_sections) else road.length
            s1 = min(s1, road.length)
            if not s1 > sec.s:
                continue
            s = _section_samples(sec.s, s1, step_m)
            rx, ry, hdg = _reference(road, s)
            elev = profile_values(road.elevation, s)
            roll = profile_values(road.superelevation, s)

            def point(t: np.ndarray, rx=rx, ry=ry, hdg=hdg, elev=elev, roll=roll
                      ) -> np.ndarray:
                across = t * np.cos(roll)
                return np.stack([rx - np.sin(hdg) * across, ry + np.cos(hdg) * across,
                                 elev + t * np.sin(roll)], axis=1)

            for side in (1, -1):  # left lanes outward from the centre, then the right ones
                inner = np.zeros_like(s)
                for lane in sorted((ln for ln in sec.lanes if ln.id * side > 0),
                                   key=lambda ln: abs(ln.id)):
                    width = np.maximum(0.0, profile_values(lane.widths, s - sec.s))
                    outer = inner + side * width
                    lanes.append({"road": road.id, "id": lane.id, "type": lane.type,
                                  "s": s - sec.s, "inner": point(inner), "outer": point(outer),
                                  "marks": lane.marks})
                    inner = outer
            centre = [ln for ln in sec.lanes if ln.id == 0 and ln.marks]
            if centre:
                line = point(np.zeros_like(s))
                lanes.append({"road": road.id, "id": 0, "type": "center", "s": s - sec.s,
                              "inner": line, "outer": line, "marks": centre[0].marks})
    return lanes


def lane_mesh(lanes: Sequence[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The lanes (not the centre line) as one ``Mesh3D``: a strip of two triangles per
    sample interval between each lane's borders, coloured by lane type."""
    positions, triangles, colors = [], [], []
    base = 0
    for lane in lanes:
        if lane["id"] == 0:
            continue
        inner, outer = lane["inner"], lane["outer"]
        m = inner.shape[0]
        positions.append(np.concatenate([inner, outer]))
        k = np.arange(m - 1)
        i0, i1, o0, o1 = base + k, base + k + 1, base + m + k, base + m + k + 1
        triangles.append(np.concatenate([np.stack([i0, o0, o1], axis=1),
                                         np.stack([i0, o1, i1], axis=1)]))
        rgb = LANE_COLORS.get(lane["type"], OTHER_LANE_COLOR)
        colors.append(np.tile([*rgb, 255], (2 * m, 1)))
        base += 2 * m
    pos = np.concatenate(positions) + [0.0, 0.0, LANE_OFFSET_M]
    return {"vertex_positions": pos.astype(np.float32),
            "triangle_indices": np.concatenate(triangles).astype(np.uint32),
            "vertex_colors": np.concatenate(colors).astype(np.uint8)}


def lane_lines(lanes: Sequence[dict[str, Any]]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``LineStrips3D`` fields of the lanes' outer borders and of their road marks."""
    borders = [lane["outer"] + [0.0, 0.0, MARK_OFFSET_M] for lane in lanes if lane["id"] != 0]
    strips, colors, radii = [], [], []
    for lane in lanes:
        s = lane["s"]
        line = lane["outer"] + [0.0, 0.0, 1.5 * MARK_OFFSET_M]
        marks = sorted(lane["marks"], key=lambda m: m.s_offset)
        for j, mark in enumerate(marks):
            end = marks[j + 1].s_offset if j + 1 < len(marks) else np.inf
            if mark.type == "none":
                continue
            on = (s >= mark.s_offset - 1e-9) & (s <= end + 1e-9)
            if mark.type == "broken":
                on &= np.mod(s - mark.s_offset, DASH_PERIOD_M) <= DASH_M + 1e-9
            for run in _runs(on):
                if run.size >= 2:
                    strips.append(line[run])
                    colors.append([*MARK_COLORS.get(mark.color, WHITE), 255])
                    radii.append(0.5 * mark.width)
    return ({"strips": borders, "colors": [[120, 120, 120, 255]] * len(borders),
             "radii": [BORDER_RADIUS_M] * len(borders)},
            {"strips": strips, "colors": colors, "radii": radii})


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the runs of True in ``mask``."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)


# -------------------------------------------------------------------------- entry
def log_terrain(rec: rr.RecordingStream, terrain: Terrain,
                spec: dict[str, Any] | None = None,
                max_vertices: int = MAX_GROUND_VERTICES) -> str:
    """Log (static) the terrain of a scene; returns its description for the scene note.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log.
    terrain : Terrain
        The scene's terrain (``Scene.terrain``); nothing is logged for the plane kind.
    spec : dict, optional
        ``Scene.terrain_spec``: an OpenDRIVE road's file, read again (no rasterising)
        for its lanes and marks.
    max_vertices : int
        Of the ground mesh.
    """
    if terrain.kind == TERRAIN_PLANE:
        return ""
    rec.log(GROUND, rr.Mesh3D(**ground_mesh(terrain, max_vertices)), static=True)
    ny, nx = terrain.heights.shape
    text = (f"{nx} x {ny} height grid of {terrain.grid[GRID_DX_M]:g} m cells, heights "
            f"{terrain.heights.min():.2f} .. {terrain.heights.max():.2f} m")
    if terrain.kind == TERRAIN_OPENDRIVE and spec is not None and "file" in spec:
        od = load_opendrive(spec["file"])
        lanes = lane_surfaces(od)
        rec.log(LANES, rr.Mesh3D(**lane_mesh(lanes)), static=True)
        borders, marks = lane_lines(lanes)
        rec.log(BORDERS, rr.LineStrips3D(**borders), static=True)
        rec.log(MARKS, rr.LineStrips3D(**marks), static=True)
        text = (f"OpenDRIVE {len(od.roads)} road(s), "
                f"{sum(1 for ln in lanes if ln['id'] != 0)} lane pieces; " + text)
    return text
