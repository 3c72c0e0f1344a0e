"""Terrain files: a scene's ``terrain:`` section to a ``core.terrain.Terrain``.

The keys of each kind (``core.terrain.TERRAIN_KINDS``) are defined once, in
``TERRAIN_SCHEMAS`` below: the loader checks a section against them and
``docs/configuration.md`` is generated from them (``adapters.config``).

- ``kind: plane`` (the default when there is no ``terrain:``): the road of the scene's
  ``road:`` section. No other key.
- ``kind: heightmap``: a grid of heights from ``.npy`` (a 2-D array of heights, m),
  ``.npz`` (array ``heights``, m, and optionally ``friction``, a friction scale per grid
  point) or a 16-bit grayscale ``.png`` (value 0 -> ``height_offset_m``, 65535 ->
  ``height_offset_m + height_scale_m``). Row ``j``, column ``i`` of the grid is the point
  ``(origin_m[0] + i cell_m, origin_m[1] + j cell_m)``.
- ``kind: opendrive``: an ``.xodr`` road rasterised into a height grid of ``cell_m`` cells
  when loaded (``simserver.adapters.opendrive.rasterise``: the grid reaches ``margin_m``
  beyond the outer lanes' edges; the ground off the lanes is the harmonic interpolation of
  their surface, continuous); seconds per kilometre of road.

Every height grid is held to the bounds of ``core.terrain.heightmap_terrain`` (heights,
slopes, friction, spacing, extent: docs/model.md section 11); a file beyond them is
refused naming it.

Files are named relative to the scene file and read like every other nested reference
(``adapters.validate.referenced_file``): inside ``confined_to`` (the server's ``load``)
a terrain file outside the config folders is refused without being opened or quoted.
``terrain_spec`` gives the section validated, every default written out and its files as
absolute paths: what ``Scene.terrain_spec`` keeps (the viewer draws the lanes from it)
and what ``resolve_scenario`` writes into a resolved scenario.

Every error names the file and the key (``ConfigError``); nothing is kept of a terrain
that failed to load.
"""

from __future__ import annotations

import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.opendrive import load_opendrive, rasterise
from simserver.adapters.validate import ConfigError, check_keys, number, referenced_file
from simserver.core.param_table import Param, ParamTable
from simserver.core.terrain import (
    TERRAIN_HEIGHTMAP,
    TERRAIN_KINDS,
    TERRAIN_OPENDRIVE,
    Terrain,
    heightmap_terrain,
    plane_terrain,
)
from simserver.core.variants import UnknownVariantError

PNG_FULL_SCALE = 65535.0

log = logging.getLogger("simserver.terrain")


@dataclass(frozen=True)
class TerrainKey:
    """A key of a ``terrain:`` section that is not a number: a file or a point.

    ``kind``: ``"file"`` (a path relative to the scene file) or ``"xy"`` (``[x, y]`` in
    metres, each within ``lo`` .. ``hi``). ``required``: no default; an optional file
    key has none (left out of the spec when absent), an optional ``xy`` key ``default``."""

    key: str
    kind: str
    meaning: str
    required: bool = True
    default: Any = None
    lo: float = -1e7
    hi: float = 1e7


@dataclass(frozen=True)
class TerrainSchema:
    """The keys of one terrain kind: its file and point keys, and its numbers."""

    kind: str
    other_keys: tuple[TerrainKey, ...]
    numbers: ParamTable

    @property
    def keys(self) -> tuple[str, ...]:
        return ("kind", *(k.key for k in self.other_keys), *self.numbers.keys)

    @property
    def required(self) -> tuple[str, ...]:
        return (*(k.key for k in self.other_keys if k.required),
                *self.numbers.required_keys)


PNG_ONLY = ("height_scale_m", "height_offset_m")
"""Height-map keys that only a ``.png`` file takes."""

TERRAIN_SCHEMAS: dict[str, TerrainSchema] = {
    "plane": TerrainSchema("plane", (), ParamTable("terrain_plane", "no key but kind", ())),
    "heightmap": TerrainSchema(
        "heightmap",
        (TerrainKey("file", "file", "the heights: `.npy` (2-D array, m), `.npz` (array "
                    "`heights`, m; optional `friction`, a friction scale per grid point) or "
                    "a 16-bit grayscale `.png`"),
         TerrainKey("origin_m", "xy", "world `[x, y]` of the grid's first sample (row 0, "
                    "column 0); row j, column i is at `origin_m + (i, j) cell_m`",
                    required=False, default=[0.0, 0.0]),
         TerrainKey("friction_file", "file", "`.npy` friction scale per grid point, same "
                    "shape as the heights (instead of the `.npz`'s `friction`)",
                    required=False)),
        ParamTable("terrain_heightmap", "a regular grid of heights", (
            Param("cell_m", "m", 1e-3, 1e4, "grid spacing along x and y"),
            Param("height_scale_m", "m", 1e-6, 1e5,
                  "`.png` only: the height of pixel value 65535 above `height_offset_m`",
                  default="required for a .png"),
            Param("height_offset_m", "m", -1e5, 1e5,
                  "`.png` only: the height of pixel value 0", default=0.0),
        ))),
    "opendrive": TerrainSchema(
        "opendrive",
        (TerrainKey("file", "file", "the ASAM OpenDRIVE road network (`.xodr`)"),),
        ParamTable("terrain_opendrive", "an OpenDRIVE road rasterised into a height grid", (
            Param("cell_m", "m", 0.05, 10.0, "cell of the height grid the road is "
                  "rasterised into when loaded", default=0.5),
            Param("margin_m", "m", 0.0, 1e3, "the grid reaches this far beyond the outer "
                  "lanes' edges; the ground off the lanes is the smoothest through their "
                  "edges (harmonic, continuous)", default=20.0),
        ))),
}
"""The keys of each terrain kind (one source: the loader's checks and the docs)."""

assert tuple(TERRAIN_SCHEMAS) == tuple(TERRAIN_KINDS.names)  # one schema per kind


def terrain_spec(source: Path, raw: Any) -> dict[str, Any] | None:
    """The ``terrain:`` section of scene file ``source`` validated against its kind's
    schema, with every default written out and its files resolved to absolute paths
    (``referenced_file``: they must exist, be regular files and lie in the confinement).
    None for no section (the plane of ``road:``)."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: key 'terrain': expected a mapping")
    kind_name = raw.get("kind", "plane")
    try:
        TERRAIN_KINDS.by_name(kind_name)
    except UnknownVariantError as exc:
        raise ConfigError(f"{source}: key 'terrain.kind': {exc}") from None
    schema = TERRAIN_SCHEMAS[kind_name]
    check_keys(f"{source} (terrain)", raw, schema.keys, required=schema.required)
    spec: dict[str, Any] = {"kind": kind_name}
    for k in schema.other_keys:
        value = raw.get(k.key, k.default)
        if k.kind == "file":
            if k.key not in raw:
                continue
            value = str(referenced_file(source, f"terrain.{k.key}", value))
        elif not (isinstance(value, list | tuple) and len(value) == 2):
            raise ConfigError(f"{source}: key 'terrain.{k.key}': expected [x, y]")
        else:
            value = [number(source, f"terrain.{k.key}[{i}]", v, k.lo, k.hi)
                     for i, v in enumerate(value)]
        spec[k.key] = value
    is_png = kind_name == "heightmap" and Path(spec["file"]).suffix.lower() == ".png"
    for p in schema.numbers:
        if kind_name == "heightmap" and p.name in PNG_ONLY and not is_png:
            if p.name in raw:
                raise ConfigError(f"{source}: key 'terrain.{p.name}': only for a .png file")
            continue
        if p.name not in raw and isinstance(p.default, str):
            raise ConfigError(f"{source}: key 'terrain.{p.name}': {p.default}")
        spec[p.name] = number(source, f"terrain.{p.name}", raw.get(p.name, p.default),
                              p.lo, p.hi)
    return spec


MAX_GRID_CELLS = 40_000_000
"""Most cells of a height-map file's grid (320 MB as float64: 6 x 6 km at 1 m), checked
from the file's header before its data is read (a compressed ``.npz`` may expand far
beyond its size on disk)."""
GRID_KINDS = "biuf"
"""Array types a grid may have: booleans, integers, floats (numpy ``dtype.kind``)."""


def _check_header(path: Path, what: str, stream: Any) -> None:
    """The ``.npy`` header at ``stream``: a real number type and at most ``MAX_GRID_CELLS``
    (read before the data, so a bomb is refused before it is expanded)."""
    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(stream)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(stream)
    if dtype.kind not in GRID_KINDS:
        raise ConfigError(f"{path}: {what}: an array of {dtype} values, expected real "
                          "numbers")
    cells = 1
    for n in shape:
        cells *= int(n)
    if cells > MAX_GRID_CELLS:
        raise ConfigError(f"{path}: {what}: shape {tuple(shape)} has {cells} cells, more "
                          f"than {MAX_GRID_CELLS}")


def _read_array(path: Path, what: str, name: str | None) -> np.ndarray:
    """A 2-D array from ``.npy`` or ``.npz`` (array ``name``); ConfigError naming the file."""
    if not path.is_file():
        raise ConfigError(f"{path}: {what}: no such file")
    try:
        if path.suffix == ".npy":
            with open(path, "rb") as f:
                _check_header(path, what, f)
            arr = np.load(path, allow_pickle=False)
        elif path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                if name not in npz.files:
                    raise ConfigError(f"{path}: {what}: no array {name!r} (has {npz.files})")
                with npz.zip.open(f"{name}.npy") as member:
                    _check_header(path, f"{what} ({name})", member)
                arr = npz[name]
        else:
            raise ConfigError(f"{path}: {what}: expected .npy, .npz or .png")
    except ConfigError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, MemoryError) as exc:
        raise ConfigError(f"{path}: {what}: unreadable ({type(exc).__name__}: "
                          f"{str(exc)[:200]})") from None
    return np.asarray(arr, dtype=np.float64)


def _read_png16(path: Path, what: str) -> np.ndarray:
    """A 16-bit grayscale PNG's values (0 .. 65535) as float64, row 0 first."""
    from PIL import Image, UnidentifiedImageError  # matplotlib's own dependency

    if not path.is_file():
        raise ConfigError(f"{path}: {what}: no such file")
    try:
        with Image.open(path) as img:
            if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise ConfigError(
                    f"{path}: {what}: expected a 16-bit grayscale PNG, got mode {img.mode}")
            if img.size[0] * img.size[1] > MAX_GRID_CELLS:  # before decoding a pixel
                raise ConfigError(f"{path}: {what}: {img.size[0]} x {img.size[1]} pixels, "
                                  f"more than {MAX_GRID_CELLS}")
            img.load()
            arr = np.array(img, dtype=np.float64)
    except ConfigError:
        raise
    except (OSError, ValueError, UnidentifiedImageError, MemoryError,
            Image.DecompressionBombError) as exc:
        raise ConfigError(f"{path}: {what}: unreadable ({type(exc).__name__}: "
                          f"{str(exc)[:200]})") from None
    return arr


def load_terrain(source: Path, raw: Any) -> Terrain:
    """The terrain of a scene file ``source`` from its ``terrain:`` mapping (``None``: the
    plane)."""
    return terrain_from_spec(terrain_spec(source, raw))


def terrain_from_spec(spec: dict[str, Any] | None) -> Terrain:
    """The terrain of a ``terrain_spec`` (read from its files; errors name the file)."""
    if spec is None or spec["kind"] == "plane":
        return plane_terrain()
    kind = TERRAIN_KINDS.by_name(spec["kind"]).id
    if kind == TERRAIN_HEIGHTMAP:
        return _load_heightmap(spec)
    if kind == TERRAIN_OPENDRIVE:
        return _load_opendrive(spec)
    raise ConfigError(f"terrain kind {spec['kind']!r} is not loadable here")


def _load_heightmap(spec: dict[str, Any]) -> Terrain:
    path = Path(spec["file"])
    friction = None
    if path.suffix.lower() == ".png":
        heights = spec["height_offset_m"] + _read_png16(path, "terrain.file") * (
            spec["height_scale_m"] / PNG_FULL_SCALE)
    else:
        heights = _read_array(path, "terrain.file", "heights")
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                if "friction" in npz.files:
                    friction = _read_array(path, "terrain.file", "friction")
    if "friction_file" in spec:
        friction = _read_array(Path(spec["friction_file"]), "terrain.friction_file",
                               "friction")
    x0, y0 = spec["origin_m"]
    try:
        return heightmap_terrain(heights, spec["cell_m"], spec["cell_m"], x0, y0, friction)
    except ValueError as exc:  # the bounds of core.terrain (docs/model.md section 11)
        named = Path(spec["friction_file"]) if "friction_file" in spec and \
            str(exc).startswith("friction") else path
        raise ConfigError(f"{named}: terrain: {exc}") from None


def _load_opendrive(spec: dict[str, Any]) -> Terrain:
    path = Path(spec["file"])
    od = load_opendrive(path)
    for line in od.dropped:  # once per load: what of the file the ground leaves out
        log.warning("%s", line)
    heights, x0, y0 = rasterise(od, spec["cell_m"], spec["margin_m"])
    try:
        terrain = heightmap_terrain(heights, spec["cell_m"], spec["cell_m"], x0, y0)
    except ValueError as exc:  # a road beyond the bounds of core.terrain
        raise ConfigError(f"{path}: terrain (rasterised): {exc}") from None
    return terrain._replace(kind=TERRAIN_OPENDRIVE)
