"""The live server's configuration: ``ServerConfig`` and its reader, ``load_server_config``
(``configs/server/default.yaml`` documents each key)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from simserver.adapters.validate import (
    ConfigError,
    check_keys,
    integer,
    is_path_text,
    number,
    read_yaml,
    short_repr,
)
from simserver.ros2 import cli as ros2_cli
from simserver.server import cars_config
from simserver.server.logfile import check_log_path
from simserver.server.realtime import (
    DEFAULT_RT_PRIORITY,
    REALTIME_MODES,
    RealtimeSettings,
    parse_cpus,
)
from simserver.wire import protocol as proto

REPO_CONFIGS = Path(__file__).resolve().parents[2] / "configs"
DEFAULT_SERVER_CONFIG = REPO_CONFIGS / "server" / "default.yaml"

TLS_FRONT_MODES = ("auto", "off")
"""``tls_front``: auto puts :mod:`simserver.adapters.tls_front` before every ``tls/`` listen
endpoint (docs/security.md section 5); off lets zenoh listen on them itself."""


@dataclass
class ServerConfig:
    """Validated server settings (``configs/server/default.yaml`` documents each key)."""

    path: Path
    scene: Path
    prefix: str = "simserver"
    vehicle_id: str = "car0"
    zenoh_config: Path | None = None
    listen: list[str] | None = None
    connect: list[str] | None = None
    mode: str | None = None
    period_s: float = 0.001
    state_every: int = 1
    diag_hz: float = 5.0
    watchdog_s: float = 0.2
    watchdog_brake: float = 0.6
    max_catchup_ticks: int = 100
    load_stall_s: float = 10.0  # server_loop.JOB_TIMEOUT_S
    load_timeout_s: float = 300.0  # server_loop.LOAD_TIMEOUT_S
    command_log: Path | None = None
    config_dirs: list[Path] = field(default_factory=list)
    viewer: str = "off"
    viewer_fps: float = 50.0  # adapters.viewer.DEFAULT_FPS (a test checks they agree)
    realtime: str = "auto"
    rt_priority: int = DEFAULT_RT_PRIORITY
    rt_cpus: tuple[int, ...] = ()
    rt_lock_memory: bool = False
    ros2: dict[str, Any] | None = None  # the ROS 2 adapter's settings; None: off
    tls_front: str = "auto"  # auto: an accept-filtering front per tls/ listen endpoint
    cars: list[cars_config.CarSpec] | None = None  # None: the one car vehicle_id
    max_cars: int = cars_config.DEFAULT_MAX_CARS
    world_hz: float = proto.WORLD_HZ_DEFAULT  # the world message's rate

    def realtime_settings(self) -> RealtimeSettings:
        """The real-time scheduling asked for (``simserver.server.realtime``)."""
        return RealtimeSettings(mode=self.realtime, priority=self.rt_priority,
                                cpus=self.rt_cpus, lock_memory=self.rt_lock_memory)


def _string_list(path: Path, key: str, value: Any) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{path}: key '{key}': expected a string or a list of strings")
    return list(value)


ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe",
                   "serial", "vsock")
"""The link protocols a zenoh endpoint may name (``proto/address``)."""
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def _check_endpoint(where: str, endpoint: str) -> None:
    """A zenoh endpoint ``proto/address[?params][#config]`` with a known protocol and, for
    IP protocols, ``host:port`` with a port in 0-65535; errors name ``where``."""
    proto_name, sep, rest = endpoint.partition("/")
    if not sep or proto_name not in ZENOH_PROTOCOLS:
        raise ConfigError(f"{where}: {short_repr(endpoint)}: expected PROTOCOL/ADDRESS with "
                          f"PROTOCOL one of {', '.join(ZENOH_PROTOCOLS)}")
    if proto_name in _IP_PROTOCOLS:
        address = rest.split("?", 1)[0].split("#", 1)[0]
        host, colon, port = address.rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ConfigError(f"{where}: {short_repr(endpoint)}: expected "
                              f"{proto_name}/HOST:PORT with a port in 0-65535")


def _check_command_log(where: str, log_path: Path) -> None:
    """The command log's file can be created: not a folder, in an existing folder, not a
    symbolic link nor anything but a regular file (checked again when it is opened)."""
    if log_path.is_dir():
        raise ConfigError(f"{where}: {log_path} is a folder, not a file")
    if not log_path.parent.is_dir():
        raise ConfigError(f"{where}: the folder {log_path.parent} does not exist")
    why = check_log_path(log_path)
    if why is not None:
        raise ConfigError(f"{where}: {log_path} {why}")


def _log_path(path: str | Path) -> Path:
    """An absolute log path whose last part is kept as it is: a symbolic link there is
    refused, never followed (``simserver.server.logfile``)."""
    path = Path(os.path.abspath(path))
    return path.parent.resolve() / path.name


# ------------------------------------------------------------------- reading the file
@dataclass(frozen=True)
class Sources:
    """The server file's values with the command line's over them, and where each came
    from (for errors that name the file and key, or the option)."""

    path: Path  # the server file, absolute
    values: dict[str, Any]  # key -> value; paths already made absolute
    from_cli: frozenset[str]
    ros2_flag: bool | None  # --ros2/--no-ros2, which switch the file's ros2 section

    def where(self, key: str) -> str:
        """``file: key 'k'``, or ``command line: option '--k'`` for a value given there."""
        if key in self.from_cli:
            return f"command line: option '--{key.replace('_', '-')}'"
        return f"{self.path}: key '{key}'"


PATH_KEYS = ("scene", "zenoh_config", "command_log")
"""The keys that name a file: relative to the server file in it, to the working directory
on the command line."""


def read_sources(path: str | Path, overrides: dict[str, Any]) -> Sources:
    """Read the server file and lay the command line's values (those not None) over it."""
    path = Path(path).resolve()
    overrides = dict(overrides)
    ros2_flag = overrides.pop("ros2", None)
    data = read_yaml(path)
    check_keys(path, data, tuple(SERVER_KEYS), required=("scene",))
    for key in PATH_KEYS:
        if (key == "scene" or data.get(key) is not None) and not is_path_text(data.get(key)):
            raise ConfigError(f"{path}: key '{key}': expected a file path")
    values = {k: _absolute(k, path.parent / v) if k in PATH_KEYS and isinstance(v, str) else v
              for k, v in data.items()}
    if overrides.get("zenoh_config") is not None:
        # a zenoh file given on the command line decides its own endpoints and mode,
        # unless they are given on the command line too
        for key in ("listen", "connect", "mode"):
            values.pop(key, None)
    from_cli = set()
    for key, value in overrides.items():
        if value is None:
            continue
        if key not in SERVER_KEYS:
            raise ConfigError(f"command line: unknown server setting '{key}'")
        values[key] = _absolute(key, value) if key in PATH_KEYS else value
        from_cli.add(key)
    return Sources(path, values, frozenset(from_cli), ros2_flag)


def _absolute(key: str, path: str | Path) -> Path:
    """A file key's path made absolute; the command log's last part kept as it is."""
    return _log_path(path) if key == "command_log" else Path(path).resolve()


# One reader per kind of key: (the sources, the key, its value) -> the setting. Errors name
# the file and key as the checks of adapters.validate do (the listen and connect endpoints,
# the files, tls_front and viewer name the command-line option when the value came there).
Reader = Callable[[Sources, str, Any], Any]


@dataclass(frozen=True)
class ServerKey:
    """One key of the server file: how its value is read, and its range if numeric."""

    read: Reader | None  # None: read with the others at the end (ros2)
    range: tuple[float, float] | None = None


def _number_key(lo: float, hi: float) -> ServerKey:
    return ServerKey(lambda src, key, value: number(src.path, key, value, lo, hi), (lo, hi))


def _integer_key(lo: int, hi: int) -> ServerKey:
    return ServerKey(lambda src, key, value: integer(src.path, key, value, lo, hi), (lo, hi))


def _text(src: Sources, key: str, value: Any) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{src.path}: key '{key}': expected a string")
    return value


def _one_of(choices: tuple[str, ...], src_where: bool = False, expected: str | None = None
            ) -> ServerKey:
    def read(src: Sources, key: str, value: Any) -> str:
        text = _text(src, key, value)
        if text not in choices:
            where = src.where(key) if src_where else f"{src.path}: key '{key}'"
            raise ConfigError(f"{where}: expected " + (expected or (
                f"one of {', '.join(choices)}, got {text!r}")))
        return text
    return ServerKey(read)


def _existing_file(src: Sources, key: str, value: Any) -> Path:
    file = Path(value)
    if not file.is_file():
        raise ConfigError(f"{src.where(key)}: {file}: no such file")
    return file


def _endpoints(src: Sources, key: str, value: Any) -> list[str]:
    endpoints = _string_list(src.path, key, value)
    for endpoint in endpoints:
        _check_endpoint(src.where(key), endpoint)
    return endpoints


def _folders(src: Sources, key: str, value: Any) -> list[Path]:
    folders = _string_list(src.path, key, value)
    if not all(is_path_text(d) for d in folders):
        raise ConfigError(f"{src.path}: key '{key}': expected folder paths")
    return [(src.path.parent / d).resolve() for d in folders]


def _command_log(src: Sources, key: str, value: Any) -> Path:
    log_path = Path(value)
    _check_command_log(src.where(key), log_path)
    return log_path


def _cpus(src: Sources, key: str, value: Any) -> tuple[int, ...]:
    try:
        return parse_cpus(str(value))
    except ValueError as exc:
        raise ConfigError(f"{src.path}: key '{key}': {exc}") from None


def _flag(src: Sources, key: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{src.path}: key '{key}': expected true or false")
    return value


def _viewer(src: Sources, key: str, value: Any) -> str:
    """``off`` or a Rerun sink (``simserver.adapters.rerun_sink.parse_sink``)."""
    text = _text(src, key, value)
    if text == "off":
        return text
    from simserver.adapters.rerun_sink import RerunSinkError, _split_host_port, parse_sink

    try:
        mode, target = parse_sink(text)
        if mode == "serve" and target is not None:
            _split_host_port(mode, target, "127.0.0.1", 0)  # the port is in 1-65535
    except RerunSinkError as exc:
        raise ConfigError(f"{src.where(key)}: {exc}") from exc
    why = check_log_path(Path(target)) if mode == "save" and target else None
    if why is not None:  # a recording is written like a log (simserver.server.logfile)
        raise ConfigError(f"{src.where(key)}: {target} {why}")
    return text


SERVER_KEYS: dict[str, ServerKey] = {
    # the keys of a server file, in the order they are read (configs/server/default.yaml)
    "scene": ServerKey(_existing_file),
    "prefix": ServerKey(_text),
    "vehicle_id": ServerKey(_text),
    "zenoh_config": ServerKey(_existing_file),
    "listen": ServerKey(_endpoints),
    "connect": ServerKey(_endpoints),
    "mode": _one_of(("peer", "router", "client"), expected="peer, router or client"),
    "period_s": _number_key(0.0001, 0.1),
    "state_every": _integer_key(1, 1000),
    "diag_hz": _number_key(0.1, 100.0),
    "watchdog_s": _number_key(0.005, 60.0),
    "watchdog_brake": _number_key(0.0, 1.0),
    "max_catchup_ticks": _integer_key(0, 100000),
    "load_stall_s": _number_key(1.0, 600.0),
    "load_timeout_s": _number_key(1.0, 3600.0),
    "command_log": ServerKey(_command_log),
    "config_dirs": ServerKey(_folders),
    "viewer": ServerKey(_viewer),
    "viewer_fps": _number_key(0.1, 1000.0),
    "realtime": _one_of(REALTIME_MODES),
    "rt_priority": _integer_key(2, 99),
    "rt_cpus": ServerKey(_cpus),
    "rt_lock_memory": ServerKey(_flag),
    "ros2": ServerKey(None),
    "tls_front": _one_of(TLS_FRONT_MODES, src_where=True),
    "max_cars": _integer_key(*cars_config.MAX_CARS_RANGE),
    "world_hz": _number_key(1.0, 1000.0),
    "cars": ServerKey(None),  # read at the end: it needs max_cars (server.cars_config)
}
"""Every key of a server file and its reader; a new key is one row here and one field of
``ServerConfig`` (of the same name)."""


def load_server_config(path: str | Path, **overrides: Any) -> ServerConfig:
    """Load a server YAML; ``overrides`` (command-line flags) replace keys that are not None.

    Paths in the file are relative to it; paths in ``overrides`` to the working directory.
    Errors name the file and the key, or the command-line option that set it.
    """
    src = read_sources(path, overrides)
    settings = {key: spec.read(src, key, src.values[key]) for key, spec in SERVER_KEYS.items()
                if spec.read is not None and src.values.get(key) is not None}
    cfg = ServerConfig(path=src.path, **settings)
    try:
        proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
    except proto.ProtocolError as exc:
        raise ConfigError(f"{src.path}: {exc}") from exc
    try:
        cfg.ros2 = ros2_cli.serve_settings(src.values.get("ros2"), src.ros2_flag,
                                           source=f"{src.path}: ros2")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if src.values.get("cars") is not None:  # several cars in one world
        cfg.cars = cars_config.parse_cars(src.path, src.values["cars"], cfg.max_cars)
    if not cfg.config_dirs:
        cfg.config_dirs = [REPO_CONFIGS, src.path.parent]
    return cfg
