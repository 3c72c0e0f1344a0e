"""The command log: every applied input change and every control that changes the physics,
one JSON line each (``CommandLog``, written off the tick), read back and checked
(``read_command_log``) and re-run headless bit for bit (``replay_command_log``)."""

from __future__ import annotations

import json
import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.validate import ConfigError, check_keys, number, short_repr
from simserver.core import layout as L
from simserver.server.config import SERVER_KEYS
from simserver.server.logfile import LogWriter, open_log_file
from simserver.sim.scene import INITIAL_RANGES, Scene
from simserver.sim.scene_files import load_scene
from simserver.sim.simulation import Simulation
from simserver.wire import protocol as proto

log = logging.getLogger("simserver.server")

COMMAND_LOG_FLUSH_S = 0.1
"""Longest time an applied input stays in the command log's buffer before it is written."""


class CommandLog:
    """Applied inputs and physics-changing controls, one JSON object a line.

    Lines: a header (scene, vehicle, step); ``{"step": n, "inputs": [steer, throttle,
    brake, parking_brake, gear]}`` whenever the applied inputs change (before physics step
    ``n``); ``{"step": n, "reset": pose|null}``, ``{"step": n, "set_road": {...}}``,
    ``{"step": n, "load": {"scene": ..., "vehicle": ...}}``; a car of a world of several
    cars also ``{"step": n, "world": {"event": "join"|"resume"|"leave", "step": W, ...}}``
    (its step ``n`` is the world's step ``W``: where it joined, with ``car`` and the
    world's ``cars`` in order; where it steps again after being held alone; where it
    left: ``simserver.server.world_replay``, which a replay of this log alone ignores);
    and at a clean shutdown
    ``{"end": n, "state": [hex floats]}``, the full final state, for checking a replay.
    A log that could not be written to its end (a full disk, an I/O error) ends instead
    with ``{"end": n, "cut": reason}``: every line before it is whole and the replay of its
    ``n`` steps is the live run's.

    Written off the tick (``docs/reliability.md``, "Logs that fail safe"): the tick thread
    only formats a line and hands it to a :class:`simserver.server.logfile.LogWriter`, whose own
    thread writes control lines at once and input lines at least every
    ``COMMAND_LOG_FLUSH_S / 2``, so a ``kill -9`` of the server loses at most the last
    :data:`COMMAND_LOG_FLUSH_S` of inputs; a line torn by the kill is ignored by
    :func:`read_command_log`. No ``fsync`` but at a clean shutdown: what the server wrote
    survives the server's crash, not a crash of the machine. A write that fails closes the
    log with one warning and the live loop goes on. The file is opened by
    :func:`simserver.server.logfile.open_log_file` (no symbolic link, regular files only, never
    blocking).
    """

    def __init__(self, path: Path, header: dict[str, Any]) -> None:
        fd = open_log_file(path, "command log")
        self._writer = LogWriter(fd, path, self._cut_line, COMMAND_LOG_FLUSH_S / 2,
                                 what="command log")
        self._logged_inputs = np.full(L.N_INPUT, np.nan)
        self._writer.put(0, json.dumps({"simserver_command_log": 1, **header},
                                       separators=(",", ":")) + "\n", urgent=True)

    @staticmethod
    def _cut_line(step: int, reason: str) -> str:
        return json.dumps({"end": step, "cut": reason}, separators=(",", ":")) + "\n"

    @property
    def cut(self) -> str | None:
        """Why the log was cut (closed before the end), or None."""
        return self._writer.cut

    def write(self, entry: dict[str, Any]) -> None:
        """Append one control line (``{"step": n, ...}``), written at once."""
        if not self._writer.stopped:
            self._writer.put(entry["step"], json.dumps(entry, separators=(",", ":")) + "\n",
                             urgent=True)

    def log_inputs(self, step: int, inputs: np.ndarray) -> None:
        """The inputs applied at physics step ``step``, if they changed since the last line
        (called at every step)."""
        if not self._writer.stopped and not np.array_equal(inputs, self._logged_inputs):
            self._logged_inputs[:] = inputs
            self._writer.put(step, json.dumps({"step": step,
                                               "inputs": [float(v) for v in inputs]},
                                              separators=(",", ":")) + "\n")

    def close(self, steps: int, state: np.ndarray) -> None:
        """Write the end line with the exact final state, fsync and close (a log already
        cut stays as it is)."""
        self._writer.close((steps, json.dumps({"end": steps, "state": [float(v).hex()
                                                                       for v in state]},
                                              separators=(",", ":")) + "\n"))


# ---------------------------------------------------------------------- replay
@dataclass
class Replay:
    """A command log re-run headless: the state after every step, and the final state.

    ``logged_final_state`` is the log's ``end`` state as written, which may be shorter
    than ``N_STATE``: a log written before state slots were appended (``core.layout``)
    holds the older layout, a prefix of this one. ``final_state_matches`` compares them
    on the slots both have.
    """

    states: np.ndarray  # (steps, N_STATE): state after step k
    outputs: np.ndarray  # (steps, N_OUT): forces at the start of step k
    final_state: np.ndarray
    logged_final_state: np.ndarray | None
    steps: int
    cut: str | None = None  # why the log was cut at ``steps`` (it holds no final state)

    @property
    def final_state_matches(self) -> bool | None:
        """The replayed final state equals the logged one bit for bit on the common slots
        (None if the log has no end state)."""
        if self.logged_final_state is None:
            return None
        n = self.logged_final_state.size
        return n <= self.final_state.size and bool(
            np.array_equal(self.final_state[:n], self.logged_final_state))


MAX_REPLAY_STEPS = 2_500_000
"""Longest log replayed (about 42 min at 1 kHz): the replay keeps every state and output in
memory, 800 bytes a step (2 GB at this limit)."""
_LOG_INPUT_RANGES = ((-1.0, 1.0), (0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (0.0, 3.0))
"""Ranges of the logged inputs, in the order of ``core.layout.INPUT_NAMES``."""


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number a command log holds")


def _log_numbers(where: str, key: str, value: Any, spec: dict[str, tuple[float, float]],
                 ) -> dict[str, float]:
    if not isinstance(value, dict) or set(value) != set(spec):
        raise ConfigError(f"{where}: key '{key}': expected an object with "
                          f"{', '.join(spec)}")
    return {k: number(where, f"{key}.{k}", value[k], *spec[k]) for k in spec}


def _control_ranges(control: str, member: str | None = None) -> dict[str, tuple[float, float]]:
    """The ranges of a control's numeric arguments, from the protocol's table."""
    args = proto.CONTROL_SPECS[control].args
    if member is not None:
        args = next(a for a in args if a.name == member).children
    return {a.name: (a.lo, a.hi) for a in args}


def _check_log_entry(where: str, entry: Any, last_step: int) -> int:
    """Validate one event line of a command log; its step."""
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: expected a JSON object, got {type(entry).__name__}")
    if "end" in entry:
        check_keys(where, entry, ("end", "state", "cut"), required=("end",))
        end = entry["end"]
        if isinstance(end, bool) or not isinstance(end, int) or \
                not last_step <= end <= MAX_REPLAY_STEPS:
            raise ConfigError(f"{where}: key 'end': expected an integer step in "
                              f"[{last_step}, {MAX_REPLAY_STEPS}], got {short_repr(end)}")
        if ("state" in entry) == ("cut" in entry):
            raise ConfigError(f"{where}: an end line holds either 'state' (a clean "
                              "shutdown) or 'cut' (a log that could not be written on)")
        if "cut" in entry:  # the log was cut there (CommandLog): no final state
            if not isinstance(entry["cut"], str) or len(entry["cut"]) > 500:
                raise ConfigError(f"{where}: key 'cut': expected the reason, a short text")
            return end
        state = entry["state"]
        # a log of an earlier release holds its shorter layout, a prefix of this one
        if not isinstance(state, list) or not L.N_STATE_V1 <= len(state) <= L.N_STATE:
            raise ConfigError(f"{where}: key 'state': expected {L.N_STATE} (or, from an "
                              f"earlier release, {L.N_STATE_V1} or more) hex floats")
        for k, v in enumerate(state):
            try:
                if not isinstance(v, str):
                    raise ValueError
                float.fromhex(v)
            except (ValueError, OverflowError):
                raise ConfigError(f"{where}: key 'state[{k}]': not a hex float: "
                                  f"{short_repr(v)}") from None
        return end
    kinds = [k for k in ("inputs", "reset", "set_road", "load", "world") if k in entry]
    if len(kinds) != 1:
        raise ConfigError(f"{where}: expected one of inputs, reset, set_road, load, world, "
                          "end")
    kind = kinds[0]
    check_keys(where, entry, ("step", kind), required=("step", kind))
    step = entry["step"]
    if isinstance(step, bool) or not isinstance(step, int) or \
            not last_step <= step <= MAX_REPLAY_STEPS:
        raise ConfigError(f"{where}: key 'step': expected an integer step in "
                          f"[{last_step}, {MAX_REPLAY_STEPS}] (steps never go back), got "
                          f"{short_repr(step)}")
    value = entry[kind]
    if kind == "inputs":
        if not isinstance(value, list) or len(value) != L.N_INPUT:
            raise ConfigError(f"{where}: key 'inputs': expected {L.N_INPUT} numbers")
        for name, v, (lo, hi) in zip(L.INPUT_NAMES, value, _LOG_INPUT_RANGES, strict=True):
            val = number(where, f"inputs.{name}", v, lo, hi)
            if name in ("parking_brake", "gear") and not val.is_integer():
                raise ConfigError(f"{where}: key 'inputs.{name}': {val:g} is not a whole "
                                  "number")
    elif kind == "reset":
        if value is not None:  # a reset control's pose, or a scene's start (a fault stop)
            spec = {k: INITIAL_RANGES[k] for k in ("x_m", "y_m", "yaw_rad")}
            if isinstance(value, dict) and "u_mps" in value:  # a reset at speed (issue 17)
                spec["u_mps"] = _control_ranges("reset")["u_mps"]
            if isinstance(value, dict) and "time_s" in value:  # the world's clock it kept
                spec["time_s"] = (0.0, MAX_REPLAY_STEPS * 1.0)
            _log_numbers(where, "reset", value, spec)
    elif kind == "set_road":
        _log_numbers(where, "set_road", value, _control_ranges("set_road"))
    elif kind == "world":
        _check_world_line(where, value)
    else:
        if not isinstance(value, dict) or set(value) != {"scene", "vehicle"} or \
                not isinstance(value["scene"], str) or \
                not isinstance(value["vehicle"], str | None):
            raise ConfigError(f"{where}: key 'load': expected {{\"scene\": path, "
                              "\"vehicle\": path or null}")
    return step


WORLD_EVENTS = ("join", "resume", "leave")
"""The events of a ``world`` line (a car of a world of several; ``CommandLog``)."""


def _check_world_line(where: str, value: Any) -> None:
    """A ``world`` line's value: ``{"event": join|resume|leave, "step": world step}``,
    a join's with ``"car"`` (this car's id) and ``"cars"`` (the world's ids in order)."""
    if not isinstance(value, dict) or value.get("event") not in WORLD_EVENTS:
        raise ConfigError(f"{where}: key 'world.event': expected one of "
                          f"{', '.join(WORLD_EVENTS)}")
    join = value["event"] == "join"
    keys = ("event", "step", "car", "cars") if join else ("event", "step")
    check_keys(f"{where} (world)", value, keys, required=keys)
    step = value["step"]
    if isinstance(step, bool) or not isinstance(step, int) or \
            not 0 <= step <= MAX_REPLAY_STEPS:
        raise ConfigError(f"{where}: key 'world.step': expected an integer step in "
                          f"[0, {MAX_REPLAY_STEPS}], got {short_repr(step)}")
    if join:
        cars = value["cars"]
        if not isinstance(cars, list) or not cars or \
                not all(isinstance(c, str) for c in cars) or len(set(cars)) != len(cars):
            raise ConfigError(f"{where}: key 'world.cars': expected the world's car ids, "
                              f"each once, got {short_repr(cars)}")
        if value["car"] not in cars:
            raise ConfigError(f"{where}: key 'world.car': {short_repr(value['car'])} is not "
                              "one of the world's cars ('world.cars')")


def read_command_log(path: str | Path) -> list[dict[str, Any]]:
    """Parse and validate a command log, with errors naming the file, line and key.

    A last line without its newline that is not valid JSON is the line the server was
    writing when it was killed (``kill -9``, a crash): it is dropped with a warning. Any
    other malformed line is an error (``ConfigError``), as are values a live server never
    logs (NaN, inputs out of range, steps going back, more than
    :data:`MAX_REPLAY_STEPS`).
    """
    path = Path(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise ConfigError(f"{path}: cannot read: not a regular file")
        with path.open("rb") as f:
            text = f.read().decode("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a simserver command log (not UTF-8 text at byte "
                          f"{exc.start})") from None
    lines = text.split("\n")
    torn = lines.pop()  # "" when the file ends with a newline, as every complete log does
    entries = []
    for n, line in enumerate(lines, 1):
        try:
            entries.append(json.loads(line, parse_constant=_reject_constant))
        except (ValueError, RecursionError) as exc:
            msg = exc.msg if isinstance(exc, json.JSONDecodeError) else str(exc) or "too deep"
            raise ConfigError(f"{path}:{n}: not a JSON line: {msg}") from None
    if torn:
        try:
            entries.append(json.loads(torn, parse_constant=_reject_constant))
        except (ValueError, RecursionError):
            log.warning("%s:%d: the last line is torn (the server was killed while writing "
                        "it): ignored", path, len(lines) + 1)
    header = entries[0] if entries else None
    if not isinstance(header, dict) or header.get("simserver_command_log") != 1:
        raise ConfigError(f"{path}: not a simserver command log (no header line)")
    where = f"{path}:1"
    if not isinstance(header.get("scene"), str):
        raise ConfigError(f"{where}: key 'scene': expected a scene path")
    number(where, "dt_s", header.get("dt_s"), *SERVER_KEYS["period_s"].range)
    last_step = 0
    for n, entry in enumerate(entries[1:], 2):
        if last_step is None:
            raise ConfigError(f"{path}:{n}: a line after the end line")
        step = _check_log_entry(f"{path}:{n}", entry, last_step)
        last_step = None if "end" in entry else step
    return entries


def apply_logged_reset(sim: Simulation, value: dict[str, Any] | None) -> None:
    """A ``reset`` line of a command log applied to its car: the scene's start (None) or
    the logged pose, at rest or at ``u_mps``; in a shared world the line also names the
    world's time the car kept (``time_s``, one clock: ``VehicleSlot.logged_start``), which
    a world reset makes 0 for every car. Used by the replay of a car alone and of a world."""
    pose = None if value is None else dict(value)
    clock = None if pose is None else pose.pop("time_s", None)
    sim.reset(pose, None if pose is None else pose.pop("u_mps", None))
    if clock is not None:
        sim.x[L.TIME_S] = clock


def replay_command_log(path: str | Path, progress: Any = None) -> Replay:
    """Re-run a command log headless with the same compiled step as the server."""
    entries = read_command_log(path)
    header = entries[0]

    def scene_of(line: int, key: str, scene: str, vehicle: str | None = None) -> Scene:
        try:
            return load_scene(scene, vehicle_path=vehicle)
        except ConfigError as exc:  # a file the log refers to: name the line and the key
            raise ConfigError(f"{path}:{line}: key '{key}': {exc}") from None

    physics = Simulation(scene_of(1, "scene", header["scene"]), float(header["dt_s"]))
    events = entries[1:]
    end = next((e for e in events if "end" in e), None)
    total = int(end["end"]) if end else max((int(e.get("step", 0)) for e in events), default=0)
    states = np.zeros((total, L.N_STATE))
    outputs = np.zeros((total, L.N_OUT))
    k = 0
    for n in range(total + 1):
        while k < len(events) and events[k].get("step") == n:
            e = events[k]
            if "inputs" in e:
                physics.inputs[:] = e["inputs"]
            elif "reset" in e:
                apply_logged_reset(physics, e["reset"])
            elif "set_road" in e:
                physics.set_road(**e["set_road"])
            elif "load" in e:
                spec = e["load"]
                physics.load(scene_of(k + 2, "load", spec["scene"], spec["vehicle"]))
            k += 1
        if n == total:
            break
        physics.step()
        states[n] = physics.x
        outputs[n] = physics.out
        if progress is not None and n % 10000 == 0:
            progress(n, total)
    logged = None if end is None or "state" not in end else \
        np.array([float.fromhex(v) for v in end["state"]])
    return Replay(states=states, outputs=outputs, final_state=physics.x.copy(),
                  logged_final_state=logged, steps=total,
                  cut=None if end is None else end.get("cut"))
