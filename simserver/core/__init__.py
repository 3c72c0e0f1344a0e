"""The pure compiled core: no I/O, no zenoh, no rerun, no YAML.

Everything here works on flat float64 arrays with named index constants and is
compiled with ``numba.njit(cache=True)``.

numba keys a cached kernel by its own source file's time stamp only, while the slot
constants it reads from other modules (``core.params``, ``core.layout``) are compiled
into it: after a change of those modules alone (a slot renumbered) the unchanged modules'
kernels would load from the cache with the old slots, and compute silently wrong numbers.
So, once per source state of the core, its kernel caches are dropped when any of its
sources changed (``drop_stale_kernel_caches``): the next import recompiles.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

SOURCES_STAMP = "simserver-core-sources.sha256"
"""The file, beside the core's kernel caches, holding the hash of the sources they were
compiled from."""


def kernel_cache_dirs(package_dir: Path) -> list[Path]:
    """Where numba caches the kernels of the modules in ``package_dir``: its
    ``__pycache__`` and, with ``NUMBA_CACHE_DIR`` set, numba's directory for it there
    (``numba.core.caching._CacheLocator.get_suitable_cache_subpath``)."""
    dirs = [package_dir / "__pycache__"]
    root = os.environ.get("NUMBA_CACHE_DIR")
    if root:
        sub = os.path.abspath(package_dir)
        hashed = hashlib.sha1(sub.encode()).hexdigest()
        dirs.append(Path(root) / f"{os.path.basename(sub)}_{hashed}")
    return dirs


def drop_stale_kernel_caches(package_dir: Path) -> bool:
    """Delete the cached kernels (``*.nbi``, ``*.nbc``) of ``package_dir`` if its ``.py``
    sources differ from those they were compiled from; True if any were dropped."""
    digest = hashlib.sha256()
    for source in sorted(package_dir.glob("*.py")):
        digest.update(source.name.encode())
        digest.update(source.read_bytes())
    key = digest.hexdigest()
    dropped = False
    for cache in kernel_cache_dirs(package_dir):
        stamp = cache / SOURCES_STAMP
        try:
            if stamp.read_text() == key:
                continue
        except OSError:
            pass
        # a cache directory not made yet is stamped now, before numba fills it: what it
        # holds is then known to come from these sources (a warm cache of a Docker build)
        for f in [*cache.glob("*.nbi"), *cache.glob("*.nbc")]:
            try:
                f.unlink()
                dropped = True
            except OSError:  # another process dropped it first, or a read-only cache
                pass
        try:
            cache.mkdir(parents=True, exist_ok=True)
            stamp.write_text(key)
        except OSError:  # a read-only tree: numba cannot cache there either
            pass
    return dropped


drop_stale_kernel_caches(Path(__file__).parent)
