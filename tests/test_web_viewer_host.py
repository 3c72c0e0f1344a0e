"""Rerun's web viewer served offline (``simserver.adapters.web_viewer_host``, issue 35).

rerun-sdk 0.41's own page links Google's web fonts and starts a viewer that checks
GitHub for a newer release and sends usage data to Rerun. The view serves that page
through its own host: with the update check off, without the font links, and with a
Content-Security-Policy that lets the page reach only itself and the view's gRPC server.
Real servers on loopback: Rerun's web server and the host in front of it, read with
``urllib`` (the browser's side: ``tests/test_web_view.py``).
"""

from __future__ import annotations

import urllib.request

import pytest
import rerun as rr

from simserver.adapters.rerun_sink import RerunSinkError, open_recording
from simserver.adapters.web_viewer_host import (
    UPDATE_CHECK_OPTION,
    WebHostError,
    content_security_policy,
    offline_page,
)
from simserver.testing import free_port

NO_PROXY = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def fetch(url: str) -> tuple[bytes, dict[str, str]]:
    with NO_PROXY.open(url, timeout=60.0) as reply:
        return reply.read(), dict(reply.headers)


@pytest.fixture(scope="module")
def served():
    """``open_recording("serve", ..., web_port=...)`` as ``simserver view --web-port``
    opens it; yields the web port and the gRPC URL."""
    grpc_port, web_port = free_port(), free_port()
    lines: list[str] = []
    rec = open_recording("serve", f"127.0.0.1:{grpc_port}", recording_id="host-test",
                         web_port=web_port, announce=lines.append)
    yield web_port, f"rerun+http://127.0.0.1:{grpc_port}/proxy", lines
    rec.disconnect()


def test_the_page_is_served_with_the_update_check_off_and_no_web_fonts(served):
    web_port, grpc_url, lines = served
    page, headers = fetch(f"http://127.0.0.1:{web_port}/")
    text = page.decode()
    assert UPDATE_CHECK_OPTION in text
    assert "fonts.googleapis.com" not in text and "fonts.gstatic.com" not in text
    policy = headers["Content-Security-Policy"]
    assert policy == content_security_policy(grpc_url)
    connect_src = next(p for p in policy.split(";") if p.strip().startswith("connect-src"))
    grpc_port = grpc_url.split(":")[2].split("/")[0]
    assert connect_src.split()[1:] == ["'self'", f"http://127.0.0.1:{grpc_port}"]
    assert lines and f"http://127.0.0.1:{web_port}/?url=" in lines[-1]


def test_the_viewer_files_pass_through_unchanged(served):
    web_port, _, _ = served
    wasm, headers = fetch(f"http://127.0.0.1:{web_port}/re_viewer_bg.wasm")
    assert wasm[:4] == b"\0asm"
    assert headers["Content-Type"] == "application/wasm"  # WebAssembly.instantiateStreaming
    assert len(wasm) > 1_000_000


def test_rerun_pages_own_version_does_not_reach_the_internet_offline_does():
    """The page as rerun-sdk 0.41 serves it links the fonts and passes no update-check
    option (what the offline host changes); a page of another shape is refused."""
    port = free_port()
    rr.serve_web_viewer(web_port=port, open_browser=False,
                        connect_to="rerun+http://127.0.0.1:1/proxy")
    from simserver.testing import wait_until

    page = wait_until(lambda: _try_fetch(f"http://127.0.0.1:{port}/"), timeout_s=60.0,
                      what="rerun's web server")
    assert "fonts.googleapis.com" in page and UPDATE_CHECK_OPTION not in page
    assert UPDATE_CHECK_OPTION in offline_page(page)
    with pytest.raises(WebHostError, match="not rerun-sdk 0.41"):
        offline_page("<html>another viewer</html>")


def _try_fetch(url: str) -> str | None:
    try:
        return fetch(url)[0].decode()
    except OSError:
        return None


def test_a_web_port_in_use_is_a_one_line_error():
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(RerunSinkError, match=f"127.0.0.1:{port} is in use"):
            open_recording("serve", f"127.0.0.1:{free_port()}", web_port=port)
