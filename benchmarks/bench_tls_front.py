"""Command-to-state latency over TLS: zenoh's listener direct, and behind the TLS front.

Run from the repository root::

    python -m benchmarks.bench_tls_front [--seconds 20] [--rounds 3] [--cmd-hz 200]

Each round starts ``simserver serve`` with ``configs/zenoh/server_tls.json5`` (throwaway
certificates made with ``openssl`` in a temporary folder) twice, once with
``--tls-front off`` (the client's TLS link ends in zenoh's own listener) and once with
``--tls-front auto`` (the link passes the accept-filtering front, a process of its own,
docs/security.md section 5); the two modes alternate, so slow drifts of a shared
machine's load hit both alike. The client (``client_tls.json5``) publishes driver
commands at ``--cmd-hz``, each at a random instant within its slot (as
``benchmarks.bench_server`` does, for the same reason) with ``sender_time_ns``, and times
the first published state (every tick) whose ``last_cmd_seq`` reflects each command,
stamped on arrival in zenoh's receiving thread. A state crosses the front on its way to
the client and a command on its way to the server, so the difference between the modes
is the front's cost on the round trip. Printed: p50/p99 of each mode by round, the
medians over rounds, and the differences.

That difference is tens of microseconds at most, below what the end-to-end figure
resolves on a loaded machine; so the front's hop is also measured alone (``--hop-rounds``,
0 to skip): a ping-pong of ``--hop-bytes`` messages (a state is 300-odd bytes) with an
echo server in a process of its own, straight to it, through a real ``simserver
tls-front`` process, and through a second front whose echo server requires a TCP MD5 key
(as zenoh's listener behind ``serve`` does, issue 34), in alternating blocks of 1000; the
front's added round-trip time (two passes through it, as a command and its state make) is
the difference of the medians, the key's the difference between the two fronts, and
each front's CPU time per round trip is read from ``/proc/PID/stat``.

``--stall-sources N`` (0: skip; issue 34) measures an attack instead: ``--stall-per-source``
whole, real ClientHellos (made with Python's ``ssl``) from each of N loopback addresses
(127.0.0.10 on), each followed by a stall, held for ``--stall-hold-s``; then the seconds a
client trying again and again needs to open a session and get a control answered during
the attack and after it ends (every stalled handshake zenoh got fails then, and costs its
accept loop 100 ms).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import ssl
import subprocess
import sys
import tempfile
import time
from collections import deque
from pathlib import Path

import numpy as np
import zenoh

from simserver.testing import Client, ServerProcess, loopback_endpoint
from simserver.testing.pki import make_pki, materialize
from simserver.wire import protocol as proto

TICK_S = 1e-3
"""The server's default period: a command's send instant is uniform over one of these."""
MODES = ("direct", "front")


def one_run(mode: str, seconds: float, cmd_hz: float, pki: Path) -> dict:
    """One server in ``mode`` (direct: ``--tls-front off``; front: ``auto``), driven for
    ``seconds``: the latencies of the commands, in microseconds."""
    endpoint = loopback_endpoint("tls")
    server_cfg, client_cfg = pki / "server_tls.json5", pki / "client_tls.json5"
    front = "off" if mode == "direct" else "auto"
    latencies_us: list[float] = []
    with ServerProcess(listen=[endpoint], log_level="WARNING", scene=None,
                       extra_args=["--zenoh-config", str(server_cfg), "--tls-front",
                                   front]) as server, \
            Client(endpoint, zenoh_config=client_cfg, state_capacity=0) as client:
        assert client.wait_controls()["ok"]
        arrivals: deque[tuple[int, bytes]] = deque()

        def on_state(sample) -> None:  # zenoh's thread: stamp first, decode later
            arrivals.append((time.monotonic_ns(), sample.payload.to_bytes()))

        states = client.ep.session.declare_subscriber(
            client.ep.keys.state, zenoh.handlers.Callback(on_state, indirect=False))
        sent: dict[int, int] = {}
        seq, period = 0, 1.0 / cmd_hz
        rng = np.random.default_rng(7)
        t_slot = time.monotonic()
        t_end = t_slot + seconds
        t_next = t_slot + rng.uniform(0.0, TICK_S)
        while time.monotonic() < t_end:
            if time.monotonic() >= t_next:
                seq += 1
                t_ns = time.monotonic_ns()
                sent[seq] = t_ns
                client.pub.put(proto.encode_command(throttle=0.2, seq=seq,
                                                    sender_time_ns=t_ns))
                t_slot += period
                t_next = t_slot + rng.uniform(0.0, TICK_S)
            while arrivals:
                t_rx, payload = arrivals.popleft()
                s = int(proto.decode_state(payload)["last_cmd_seq"])
                if s in sent:  # the first state reflecting command s
                    latencies_us.append((t_rx - sent.pop(s)) / 1e3)
            time.sleep(0.0005)
        states.undeclare()
        assert server.alive()
    lat = np.array(latencies_us)
    return {"mode": mode, "commands": seq, "acknowledged": int(lat.size),
            "p50_us": float(np.percentile(lat, 50)), "p99_us": float(np.percentile(lat, 99)),
            "max_us": float(lat.max())}


ECHO = """
import socket, sys, threading
from simserver.adapters.tls_front import set_md5_key
def echo(conn):
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    while data := conn.recv(65536):
        conn.sendall(data)
    conn.close()
srv = socket.socket()
srv.bind(("127.0.0.1", 0))
if len(sys.argv) > 1:  # a throwaway key: the listener requires it, as zenoh's behind serve
    set_md5_key(srv, bytes.fromhex(sys.argv[1]))
srv.listen(16)
print(srv.getsockname()[1], flush=True)
while True:
    threading.Thread(target=echo, args=(srv.accept()[0],), daemon=True).start()
"""
HELLO = bytes([0x16, 0x03, 0x01, 0x00, 0x20, 0x01]) + bytes(31)  # a whole first record
BLOCK = 1000
HOP_MODES = ("direct", "front", "front_md5")


def _cpu_s(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat", encoding="ascii").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _front(echo_port: int, key: bytes | None) -> subprocess.Popen:
    """A ``simserver tls-front`` before the echo server, signing with ``key`` if given
    (handed over in a pipe, as ``serve`` does)."""
    key_args, fds, key_fd = [], (), None
    if key is not None:
        key_fd, write_fd = os.pipe()
        os.write(write_fd, key)
        os.close(write_fd)
        key_args, fds = ["--backend-key-fd", str(key_fd)], (key_fd,)
    try:
        return subprocess.Popen([sys.executable, "-m", "simserver", "tls-front", "--listen",
                                 "127.0.0.1:0", "--backend", f"127.0.0.1:{echo_port}",
                                 *key_args, "--log-level", "WARNING"],
                                stdout=subprocess.PIPE, text=True, pass_fds=fds)
    finally:
        if key_fd is not None:
            os.close(key_fd)


def hop(rounds: int, size: int) -> dict:
    """Round-trip times of ``size``-byte ping-pongs: direct; through a front; through a
    front whose backend requires a TCP MD5 key (as zenoh's behind ``serve``)."""
    key = os.urandom(32)
    procs = []
    try:
        echo = subprocess.Popen([sys.executable, "-c", ECHO], stdout=subprocess.PIPE,
                                text=True)
        echo_md5 = subprocess.Popen([sys.executable, "-c", ECHO, key.hex()],
                                    stdout=subprocess.PIPE, text=True)
        procs += [echo, echo_md5]
        echo_port, echo_md5_port = (int(p.stdout.readline()) for p in (echo, echo_md5))
        fronts = {"front": _front(echo_port, None), "front_md5": _front(echo_md5_port, key)}
        procs += fronts.values()
        ports = {"direct": echo_port}
        for mode, front in fronts.items():
            line = front.stdout.readline()  # tls-front: ready on 127.0.0.1:PORT -> ...
            ports[mode] = int(line.split(" -> ")[0].rsplit(":", 1)[1])
        socks = {}
        for mode in HOP_MODES:
            sock = socket.create_connection(("127.0.0.1", ports[mode]))
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.sendall(HELLO)
            _recv(sock, len(HELLO))
            socks[mode] = sock
        msg = os.urandom(size)
        rtt: dict[str, list[float]] = {m: [] for m in HOP_MODES}
        cpu0 = {m: _cpu_s(f.pid) for m, f in fronts.items()}
        for k in range(len(HOP_MODES) * rounds):
            mode = HOP_MODES[k % len(HOP_MODES)]
            sock, out = socks[mode], rtt[mode]
            for _ in range(BLOCK):
                t0 = time.perf_counter_ns()
                sock.sendall(msg)
                _recv(sock, size)
                out.append((time.perf_counter_ns() - t0) / 1e3)
        cpu_us = {m: 1e6 * (_cpu_s(f.pid) - cpu0[m]) / len(rtt[m]) for m, f in fronts.items()}
        for sock in socks.values():
            sock.close()
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
    r = {m: {"p50_us": float(np.percentile(v, 50)), "p99_us": float(np.percentile(v, 99))}
         for m, v in rtt.items()}
    r["added_p50_us"] = r["front"]["p50_us"] - r["direct"]["p50_us"]
    r["added_p99_us"] = r["front"]["p99_us"] - r["direct"]["p99_us"]
    r["md5_added_p50_us"] = r["front_md5"]["p50_us"] - r["front"]["p50_us"]
    r["front_cpu_us_per_round_trip"] = cpu_us["front"]
    r["front_md5_cpu_us_per_round_trip"] = cpu_us["front_md5"]
    r["round_trips"] = len(rtt["front"])
    print(f"hop ({size}-byte ping-pong, {r['round_trips']} round trips each): direct p50 "
          f"{r['direct']['p50_us']:.1f} us, p99 {r['direct']['p99_us']:.1f} us; through the "
          f"front p50 {r['front']['p50_us']:.1f} us, p99 {r['front']['p99_us']:.1f} us; "
          f"added {r['added_p50_us']:+.1f} us (p50), {r['added_p99_us']:+.1f} us (p99); "
          f"front CPU {cpu_us['front']:.1f} us per round trip; with the backend's MD5 key "
          f"p50 {r['front_md5']['p50_us']:.1f} us, p99 {r['front_md5']['p99_us']:.1f} us "
          f"({r['md5_added_p50_us']:+.1f} us p50 for the key), front CPU "
          f"{cpu_us['front_md5']:.1f} us per round trip", flush=True)
    return r


def _recv(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return bytes(data)


def _client_hello() -> bytes:
    """A real TLS ClientHello: the first flight of Python's TLS client."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
    tls = ctx.wrap_bio(incoming, outgoing, server_hostname="localhost")
    try:
        tls.do_handshake()
    except ssl.SSLWantReadError:
        pass
    return outgoing.read()


def _get_in_s(endpoint: str, cfg: Path, give_up_s: float = 120.0) -> float:
    """Seconds until a session opens and answers ``get_config``, trying again at once."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < give_up_s:
        try:
            with Client(endpoint, zenoh_config=cfg, state_capacity=0) as client:
                if client.request("get_config", timeout_s=5.0)["ok"]:
                    return time.monotonic() - t0
        except Exception:  # noqa: BLE001 (refused, reset, timed out: try again)
            continue
    return float("inf")


def stall(sources: int, per_source: int, hold_s: float, pki: Path) -> dict:
    """Whole ClientHellos then a stall from ``sources`` addresses (docstring above)."""
    endpoint = loopback_endpoint("tls")
    port = int(endpoint.rsplit(":", 1)[1])
    client_cfg = pki / "client_tls.json5"
    hello = _client_hello()
    held = []
    with ServerProcess(listen=[endpoint], log_level="WARNING", scene=None,
                       extra_args=["--zenoh-config", str(pki / "server_tls.json5")]):
        baseline = _get_in_s(endpoint, client_cfg)
        for i in range(sources * per_source):
            try:
                sock = socket.create_connection(
                    ("127.0.0.1", port), timeout=1.0,
                    source_address=(f"127.0.0.{10 + i % sources}", 0))
                sock.sendall(hello)
                held.append(sock)
            except OSError:
                continue
        time.sleep(hold_s)  # the attack holds (a benchmark's pacing, not a test's wait)
        during = _get_in_s(endpoint, client_cfg)
        for sock in held:
            sock.close()
        after = _get_in_s(endpoint, client_cfg)
    r = {"sources": sources, "per_source": per_source, "held": len(held),
         "baseline_s": baseline, "during_s": during, "after_s": after}
    print(f"stall: {len(held)} whole ClientHellos then a stall from {sources} addresses, "
          f"held {hold_s:g} s; a session opened in {baseline:.2f} s before, "
          f"{during:.2f} s during, {after:.2f} s after the attack's end", flush=True)
    return r


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="per run (default 20)")
    parser.add_argument("--rounds", type=int, default=3, help="direct/front pairs (default 3)")
    parser.add_argument("--cmd-hz", type=float, default=200.0)
    parser.add_argument("--hop-rounds", type=int, default=10,
                        help="blocks of 1000 ping-pongs per mode for the hop alone "
                             "(default 10; 0: skip)")
    parser.add_argument("--hop-bytes", type=int, default=320)
    parser.add_argument("--stall-sources", type=int, default=0,
                        help="addresses of the stall attack (default 0: skip it)")
    parser.add_argument("--stall-per-source", type=int, default=6)
    parser.add_argument("--stall-hold-s", type=float, default=3.0)
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args(argv)
    if args.stall_sources > 0:
        with tempfile.TemporaryDirectory() as tmp:
            pki = make_pki(Path(tmp))
            materialize("server_tls.json5", pki)
            materialize("client_tls.json5", pki)
            return stall(args.stall_sources, args.stall_per_source, args.stall_hold_s, pki)
    hop_result = hop(args.hop_rounds, args.hop_bytes) if args.hop_rounds > 0 else None
    runs: dict[str, list[dict]] = {m: [] for m in MODES}
    with tempfile.TemporaryDirectory() as tmp:
        pki = make_pki(Path(tmp))
        materialize("server_tls.json5", pki)
        materialize("client_tls.json5", pki)
        for k in range(args.rounds):
            for mode in MODES if k % 2 == 0 else MODES[::-1]:
                r = one_run(mode, args.seconds, args.cmd_hz, pki)
                runs[mode].append(r)
                print(f"round {k + 1} {mode:6s}: p50 {r['p50_us']:7.1f} us, p99 "
                      f"{r['p99_us']:7.1f} us, max {r['max_us'] / 1e3:6.2f} ms "
                      f"({r['acknowledged']} of {r['commands']} commands)", flush=True)
    summary = {m: {"p50_us": float(np.median([r["p50_us"] for r in rs])),
                   "p99_us": float(np.median([r["p99_us"] for r in rs]))}
               for m, rs in runs.items()}
    d, f = summary["direct"], summary["front"]
    summary["front_minus_direct"] = {"p50_us": f["p50_us"] - d["p50_us"],
                                     "p99_us": f["p99_us"] - d["p99_us"]}
    print(f"median over {args.rounds} rounds: direct p50 {d['p50_us']:.1f} us, p99 "
          f"{d['p99_us']:.1f} us; front p50 {f['p50_us']:.1f} us, p99 {f['p99_us']:.1f} us; "
          f"the front adds {f['p50_us'] - d['p50_us']:+.1f} us (p50), "
          f"{f['p99_us'] - d['p99_us']:+.1f} us (p99)")
    result = {"runs": runs, "summary": summary, "hop": hop_result, "seconds": args.seconds,
              "cmd_hz": args.cmd_hz}
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1), encoding="utf-8")
    return result


if __name__ == "__main__":
    main()
