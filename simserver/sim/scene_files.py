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
