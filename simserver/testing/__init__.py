"""The harness that starts a live ``simserver serve`` and talks to it over zenoh.

One harness for the end-to-end tests, the benchmarks and users' own soak scripts::

    from simserver.testing import Client, ServerProcess

    with ServerProcess(scene="flat_paper_sedan") as server, Client(server) as client:
        client.drive_until(lambda s: s["u_mps"] > 2.0, throttle=0.4, gear=proto.Gear.D)
        before = client.diagnostics()
        ...
    print(server.final_stats())

- ``free_port()``: a free loopback TCP port; ``loopback_endpoint()`` the zenoh endpoint on one.
- ``ServerProcess``: ``simserver serve`` as a subprocess with explicit loopback endpoints
  (multicast scouting off, the default of ``make_zenoh_config``), its output read by a
  thread (a long run never fills the pipe), started once it prints ``ready on``, stopped
  with SIGTERM or SIGINT and its final statistics parsed; ``wait_for_line`` waits for a
  line of its output.
- ``Client``: an in-process protocol client (commands, state, diagnostics, controls,
  liveliness) with waits on conditions: ``wait_state`` (a state satisfying a predicate),
  ``drive_until`` (command until one does), ``wait_diagnostics`` (a diagnostics message
  satisfying a predicate, e.g. a counter reaching a value), ``wait_alive`` (the
  liveliness tokens).
- ``RoleProcess``: a client program of ``simserver.testing.roles`` (driver, recorder,
  joiner, flood, slow subscriber, router) as its own process.
- ``wait_until``: poll any function until its value satisfies a predicate.

Every wait has a timeout and fails with a message naming what it waited for; nothing
here sleeps a fixed time except to pace a command stream.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from simserver.server.realtime import open_files
from simserver.wire import protocol as proto

REPO = Path(__file__).resolve().parents[2]
"""The source checkout (the servers and client programs are started from here; scene
names are looked up in its ``configs/scenes``: from an installed package, pass paths)."""
CONFIGS = REPO / "configs"
ROLES_MODULE = "simserver.testing.roles"

T = TypeVar("T")


# ============================================================================ waiting


def wait_until(poll: Callable[[], T], predicate: Callable[[T], bool] = bool, *,
               timeout_s: float = 10.0, what: str = "a condition",
               interval_s: float = 0.005) -> T:
    """Call ``poll`` until ``predicate`` holds for its value; that value.

    Raises
    ------
    TimeoutError
        After ``timeout_s`` seconds, naming ``what`` and the last value seen.
    """
    end = time.monotonic() + timeout_s
    while True:
        value = poll()
        if predicate(value):
            return value
        if time.monotonic() >= end:
            raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}; "
                               f"last value: {value!r}")
        time.sleep(interval_s)


# ============================================================================ processes


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback_endpoint(scheme: str = "tcp") -> str:
    """A zenoh endpoint ``SCHEME/127.0.0.1:PORT`` on a free port."""
    return f"{scheme}/127.0.0.1:{free_port()}"


def proc_status(pid: int) -> dict[str, int]:
    """Memory lines of ``/proc/PID/status`` in kB (``VmRSS``, ``VmHWM``, ...)."""
    out: dict[str, int] = {}
    with open(f"/proc/{pid}/status", encoding="ascii") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key.startswith("Vm") or key.startswith("Rss"):
                parts = value.split()
                if parts and parts[0].isdigit():
                    out[key] = int(parts[0])
    return out


def _hex_addr(text: str) -> tuple[str, int]:
    """Decode a ``/proc/net/{tcp,udp}[6]`` address ``HEXIP:HEXPORT``."""
    ip_hex, port_hex = text.split(":")
    raw = bytes.fromhex(ip_hex)
    if len(raw) == 4:
        ip = socket.inet_ntop(socket.AF_INET, raw[::-1])
    else:  # four little-endian 32-bit words
        words = b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))
        ip = socket.inet_ntop(socket.AF_INET6, words)
    return ip, int(port_hex, 16)


@dataclass(frozen=True)
class SocketInfo:
    """One socket of a process, from ``/proc/PID/net``."""

    proto: str  # tcp, tcp6, udp, udp6
    local_ip: str
    local_port: int
    state: str  # "0A" = TCP LISTEN; "07" = UDP unconnected

    @property
    def listening(self) -> bool:
        """A TCP socket in LISTEN state."""
        return self.proto.startswith("tcp") and self.state == "0A"


def process_sockets(pid: int) -> list[SocketInfo]:
    """Every TCP and UDP socket held by process ``pid`` (matched by inode)."""
    inodes = {target[8:-1] for target in open_files(pid).values()
              if target.startswith("socket:[")}
    found = []
    for proto_name in ("tcp", "tcp6", "udp", "udp6"):
        try:
            fh = open(f"/proc/{pid}/net/{proto_name}", encoding="ascii")
        except OSError:
            continue
        with fh:
            next(fh)
            for line in fh:
                parts = line.split()
                if parts[9] in inodes:
                    ip, port = _hex_addr(parts[1])
                    found.append(SocketInfo(proto_name, ip, port, parts[3]))
    return found


def child_pids(pid: int) -> list[int]:
    """Process ids whose parent is ``pid``."""
    kids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as fh:
                stat = fh.read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            kids.append(int(entry))
    return kids


def process_argv(pid: int) -> list[str]:
    """The command line of ``pid`` (empty once it has ended)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def process_running(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie waiting for its parent to reap it."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


class OutputProcess:
    """A subprocess whose merged stdout/stderr a thread collects line by line.

    Parameters
    ----------
    argv : sequence of str
        The command (run from the repository root).
    ready : str
        Marker of its ready line: ``wait_ready`` waits for a line containing it (default:
        the first line).
    env : dict, optional
        Environment, as given (default this one, with ``PYTHONUNBUFFERED=1``).
    cwd : Path
        Working directory (default the repository).
    new_session : bool
        Start it in a session and process group of its own, as a shell starts a job:
        ``signal_group`` then signals it and every child, as Ctrl-C in a terminal does.
    """

    def __init__(self, argv: Sequence[str], ready: str = "", env: dict[str, str] | None = None,
                 cwd: Path = REPO, new_session: bool = False) -> None:
        self.argv = list(argv)
        self.output: list[str] = []
        self.returncode: int | None = None
        self.ready_line: str | None = None
        self._ready_marker = ready
        self._ready = threading.Event()
        self._grew = threading.Condition()
        self.t_launch = time.monotonic()
        self.proc = subprocess.Popen(self.argv, cwd=cwd, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True,
                                     env=dict(os.environ, PYTHONUNBUFFERED="1")
                                     if env is None else env,
                                     start_new_session=new_session)
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._grew:
                self.output.append(line)
                self._grew.notify_all()
            if self.ready_line is None and self._ready_marker in line:
                self.ready_line = line
                self._ready.set()
        self._ready.set()
        with self._grew:
            self._grew.notify_all()

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait for the ready line; False if it did not come or the process ended."""
        return self._ready.wait(timeout_s) and self.ready_line is not None

    def wait_for_line(self, contains: str, timeout_s: float = 10.0, start: int = 0) -> str:
        """The first line (from line ``start`` on) containing ``contains``.

        Raises
        ------
        TimeoutError
            If none comes within ``timeout_s`` or the process closes its output first.
        """
        end = time.monotonic() + timeout_s
        with self._grew:
            while True:
                for line in self.output[start:]:
                    if contains in line:
                        return line
                start = len(self.output)
                left = end - time.monotonic()
                if left <= 0 or not self._reader.is_alive():
                    raise TimeoutError(f"no line containing {contains!r} in the output of "
                                       f"{self.argv[:4]}:\n{self.text()}")
                self._grew.wait(min(left, 0.5))

    @property
    def pid(self) -> int:
        """The process id."""
        return self.proc.pid

    def alive(self) -> bool:
        """True while the process runs."""
        return self.proc.poll() is None

    def text(self) -> str:
        """Everything it printed so far."""
        return "".join(self.output)

    def memory_kb(self) -> dict[str, int]:
        """``VmRSS``, ``VmHWM`` and the other memory lines, in kB."""
        return proc_status(self.proc.pid)

    def children(self) -> list[int]:
        """Process ids whose parent is this process."""
        return child_pids(self.proc.pid)

    def signal_group(self, sig: int) -> None:
        """Send ``sig`` to its whole process group (started with ``new_session``)."""
        os.killpg(self.proc.pid, sig)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 30.0) -> int:
        """Send ``sig`` (default SIGTERM), wait, SIGKILL if it hangs; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self._wait_or_kill(timeout_s)

    def wait(self, timeout_s: float) -> int:
        """Wait for it to end by itself (SIGKILL after ``timeout_s``); the exit code."""
        return self._wait_or_kill(timeout_s)

    def _wait_or_kill(self, timeout_s: float) -> int:
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return self._ended()

    def kill(self) -> int:
        """SIGKILL: it vanishes without closing anything; the exit code."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        return self._ended()

    def _ended(self) -> int:
        self._reader.join(timeout=5)
        self.returncode = self.proc.returncode
        return self.returncode

    def __enter__(self) -> OutputProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        """Leaves nothing running: a process still alive (a test that failed) is killed."""
        if self.alive():
            self.kill()


# ============================================================================ the server


STATS_JSON = "--stats-json"
"""The flag that makes ``simserver serve`` print its stop statistics as a JSON line too
(``final_stats`` reads it): the harness adds it to every server it starts, a README
command as written included."""


def serve_args(*, vehicle_id: str = "car0", scene: str | Path | None = "flat_paper_sedan",
               listen: Sequence[str] = (), viewer: str = "off", log_level: str = "INFO",
               command_log: Path | None = None, config: Path | None = None,
               extra_args: Sequence[str] = ()) -> list[str]:
    """The ``simserver serve`` command line (``scene``: a name of ``configs/scenes``, a
    path, or None for the server config's)."""
    args = [sys.executable, "-m", "simserver", "serve", "--vehicle-id", vehicle_id,
            "--viewer", viewer, "--log-level", log_level, STATS_JSON]
    if scene is not None:
        scene_path = Path(scene) if str(scene).endswith((".yaml", ".yml")) else \
            CONFIGS / "scenes" / f"{scene}.yaml"
        args += ["--scene", str(scene_path)]
    for ep in listen:
        args += ["--listen", ep]
    if command_log is not None:
        args += ["--command-log", str(command_log)]
    if config is not None:
        args += ["--config", str(config)]
    return args + list(extra_args)


class ServerProcess(OutputProcess):
    """``simserver serve`` in a subprocess, started once it prints ``ready on``.

    Parameters
    ----------
    vehicle_id : str
        Vehicle id of its keys.
    scene : str or Path or None
        A scene name of ``configs/scenes``, a path, or None (the server config's).
    listen : list of str, optional
        Endpoints (default one free ``tcp/127.0.0.1`` port); ``[]`` passes none, so the
        server config or the zenoh config file decides.
    extra_args : sequence of str
        More ``simserver serve`` arguments (``--zenoh-config``, ``--connect``, ...).
    viewer, log_level : str
        ``--viewer`` (default ``off``) and ``--log-level`` values.
    command_log, config : Path, optional
        ``--command-log`` file, ``--config`` server YAML.
    argv : sequence of str, optional
        A command line of its own instead (a README command, say); ``listen[0]`` must
        then be its endpoint.
    env : dict, optional
        Its environment (as given).
    cwd : Path
        Its working directory (default the repository).
    ready_timeout_s : float
        How long to wait for ``ready on`` (the numba core may compile first).

    Notes
    -----
    As a context manager it is stopped (SIGTERM, SIGKILL after ``stop``'s timeout)
    whatever happens in the block. ``ready_s`` is the time from launch to ready.
    """

    def __init__(self, *, vehicle_id: str = "car0",
                 scene: str | Path | None = "flat_paper_sedan",
                 listen: Sequence[str] | None = None, extra_args: Sequence[str] = (),
                 viewer: str = "off", log_level: str = "INFO",
                 command_log: Path | None = None, config: Path | None = None,
                 argv: Sequence[str] | None = None, env: dict[str, str] | None = None,
                 cwd: Path = REPO, ready_timeout_s: float = 120.0,
                 new_session: bool = False) -> None:
        self.vehicle_id = vehicle_id
        if listen is None:
            self.port: int | None = free_port()
            listen = [f"tcp/127.0.0.1:{self.port}"]
        else:
            self.port = None
        self.endpoint = listen[0] if listen else None
        self.command_log = command_log
        if argv is None:
            argv = serve_args(vehicle_id=vehicle_id, scene=scene, listen=listen,
                              viewer=viewer, log_level=log_level, command_log=command_log,
                              config=config, extra_args=extra_args)
        elif "serve" in argv and STATS_JSON not in argv:
            argv = [*argv, STATS_JSON]
        super().__init__(argv, ready="ready on", env=env, cwd=cwd, new_session=new_session)
        if not self.wait_ready(ready_timeout_s) or not self.alive():
            self.kill()
            raise RuntimeError("server did not become ready:\n" + self.text())
        self.ready_s = time.monotonic() - self.t_launch

    def crash_report(self, timeout_s: float = 10.0) -> str:
        """Whether it still runs and the tail of its output, for a failure message; a
        server that crashes takes a moment to exit, so this waits up to ``timeout_s`` for
        that first."""
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            pass
        return f"server alive: {self.alive()}\n" + self.text()[-3000:]

    def viewer_pids(self) -> list[int]:
        """Its children that are live viewers (``simserver view``), not its other children
        (the ``load`` worker, multiprocessing's resource tracker)."""
        return [pid for pid in self.children()
                if {"simserver", "view"} <= set(process_argv(pid))]

    def client_args(self) -> list[str]:
        """The connection flags of a client program of this server."""
        return ["--connect", self.endpoint, "--vehicle-id", self.vehicle_id]

    def final_stats(self) -> dict[str, Any] | None:
        """The JSON of the ``simserver: stopped {...}`` line (``--stats-json``, which this
        harness passes), once stopped cleanly."""
        for line in reversed(self.output):
            if line.startswith("simserver: stopped "):
                return json.loads(line[len("simserver: stopped "):])
        return None

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class RoleProcess(OutputProcess):
    """A client program of ``simserver.testing.roles`` as its own process.

    Parameters
    ----------
    role : str
        The role name (driver, recorder, joiner, flood, slowsub, router).
    args : sequence of str
        Its arguments (``--connect`` etc.).
    wait_ready_s : float or None
        Wait for its ``READY`` line this long (None: do not wait).
    """

    def __init__(self, role: str, args: Sequence[str], wait_ready_s: float | None = 60.0) -> None:
        self.role = role
        super().__init__([sys.executable, "-m", ROLES_MODULE, role, *args], ready="READY")
        if wait_ready_s is not None and not (self.wait_ready(wait_ready_s) and self.alive()):
            self.kill()
            raise RuntimeError(f"role {role} did not start:\n{self.text()}")

    def result(self) -> dict[str, Any] | None:
        """Its ``RESULT`` JSON (once it ended cleanly)."""
        for line in reversed(self.output):
            if line.startswith("RESULT "):
                return json.loads(line[7:])
        return None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 20.0) -> dict[str, Any] | None:
        """SIGTERM, wait for the ``RESULT`` line, SIGKILL if it hangs; the result."""
        super().stop(sig, timeout_s)
        return self.result()

    def wait(self, timeout_s: float) -> dict[str, Any] | None:
        """Wait for the role to end by itself (SIGKILL after ``timeout_s``); the result."""
        self._wait_or_kill(timeout_s)
        return self.result()


# ============================================================================ the client


def client_config(endpoint: str | Sequence[str], zenoh_config: str | Path | None = None,
                  mode: str = "client") -> Any:
    """The zenoh config of a protocol client: ``mode`` connecting to ``endpoint``.

    With ``zenoh_config`` (a client-side JSON5 file: credentials, TLS trust) the file is
    the base and the endpoint and mode are set on top of it.
    """
    from simserver.adapters.zenoh_io import make_zenoh_config

    eps = [endpoint] if isinstance(endpoint, str) else list(endpoint)
    return make_zenoh_config(listen=[], connect=eps, config_file=zenoh_config, mode=mode)


def state_is_finite(state: np.void) -> bool:
    """Every numeric field of a decoded VehicleState is finite."""
    return all(np.all(np.isfinite(np.asarray(state[name], dtype=float)))
               for name in state.dtype.names)


class Client:
    """An in-process protocol client: commands, state and diagnostics, controls, liveliness.

    Parameters
    ----------
    server : ServerProcess, str or list of str
        The server (its endpoint and vehicle id) or endpoints to connect to.
    vehicle_id : str, optional
        Vehicle id (default the server's, else ``car0``).
    zenoh_config : Path, optional
        Client-side zenoh JSON5 file (credentials, TLS).
    mode : str
        zenoh mode (default ``client``).
    state_capacity : int
        Ring capacity of the state subscriber; 0: no state subscriber (a caller that
        subscribes its own way).
    keep_history : bool
        Keep every state received in ``history`` (else only the newest is decoded).
    """

    def __init__(self, server: ServerProcess | str | Sequence[str],
                 vehicle_id: str | None = None, zenoh_config: str | Path | None = None,
                 mode: str = "client", state_capacity: int = 1 << 14,
                 keep_history: bool = False) -> None:
        from simserver.adapters.zenoh_io import ZenohEndpoint

        endpoint = server.endpoint if isinstance(server, ServerProcess) else server
        if vehicle_id is None:
            vehicle_id = server.vehicle_id if isinstance(server, ServerProcess) else "car0"
        self.ep = ZenohEndpoint(client_config(endpoint, zenoh_config, mode),
                                prefix="simserver", vehicle=vehicle_id)
        self.pub = self.ep.declare_command_publisher()
        self.states = self.ep.declare_state_inbox(capacity=state_capacity) \
            if state_capacity else None
        self.diag = self.ep.declare_diag_inbox(capacity=256)
        self.seq = 0
        self.last: np.void | None = None
        self.received = 0
        self.keep_history = keep_history
        self.history: list[np.void] = []

    # ------------------------------------------------------------------ commands
    def send(self, **kw: Any) -> None:
        """One command with the next ``seq``."""
        self.seq += 1
        self.pub.put(proto.encode_command(seq=self.seq, **kw))

    def drive(self, seconds: float, rate_hz: float = 200.0, **kw: Any) -> np.void | None:
        """Command ``kw`` at ``rate_hz`` for ``seconds`` (a driver holding its inputs that
        long); the newest state."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.send(**kw)
            self.poll()
            time.sleep(1.0 / rate_hz)  # the pace of the command stream
        return self.poll()

    def drive_until(self, predicate: Callable[[np.void], bool], timeout_s: float = 20.0,
                    rate_hz: float = 200.0, what: str = "a state", **kw: Any) -> np.void:
        """Command ``kw`` at ``rate_hz`` until a state satisfies ``predicate``; that state.

        Raises
        ------
        TimeoutError
            If none does within ``timeout_s``.
        """
        return self._first_state(predicate, timeout_s, f"{what} (driving {kw})",
                                 each=lambda: self.send(**kw), interval_s=1.0 / rate_hz)

    # ------------------------------------------------------------------ state
    def poll(self) -> np.void | None:
        """Decode whatever arrived; the newest state (or None)."""
        if self.keep_history:
            self.drain_states()
            return self.last
        payloads = self.states.drain_newest()
        self.received += len(payloads)
        if payloads:
            self.last = proto.decode_state(payloads[-1])
        return self.last

    def drain_states(self) -> list[np.void]:
        """Every state received since the last call, decoded, oldest first."""
        payloads = self.states.drain_newest()
        self.received += len(payloads)
        out = [proto.decode_state(p) for p in payloads]
        if out:
            self.last = out[-1]
            if self.keep_history:
                self.history += out
        return out

    def wait_state(self, predicate: Callable[[np.void], bool] = lambda s: True,
                   timeout_s: float = 10.0, what: str = "a state") -> np.void:
        """The first state received from now on that satisfies ``predicate``.

        Raises
        ------
        TimeoutError
            If none does within ``timeout_s``.
        """
        self.drain_states()
        return self._first_state(predicate, timeout_s, what)

    def _first_state(self, predicate: Callable[[np.void], bool], timeout_s: float, what: str,
                     each: Callable[[], None] = lambda: None,
                     interval_s: float = 0.002) -> np.void:
        """Run ``each`` and drain the states every ``interval_s`` until one satisfies
        ``predicate``; that state (TimeoutError after ``timeout_s``)."""
        def poll() -> np.void | None:
            each()
            return next((st for st in self.drain_states() if predicate(st)), None)

        try:
            return wait_until(poll, lambda st: st is not None, timeout_s=timeout_s,
                              what=what, interval_s=interval_s)
        except TimeoutError as exc:
            raise TimeoutError(f"{exc}; last state received: {self.last}") from None

    def next_states(self, n: int, timeout_s: float = 10.0) -> list[np.void]:
        """The next ``n`` states received from now on (the server publishes one a loop,
        paused or not: ``n`` of them span about ``n`` periods)."""
        self.drain_states()
        got: list[np.void] = []
        wait_until(lambda: got.extend(self.drain_states()) or len(got), lambda k: k >= n,
                   timeout_s=timeout_s, what=f"{n} states", interval_s=0.002)
        return got[:n]

    def fresh_state(self, timeout_s: float = 5.0) -> np.void:
        """The first state published after this call."""
        return self.wait_state(timeout_s=timeout_s, what="a fresh state")

    def newest(self, timeout_s: float = 5.0) -> np.void:
        """The newest state received (waits for a first one)."""
        if self.poll() is None:
            self.wait_state(timeout_s=timeout_s, what="a first state")
        return self.last

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, timeout_s: float = 5.0) -> np.void:
        """The first diagnostics published after this call."""
        return self.wait_diagnostics(lambda d: True, timeout_s, "a diagnostics message")

    def wait_load_worker(self, timeout_s: float = 120.0) -> dict[str, Any]:
        """Wait until the server's load worker has finished its warm-up (``get_config``'s
        ``load_worker``: imports and one scene read, seconds on a busy machine), so that a
        ``load`` asked next is answered within its 2 s query timeout instead of waiting
        behind the warm-up; the worker's status. A server without a worker (loads inline)
        is ready at once."""
        def status() -> dict[str, Any] | None:
            try:
                return self.ep.request("get_config", timeout_s=5.0)["config"]["load_worker"]
            except TimeoutError as exc:  # a server starved of CPU: ask again
                return {"ready": False, "progress": str(exc)}

        return wait_until(status, lambda s: s is None or s["ready"], timeout_s=timeout_s,
                          what="the server's load worker to finish its warm-up",
                          interval_s=0.05)

    def wait_diagnostics(self, predicate: Callable[[np.void], bool], timeout_s: float = 10.0,
                         what: str = "diagnostics") -> np.void:
        """The first diagnostics published from now on satisfying ``predicate`` (a counter
        reaching a value, say).

        Raises
        ------
        TimeoutError
            If none does within ``timeout_s``.
        """
        self.diag.drain_newest()
        end = time.monotonic() + timeout_s
        last = None
        while True:
            left = end - time.monotonic()
            payload = self.diag.wait_newest(max(left, 0.0))
            if payload is not None:
                last = proto.decode_diagnostics(payload)
                if predicate(last):
                    return last
            if time.monotonic() >= end:
                raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}; "
                                   f"last diagnostics: {last}")

    # ------------------------------------------------------------------ controls, liveliness
    def request(self, name: str, args: dict | None = None, *, payload: bytes | None = None,
                timeout_s: float = 2.0) -> dict[str, Any]:
        """A control request (see ``ZenohEndpoint.request``)."""
        return self.ep.request(name, args, payload=payload, timeout_s=timeout_s)

    def wait_controls(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Ask ``get_config`` until the server's queryable is known to this client (through
        a router that may take a moment); its reply."""
        def ask() -> dict[str, Any] | None:
            try:
                return self.request("get_config", timeout_s=1.0)
            except TimeoutError:
                return None

        return wait_until(ask, lambda r: r is not None, timeout_s=timeout_s,
                          what="the server's controls", interval_s=0.1)

    def wait_alive(self, predicate: Callable[[list[str]], bool], timeout_s: float = 10.0,
                   what: str = "the liveliness tokens") -> list[str]:
        """Query the liveliness tokens until ``predicate`` holds for their list; the list."""
        return wait_until(lambda: sorted(self.ep.alive_tokens(timeout_s=0.5)), predicate,
                          timeout_s=timeout_s, what=what, interval_s=0.05)

    def close(self) -> None:
        """Close the session."""
        self.ep.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def client_command(module: str, *args: str) -> list[str]:
    """``python -m clients.MODULE ARGS`` (run from the repository root)."""
    return [sys.executable, "-m", f"clients.{module}", *args]


def client_env() -> dict[str, str]:
    """Environment of a client subprocess: headless SDL, no pygame banner."""
    env = dict(os.environ)
    env.update(SDL_VIDEODRIVER="dummy", SDL_AUDIODRIVER="dummy",
               PYGAME_HIDE_SUPPORT_PROMPT="1", PYTHONUNBUFFERED="1")
    return env
