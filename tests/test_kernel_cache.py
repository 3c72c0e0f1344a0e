"""The numba cache kept true to the kernel sources (``simserver.adapters.kernel_cache``):
numba keys a cached function on its own file only, so a change to an inlined module
(``core/chassis.py`` under the step of ``core/integrator.py``) left the old compiled step
in the cache, run without a word (seen merging issue 34's chassis change)."""

from __future__ import annotations

from pathlib import Path

from simserver.adapters import kernel_cache as kc


def _tree(tmp_path: Path) -> tuple[list[Path], Path]:
    src = tmp_path / "pkg"
    (src / "__pycache__").mkdir(parents=True)
    files = []
    for name in ("chassis.py", "integrator.py"):
        (src / name).write_text(f"# {name}\n")
        files.append(src / name)
    for cached in ("integrator.step-426.py311.nbi", "integrator.step-426.py311.1.nbc",
                   "chassis.follow_terrain-311.py311.1.nbc"):
        (src / "__pycache__" / cached).write_bytes(b"compiled")
    (src / "__pycache__" / "integrator.cpython-311.pyc").write_bytes(b"bytecode")
    return files, src / "__pycache__"


def test_a_change_to_any_kernel_source_drops_every_cached_kernel_once(tmp_path):
    files, cache = _tree(tmp_path)
    assert kc.drop_stale_kernels(files) == 3  # no stamp yet: nothing cached is trusted
    assert sorted(p.name for p in cache.iterdir()) == ["integrator.cpython-311.pyc",
                                                      kc.STAMP]
    (cache / "integrator.step-426.py311.nbi").write_bytes(b"compiled again")
    assert kc.drop_stale_kernels(files) == 0  # same sources: the cache stays
    assert (cache / "integrator.step-426.py311.nbi").exists()
    files[0].write_text("# chassis.py, changed\n")  # an inlined module changes
    assert kc.drop_stale_kernels(files) == 1  # the integrator's step goes too
    assert not (cache / "integrator.step-426.py311.nbi").exists()
    assert (cache / "integrator.cpython-311.pyc").exists()  # bytecode is Python's own


def test_numba_cache_dir_is_one_of_the_places_looked_at(tmp_path, monkeypatch):
    from numba.core import config
    from numba.core.caching import _CacheLocator

    files, _ = _tree(tmp_path)
    shared = tmp_path / "shared"
    mirror = shared / _CacheLocator.get_suitable_cache_subpath(str(files[0]))
    mirror.mkdir(parents=True)
    (mirror / "chassis.wheel_position-236.py311.1.nbc").write_bytes(b"compiled")
    monkeypatch.setattr(config, "CACHE_DIR", str(shared))
    assert mirror in kc.cache_dirs(files)
    assert kc.drop_stale_kernels(files) == 4  # the mirror's and the in-tree ones
    assert (mirror / kc.STAMP).read_text().strip() == kc.source_digest(files)


def test_the_package_sources_cover_the_compiled_modules():
    """Every module of the package with a compiled kernel is hashed."""
    hashed = {p.resolve() for p in kc.kernel_sources()}
    compiled = {p.resolve() for p in kc.PACKAGE.rglob("*.py")
                if "@nb.njit" in p.read_text(encoding="utf-8")
                or "numba.njit" in p.read_text(encoding="utf-8")}
    assert compiled and compiled <= hashed, sorted(map(str, compiled - hashed))
