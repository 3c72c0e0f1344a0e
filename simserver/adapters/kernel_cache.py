"""The compiled kernels' numba cache kept true to their sources.

numba's cache (``cache=True``) keys a compiled function on its own source file's time
stamp and size only. The step in ``core/integrator.py`` inlines functions of
``core/chassis.py``, ``core/tire.py`` and the rest, so after a change to one of those
(a ``git pull``, a branch switch, an edit) a process would load the old compiled step
from the cache and run the old physics without a word. ``drop_stale_kernels`` prevents
that: it hashes every source file that holds compiled kernels (``kernel_sources``) and,
in each cache directory numba may use for them (``cache_dirs``: ``NUMBA_CACHE_DIR``'s
mirror, the in-tree ``__pycache__``, the user-wide cache), removes their cached kernels
when the stamp file there (``STAMP``) names another hash, then writes the new one. The
next call compiles afresh (the cold compile of a first start) and caches again.

It runs when ``simserver.tire_models`` is imported (before any kernel is called: every
runner, the load worker and the sweep workers import it first). A cache directory that
cannot be written is left as it is.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from pathlib import Path

STAMP = "simserver-kernels.stamp"
"""Name of the stamp file in each cache directory: the hash of the kernel sources."""

PACKAGE = Path(__file__).resolve().parent.parent
KERNEL_FILES = ("tire_models.py", "adapters/opendrive.py")
"""Sources with compiled kernels outside ``core/`` (every ``core/*.py`` is one)."""


def kernel_sources() -> list[Path]:
    """Every source file of the package that defines or inlines compiled kernels."""
    return sorted(PACKAGE.glob("core/*.py")) + [PACKAGE / f for f in KERNEL_FILES]


def source_digest(files: Iterable[Path]) -> str:
    """One hash of the files' names and contents."""
    digest = hashlib.blake2b(digest_size=16)
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def cache_dirs(files: Iterable[Path]) -> dict[Path, list[Path]]:
    """The existing directories where numba may cache the files' kernels, each with the
    sources whose kernels it holds (numba's locators: ``NUMBA_CACHE_DIR``, in-tree
    ``__pycache__``, the user-wide cache)."""
    from numba.core import config
    from numba.core.caching import _CacheLocator
    from numba.misc.appdirs import AppDirs

    user_wide = Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)
    found: dict[Path, list[Path]] = {}
    for path in files:
        subpath = _CacheLocator.get_suitable_cache_subpath(str(path))
        candidates = [path.parent / "__pycache__", user_wide / subpath]
        if config.CACHE_DIR:
            candidates.insert(0, Path(config.CACHE_DIR) / subpath)
        for directory in candidates:
            if directory.is_dir():
                found.setdefault(directory, []).append(path)
    return found


def drop_stale_kernels(files: list[Path] | None = None) -> int:
    """Remove the cached kernels of ``files`` (default ``kernel_sources()``) wherever the
    stamp does not name their current hash, and stamp; the number of files removed."""
    files = kernel_sources() if files is None else files
    digest = source_digest(files)
    removed = 0
    for directory, sources in cache_dirs(files).items():
        stamp = directory / STAMP
        try:
            if stamp.read_text(encoding="ascii").strip() == digest:
                continue
        except (OSError, UnicodeDecodeError):
            pass  # no stamp yet (or unreadable): treat the cache as stale
        try:
            for source in sources:
                for cached in directory.glob(f"{source.stem}.*.nb[ic]"):
                    cached.unlink(missing_ok=True)
                    removed += 1
            partial = directory / f"{STAMP}.{os.getpid()}"
            partial.write_text(digest + "\n", encoding="ascii")
            partial.replace(stamp)  # atomic: a reader sees the old stamp or the new
        except OSError:
            continue  # a read-only cache (an image's): numba cannot write there either
    return removed
