"""The load worker's results through shared memory (``simserver.server.load_worker``, issue 13):
a terrain scene's grids reach the server as views of a block the worker wrote, with no
copy; the block's name is gone once mapped, its memory once the arrays are; blocks left by
a killed worker or a dead server are removed.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys

import numpy as np
import pytest

from simserver.server.load_worker import (
    SHARE_PREFIX,
    ProcessPreparer,
    SharedResult,
    opened,
    remove_stale_blocks,
    share_result,
)
from simserver.server.slot import prepare_load, unwrap_prepared
from simserver.testing import CONFIGS

pytestmark = pytest.mark.timeout(120)

CREST = CONFIGS / "scenes" / "crest_curve_paper_sedan.yaml"


def _blocks(directory) -> list[str]:
    return sorted(p.name for p in directory.glob(f"{SHARE_PREFIX}{os.getpid()}-*"))


def _mapped(path: str) -> bool:
    with open("/proc/self/maps", encoding="utf-8") as maps:
        return any(path in line for line in maps)


def test_a_terrain_scene_comes_back_as_views_of_a_shared_block():
    job = (str(CREST), None, CREST, (CONFIGS,), os.getcwd(), CONFIGS / "server")
    direct = unwrap_prepared(prepare_load(*job))[0]
    preparer = ProcessPreparer()
    try:
        result = preparer.submit(prepare_load, *job).result(timeout=90)
        assert isinstance(result, SharedResult) and result.path is not None
        # what crossed the pipe is the scene without its grids (6.6 MB of them)
        assert len(result.payload) < 64 * 1024 < direct.terrain.heights.nbytes
        assert os.path.exists(result.path)
        scene = unwrap_prepared(opened(result))[0]
        assert not os.path.exists(result.path)  # unlinked as soon as it is mapped
        # a result the loop abandoned (its worker killed) is removed with the worker
        abandoned = preparer.submit(prepare_load, *job).result(timeout=90)
        assert os.path.exists(abandoned.path)
        preparer.restart()
        assert not os.path.exists(abandoned.path)
    finally:
        preparer.close()
    for name in ("heights", "friction"):
        got, want = getattr(scene.terrain, name), getattr(direct.terrain, name)
        assert np.array_equal(got, want) and got.dtype == want.dtype
        # the compiled step's array type: writable, C-contiguous (no new specialisation)
        assert got.flags.writeable and got.flags.c_contiguous and got.flags.aligned
        assert not got.flags.owndata  # a view of the mapping, not a copy
    assert scene.vehicle.name == direct.vehicle.name and scene.initial == direct.initial
    assert _mapped(result.path)
    del scene, got, want
    gc.collect()
    assert not _mapped(result.path)  # the memory goes with the last array


def test_a_small_result_is_pickled_as_before(tmp_path, monkeypatch):
    monkeypatch.setattr("simserver.server.load_worker.SHARE_DIR", tmp_path)
    small = {"a": np.arange(10.0), "b": "text"}
    result = share_result(small, os.getpid())
    assert result.path is None and _blocks(tmp_path) == []
    back = opened(result)
    assert np.array_equal(back["a"], small["a"]) and back["b"] == "text"
    big = {"grid": np.arange(100_000.0).reshape(100, 1000), "f": np.asfortranarray(
        np.ones((300, 300)))}
    shared = share_result(big, os.getpid())
    assert _blocks(tmp_path) == [os.path.basename(shared.path)]
    back = opened(shared)
    assert _blocks(tmp_path) == []
    assert np.array_equal(back["grid"], big["grid"]) and not back["grid"].flags.owndata
    assert np.array_equal(back["f"], big["f"]) and back["f"].flags.f_contiguous  # copied


def test_blocks_of_this_server_and_of_dead_servers_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead_pid = int(dead.stdout)
    alive_pid = os.getppid()  # another running process: its blocks may still be mapped
    for owner in (os.getpid(), dead_pid, alive_pid):
        (tmp_path / f"{SHARE_PREFIX}{owner}-1-0").write_bytes(b"x" * 64)
    (tmp_path / "unrelated").write_bytes(b"y")
    assert remove_stale_blocks(os.getpid(), tmp_path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        f"{SHARE_PREFIX}{alive_pid}-1-0", "unrelated"]


def test_a_block_that_does_not_fit_falls_back_to_the_pipe(tmp_path, monkeypatch):
    import errno

    def full(fd, offset, length):  # a full tmpfs (a container's 64 MB /dev/shm)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("simserver.server.load_worker.SHARE_DIR", tmp_path)
    monkeypatch.setattr(os, "posix_fallocate", full)
    grid = np.arange(100_000.0).reshape(100, 1000)
    result = share_result({"grid": grid}, os.getpid())
    assert result.path is None and list(tmp_path.iterdir()) == []  # nothing left behind
    assert np.array_equal(opened(result)["grid"], grid)


def test_the_worker_outlives_a_ctrl_c_during_its_imports():
    """Ctrl-C in a terminal reaches every process of the server's group, often while the
    load worker still imports (the server is ready before it): the worker must not die
    of it with a ``KeyboardInterrupt`` traceback (issue 32: it printed one before the
    server's statistics); the server ends the worker when it stops."""
    import signal

    preparer = ProcessPreparer()
    try:
        warming = preparer.warm(os.getpid)
        (worker,) = preparer._pool._processes  # spawned by warm(), now importing
        os.kill(worker, signal.SIGINT)
        assert warming.result(timeout=90) == worker
        assert preparer.submit(os.getpid).result(timeout=90).payload is not None
        assert worker in preparer._pool._processes and preparer.restarts == 0
    finally:
        preparer.close()
