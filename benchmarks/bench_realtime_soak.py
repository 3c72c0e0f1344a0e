"""Real-time soak of the live server, and the process harness of the reliability tests.

Run from the repository root::

    python -m benchmarks.bench_realtime_soak --seconds 600 [--rate 1000] [--join-every 3]
                                             [--json FILE]

Starts ``simserver serve`` (no viewer) on a free loopback port and, each in its own
process, as a lab would run them:

- a **driver** commanding at ``--rate`` (1 kHz) on absolute deadlines: a plausible
  stop-and-go cycle (throttle with a slow weave, brake to a stop, hold), ``seq`` from 1;
- a **recorder**: subscribes to the state and the diagnostics and appends every state
  payload to a file, checking the tick numbers for gaps;
- **joiners**: every ``--join-every`` seconds a client connects, subscribes to the state,
  asks ``get_config`` and leaves after 1-4 s; every third one is killed with SIGKILL
  instead of leaving cleanly.

At the end the driver stops first (it reports how many commands it sent), then the
server's diagnostics are read (``cmd_received``: every command sent while the server was
up must have arrived, since no other process commands), then the server gets SIGTERM and
prints its final statistics. Reported: missed deadlines (late ticks, overruns, skipped
deadlines, lateness), lost and stale commands, states lost by the recorder, and the
server's memory (``VmRSS`` sampled once a second from ``/proc/PID/status``, and
``VmHWM``, the peak).

The classes here (``LiveServer``, ``RoleProcess``, ``Probe``) are also the harness of
``tests/test_faults.py``, ``tests/test_fuzz.py`` and ``tests/test_security.py``; the
client programs are roles of this module::

    python -m benchmarks.bench_realtime_soak role driver --connect tcp/127.0.0.1:7447 ...

Every role prints ``READY`` once its session is up and, when it ends (its duration is
over, or SIGTERM), one line ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver import protocol as proto

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
ROLE_MODULE = "benchmarks.bench_realtime_soak"


# ============================================================================ helpers


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
    inodes = set()
    fd_dir = f"/proc/{pid}/fd"
    for fd in os.listdir(fd_dir):
        try:
            target = os.readlink(f"{fd_dir}/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
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


def slow_enabled(markexpr: str | None) -> bool:
    """Whether the long (``slow``) tests should run.

    They run with ``SIMSERVER_SLOW=1`` in the environment or when pytest's ``-m``
    expression selects ``slow`` (``-m slow``); the default suite runs their short forms.
    """
    expr = markexpr or ""
    return os.environ.get("SIMSERVER_SLOW") == "1" or ("slow" in expr and "not slow" not in expr)


def client_config(endpoint: str | Sequence[str], zenoh_config: str | Path | None = None,
                  mode: str = "client") -> Any:
    """The zenoh config of a protocol client: ``mode`` connecting to ``endpoint``.

    With ``zenoh_config`` (a client-side JSON5 file: credentials, TLS trust) the file is
    the base and the endpoint and mode are set on top of it.
    """
    from simserver.adapters.zenoh_io import make_zenoh_config

    eps = [endpoint] if isinstance(endpoint, str) else list(endpoint)
    return make_zenoh_config(listen=[], connect=eps, config_file=zenoh_config, mode=mode)


def percentile(values: Sequence[float], q: float) -> float:
    """``q``-th percentile (NaN for no values)."""
    return float(np.percentile(np.asarray(values, dtype=float), q)) if len(values) else math.nan


# ============================================================================ server


class LiveServer:
    """``simserver serve`` in a subprocess; its output is read by a thread.

    Parameters
    ----------
    vehicle_id : str
        Vehicle id of its keys.
    scene : str or Path
        A scene name of ``configs/scenes`` or a path.
    listen : list of str, optional
        Endpoints (default one free ``tcp/127.0.0.1`` port); ``[]`` passes none, so the
        server config or the zenoh config file decides.
    extra_args : sequence of str
        More ``simserver serve`` arguments (``--zenoh-config``, ``--connect``, ...).
    viewer : str
        ``--viewer`` value (default ``off``).
    command_log : Path, optional
        ``--command-log`` file.
    config : Path, optional
        ``--config`` server YAML.
    ready_timeout_s : float
        How long to wait for ``ready on``.

    Notes
    -----
    Use it as a context manager: the server is stopped (SIGTERM, then SIGKILL after
    ``stop``'s timeout) whatever happens in the block.
    """

    def __init__(self, *, vehicle_id: str = "car0", scene: str | Path = "flat_paper_sedan",
                 listen: Sequence[str] | None = None, extra_args: Sequence[str] = (),
                 viewer: str = "off", command_log: Path | None = None,
                 config: Path | None = None, log_level: str = "INFO",
                 ready_timeout_s: float = 120.0) -> None:
        self.vehicle_id = vehicle_id
        if listen is None:
            self.port = free_port()
            listen = [f"tcp/127.0.0.1:{self.port}"]
        else:
            self.port = None
        self.endpoint = listen[0] if listen else None
        scene_path = Path(scene) if str(scene).endswith((".yaml", ".yml")) else \
            CONFIGS / "scenes" / f"{scene}.yaml"
        args = [sys.executable, "-m", "simserver", "serve", "--vehicle-id", vehicle_id,
                "--scene", str(scene_path), "--viewer", viewer, "--log-level", log_level]
        for ep in listen:
            args += ["--listen", ep]
        if command_log is not None:
            args += ["--command-log", str(command_log)]
        if config is not None:
            args += ["--config", str(config)]
        args += list(extra_args)
        self.args = args
        self.output: list[str] = []
        self.returncode: int | None = None
        self._ready = threading.Event()
        self.proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()
        if not self._ready.wait(ready_timeout_s) or self.proc.poll() is not None:
            self.kill()
            raise RuntimeError("server did not become ready:\n" + self.text())

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line)
            if "ready on" in line:
                self._ready.set()
        self._ready.set()

    @property
    def pid(self) -> int:
        """The server's process id."""
        return self.proc.pid

    def alive(self) -> bool:
        """True while the process runs."""
        return self.proc.poll() is None

    def text(self) -> str:
        """Everything the server printed so far."""
        return "".join(self.output)

    def memory_kb(self) -> dict[str, int]:
        """``VmRSS``, ``VmHWM`` and the other memory lines of the server, in kB."""
        return proc_status(self.proc.pid)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 30.0) -> int:
        """Send ``sig`` (default SIGTERM), wait, SIGKILL if it hangs; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(timeout=5)
        self.returncode = self.proc.returncode
        return self.returncode

    def kill(self) -> None:
        """SIGKILL (used on failures)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self._reader.join(timeout=5)
        self.returncode = self.proc.returncode

    def final_stats(self) -> dict[str, Any] | None:
        """The JSON of the ``simserver: stopped {...}`` line, once stopped cleanly."""
        for line in reversed(self.output):
            if line.startswith("simserver: stopped "):
                return json.loads(line[len("simserver: stopped "):])
        return None

    def children(self) -> list[int]:
        """Process ids whose parent is the server (its viewer)."""
        kids = []
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as fh:
                    stat = fh.read()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == self.proc.pid:
                kids.append(int(entry))
        return kids

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ============================================================================ role processes


class RoleProcess:
    """A role of this module (driver, recorder, joiner, flood, slowsub, router) as a process.

    Parameters
    ----------
    role : str
        The role name.
    args : sequence of str
        Its arguments (``--connect`` etc.).
    wait_ready_s : float or None
        Wait for its ``READY`` line this long (None: do not wait).
    """

    def __init__(self, role: str, args: Sequence[str], wait_ready_s: float | None = 60.0) -> None:
        self.role = role
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, "-m", ROLE_MODULE, "role", role, *args],
                                     cwd=REPO, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, env=env)
        self.output: list[str] = []
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()
        if wait_ready_s is not None and not self.wait_ready(wait_ready_s):
            self.kill()
            raise RuntimeError(f"role {role} did not start:\n{self.text()}")

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line)
            if line.startswith("READY"):
                self._ready.set()
        self._ready.set()

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait for ``READY``; False if it did not come or the process ended."""
        return self._ready.wait(timeout_s) and self.proc.poll() is None

    @property
    def pid(self) -> int:
        """Its process id."""
        return self.proc.pid

    def text(self) -> str:
        """Everything it printed."""
        return "".join(self.output)

    def result(self) -> dict[str, Any] | None:
        """Its ``RESULT`` JSON (once it ended cleanly)."""
        for line in reversed(self.output):
            if line.startswith("RESULT "):
                return json.loads(line[7:])
        return None

    def stop(self, timeout_s: float = 20.0) -> dict[str, Any] | None:
        """SIGTERM, wait for the ``RESULT`` line, SIGKILL if it hangs; the result."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout=5)
        return self.result()

    def wait(self, timeout_s: float) -> dict[str, Any] | None:
        """Wait for the role to end by itself (SIGKILL after ``timeout_s``); the result."""
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout=5)
        return self.result()

    def kill(self) -> None:
        """SIGKILL: the process vanishes without closing anything."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self._reader.join(timeout=5)


# ============================================================================ in-process probe


class Probe:
    """An in-process protocol client: commands, state and diagnostics, controls.

    Parameters
    ----------
    endpoint : str or list of str
        Where to connect.
    vehicle_id : str
        Vehicle id.
    zenoh_config : Path, optional
        Client-side zenoh JSON5 file (credentials, TLS).
    mode : str
        zenoh mode (default ``client``).
    state_capacity : int
        Ring capacity of the state subscriber.
    """

    def __init__(self, endpoint: str | Sequence[str], vehicle_id: str = "car0",
                 zenoh_config: str | Path | None = None, mode: str = "client",
                 state_capacity: int = 1 << 14) -> None:
        from simserver.adapters.zenoh_io import ZenohEndpoint

        self.ep = ZenohEndpoint(client_config(endpoint, zenoh_config, mode),
                                prefix="simserver", vehicle=vehicle_id)
        self.pub = self.ep.declare_command_publisher()
        self.states = self.ep.declare_state_inbox(capacity=state_capacity)
        self.diag = self.ep.declare_diag_inbox(capacity=256)
        self.seq = 0
        self.last: np.void | None = None
        self.received = 0

    def send(self, **kw: Any) -> None:
        """One command with the next ``seq``."""
        self.seq += 1
        self.pub.put(proto.encode_command(seq=self.seq, **kw))

    def poll(self) -> np.void | None:
        """Decode whatever arrived; the newest state (or None)."""
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
        return out

    def drive(self, seconds: float, rate_hz: float = 200.0, **kw: Any) -> np.void | None:
        """Command ``kw`` at ``rate_hz`` for ``seconds``; the newest state."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.send(**kw)
            self.poll()
            time.sleep(1.0 / rate_hz)
        return self.poll()

    def fresh_state(self, timeout_s: float = 5.0) -> np.void:
        """The first state published after this call."""
        self.states.drain_newest()
        payload = self.states.wait_newest(timeout_s)
        if payload is None:
            raise TimeoutError("no state received")
        self.last = proto.decode_state(payload)
        return self.last

    def diagnostics(self, timeout_s: float = 5.0) -> np.void:
        """The first diagnostics published after this call."""
        self.diag.drain_newest()
        payload = self.diag.wait_newest(timeout_s)
        if payload is None:
            raise TimeoutError("no diagnostics received")
        return proto.decode_diagnostics(payload)

    def request(self, name: str, args: dict | None = None, *, payload: bytes | None = None,
                timeout_s: float = 2.0) -> dict[str, Any]:
        """A control request (see ``ZenohEndpoint.request``)."""
        return self.ep.request(name, args, payload=payload, timeout_s=timeout_s)

    def close(self) -> None:
        """Close the session."""
        self.ep.close()

    def __enter__(self) -> Probe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def state_is_finite(state: np.void) -> bool:
    """Every numeric field of a decoded VehicleState is finite."""
    return all(np.all(np.isfinite(np.asarray(state[name], dtype=float)))
               for name in state.dtype.names)


# ============================================================================ roles


class _Stop:
    """SIGTERM/SIGINT set a flag that the role's loop polls."""

    def __init__(self) -> None:
        self.stopped = False
        signal.signal(signal.SIGTERM, self._set)
        signal.signal(signal.SIGINT, self._set)

    def _set(self, *_: Any) -> None:
        self.stopped = True


def _role_endpoint(args: argparse.Namespace) -> Any:
    from simserver.adapters.zenoh_io import ZenohEndpoint

    cfg = client_config(args.connect, args.zenoh_config, args.mode)
    return ZenohEndpoint(cfg, prefix="simserver", vehicle=args.vehicle_id)


def _result(data: dict[str, Any]) -> None:
    print("RESULT " + json.dumps(data), flush=True)


def _profile_inputs(profile: str, t: float) -> dict[str, Any]:
    """Driver inputs of a profile at ``t`` seconds since the start."""
    if profile.startswith("throttle:"):
        return {"throttle": float(profile.split(":")[1])}
    if profile.startswith("brake:"):
        return {"brake": float(profile.split(":")[1])}
    # "cycle": 4 s throttle with a slow weave, 3 s braking to a stop, 2 s hold
    phase = t % 9.0
    if phase < 4.0:
        return {"throttle": 0.35, "steer": 0.15 * math.sin(2 * math.pi * t / 4.0)}
    return {"brake": 0.6}


def role_driver(args: argparse.Namespace) -> None:
    """Command at ``--rate`` on absolute deadlines for ``--seconds`` (or until SIGTERM)."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        pub = ep.declare_command_publisher()
        period = 1.0 / args.rate
        seq = args.seq_start - 1
        sent = late = 0
        t0 = time.monotonic()
        next_t = t0
        end = t0 + args.seconds if args.seconds > 0 else math.inf
        print("READY", flush=True)
        while not stop.stopped:
            now = time.monotonic()
            if now >= end:
                break
            if now < next_t:
                time.sleep(min(next_t - now, 0.01))
                continue
            seq += 1
            pub.put(proto.encode_command(seq=seq & 0xFFFFFFFF, gear=proto.Gear.D,
                                         sender_time_ns=time.monotonic_ns(),
                                         **_profile_inputs(args.profile, now - t0)))
            sent += 1
            next_t += period
            if now - next_t > 100 * period:  # a long stall: do not burst to catch up
                late += int((now - next_t) / period)
                next_t = now + period
        time.sleep(0.2)  # let the last puts leave before the session closes
    _result({"sent": sent, "first_seq": args.seq_start, "last_seq": seq,
             "seconds": round(time.monotonic() - t0, 3), "deadlines_dropped": late})


def role_flood(args: argparse.Namespace) -> None:
    """Commands at ``--rate`` (far above 1 kHz), sent in one batch per millisecond."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        pub = ep.declare_command_publisher()
        per_ms = max(1, int(round(args.rate / 1000.0)))
        seq = args.seq_start - 1
        sent = 0
        print("READY", flush=True)
        t0 = time.monotonic()
        next_t = t0
        end = t0 + args.seconds
        # a valid command, its seq patched in place (encoding each one would cap the rate)
        template = bytearray(proto.encode_command(brake=0.3, gear=proto.Gear.D))
        seq_offset = proto.COMMAND_DTYPE.fields["seq"][1]
        put, pack_into = pub.put, struct.Struct("<I").pack_into
        while not stop.stopped and time.monotonic() < end:
            for _ in range(per_ms):
                seq += 1
                pack_into(template, seq_offset, seq & 0xFFFFFFFF)
                put(bytes(template))
            sent += per_ms
            next_t += 0.001
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        elapsed = time.monotonic() - t0
        time.sleep(0.3)
    _result({"sent": sent, "seconds": round(elapsed, 3),
             "rate_hz": round(sent / elapsed, 1), "last_seq": seq})


def role_recorder(args: argparse.Namespace) -> None:
    """Record every state to ``--out`` (raw payloads) and check the ticks for gaps."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        states = ep.declare_state_inbox(capacity=1 << 16)
        diag = ep.declare_diag_inbox(capacity=256)
        n = gaps = missing = resets = watchdog = 0
        ages: list[float] = []
        last_tick: int | None = None
        diags = 0
        out = open(args.out, "wb") if args.out else None
        print("READY", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        try:
            while not stop.stopped and time.monotonic() < end:
                payloads = states.drain_newest()
                for payload in payloads:
                    st = proto.decode_state(payload)
                    tick = int(st["tick"])
                    if last_tick is not None:
                        if tick > last_tick + 1:
                            gaps += 1
                            missing += tick - last_tick - 1
                        elif tick < last_tick:
                            resets += 1
                    last_tick = tick
                    if st["flags"] & proto.StateFlag.WATCHDOG:
                        watchdog += 1
                    elif st["cmd_age_s"] >= 0:
                        ages.append(float(st["cmd_age_s"]))
                    n += 1
                    if out is not None:
                        out.write(payload)
                diags += len(diag.drain_newest())
                time.sleep(0.005)
        finally:
            if out is not None:
                out.close()
    _result({"states": n, "gaps": gaps, "missing_ticks": missing, "resets": resets,
             "watchdog_states": watchdog, "diagnostics": diags,
             "cmd_age_p50_ms": round(1e3 * percentile(ages, 50), 3),
             "cmd_age_p99_ms": round(1e3 * percentile(ages, 99), 3),
             "cmd_age_max_ms": round(1e3 * max(ages), 3) if ages else None})


def role_joiner(args: argparse.Namespace) -> None:
    """Connect, subscribe to the state, ask ``get_config``, leave after ``--seconds``."""
    stop = _Stop()
    with _role_endpoint(args) as ep:
        states = ep.declare_state_inbox(capacity=1 << 13)
        print("READY", flush=True)
        try:
            config_ok = bool(ep.request("get_config", timeout_s=2.0)["ok"])
        except (TimeoutError, ValueError):
            config_ok = False
        n = 0
        end = time.monotonic() + args.seconds
        while not stop.stopped and time.monotonic() < end:
            n += len(states.drain_newest())
            time.sleep(0.01)
    _result({"states": n, "config_ok": config_ok})


def role_slowsub(args: argparse.Namespace) -> None:
    """Subscribe to the state through a tiny FIFO that is never drained; sleep."""
    import zenoh

    stop = _Stop()
    with _role_endpoint(args) as ep:
        sub = ep.session.declare_subscriber(ep.keys.state,
                                            zenoh.handlers.FifoChannel(args.capacity))
        print("READY", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        while not stop.stopped and time.monotonic() < end:
            time.sleep(0.05)  # never reads: the FIFO fills and blocks zenoh's receiver
        sub.undeclare()
    _result({"slept": True})


def role_router(args: argparse.Namespace) -> None:
    """A zenoh router (this Python process) on ``--listen``: clients and servers meet here."""
    import zenoh

    from simserver.adapters.zenoh_io import make_zenoh_config

    stop = _Stop()
    cfg = make_zenoh_config(listen=args.listen, connect=args.connect or [],
                            config_file=args.zenoh_config, mode="router")
    with zenoh.open(cfg):
        print("READY", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else math.inf
        while not stop.stopped and time.monotonic() < end:
            time.sleep(0.05)
    _result({"routed": True})


ROLES = {"driver": role_driver, "flood": role_flood, "recorder": role_recorder,
         "joiner": role_joiner, "slowsub": role_slowsub, "router": role_router}


def role_main(argv: Sequence[str]) -> int:
    """``role NAME ...``: run one client role (see the module docstring)."""
    parser = argparse.ArgumentParser(prog=f"python -m {ROLE_MODULE} role")
    parser.add_argument("name", choices=sorted(ROLES))
    parser.add_argument("--connect", action="append", default=None)
    parser.add_argument("--listen", action="append", default=None, help="router: endpoints")
    parser.add_argument("--vehicle-id", default="car0")
    parser.add_argument("--zenoh-config", default=None, help="client-side zenoh JSON5 file")
    parser.add_argument("--mode", default="client")
    parser.add_argument("--seconds", type=float, default=0.0, help="0: until SIGTERM")
    parser.add_argument("--rate", type=float, default=1000.0, help="commands per second")
    parser.add_argument("--seq-start", type=int, default=1)
    parser.add_argument("--profile", default="cycle", help="cycle | throttle:X | brake:X")
    parser.add_argument("--out", default=None, help="recorder: file of raw state payloads")
    parser.add_argument("--capacity", type=int, default=1, help="slowsub: FIFO capacity")
    args = parser.parse_args(argv)
    if args.name != "router" and not args.connect:
        parser.error(f"role {args.name} needs --connect")
    ROLES[args.name](args)
    return 0


# ============================================================================ the soak


@dataclass
class SoakReport:
    """Figures of one real-time soak."""

    seconds: float
    rate_hz: float
    commands_sent: int = 0
    commands_received: int = 0
    commands_lost: int = 0
    commands_rejected: int = 0
    commands_stale: int = 0
    watchdog_trips_while_driving: int = 0
    ticks: int = 0
    late_ticks: int = 0
    overruns: int = 0
    skipped_ticks: int = 0
    lateness_max_us: float = math.nan
    lateness_p99_us_worst_window: float = math.nan
    period_p99_us_median_window: float = math.nan
    states_published: int = 0
    recorder: dict[str, Any] = field(default_factory=dict)
    joiners: int = 0
    joiners_killed: int = 0
    joiners_config_ok: int = 0
    rss_start_kb: int = 0
    rss_end_kb: int = 0
    rss_growth_kb: int = 0
    rss_slope_kb_per_min: float = math.nan
    rss_samples: list[tuple[float, int]] = field(default_factory=list)
    vm_hwm_kb: int = 0
    server_alive_at_end: bool = False
    server_exit_code: int | None = None
    final_stats: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready figures."""
        return {k: v for k, v in self.__dict__.items()}


def run_realtime_soak(seconds: float, rate_hz: float = 1000.0, join_every_s: float = 3.0,
                      workdir: Path | None = None, log: Any = print,
                      seed: int = 1) -> SoakReport:
    """Run the live server with a driver, a recorder and joiners for ``seconds`` (wall).

    Returns
    -------
    SoakReport
        See the module docstring. ``commands_lost`` = sent - received by the server.
    """
    import tempfile

    rng = random.Random(seed)
    own_tmp = None
    if workdir is None:
        own_tmp = tempfile.TemporaryDirectory(prefix="rt_soak_")
        workdir = Path(own_tmp.name)
    rep = SoakReport(seconds=seconds, rate_hz=rate_hz)
    server = LiveServer(log_level="WARNING")
    roles: list[RoleProcess] = []
    joiners: list[tuple[RoleProcess, float, bool]] = []
    windows_p99: list[float] = []
    windows_period: list[float] = []
    try:
        conn = ["--connect", server.endpoint]
        with Probe(server.endpoint) as probe:
            recorder = RoleProcess("recorder", [*conn, "--out", str(workdir / "states.bin")])
            roles.append(recorder)
            driver = RoleProcess("driver", [*conn, "--rate", str(rate_hz)])
            roles.append(driver)
            time.sleep(1.0)  # everyone connected, the car moving
            trips0 = int(probe.diagnostics()["watchdog_trips"])
            rss: list[tuple[float, int]] = []
            t0 = time.monotonic()
            next_join = t0 + join_every_s
            next_sample = t0
            end = t0 + seconds
            while time.monotonic() < end:
                now = time.monotonic()
                if now >= next_sample:
                    rss.append((now - t0, server.memory_kb()["VmRSS"]))
                    next_sample += 1.0
                    for payload in probe.diag.drain_newest():
                        d = proto.decode_diagnostics(payload)
                        windows_p99.append(float(d["lateness_p99_us"]))
                        windows_period.append(float(d["period_p99_us"]))
                if join_every_s > 0 and now >= next_join:
                    rep.joiners += 1
                    kill = rep.joiners % 3 == 0
                    life = rng.uniform(1.0, 4.0)
                    # a killed joiner vanishes mid-session; the others leave by themselves
                    due = now + (0.6 * life if kill else life + 0.5)
                    joiners.append((RoleProcess("joiner", [*conn, "--seconds", f"{life:.2f}"],
                                                wait_ready_s=None), due, kill))
                    next_join += join_every_s
                for j in [j for j in joiners if now >= j[1]]:
                    proc, _, kill = j
                    if kill and proc.proc.poll() is None and not proc.wait_ready(0.0):
                        continue  # still starting: kill it once its session is up
                    joiners.remove(j)
                    if kill and proc.proc.poll() is None:
                        proc.kill()
                        rep.joiners_killed += 1
                    else:
                        res = proc.wait(10.0)
                        rep.joiners_config_ok += int(bool(res and res["config_ok"]))
                if not server.alive():
                    break
                probe.states.drain_newest()
                time.sleep(0.05)
            for proc, _, _ in joiners:
                proc.kill()
            joiners.clear()
            rss.append((time.monotonic() - t0, server.memory_kb()["VmRSS"]))
            rep.rss_samples = [(round(t, 1), kb) for t, kb in rss]
            rep.server_alive_at_end = server.alive()
            rep.recorder = recorder.stop() or {}  # its figures cover the driving only
            sent = driver.stop()
            time.sleep(0.6)  # a diagnostics message published after the last command
            diag = probe.diagnostics()
            rep.commands_sent = int(sent["sent"]) if sent else -1
            rep.commands_received = int(diag["cmd_received"])
            rep.commands_lost = rep.commands_sent - rep.commands_received
            rep.commands_rejected = int(diag["cmd_rejected"])
            rep.commands_stale = int(diag["cmd_stale"])
            rep.watchdog_trips_while_driving = int(diag["watchdog_trips"]) - trips0 - 1
            mem = server.memory_kb()
            rep.vm_hwm_kb = mem["VmHWM"]
            start = next((kb for t, kb in rss if t >= min(2.0, seconds / 4)), rss[0][1])
            rep.rss_start_kb = start
            rep.rss_end_kb = rss[-1][1]
            rep.rss_growth_kb = rep.rss_end_kb - rep.rss_start_kb
            tail = [(t, kb) for t, kb in rss if t >= seconds / 4]
            if len(tail) >= 3:
                ts, kbs = np.array(tail, dtype=float).T
                rep.rss_slope_kb_per_min = round(float(np.polyfit(ts, kbs, 1)[0]) * 60.0, 1)
    finally:
        for proc, _, _ in joiners:
            proc.kill()
        for r in roles:
            r.stop()
        rep.server_exit_code = server.stop()
        if own_tmp is not None:
            own_tmp.cleanup()
    stats = server.final_stats() or {}
    rep.final_stats = stats
    rep.ticks = int(stats.get("steps_total", 0))
    rep.late_ticks = int(stats.get("late_ticks", -1))
    rep.overruns = int(stats.get("overruns", -1))
    rep.skipped_ticks = int(stats.get("skipped_ticks", -1))
    rep.lateness_max_us = float(stats.get("lateness_max_us", math.nan))
    rep.states_published = int(stats.get("state_published", 0))
    rep.lateness_p99_us_worst_window = round(max(windows_p99), 1) if windows_p99 else math.nan
    rep.period_p99_us_median_window = round(percentile(windows_period, 50), 1)
    return rep


def format_report(rep: SoakReport) -> str:
    """A human-readable summary."""
    r = rep.recorder or {}
    lines = [
        f"real-time soak: {rep.seconds:.0f} s wall, driver at {rep.rate_hz:.0f} Hz, "
        f"{rep.joiners} joiners ({rep.joiners_killed} killed -9)",
        f"  commands: sent {rep.commands_sent}, received {rep.commands_received}, lost "
        f"{rep.commands_lost}, rejected {rep.commands_rejected}, stale (superseded within a "
        f"tick) {rep.commands_stale}, watchdog trips while driving "
        f"{rep.watchdog_trips_while_driving}",
        f"  ticks: {rep.ticks}, late (> 1 ms) {rep.late_ticks} "
        f"({100.0 * rep.late_ticks / max(rep.ticks, 1):.3f} %), overruns {rep.overruns}, "
        f"skipped deadlines {rep.skipped_ticks}, max lateness {rep.lateness_max_us:.0f} us, "
        f"worst window p99 lateness {rep.lateness_p99_us_worst_window} us, "
        f"median window p99 period {rep.period_p99_us_median_window} us",
        f"  recorder: {r.get('states')} states of {rep.states_published} published, "
        f"{r.get('missing_ticks')} missing ticks in {r.get('gaps')} gaps, command age p50 "
        f"{r.get('cmd_age_p50_ms')} ms p99 {r.get('cmd_age_p99_ms')} ms max "
        f"{r.get('cmd_age_max_ms')} ms",
        f"  server memory: VmRSS {rep.rss_start_kb} -> {rep.rss_end_kb} kB "
        f"({rep.rss_growth_kb:+d} kB, slope {rep.rss_slope_kb_per_min} kB/min after the "
        f"first quarter), VmHWM {rep.vm_hwm_kb} kB",
        f"  server alive at the end: {rep.server_alive_at_end}, exit code "
        f"{rep.server_exit_code}",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: the soak, or ``role NAME ...``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "role":
        return role_main(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="wall seconds (default 60)")
    parser.add_argument("--rate", type=float, default=1000.0, help="driver command rate")
    parser.add_argument("--join-every", type=float, default=3.0,
                        help="a client joins every this many seconds (0: none)")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = parser.parse_args(argv)
    rep = run_realtime_soak(args.seconds, args.rate, args.join_every)
    print(format_report(rep))
    if args.json is not None:
        args.json.write_text(json.dumps(rep.as_dict(), indent=2) + "\n", encoding="utf-8")
    ok = rep.commands_lost == 0 and rep.server_alive_at_end and rep.server_exit_code == 0
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
