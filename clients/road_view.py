"""Where the car is on an OpenDRIVE road, for the driver's screen: road, lane, s and the
distance to the road's edge, on or off the road.

The server names its scene in ``get_config`` (``scene.path``, shown relative to its config
folders, and ``scene.terrain``); on an ``opendrive`` terrain this reads the scene file and
the ``.xodr`` road it names, the same file the server rasterised, once per scene and in a
thread of its own (a large road takes seconds), and places the state's world position on
it with ``simserver.adapters.road_position`` (the one projection the tests check against
the road's geometry). The server publishes no road coordinates: the road file is their one
source, and the client computes them at the screen's rate, never in the server's tick.
"""

from __future__ import annotations

import threading
from typing import Any

from simserver.adapters.config_paths import local_config_file

OPENDRIVE = "opendrive"


class RoadView:
    """The road of the server's scene, loaded in the background, and the car's place on it.

    ``line(x_m, y_m)`` is the screen's ``road`` line, or None when the scene has no
    OpenDRIVE road."""

    def __init__(self) -> None:
        self._scene: str | None = None
        self._locator: Any = None
        self._status = ""
        self._lock = threading.Lock()

    def follow(self, config: dict[str, Any]) -> None:
        """Take the scene of a ``get_config`` reply: a new OpenDRIVE scene starts loading
        its road (in a thread), any other scene clears it."""
        scene = config.get("scene", {})
        path, terrain = str(scene.get("path", "")), str(scene.get("terrain", ""))
        with self._lock:
            if path == self._scene:
                return
            self._scene, self._locator = path, None
            if terrain != OPENDRIVE:
                self._status = ""
                return
            self._status = f"loading the road of {path} ..."
        threading.Thread(target=self._load, args=(path,), name="driver-road",
                         daemon=True).start()

    def _load(self, shown: str) -> None:
        try:
            from simserver.adapters.opendrive import load_opendrive
            from simserver.adapters.road_position import RoadLocator
            from simserver.adapters.validate import read_yaml

            scene_file = local_config_file(shown)
            terrain = read_yaml(scene_file).get("terrain") or {}
            locator = RoadLocator(load_opendrive(scene_file.parent / str(terrain["file"])))
            status = ""
        except Exception as exc:  # noqa: BLE001 - any failure is shown, the driving goes on
            locator, status = None, f"cannot read the road of {shown}: {exc}"
        with self._lock:
            if self._scene == shown:
                self._locator, self._status = locator, status

    def line(self, x_m: float, y_m: float) -> str | None:
        """``road    road 1  lane -2 (driving)  s 250.3 m  to the edge 4.50 m  ON the road``
        (or ``OFF the road, 3.20 m beyond its edge``), a loading or error note, or None
        off an OpenDRIVE scene."""
        with self._lock:
            locator, status = self._locator, self._status
        if locator is None:
            return f"road    {status}" if status else None
        pos = locator.locate(x_m, y_m)
        if pos is None:
            return "road    OFF the road: no road within 200 m"
        where = (f"ON the road, {pos.edge_m:.2f} m from its edge" if pos.on_road else
                 f"OFF the road, {-pos.edge_m:.2f} m beyond its edge")
        return (f"road    road {pos.road}  lane {pos.lane} ({pos.lane_type})  "
                f"s {pos.s_m:7.1f} m  t {pos.t_m:+6.2f} m  {where}")
