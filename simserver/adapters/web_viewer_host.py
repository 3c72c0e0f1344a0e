"""Rerun's web viewer served offline: no telemetry, no version check, no web fonts.

rerun-sdk 0.41's web viewer (``rr.serve_web_viewer``) asks the internet from the browser
as it starts: its page loads fonts from Google, its viewer asks GitHub for the latest
release and sends usage data to Rerun (seen from headless Chromium: requests to
``fonts.googleapis.com``, ``api.github.com/repos/rerun-io/rerun/releases/latest`` and
``tel.rerun.io``), and its URL takes no option to stop any of it. On a machine with no
network each is a failed request; on one with a network, the view of a private server
should not report to anyone.

So ``simserver view`` serves the web viewer through this small host in its own process:
Rerun's web server runs on an internal loopback-side port, and this host, on the port the
user asked for, hands on every file unchanged except the page itself, which it changes
in three ways:

- the viewer is started with ``check_for_updates_on_startup: false`` (an option of the
  viewer that the page does not pass on from its URL);
- the links to the web fonts are dropped (the viewer draws with its own fonts);
- the page is sent with a Content-Security-Policy that lets it connect only to itself and
  to the gRPC server it shows (``connect-src``): the browser refuses anything else,
  Rerun's analytics included, whatever the viewer's saved settings say.

The host binds the gRPC server's address (loopback by default). rerun-sdk 0.41 binds its
own web server to all interfaces; here that is a port no one is told about, serving only
the viewer's files.
"""

from __future__ import annotations

import http.server
import re
import threading
import time
import urllib.error
import urllib.request
from urllib.parse import urlsplit

PAGE_PATHS = ("/", "/index.html")

FONT_LINK = re.compile(r'\s*<link[^>]*href="https://fonts\.(googleapis|gstatic)\.com[^"]*"[^>]*>')
"""The page's links to web fonts (preconnects and the stylesheet)."""

UPDATE_CHECK_OPTION = "check_for_updates_on_startup: false,"
OPTIONS_ANCHOR = "enable_history: true,"
"""Where the page builds the viewer's options: the update check option is added after it."""

CHUNK_BYTES = 1 << 16

STARTUP_WAIT_S = 30.0
"""How long to wait for Rerun's own web server to answer (a starved machine)."""

_LOCAL = urllib.request.build_opener(urllib.request.ProxyHandler({}))
"""Fetches from Rerun's web server on this machine, never through a proxy of the
environment."""


class WebHostError(RuntimeError):
    """Rerun's page is not as expected (another rerun-sdk): nothing is served."""


def offline_page(html: str) -> str:
    """Rerun's web viewer page with the update check off and no web font links.

    Raises ``WebHostError`` when the page has no viewer options to change (a rerun-sdk
    whose page differs from 0.41's).
    """
    if OPTIONS_ANCHOR not in html:
        raise WebHostError("rerun's web viewer page has no 'enable_history: true,' option "
                           "to add the update check option to (not rerun-sdk 0.41?)")
    html = html.replace(OPTIONS_ANCHOR, f"{OPTIONS_ANCHOR} {UPDATE_CHECK_OPTION}", 1)
    return FONT_LINK.sub("", html)


def content_security_policy(grpc_url: str) -> str:
    """The page's policy: its own files, inline scripts and WebAssembly, and connections
    to itself and to ``grpc_url``'s origin only."""
    parts = urlsplit(grpc_url.replace("rerun+", "", 1))
    grpc_origin = f"{parts.scheme}://{parts.netloc}"
    return ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
            "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
            f"font-src 'self' data:; worker-src 'self' blob:; connect-src 'self' {grpc_origin}")


def serve_offline(host: str, port: int, rerun_port: int, grpc_url: str) -> http.server.HTTPServer:
    """Serve Rerun's web viewer (running on ``rerun_port`` on this machine) at
    ``host:port`` with ``offline_page`` and its ``content_security_policy``; returns the
    server, running in a daemon thread (``shutdown()`` stops it).

    The page is fetched and checked once first, so that a changed page fails here.
    """
    upstream = f"http://127.0.0.1:{rerun_port}"
    deadline = time.monotonic() + STARTUP_WAIT_S
    while True:  # Rerun's server starts in a thread of its own: it may not listen yet
        try:
            with _LOCAL.open(upstream + "/", timeout=30.0) as reply:
                page = offline_page(reply.read().decode()).encode()
            break
        except urllib.error.URLError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
    policy = content_security_policy(grpc_url)

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the http.server name
            path = self.path.split("?", 1)[0]
            if path in PAGE_PATHS:
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(page)))
                self.send_header("Content-Security-Policy", policy)
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                self.wfile.write(page)
                return
            try:
                reply = _LOCAL.open(upstream + self.path, timeout=60.0)
            except urllib.error.HTTPError as exc:
                self.send_error(exc.code)
                return
            except OSError:
                self.send_error(502)
                return
            with reply:
                self.send_response(reply.status)
                for name in ("Content-Type", "Content-Length", "Content-Encoding"):
                    if reply.headers.get(name):
                        self.send_header(name, reply.headers[name])
                self.end_headers()
                while chunk := reply.read(CHUNK_BYTES):
                    self.wfile.write(chunk)

        def log_message(self, *_: object) -> None:  # quiet: the view prints its own lines
            pass

    server = http.server.ThreadingHTTPServer((host, port), Handler)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, name="web-viewer-host",
                     daemon=True).start()
    return server
