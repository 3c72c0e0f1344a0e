"""Security: safe defaults, and opening the server up with zenoh's own mechanisms.

Real ``simserver serve`` subprocesses and real zenoh clients on loopback. The secured
servers run the example configs of ``configs/zenoh/`` as shipped, with only their
placeholder paths, passwords and listen address replaced: throwaway certificates (made
with ``openssl`` at test time) and random passwords live in pytest's tmp_path and are
never committed.

- defaults: the server listens on 127.0.0.1 only and holds no UDP socket (no multicast
  scouting); its live viewer listens on loopback too;
- TLS (``server_tls.json5``): a client trusting the CA drives; a plain-tcp client, or a
  TLS client that does not trust the CA, cannot open a session;
- user/password + access control (``server_auth_acl.json5``): no session without valid
  credentials; the ``viewer`` user reads state but its commands and controls have no
  effect; the ``driver`` user commands, resets and controls; nobody but the server can
  publish the state;
- mutual TLS + access control by certificate name (``server_mtls_acl.json5``).
"""

from __future__ import annotations

import json
import secrets
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from simserver import protocol as proto
from simserver.adapters.zenoh_io import (
    DEFAULT_LISTEN,
    ZenohOpenError,
    config_warnings,
    make_zenoh_config,
)
from simserver.server import DEFAULT_SERVER_CONFIG, load_server_config
from simserver.testing import (
    CONFIGS,
    Client,
    RoleProcess,
    ServerProcess,
    free_port,
    loopback_endpoint,
    process_sockets,
    state_is_finite,
    wait_until,
)

pytestmark = pytest.mark.timeout(300)

ZENOH_EXAMPLES = CONFIGS / "zenoh"
PLACEHOLDER_DIR = "/etc/simserver/"
PLACEHOLDER_CLIENT_KEY = "/etc/simserver/tls/client.key"
PLACEHOLDER_CLIENT_CERT = "/etc/simserver/tls/client.pem"


# ============================================================================ PKI


def _openssl(*args: str, cwd: Path) -> None:
    proc = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=60)
    if proc.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args)} failed:\n{proc.stderr}")


def _issue(tls: Path, name: str, cn: str, ca: str, ext: str) -> None:
    """Key and certificate ``name.key``/``name.pem`` for ``cn``, signed by ``ca``."""
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out",
             f"{name}.csr", "-subj", f"/CN={cn}", cwd=tls)
    (tls / f"{name}.ext").write_text(ext, encoding="ascii")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
             "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile",
             f"{name}.ext", cwd=tls)


def make_pki(root: Path) -> Path:
    """A throwaway CA, a server certificate for 127.0.0.1/localhost, client certificates.

    Layout (as the example configs expect under ``/etc/simserver/``): ``tls/ca.pem``,
    ``tls/server.{key,pem}``, ``tls/driver.{key,pem}`` (CN driver), ``tls/viewer.{key,pem}``
    (CN viewer), and ``tls/rogue.{key,pem}`` (CN driver, signed by another CA).
    """
    tls = root / "tls"
    tls.mkdir(parents=True)
    for ca, cn in (("ca", "simserver test CA"), ("rogue_ca", "someone else's CA")):
        _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{ca}.key",
                 "-out", f"{ca}.pem", "-days", "2", "-subj", f"/CN={cn}",
                 "-addext", "basicConstraints=critical,CA:TRUE",
                 "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=tls)
    server_ext = ("subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n"
                  "keyUsage=digitalSignature,keyEncipherment\n"
                  "extendedKeyUsage=serverAuth,clientAuth\n")
    client_ext = ("basicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\n"
                  "extendedKeyUsage=clientAuth\n")
    _issue(tls, "server", "simserver", "ca", server_ext)
    _issue(tls, "driver", "driver", "ca", client_ext)
    _issue(tls, "viewer", "viewer", "ca", client_ext)
    _issue(tls, "rogue", "driver", "rogue_ca", client_ext)
    for key in tls.glob("*.key"):
        key.chmod(0o600)
    return root


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Certificates and a user dictionary with random passwords (module-wide)."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    root = make_pki(tmp_path_factory.mktemp("pki"))
    passwords = {"driver": secrets.token_urlsafe(16), "viewer": secrets.token_urlsafe(16)}
    users = root / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()), encoding="ascii")
    users.chmod(0o600)
    (root / "passwords.json").write_text(json.dumps(passwords), encoding="ascii")
    return root


def materialize(example: str, pki_root: Path, out_name: str | None = None,
                replace: dict[str, str] | None = None) -> Path:
    """An example config of ``configs/zenoh`` with its placeholders filled in."""
    text = (ZENOH_EXAMPLES / example).read_text(encoding="utf-8")
    for old, new in (replace or {}).items():
        assert old in text, f"{example} has no placeholder {old!r}"
        text = text.replace(old, new)
    text = text.replace(PLACEHOLDER_DIR, f"{pki_root}/")
    path = pki_root / (out_name or example)
    path.write_text(text, encoding="utf-8")
    path.chmod(0o600)
    return path


def passwords(pki_root: Path) -> dict[str, str]:
    """The random passwords of the module's users."""
    return json.loads((pki_root / "passwords.json").read_text(encoding="ascii"))


@contextmanager
def driver_and_viewer(endpoint: str, driver_cfg: Path,
                      viewer_cfg: Path) -> Iterator[tuple[Client, Client]]:
    """A driver and a viewer client (their own credentials), the server's controls known
    to both (``get_config`` is open to viewers too)."""
    with Client(endpoint, zenoh_config=driver_cfg) as driver, \
            Client(endpoint, zenoh_config=viewer_cfg) as viewer:
        assert driver.wait_controls()["ok"]
        assert viewer.wait_controls()["ok"]
        yield driver, viewer


def no_reply(probe: Client, name: str, args: dict | None = None) -> bool:
    """True if a control request got no reply at all (denied, or nobody serving)."""
    try:
        probe.request(name, args, timeout_s=1.0)
    except TimeoutError:
        return True
    return False


# ============================================================================ defaults


def test_default_config_is_loopback_only_without_multicast_or_shared_memory():
    cfg = load_server_config(DEFAULT_SERVER_CONFIG)
    assert cfg.listen == [DEFAULT_LISTEN] == ["tcp/127.0.0.1:7447"]
    assert cfg.connect is None and cfg.zenoh_config is None and cfg.mode is None
    zcfg = make_zenoh_config(listen=cfg.listen, connect=cfg.connect,
                             config_file=cfg.zenoh_config, mode=cfg.mode)
    assert json.loads(zcfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(zcfg.get_json("connect/endpoints")) == []
    assert json.loads(zcfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(zcfg.get_json("transport/shared_memory/enabled")) is False
    assert config_warnings(zcfg) == []
    # the examples keep multicast off too; only their listen address is "open"
    for example in sorted(ZENOH_EXAMPLES.glob("*.json5")):
        warnings = config_warnings(make_zenoh_config(config_file=example))
        assert not any("multicast" in w or "shared memory" in w for w in warnings), example


def test_default_server_holds_only_a_loopback_listener_and_no_udp_socket():
    """The live default server (and its live viewer): loopback TCP only, no UDP at all.

    No UDP socket means no multicast scouting: nothing is announced on, or accepted from,
    224.0.0.224:7446. The port is the only thing changed from the default config (a free
    one, so the test never collides with a server already on 7447).
    """
    view_port = free_port()
    with ServerProcess(viewer=f"serve:{view_port}") as server:
        socks = process_sockets(server.pid)
        listeners = [s for s in socks if s.listening]
        assert [(s.local_ip, s.local_port) for s in listeners] == [("127.0.0.1", server.port)]
        assert not [s for s in socks if s.proto.startswith("udp")], socks
        # the live viewer (its own process) serves Rerun on loopback only
        viewer_listeners = wait_until(
            lambda: [s for pid in server.children() for s in process_sockets(pid)
                     if s.listening], timeout_s=60, what="the viewer listening",
            interval_s=0.3)
        assert viewer_listeners, "the viewer did not start listening"
        assert all(s.local_ip == "127.0.0.1" for s in viewer_listeners), viewer_listeners
        assert view_port in [s.local_port for s in viewer_listeners]
        assert server.alive()
    assert server.returncode == 0


# ============================================================================ TLS


def test_tls_client_that_trusts_the_ca_drives_and_plain_tcp_cannot_talk(pki):
    server_cfg = materialize("server_tls.json5", pki)
    client_cfg = materialize("client_tls.json5", pki)
    port = free_port()
    tls_ep, tcp_ep = f"tls/127.0.0.1:{port}", f"tcp/127.0.0.1:{port}"
    with ServerProcess(listen=[tls_ep], extra_args=["--zenoh-config", str(server_cfg)]) as server:
        socks = process_sockets(server.pid)
        assert [(s.local_ip, s.local_port) for s in socks if s.listening] == \
            [("127.0.0.1", port)]
        assert not [s for s in socks if s.proto.startswith("udp")]
        with Client(tls_ep, zenoh_config=client_cfg) as client:
            assert client.wait_controls()["ok"]
            assert client.request("reset")["ok"]
            state = client.drive_until(lambda s: s["u_mps"] > 1.0 and s["throttle"] > 0.49
                                       and not s["flags"] & proto.StateFlag.WATCHDOG,
                                       throttle=0.5, gear=proto.Gear.D, what="driving")
            assert state is not None and state_is_finite(state)
            assert state["throttle"] > 0.49 and state["u_mps"] > 1.0
            assert not state["flags"] & proto.StateFlag.WATCHDOG
            before = client.diagnostics()
            # plain tcp to the TLS port: no session (client mode fails to open) ...
            with pytest.raises(ZenohOpenError):
                Client(tcp_ep)
            # ... nor a TLS client that does not trust the CA (system roots only) ...
            with pytest.raises(ZenohOpenError):
                Client(tls_ep)
            # ... and a peer, which opens anyway, reaches nothing: no command arrives
            with Client(tcp_ep, mode="peer") as intruder:
                intruder.drive(0.5, brake=1.0)
                assert no_reply(intruder, "reset")
                assert intruder.received == 0
            after = client.diagnostics()
            # only the legitimate client's commands were counted (none during the attempt)
            assert after["cmd_received"] == before["cmd_received"]
            assert after["cmd_rejected"] == before["cmd_rejected"]
    assert server.returncode == 0


# ============================================================================ user/password + ACL


@pytest.fixture(scope="module")
def acl_server(pki) -> Iterator[tuple[ServerProcess, str, dict[str, Path]]]:
    """server_auth_acl.json5 (TLS + user/password + access control) and client configs."""
    pw = passwords(pki)
    configs = {
        "server": materialize("server_auth_acl.json5", pki),
        "driver": materialize("client_driver.json5", pki, replace={
            "REPLACE-WITH-THE-DRIVER-PASSWORD": pw["driver"]}),
        "viewer": materialize("client_viewer.json5", pki, replace={
            "REPLACE-WITH-THE-VIEWER-PASSWORD": pw["viewer"]}),
        "wrong_password": materialize("client_driver.json5", pki, "wrong_password.json5",
                                      replace={"REPLACE-WITH-THE-DRIVER-PASSWORD":
                                               pw["driver"] + "x"}),
        "unknown_user": materialize("client_driver.json5", pki, "unknown_user.json5",
                                    replace={'user: "driver"': 'user: "mallory"',
                                             "REPLACE-WITH-THE-DRIVER-PASSWORD":
                                             pw["driver"]}),
        "no_credentials": materialize("client_tls.json5", pki),
    }
    endpoint = loopback_endpoint("tls")
    server = ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                       str(configs["server"])])
    try:
        yield server, endpoint, configs
    finally:
        server.stop()


def test_no_session_without_valid_credentials(acl_server):
    server, endpoint, configs = acl_server
    for name in ("no_credentials", "wrong_password", "unknown_user"):
        with pytest.raises(ZenohOpenError):
            Client(endpoint, zenoh_config=configs[name])
    with Client(endpoint, zenoh_config=configs["driver"]) as driver:
        driver.wait_controls()
        driver.drive(0.5, throttle=0.3)
        before = driver.diagnostics()
        # a peer opens a session anyway; without credentials it never gets a link
        with Client(endpoint, zenoh_config=configs["no_credentials"], mode="peer") as peer:
            peer.drive(0.5, brake=1.0, gear=proto.Gear.R)
            assert no_reply(peer, "reset") and no_reply(peer, "pause")
            assert peer.received == 0  # and it reads nothing either
        driver.drive(0.3, throttle=0.3)
        after = driver.diagnostics()
        sent_by_driver = driver.seq
        assert after["cmd_received"] - before["cmd_received"] <= sent_by_driver
        assert after["cmd_rejected"] == before["cmd_rejected"]
        state = driver.fresh_state()
        assert state["gear"] == proto.Gear.D and state["throttle"] > 0.29  # not reversed
        assert not state["flags"] & proto.StateFlag.PAUSED
    assert server.alive()


def test_viewer_reads_state_but_cannot_command_or_control(acl_server):
    server, endpoint, configs = acl_server
    with driver_and_viewer(endpoint, configs["driver"], configs["viewer"]) as (driver, viewer):
        assert viewer.ep.alive_tokens() == ["simserver/car0/alive"]
        assert driver.request("reset")["ok"]
        moved = driver.drive_until(lambda s: s["u_mps"] > 1.0, throttle=0.4, what="moving")
        assert moved["u_mps"] > 1.0
        road = driver.request("get_config")["config"]["road"]
        driver.wait_state(lambda s: s["flags"] & proto.StateFlag.WATCHDOG,
                          what="the watchdog holding the car")  # the driver is silent
        before = driver.diagnostics()
        state0 = driver.fresh_state()
        # the viewer reads the state ...
        assert state_is_finite(viewer.fresh_state())
        # ... but its commands never reach the server
        viewer.drive(1.0, throttle=1.0, gear=proto.Gear.D)
        after = driver.diagnostics()
        assert after["cmd_received"] == before["cmd_received"]
        assert after["cmd_rejected"] == before["cmd_rejected"]
        state = driver.fresh_state()
        assert state["throttle"] == 0.0 and state["flags"] & proto.StateFlag.WATCHDOG
        assert state["u_mps"] < moved["u_mps"]  # braking, not driven
        # ... and its controls get no reply and change nothing
        hill = str(CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml")
        for name, args in (("reset", None), ("pause", None), ("set_road", {"grade_pct": 20}),
                           ("load", {"scene": hill}), ("step", {"n": 5})):
            assert no_reply(viewer, name, args), name
        state1 = driver.fresh_state()
        assert state1["tick"] > state0["tick"]  # not reset, not paused
        assert not state1["flags"] & proto.StateFlag.PAUSED
        config = driver.request("get_config")["config"]
        assert config["road"] == road
        assert config["scene"]["path"].endswith("flat_paper_sedan.yaml")
    assert server.alive()


def test_driver_commands_resets_and_controls(acl_server):
    server, endpoint, configs = acl_server
    with Client(endpoint, zenoh_config=configs["driver"]) as driver:
        driver.wait_controls()
        before = driver.diagnostics()
        state = driver.drive_until(lambda s: s["u_mps"] > 1.0 and s["throttle"] > 0.49
                                   and not s["flags"] & proto.StateFlag.WATCHDOG,
                                   throttle=0.5, gear=proto.Gear.D, what="driving")
        assert state["throttle"] > 0.49 and state["u_mps"] > 1.0
        assert not state["flags"] & proto.StateFlag.WATCHDOG
        after = driver.diagnostics()
        assert after["cmd_received"] > before["cmd_received"]
        reply = driver.request("reset", {"pose": {"x_m": 3.0, "y_m": 0.0, "yaw_rad": 0.0}})
        assert reply["ok"] and reply["tick"] == 0
        state = driver.drive(0.2, brake=0.5)
        assert abs(state["x_m"] - 3.0) < 0.01 and state["tick"] < 1000
        assert driver.request("set_road", {"grade_pct": 5.0})["ok"]
        assert driver.request("get_config")["config"]["road"]["grade_pct"] == 5.0
        assert driver.request("set_road", {"grade_pct": 0.0})["ok"]
    assert server.alive()


def test_nobody_but_the_server_can_publish_the_state(acl_server):
    """A client publishing fake states on the state key reaches no other client."""
    _, endpoint, configs = acl_server
    with driver_and_viewer(endpoint, configs["driver"], configs["viewer"]) as (driver, viewer):
        fake_v = viewer.ep.session.declare_publisher(viewer.ep.keys.state)
        fake_d = driver.ep.session.declare_publisher(driver.ep.keys.state)
        driver.states.drain_newest()
        viewer.states.drain_newest()
        seen_by_driver: list[bytes] = []
        seen_by_viewer: list[bytes] = []

        def real_states(seen: list[bytes], inbox, n: int) -> None:
            """Collect what arrives until ``n`` more real states came."""
            start = len([p for p in seen if p[:1] not in (b"V", b"D")])
            wait_until(lambda: seen.extend(inbox.drain_newest()) or seen,
                       lambda got: len([p for p in got if p[:1] not in (b"V", b"D")])
                       >= start + n, timeout_s=10, what=f"{n} real states")

        for _ in range(50):  # a fake state between two real ones
            fake_v.put(b"V" * proto.STATE_SIZE)
            fake_d.put(b"D" * proto.STATE_SIZE)
            real_states(seen_by_driver, driver.states, 1)
            seen_by_viewer += viewer.states.drain_newest()
        # whatever of the fakes could travel has arrived 300 server periods later
        real_states(seen_by_driver, driver.states, 300)
        real_states(seen_by_viewer, viewer.states, 300)
        # (a session sees its own publications locally; never the other client's)
        assert not [p for p in seen_by_driver if p[:1] == b"V"]
        assert not [p for p in seen_by_viewer if p[:1] == b"D"]
        assert len(seen_by_driver) > 50 and len(seen_by_viewer) > 50  # the real ones flow
        fake_v.undeclare()
        fake_d.undeclare()


# ============================================================================ mutual TLS


def test_mutual_tls_rights_follow_the_certificate_name(pki):
    server_cfg = materialize("server_mtls_acl.json5", pki)
    clients = {
        name: materialize("client_mtls.json5", pki, f"client_mtls_{name}.json5", replace={
            PLACEHOLDER_CLIENT_KEY: f"{pki}/tls/{name}.key",
            PLACEHOLDER_CLIENT_CERT: f"{pki}/tls/{name}.pem"})
        for name in ("driver", "viewer", "rogue")
    }
    no_cert = materialize("client_tls.json5", pki)
    endpoint = loopback_endpoint("tls")
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config", str(server_cfg)]) as srv:
        with pytest.raises(ZenohOpenError):  # no client certificate
            Client(endpoint, zenoh_config=no_cert)
        with pytest.raises(ZenohOpenError):  # CN "driver", but signed by another CA
            Client(endpoint, zenoh_config=clients["rogue"])
        with driver_and_viewer(endpoint, clients["driver"], clients["viewer"]) as (driver,
                                                                                   viewer):
            # the viewer's declarations (its command publisher first) reached the server
            viewer.fresh_state()
            before = driver.diagnostics()
            viewer.drive(0.5, throttle=1.0)
            assert no_reply(viewer, "reset")
            after = driver.diagnostics()
            assert after["cmd_received"] == before["cmd_received"]
            state = driver.drive_until(lambda s: s["u_mps"] > 1.0 and s["throttle"] > 0.49,
                                       throttle=0.5, what="driving")
            assert state["throttle"] > 0.49 and state["u_mps"] > 1.0
            assert driver.request("reset")["ok"]
        assert srv.alive()
    assert srv.returncode == 0


# ============================================================================ through a router


def test_router_access_control_separates_servers_drivers_and_viewers(pki, tmp_path):
    """router_auth_acl.json5 + server_via_router.json5: the lab topology of several hosts.

    The server is a zenoh client of the router (no listening socket of its own) and
    authenticates as "simserver"; drivers and viewers connect to the router only.
    """
    pw = dict(passwords(pki), simserver="srv-" + secrets.token_urlsafe(12))
    users = tmp_path / "router_users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in pw.items()), encoding="ascii")
    router_cfg = materialize("router_auth_acl.json5", pki, "router.json5",
                             replace={"/etc/simserver/users.txt": str(users)})
    server_zenoh = materialize("server_via_router.json5", pki, replace={
        "REPLACE-WITH-THE-SERVER-PASSWORD": pw["simserver"]})
    impostor_zenoh = materialize("server_via_router.json5", pki, "impostor.json5", replace={
        'user: "simserver"': 'user: "driver"', "REPLACE-WITH-THE-SERVER-PASSWORD":
        pw["driver"]})
    driver_cfg = materialize("client_driver.json5", pki, "router_driver.json5", replace={
        "REPLACE-WITH-THE-DRIVER-PASSWORD": pw["driver"]})
    viewer_cfg = materialize("client_viewer.json5", pki, "router_viewer.json5", replace={
        "REPLACE-WITH-THE-VIEWER-PASSWORD": pw["viewer"]})
    router_ep = loopback_endpoint("tls")

    def server_yaml(name: str, zenoh_file: Path, vehicle: str) -> Path:
        # listen: null, so the zenoh file decides (no listener: the server is a client)
        path = tmp_path / name
        path.write_text(f"scene: {CONFIGS / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                        f"vehicle_id: {vehicle}\nzenoh_config: {zenoh_file}\n"
                        "listen: null\nviewer: 'off'\n", encoding="utf-8")
        return path

    router = RoleProcess("router", ["--listen", router_ep, "--zenoh-config", str(router_cfg)])
    server = impostor = None
    try:
        server = ServerProcess(listen=[], config=server_yaml("server.yaml", server_zenoh, "car0"),
                            extra_args=["--connect", router_ep])
        assert not [s for s in process_sockets(server.pid) if s.listening]
        with driver_and_viewer(router_ep, driver_cfg, viewer_cfg) as (driver, viewer):
            state = driver.drive_until(lambda s: s["u_mps"] > 1.0 and s["throttle"] > 0.49,
                                       throttle=0.5, what="driving")
            assert state["throttle"] > 0.49 and state["u_mps"] > 1.0
            assert driver.request("reset")["ok"]
            driver.wait_state(lambda s: s["flags"] & proto.StateFlag.WATCHDOG,
                              what="the watchdog holding the car")  # the driver is silent
            before = driver.diagnostics()
            viewer.drive(0.5, throttle=1.0)
            assert no_reply(viewer, "reset") and no_reply(viewer, "pause")
            after = driver.diagnostics()
            assert after["cmd_received"] == before["cmd_received"]
            assert state_is_finite(viewer.fresh_state())
            # a client cannot impersonate a server: a "car1" served by the driver's
            # credentials never gets a command or a query through
            impostor = ServerProcess(listen=[], vehicle_id="car1", config=server_yaml(
                "impostor.yaml", impostor_zenoh, "car1"), extra_args=["--connect", router_ep])
            with Client(router_ep, vehicle_id="car1", zenoh_config=driver_cfg) as victim:
                assert no_reply(victim, "get_config")
                victim.drive(0.5, throttle=0.5)
                assert victim.received == 0  # and its states reach nobody
        # and without credentials, no session with the router
        with pytest.raises(ZenohOpenError):
            Client(router_ep, zenoh_config=materialize("client_tls.json5", pki))
        assert server.alive()
    finally:
        if impostor is not None:
            impostor.stop()
        if server is not None:
            server.stop()
        router.stop()


# ============================================================================ floods
# Issue 14 items 1 and 2, against the shipped secured configuration.
TLS_ACCEPT_THROTTLE_REASON = (
    "zenoh 1.10's TLS listener accepts one handshake at a time and sleeps 100 ms after "
    "each failed one (TLS_ACCEPT_THROTTLE_TIME, a compile-time constant): 500 plain "
    "connects hold new sessions off for about 50 s whatever the config; docs/security.md "
    "gives the firewall rule that bounds it")
NEW_SESSION_WITHIN_S = 2.0


def _open_timed(endpoint: str, cfg: Path) -> float:
    """Seconds to open an authenticated session and get its first control reply."""
    t0 = time.monotonic()
    with Client(endpoint, zenoh_config=cfg, state_capacity=0) as client:
        assert client.request("get_config", timeout_s=5.0)["ok"]
        return time.monotonic() - t0


def _connect_burst(port: int, n: int) -> None:
    """Plain TCP connect-and-close, no byte sent (the issue's one-liner)."""
    for _ in range(n):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=2.0).close()
        except OSError:
            pass


@pytest.mark.xfail(reason=TLS_ACCEPT_THROTTLE_REASON, strict=False)
def test_a_tcp_connect_burst_does_not_lock_authenticated_sessions_out(acl_server):
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")  # a server of its own: the burst outlasts the test
    port = int(endpoint.rsplit(":", 1)[1])
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        assert _open_timed(endpoint, configs["driver"]) < NEW_SESSION_WITHIN_S
        burst = threading.Thread(target=_connect_burst, args=(port, 500))
        burst.start()
        try:
            during = _open_timed(endpoint, configs["driver"])
        finally:
            burst.join(120)
        after = _open_timed(endpoint, configs["driver"])
        print(f"\n[connect burst] new session during 500 connects: {during:.2f} s, after: "
              f"{after:.2f} s")
        assert during < NEW_SESSION_WITHIN_S and after < NEW_SESSION_WITHIN_S
        assert server.alive()


VIEWER_SESSIONS = 64
"""The read-only user's session flood: as many sessions as the shipped config's old
``max_sessions`` (the issue's viewer filled it with 62 and locked the driver out)."""


def test_a_read_only_users_session_and_query_flood_does_not_lock_the_driver_out(acl_server):
    """The viewer opens 64 sessions and floods ``get_config`` (allowed by its ACL) from
    each; the driver still connects and each of its 20 controls is answered."""
    import zenoh

    from simserver.testing import client_config

    server, endpoint, configs = acl_server
    key = proto.vehicle_keys("simserver", server.vehicle_id).ctl["get_config"]
    sessions = []
    stop = threading.Event()
    sent = [0]

    def flood(session: zenoh.Session) -> None:
        while not stop.is_set():
            session.get(key, handler=lambda _reply: None, timeout=0.5)
            sent[0] += 1
            time.sleep(0.0005)  # the subject: the flood's pace

    threads = []
    try:
        for _ in range(VIEWER_SESSIONS):
            try:
                sessions.append(zenoh.open(client_config(endpoint, configs["viewer"])))
            except zenoh.ZError:
                break  # refused: the server is full, which is what the driver must survive
        threads = [threading.Thread(target=flood, args=(s,), daemon=True) for s in sessions]
        for thread in threads:
            thread.start()
        with Client(endpoint, zenoh_config=configs["driver"], state_capacity=0) as driver:
            answered = 0
            for k in range(20):
                name = "pause" if k % 2 == 0 else "resume"
                answered += driver.request(name, timeout_s=2.0)["ok"]
            assert answered == 20
    finally:
        stop.set()
        for thread in threads:
            thread.join(5)
        for session in sessions:
            session.close()
    print(f"\n[viewer flood] {len(sessions)} viewer sessions, {sent[0]} get_config queries; "
          "the driver connected and all 20 controls were answered")
    assert server.alive()


GET_CONFIG_PER_SESSION_HZ = 20.0
"""The shipped configs' ``downsampling`` of ``get_config`` queries, per session."""


def test_a_get_config_flood_is_rate_limited_per_session_and_spares_the_driver(acl_server):
    """One viewer session asks ``get_config`` about 500 times a second for 2 s: zenoh
    drops all but 20 a second before they reach the server (before the fix each was
    answered, and the issue's 48 568 left 8 of 20 driver controls unanswered); the
    driver's controls, meanwhile, are all answered."""
    import zenoh

    from simserver.testing import client_config

    server, endpoint, configs = acl_server
    key = proto.vehicle_keys("simserver", server.vehicle_id).ctl["get_config"]
    pending = []  # one reply stream per query, finalized when answered or timed out

    viewer = zenoh.open(client_config(endpoint, configs["viewer"]))
    try:
        with Client(endpoint, zenoh_config=configs["driver"], state_capacity=0) as driver:
            sent, t0, answered = 0, time.monotonic(), 0
            while time.monotonic() - t0 < 2.0:
                pending.append(viewer.get(key, timeout=1.0))
                sent += 1
                if sent % 50 == 0:
                    name = "pause" if answered % 2 == 0 else "resume"
                    answered += driver.request(name, timeout_s=2.0)["ok"]
                time.sleep(0.002)  # the subject: the flood's pace
            flood_s = time.monotonic() - t0
            replies = sum(1 for stream in pending for r in stream if r.ok is not None)
    finally:
        viewer.close()
    print(f"\n[get_config flood] {sent} queries in {flood_s:.1f} s, {replies} answered; "
          f"driver: {answered} controls answered")
    assert sent > 3 * GET_CONFIG_PER_SESSION_HZ * flood_s  # a flood, well above the limit
    assert replies <= GET_CONFIG_PER_SESSION_HZ * flood_s + 5
    assert answered == sent // 50


# ============================================================================ hijacking
HIJACKED = json.dumps({"ok": True, "tick": 0, "hijacked": True}).encode()


def _reset_replies(impostor: Client, victim: Client, queries: int) -> list[dict]:
    """The replies the victim's ``ctl/reset`` queries get while the impostor serves that
    key: up to ``queries`` queries, stopping at the first reply of the impostor.

    The victim asks every queryable (``QueryTarget.ALL``): with the default target zenoh
    picks one, on this topology the server's, which is routing, not protection."""
    key = victim.ep.keys.ctl["reset"]

    def answer(query) -> None:
        query.reply(key, HIJACKED)

    queryable = impostor.ep.session.declare_queryable(key, answer, complete=True)
    bodies: list[dict] = []
    try:
        for _ in range(queries):  # the declaration travels meanwhile (or is denied)
            replies = victim.ep.session.get(key, target=zenoh.QueryTarget.ALL, timeout=1.0)
            bodies += [json.loads(r.ok.payload.to_bytes()) for r in replies
                       if r.ok is not None]
            if any(b.get("hijacked") for b in bodies):
                break
    finally:
        queryable.undeclare()
    return bodies


def test_on_the_loopback_default_a_local_process_can_answer_the_controls():
    """docs/security.md 1.1, as stated: without access control any local peer session
    can serve ``ctl/*``, and its answer reaches a client beside the server's."""
    with ServerProcess(listen=[loopback_endpoint()]) as server, \
            Client(server, mode="peer") as impostor, Client(server) as victim:
        victim.wait_controls()
        bodies = _reset_replies(impostor, victim, queries=50)
    assert any(b.get("hijacked") for b in bodies), bodies


def test_the_secured_config_lets_nobody_but_the_server_answer_the_controls(acl_server):
    """With ``server_auth_acl.json5``, a driver's session serving ``ctl/reset`` reaches
    no other client: the other driver gets the server's reply only."""
    _, endpoint, configs = acl_server
    with Client(endpoint, zenoh_config=configs["driver"], mode="peer") as impostor, \
            Client(endpoint, zenoh_config=configs["driver"]) as victim:
        victim.wait_controls()
        bodies = _reset_replies(impostor, victim, queries=10)
    assert len(bodies) >= 10 and not any(b.get("hijacked") for b in bodies), bodies
