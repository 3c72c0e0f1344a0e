"""Headless Chromium driven over the DevTools protocol, for tests of the web viewer.

Chromium is started with ``--remote-debugging-pipe``: the protocol's JSON messages go
over two pipes (the browser reads file descriptor 3 and writes 4, each message ended by
a NUL byte), so no WebSocket client package and no debugging port are needed.

Software GL: this machine has no GPU; ``--use-angle=swiftshader`` with
``--enable-unsafe-swiftshader`` gives the page WebGL 2 on the CPU (Rerun's web viewer
falls back to WebGL where WebGPU is missing). The flags that keep a headless Chromium off
the network on a machine with none (no background networking, component updates, sync)
are from the machine's notes; the page's own requests are recorded (``requests``) so a
test can check that nothing but loopback was asked for.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")

CHROMIUM_FLAGS = (
    "--headless=new", "--no-first-run", "--no-default-browser-check",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-quic", "--disable-breakpad", "--disable-dev-shm-usage",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--enable-webgl", "--mute-audio",
)


def chromium_path() -> str | None:
    """The Chromium executable on PATH, or None."""
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


class BrowserError(RuntimeError):
    """The browser ended, or did not answer a DevTools command in time."""


class Browser:
    """One headless Chromium with one page, driven over the DevTools pipe.

    Parameters
    ----------
    width, height : int
        The window's size in CSS pixels (the screenshot's size).
    executable : str, optional
        Default ``chromium_path()``.
    """

    def __init__(self, width: int = 1280, height: int = 800,
                 executable: str | None = None) -> None:
        exe = executable or chromium_path()
        if exe is None:
            raise BrowserError("no Chromium on PATH (Debian: apt-get install chromium)")
        self._profile = tempfile.TemporaryDirectory(prefix="simserver_chromium_")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # the browser's ends, moved above 4 so that the shell's 3<&N 4>&M cannot close them
        to_browser_r, from_browser_w = (_above_four(fd) for fd in (to_browser_r,
                                                                    from_browser_w))
        argv = [exe, *CHROMIUM_FLAGS, "--remote-debugging-pipe",
                f"--user-data-dir={self._profile.name}", f"--window-size={width},{height}"]
        if os.geteuid() == 0:  # Chromium's sandbox refuses root
            argv.append("--no-sandbox")
        argv.append("about:blank")
        # the browser reads commands on fd 3 and writes replies and events on fd 4: a
        # shell moves the pipe ends there and execs it (no preexec_fn in a threaded test)
        shell = (f'exec "$0" "$@" 3<&{to_browser_r} 4>&{from_browser_w} '
                 f'{to_browser_r}<&- {from_browser_w}>&-')
        self.proc = subprocess.Popen(
            ["/bin/bash", "-c", shell, *argv], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            pass_fds=(to_browser_r, from_browser_w), start_new_session=True)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._next_id = 0
        self._replies: dict[int, dict[str, Any]] = {}
        self._cond = threading.Condition()
        self.events: list[dict[str, Any]] = []
        self.requests: list[str] = []
        """Every URL the page asked for (``Network.requestWillBeSent``)."""
        self.blocked: dict[str, str] = {}
        """URLs the browser refused to fetch, with why (``csp``: the page's policy)."""
        self._urls: dict[str, str] = {}
        self.console: list[str] = []
        """The page's console messages and uncaught exceptions, as text."""
        self.stderr: list[str] = []
        self._closed = False
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()
        target = self.send("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.send("Target.attachToTarget", targetId=target,
                                 flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Network"):
            self.send(f"{domain}.enable", session=True)

    # -------------------------------------------------------------- the pipe
    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr.append(line.decode(errors="replace").rstrip())

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_browser, 1 << 20)
            except OSError:
                chunk = b""
            if not chunk:
                with self._cond:
                    self._closed = True
                    self._cond.notify_all()
                return
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                self._dispatch(json.loads(raw))

    def _dispatch(self, msg: dict[str, Any]) -> None:
        method = msg.get("method")
        if method == "Network.requestWillBeSent":
            self.requests.append(msg["params"]["request"]["url"])
            self._urls[msg["params"]["requestId"]] = msg["params"]["request"]["url"]
        elif method == "Network.loadingFailed" and msg["params"].get("blockedReason"):
            url = self._urls.get(msg["params"]["requestId"], "?")
            self.blocked[url] = msg["params"]["blockedReason"]
        elif method == "Runtime.consoleAPICalled":
            args = msg["params"].get("args", [])
            self.console.append(" ".join(str(a.get("value", a.get("description", "")))
                                         for a in args))
        elif method == "Runtime.exceptionThrown":
            self.console.append(str(msg["params"]["exceptionDetails"].get("text")))
        with self._cond:
            if "id" in msg:
                self._replies[msg["id"]] = msg
            self._cond.notify_all()

    def send(self, method: str, session: bool = False, timeout_s: float = 60.0,
             **params: Any) -> dict[str, Any]:
        """Send one DevTools command (to the page's session with ``session``) and return
        its result; raises ``BrowserError`` on an error reply, a timeout or a dead browser."""
        with self._cond:
            self._next_id += 1
            msg_id = self._next_id
        msg: dict[str, Any] = {"id": msg_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        try:
            os.write(self._to_browser, json.dumps(msg).encode() + b"\0")
        except OSError as exc:
            raise BrowserError(f"{method}: the browser is gone ({exc})") from None
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while msg_id not in self._replies:
                left = deadline - time.monotonic()
                if self._closed or left <= 0:
                    what = "ended" if self._closed else f"gave no reply in {timeout_s:g} s"
                    raise BrowserError(f"{method}: the browser {what}; "
                                       f"stderr: {self.stderr[-5:]}")
                self._cond.wait(left)
            reply = self._replies.pop(msg_id)
        if "error" in reply:
            raise BrowserError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    # -------------------------------------------------------------- the page
    def goto(self, url: str) -> None:
        """Open ``url`` in the page (returns once the navigation is committed)."""
        self.send("Page.navigate", session=True, url=url)

    def evaluate(self, expression: str, timeout_s: float = 30.0) -> Any:
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.send("Runtime.evaluate", session=True, timeout_s=timeout_s,
                           expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise BrowserError(f"{expression!r}: {result['exceptionDetails'].get('text')}")
        return result.get("result", {}).get("value")

    def screenshot_png(self) -> bytes:
        """A PNG of the page as shown now."""
        data = self.send("Page.captureScreenshot", session=True, format="png")["data"]
        return base64.b64decode(data)

    def wait(self, poll: Callable[[], Any], timeout_s: float, interval_s: float = 0.5,
             what: str = "the page") -> Any:
        """``poll()`` until it returns something true, or ``BrowserError`` after
        ``timeout_s`` (with the page's last console lines)."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = poll()
            if value:
                return value
            if time.monotonic() > deadline:
                raise BrowserError(f"{what}: not within {timeout_s:g} s; console: "
                                   f"{self.console[-8:]}")
            time.sleep(interval_s)

    def close(self) -> None:
        """End the browser and remove its profile."""
        if self.proc.poll() is None:
            try:
                self.send("Browser.close", timeout_s=5.0)
            except BrowserError:
                pass
            try:
                self.proc.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for fd in (self._to_browser, self._from_browser):
            try:
                os.close(fd)
            except OSError:
                pass
        self._profile.cleanup()

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _above_four(fd: int) -> int:
    """``fd`` moved to a descriptor number of at least 10 (the original closed)."""
    moved = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10)
    os.close(fd)
    return moved


def web_viewer_recording(browser: Browser, path: str | os.PathLike[str],
                         timeout_s: float = 120.0) -> bool:
    """Write what Rerun's web viewer in ``browser`` holds of its active recording to
    ``path`` (an ``.rrd``, from the viewer's own ``save_recording``): what the browser
    has received and ingested, not what was sent. False when the viewer is not started
    or has no recording yet."""
    data = browser.evaluate(
        "(async () => { const h = window._handle; if (!h) return null;"
        " let r; try { r = await h.save_recording(); } catch (e) { return null; }"
        " if (!r || !r.length) return null; let s = '';"
        " for (let i = 0; i < r.length; i += 32768)"
        "   s += String.fromCharCode.apply(null, r.subarray(i, i + 32768));"
        " return btoa(s); })()", timeout_s=timeout_s)
    if not data:
        return False
    with open(path, "wb") as f:
        f.write(base64.b64decode(data))
    return True


def recording_extent(path: str | os.PathLike[str], entity_prefix: str,
                     timeline: str = "sim_time") -> tuple[set[str], float | None]:
    """The entity paths of an ``.rrd`` and the newest ``timeline`` time (s) logged on
    entities under ``entity_prefix`` (None when none is)."""
    from rerun.chunk import RrdReader

    paths: set[str] = set()
    newest_ns: int | None = None
    try:
        chunks = RrdReader(path).stream()
    except ValueError:  # "No recording store found": nothing of the recording yet
        return paths, None
    for chunk in chunks:
        paths.add(chunk.entity_path)
        if chunk.is_static or not chunk.entity_path.startswith(entity_prefix):
            continue
        batch = chunk.to_record_batch()
        if timeline not in batch.schema.names:
            continue
        times = [t for t in batch.column(timeline).cast("int64").to_pylist() if t is not None]
        if times:
            newest_ns = max(times) if newest_ns is None else max(newest_ns, *times)
    return paths, None if newest_ns is None else newest_ns * 1e-9


GEOMETRY_FIELDS = ("half_sizes", "lengths", "vertex_positions", "strips")
"""The component fields that give an entity something to draw (``Boxes3D:half_sizes``,
``Cylinders3D:lengths``, ``Mesh3D:vertex_positions``, ``LineStrips3D:strips``): an entity
path alone, or a ``Clear``, draws nothing."""


@dataclass
class PageCar:
    """What a page's viewer holds of a car (``car_in_page``)."""

    parts_with_geometry: set[str] = field(default_factory=set)
    """The car's parts that hold geometry in the page."""
    pose_times_s: set[float] = field(default_factory=set)
    """The ``sim_time`` stamps (s) at which the car's own pose (its transform) is held."""
    entities: int = 0
    """How many entity paths the page holds in all."""

    def drawn(self, parts: Iterable[str]) -> bool:
        """The car counts as drawn: every one of ``parts`` has geometry, and the car has
        been placed at two or more instants of ``sim_time`` (it is shown moving on that
        timeline, not a single frame of a stalled start)."""
        return set(parts) <= self.parts_with_geometry and len(self.pose_times_s) >= 2


def car_in_page(path: str | os.PathLike[str], car_entity: str, parts: Iterable[str],
                timeline: str = "sim_time") -> PageCar:
    """What the ``.rrd`` a page's viewer saved (``web_viewer_recording``) holds of the car
    at ``car_entity``: which of ``parts`` carry geometry (``GEOMETRY_FIELDS``, a non-empty
    value) and at which ``timeline`` instants the car's own transform is logged."""
    from rerun.chunk import RrdReader

    wanted = set(parts)
    found = PageCar()
    try:
        chunks = RrdReader(path).stream()
    except ValueError:  # "No recording store found": nothing of the recording yet
        return found
    paths: set[str] = set()
    for chunk in chunks:
        paths.add(chunk.entity_path)
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if chunk.entity_path in wanted:
            for name in names:
                if name.rsplit(":", 1)[-1] in GEOMETRY_FIELDS and any(
                        v for v in batch.column(name).to_pylist()):
                    found.parts_with_geometry.add(chunk.entity_path)
        if chunk.entity_path == car_entity and timeline in names and any(
                n.startswith("Transform3D:") for n in names):
            found.pose_times_s.update(t * 1e-9 for t in
                                      batch.column(timeline).cast("int64").to_pylist()
                                      if t is not None)
    found.entities = len(paths)
    return found
