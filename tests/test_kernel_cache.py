"""simserver.core drops its numba kernel caches when any core source changed: numba keys a
cached kernel by its own file only, and a renumbered slot constant in core.params would
otherwise load old kernels computing with the old slots."""

from __future__ import annotations

import pytest

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


# ------------------------------------------------------- one cache for several checkouts
_CHILD = """
import json, numpy as np, simserver
from simserver.core import layout as L
from simserver.core.pose import world_pose
world_pose(np.zeros(L.N_STATE), np.eye(3), 0.5, np.zeros(7))
s = world_pose.stats
print(json.dumps({"package": simserver.__file__, "hits": sum(s.cache_hits.values()),
                  "misses": sum(s.cache_misses.values())}))
"""


def _checkout(dest):
    """A copy of this tree's package at ``dest`` (no compiled caches), as a second clone."""
    import os
    import shutil
    import time
    from pathlib import Path

    import simserver

    src = Path(simserver.__file__).parent
    shutil.copytree(src, dest / "simserver",
                    ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    # a clone's files are as new as the clone: each checkout's sources get their own
    # modification time (numba's own stamp would call the other's cache stale)
    stamp = time.time() - 3600 * (1 + len(list(dest.parent.iterdir())))
    for source in (dest / "simserver").rglob("*.py"):
        os.utime(source, (stamp, stamp))
    return dest


def _run_in(checkout, env_extra):
    """``_CHILD`` run with ``checkout`` first on the path: which package it imported and
    ``world_pose``'s cache hits and misses."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")
           and k != "SIMSERVER_CACHE_DIR"}
    # the checkout before anything else (the noeditable shim, if any, stays behind it)
    env["PYTHONPATH"] = os.pathsep.join([str(checkout), *[
        p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
        if p and not (Path(p) / "simserver").is_dir()]])
    env.update(env_extra)
    proc = subprocess.run([sys.executable, "-c", _CHILD], env=env, cwd=checkout,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert Path(result["package"]).parent.parent == checkout, result
    return result


from pathlib import Path  # noqa: E402


def test_two_checkouts_share_one_cache(tmp_path):
    """Two clones of the same sources at different paths, one ``SIMSERVER_CACHE_DIR``: the
    first compiles, the second loads what the first compiled (with numba's own
    ``NUMBA_CACHE_DIR``, which keys a cache by the sources' absolute path, the second
    compiled again). A clone whose core sources differ (another commit) compiles into a
    directory of its own and leaves the first one's kernels in place."""
    a, b, c = (_checkout(tmp_path / n) for n in "abc")
    shared = {"SIMSERVER_CACHE_DIR": str(tmp_path / "cache")}
    first = _run_in(a, shared)
    assert first["misses"] >= 1 and first["hits"] == 0
    second = _run_in(b, shared)
    assert second["misses"] == 0 and second["hits"] >= 1
    assert not list((b / "simserver").rglob("*.nbi")), "cached beside the sources"
    with open(c / "simserver" / "core" / "road.py", "a") as f:
        f.write("\n# another commit\n")
    assert _run_in(c, shared)["misses"] >= 1
    assert len(list((tmp_path / "cache").glob("simserver-*"))) == 2
    assert _run_in(b, shared)["misses"] == 0


# ------------------------------------------------ the server's helper compiles (issue 33)
_HELPER_CHILD = """
import json, sys
from numba.core import event
compiled = []
class Seen(event.Listener):
    def on_start(self, ev):
        f = ev.data["dispatcher"].py_func
        compiled.append(f"{f.__module__}.{f.__qualname__}")
    def on_end(self, ev):
        pass
event.register("numba:compile", Seen())
from simserver.sim.scene_files import warm_up_in_helper
from simserver.sim.simulation import HELPER_KERNELS, Simulation
from simserver.sim.scene_files import load_scene
scene, role = sys.argv[1], sys.argv[2]
if role == "helper":
    warm_up_in_helper(scene, 0.001)
    print(json.dumps(compiled))
else:  # the server's warm-up of the same names, after Simulation() compiled its own
    sim = Simulation(load_scene(scene), 0.001)
    before = len(compiled)
    for name, call in sim.warm_up_calls(live=True):
        if name in HELPER_KERNELS:
            call()
    print(json.dumps(compiled[before:]))
"""


def test_the_helper_kernels_are_live_warm_up_entry_points():
    """The names the server's load worker compiles as it starts (``HELPER_KERNELS``) are
    entry points of the live warm-up (a renamed one would silently leave the server to
    compile it on its own core), and none of them is the step."""
    from simserver.sim.scene_files import load_scene
    from simserver.sim.simulation import HELPER_KERNELS, Simulation

    root = Path(__file__).resolve().parent.parent
    sim = Simulation(load_scene(root / "configs" / "scenes" / "flat_paper_sedan.yaml"), 0.001)
    names = [name for name, _ in sim.warm_up_calls(live=True)]
    assert set(HELPER_KERNELS) <= set(names), (HELPER_KERNELS, names)
    assert "step" not in HELPER_KERNELS


@pytest.mark.slow
def test_the_helper_compiles_no_step_and_the_server_finds_its_kernels(tmp_path):
    """From an empty cache, ``warm_up_in_helper`` (the load worker's first job, run while
    the server compiles the step) compiles no car or world step (else it would repeat the
    server's longest compile on the other core), and the server's own warm-up of the same
    entry points then compiles nothing: the helper's signatures are the server's."""
    import json
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    scene = str(root / "configs" / "scenes" / "flat_paper_sedan.yaml")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env["SIMSERVER_CACHE_DIR"] = str(tmp_path / "cache")

    def run(role):
        proc = subprocess.run([sys.executable, "-c", _HELPER_CHILD, scene, role], env=env,
                              cwd=root, capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout.strip().splitlines()[-1])

    helper = run("helper")
    assert "simserver.core.chassis.follow_terrain" in helper, helper  # place_on_terrain's
    steps = [f for f in helper if f.endswith((".integrator.step", ".world.step"))]
    assert not steps, helper
    assert run("server") == []
