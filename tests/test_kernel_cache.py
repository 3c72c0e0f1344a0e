"""simserver.core drops its numba kernel caches when any core source changed: numba keys a
cached kernel by its own file only, and a renumbered slot constant in core.params would
otherwise load old kernels computing with the old slots."""

from __future__ import annotations

from simserver.core import SOURCES_STAMP, drop_stale_kernel_caches, kernel_cache_dirs


def _package(tmp_path):
    pkg = tmp_path / "core"
    pkg.mkdir()
    (pkg / "params.py").write_text("VP_MASS_KG = 0\n")
    (pkg / "steering.py").write_text("def f(vp): return vp[0]\n")
    return pkg


def test_a_changed_source_drops_every_cached_kernel_once(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    pkg = _package(tmp_path)
    cache = pkg / "__pycache__"
    cache.mkdir()
    assert kernel_cache_dirs(pkg) == [cache]
    drop_stale_kernel_caches(pkg)  # first sight: stamped
    kernels = [cache / "steering.f-1.py311.nbi", cache / "steering.f-1.py311.1.nbc"]
    for f in kernels:
        f.write_bytes(b"compiled with VP_MASS_KG = 0")
    assert not drop_stale_kernel_caches(pkg)  # unchanged sources: kept
    assert all(f.exists() for f in kernels)
    (pkg / "params.py").write_text("VP_MASS_KG = 1\n")  # steering.py itself unchanged
    assert drop_stale_kernel_caches(pkg)
    assert not any(f.exists() for f in kernels)
    assert (cache / SOURCES_STAMP).exists()
    assert not drop_stale_kernel_caches(pkg)


def test_the_numba_cache_dir_is_dropped_too(tmp_path, monkeypatch):
    pkg = _package(tmp_path)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "nc"))
    elsewhere = kernel_cache_dirs(pkg)[1]
    assert elsewhere.parent == tmp_path / "nc" and elsewhere.name.startswith("core_")
    elsewhere.mkdir(parents=True)
    drop_stale_kernel_caches(pkg)
    kernel = elsewhere / "steering.f-1.py311.nbi"
    kernel.write_bytes(b"old")
    (pkg / "steering.py").write_text("def f(vp): return vp[1]\n")
    assert drop_stale_kernel_caches(pkg) and not kernel.exists()


def test_a_cache_made_after_the_stamp_is_kept(tmp_path, monkeypatch):
    """A ``NUMBA_CACHE_DIR`` that does not exist yet (a cold start, a Docker build) is
    stamped at the first import, so the kernels compiled into it survive the next start."""
    pkg = _package(tmp_path)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "fresh"))
    drop_stale_kernel_caches(pkg)
    elsewhere = kernel_cache_dirs(pkg)[1]
    kernel = elsewhere / "steering.f-1.py311.nbi"
    kernel.write_bytes(b"compiled after the stamp")
    assert not drop_stale_kernel_caches(pkg) and kernel.exists()
