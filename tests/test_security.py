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
- mutual TLS + access control by certificate name (``server_mtls_acl.json5``);
- floods (issue 14): connect bursts, garbage ClientHellos and held sockets against the
  secured server, whose TLS listener sits behind ``serve``'s accept-filtering TLS front
  (``simserver.adapters.tls_front``; every secured server here runs with it, as shipped).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from simserver.adapters.zenoh_io import (
    DEFAULT_LISTEN,
    ZenohOpenError,
    config_warnings,
    make_zenoh_config,
)
from simserver.server.config import DEFAULT_SERVER_CONFIG, load_server_config
from simserver.testing import (
    CONFIGS,
    Client,
    OutputProcess,
    RoleProcess,
    ServerProcess,
    free_port,
    loopback_endpoint,
    process_argv,
    process_sockets,
    state_is_finite,
    wait_until,
)
from simserver.testing.pki import ZENOH_EXAMPLES, make_pki, materialize
from simserver.wire import protocol as proto

pytestmark = pytest.mark.timeout(300)

PLACEHOLDER_CLIENT_KEY = "/etc/simserver/tls/client.key"
PLACEHOLDER_CLIENT_CERT = "/etc/simserver/tls/client.pem"


# ============================================================================ PKI


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


def front_pids(server: ServerProcess) -> list[int]:
    """The server's TLS front processes (``simserver tls-front``)."""
    return [pid for pid in server.children() if "tls-front" in process_argv(pid)]


def front_counters(server: ServerProcess) -> dict[str, int]:
    """The front's last logged counters (it logs them at exit: call after stop)."""
    for line in reversed(server.output):
        if "tls front:" in line and "counters {" in line:
            return json.loads(line.split("counters ", 1)[1])
    raise AssertionError("no tls front counters in the server's output:\n"
                         + server.text()[-2000:])


def no_reply(probe: Client, name: str, args: dict | None = None) -> bool:
    """True if a control request got no reply from any server (denied, or nobody serving).

    Asked directly rather than with ``Client.request``: zenoh itself may end a query that
    nobody answered with an error reply of its own (not a server's JSON body), which
    ``request`` reports as a malformed reply; that is no reply too. Any reply with a JSON
    body (a server's answer, ok or error) is a reply.
    """
    replies = probe.ep.session.get(probe.ep.keys.control(name),
                                   payload=proto.encode_control(name, args), timeout=1.0)
    for reply in replies:
        body = (reply.ok if reply.ok is not None else reply.err).payload.to_bytes()
        try:
            json.loads(body)
        except ValueError:
            continue  # zenoh's own error (a timeout), not a server's reply
        return False
    return True


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
        # the public port is the accept-filtering front's (docs/security.md section 5): a
        # process of its own, on the socket the server bound; zenoh listens on loopback
        fronts = front_pids(server)
        assert len(fronts) == 1
        socks = process_sockets(server.pid)
        listeners = sorted((s.local_ip, s.local_port) for s in socks if s.listening)
        assert [ip for ip, _ in listeners] == ["127.0.0.1", "127.0.0.1"]
        assert port in [p for _, p in listeners]  # the public socket, held for restarts
        assert [(s.local_ip, s.local_port) for s in process_sockets(fronts[0])
                if s.listening] == [("127.0.0.1", port)]
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


def test_tls_front_off_lets_zenoh_listen_on_the_public_port_itself(pki):
    """``--tls-front off``: no front process; zenoh's TLS listener is the public port (the
    configuration the connect burst locked out, kept for access-control subjects by
    interface, docs/security.md 5.1)."""
    server_cfg = materialize("server_tls.json5", pki)
    client_cfg = materialize("client_tls.json5", pki)
    port = free_port()
    tls_ep = f"tls/127.0.0.1:{port}"
    with ServerProcess(listen=[tls_ep], extra_args=["--zenoh-config", str(server_cfg),
                                                    "--tls-front", "off"]) as server:
        assert front_pids(server) == []
        assert [(s.local_ip, s.local_port) for s in process_sockets(server.pid)
                if s.listening] == [("127.0.0.1", port)]
        with Client(tls_ep, zenoh_config=client_cfg) as client:
            assert client.wait_controls()["ok"]
    assert server.returncode == 0


def test_view_with_the_tls_client_config_uses_its_endpoints_and_draws(pki, tmp_path):
    """``simserver view --zenoh-config client_tls.json5`` (issue 35): the view emptied the
    file's connect endpoints, and the client-mode session then failed to open with a
    traceback. The file's own endpoint (its placeholder server name replaced by the
    test server's, ``localhost`` in the certificate) is used; no ``--connect``."""
    from simserver.adapters.rerun_scene import CAR

    port = free_port()
    server_cfg = materialize("server_tls.json5", pki)
    client_cfg = materialize("client_tls.json5", pki, out_name="view_tls.json5",
                             replace={"tls/simserver.lab.example:7447":
                                      f"tls/localhost:{port}"})
    rrd = tmp_path / "tls.rrd"
    env = dict(os.environ, PYTHONUNBUFFERED="1",
               XDG_CONFIG_HOME=str(tmp_path / "xdg_config"),
               XDG_DATA_HOME=str(tmp_path / "xdg_data"))
    with ServerProcess(listen=[f"tls/127.0.0.1:{port}"],
                       extra_args=["--zenoh-config", str(server_cfg)]):
        viewer = OutputProcess(
            [sys.executable, "-m", "simserver", "view", "--sink", f"save:{rrd}",
             "--zenoh-config", str(client_cfg), "--normal-priority", "--wait", "120"],
            env=env)
        try:
            wait_until(lambda: rrd.exists() and rrd.stat().st_size > 100_000
                       or not viewer.alive(), timeout_s=120.0,
                       what="the TLS viewer to draw", interval_s=0.05)
            assert viewer.alive(), viewer.text()
            assert viewer.stop(timeout_s=60.0) == 0, viewer.text()
        finally:
            viewer.kill()
    assert "Traceback" not in viewer.text(), viewer.text()
    from rerun.chunk import RrdReader

    assert any(c.entity_path.startswith("/" + CAR) and not c.is_static
               for c in RrdReader(rrd).stream()), viewer.text()


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
        # through the TLS front, which does not end TLS: client certificates reach zenoh
        assert len(front_pids(srv)) == 1
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
        assert len(front_pids(server)) == 1  # every test of it passes the TLS front
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
        # the driver's own commands apply (read while it commands: once it stops, the
        # watchdog zeroes the throttle after 200 ms, which a loaded machine can exceed
        # before the state is read)
        state = driver.drive_until(lambda s: s["throttle"] > 0.29, throttle=0.3,
                                   what="the driver's throttle applied")
        assert state["gear"] == proto.Gear.D  # not reversed
        assert not state["flags"] & proto.StateFlag.PAUSED
        after = driver.diagnostics()
        sent_by_driver = driver.seq
        assert after["cmd_received"] - before["cmd_received"] <= sent_by_driver
        assert after["cmd_rejected"] == before["cmd_rejected"]
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


# ============================================================================ floods
# Issue 14 items 1 and 2, against the shipped secured configuration.
NEW_SESSION_WITHIN_S = 2.0
BURST_CONNECTS = 500
FLOOD_THREADS = 16
FLOOD_CONNECTS = 160
"""Connections the flood from another host has made before the sessions open."""


def _open_timed(endpoint: str, cfg: Path) -> float:
    """Seconds to open an authenticated session and get its first control reply."""
    t0 = time.monotonic()
    with Client(endpoint, zenoh_config=cfg, state_capacity=0) as client:
        assert client.request("get_config", timeout_s=5.0)["ok"]
        return time.monotonic() - t0


def _open_baseline(endpoint: str, cfg: Path) -> float:
    """``_open_timed`` with no attack under way, which must be within the bound: if it is
    not, the machine is too loaded for the bound to say anything about an attack."""
    baseline = _open_timed(endpoint, cfg)
    assert baseline < NEW_SESSION_WITHIN_S, (
        f"with no attack a session took {baseline:.2f} s to open (load average "
        f"{os.getloadavg()[0]:.1f}): the machine is too loaded to judge the "
        f"{NEW_SESSION_WITHIN_S:g} s bound")
    return baseline


class Burst:
    """Hostile connections to ``port`` from ``source`` in a thread, ``one(sock)`` each
    (after the connect), until stopped and at least ``at_least`` were made."""

    def __init__(self, port: int, one, at_least: int, source: str = "127.0.0.1") -> None:
        self.port, self.one, self.at_least, self.source = port, one, at_least, source
        self.count = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.is_set() or self.count < self.at_least:
            try:
                sock = socket.create_connection(("127.0.0.1", self.port), timeout=2.0,
                                                source_address=(self.source, 0))
            except OSError:
                self.count += 1  # refused or reset at once: still one connect
                continue
            try:
                self.one(sock)
            except OSError:
                pass
            finally:
                sock.close()
            self.count += 1

    def __enter__(self) -> Burst:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(120)


def _connect_and_close(sock: socket.socket) -> None:
    """The issue's one-liner: no byte sent."""


def test_a_tcp_connect_burst_does_not_lock_authenticated_sessions_out(acl_server):
    """Issue 14 item 1's acceptance: during and after 500 plain connect-and-close, a new
    authenticated session opens within 2 s (before the front: about 50 s after them).

    The burst and the driver share 127.0.0.1: the connections that close never take a
    pending slot for long (the front reads their end at accept)."""
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")  # a server of its own, to read its front's counters
    port = int(endpoint.rsplit(":", 1)[1])
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        _open_baseline(endpoint, configs["driver"])
        with Burst(port, _connect_and_close, BURST_CONNECTS) as burst:
            wait_until(lambda: burst.count, lambda n: n >= 20, timeout_s=10,
                       what="the burst under way")
            during = _open_timed(endpoint, configs["driver"])
            count_at_open = burst.count
            assert burst.thread.is_alive()  # it was opened during the burst
        after = _open_timed(endpoint, configs["driver"])
        print(f"\n[connect burst] new session during the burst (at connect {count_at_open}): "
              f"{during:.2f} s; after {burst.count} connects: {after:.2f} s")
        assert during < NEW_SESSION_WITHIN_S and after < NEW_SESSION_WITHIN_S
        assert burst.count >= BURST_CONNECTS
        assert server.alive()
    counters = front_counters(server)
    # every burst connection was kept from zenoh; the three sessions were forwarded
    assert counters["dropped_closed"] + counters["refused_source_cap"] >= BURST_CONNECTS
    assert counters["forwarded"] == 3 and counters["handshakes_failed"] == 0


def _hello_then_garbage(sock: socket.socket) -> None:
    """The start of a ClientHello (passes the front's check), then garbage: zenoh's TLS
    handshake fails, which costs its accept loop a 100 ms sleep."""
    sock.sendall(bytes([0x16, 0x03, 0x01, 0x00, 0x30, 0x01]) + secrets.token_bytes(48))
    sock.recv(64)


def _held_silent(sock: socket.socket) -> None:
    """Connect and hold, silent, until the front drops it (the issue's 150 held sockets)."""
    sock.settimeout(5.0)
    sock.recv(1)


@pytest.mark.parametrize("attack", ["hello_then_garbage", "held_silent"])
def test_floods_from_another_host_do_not_lock_authenticated_sessions_out(acl_server, attack):
    """ClientHellos followed by garbage (they reach zenoh: the front bars the source for a
    doubling backoff after each failed handshake), and silent held connections (the
    per-source pending cap refuses more than 8, the hello timeout drops them after 2 s),
    from 127.0.0.2 in 16 threads: a new authenticated session from 127.0.0.1 opens within
    2 s during the flood and after it."""
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")
    port = int(endpoint.rsplit(":", 1)[1])
    one = {"hello_then_garbage": _hello_then_garbage, "held_silent": _held_silent}[attack]
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        _open_baseline(endpoint, configs["driver"])
        # no minimum per thread: a thread whose sockets the front holds makes one
        # connection per 2 s hello timeout, and waiting for each to make 10 took 20 s
        # more after the flood's purpose was served; the flood's size is counted before
        # the sessions open instead
        bursts = [Burst(port, one, 0, source="127.0.0.2") for _ in range(FLOOD_THREADS)]
        for burst in bursts:
            burst.__enter__()
        try:
            # the flood is under way: the front's backoff or caps are refusing it
            wait_until(lambda: sum(b.count for b in bursts),
                       lambda n: n >= FLOOD_CONNECTS, timeout_s=30, what="the flood under way")
            during = [_open_timed(endpoint, configs["driver"]) for _ in range(3)]
            assert all(b.thread.is_alive() for b in bursts)
        finally:
            for burst in bursts:  # all stopped first: joined one by one, the others
                burst.stop.set()  # spun on and a join took 1 s of the GIL each
            for burst in bursts:
                burst.__exit__()
        after = _open_timed(endpoint, configs["driver"])
        made = sum(b.count for b in bursts)
        print(f"\n[{attack}] {made} connections from 127.0.0.2; new sessions during: "
              f"{', '.join(f'{d:.2f}' for d in during)} s, after: {after:.2f} s")
        assert max(during) < NEW_SESSION_WITHIN_S and after < NEW_SESSION_WITHIN_S
    counters = front_counters(server)
    if attack == "hello_then_garbage":
        assert counters["refused_backoff"] > 0 and counters["handshakes_failed"] >= 1
        # zenoh saw only a few of them: each failure bars the source for 1, 2, 4 ... s
        assert counters["handshakes_failed"] <= 5 + made // 100, counters
    else:
        # only the driver's 5 sessions (baseline, 3 during, 1 after) reached zenoh
        assert counters["refused_source_cap"] > 0 and counters["forwarded"] == 5


# ---------------------------------------------------------------------------- issue 34

GET_IN_GIVE_UP_S = 90.0
"""How long ``_get_in`` keeps trying (the issue measured lock-outs of 25-59 s)."""


def _get_in(endpoint: str, cfg: Path) -> float:
    """Seconds until an authenticated session opens and answers, trying again at once
    after each refused or failed try (as a driver would); ``inf`` after
    ``GET_IN_GIVE_UP_S``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < GET_IN_GIVE_UP_S:
        try:
            _open_timed(endpoint, cfg)
            return time.monotonic() - t0
        except (ZenohOpenError, AssertionError, TimeoutError):
            continue
    return float("inf")


def _backend_port(server: ServerProcess, public_port: int) -> int:
    """zenoh's own TLS listener behind the front: the server's other listening socket."""
    (port,) = [s.local_port for s in process_sockets(server.pid)
               if s.listening and s.local_ip == "127.0.0.1" and s.local_port != public_port]
    return port


def test_zenohs_listener_behind_the_front_is_reachable_by_the_front_alone(acl_server):
    """Issue 34, the backend burst: 500 plain connect-and-close in about 0.1 s on zenoh's
    loopback port behind the front kept the authenticated driver out for 59.2 s. Now
    zenoh's listener requires the front's TCP MD5 key: the kernel drops the burst's SYNs,
    a plain connect times out, and the driver gets in within 2 s."""
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        _open_baseline(endpoint, configs["driver"])
        backend = _backend_port(server, int(endpoint.rsplit(":", 1)[1]))
        t0 = time.monotonic()
        for _ in range(BURST_CONNECTS):
            with socket.socket() as sock:
                sock.setblocking(False)
                sock.connect_ex(("127.0.0.1", backend))
        burst_s = time.monotonic() - t0
        got_in = _get_in(endpoint, configs["driver"])
        with socket.socket() as probe:
            probe.settimeout(1.0)
            try:
                probe.connect(("127.0.0.1", backend))
                reachable = True
            except TimeoutError:
                reachable = False
        print(f"\n[backend burst] {BURST_CONNECTS} connect-and-close on zenoh's port "
              f"{backend} in {burst_s:.2f} s; the driver got in {got_in:.2f} s after it; "
              f"a plain connect to that port {'succeeds' if reachable else 'times out'}")
        assert got_in < NEW_SESSION_WITHIN_S
        assert not reachable
        assert server.alive()
    assert "cannot be locked to the front" not in server.text()


SLOW_SOURCES = [f"127.0.0.{i}" for i in range(10, 60)]
"""The issue's 50 other loopback source addresses."""
SLOW_HELLOS = 300
SLOW_HELLO_SENT = 11
"""Bytes sent of a 249-byte ClientHello record (5-byte header, 244-byte body)."""
SLOW_HELLO = bytes([0x16, 0x03, 0x01, 0x00, 0xF4, 0x01, 0x00, 0x00, 0xF0, 0x03, 0x03]) \
    + bytes(238)


class SlowHellos:
    """The issue's slowloris: ``count`` connections spread over ``sources``, each sending
    the first 11 bytes of a 249-byte ClientHello and then holding; a connection the front
    closes or refuses is opened again (after 20 ms), so the attack lasts until stopped.
    One thread, non-blocking sockets."""

    def __init__(self, port: int, sources: list[str], count: int = SLOW_HELLOS) -> None:
        self.port, self.sources, self.count = port, sources, count
        self.opened = 0
        self.holding = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _open(self, source: str) -> socket.socket | None:
        sock = socket.socket()
        try:
            sock.bind((source, 0))
            sock.settimeout(1.0)
            sock.connect(("127.0.0.1", self.port))
            sock.sendall(SLOW_HELLO[:SLOW_HELLO_SENT])
            sock.setblocking(False)
        except OSError:
            sock.close()
            return None
        self.opened += 1
        return sock

    def _run(self) -> None:
        import selectors

        sel = selectors.DefaultSelector()
        slots: list[tuple[str, socket.socket | None, float]] = [
            (self.sources[i % len(self.sources)], None, 0.0) for i in range(self.count)]
        try:
            while not self.stop.is_set():
                now = time.monotonic()
                for i, (source, sock, retry_at) in enumerate(slots):
                    if sock is None and now >= retry_at:
                        sock = self._open(source)
                        if sock is not None:
                            sel.register(sock, selectors.EVENT_READ, i)
                        slots[i] = (source, sock, now + 0.02)
                self.holding = sum(1 for _, sock, _ in slots if sock is not None)
                for key, _ in sel.select(timeout=0.02):
                    sock = key.fileobj
                    try:
                        data = sock.recv(64)
                    except BlockingIOError:
                        continue
                    except OSError:
                        data = b""
                    if not data:  # closed or reset by the front: open another
                        sel.unregister(sock)
                        sock.close()
                        source = slots[key.data][0]
                        slots[key.data] = (source, None, time.monotonic() + 0.02)
        finally:
            for _, sock, _ in slots:
                if sock is not None:
                    sock.close()
            sel.close()

    def __enter__(self) -> SlowHellos:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(30)


def test_partial_client_hellos_from_other_sources_never_reach_zenoh_nor_lock_out(acl_server):
    """Issue 34, the slowloris: 300 partial ClientHellos (11 of 249 bytes) held from 50
    other loopback addresses refused the driver on every try during the attack and let
    it in only 25.8 s after it ended (the front's total cap was full, and it forwarded
    265-279 of them to zenoh after its hello timeout, each failing there with a 100 ms
    sleep). Now the front forwards only whole ClientHellos, drops the rest at the hello
    timeout, and at its total cap closes a hello of the source holding the most for a
    source holding fewer: the driver gets in within 2 s during the attack and after it."""
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")
    port = int(endpoint.rsplit(":", 1)[1])
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        _open_baseline(endpoint, configs["driver"])
        with SlowHellos(port, SLOW_SOURCES) as attack:
            wait_until(lambda: attack.holding, lambda n: n >= 250, timeout_s=30,
                       what="the partial hellos held")
            # past the hello timeout (2 s), so the front had its chance to forward them
            t_held = time.monotonic()
            wait_until(time.monotonic, lambda t: t > t_held + 3.0, timeout_s=10,
                       what="3 s of attack")
            during = _get_in(endpoint, configs["driver"])
            held = attack.holding
            assert attack.thread.is_alive()
        after = _get_in(endpoint, configs["driver"])
        print(f"\n[slowloris, 50 other sources] {attack.opened} partial hellos opened, "
              f"{held} held when the driver tried; the driver got in {during:.2f} s into "
              f"its tries during the attack, {after:.2f} s after its end")
        assert during < NEW_SESSION_WITHIN_S and after < NEW_SESSION_WITHIN_S
        assert server.alive()
    counters = front_counters(server)
    print(f"[slowloris, 50 other sources] front counters {counters}")
    # the partial hellos never reached zenoh: only the driver's sessions did (baseline,
    # during, after: 3, plus any try of the driver's that failed)
    assert counters["dropped_partial_hello"] > 0 and counters["handshakes_failed"] == 0
    assert counters["forwarded"] == 3


def test_partial_client_hellos_from_the_drivers_own_source_do_not_bar_it(acl_server):
    """Issue 34: the same slowloris from the driver's own address (127.0.0.1) let the
    driver in only 32.1 s after it ended: each partial hello forwarded to zenoh failed
    there and barred the address for a doubling backoff. Now they never reach zenoh, so
    nothing bars the driver: it gets in within 2 s of the attack's end."""
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")
    port = int(endpoint.rsplit(":", 1)[1])
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        _open_baseline(endpoint, configs["driver"])
        with SlowHellos(port, ["127.0.0.1"]) as attack:
            wait_until(lambda: attack.opened, lambda n: n >= 30, timeout_s=30,
                       what="the partial hellos under way")
            # 12 s: past the front's 10 s handshake timeout of a forwarded hello
            t_under_way = time.monotonic()
            wait_until(time.monotonic, lambda t: t > t_under_way + 12.0, timeout_s=30,
                       what="12 s of attack")
            assert attack.thread.is_alive()
        after = _get_in(endpoint, configs["driver"])
        print(f"\n[slowloris, the driver's source] {attack.opened} partial hellos opened; "
              f"the driver got in {after:.2f} s after the attack's end")
        assert after < NEW_SESSION_WITHIN_S
        assert server.alive()
    counters = front_counters(server)
    assert counters["refused_backoff"] == 0 and counters["handshakes_failed"] == 0


def test_the_front_is_restarted_if_it_dies_and_the_port_stays_open(acl_server):
    """``serve`` supervises its TLS front: killed, it is restarted (logged) on the same
    public socket, and a new authenticated session opens through the new one."""
    _, _, configs = acl_server
    endpoint = loopback_endpoint("tls")
    with ServerProcess(listen=[endpoint], extra_args=["--zenoh-config",
                                                      str(configs["server"])]) as server:
        (first,) = front_pids(server)
        os.kill(first, signal.SIGKILL)
        server.wait_for_line("restarting it", timeout_s=10)
        wait_until(lambda: front_pids(server), lambda p: len(p) == 1 and p[0] != first,
                   timeout_s=10, what="a new front")
        assert _open_timed(endpoint, configs["driver"]) < 10.0  # includes the restart
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


def _reset_replies(impostor: Client, victim: Client, seconds: float) -> list[dict]:
    """The replies the victim's ``ctl/reset`` queries get while the impostor serves that
    key: a query every 20 ms for ``seconds`` (the declaration travels meanwhile, or is
    denied; a count of queries was not a time: on a busy machine 50 quick queries ended
    before the declaration arrived), stopping at the first reply of the impostor.

    The victim asks every queryable (``QueryTarget.ALL``): with the default target zenoh
    picks one, on this topology the server's, which is routing, not protection."""
    key = victim.ep.keys.ctl["reset"]

    def answer(query) -> None:
        query.reply(key, HIJACKED)

    queryable = impostor.ep.session.declare_queryable(key, answer, complete=True)
    bodies: list[dict] = []

    def ask() -> bool:
        replies = victim.ep.session.get(key, target=zenoh.QueryTarget.ALL, timeout=1.0)
        bodies.extend(json.loads(r.ok.payload.to_bytes()) for r in replies
                      if r.ok is not None)
        return any(b.get("hijacked") for b in bodies)

    try:
        with contextlib.suppress(TimeoutError):  # no hijack within the time: the answer
            wait_until(ask, timeout_s=seconds, interval_s=0.02, what="the impostor's reply")
    finally:
        queryable.undeclare()
    return bodies


def test_the_secured_config_lets_nobody_but_the_server_answer_the_controls(acl_server):
    """With ``server_auth_acl.json5``, a driver's session serving ``ctl/reset`` reaches
    no other client: the other driver gets the server's reply only."""
    _, endpoint, configs = acl_server
    with Client(endpoint, zenoh_config=configs["driver"], mode="peer") as impostor, \
            Client(endpoint, zenoh_config=configs["driver"]) as victim:
        victim.wait_controls()
        bodies = _reset_replies(impostor, victim, seconds=2.0)
    assert len(bodies) >= 10 and not any(b.get("hijacked") for b in bodies), bodies


# (after the last test of the module's ACL server, which ends with it: tests/conftest.py)
def test_on_the_loopback_default_a_local_process_can_answer_the_controls():
    """docs/security.md 1.1, as stated: without access control any local peer session
    can serve ``ctl/*``, and its answer reaches a client beside the server's."""
    with ServerProcess(listen=[loopback_endpoint()]) as server, \
            Client(server, mode="peer") as impostor, Client(server) as victim:
        victim.wait_controls()
        bodies = _reset_replies(impostor, victim, seconds=10.0)
    assert any(b.get("hijacked") for b in bodies), bodies
