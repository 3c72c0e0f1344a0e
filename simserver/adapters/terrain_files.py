"""Terrain files: a scene's ``terrain:`` section to a ``core.terrain.Terrain``.

``terrain:`` keys, by kind (``core.terrain.TERRAIN_KINDS``):

- ``kind: plane`` (the default when there is no ``terrain:``): the road of the scene's
  ``road:`` section. No other key.
- ``kind: heightmap``:
  - ``file`` (required): ``.npy`` (a 2-D array of heights, m), ``.npz`` (array
    ``heights``, m, and optionally ``friction``, a friction scale per grid point) or a
    16-bit grayscale ``.png`` (value 0 -> ``height_offset_m``, 65535 ->
    ``height_offset_m + height_scale_m``), relative to the scene file. Row ``j``, column
    ``i`` of the grid is the point ``(origin_m[0] + i cell_m, origin_m[1] + j cell_m)``.
  - ``cell_m`` (required): grid spacing (m).
  - ``origin_m``: world ``[x, y]`` of the grid's first sample (default ``[0, 0]``).
  - ``height_scale_m``, ``height_offset_m``: for a PNG (``height_scale_m`` required there).
  - ``friction_file``: ``.npy`` friction scale per grid point (instead of the ``.npz``'s).

- ``kind: opendrive``: ``file`` (required, ``.xodr``), ``cell_m`` (default 0.5) and
  ``margin_m`` (default 20): the road is rasterised into a height grid of ``cell_m`` cells
  when loaded (``simserver.adapters.opendrive.rasterise``: the lanes' edges extend flat
  for ``margin_m``, farther cells take the nearest surface cell's height along their grid
  row or column); seconds per kilometre of road.

Every error names the file and the key (``ConfigError``); nothing is kept of a terrain
that failed to load.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.opendrive import load_opendrive, rasterise
from simserver.adapters.validate import ConfigError, check_keys, number
from simserver.core.terrain import (
    TERRAIN_HEIGHTMAP,
    TERRAIN_KINDS,
    TERRAIN_OPENDRIVE,
    TERRAIN_PLANE,
    Terrain,
    heightmap_terrain,
    plane_terrain,
)
from simserver.core.variants import UnknownVariantError

OPENDRIVE_KEYS = ("kind", "file", "cell_m", "margin_m")
HEIGHTMAP_KEYS = ("kind", "file", "cell_m", "origin_m", "height_scale_m", "height_offset_m",
                  "friction_file")
PNG_FULL_SCALE = 65535.0


def _read_array(path: Path, what: str, name: str | None) -> np.ndarray:
    """A 2-D array from ``.npy`` or ``.npz`` (array ``name``); ConfigError naming the file."""
    if not path.is_file():
        raise ConfigError(f"{path}: {what}: no such file")
    try:
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                if name not in npz.files:
                    raise ConfigError(f"{path}: {what}: no array {name!r} (has {npz.files})")
                arr = npz[name]
        else:
            raise ConfigError(f"{path}: {what}: expected .npy, .npz or .png")
    except ConfigError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"{path}: {what}: unreadable ({exc})") from None
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
            img.load()
            arr = np.array(img, dtype=np.float64)
    except ConfigError:
        raise
    except (OSError, ValueError, UnidentifiedImageError) as exc:
        raise ConfigError(f"{path}: {what}: unreadable ({exc})") from None
    return arr


def load_terrain(source: Path, raw: Any) -> Terrain:
    """The terrain of a scene file ``source`` from its ``terrain:`` mapping (``None``: the
    plane)."""
    if raw is None:
        return plane_terrain()
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: key 'terrain': expected a mapping")
    kind_name = raw.get("kind", "plane")
    try:
        kind = TERRAIN_KINDS.by_name(kind_name).id
    except UnknownVariantError as exc:
        raise ConfigError(f"{source}: key 'terrain.kind': {exc}") from None
    if kind == TERRAIN_PLANE:
        check_keys(f"{source} (terrain)", raw, ("kind",))
        return plane_terrain()
    if kind == TERRAIN_HEIGHTMAP:
        return _load_heightmap(source, raw)
    if kind == TERRAIN_OPENDRIVE:
        return _load_opendrive(source, raw)
    raise ConfigError(f"{source}: key 'terrain.kind': {kind_name!r} is not loadable here")


def _load_heightmap(source: Path, raw: dict[str, Any]) -> Terrain:
    check_keys(f"{source} (terrain)", raw, HEIGHTMAP_KEYS, required=("file", "cell_m"))
    if not isinstance(raw["file"], str):
        raise ConfigError(f"{source}: key 'terrain.file': expected a file path")
    path = (source.parent / raw["file"]).resolve()
    cell = number(source, "terrain.cell_m", raw["cell_m"], 1e-3, 1e4)
    origin = raw.get("origin_m", [0.0, 0.0])
    if not (isinstance(origin, list) and len(origin) == 2):
        raise ConfigError(f"{source}: key 'terrain.origin_m': expected [x, y]")
    x0 = number(source, "terrain.origin_m[0]", origin[0], -1e7, 1e7)
    y0 = number(source, "terrain.origin_m[1]", origin[1], -1e7, 1e7)
    friction = None
    if path.suffix == ".png":
        if "height_scale_m" not in raw:
            raise ConfigError(f"{source}: key 'terrain.height_scale_m': required for a PNG")
        scale = number(source, "terrain.height_scale_m", raw["height_scale_m"], 1e-6, 1e5)
        offset = number(source, "terrain.height_offset_m", raw.get("height_offset_m", 0.0),
                        -1e5, 1e5)
        heights = offset + _read_png16(path, "terrain.file") * (scale / PNG_FULL_SCALE)
    else:
        for key in ("height_scale_m", "height_offset_m"):
            if key in raw:
                raise ConfigError(f"{source}: key 'terrain.{key}': only for a .png file")
        heights = _read_array(path, "terrain.file", "heights")
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                if "friction" in npz.files:
                    friction = _read_array(path, "terrain.file", "friction")
    if "friction_file" in raw:
        if not isinstance(raw["friction_file"], str):
            raise ConfigError(f"{source}: key 'terrain.friction_file': expected a file path")
        fpath = (source.parent / raw["friction_file"]).resolve()
        friction = _read_array(fpath, "terrain.friction_file", "friction")
    try:
        return heightmap_terrain(heights, cell, cell, x0, y0, friction)
    except ValueError as exc:
        raise ConfigError(f"{path}: terrain: {exc}") from None


def _load_opendrive(source: Path, raw: dict[str, Any]) -> Terrain:
    check_keys(f"{source} (terrain)", raw, OPENDRIVE_KEYS, required=("file",))
    if not isinstance(raw["file"], str):
        raise ConfigError(f"{source}: key 'terrain.file': expected a file path")
    cell = number(source, "terrain.cell_m", raw.get("cell_m", 0.5), 0.05, 10.0)
    margin = number(source, "terrain.margin_m", raw.get("margin_m", 20.0), 0.0, 1e3)
    od = load_opendrive((source.parent / raw["file"]).resolve())
    heights, x0, y0 = rasterise(od, cell, margin)
    return heightmap_terrain(heights, cell, cell, x0, y0)._replace(kind=TERRAIN_OPENDRIVE)
