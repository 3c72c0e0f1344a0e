"""The live server's configuration: ``ServerConfig`` and its reader, ``load_server_config``
(``configs/server/default.yaml`` documents each key)."""

from __future__ import annotations

import os
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

SERVER_KEYS: dict[str, tuple[float, float] | None] = {
    # key: numeric range, or None for non-numeric keys
    "scene": None,
    "prefix": None,
    "vehicle_id": None,
    "zenoh_config": None,
    "listen": None,
    "connect": None,
    "mode": None,
    "period_s": (0.0001, 0.1),
    "state_every": (1, 1000),
    "diag_hz": (0.1, 100.0),
    "watchdog_s": (0.005, 60.0),
    "watchdog_brake": (0.0, 1.0),
    "max_catchup_ticks": (0, 100000),
    "load_stall_s": (1.0, 600.0),
    "load_timeout_s": (1.0, 3600.0),
    "command_log": None,
    "config_dirs": None,
    "viewer": None,
    "realtime": None,
    "rt_priority": (2, 99),
    "rt_cpus": None,
    "rt_lock_memory": None,
    "ros2": None,
    "tls_front": None,
}


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
    realtime: str = "auto"
    rt_priority: int = DEFAULT_RT_PRIORITY
    rt_cpus: tuple[int, ...] = ()
    rt_lock_memory: bool = False
    ros2: dict[str, Any] | None = None  # the ROS 2 adapter's settings; None: off
    tls_front: str = "auto"  # auto: an accept-filtering front per tls/ listen endpoint

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


def load_server_config(path: str | Path, **overrides: Any) -> ServerConfig:
    """Load a server YAML; ``overrides`` (command-line flags) replace keys that are not None.

    Paths in the file are relative to it; paths in ``overrides`` to the working directory.
    Errors name the file and the key, or the command-line option that set it.
    """
    path = Path(path).resolve()
    ros2_flag = overrides.pop("ros2", None)  # --ros2/--no-ros2 switch the config's section
    data = read_yaml(path)
    check_keys(path, data, tuple(SERVER_KEYS), required=("scene",))
    for key in ("scene", "zenoh_config", "command_log"):
        if (key == "scene" or data.get(key) is not None) and not is_path_text(data.get(key)):
            raise ConfigError(f"{path}: key '{key}': expected a file path")
    base = {k: (path.parent / v).resolve() if k in ("scene", "zenoh_config")
            and isinstance(v, str) else v for k, v in data.items()}
    if isinstance(base.get("command_log"), str):
        base["command_log"] = _log_path(path.parent / base["command_log"])
    if overrides.get("zenoh_config") is not None:
        # a zenoh file given on the command line decides its own endpoints and mode,
        # unless they are given on the command line too
        for key in ("listen", "connect", "mode"):
            base.pop(key, None)
    from_cli: set[str] = set()
    for k, v in overrides.items():
        if v is not None:
            if k not in SERVER_KEYS:
                raise ConfigError(f"command line: unknown server setting '{k}'")
            base[k] = Path(v).resolve() if k in ("scene", "zenoh_config") else \
                _log_path(v) if k == "command_log" else v
            from_cli.add(k)

    def where(key: str) -> str:
        if key in from_cli:
            return f"command line: option '--{key.replace('_', '-')}'"
        return f"{path}: key '{key}'"

    cfg = ServerConfig(path=path, scene=Path(base["scene"]))
    for key, rng in SERVER_KEYS.items():
        if key not in base or key in ("scene", "ros2") or base[key] is None:
            continue
        value = base[key]
        if key in ("state_every", "max_catchup_ticks", "rt_priority"):
            lo, hi = rng
            setattr(cfg, key, integer(path, key, value, int(lo), int(hi)))
        elif rng is not None:
            setattr(cfg, key, number(path, key, value, *rng))
        elif key in ("listen", "connect"):
            endpoints = _string_list(path, key, value)
            for endpoint in endpoints:
                _check_endpoint(where(key), endpoint)
            setattr(cfg, key, endpoints)
        elif key == "config_dirs":
            folders = _string_list(path, key, value)
            if not all(is_path_text(d) for d in folders):
                raise ConfigError(f"{path}: key '{key}': expected folder paths")
            cfg.config_dirs = [(path.parent / d).resolve() for d in folders]
        elif key == "rt_cpus":
            try:
                cfg.rt_cpus = parse_cpus(str(value))
            except ValueError as exc:
                raise ConfigError(f"{path}: key 'rt_cpus': {exc}") from None
        elif key == "rt_lock_memory":
            if not isinstance(value, bool):
                raise ConfigError(f"{path}: key 'rt_lock_memory': expected true or false")
            cfg.rt_lock_memory = value
        elif key in ("prefix", "vehicle_id", "mode", "viewer", "realtime", "tls_front"):
            if not isinstance(value, str):
                raise ConfigError(f"{path}: key '{key}': expected a string")
            setattr(cfg, key, value)
        else:
            setattr(cfg, key, Path(value))
    if cfg.realtime not in REALTIME_MODES:
        raise ConfigError(f"{path}: key 'realtime': expected one of "
                          f"{', '.join(REALTIME_MODES)}, got {cfg.realtime!r}")
    if cfg.tls_front not in TLS_FRONT_MODES:
        raise ConfigError(f"{where('tls_front')}: expected one of "
                          f"{', '.join(TLS_FRONT_MODES)}, got {cfg.tls_front!r}")
    if cfg.mode not in (None, "peer", "router", "client"):
        raise ConfigError(f"{path}: key 'mode': expected peer, router or client")
    for key in ("scene", "zenoh_config"):
        file = getattr(cfg, key)
        if file is not None and not file.is_file():
            raise ConfigError(f"{where(key)}: {file}: no such file")
    if cfg.command_log is not None:
        _check_command_log(where("command_log"), cfg.command_log)
    try:
        proto.vehicle_keys(cfg.prefix, cfg.vehicle_id)
    except proto.ProtocolError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    if cfg.viewer != "off":
        from simserver.adapters.rerun_sink import RerunSinkError, _split_host_port, parse_sink

        try:
            mode, target = parse_sink(cfg.viewer)
            if mode == "serve" and target is not None:
                _split_host_port(mode, target, "127.0.0.1", 0)  # the port is in 1-65535
        except RerunSinkError as exc:
            raise ConfigError(f"{where('viewer')}: {exc}") from exc
        why = check_log_path(Path(target)) if mode == "save" and target else None
        if why is not None:  # a recording is written like a log (simserver.server.logfile)
            raise ConfigError(f"{where('viewer')}: {target} {why}")
    try:
        cfg.ros2 = ros2_cli.serve_settings(base.get("ros2"), ros2_flag, source=f"{path}: ros2")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if not cfg.config_dirs:
        cfg.config_dirs = [REPO_CONFIGS, path.parent]
    return cfg
