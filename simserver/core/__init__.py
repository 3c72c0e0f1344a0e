"""The pure compiled core: no I/O, no zenoh, no rerun, no YAML.

Everything here works on flat float64 arrays with named index constants and is
compiled with ``numba.njit(cache=True)``.

numba keys a cached kernel by its own source file's time stamp only, while the slot
constants it reads from other modules (``core.params``, ``core.layout``) are compiled
into it: after a change of those modules alone (a slot renumbered) the unchanged modules'
kernels would load from the cache with the old slots, and compute silently wrong numbers.
So, once per source state of the core, its kernel caches are dropped when any of its
sources changed (``drop_stale_kernel_caches``): the next import recompiles.

One cache for several checkouts, users, sweep workers or a container: set
``SIMSERVER_CACHE_DIR`` (``CACHE_DIR_ENV``) to a directory before the core is imported.
Every simserver kernel is then cached below ``DIR/simserver-<key>/<package path>``
(``SharedCacheLocator``), where ``<key>`` is the hash of the core's sources: numba's own
locators key a cache by the absolute path of the source directory, so two checkouts (or
two users' installs) of the same sources compiled twice, while here identical sources find
one cache whatever their path, and other sources (another commit) get a directory of their
own instead of dropping this one's kernels. numba checks the rest as usual: the source
file's content, the function's bytecode, numba's version and the CPU.
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


def sources_key(package_dir: Path) -> str:
    """The hash of the ``.py`` sources of ``package_dir`` (names and contents)."""
    digest = hashlib.sha256()
    for source in sorted(package_dir.glob("*.py")):
        digest.update(source.name.encode())
        digest.update(source.read_bytes())
    return digest.hexdigest()


def drop_stale_kernel_caches(package_dir: Path) -> bool:
    """Delete the cached kernels (``*.nbi``, ``*.nbc``) of ``package_dir`` if its ``.py``
    sources differ from those they were compiled from; True if any were dropped."""
    key = sources_key(package_dir)
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


CACHE_DIR_ENV = "SIMSERVER_CACHE_DIR"
"""The environment variable naming the shared kernel cache (module docstring)."""

PACKAGE_DIR = Path(__file__).resolve().parent.parent
"""The ``simserver`` package whose kernels ``SharedCacheLocator`` places."""


def shared_cache_dir(root: str | os.PathLike[str], package_dir: Path = PACKAGE_DIR,
                     key: str | None = None) -> Path:
    """The directory of this source state's kernels in the shared cache ``root``."""
    key = key or sources_key(package_dir / "core")
    return Path(root).expanduser().resolve() / f"simserver-{key[:20]}"


def _shared_locator_class() -> type:
    from numba.core.caching import _CacheLocator, _SourceFileBackedLocatorMixin

    class SharedCacheLocator(_SourceFileBackedLocatorMixin, _CacheLocator):
        """numba's cache locator for simserver's kernels under ``SIMSERVER_CACHE_DIR``:
        ``DIR/simserver-<core sources key>/<the module's folder in the package>``, the
        same for every checkout of the same sources (module docstring). Functions of
        other packages, or no ``SIMSERVER_CACHE_DIR``: numba's own locators."""

        _roots: dict[str, Path] = {}

        def __init__(self, py_func: object, py_file: str, base: Path) -> None:
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno  # type: ignore[attr-defined]
            rel = Path(os.path.abspath(py_file)).parent.relative_to(PACKAGE_DIR.parent)
            self._cache_path = str(base / rel)

        def get_cache_path(self) -> str:
            return self._cache_path

        @classmethod
        def from_function(cls, py_func: object, py_file: str) -> object:
            root = os.environ.get(CACHE_DIR_ENV)
            if not root or not os.path.isfile(py_file):
                return None
            path = Path(os.path.abspath(py_file))
            if not path.is_relative_to(PACKAGE_DIR):
                return None
            if root not in cls._roots:
                cls._roots[root] = shared_cache_dir(root)
            self = cls(py_func, py_file, cls._roots[root])
            try:
                self.ensure_cache_path()
            except OSError as exc:
                import warnings

                warnings.warn(f"{CACHE_DIR_ENV}={root}: cannot write there ({exc}); numba "
                              "caches simserver's kernels in its default place instead",
                              stacklevel=2)
                return None
            return self

    return SharedCacheLocator


def install_shared_locator() -> type:
    """Put ``SharedCacheLocator`` first among numba's cache locators (once): from then on
    every simserver kernel defined goes to ``SIMSERVER_CACHE_DIR`` when that is set."""
    from numba.core.caching import CacheImpl

    for cls in CacheImpl._locator_classes:
        if cls.__name__ == "SharedCacheLocator":
            return cls
    cls = _shared_locator_class()
    CacheImpl._locator_classes.insert(0, cls)
    return cls


install_shared_locator()
drop_stale_kernel_caches(Path(__file__).parent)
