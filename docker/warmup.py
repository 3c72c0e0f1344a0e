"""Compile every numba kernel of simserver into the cache, so a server starts within seconds.

The container image runs this at build time (``Dockerfile``) and ``tests/test_dockerfile.py``
runs the very same command in a fresh virtual environment::

    SIMSERVER_CACHE_DIR=/var/cache/simserver/numba \\
        python docker/warmup.py --configs /etc/simserver [--expect-cached]

For each scene (default: ``scenes/flat_paper_sedan.yaml`` and ``scenes/flat_mf_hatchback.yaml``
under ``--configs``, i.e. the simple brush tire and the MF 6.1 tire) it runs:

1. the headless path: ``simserver soak --scene SCENE --duration 1 --quiet`` (the compiled
   ``simulate`` loop and everything it calls), in this process through ``simserver.cli``;
2. the ``serve`` path: the server config ``server/default.yaml`` loaded with the scene,
   ``simserver.server.app.SimServer`` constructed (no network is opened) and its
   ``Simulation.warm_up()`` called, exactly what ``simserver serve`` does before its clock
   starts (``step``, ``world_pose``, ``set_road``), and the live loop's state-record
   kernels (``simserver.server.state_frame``);
3. the ``tire-curves`` path: ``core.tire.tire_forces`` called from Python with the
   registered kernels;
4. the ``view`` path (``simserver view``, or ``serve --viewer save:FILE.rrd``): one state
   record turned back into the core layout (``core.pose.road_pose``).

Then it reports, from numba's own counters, how many specialisations were loaded from the
cache and how many had to be compiled. With ``--expect-cached`` it exits 1 if anything was
compiled: run a second time after a first warm-up, that proves the cache is written,
readable by a fresh process and valid for these files (the image does this at build time).

numba keys its cache on the source files (path, modification time, bytecode) and on the CPU
(``llvmlite``'s host CPU name and features, or ``NUMBA_CPU_NAME``/``NUMBA_CPU_FEATURES``):
a cache warmed on one CPU model is cold on another unless ``NUMBA_CPU_NAME=generic``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import os
import pkgutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

DEFAULT_SCENES = ("scenes/flat_paper_sedan.yaml", "scenes/flat_mf_hatchback.yaml")
"""Scenes warmed by default, relative to ``--configs``: one per tire model."""

SERVER_CONFIG = "server/default.yaml"
"""The server config the ``serve`` path loads, relative to ``--configs``."""


@dataclass
class KernelCount:
    """numba's compile counters over every dispatcher of ``simserver.core``.

    Attributes
    ----------
    dispatchers : int
        Compiled functions found in ``simserver.core.*``.
    specialisations : int
        Type signatures they hold in this process after the warm-up.
    cache_hits : int
        Specialisations loaded from the on-disk cache.
    cache_misses : int
        Specialisations compiled (not found in the cache, or stale).
    names_compiled : list of str
        Qualified names of the functions with a cache miss.
    names_not_compiled : list of str
        Functions with no specialisation in this process, ``inline="always"`` ones aside.
        After a cold warm-up: what no path of the server uses (tests-only helpers, say);
        after a warm one it also lists the callees, which the cached callers embed.
    """

    dispatchers: int
    specialisations: int
    cache_hits: int
    cache_misses: int
    names_compiled: list[str]
    names_not_compiled: list[str]


SERVER_KERNEL_MODULES = ("simserver.server.state_frame",)
"""Modules outside ``simserver.core`` with kernels of their own (the live loop's)."""


def core_dispatchers() -> dict[str, object]:
    """Every numba dispatcher defined in the ``simserver.core`` modules and in
    :data:`SERVER_KERNEL_MODULES`, by qualified name."""
    import numba.core.registry

    import simserver.core as core

    found: dict[str, object] = {}
    names = [f"simserver.core.{info.name}" for info in pkgutil.iter_modules(core.__path__)]
    for name in names + list(SERVER_KERNEL_MODULES):
        module = importlib.import_module(name)
        for name, obj in vars(module).items():
            if (isinstance(obj, numba.core.registry.CPUDispatcher)
                    and obj.py_func.__module__ == module.__name__):
                found[f"{module.__name__}.{name}"] = obj
    return found


def count_kernels() -> KernelCount:
    """Read numba's per-dispatcher cache counters (this process only)."""
    dispatchers = core_dispatchers()
    hits = misses = specs = 0
    compiled: list[str] = []
    untouched: list[str] = []
    for name, disp in dispatchers.items():
        specs += len(disp.signatures)  # type: ignore[attr-defined]
        inline = disp.targetoptions.get("inline") == "always"  # type: ignore[attr-defined]
        if not disp.signatures and not inline:  # type: ignore[attr-defined]
            untouched.append(name)
        stats = disp.stats  # type: ignore[attr-defined]
        hits += sum(stats.cache_hits.values())
        n_miss = sum(stats.cache_misses.values())
        misses += n_miss
        if n_miss:
            compiled.append(name)
    return KernelCount(len(dispatchers), specs, hits, misses, sorted(compiled),
                       sorted(untouched))


def warm_scene(configs: Path, scene: Path) -> None:
    """Run the headless, ``serve`` and ``tire-curves`` paths once for ``scene``."""
    import numpy as np

    from simserver import cli
    from simserver.adapters.viewer import rows_from_state
    from simserver.core import layout as L
    from simserver.core.params import VP_CG_HEIGHT_M
    from simserver.server.app import SimServer
    from simserver.server.config import load_server_config
    from simserver.server.state_frame import compile_kernels as compile_state_frame
    from simserver.wire import protocol as proto

    # 1. headless: the soak command as a user runs it (its JSON summary is not wanted here).
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = cli.main(["soak", "--scene", str(scene), "--duration", "1", "--quiet"])
    if code != 0:
        sys.stdout.write(buf.getvalue())
        raise SystemExit(f"warm-up: 'simserver soak --scene {scene}' exited {code}")
    # 2. serve: what 'simserver serve --config ... --scene ...' compiles before its clock.
    cfg = load_server_config(configs / SERVER_CONFIG, scene=scene, viewer="off")
    physics = SimServer(cfg).physics
    physics.warm_up()
    physics.step()
    compile_state_frame(physics.world)  # the live loop's state records (its first bind)
    # 3. tire-curves: tire_forces called from Python with scalars.
    for tp in physics.tp:
        cli.tire_curve_data(tp, [cli.nominal_load_n(tp)], n_points=3,
                            combined_alpha_deg=(2.0,))
    # 4. view: a received state back into the core layout.
    rows_from_state(proto.new_state_record(), physics.axes, float(physics.vp[VP_CG_HEIGHT_M]),
                    np.zeros(L.N_STATE), np.zeros(L.N_OUT), np.zeros(L.N_INPUT))


def main(argv: list[str] | None = None) -> int:
    """Warm every scene, print a one-line report (and JSON with ``--json``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=Path, required=True, metavar="DIR",
                        help="the configs tree (server/, scenes/, vehicles/, tires/)")
    parser.add_argument("--scene", action="append", type=Path, default=None, metavar="FILE",
                        help="scene to warm (repeatable; default: "
                             + ", ".join(DEFAULT_SCENES) + " under --configs)")
    parser.add_argument("--expect-cached", action="store_true",
                        help="exit 1 if any kernel had to be compiled (cache not warm)")
    parser.add_argument("--json", action="store_true", help="also print the counts as JSON")
    args = parser.parse_args(argv)

    configs: Path = args.configs.resolve()
    scenes = args.scene or [configs / s for s in DEFAULT_SCENES]
    t0 = time.perf_counter()
    for scene in scenes:
        warm_scene(configs, Path(scene))
    wall_s = time.perf_counter() - t0
    k = count_kernels()
    import numba

    import simserver

    package = str(Path(simserver.__file__).parent)
    from simserver.core import CACHE_DIR_ENV, shared_cache_dir

    shared = os.environ.get(CACHE_DIR_ENV)
    cache_dir = (str(shared_cache_dir(shared)) if shared
                 else os.environ.get("NUMBA_CACHE_DIR") or "(next to the sources)")
    print(f"warm-up: {len(scenes)} scenes in {wall_s:.1f} s; {k.dispatchers} kernels, "
          f"{k.cache_hits} specialisations loaded from the cache, {k.cache_misses} compiled "
          f"(simserver {package}, numba {numba.__version__}, cache {cache_dir}, "
          f"CPU {numba.config.CPU_NAME or 'host'})", flush=True)
    if args.json:
        print(json.dumps({"wall_s": wall_s, "scenes": [str(s) for s in scenes],
                          "package": package, "numba_cache_dir": cache_dir, **vars(k)}),
              flush=True)
    if args.expect_cached and k.cache_misses:
        print("warm-up: expected a warm cache, but these were compiled: "
              + ", ".join(k.names_compiled), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
