"""Any scene file, by its kind: a YAML scene or scenario (``simserver.sim.scene``) or an
OpenSCENARIO ``.xosc``, whose ego's start is the scene (``simserver.sim.xosc_run``,
docs/openscenario.md). Everything that accepts a scene file (``serve --scene``,
``ctl/load``, ``add_car``, replay, the viewer's terrain) reads it here; this module sits
above both readers so that the scene layer does not import the scenario player."""

from __future__ import annotations

from pathlib import Path

from simserver.sim.scene import Scene
from simserver.sim.scene import load_scene as load_yaml_scene

OPENSCENARIO_SUFFIX = ".xosc"


def load_scene(path: str | Path, vehicle_path: str | Path | None = None) -> Scene:
    """Read a scene file of any kind; ``vehicle_path`` replaces the scene's vehicle."""
    if Path(path).suffix.lower() == OPENSCENARIO_SUFFIX:
        # imported here: the OpenSCENARIO reader and player cost a YAML scene nothing
        from simserver.sim.xosc_run import xosc_scene

        return xosc_scene(path, vehicle_path)
    return load_yaml_scene(path, vehicle_path)


def warm_up_in_helper(scene_path: str, dt_s: float,
                      names: tuple[str, ...] | None = None) -> None:
    """Compile (or load) the warm-up entry points ``names`` of a car of the scene at
    ``scene_path``, in the calling process: the server's load worker runs it as it starts
    (``simserver.server.app.SimServer``), so that on a cold cache these kernels compile on
    the second core, side by side with the server's compile of the step, and the server
    loads them from the cache (about 11 s of CPU of a cold start on one core less,
    ``python -m benchmarks.bench_compile --by-function``). The arrays' types are those of
    any car of any world (``World``), so the server's calls find the same signatures.
    ``names``: default ``simulation.HELPER_KERNELS``. Here, above both the scene and the
    scenario layers, as ``load_scene`` is (the simulation module is imported when called:
    reading a scene file compiles nothing)."""
    from simserver.sim.simulation import HELPER_KERNELS, Simulation

    names = HELPER_KERNELS if names is None else names
    sim = Simulation(load_scene(scene_path), dt_s)
    for name, call in sim.warm_up_calls(live=True):
        if name in names:
            call()
