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
from dataclasses import dataclass, field
from pathlib import Path

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
class Lane:
    id: int
    type: str
    widths: list[Cubic]  # s = sOffset from the section start


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
                    lanes.append(Lane(lane_id, lane.get("type", "none"), widths))
            if not any(lane.id != 0 for lane in lanes):
                raise OpenDriveError(f"{path}: {swhat}: no lanes")
            sections.append(LaneSection(s0, lanes))
        roads.append(Road(rid, _num(path, road_el, what, "length"), geometries, elevation,
                          superelevation, sections))
    if not roads:
        raise OpenDriveError(f"{path}: no <road>")
    return OpenDrive(path, roads)
