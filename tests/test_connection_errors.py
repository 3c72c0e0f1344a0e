"""Connection errors that say what the server wants (issue 35 item 3), and ``simserver
view --zenoh-config`` with each client config the docs show.

zenoh 1.10 answers "Unable to connect to any of [...]" whatever went wrong, and a
peer-mode client (``simserver view``) pointed with plain TCP at a TLS server opens its
session and was then told to start a server. Now the error names what is missing: TLS,
the CA file, a client certificate, credentials (``simserver.adapters.zenoh_diagnose``).

Real ``simserver serve`` subprocesses running the example configs of ``configs/zenoh/``
as shipped (placeholders filled with throwaway certificates and random passwords), real
zenoh clients, real ``simserver view`` subprocesses writing recordings read back.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from simserver.adapters.rerun_scene import CAR
from simserver.adapters.zenoh_io import ZenohOpenError
from simserver.testing import Client, OutputProcess, ServerProcess, free_port, wait_until
from simserver.testing.pki import make_pki, materialize

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    root = make_pki(tmp_path_factory.mktemp("pki"))
    passwords = {"driver": secrets.token_urlsafe(16), "viewer": secrets.token_urlsafe(16)}
    users = root / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()), encoding="ascii")
    users.chmod(0o600)
    (root / "passwords.json").write_text(json.dumps(passwords), encoding="ascii")
    return root


def _password(pki: Path, user: str) -> str:
    return json.loads((pki / "passwords.json").read_text(encoding="ascii"))[user]


@pytest.fixture(scope="module")
def servers(pki) -> Iterator[dict[str, tuple[ServerProcess, int]]]:
    """One server per secured example: TLS only, TLS + user/password, mutual TLS."""
    out: dict[str, tuple[ServerProcess, int]] = {}
    try:
        for example in ("server_tls.json5", "server_auth_acl.json5", "server_mtls_acl.json5"):
            port = free_port()
            out[example] = (ServerProcess(
                listen=[f"tls/127.0.0.1:{port}"],
                extra_args=["--zenoh-config", str(materialize(example, pki))]), port)
        yield out
    finally:
        for server, _ in out.values():
            server.stop()


def open_error(endpoint: str, zenoh_config: Path | None = None) -> str:
    with pytest.raises(ZenohOpenError) as err:
        Client(endpoint, zenoh_config=zenoh_config)
    return str(err.value)


def test_plain_tcp_to_a_tls_server_is_told_it_speaks_tls(servers):
    _, port = servers["server_tls.json5"]
    message = open_error(f"tcp/127.0.0.1:{port}")
    # before: "cannot open the zenoh session: Unable to connect to any of [...]!" alone
    assert "Unable to connect" in message
    assert f"the server at 127.0.0.1:{port} speaks TLS and this client plain TCP" in message
    assert f"tls/127.0.0.1:{port}" in message and "root_ca_certificate" in message


def test_a_tls_client_without_the_ca_is_told_to_name_the_ca_file(servers, pki):
    _, port = servers["server_tls.json5"]
    message = open_error(f"tls/127.0.0.1:{port}")  # TLS, system roots only
    assert "does not trust its certificate" in message, message
    assert "names no CA file (transport.link.tls.root_ca_certificate)" in message
    # a CA file that did not sign the server's certificate: named in the error
    other_ca = materialize("client_tls.json5", pki, "other_ca.json5",
                           replace={"tls/ca.pem": "tls/rogue_ca.pem"})
    message = open_error(f"tls/127.0.0.1:{port}", other_ca)
    assert f"is not signed by the CA in {pki}/tls/rogue_ca.pem" in message, message


def test_credentials_missing_or_refused_are_named(servers, pki):
    _, port = servers["server_auth_acl.json5"]
    endpoint = f"tls/127.0.0.1:{port}"
    message = open_error(endpoint, materialize("client_tls.json5", pki))
    assert "the server refused the zenoh session: it requires credentials " \
           "(transport.auth.usrpwd.user and password" in message, message
    wrong = materialize("client_driver.json5", pki, "wrong.json5", replace={
        "REPLACE-WITH-THE-DRIVER-PASSWORD": _password(pki, "driver") + "x"})
    message = open_error(endpoint, wrong)
    assert "refused the credentials of user 'driver'" in message, message
    # credentials sent to a server that asks for none: zenoh refuses the session too
    _, tls_port = servers["server_tls.json5"]
    message = open_error(f"tls/127.0.0.1:{tls_port}", wrong)
    assert "does not ask for credentials" in message and "remove transport.auth.usrpwd" \
        in message, message


def test_a_client_without_a_certificate_is_told_the_server_wants_one(servers, pki):
    _, port = servers["server_mtls_acl.json5"]
    message = open_error(f"tls/127.0.0.1:{port}", materialize("client_tls.json5", pki))
    assert "requires a client certificate (mutual TLS" in message, message
    assert "connect_certificate" in message


def _view_env(tmp_path: Path) -> dict[str, str]:
    return dict(os.environ, PYTHONUNBUFFERED="1",
                XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
                XDG_DATA_HOME=str(tmp_path / "xdg_data"))


def test_a_plain_tcp_view_of_a_tls_server_says_it_wants_tls(servers, tmp_path):
    """The view's default session is a peer: it opens, reaches nobody, and used to say
    the server was not started."""
    _, port = servers["server_tls.json5"]
    viewer = OutputProcess([sys.executable, "-m", "simserver", "view", "--sink",
                            f"save:{tmp_path / 'x.rrd'}", "--connect",
                            f"tcp/127.0.0.1:{port}", "--wait", "3", "--normal-priority"],
                           env=_view_env(tmp_path))
    assert viewer.wait(timeout_s=120.0) == 3, viewer.text()
    (final,) = [ln for ln in viewer.text().splitlines() if ln.startswith("error:")]
    assert "liveliness token simserver/car0/alive was never seen" in final
    assert f"the server at 127.0.0.1:{port} speaks TLS and this client plain TCP" in final
    assert "it is not started" not in final
    assert "Traceback" not in viewer.text()


@pytest.mark.parametrize(("server_example", "client_example", "replace"), [
    ("server_auth_acl.json5", "client_viewer.json5",
     {"REPLACE-WITH-THE-VIEWER-PASSWORD": "viewer"}),
    ("server_auth_acl.json5", "client_driver.json5",
     {"REPLACE-WITH-THE-DRIVER-PASSWORD": "driver"}),
    ("server_mtls_acl.json5", "client_mtls.json5",
     {"tls/client.key": "tls/viewer.key", "tls/client.pem": "tls/viewer.pem"}),
], ids=["credentials-viewer", "credentials-driver", "mutual-tls-viewer"])
def test_view_with_each_documented_client_config_draws(servers, pki, tmp_path,
                                                        server_example, client_example,
                                                        replace):
    """``simserver view --zenoh-config FILE`` with the docs' client configs (the TLS-only
    one: ``test_security``), the file's own endpoint used (its placeholder server name
    replaced by the test server's)."""
    _, port = servers[server_example]
    fill = {k: (_password(pki, v) if k.startswith("REPLACE") else v)
            for k, v in replace.items()}
    fill["tls/simserver.lab.example:7447"] = f"tls/localhost:{port}"
    cfg = materialize(client_example, pki, f"view_{client_example}", replace=fill)
    rrd = tmp_path / "view.rrd"
    viewer = OutputProcess([sys.executable, "-m", "simserver", "view", "--sink",
                            f"save:{rrd}", "--zenoh-config", str(cfg), "--normal-priority",
                            "--wait", "120"], env=_view_env(tmp_path))
    try:
        wait_until(lambda: rrd.exists() and rrd.stat().st_size > 100_000
                   or not viewer.alive(), timeout_s=120.0, interval_s=0.05,
                   what=f"the view with {client_example} to draw")
        assert viewer.alive(), viewer.text()
        assert viewer.stop(timeout_s=60.0) == 0, viewer.text()
    finally:
        viewer.kill()
    assert "Traceback" not in viewer.text(), viewer.text()
    from rerun.chunk import RrdReader

    assert any(c.entity_path.startswith("/" + CAR) and not c.is_static
               for c in RrdReader(rrd).stream()), viewer.text()
