"""ASAM OpenDRIVE roads: the subset the terrain needs, read from an ``.xodr`` file.

Per road: the reference line (``planView``: ``line``, ``arc``, ``spiral``, ``poly3``,
``paramPoly3``), the elevation and superelevation profiles (cubic in ``ds`` per piece)
and the lane sections with their lane widths (cubic in ``ds`` from ``sOffset``). The
geometry follows the standard's definitions:

- ``line``: ``x = x0 + ds cos(hdg)``, ``y = y0 + ds sin(hdg)``;
- ``arc`` (curvature k): ``x = x0 + (sin(hdg + k ds) - sin(hdg)) / k``,
  ``y = y0 - (cos(hdg + k ds) - cos(hdg)) / k``, heading ``hdg + k ds``;
- ``spiral`` (clothoid, curvature linear in ``ds`` from ``curvStart`` to ``curvEnd``):
  heading ``hdg + k0 ds + (k1 - k0) ds^2 / (2 L)``, position the integral of the heading's
  unit vector (Gauss-Legendre, 8 nodes per metre or less: exact to rounding here);
- ``poly3``: ``v = a + b u + c u^2 + d u^3`` in the local frame at (x0, y0, hdg), with
  ``ds`` the arc length along the curve (``u`` found from it);
- ``paramPoly3``: ``u(p)``, ``v(p)`` cubic in ``p``, with ``pRange`` ``arcLength``
  (``p`` in [0, length]) or ``normalized`` (``p`` in [0, 1]).

Superelevation is the roll angle of the cross-section about the reference line (positive:
the right side, ``t < 0``, goes down; ASAM OpenDRIVE 1.6, 8.4.1), so a surface point at
lateral offset ``t`` stands ``t sin(roll)`` above the reference line's elevation.

Errors name the file and the element (``OpenDriveError``, a ``ConfigError``); a file that
fails is not kept in part.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
import xml.parsers.expat
from dataclasses import dataclass, field
from pathlib import Path

import numba as nb
import numpy as np

from simserver.adapters.validate import ConfigError

GEOMETRY_KINDS = ("line", "arc", "spiral", "poly3", "paramPoly3")
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(8)


class OpenDriveError(ConfigError):
    """An ``.xodr`` file is unreadable or outside the supported subset; names the element."""


@dataclass(frozen=True)
class Geometry:
    """One piece of a reference line, starting at ``s`` with ``(x, y, hdg)``."""

    s: float
    x: float
    y: float
    hdg: float
    length: float
    kind: str  # one of GEOMETRY_KINDS
    params: dict[str, float | str] = field(default_factory=dict)

    def point(self, ds: float) -> tuple[float, float, float]:
        """World ``(x, y, heading)`` at ``ds`` (0 .. length) along the piece."""
        h0 = self.hdg
        if self.kind == "line":
            return self.x + ds * math.cos(h0), self.y + ds * math.sin(h0), h0
        if self.kind == "arc":
            k = float(self.params["curvature"])
            if k == 0.0:
                return self.x + ds * math.cos(h0), self.y + ds * math.sin(h0), h0
            return (self.x + (math.sin(h0 + k * ds) - math.sin(h0)) / k,
                    self.y - (math.cos(h0 + k * ds) - math.cos(h0)) / k, h0 + k * ds)
        if self.kind == "spiral":
            k0 = float(self.params["curvStart"])
            k1 = float(self.params["curvEnd"])
            rate = (k1 - k0) / self.length

            def heading(s: np.ndarray) -> np.ndarray:
                return h0 + k0 * s + 0.5 * rate * s * s

            u, v = _integrate_unit(heading, ds)
            return self.x + u, self.y + v, float(heading(np.array(ds)))
        if self.kind == "poly3":
            a, b, c, d = (float(self.params[k]) for k in "abcd")
            u = _poly3_u_at_length(b, c, d, ds)
            v = a + b * u + c * u * u + d * u ** 3
            dv = b + 2.0 * c * u + 3.0 * d * u * u
            return (*_local_to_world(self.x, self.y, h0, u, v), h0 + math.atan(dv))
        if self.kind == "paramPoly3":
            p = ds if self.params["pRange"] == "arcLength" else ds / self.length
            cu = [float(self.params[f"{k}U"]) for k in "abcd"]
            cv = [float(self.params[f"{k}V"]) for k in "abcd"]
            u = cu[0] + cu[1] * p + cu[2] * p * p + cu[3] * p ** 3
            v = cv[0] + cv[1] * p + cv[2] * p * p + cv[3] * p ** 3
            du = cu[1] + 2.0 * cu[2] * p + 3.0 * cu[3] * p * p
            dv = cv[1] + 2.0 * cv[2] * p + 3.0 * cv[3] * p * p
            return (*_local_to_world(self.x, self.y, h0, u, v), h0 + math.atan2(dv, du))
        raise ValueError(f"unknown geometry kind {self.kind!r}")

    def points(self, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``point`` at every ``ds`` of an increasing array (vectorised; the spiral is
        integrated piece by piece between the samples)."""
        ds = np.asarray(ds, dtype=np.float64)
        h0 = self.hdg
        if self.kind == "line" or (self.kind == "arc" and self.params["curvature"] == 0.0):
            return self.x + ds * math.cos(h0), self.y + ds * math.sin(h0), np.full_like(ds, h0)
        if self.kind == "arc":
            k = float(self.params["curvature"])
            return (self.x + (np.sin(h0 + k * ds) - math.sin(h0)) / k,
                    self.y - (np.cos(h0 + k * ds) - math.cos(h0)) / k, h0 + k * ds)
        if self.kind == "spiral":
            k0 = float(self.params["curvStart"])
            rate = (float(self.params["curvEnd"]) - k0) / self.length
            edges = np.concatenate(([0.0], ds))
            half = 0.5 * np.diff(edges)
            mid = 0.5 * (edges[1:] + edges[:-1])
            sq = mid[:, None] + half[:, None] * _GL_NODES[None, :]
            theta = h0 + k0 * sq + 0.5 * rate * sq * sq
            w = half[:, None] * _GL_WEIGHTS[None, :]
            u = np.cumsum(np.sum(w * np.cos(theta), axis=1))
            v = np.cumsum(np.sum(w * np.sin(theta), axis=1))
            return self.x + u, self.y + v, h0 + k0 * ds + 0.5 * rate * ds * ds
        pts = np.array([self.point(float(d)) for d in ds]).reshape(-1, 3)
        return pts[:, 0], pts[:, 1], pts[:, 2]

    def end(self) -> tuple[float, float, float]:
        """``point(length)``."""
        return self.point(self.length)


def _local_to_world(x0: float, y0: float, hdg: float, u: float, v: float) -> tuple[float, float]:
    c, s = math.cos(hdg), math.sin(hdg)
    return x0 + c * u - s * v, y0 + s * u + c * v


def _integrate_unit(heading, ds: float) -> tuple[float, float]:  # noqa: ANN001 - a callable
    """``(int_0^ds cos(heading), int_0^ds sin(heading))`` by composite Gauss-Legendre."""
    if ds <= 0.0:
        return 0.0, 0.0
    n = max(1, math.ceil(ds))  # pieces of at most 1 m, 8 nodes each
    edges = np.linspace(0.0, ds, n + 1)
    half = 0.5 * (edges[1:] - edges[:-1])
    mid = 0.5 * (edges[1:] + edges[:-1])
    s = (mid[:, None] + half[:, None] * _GL_NODES[None, :]).ravel()
    w = (half[:, None] * _GL_WEIGHTS[None, :]).ravel()
    theta = heading(s)
    return float(np.sum(w * np.cos(theta))), float(np.sum(w * np.sin(theta)))


def _poly3_u_at_length(b: float, c: float, d: float, length: float) -> float:
    """The ``u`` at which the arc length of ``v(u)`` from 0 reaches ``length`` (Newton)."""
    def arc(u: float) -> float:
        if u <= 0.0:
            return 0.0
        n = max(1, math.ceil(u))
        edges = np.linspace(0.0, u, n + 1)
        half = 0.5 * (edges[1:] - edges[:-1])
        mid = 0.5 * (edges[1:] + edges[:-1])
        x = (mid[:, None] + half[:, None] * _GL_NODES[None, :]).ravel()
        w = (half[:, None] * _GL_WEIGHTS[None, :]).ravel()
        dv = b + 2.0 * c * x + 3.0 * d * x * x
        return float(np.sum(w * np.sqrt(1.0 + dv * dv)))

    u = length
    for _ in range(50):
        dv = b + 2.0 * c * u + 3.0 * d * u * u
        step = (arc(u) - length) / math.sqrt(1.0 + dv * dv)
        u -= step
        if abs(step) < 1e-12:
            break
    return u


@dataclass(frozen=True)
class Cubic:
    """``a + b ds + c ds^2 + d ds^3`` from ``s`` on (one piece of a profile)."""

    s: float
    a: float
    b: float
    c: float
    d: float

    def at(self, s: float) -> float:
        ds = s - self.s
        return self.a + ds * (self.b + ds * (self.c + ds * self.d))


def profile_values(pieces: list[Cubic], s: np.ndarray) -> np.ndarray:
    """``profile_at`` at every ``s`` (vectorised)."""
    s = np.asarray(s, dtype=np.float64)
    if not pieces:
        return np.zeros_like(s)
    starts = np.array([p.s for p in pieces])
    coef = np.array([(p.a, p.b, p.c, p.d) for p in pieces])
    k = np.clip(np.searchsorted(starts, s + 1e-9, side="right") - 1, 0, len(pieces) - 1)
    ds = s - starts[k]
    a, b, c, d = coef[k].T
    return a + ds * (b + ds * (c + ds * d))


def profile_at(pieces: list[Cubic], s: float) -> float:
    """The value of a piecewise-cubic profile at ``s`` (the last piece starting at or
    before ``s``; 0 for an empty profile)."""
    value = 0.0
    for piece in pieces:
        if piece.s <= s + 1e-9:
            value = piece.at(s)
        else:
            break
    return value


@dataclass(frozen=True)
class RoadMark:
    """A ``<roadMark>`` on a lane's outer border from ``s_offset`` (section-relative) on:
    its ``type`` (``solid``, ``broken``, ``none``, ...), ``color`` and ``width`` (m)."""

    s_offset: float
    type: str
    color: str
    width: float


@dataclass(frozen=True)
class Lane:
    id: int
    type: str
    widths: list[Cubic]  # s = sOffset from the section start
    marks: list[RoadMark] = field(default_factory=list)  # drawn only (adapters.rerun_terrain)


@dataclass(frozen=True)
class LaneSection:
    s: float
    lanes: list[Lane]


@dataclass(frozen=True)
class Road:
    id: str
    length: float
    geometries: list[Geometry]
    elevation: list[Cubic]
    superelevation: list[Cubic]
    lane_sections: list[LaneSection]
    rule: str = "RHT"  # traffic rule: RHT, the right lanes (t < 0) travel along +s; LHT

    def reference(self, s: float) -> tuple[float, float, float]:
        """World ``(x, y, heading)`` of the reference line at ``s``."""
        geo = self.geometries[0]
        for g in self.geometries:
            if g.s <= s + 1e-9:
                geo = g
        return geo.point(min(max(s - geo.s, 0.0), geo.length))


@dataclass(frozen=True)
class OpenDrive:
    path: Path
    roads: list[Road]
    dropped: tuple[str, ...] = ()  # what the file has and the reader does not use
    # (``dropped_elements``): one line per element name, reported once when loaded


READ_ELEMENTS = frozenset((
    "OpenDRIVE", "road", "planView", "geometry", *GEOMETRY_KINDS, "elevationProfile",
    "elevation", "lateralProfile", "superelevation", "lanes", "laneSection", "left",
    "center", "right", "lane", "width"))
"""The elements ``load_opendrive`` reads."""
UNUSED_WHOLE = frozenset(("header", "link", "roadMark", "userData"))
"""Elements whose content does not shape the ground or the lanes, not reported: the
header (name, date, geo-reference), road and lane links (the ground is one grid: no
topology is needed), road marks (drawn by their ``type``; their line patterns are not)
and user data."""
CONTAINERS = frozenset(("objects", "signals"))
"""Containers whose children are each reported (an ``<object>``, a ``<tunnel>``, a
``<signal>``), not the container itself."""
DROPPED_NOTES = {
    "height": "lane heights (kerbs, sidewalks) are not applied: every lane lies on the "
              "road's surface",
}


def dropped_elements(path: Path, data: bytes) -> tuple[str, ...]:
    """The elements of an ``.xodr`` file (its bytes ``data``) that ``load_opendrive`` does
    not use, one line per element name with the lines it is on (the first ten): objects,
    signals, lane heights, borders, offsets, junctions, ... (``READ_ELEMENTS``,
    ``UNUSED_WHOLE``, ``CONTAINERS``). A dropped element's own children are not listed
    again. Read by a streaming parser: no tree is built."""
    found: dict[str, list[int]] = {}
    skip_depth = 0  # > 0: inside an element not read (its children are not listed)
    parser = xml.parsers.expat.ParserCreate()

    def start(tag: str, _attrs: dict) -> None:
        nonlocal skip_depth
        if skip_depth:
            skip_depth += 1
            return
        if tag in READ_ELEMENTS or tag in CONTAINERS:
            return
        if tag not in UNUSED_WHOLE:
            found.setdefault(tag, []).append(parser.CurrentLineNumber)
        skip_depth = 1

    def end(_tag: str) -> None:
        nonlocal skip_depth
        if skip_depth:
            skip_depth -= 1

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    try:
        parser.Parse(data, True)
    except xml.parsers.expat.ExpatError:
        return ()  # load_opendrive names the XML error itself
    lines = []
    for tag, at in found.items():
        shown = ", ".join(str(n) for n in at[:10]) + (", ..." if len(at) > 10 else "")
        note = DROPPED_NOTES.get(tag, "not used by the terrain")
        lines.append(f"{path.name}: <{tag}> dropped, {len(at)} x (line{'s' if len(at) > 1 else ''} "
                     f"{shown}): {note}")
    return tuple(lines)


def _num(path: Path, elem: ET.Element, what: str, key: str) -> float:
    raw = elem.get(key)
    if raw is None:
        raise OpenDriveError(f"{path}: {what}: attribute '{key}' missing")
    try:
        value = float(raw)
    except ValueError:
        raise OpenDriveError(f"{path}: {what}: attribute '{key}'={raw!r} is not a number") from None
    if not math.isfinite(value):
        raise OpenDriveError(f"{path}: {what}: attribute '{key}'={raw!r} is not finite")
    return value


def _cubics(path: Path, parent: ET.Element | None, tag: str, what: str, s_key: str = "s"
            ) -> list[Cubic]:
    if parent is None:
        return []
    pieces = []
    for k, e in enumerate(parent.findall(tag)):
        where = f"{what} <{tag}> #{k}"
        pieces.append(Cubic(*(_num(path, e, where, key) for key in (s_key, "a", "b", "c", "d"))))
    return pieces


def load_opendrive(path: str | Path) -> OpenDrive:
    """Read an ``.xodr`` file (module docstring); ``OpenDriveError`` names file and
    element."""
    path = Path(path)
    if not path.is_file():
        raise OpenDriveError(f"{path}: no such file")
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise OpenDriveError(f"{path}: unreadable XML ({exc})") from None
    if root.tag != "OpenDRIVE":
        raise OpenDriveError(f"{path}: root element <{root.tag}>, expected <OpenDRIVE>")
    roads = []
    for road_el in root.findall("road"):
        rid = road_el.get("id", "?")
        what = f"road {rid}"
        plan = road_el.find("planView")
        if plan is None:
            raise OpenDriveError(f"{path}: {what}: no <planView>")
        geometries = []
        for k, g in enumerate(plan.findall("geometry")):
            gwhat = f"{what} <geometry> #{k}"
            base = [_num(path, g, gwhat, key) for key in ("s", "x", "y", "hdg", "length")]
            if len(g) != 1 or g[0].tag not in GEOMETRY_KINDS:
                kinds = [c.tag for c in g]
                raise OpenDriveError(f"{path}: {gwhat}: unknown geometry {kinds} (supported: "
                                     f"{', '.join(GEOMETRY_KINDS)})")
            shape = g[0]
            params: dict[str, float | str] = {}
            keys = {"line": (), "arc": ("curvature",), "spiral": ("curvStart", "curvEnd"),
                    "poly3": ("a", "b", "c", "d"),
                    "paramPoly3": tuple(f"{c}{a}" for a in "UV" for c in "abcd")}[shape.tag]
            for key in keys:
                params[key] = _num(path, shape, f"{gwhat} <{shape.tag}>", key)
            if shape.tag == "paramPoly3":
                p_range = shape.get("pRange", "normalized")
                if p_range not in ("arcLength", "normalized"):
                    raise OpenDriveError(f"{path}: {gwhat} <paramPoly3>: pRange {p_range!r}")
                params["pRange"] = p_range
            if not base[4] > 0.0:
                raise OpenDriveError(f"{path}: {gwhat}: length must be > 0")
            geometries.append(Geometry(*base, kind=shape.tag, params=params))
        if not geometries:
            raise OpenDriveError(f"{path}: {what}: <planView> has no <geometry>")
        elevation = _cubics(path, road_el.find("elevationProfile"), "elevation", what)
        superelevation = _cubics(path, road_el.find("lateralProfile"), "superelevation", what)
        sections = []
        lanes_el = road_el.find("lanes")
        for k, sec in enumerate([] if lanes_el is None else lanes_el.findall("laneSection")):
            swhat = f"{what} <laneSection> #{k}"
            s0 = _num(path, sec, swhat, "s")
            lanes = []
            for side in ("left", "center", "right"):
                side_el = sec.find(side)
                for lane in [] if side_el is None else side_el.findall("lane"):
                    lwhat = f"{swhat} <{side}> lane {lane.get('id')}"
                    try:
                        lane_id = int(lane.get("id", ""))
                    except ValueError:
                        raise OpenDriveError(f"{path}: {lwhat}: id is not an integer") from None
                    if (side == "left") != (lane_id > 0) and side != "center":
                        raise OpenDriveError(f"{path}: {lwhat}: id on the wrong side")
                    widths = _cubics(path, lane, "width", lwhat, s_key="sOffset")
                    if side != "center" and not widths:
                        raise OpenDriveError(f"{path}: {lwhat}: no <width>")
                    marks = []
                    for j, m in enumerate(lane.findall("roadMark")):
                        mwhat = f"{lwhat} <roadMark> #{j}"
                        marks.append(RoadMark(
                            _num(path, m, mwhat, "sOffset"), m.get("type", "none"),
                            m.get("color", "standard"),
                            _num(path, m, mwhat, "width") if "width" in m.attrib else 0.12))
                    lanes.append(Lane(lane_id, lane.get("type", "none"), widths, marks))
            if not any(lane.id != 0 for lane in lanes):
                raise OpenDriveError(f"{path}: {swhat}: no lanes")
            sections.append(LaneSection(s0, lanes))
        rule = road_el.get("rule", "RHT")
        if rule not in ("RHT", "LHT"):
            raise OpenDriveError(f"{path}: {what}: rule {rule!r} (expected RHT or LHT)")
        roads.append(Road(rid, _num(path, road_el, what, "length"), geometries, elevation,
                          superelevation, sections, rule))
    if not roads:
        raise OpenDriveError(f"{path}: no <road>")
    return OpenDrive(path, roads, dropped_elements(path, path.read_bytes()))


def _section_at(road: Road, s: float) -> LaneSection | None:
    section = None
    for sec in road.lane_sections:
        if sec.s <= s + 1e-9:
            section = sec
    return section


def road_extent(road: Road, s: float) -> tuple[float, float]:
    """Lateral extent ``(t_right <= 0, t_left >= 0)`` of the road's lanes at ``s``."""
    right, left = road_extents(road, np.array([float(s)]))
    return float(right[0]), float(left[0])


def road_extents(road: Road, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``road_extent`` at every ``s`` (vectorised): the sums of the lane widths (each
    clamped at 0; a width profile is 0 before its first piece) of the lane section at
    ``s``."""
    s = np.asarray(s, dtype=np.float64)
    right = np.zeros_like(s)
    left = np.zeros_like(s)
    if not road.lane_sections:
        return right, left
    starts = np.array([sec.s for sec in road.lane_sections])
    which = np.searchsorted(starts, s + 1e-9, side="right") - 1
    for k, sec in enumerate(road.lane_sections):
        sel = which == k
        if not sel.any():
            continue
        ds = s[sel] - sec.s
        for lane in sec.lanes:
            if lane.id == 0 or not lane.widths:
                continue
            width = np.where(ds + 1e-9 >= lane.widths[0].s,
                             np.maximum(0.0, profile_values(lane.widths, ds)), 0.0)
            if lane.id > 0:
                left[sel] += width
            else:
                right[sel] -= width
    return right, left


START_KEYS: dict[str, tuple[str, str]] = {
    "road": ("-", "id of a road of the scene's OpenDRIVE terrain (`terrain: {kind: "
                  "opendrive}`), as written in the file"),
    "s": ("m", "distance along the road's reference line, 0 .. the road's length"),
    "lane": ("-", "lane id at `s`: negative right of the reference line, positive left, "
                  "not 0"),
}
"""The keys of a start by road, s and lane (a scene's ``start:``, ``reset``'s ``lane``):
the car at rest on the lane's centre, heading along its direction of travel, on the
surface (``lane_start``). One table for the validation and the docs."""


class LaneStartError(ValueError):
    """A start by road, s and lane that the roads do not have; ``key`` names which."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def lane_start(od: OpenDrive, road_id: str, s: float, lane_id: int
               ) -> tuple[float, float, float]:
    """World ``(x, y, yaw)`` of the centre of lane ``lane_id`` of road ``road_id`` at
    ``s``, heading along the lane's direction of travel (right-hand traffic, ``rule="RHT"``,
    the default: the right lanes, ids < 0, travel along +s, the left lanes against it;
    ``LHT`` the other way round). The centre is at ``t`` half the lane's width beyond the
    lanes between it and the reference line, placed horizontally as ``rasterise`` places
    the surface (``t cos(superelevation)`` across the heading). ``LaneStartError`` (its
    ``key`` one of ``road``, ``s``, ``lane``) when the road, ``s`` or the lane does not
    exist there."""
    roads = {road.id: road for road in od.roads}
    road = roads.get(str(road_id))
    if road is None:
        raise LaneStartError("road", f"no road {road_id!r} in {od.path.name} (roads: "
                                     f"{', '.join(roads)})")
    if not 0.0 <= s <= road.length:
        raise LaneStartError("s", f"s = {s} m is off road {road.id} (0 .. {road.length} m)")
    sec = _section_at(road, s)
    widths = {} if sec is None else {
        lane.id: max(0.0, profile_at(lane.widths, s - sec.s)) if lane.widths
        and lane.widths[0].s <= s - sec.s + 1e-9 else 0.0 for lane in sec.lanes if lane.id != 0}
    if lane_id == 0 or lane_id not in widths or widths[lane_id] <= 0.0:
        have = sorted(k for k, w in widths.items() if w > 0.0)
        raise LaneStartError("lane", f"road {road.id} has no lane {lane_id} at s = {s} m "
                                     f"(lanes there: {have})")
    side = 1 if lane_id > 0 else -1
    inner = sum(w for k, w in widths.items() if k * side > 0 and abs(k) < abs(lane_id))
    t = side * (inner + 0.5 * widths[lane_id])
    ref_x, ref_y, hdg = road.reference(s)
    roll = profile_at(road.superelevation, s)
    lateral = t * math.cos(roll)
    along_s = (lane_id < 0) == (road.rule == "RHT")
    yaw = hdg if along_s else hdg + math.pi
    yaw = (yaw + math.pi) % (2.0 * math.pi) - math.pi
    return ref_x - math.sin(hdg) * lateral, ref_y + math.cos(hdg) * lateral, yaw


@nb.njit(cache=True)
def _scatter_cross_sections(ref_x: np.ndarray, ref_y: np.ndarray, ref_hdg: np.ndarray,
                            elev: np.ndarray, slope: np.ndarray, roll: np.ndarray,
                            t_right: np.ndarray, t_left: np.ndarray, margin_m: float,
                            step_m: float, x0: float, y0: float, cell_m: float,
                            heights: np.ndarray, best_d2: np.ndarray) -> None:
    """One road's cross-sections into the grid (``rasterise``): the samples every
    ``step_m`` across each cross-section, from ``margin_m`` beyond the right edge to
    ``margin_m`` beyond the left; each grid point keeps the sample nearest to it (the
    first of equals), moved to it along the surface's local slope. ``heights`` and
    ``best_d2`` (float64[ny, nx], NaN and inf where nothing landed yet) are updated."""
    ny, nx = heights.shape
    for n in range(ref_x.size):
        c = np.cos(ref_hdg[n])
        sn = np.sin(ref_hdg[n])
        cos_roll = np.cos(roll[n])
        sin_roll = np.sin(roll[n])
        tan_roll = np.tan(roll[n])
        t_start = t_right[n] - margin_m
        n_t = int(np.ceil((t_left[n] + margin_m + 0.5 * step_m - t_start) / step_m))
        for k in range(n_t):
            t = t_start + k * step_m
            t_surface = min(max(t, t_right[n]), t_left[n])  # the edges extend flat beyond
            lateral = t * cos_roll
            px = ref_x[n] - sn * lateral
            py = ref_y[n] + c * lateral
            pz = elev[n] + t_surface * sin_roll
            # gradient: dz/ds along the heading, the bank across it (horizontal axes)
            bank = tan_roll if t_right[n] <= t <= t_left[n] else 0.0
            gx = slope[n] * c - bank * sn
            gy = slope[n] * sn + bank * c
            ci = int(np.rint((px - x0) / cell_m))
            cj = int(np.rint((py - y0) / cell_m))
            if ci < 0 or cj < 0 or ci >= nx or cj >= ny:
                continue
            dx = x0 + ci * cell_m - px
            dy = y0 + cj * cell_m - py
            d2 = dx * dx + dy * dy
            if d2 < best_d2[cj, ci]:
                best_d2[cj, ci] = d2
                heights[cj, ci] = pz + gx * dx + gy * dy


def rasterise(od: OpenDrive, cell_m: float, margin_m: float = 20.0
              ) -> tuple[np.ndarray, float, float]:
    """The road surface as a height grid: ``(heights[j, i], x0, y0)`` with cells of
    ``cell_m``, reaching ``margin_m`` beyond the outer lanes' edges.

    The surface point at ``(s, t)`` is the reference line's point moved ``t cos(roll)``
    across it horizontally and ``t sin(roll)`` up from the elevation (roll: the
    superelevation). Each cell the lanes cover takes the surface sample nearest to its
    centre, moved to the centre along the surface's local slope (samples every quarter of
    a cell, along and across the road). The standard describes no ground off the lanes:
    every other cell takes the smoothest ground through the lanes' edges, a harmonic
    interpolation (``_fill_harmonic``: continuous, no step where the standard has none;
    flat, with no slope across it, at the grid's border). The reference line and profiles
    are sampled with numpy, the cross-sections are scattered into the grid by a compiled
    loop (``_scatter_cross_sections``): a kilometre of road loads in well under a
    second."""
    step = 0.25 * cell_m
    sections = []
    lo_x = lo_y = math.inf
    hi_x = hi_y = -math.inf
    for road in od.roads:
        s_all = np.arange(0.0, road.length + 0.5 * step, step)
        s_all[-1] = min(s_all[-1], road.length)
        ref_x, ref_y, ref_h = np.empty_like(s_all), np.empty_like(s_all), np.empty_like(s_all)
        starts = np.array([g.s for g in road.geometries])
        which = np.clip(np.searchsorted(starts, s_all + 1e-9, side="right") - 1, 0,
                        len(starts) - 1)
        for k, geo in enumerate(road.geometries):
            sel = which == k
            if sel.any():
                ds = np.clip(s_all[sel] - geo.s, 0.0, geo.length)
                ref_x[sel], ref_y[sel], ref_h[sel] = geo.points(ds)
        elev = profile_values(road.elevation, s_all)
        slope = (profile_values(road.elevation, s_all + 1e-3)
                 - profile_values(road.elevation, s_all - 1e-3)) / 2e-3
        rolls = profile_values(road.superelevation, s_all)
        t_right, t_left = road_extents(road, s_all)
        sections.append((ref_x, ref_y, ref_h, elev, slope, rolls, t_right, t_left))
        # the cross-sections are straight in the horizontal plane: their ends bound them
        for t_end in (t_right - margin_m, t_left + margin_m):
            lateral = t_end * np.cos(rolls)
            ends_x = ref_x - np.sin(ref_h) * lateral
            ends_y = ref_y + np.cos(ref_h) * lateral
            lo_x, hi_x = min(lo_x, ends_x.min()), max(hi_x, ends_x.max())
            lo_y, hi_y = min(lo_y, ends_y.min()), max(hi_y, ends_y.max())
    x0 = math.floor(lo_x / cell_m) * cell_m
    y0 = math.floor(lo_y / cell_m) * cell_m
    nx = int(math.ceil((hi_x - x0) / cell_m)) + 1
    ny = int(math.ceil((hi_y - y0) / cell_m)) + 1
    grid = np.full((ny, nx), np.nan)
    best_d2 = np.full((ny, nx), np.inf)
    for arrays in sections:
        # the lanes only (no margin): the ground beyond them is filled below
        _scatter_cross_sections(*arrays, 0.0, step, x0, y0, cell_m, grid, best_d2)
    _fill_harmonic(grid)
    return grid, x0, y0


FILL_SWEEPS = 60
"""Gauss-Seidel sweeps of ``_fill_harmonic`` on each level of its pyramid (the coarsest
level relaxes until it has converged)."""
FILL_COARSEST = 16
"""``_fill_harmonic`` stops coarsening at a level this small on its shorter side."""


@nb.njit(cache=True)
def _relax(h: np.ndarray, fixed: np.ndarray, sweeps: int, omega: float) -> float:
    """``sweeps`` Gauss-Seidel (over-relaxed by ``omega``) sweeps of Laplace's equation
    over the cells not ``fixed``, each the mean of its 2 to 4 neighbours (a border cell
    has fewer: no slope across the border); the largest change of the last sweep."""
    ny, nx = h.shape
    change = 0.0
    for sweep in range(sweeps):
        last = sweep == sweeps - 1
        for j in range(ny):
            up = max(j - 1, 0)
            down = min(j + 1, ny - 1)
            for i in range(nx):
                if fixed[j, i]:
                    continue
                # a neighbour beyond the border is the cell itself mirrored: no slope
                left = h[j, max(i - 1, 0)]
                right = h[j, min(i + 1, nx - 1)]
                delta = omega * (0.25 * (left + right + h[up, i] + h[down, i]) - h[j, i])
                h[j, i] += delta
                if last:
                    change = max(change, abs(delta))
    return change


def _coarser(grid: np.ndarray) -> np.ndarray:
    """The grid at twice the cell: each coarse cell the mean of the known (not NaN) cells
    of its 2 x 2 block, NaN if it has none."""
    ny, nx = grid.shape
    padded = np.full((ny + ny % 2, nx + nx % 2), np.nan)
    padded[:ny, :nx] = grid
    blocks = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2)
    known = ~np.isnan(blocks)
    count = known.sum(axis=(1, 3))
    total = np.where(known, blocks, 0.0).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _finer(coarse: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A filled coarse grid interpolated bilinearly onto the fine grid of ``shape`` (a
    fine cell ``j`` lies at coarse ``(j - 0.5) / 2``; clamped at the border)."""
    def axis(n_fine: int, n_coarse: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos = np.clip((np.arange(n_fine) - 0.5) / 2.0, 0.0, n_coarse - 1)
        lo = np.minimum(pos.astype(np.int64), max(n_coarse - 2, 0))
        hi = np.minimum(lo + 1, n_coarse - 1)
        return lo, hi, pos - lo

    j0, j1, ty = axis(shape[0], coarse.shape[0])
    i0, i1, tx = axis(shape[1], coarse.shape[1])
    top = coarse[j0][:, i0] * (1.0 - tx) + coarse[j0][:, i1] * tx
    bottom = coarse[j1][:, i0] * (1.0 - tx) + coarse[j1][:, i1] * tx
    return top * (1.0 - ty)[:, None] + bottom * ty[:, None]


def _fill_harmonic(grid: np.ndarray) -> None:
    """Fill the NaN cells (in place) with the harmonic interpolation of the others: the
    solution of Laplace's equation with the known cells fixed and no slope across the
    grid's border, the smoothest ground through them (continuous: no cliff, and no point
    of it higher or lower than the known cells around it). Solved coarse to fine: the
    grid's 2 x 2 means, recursively, filled and relaxed to convergence on the coarsest
    level, each finer level starting from the coarser one interpolated and relaxed
    ``FILL_SWEEPS`` times (a full multigrid pass: a second for millions of cells)."""
    unknown = np.isnan(grid)
    if unknown.all():
        raise OpenDriveError("rasterise: no road surface to extend")
    if not unknown.any():
        return
    if min(grid.shape) <= FILL_COARSEST:
        start = np.where(unknown, np.nanmean(grid), grid)
        for _ in range(200):  # converged: a change under a micrometre a sweep
            if _relax(start, ~unknown, 50, 1.9) < 1e-6:
                break
    else:
        coarse = _coarser(grid)
        _fill_harmonic(coarse)
        start = np.where(unknown, _finer(coarse, grid.shape), grid)
        _relax(start, ~unknown, FILL_SWEEPS, 1.9)
    grid[:] = start
