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

Errors name the file, the line and the element (``OpenDriveError``, a ``ConfigError``:
``FILE:LINE: road 7 <geometry> #0 <poly3>: attribute 'c'=...``); a file that fails is not
kept in part. Every number is checked against ``XODR_BOUNDS`` as it is read (the cubics by
their values over their pieces), so nothing later overflows; the file is parsed as it is
read (expat: it gives each element's line, and no tree of a large file is kept).
"""

from __future__ import annotations

import array
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn
from xml.parsers import expat

import numba as nb
import numpy as np

from simserver.adapters.validate import (
    ConfigError,
    read_regular_chunks,
    report_progress,
    short_repr,
)

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


_PARAM_KEYS: dict[str, tuple[str, ...]] = {
    "line": (), "arc": ("curvature",), "spiral": ("curvStart", "curvEnd"),
    "poly3": ("a", "b", "c", "d"),
    "paramPoly3": tuple(f"{c}{a}" for a in "UV" for c in "abcd")}
"""The number attributes of each geometry kind, in the order ``GeometryArray`` keeps them."""
_P_RANGES = ("normalized", "arcLength")


class GeometryArray(Sequence[Geometry]):
    """A road's geometries kept as arrays, each :class:`Geometry` made when asked for.

    A road of a million geometries is 46 MB of arrays, not a million Python objects: the
    load worker's result is pickled as those arrays (written to its shared block,
    ``simserver.server.load_worker``) and unpickled in the server's tick in microseconds, where
    a list of objects took seconds."""

    def __init__(self, base: np.ndarray, kind: np.ndarray, p_range: np.ndarray,
                 param_index: np.ndarray, params: np.ndarray) -> None:
        self.base = base  # float64[n, 5]: s, x, y, hdg, length
        self.kind = kind  # int8[n]: index in GEOMETRY_KINDS
        self.p_range = p_range  # int8[n]: index in _P_RANGES (paramPoly3)
        self.param_index = param_index  # int32[n]: row of ``params``, -1 for a line
        self.params = params  # float64[m, 8]: the kind's numbers (_PARAM_KEYS order)

    @property
    def starts(self) -> np.ndarray:
        return self.base[:, 0]

    def __len__(self) -> int:
        return int(self.kind.size)

    def __getitem__(self, index):  # noqa: ANN001, ANN204 - int or slice, as a list
        if isinstance(index, slice):
            return [self[k] for k in range(*index.indices(len(self)))]
        k = int(index)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(index)
        kind = GEOMETRY_KINDS[int(self.kind[k])]
        params: dict[str, float | str] = _NO_PARAMS
        if self.param_index[k] >= 0:
            row = self.params[self.param_index[k]]
            params = {key: float(row[j]) for j, key in enumerate(_PARAM_KEYS[kind])}
            if kind == "paramPoly3":
                params["pRange"] = _P_RANGES[int(self.p_range[k])]
        return Geometry(*(float(v) for v in self.base[k]), kind=kind, params=params)


class _GeometryRows:
    """A road's geometries as the parser meets them (compact arrays, no objects)."""

    def __init__(self) -> None:
        self.base = array.array("d")
        self.kind = array.array("b")
        self.p_range = array.array("b")
        self.param_index = array.array("i")
        self.params = array.array("d")
        self.last_s = -math.inf

    def __len__(self) -> int:
        return len(self.kind)

    def add(self, base: list[float], kind: int, params: tuple[float, ...] = (),
            p_range: int = 0) -> None:
        self.base.extend(base)
        self.kind.append(kind)
        self.p_range.append(p_range)
        if params:
            self.param_index.append(len(self.params) // 8)
            self.params.extend(params + (0.0,) * (8 - len(params)))
        else:
            self.param_index.append(-1)
        self.last_s = base[0]

    def done(self) -> GeometryArray:
        return GeometryArray(np.frombuffer(self.base, np.float64).reshape(-1, 5).copy(),
                             np.frombuffer(self.kind, np.int8).copy(),
                             np.frombuffer(self.p_range, np.int8).copy(),
                             np.frombuffer(self.param_index, np.int32).copy(),
                             np.frombuffer(self.params, np.float64).reshape(-1, 8).copy())


@dataclass(frozen=True)
class Road:
    id: str
    length: float
    geometries: Sequence[Geometry]  # a GeometryArray when read from a file
    elevation: list[Cubic]
    superelevation: list[Cubic]
    lane_sections: list[LaneSection]
    rule: str = "RHT"  # traffic rule: RHT, the right lanes (t < 0) travel along +s; LHT

    def reference(self, s: float) -> tuple[float, float, float]:
        """World ``(x, y, heading)`` of the reference line at ``s``."""
        geos = self.geometries
        starts = geos.starts if isinstance(geos, GeometryArray) else np.array([g.s for g in geos])
        geo = geos[max(0, int(np.searchsorted(starts, s + 1e-9, side="right")) - 1)]
        return geo.point(min(max(s - geo.s, 0.0), geo.length))


@dataclass(frozen=True)
class OpenDrive:
    path: Path
    roads: list[Road]
    dropped: tuple[str, ...] = ()  # what the file has and the reader does not use
    # (``DroppedElements``): one line per element name, reported once when loaded


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


class DroppedElements:
    """The elements of an ``.xodr`` file that ``load_opendrive`` does not use, collected
    as the reader streams through it (``start`` and ``end`` of every element): objects,
    signals, lane heights, borders, offsets, junctions, ... (``READ_ELEMENTS``,
    ``UNUSED_WHOLE``, ``CONTAINERS``). A dropped element's own children are not listed
    again."""

    def __init__(self) -> None:
        self.found: dict[str, list[int]] = {}
        self._skip_depth = 0  # > 0: inside an element not read

    def start(self, tag: str, line: int) -> None:
        if self._skip_depth:
            self._skip_depth += 1
            return
        if tag in READ_ELEMENTS or tag in CONTAINERS:
            return
        if tag not in UNUSED_WHOLE:
            self.found.setdefault(tag, []).append(line)
        self._skip_depth = 1

    def end(self) -> None:
        if self._skip_depth:
            self._skip_depth -= 1

    def lines(self, path: Path) -> tuple[str, ...]:
        """One line per element name with the lines it is on (the first ten)."""
        out = []
        for tag, at in self.found.items():
            shown = ", ".join(str(n) for n in at[:10]) + (", ..." if len(at) > 10 else "")
            note = DROPPED_NOTES.get(tag, "not used by the terrain")
            out.append(f"{path.name}: <{tag}> dropped, {len(at)} x "
                       f"(line{'s' if len(at) > 1 else ''} {shown}): {note}")
        return tuple(out)


MAX_XODR_BYTES = 256 << 20
"""Largest ``.xodr`` file read (256 MiB: a road of a million geometries is about 90 MB)."""
_READ_CHUNK_BYTES = 1 << 20  # the file is parsed as it is read, a MiB at a time
MAX_LENGTH_M = 1e6
MAX_COORD_M = 1e7


@dataclass(frozen=True)
class XodrBound:
    """The range an ``.xodr`` number must lie in: ``lo`` .. ``hi`` in ``unit``."""

    applies_to: str
    unit: str
    lo: float
    hi: float
    why: str


XODR_BOUNDS: dict[str, XodrBound] = {
    "s": XodrBound("`s` of a `<geometry>`, `<elevation>`, `<superelevation>`, "
                   "`<laneSection>`; `sOffset` of a `<width>`, `<roadMark>`; "
                   "a `<road>`'s `length`", "m", 0.0, MAX_LENGTH_M,
                   "in order along the road (each at or after the one before)"),
    "length": XodrBound("`length` of a `<geometry>`", "m", 0.0, MAX_LENGTH_M,
                        "more than 0"),
    "xy": XodrBound("`x`, `y` of a `<geometry>`", "m", -MAX_COORD_M, MAX_COORD_M,
                    "as a height map's `origin_m`"),
    "hdg": XodrBound("`hdg` of a `<geometry>`", "rad", -1e3, 1e3,
                     "any turn, unwrapped or not"),
    "curvature": XodrBound("`curvature` of an `<arc>`, `curvStart`, `curvEnd` of a "
                           "`<spiral>`", "1/m", -1e3, 1e3, "a radius of 1 mm or more"),
    "curve": XodrBound("`<poly3>` `v(u)`, `<paramPoly3>` `u(p)` and `v(p)`, over the "
                       "piece", "m", -MAX_COORD_M, MAX_COORD_M,
                       "the cubic's largest value over its range, not each coefficient"),
    "elevation": XodrBound("`<elevation>` height over its piece", "m", -1e4, 1e4,
                           "the cubic's largest value up to the next piece or the road's end"),
    "superelevation": XodrBound("`<superelevation>` roll over its piece", "rad",
                                -math.pi / 2, math.pi / 2, "as for the elevation"),
    "width": XodrBound("`<width>` of a lane over its piece", "m", -1e3, 1e3,
                       "as for the elevation (a negative width counts as 0)"),
    "mark_width": XodrBound("`width` of a `<roadMark>`", "m", 0.0, 10.0, "drawn only"),
}
"""Every number an ``.xodr`` file gives is finite, normal and within these bounds, or the
file is refused with an error naming the element, its line and the attribute (one source:
the reader and docs/configuration.md). The cubics are checked by their values over their
pieces, so a file cannot make a height, an angle or a coordinate overflow later."""


class _Piece:
    """A cubic as read, with where it came from (checked once the road's pieces and spans
    are known)."""

    __slots__ = ("coef", "line", "what")

    def __init__(self, coef: tuple[float, float, float, float, float], line: int,
                 what: str) -> None:
        self.coef = coef
        self.line = line
        self.what = what


def cubic_peak(a: float, b: float, c: float, d: float, span: float) -> float:
    """The largest ``|a + b x + c x^2 + d x^3|`` for ``x`` in ``[0, span]`` (at an end or
    where the derivative vanishes); ``inf`` when it overflows."""
    xs = [0.0, span] if span > 0.0 else [0.0]
    if d != 0.0:
        disc = c * c - 3.0 * d * b
        if disc >= 0.0:
            root = math.sqrt(disc)
            xs += [(-c + root) / (3.0 * d), (-c - root) / (3.0 * d)]
    elif c != 0.0:
        xs.append(-b / (2.0 * c))
    peak = 0.0
    for x in xs:
        if 0.0 <= x <= max(span, 0.0):
            value = abs(a + x * (b + x * (c + x * d)))
            if not value <= math.inf or value == math.inf:  # NaN from inf - inf: overflow
                return math.inf
            peak = max(peak, value)
    return peak


class _XodrReader:
    """Builds an :class:`OpenDrive` from the parser's events as the file is read (expat:
    no tree is kept, every element's line is known)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.parser = expat.ParserCreate()
        self.parser.StartElementHandler = self._start
        self.parser.EndElementHandler = self._end
        self.parser.EntityDeclHandler = self._entity
        self.stack: list[str] = []
        self.roads: list[Road] = []
        self.road: dict[str, Any] | None = None
        self.geometry: tuple[list[float], int, str, list[tuple[str, dict[str, str], int]]] \
            | None = None
        self.section: dict[str, Any] | None = None
        self.lane: dict[str, Any] | None = None
        self.side = ""
        self.dropped = DroppedElements()  # what the file has and the terrain does not use

    # ------------------------------------------------------------------ helpers
    def fail(self, what: str, message: str, line: int | None = None) -> NoReturn:
        line = self.parser.CurrentLineNumber if line is None else line
        raise OpenDriveError(f"{self.path}:{line}: {what}: {message}")

    def num(self, attrs: dict[str, str], what: str, key: str, bound: str,
            line: int | None = None) -> float:
        """Attribute ``key``: a finite, normal number within ``XODR_BOUNDS[bound]``."""
        value = self.num_any(attrs, what, key, line)
        if bound in ("length", "curvature") and 0.0 < abs(value) < sys.float_info.min:
            self.fail(what, f"attribute '{key}'={short_repr(attrs[key])} is subnormal (use 0 "
                            "or a normal number: it is divided by)", line)
        b = XODR_BOUNDS[bound]
        if not b.lo <= value <= b.hi:
            self.fail(what, f"attribute '{key}'={short_repr(attrs[key])} is outside "
                            f"[{b.lo:g}, {b.hi:g}] {b.unit}", line)
        return value

    def cubic(self, attrs: dict[str, str], what: str, s_key: str) -> _Piece:
        s = self.num(attrs, what, s_key, "s")
        a, b, c, d = (self.num_any(attrs, what, key) for key in "abcd")
        return _Piece((s, a, b, c, d), self.parser.CurrentLineNumber, what)

    def num_any(self, attrs: dict[str, str], what: str, key: str,
                line: int | None = None) -> float:
        """Attribute ``key``: a finite, normal number (a cubic's coefficient: bounded by
        the cubic's values over its piece, ``check_peak``)."""
        raw = attrs.get(key)
        if raw is None:
            self.fail(what, f"attribute '{key}' missing", line)
        try:
            value = float(raw)
        except ValueError:
            self.fail(what, f"attribute '{key}'={short_repr(raw)} is not a number", line)
        if not math.isfinite(value):
            self.fail(what, f"attribute '{key}'={short_repr(raw)} is not finite", line)
        return value

    def check_peak(self, what: str, line: int, keys: str, coef: tuple[float, ...],
                   span: float, bound: str) -> None:
        """The cubic ``coef`` (a, b, c, d) stays within ``XODR_BOUNDS[bound]`` over
        ``[0, span]``; else an error naming the largest term's attribute."""
        b = XODR_BOUNDS[bound]
        limit = min(-b.lo, b.hi)
        peak = cubic_peak(*coef, span)
        if peak <= limit:
            return
        terms = [abs(k) * max(span, 1.0) ** n for n, k in enumerate(coef)]
        worst = keys.split(",")[max(range(4), key=lambda n: terms[n])]
        self.fail(what, f"attribute '{worst}'={coef[keys.split(',').index(worst)]:g}: the "
                        f"cubic reaches {peak:g} {b.unit} within {span:g} of its start, "
                        f"outside [{b.lo:g}, {b.hi:g}] {b.unit}", line)

    def check_order(self, pieces: list[_Piece]) -> None:
        for prev, piece in zip(pieces, pieces[1:], strict=False):
            if piece.coef[0] < prev.coef[0]:
                self.fail(piece.what, f"s={piece.coef[0]:g} comes before the previous "
                                      f"piece's s={prev.coef[0]:g} (pieces in order along "
                                      "the road)", piece.line)

    def check_profile(self, pieces: list[_Piece], end: float, bound: str,
                      keys: str = "a,b,c,d") -> list[Cubic]:
        """Pieces in order, each within ``bound`` up to the next one (or ``end``)."""
        self.check_order(pieces)
        for k, piece in enumerate(pieces):
            stop = pieces[k + 1].coef[0] if k + 1 < len(pieces) else end
            self.check_peak(piece.what, piece.line, keys, piece.coef[1:],
                            stop - piece.coef[0], bound)
        return [Cubic(*p.coef) for p in pieces]

    # ------------------------------------------------------------------ events
    def _entity(self, *_: Any) -> None:
        self.fail("<!DOCTYPE>", "declares an entity (an OpenDRIVE file has none)")

    def _start(self, name: str, attrs: dict[str, str]) -> None:
        self.dropped.start(name, self.parser.CurrentLineNumber)
        stack = self.stack
        depth = len(stack)
        parent = stack[-1] if stack else ""
        stack.append(name)
        if depth == 0:
            if name != "OpenDRIVE":
                raise OpenDriveError(f"{self.path}: root element <{name}>, expected "
                                     "<OpenDRIVE>")
        elif depth == 1:
            if name == "road":
                self._start_road(attrs)
        elif self.road is None:
            return
        elif depth == 2:
            if name in ("planView", "elevationProfile", "lateralProfile", "lanes"):
                self.road["seen"].add(name)
        elif depth == 3:
            road = self.road
            if parent == "planView" and name == "geometry":
                self.geometry = (self._geometry_base(attrs), self.parser.CurrentLineNumber,
                                 None, [])
            elif parent == "elevationProfile" and name == "elevation":
                road["elevation"].append(self.cubic(
                    attrs, f"{road['what']} <elevation> #{len(road['elevation'])}", "s"))
            elif parent == "lateralProfile" and name == "superelevation":
                road["superelevation"].append(self.cubic(
                    attrs, f"{road['what']} <superelevation> #{len(road['superelevation'])}",
                    "s"))
            elif parent == "lanes" and name == "laneSection":
                what = f"{road['what']} <laneSection> #{len(road['sections'])}"
                self.section = {"what": what, "s": self.num(attrs, what, "s", "s"),
                                "line": self.parser.CurrentLineNumber, "lanes": []}
        elif depth == 4:
            if parent == "geometry" and self.geometry is not None:
                self.geometry[3].append((name, attrs, self.parser.CurrentLineNumber))
            elif parent == "laneSection" and name in _SIDES:
                self.side = name
        elif depth == 5:
            if name == "lane" and self.section is not None and self.side:
                what = f"{self.section['what']} <{self.side}> lane {attrs.get('id')}"
                try:
                    lane_id = int(attrs.get("id", ""))
                except ValueError:
                    self.fail(what, "id is not an integer")
                if not -1000 <= lane_id <= 1000:
                    self.fail(what, "id outside -1000 .. 1000")
                if (self.side == "left") != (lane_id > 0) and self.side != "center":
                    self.fail(what, "id on the wrong side")
                self.lane = {"what": what, "id": lane_id, "type": attrs.get("type", "none"),
                             "widths": [], "marks": [], "line": self.parser.CurrentLineNumber}
        elif depth == 6 and self.lane is not None and parent == "lane":
            lane = self.lane
            if name == "width":
                lane["widths"].append(self.cubic(
                    attrs, f"{lane['what']} <width> #{len(lane['widths'])}", "sOffset"))
            elif name == "roadMark":
                what = f"{lane['what']} <roadMark> #{len(lane['marks'])}"
                lane["marks"].append(RoadMark(
                    self.num(attrs, what, "sOffset", "s"), attrs.get("type", "none"),
                    attrs.get("color", "standard"),
                    self.num(attrs, what, "width", "mark_width") if "width" in attrs
                    else 0.12))

    def _start_road(self, attrs: dict[str, str]) -> None:
        rid = attrs.get("id", "?")
        what = f"road {rid}"
        rule = attrs.get("rule", "RHT")
        if rule not in ("RHT", "LHT"):
            self.fail(what, f"rule {short_repr(rule)} (expected RHT or LHT)")
        self.road = {"id": rid, "what": what, "line": self.parser.CurrentLineNumber,
                     "length": self.num(attrs, what, "length", "s"), "rule": rule,
                     "geometries": _GeometryRows(), "elevation": [], "superelevation": [],
                     "sections": [], "seen": set()}

    def _end(self, name: str) -> None:
        self.dropped.end()
        stack = self.stack
        stack.pop()
        depth = len(stack)
        if self.road is None:
            return
        if depth == 1 and name == "road":
            self._end_road()
        elif depth == 3 and name == "geometry" and self.geometry is not None:
            self._end_geometry()
        elif depth == 3 and name == "laneSection" and self.section is not None:
            sec = self.section
            if not any(lane.id != 0 for _, lane, _ in sec["lanes"]):
                self.fail(sec["what"], "no lanes", sec["line"])
            self.road["sections"].append(sec)
            self.section = None
        elif depth == 4 and name in _SIDES:
            self.side = ""
        elif depth == 5 and name == "lane" and self.lane is not None:
            lane = self.lane
            if self.side != "center" and not lane["widths"]:
                self.fail(lane["what"], "no <width>", lane["line"])
            self.check_order(lane["widths"])
            self.section["lanes"].append((_SIDES.index(self.side), Lane(
                lane["id"], lane["type"], [], lane["marks"]), lane["widths"]))
            self.lane = None

    def _geometry_base(self, attrs: dict[str, str]) -> list[float]:
        """``s, x, y, hdg, length`` of a ``<geometry>`` (the common case checked in one go:
        a road may have a million of them; any doubt and each is checked with its error)."""
        try:
            base = [float(attrs["s"]), float(attrs["x"]), float(attrs["y"]),
                    float(attrs["hdg"]), float(attrs["length"])]
            s, x, y, hdg, length = base
            if (0.0 <= s <= MAX_LENGTH_M and -MAX_COORD_M <= x <= MAX_COORD_M
                    and -MAX_COORD_M <= y <= MAX_COORD_M and -1e3 <= hdg <= 1e3
                    and sys.float_info.min <= length <= MAX_LENGTH_M):
                return base
        except (KeyError, ValueError):
            pass
        what = self._geometry_what()
        base = [self.num(attrs, what, "s", "s"), self.num(attrs, what, "x", "xy"),
                self.num(attrs, what, "y", "xy"), self.num(attrs, what, "hdg", "hdg"),
                self.num(attrs, what, "length", "length")]
        if not base[4] > 0.0:
            self.fail(what, "length must be > 0")
        return base

    def _geometry_what(self) -> str:
        return f"{self.road['what']} <geometry> #{len(self.road['geometries'])}"

    def _end_geometry(self) -> None:
        base, line, _, children = self.geometry
        self.geometry = None
        rows = self.road["geometries"]
        if len(children) == 1 and children[0][0] == "line" and base[0] >= rows.last_s:
            rows.add(base, 0)
            self._added(rows)
            return
        what = self._geometry_what()
        if len(children) != 1 or children[0][0] not in GEOMETRY_KINDS:
            kinds = [c[0] for c in children]
            self.fail(what, f"unknown geometry {kinds} (supported: "
                            f"{', '.join(GEOMETRY_KINDS)})", line)
        kind, attrs, shape_line = children[0]
        swhat = f"{what} <{kind}>"
        length = base[4]
        params: dict[str, float | str]
        if kind == "line":
            params = _NO_PARAMS
        elif kind == "arc":
            params = {"curvature": self.num(attrs, swhat, "curvature", "curvature",
                                             shape_line)}
        elif kind == "spiral":
            params = {k: self.num(attrs, swhat, k, "curvature", shape_line)
                      for k in ("curvStart", "curvEnd")}
        elif kind == "poly3":
            params = {k: self.num_any(attrs, swhat, k, shape_line) for k in "abcd"}
            self.check_peak(swhat, shape_line, "a,b,c,d",
                            tuple(float(params[k]) for k in "abcd"), length, "curve")
        else:
            p_range = attrs.get("pRange", "normalized")
            if p_range not in ("arcLength", "normalized"):
                self.fail(swhat, f"pRange {short_repr(p_range)}", shape_line)
            params = {f"{c}{a}": self.num_any(attrs, swhat, f"{c}{a}", shape_line)
                      for a in "UV" for c in "abcd"}
            span = length if p_range == "arcLength" else 1.0
            for axis in "UV":
                keys = ",".join(f"{c}{axis}" for c in "abcd")
                self.check_peak(swhat, shape_line, keys,
                                tuple(float(params[f"{c}{axis}"]) for c in "abcd"), span,
                                "curve")
            params["pRange"] = p_range
        if base[0] < rows.last_s:
            self.fail(what, f"s={base[0]:g} comes before the previous geometry's "
                            f"s={rows.last_s:g} (geometries in order along the road)", line)
        rows.add(base, GEOMETRY_KINDS.index(kind),
                 tuple(float(params[k]) for k in _PARAM_KEYS[kind]),
                 _P_RANGES.index(str(params.get("pRange", "normalized"))))
        self._added(rows)

    def _added(self, rows: _GeometryRows) -> None:
        if len(rows) % 65536 == 0:
            report_progress(f"{self.path.name}: {len(rows)} geometries")

    def _end_road(self) -> None:
        road = self.road
        self.road = None
        what = road["what"]
        if "planView" not in road["seen"]:
            self.fail(what, "no <planView>", road["line"])
        if not road["geometries"]:
            self.fail(what, "<planView> has no <geometry>", road["line"])
        length = road["length"]
        elevation = self.check_profile(road["elevation"], length, "elevation")
        superelevation = self.check_profile(road["superelevation"], length, "superelevation")
        sections = road["sections"]
        for prev, sec in zip(sections, sections[1:], strict=False):
            if sec["s"] < prev["s"]:
                self.fail(sec["what"], f"s={sec['s']:g} comes before the previous section's "
                                       f"s={prev['s']:g}", sec["line"])
        built = []
        for k, sec in enumerate(sections):
            sec_end = (sections[k + 1]["s"] if k + 1 < len(sections) else length) - sec["s"]
            lanes = [Lane(lane.id, lane.type, self.check_profile(widths, sec_end, "width"),
                          lane.marks)
                     for _, lane, widths in sorted(sec["lanes"], key=lambda e: e[0])]
            built.append(LaneSection(sec["s"], lanes))
        self.roads.append(Road(road["id"], length, road["geometries"].done(), elevation,
                               superelevation, built, road["rule"]))

    # ------------------------------------------------------------------ reading
    def read(self) -> OpenDrive:
        path = self.path
        try:
            size = max(path.stat().st_size, 1)
            done = 0
            for chunk in read_regular_chunks(path, MAX_XODR_BYTES, _READ_CHUNK_BYTES,
                                             OpenDriveError,
                                             "the most an .xodr file may have"):
                done += len(chunk)
                self.parser.Parse(chunk, False)
                report_progress(f"{path.name}: {done >> 20} of {size >> 20} MiB read")
            self.parser.Parse(b"", True)
        except expat.ExpatError as exc:
            raise OpenDriveError(f"{path}:{exc.lineno}: unreadable XML "
                                 f"({expat.ErrorString(exc.code)}, column "
                                 f"{exc.offset + 1})") from None
        except OSError as exc:
            raise OpenDriveError(f"{path}: cannot read: {exc.strerror or exc}") from None
        except RecursionError:
            raise OpenDriveError(f"{path}: elements nested too deeply") from None
        if not self.roads:
            raise OpenDriveError(f"{path}: no <road>")
        return OpenDrive(path, self.roads, self.dropped.lines(path))


_NO_PARAMS: dict[str, float | str] = {}  # shared by every line (a million lines: no dicts)
_SIDES = ("left", "center", "right")  # a section's lanes in this order, as before


def load_opendrive(path: str | Path) -> OpenDrive:
    """Read an ``.xodr`` file (module docstring); ``OpenDriveError`` names the file, the
    line and the element (and the attribute), numbers checked against ``XODR_BOUNDS``.
    The file is parsed as it is read (expat, no tree kept): at most ``MAX_XODR_BYTES``."""
    path = Path(path)
    if not path.is_file():
        raise OpenDriveError(f"{path}: no such file")
    info = path.stat()
    key = (str(path.resolve()), info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns)
    if _last_read[0] == key:  # a scene reads its file twice: the terrain, the lane start
        return _last_read[1]
    od = _XodrReader(path).read()
    _last_read[:] = [key, od]
    return od


_last_read: list = [None, None]  # the last file read, by path and version, and its roads


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


MAX_RASTER_SAMPLES = 8_000_000
"""Most reference-line samples ``rasterise`` takes over all roads (every quarter of a cell:
1 000 km of road at the default 0.5 m cells; each costs about 100 bytes while loading)."""
SCATTER_CHUNK = 20_000
"""Cross-sections scattered per call of the compiled loop (a progress report after each:
tens of milliseconds apart)."""
MAX_RASTER_CELLS = 40_000_000
"""Most cells of a rasterised grid (320 MB of heights: a 6 x 6 km area at 1 m cells)."""


def reference_points(road: Road, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World ``(x, y, heading)`` of the reference line at every ``s`` of an increasing
    array: the lines and arcs of all geometries at once, each other piece on its own
    samples (a road of a million geometries takes as long as one of a few)."""
    geos = road.geometries
    if not isinstance(geos, GeometryArray):
        rows = _GeometryRows()
        for g in geos:
            rows.add([g.s, g.x, g.y, g.hdg, g.length], GEOMETRY_KINDS.index(g.kind),
                     tuple(float(g.params[k]) for k in _PARAM_KEYS[g.kind]),
                     _P_RANGES.index(str(g.params.get("pRange", "normalized"))))
        geos = rows.done()
    n = len(geos)
    starts = geos.starts
    which = np.clip(np.searchsorted(starts, s + 1e-9, side="right") - 1, 0, n - 1)
    x0, y0, h0 = (geos.base[which, j] for j in (1, 2, 3))
    ds = np.clip(s - starts[which], 0.0, geos.base[which, 4])
    kind = geos.kind[which]
    arc_kind = GEOMETRY_KINDS.index("arc")
    curvature = np.where(kind == arc_kind, geos.params[np.maximum(geos.param_index[which], 0),
                                                       0] if len(geos.params) else 0.0, 0.0)
    simple = kind <= arc_kind  # line (0) or arc (1)
    x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
    line = simple & (curvature == 0.0)
    x[line] = x0[line] + ds[line] * np.cos(h0[line])
    y[line] = y0[line] + ds[line] * np.sin(h0[line])
    h[line] = h0[line]
    arc = simple & (curvature != 0.0)
    k, hh, dd = curvature[arc], h0[arc], ds[arc]
    x[arc] = x0[arc] + (np.sin(hh + k * dd) - np.sin(hh)) / k
    y[arc] = y0[arc] - (np.cos(hh + k * dd) - np.cos(hh)) / k
    h[arc] = hh + k * dd
    for index in np.unique(which[~simple]):  # the samples of one geometry are contiguous
        lo, hi = np.searchsorted(which, [index, index + 1])
        x[lo:hi], y[lo:hi], h[lo:hi] = geos[index].points(ds[lo:hi])
    return x, y, h


def compile_kernels() -> None:
    """Load (or compile) the rasteriser's compiled loop once, on a single cross-section:
    the load worker does it as it starts, so no load waits on the compiler."""
    one = np.zeros(1)
    _scatter_cross_sections(one, one, one, one, one, one, one, one, 0.0, 1.0, 0.0, 0.0,
                            1.0, np.full((1, 1), np.nan), np.full((1, 1), np.inf))


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
    samples = sum(road.length for road in od.roads) / step
    if samples > MAX_RASTER_SAMPLES:
        raise OpenDriveError(f"{od.path}: {sum(r.length for r in od.roads):g} m of road "
                             f"at cell_m = {cell_m:g} m is {samples:.3g} samples, more than "
                             f"{MAX_RASTER_SAMPLES} (a coarser cell_m, or fewer roads)")
    sections = []
    lo_x = lo_y = math.inf
    hi_x = hi_y = -math.inf
    for road in od.roads:
        s_all = np.arange(0.0, road.length + 0.5 * step, step)
        s_all[-1] = min(s_all[-1], road.length)
        ref_x, ref_y, ref_h = reference_points(road, s_all)
        report_progress(f"{od.path.name}: road {road.id} sampled ({s_all.size} samples)")
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
    if nx * ny > MAX_RASTER_CELLS:
        raise OpenDriveError(f"{od.path}: the roads span {hi_x - lo_x:.0f} x {hi_y - lo_y:.0f}"
                             f" m: {nx} x {ny} cells of {cell_m:g} m, more than "
                             f"{MAX_RASTER_CELLS} (a coarser cell_m)")
    grid = np.full((ny, nx), np.nan)
    best_d2 = np.full((ny, nx), np.inf)
    for arrays in sections:  # in pieces, in order (the same grid), progress between
        for lo in range(0, arrays[0].size, SCATTER_CHUNK):
            # the lanes only (no margin): the ground beyond them is filled below
            _scatter_cross_sections(*(a[lo:lo + SCATTER_CHUNK] for a in arrays), 0.0,
                                    step, x0, y0, cell_m, grid, best_d2)
            report_progress(f"{od.path.name}: rasterising into {nx} x {ny} cells")
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
