"""The world's controls in the live loop: cars added and removed while the world runs.

``{prefix}/world/ctl/{add_car, remove_car, get_config}`` (``protocol.WORLD_CONTROL_SPECS``,
docs/protocol.md section 5.1). The loop calls :meth:`WorldDesk.tick` once a tick; nothing
slow runs there:

- ``add_car``: checked in the tick (the id, the count, ``driven_by`` with its ``driver``
  block), its files read by the load worker
  (the vehicle file, the world's scene for its defaults and roads: the scene its cars
  stand on now, which a world of one car may have loaded while running; a start on the road and
  clear of where the other cars are now: ``simserver.server.cars_config.new_car``; a
  driven car's ``driver`` block parsed as a ``cars:`` entry's, its path on the road, and
  the path sampled: ``cars_config.driver_spec``, ``live_drivers.sample_path``), its
  transport made in
  a thread of the desk (``make_ports``: the zenoh subscriber, publishers, queryable and liveliness
  token, milliseconds), then the car made alone and moved into the world between two
  ticks (``fleet.join_world``; a driven car's driver handed to the loop's
  ``live_drivers`` and the drivers reassembled, the others' driver states kept) and
  served from the next tick; answered then.
- ``remove_car``: the car taken out between two ticks (``ServerLoop.remove``), its
  transport closed in the desk's thread.
- ``reset``: every car back to its start together: the start states made one car a tick
  beside the running world (``VehicleSlot.begin_reset``, settled in pieces), then all
  committed in one tick (a copy of each car's rows).
- ``get_config``: the cars, who drives each, ``max_cars`` and ``world_hz``.

One add, remove or reset at a time: another meanwhile is answered busy.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from simserver.adapters.validate import ConfigError, confined_to
from simserver.core.layout import TIME_S
from simserver.server import cars_config, fleet
from simserver.server.load_worker import opened
from simserver.wire import protocol as proto

log = logging.getLogger("simserver.server")


def prepare_added_car(car_id: str, vehicle: str | None, pose: dict[str, float] | None,
                      scene_path: Path, config_dirs: tuple[Path, ...], cwd: str,
                      config_folder: Path, dt_s: float,
                      others: dict[str, Any],
                      driver: dict[str, Any] | None = None,
                      start: dict[str, Any] | None = None) -> tuple[str, Any]:
    """Read and check a car to add (run in the load worker): ``("ok", (scene, table,
    vehicle path, driven))`` or ``("error", field, message)`` (errors as data: they cross
    a process boundary). ``driver``: the ``driver`` block of a car ``driven_by: driver``
    (as JSON gave it); ``driven`` is then its ``DriverSpec`` and its path's rows sampled
    over the scene's terrain, else None. ``start``: road, s and lane instead of
    ``pose``."""
    from simserver.server.live_drivers import sample_path
    from simserver.server.slot import redacted, resolve_config_path
    from simserver.sim.scene_files import load_scene

    try:
        vehicle_path = None if vehicle is None else resolve_config_path(
            "vehicle", vehicle, config_dirs, cwd, config_folder)
    except proto.ProtocolError as exc:
        return "error", exc.field, redacted(str(exc), config_dirs, cwd)
    spec = cars_config.CarSpec(id=car_id, where=f"add_car ({car_id})", vehicle=vehicle_path,
                               pose=pose, start=start,
                               driven_by="client" if driver is None else "driver",
                               driver=driver)
    with confined_to(config_dirs):
        try:
            scene, table = cars_config.new_car(spec, load_scene(scene_path), dt_s, others)
        except ConfigError as exc:
            message = redacted(str(exc), config_dirs, cwd)
            key = re.search(r"key '((?:vehicle|id|start)\b[^']*)'", message)
            field = key.group(1) if key else "start" if start is not None else "pose"
            return "error", field, message
        driven = None
        if driver is not None:
            try:  # the headless scenarios' parser: a path off the road is refused
                block = cars_config.driver_spec(spec, scene)
            except ConfigError as exc:
                message = redacted(str(exc), config_dirs, cwd)
                return "error", driver_field(message), message
            driven = (block, sample_path(block, scene.terrain))
    return "ok", (scene, table, vehicle_path, driven)


def driver_field(message: str) -> str:
    """The argument a ``driver`` block's error is about: the key it names
    (``driver.path``, ``driver.idm.T_s``), the part of the block whose keys are wrong
    (``(driver.path): missing key 'road'``), or the block."""
    key = re.search(r"key '(driver(?:\.[^']*)?)'", message)
    part = re.search(r"\((driver(?:\.[^)]*)?)\):", message)
    return key.group(1) if key else part.group(1) if part else "driver"


@dataclasses.dataclass
class _Adding:
    request: Any
    car_id: str
    job: Future | None = None
    prepared: tuple[Any, Any, Path | None, Any] | None = None
    ports: Future | None = None


class WorldDesk:
    """Serves the world's controls from the loop (module docstring).

    Parameters
    ----------
    loop : ServerLoop
        The loop whose slots are the world's cars (its ``preparer`` reads the files).
    cfg : ServerConfig
        ``max_cars``, ``world_hz``, the scene, the config folders, each car's settings.
    controls : ControlInbox
        The world's control requests (``validate=False``: validated here).
    make_ports : callable
        ``make_ports(slot_cfg) -> SlotPorts``: a new car's transport (run in a thread).
    close_ports : callable
        ``close_ports(slot, ports)``: a removed car's (run in a thread).
    """

    def __init__(self, loop: Any, cfg: Any, controls: Any,
                 make_ports: Callable[[Any], Any], close_ports: Callable[[Any, Any], None],
                 on_added: Callable[[Any], None] | None = None) -> None:
        self.loop = loop
        self.cfg = cfg
        self.controls = controls
        self.make_ports = make_ports
        self.close_ports = close_ports
        self.on_added = on_added
        self._threads = ThreadPoolExecutor(max_workers=1, thread_name_prefix="world-desk")
        self._adding: _Adding | None = None
        self._resetting: dict[str, Any] | None = None

    def close(self) -> None:
        self._threads.shutdown(wait=True)

    def _ids(self) -> list[str]:
        return [s.keys.vehicle for s, _ in self.loop.slots]

    def tick(self, now: int) -> None:
        """Advance an add in progress one step; serve at most one new request."""
        if self._adding is not None:
            self._advance(self._adding)
        if self._resetting is not None:
            self._reset_step(self._resetting)
        for request in self.controls.poll(1):
            try:
                args = proto.validate_control(request.name, request.payload,
                                              proto.WORLD_CONTROL_SPECS)
                members = getattr(self, f"_ctl_{request.name}")(request, args)
            except proto.ProtocolError as exc:
                request.reply(proto.reply_error(exc))
                continue
            except Exception as exc:  # a bug must not stop the loop: answer, log
                log.error("world control %s failed", request.name, exc_info=exc)
                request.reply(proto.reply_error(
                    f"{request.name}: internal error ({type(exc).__name__})", request.name))
                continue
            if members is not None:
                request.reply(proto.reply_ok(**members))

    # ------------------------------------------------------------------ the controls
    def _ctl_get_config(self, request: Any, args: dict[str, Any]) -> dict[str, Any]:
        return {"cars": [{"id": s.keys.vehicle, "driven_by": s.driven_by}
                         for s, _ in self.loop.slots],
                "max_cars": self.cfg.max_cars, "world_hz": self.cfg.world_hz}

    def _busy(self, name: str) -> None:
        if self._adding is not None or self._resetting is not None:
            what = "a car is still being added" if self._adding else "a reset is under way"
            raise proto.ProtocolError(name, f"busy: {what}; ask again when it has been "
                                      "answered")

    def _ctl_reset(self, request: Any, args: dict[str, Any]) -> None:
        self._busy("reset")
        self._resetting = {"request": request, "staged": [], "slots": [
            s for s, _ in self.loop.slots]}
        self._reset_step(self._resetting)
        return None

    def _reset_step(self, job: dict[str, Any]) -> None:
        """Make the next car's start (or settle it a piece further); when every car's is
        ready, commit them all in this tick and answer."""
        from simserver.server.loop import SETTLE_STEPS_PER_TICK

        staged = job["staged"]
        slots = job["slots"]
        if staged and not staged[-1].advance(SETTLE_STEPS_PER_TICK):
            return
        if len(staged) < len(slots):
            try:
                slot = slots[len(staged)]  # a served scenario's car restarts at its speed
                staged.append(slot.begin_reset(getattr(slot, "world_reset_args", {})))
            except Exception as exc:  # noqa: BLE001 - answered; nothing was changed
                self._resetting = None
                job["request"].reply(proto.reply_error(f"reset: {exc}", "reset"))
            return
        self._resetting = None
        current = [s for s, _ in self.loop.slots]
        # the world's one clock restarts at 0 (each car's commit keeps the world's time)
        current[0].sim.world.data.x[:, TIME_S] = 0.0
        for slot, start in zip(slots, staged, strict=True):
            if slot in current:  # not removed meanwhile
                start.commit()
        self.loop.assemble_drivers(fresh=True)  # the built-in drivers start anew too
        job["request"].reply(proto.reply_ok(cars=self._ids()))

    def _ctl_add_car(self, request: Any, args: dict[str, Any]) -> None:
        self._busy("add_car")
        if self._adding is not None:
            raise proto.ProtocolError("add_car", "busy: a car is still being added; ask "
                                      "again when it has been answered")
        car_id = args["id"]
        try:
            cars_config.check_car_id("add_car", car_id)
        except ConfigError as exc:
            raise proto.ProtocolError(
                "id", str(exc).removeprefix("add_car: key 'id': ")) from None
        if car_id in self._ids():
            raise proto.ProtocolError("id", f"the world has a car {car_id!r} already")
        if len(self.loop.slots) >= self.cfg.max_cars:
            raise proto.ProtocolError("id", f"the world has {len(self.loop.slots)} cars, "
                                      f"max_cars ({self.cfg.max_cars})")
        if "pose" in args and "start" in args:
            raise proto.ProtocolError("start", "give pose or start, not both")
        driver = args.get("driver")
        if args["driven_by"] == "driver" and driver is None:
            raise proto.ProtocolError("driver", f"car {car_id!r} is driven by the driver "
                                      "and needs a driver block (path or lane, speed "
                                      "profile, idm, stop_s_m, go_t_s)")
        if args["driven_by"] != "driver" and driver is not None:
            raise proto.ProtocolError("driver", f"car {car_id!r} is driven_by "
                                      f"{args['driven_by']}; only a car driven_by driver "
                                      "takes a driver block")
        cfg = self.cfg
        others = fleet.poses_now([s for s, _ in self.loop.slots])
        job = self.loop.preparer.submit(
            prepare_added_car, car_id, args.get("vehicle"), args.get("pose"), self._scene(),
            tuple(cfg.config_dirs), os.getcwd(), cfg.path.parent, cfg.period_s, others,
            driver, args.get("start"))
        self._adding = _Adding(request, car_id, job=job)
        self._advance(self._adding)  # an inline preparer (tests) is done already
        return None

    def _advance(self, adding: _Adding) -> None:
        """One step of an add: the worker's result, then the transport, then the join."""
        if adding.job is not None:
            if not adding.job.done():
                return
            job, adding.job = adding.job, None
            try:
                result = opened(job.result())
            except Exception as exc:  # the worker failed: nothing changed
                self._fail(adding, "add_car", f"add_car: the worker preparing it failed "
                                              f"({type(exc).__name__}); nothing changed")
                return
            if result[0] != "ok":
                _, field, message = result
                self._fail(adding, field, message)
                return
            adding.prepared = result[1]
            slot_cfg = self._slot_cfg(adding.car_id)
            adding.ports = self._threads.submit(self.make_ports, slot_cfg)
            return
        if adding.ports is None or not adding.ports.done():
            return
        try:
            ports = adding.ports.result()
        except Exception as exc:
            self._fail(adding, "add_car", f"add_car: its transport could not be made "
                                          f"({type(exc).__name__}: {exc}); nothing changed")
            return
        scene, table, _vehicle, driven = adding.prepared
        world = self.loop.slots[0][0].sim.world
        slot = fleet.join_world(self._slot_cfg(adding.car_id), scene, table, world)
        if driven is not None:  # its driver, prepared by the worker: loop.add assembles
            if self.loop.live_drivers is None:  # the world's drivers with it
                from simserver.server.live_drivers import LiveDrivers

                self.loop.live_drivers = LiveDrivers()
            self.loop.live_drivers.take(adding.car_id, *driven)
            slot.drive_by_driver()
        slot.warm_up()  # microseconds: every kernel (drive() too) is compiled already
        self.loop.add(slot, ports)
        if self.on_added is not None:
            self.on_added(slot)
        self._adding = None
        log.info("car %s added to the world (%d cars)", adding.car_id, len(self.loop.slots))
        adding.request.reply(proto.reply_ok(car=adding.car_id, cars=self._ids()))

    def _fail(self, adding: _Adding, field: str, message: str) -> None:
        self._adding = None
        adding.request.reply(proto.reply_error(message, field=field))

    def _scene(self) -> Path:
        """The world's scene now: the one its cars stand on (a world of one car may have
        loaded another than the server config's while running; a car of several loads
        another vehicle only, on the world's scene)."""
        return self.loop.slots[0][0].scene_path

    def _slot_cfg(self, car_id: str) -> Any:
        cfg = self.cfg  # the world's scene: the new car's log names it, its replay loads it
        return dataclasses.replace(cfg, vehicle_id=car_id, scene=self._scene(),
                                   command_log=fleet.car_log_path(cfg.command_log, car_id,
                                                                  True))

    def _ctl_remove_car(self, request: Any, args: dict[str, Any]) -> dict[str, Any]:
        car_id = args["id"]
        slot = next((s for s, _ in self.loop.slots if s.keys.vehicle == car_id), None)
        if slot is None:
            raise proto.ProtocolError("id", f"no car {car_id!r} in the world (cars: "
                                      f"{', '.join(self._ids())})")
        if len(self.loop.slots) == 1:
            raise proto.ProtocolError("id", f"{car_id!r} is the world's last car")
        self._busy("remove_car")
        slot.final_state = slot.sim.x.copy()  # its rows leave the world with it
        if slot.command_log is not None:  # where it left: a world replay takes it out there
            slot.command_log.write({"step": slot.steps_total, "world": {
                "event": "leave", "step": slot.sim.world.steps}})
        ports = self.loop.remove(slot)
        self._threads.submit(self.close_ports, slot, ports)
        log.info("car %s removed from the world (%d cars)", car_id, len(self.loop.slots))
        return {"car": car_id, "cars": self._ids()}
