"""A live server and protocol clients as real processes on loopback, for end-to-end tests.

The same pattern as ``tests/test_server.py`` (``simserver serve`` on a free loopback
port, multicast scouting off, stopped with SIGTERM), with the server's output read by a
thread (a long test never fills the pipe) and helpers to start the ``clients`` programs.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from simserver import protocol as proto
from simserver.adapters.zenoh_io import ZenohEndpoint, make_zenoh_config

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``simserver serve`` in a subprocess (no viewer), stopped with SIGTERM.

    Parameters
    ----------
    vehicle_id : str
        The vehicle id of its keys.
    scene : str
        A scene name of ``configs/scenes`` (or a path).
    """

    def __init__(self, vehicle_id: str = "car0", scene: str = "flat_paper_sedan") -> None:
        self.port = free_port()
        self.vehicle_id = vehicle_id
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        scene_path = Path(scene) if scene.endswith(".yaml") else \
            CONFIGS / "scenes" / f"{scene}.yaml"
        args = [sys.executable, "-m", "simserver", "serve", "--vehicle-id", vehicle_id,
                "--listen", self.endpoint, "--scene", str(scene_path), "--viewer", "off"]
        self.proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.output: list[str] = []
        ready = threading.Event()

        def pump() -> None:
            for line in self.proc.stdout:
                self.output.append(line)
                if "ready on" in line:
                    ready.set()
            ready.set()

        self._reader = threading.Thread(target=pump, daemon=True)
        self._reader.start()
        if not ready.wait(120) or self.proc.poll() is not None:
            self.proc.kill()
            raise RuntimeError("server did not become ready:\n" + "".join(self.output))

    def client_args(self) -> list[str]:
        """The connection flags of a client of this server."""
        return ["--connect", self.endpoint, "--vehicle-id", self.vehicle_id]

    def stop(self) -> str:
        """SIGTERM, wait, and return everything the server printed."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(timeout=5)
        return "".join(self.output)


def client_command(module: str, *args: str) -> list[str]:
    """``python -m clients.MODULE ARGS`` (run from the repository root)."""
    return [sys.executable, "-m", f"clients.{module}", *args]


def client_env() -> dict[str, str]:
    """Environment of a client subprocess: headless SDL, no pygame banner."""
    env = dict(os.environ)
    env.update(SDL_VIDEODRIVER="dummy", SDL_AUDIODRIVER="dummy",
               PYGAME_HIDE_SUPPORT_PROMPT="1", PYTHONUNBUFFERED="1")
    return env


class Watcher:
    """A protocol client that only listens (state history), as an independent observer."""

    def __init__(self, server: ServerProcess) -> None:
        cfg = make_zenoh_config(listen=[], connect=[server.endpoint])
        self.ep = ZenohEndpoint(cfg, prefix="simserver", vehicle=server.vehicle_id)
        self.states = self.ep.declare_state_inbox(capacity=1 << 15)
        self.history: list[np.void] = []

    def poll(self) -> list[np.void]:
        """Decode everything received; returns the whole history."""
        for payload in self.states.drain_newest():
            self.history.append(proto.decode_state(payload))
        return self.history

    def watch(self, seconds: float) -> list[np.void]:
        """Poll for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.poll()
            time.sleep(0.01)
        return self.poll()

    def newest(self, timeout_s: float = 5.0) -> np.void:
        """The newest state (waits for one)."""
        end = time.monotonic() + timeout_s
        while not self.poll() and time.monotonic() < end:
            time.sleep(0.01)
        assert self.history, "no state received"
        return self.history[-1]

    def close(self) -> None:
        """Close the session."""
        self.ep.close()
