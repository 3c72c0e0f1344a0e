"""A run's fully resolved configuration: one nested mapping, changed by dotted paths,
identified by a hash.

``resolve_scenario`` (simserver/sim/scenario.py) turns a scenario file into one mapping with
everything it refers to inline (the vehicle, its subsystem and tire files, every
default); ``load_scenario(label, resolved)`` loads it back into the same ``Scenario``.
A sweep changes it by dotted paths (``vehicle.chassis.mass_kg``,
``vehicle.tires.front.relaxation_length_long_m``, ``road.grade_pct``,
``model.damping_ratio``, ``initial.u_mps``, ``duration_s``, ``inputs.1.brake``: a list
item by its index); ``*`` stands for every key at its level
(``vehicle.tires.*.relaxation_length_long_m``: both axles). A run's
identity is the hash of its resolved mapping (``run_id``): the same on every machine and
process for the same configuration.
"""

from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path
from typing import Any

from simserver.adapters.config import ConfigError, resolve_vehicle
from simserver.adapters.validate import read_regular_chunks

RUN_ID_CHARS = 16  # hex digits of the SHA-256 kept as the run's identity
MAX_HASHED_BYTES = 512 << 20
"""Largest file a run id hashes (512 MiB: above the largest file a run reads, an .xodr
of 256 MiB); hashed a MiB at a time, once per file and version."""
_HASH_CHUNK_BYTES = 1 << 20
_digests: dict[tuple[str, int, int, int], str] = {}  # (path, dev, inode, mtime) -> SHA-256


def file_digest(path: str | Path) -> str:
    """The SHA-256 of a regular file of at most ``MAX_HASHED_BYTES``, read in chunks
    (opened without blocking, checked with ``fstat``: a FIFO or device is refused, not
    read), remembered per file and modification time. ``ConfigError`` names the file."""
    path = Path(path)
    try:
        info = path.stat()  # the memo's key; the read itself is checked again
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    key = (str(path.resolve()), info.st_dev, info.st_ino, info.st_mtime_ns)
    known = _digests.get(key)
    if known is not None:
        return known
    digest = hashlib.sha256()
    for chunk in read_regular_chunks(path, MAX_HASHED_BYTES, _HASH_CHUNK_BYTES,
                                     what="the most a run's file may have"):
        digest.update(chunk)
    _digests[key] = digest.hexdigest()
    return _digests[key]


def set_path(resolved: dict[str, Any], dotted: str, value: Any, origin: str,
             base_dir: Path | None = None) -> None:
    """Set ``dotted`` (``a.b.c``; ``*`` matches every key at its level) in ``resolved``.

    Every part but the last must exist (a typo is an error naming the path); the last may
    be new when its parent is a mapping (an optional key, checked when the run loads).
    ``vehicle`` set to a string is a vehicle file (relative to ``base_dir``), read inline.
    """
    parts = dotted.split(".")
    if not dotted or any(not p for p in parts):
        raise ConfigError(f"{origin}: parameter {dotted!r}: expected a dotted path like "
                          f"'vehicle.chassis.mass_kg'")
    if parts == ["vehicle"] and isinstance(value, str):
        vehicle_path = Path(value) if base_dir is None else (base_dir / value).resolve()
        resolved["vehicle"] = resolve_vehicle(vehicle_path)
        return
    _set(resolved, parts, value, dotted, origin, 0)


def _set(node: Any, parts: list[str], value: Any, dotted: str, origin: str, depth: int) -> None:
    here = ".".join(parts[:depth]) or "the scenario"
    if isinstance(node, list):  # a list (``inputs``) is indexed by number: inputs.1.brake
        if not parts[depth].isdigit() or int(parts[depth]) >= len(node):
            raise ConfigError(f"{origin}: parameter {dotted!r}: {here} has items 0 .. "
                              f"{len(node) - 1}, not {parts[depth]!r}")
        if depth == len(parts) - 1:
            node[int(parts[depth])] = copy.deepcopy(value)
        else:
            _set(node[int(parts[depth])], parts, value, dotted, origin, depth + 1)
        return
    if not isinstance(node, dict):
        raise ConfigError(f"{origin}: parameter {dotted!r}: {here} is not a mapping")
    key = parts[depth]
    last = depth == len(parts) - 1
    keys = list(node) if key == "*" else [key]
    if key == "*" and not keys:
        raise ConfigError(f"{origin}: parameter {dotted!r}: {here} is empty")
    for k in keys:
        if last:
            node[k] = copy.deepcopy(value)
            continue
        if k not in node:
            raise ConfigError(f"{origin}: parameter {dotted!r}: no key {k!r} in {here} "
                              f"(has: {', '.join(map(str, node))})")
        _set(node[k], parts, value, dotted, origin, depth + 1)


def with_overrides(resolved: dict[str, Any], overrides: dict[str, Any], origin: str,
                   base_dir: Path | None = None) -> dict[str, Any]:
    """A copy of ``resolved`` with each ``dotted path -> value`` of ``overrides`` set."""
    out = copy.deepcopy(resolved)
    for dotted, value in overrides.items():
        set_path(out, dotted, value, origin, base_dir)
    return out


def _canonical(obj: Any) -> Any:
    """Numbers as floats (``25`` and ``25.0`` are the same configuration), files named by
    a key ending in ``_file`` or called ``file`` (a terrain's) also by the SHA-256 of their
    contents."""
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            out[str(key)] = _canonical(value)
            if (str(key) == "file" or str(key).endswith("_file")) and isinstance(value, str) \
                    and Path(value).is_file():
                out[f"{key}#sha256"] = file_digest(value)
        return out
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, (int, float)):
        return float(obj)
    return str(obj)


def run_id(resolved: dict[str, Any]) -> str:
    """The run's identity: a hash of its resolved configuration (stable across processes
    and machines; key order does not matter)."""
    text = json.dumps(_canonical(resolved), sort_keys=True, separators=(",", ":"),
                      allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:RUN_ID_CHARS]
