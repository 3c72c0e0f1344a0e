"""Every car of a multi-car world in the live viewer's scene (issue 30 item 4).

The followed car is drawn in full under ``world/car`` from its own states
(``rerun_scene.SceneLogger``). Every car the world message (``{prefix}/world/state``,
docs/protocol.md section 5.1: each car's id and world pose, 80 bytes a car) names is drawn
under ``world/cars/{id}``: a transform (its CG's world position, yaw, pitch and roll,
z-y-x as ISO 8855) and, once per car, a body box labelled with its id. The followed car
gets only its label there (its full model is under ``world/car``). The world message is
cheap (one message for all the cars, at ``world_hz``), so the viewer needs no per-car
state subscriptions to draw traffic.

Each car is logged at the ``sim_time`` of the followed car's frame it is drawn with (the
world message at most one world period older than that frame: 10 ms at the default 100 Hz).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from simserver.adapters.rerun_scene import CARS, TIMELINE, quat_axis, quat_mul, time_ns

BOX_HALF_SIZES_M = (2.25, 0.9, 0.7)
"""Half length, width and height of the box drawn for a car: the world message carries no
dimensions, so every car gets a mid-size car's (4.5 x 1.8 x 1.4 m)."""
BOX_BOTTOM_BELOW_CG_M = 0.35
"""The box's bottom below the CG (a car's CG is about 0.5 m above the road, its floor
about 0.15 m): the box's centre is this much less than its half height above the CG."""
LABEL_ABOVE_CG_M = 1.4
"""Where the followed car's label sits above its CG (above the roof)."""
BOX_COLOR = (230, 150, 40, 255)


def car_path(car_id: str) -> str:
    """The entity path of car ``car_id``."""
    return f"{CARS}/{car_id}"


def world_quaternions(yaw_rad: np.ndarray, pitch_rad: np.ndarray,
                      roll_rad: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternions of body attitudes: yaw about z, then pitch about the new
    y, then roll about the newest x (ISO 8855 Tait-Bryan z-y'-x'')."""
    return quat_mul(quat_mul(quat_axis(2, yaw_rad), quat_axis(1, pitch_rad)),
                    quat_axis(0, roll_rad))


class FleetLogger:
    """Logs the cars of world messages to a recording.

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log.
    followed : str
        The car drawn in full under ``world/car``: labelled only.
    """

    def __init__(self, rec: Any, followed: str) -> None:
        self.rec = rec
        self.followed = followed
        self.drawn: set[str] = set()
        self.frames = 0

    def _static(self, car_id: str) -> None:
        path = car_path(car_id)
        if car_id == self.followed:
            self.rec.log(f"{path}/label", rr.Points3D([[0.0, 0.0, LABEL_ABOVE_CG_M]],
                                                     labels=[car_id], radii=0.05,
                                                     show_labels=True), static=True)
        else:
            hx, hy, hz = BOX_HALF_SIZES_M
            self.rec.log(f"{path}/box", rr.Boxes3D(
                centers=[[0.0, 0.0, hz - BOX_BOTTOM_BELOW_CG_M]], half_sizes=[[hx, hy, hz]],
                labels=[car_id], colors=[BOX_COLOR], fill_mode="majorwireframe",
                radii=0.03, show_labels=True), static=True)
        self.drawn.add(car_id)

    def log(self, time_s: float, world: Any) -> None:
        """Log every car of ``world`` (a ``protocol.WorldState``) at ``time_s``; cars
        whose pose is not finite are skipped (nothing non-finite is drawn)."""
        cars = world.cars
        if len(cars) == 0:
            return
        pos = np.stack([cars["x_m"], cars["y_m"], cars["z_m"]], axis=1).astype(np.float64)
        quat = world_quaternions(cars["yaw_rad"].astype(np.float64),
                                 cars["pitch_rad"].astype(np.float64),
                                 cars["roll_rad"].astype(np.float64))
        finite = np.isfinite(pos).all(axis=1) & np.isfinite(quat).all(axis=1)
        self.rec.set_time(TIMELINE, duration=time_ns(time_s)[()])
        for k, car_id in enumerate(world.ids):
            if not finite[k]:
                continue
            if car_id not in self.drawn:
                self._static(car_id)
            self.rec.log(car_path(car_id), rr.Transform3D(translation=pos[k],
                                                          quaternion=quat[k]))
        self.frames += 1
