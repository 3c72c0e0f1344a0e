"""Where a point of the world lies on the roads of an OpenDRIVE terrain: the road, ``s``
along its reference line, ``t`` across it, the lane there and the distance to the road's
edge, on or off the road.

The road's edge is the outer border of its outermost lanes on either side (border and
shoulder lanes included: the terrain lays every lane on the road's surface, and the ground
beyond them is a fill, docs/model.md section 11). ``edge_m`` is the distance to the
nearer edge, positive on the road and negative off it (how far beyond the edge).

The point is projected onto the reference lines: the nearest of the reference line's
samples (every ``spacing_m``, found in a grid of buckets) is refined by Newton steps on
``s`` along the geometry itself (``Road.reference``), so ``s`` and ``t`` are exact to the
geometry, not to the samples. numpy only, no core: the driver clients and the tests use
it (``clients/driver.py`` shows the car's road position on an OpenDRIVE terrain).
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from simserver.adapters.opendrive import (
    OpenDrive,
    Road,
    _section_at,
    profile_at,
    reference_points,
)

SAMPLE_SPACING_M = 1.0
"""Reference-line samples of the coarse search, one every this many metres."""
BUCKET_M = 16.0
"""Side of the grid buckets the samples are kept in."""
SEARCH_RADIUS_M = 200.0
"""A point farther than about this from every reference line is on no road (None)."""


@dataclass(frozen=True)
class RoadPosition:
    """A point's place on a road.

    Attributes
    ----------
    road : str
        The road's id, as written in the file.
    s_m : float
        Distance along the road's reference line.
    t_m : float
        Lateral offset from the reference line along the road's surface (its
        cross-section, rolled by the superelevation), left of its direction +.
    lane : int
        Id of the lane at ``(s, t)`` (negative right of the reference line, positive
        left); off the road the id of the outermost lane on that side.
    lane_type : str
        That lane's OpenDRIVE type (``driving``, ``border``, ``shoulder``, ...).
    edge_m : float
        Distance to the nearer edge of the road: >= 0 on it, < 0 beyond the edge.
    surface_z_m : float
        Height of the road's surface under the point: the elevation profile plus the
        superelevation's rise across (``t sin(roll)``).
    """

    road: str
    s_m: float
    t_m: float
    lane: int
    lane_type: str
    edge_m: float
    surface_z_m: float

    @property
    def on_road(self) -> bool:
        """Within the road's edges."""
        return self.edge_m >= 0.0


def lane_at(road: Road, s: float, t: float) -> tuple[int, str, float, float]:
    """``(lane id, lane type, t_right, t_left)`` at ``(s, t)``: the lane whose band holds
    ``t`` (the outermost one on that side when ``t`` is beyond the road), and the road's
    edges there (``t_right <= 0 <= t_left``)."""
    section = _section_at(road, s)
    if section is None:
        return 0, "none", 0.0, 0.0
    ds = s - section.s
    side = [lane for lane in section.lanes if (lane.id > 0) == (t >= 0.0) and lane.id != 0]
    side.sort(key=lambda lane: abs(lane.id))  # inner to outer
    inner = 0.0
    found: tuple[int, str] | None = None
    for lane in side:
        width = 0.0
        if lane.widths and ds + 1e-9 >= lane.widths[0].s:
            width = max(0.0, profile_at(lane.widths, ds))
        outer = inner + width
        if found is None and abs(t) <= outer:
            found = lane.id, lane.type
        inner = outer
    right, left = road_edges(road, s)
    if found is None:
        found = (side[-1].id, side[-1].type) if side else (0, "none")
    return found[0], found[1], right, left


def road_edges(road: Road, s: float) -> tuple[float, float]:
    """``(t_right <= 0, t_left >= 0)``: the road's edges at ``s`` (every lane's width)."""
    section = _section_at(road, s)
    right = left = 0.0
    if section is None:
        return right, left
    ds = s - section.s
    for lane in section.lanes:
        if lane.id == 0 or not lane.widths or ds + 1e-9 < lane.widths[0].s:
            continue
        width = max(0.0, profile_at(lane.widths, ds))
        if lane.id > 0:
            left += width
        else:
            right -= width
    return right, left


class RoadLocator:
    """The road positions of world points on the roads of ``od`` (module docstring).

    Parameters
    ----------
    od : OpenDrive
        The terrain's roads (``adapters.opendrive.load_opendrive``).
    spacing_m : float
        Spacing of the reference-line samples of the coarse search.
    """

    def __init__(self, od: OpenDrive, spacing_m: float = SAMPLE_SPACING_M) -> None:
        self.roads = list(od.roads)
        xs, ys, owner, ss = [], [], [], []
        for k, road in enumerate(self.roads):
            n = max(2, int(math.ceil(road.length / spacing_m)) + 1)
            s = np.linspace(0.0, road.length, n)
            x, y, _ = reference_points(road, s)
            xs.append(x)
            ys.append(y)
            ss.append(s)
            owner.append(np.full(n, k))
        self._x = np.concatenate(xs) if xs else np.zeros(0)
        self._y = np.concatenate(ys) if ys else np.zeros(0)
        self._s = np.concatenate(ss) if ss else np.zeros(0)
        self._road = np.concatenate(owner) if owner else np.zeros(0, dtype=int)
        buckets: dict[tuple[int, int], list[int]] = defaultdict(list)
        for i, key in enumerate(zip(np.floor(self._x / BUCKET_M).astype(int),
                                    np.floor(self._y / BUCKET_M).astype(int), strict=True)):
            buckets[key].append(i)
        self._buckets = {key: np.array(idx) for key, idx in buckets.items()}

    def _candidates(self, x: float, y: float) -> np.ndarray:
        """Sample indices of the nearest non-empty ring of buckets around ``(x, y)``, with
        the ring beyond it (a nearer sample may sit just across a bucket's side)."""
        cx, cy = math.floor(x / BUCKET_M), math.floor(y / BUCKET_M)
        rings = int(SEARCH_RADIUS_M / BUCKET_M) + 1
        for ring in range(rings + 1):
            found = [self._buckets[(cx + i, cy + j)]
                     for i in range(-ring - 1, ring + 2) for j in range(-ring - 1, ring + 2)
                     if (cx + i, cy + j) in self._buckets]
            if found:
                return np.concatenate(found)
        return np.zeros(0, dtype=int)

    def locate(self, x: float, y: float) -> RoadPosition | None:
        """The road position of the world point ``(x, y)``, or None when no road's
        reference line passes within about :data:`SEARCH_RADIUS_M`."""
        idx = self._candidates(x, y)
        if idx.size == 0:
            return None
        d2 = (self._x[idx] - x) ** 2 + (self._y[idx] - y) ** 2
        best: tuple[float, int, float, float] | None = None
        # the nearest sample of each road among the candidates, refined on its geometry
        for k in np.unique(self._road[idx]):
            mine = idx[self._road[idx] == k]
            i = mine[np.argmin(d2[self._road[idx] == k])]
            road = self.roads[int(k)]
            s, t, dist = project(road, x, y, float(self._s[i]))
            if best is None or dist < best[0]:
                best = dist, int(k), s, t
        _, k, s, across = best
        road = self.roads[k]
        # the cross-section is rolled by the superelevation: a point ``t`` along it lies
        # ``t cos(roll)`` across horizontally and ``t sin(roll)`` up (as the terrain
        # lays it, adapters.opendrive)
        roll = profile_at(road.superelevation, s)
        t = across / math.cos(roll)
        lane, lane_type, right, left = lane_at(road, s, t)
        edge = min(t - right, left - t)
        z = profile_at(road.elevation, s) + across * math.tan(roll)
        return RoadPosition(road.id, s, t, lane, lane_type, edge, z)


def project(road: Road, x: float, y: float, s0: float, steps: int = 6
            ) -> tuple[float, float, float]:
    """``(s, across, distance)`` of the point ``(x, y)`` projected on the road's reference
    line from the guess ``s0`` (Newton steps along the tangent, ``s`` kept within the
    road): ``across`` is its horizontal offset, left +, and ``distance`` its distance from
    the reference point at ``s``."""
    s = s0
    for _ in range(steps):
        rx, ry, h = road.reference(s)
        ds = (x - rx) * math.cos(h) + (y - ry) * math.sin(h)
        s_new = min(max(s + ds, 0.0), road.length)
        if abs(s_new - s) < 1e-9:
            s = s_new
            break
        s = s_new
    rx, ry, h = road.reference(s)
    t = -(x - rx) * math.sin(h) + (y - ry) * math.cos(h)
    return s, t, math.hypot(x - rx, y - ry)
