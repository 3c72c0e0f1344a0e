"""Logs that fail safe (issue 34 item 3): a command log that cannot be written is cut with
one warning while the live loop goes on; log paths are never followed through a symbolic
link, never anything but a regular file, and never block the start-up.

The full-disk cases run a real server on a real small file system (a tmpfs mounted for the
test; skipped where mounting is not permitted) and under a real file size limit
(``RLIMIT_FSIZE``), driven over zenoh on loopback; the written log is replayed with
``simserver replay`` and compared with the states the server published.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.config import ConfigError
from simserver.core import layout as L
from simserver.testing import REPO, Client, ServerProcess, free_port, serve_args, wait_until
from simserver.wire import protocol as proto

CUT_WARNING = "the command log cannot be written"


@pytest.fixture
def small_disk(tmp_path):
    """A 160 KiB tmpfs (a disk that fills up within seconds of driving)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=160k", "tmpfs", str(disk)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {done.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def _drive_until_cut(server: ServerProcess, probe: Client, log: Path) -> tuple[int, int]:
    """Drive with inputs changing at every command (an inputs line nearly every tick) until
    the log is cut, then 1 s more; (tick at the cut, last tick seen)."""
    k = 0

    def steer_and_go() -> None:
        nonlocal k
        k += 1
        probe.send(steer=0.2 * math.sin(k / 50), throttle=0.3, gear=proto.Gear.D)

    def cut_seen() -> bool:
        steer_and_go()
        probe.drain_states()
        return CUT_WARNING in server.text() or not server.alive()

    wait_until(cut_seen, timeout_s=60.0, interval_s=0.002,
               what=f"the command log {log} to fill its disk")
    assert server.alive(), "the server died when its log could not be written:\n" + \
        server.crash_report()
    tick_at_cut = int(probe.last["tick"])
    # the live loop goes on: a second of driving after the cut
    probe._first_state(lambda s: int(s["tick"]) >= tick_at_cut + 1000, 20.0,
                       "1 s of states after the cut", each=steer_and_go, interval_s=0.002)
    return tick_at_cut, int(probe.last["tick"])


def _check_cut_log_replays(server: ServerProcess, probe: Client, log: Path) -> None:
    """The server stops cleanly with its statistics; the cut log is whole lines ending with
    a cut end line, replays with ``simserver replay``, and the replay is the live run."""
    from simserver.server.command_log import read_command_log, replay_command_log

    code = server.stop()
    out = server.text()
    assert code == 0, out[-3000:]
    final = server.final_stats()
    assert final is not None and final["command_log_cut"], out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    assert out.count(CUT_WARNING) == 1, out[-3000:]
    entries = read_command_log(log)
    end = entries[-1]
    assert set(end) == {"end", "cut"}, end
    assert log.read_bytes().endswith(b"\n")
    cut_step = end["end"]
    assert cut_step > 1000
    done = subprocess.run([sys.executable, "-m", "simserver", "replay", str(log)],
                          capture_output=True, text=True, cwd=REPO, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"replayed {cut_step} steps (the log was cut there" in done.stdout, done.stdout
    rep = replay_command_log(log)
    assert rep.steps == cut_step and rep.cut == end["cut"]
    compared = 0
    for state in probe.history:
        tick = int(state["tick"])
        if 1 <= tick <= cut_step:
            x = rep.states[tick - 1]
            assert state["u_mps"] == np.float32(x[L.U_MPS]), tick
            assert np.array_equal(state["omega_radps"],
                                  x[L.OMEGA0:L.OMEGA0 + 4].astype(np.float32)), tick
            compared += 1
    assert compared > 500, compared
    print(f"\n[cut log] {end['cut']}: cut at step {cut_step}; {compared} published states "
          f"replayed identically; stopped with {final}")


def test_a_full_disk_cuts_the_command_log_and_the_loop_goes_on(small_disk):
    """Before: ``CommandLog.flush`` raised ENOSPC in the tick thread, the loop ended,
    ``close()`` raised again and the server exited 1 with two tracebacks and no
    statistics. Now: one warning, the live loop goes on, statistics printed, and the
    written part replays the live run up to the cut, which its end line marks."""
    log = small_disk / "run.jsonl"
    server = ServerProcess(command_log=log)
    try:
        with Client(server, keep_history=True) as probe:
            tick_at_cut, last_tick = _drive_until_cut(server, probe, log)
            assert last_tick >= tick_at_cut + 1000
            assert "No space left on device" in server.text()
            _check_cut_log_replays(server, probe, log)
    finally:
        server.stop()


def test_a_file_size_limit_cuts_the_command_log_and_the_loop_goes_on(tmp_path):
    """The same under a file size limit (``RLIMIT_FSIZE``: EFBIG), which needs no mount:
    before, the write failed in the tick and the server exited 1."""
    log = tmp_path / "run.jsonl"
    limit = 192 * 1024
    listen = [f"tcp/127.0.0.1:{free_port()}"]
    argv = ["prlimit", f"--fsize={limit}", *serve_args(listen=listen, command_log=log)]
    server = ServerProcess(argv=argv, listen=listen)
    try:
        with Client(server, keep_history=True) as probe:
            _drive_until_cut(server, probe, log)
            assert "file size limit" in server.text()
            _check_cut_log_replays(server, probe, log)
            assert log.stat().st_size <= limit
    finally:
        server.stop()


def _serve_refused(log: Path) -> tuple[int | None, str, float]:
    """``simserver serve --command-log LOG`` expected to refuse at once: (exit code, or
    None if it still ran after 60 s and was killed; output; seconds)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(serve_args(listen=["tcp/127.0.0.1:0"], command_log=log),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=REPO)
    try:
        out, _ = proc.communicate(timeout=60)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        code = None
    return code, out, time.monotonic() - t0


def test_a_symbolic_link_at_the_log_path_is_refused_and_its_target_untouched(tmp_path):
    """Before: the server (root here) followed a link planted at the log path and
    truncated and overwrote the link's target. Now it refuses to start, naming the file."""
    target = tmp_path / "precious.txt"
    target.write_text("not yours\n")
    link = tmp_path / "run.jsonl"
    link.symlink_to(target)
    code, out, _ = _serve_refused(link)
    assert target.read_text() == "not yours\n", "the server wrote through the link"
    assert code == 2, out
    assert "Traceback" not in out
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and str(link) in errors[0] and "symbolic link" in errors[0], out


def test_a_fifo_at_the_log_path_is_refused_at_once(tmp_path):
    """Before: a FIFO with no reader at the log path kept the server from becoming ready
    (blocked in ``open``, ignoring SIGINT). Now it is refused at once with one line."""
    fifo = tmp_path / "run.jsonl"
    os.mkfifo(fifo)
    code, out, took_s = _serve_refused(fifo)
    assert code is not None, "the server blocked on a FIFO at its log path:\n" + out
    assert code == 2, out
    assert "Traceback" not in out
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and str(fifo) in errors[0] and "FIFO" in errors[0], out
    print(f"\n[fifo] refused in {took_s:.1f} s (process start and imports included)")


def test_the_tick_hands_lines_over_and_another_thread_writes_them(tmp_path):
    """Before: the tick thread wrote the command log itself (a ``flush`` every 100 ms and
    at every control line), so a slow disk stalled the tick and a failing one raised in
    it. Now ``log_inputs`` and ``write`` only queue a line: with no further call from
    the tick, the lines reach the file within ``COMMAND_LOG_FLUSH_S``, written by the
    log's own thread, and the tick thread never writes (checked by its thread id)."""
    from simserver.server.command_log import COMMAND_LOG_FLUSH_S, CommandLog, read_command_log

    scene = REPO / "configs" / "scenes" / "flat_paper_sedan.yaml"
    path = tmp_path / "cmd.jsonl"
    writers: set[int] = set()
    real_write, real_pwrite = os.write, os.pwrite

    def spy_write(fd: int, data: bytes) -> int:
        writers.add(threading.get_ident())
        return real_write(fd, data)

    def spy_pwrite(fd: int, data: bytes, offset: int) -> int:
        writers.add(threading.get_ident())
        return real_pwrite(fd, data, offset)

    log = CommandLog(path, {"scene": str(scene), "dt_s": 0.001, "step": 0})
    os.write, os.pwrite = spy_write, spy_pwrite  # see who writes; the writes are real
    try:
        log.log_inputs(0, np.array([0.1, 0.2, 0.0, 0.0, 3.0]))
        t0 = time.monotonic()
        wait_until(lambda: path.read_bytes().count(b"\n") >= 2, timeout_s=5.0,
                   what="the inputs line written without another call", interval_s=0.005)
        took_s = time.monotonic() - t0
        log.write({"step": 5, "set_road": {"grade_pct": 1.0, "cross_slope_pct": 0.0,
                                           "friction_scale": 1.0}})
        wait_until(lambda: b"set_road" in path.read_bytes(), timeout_s=5.0,
                   what="the control line written at once", interval_s=0.005)
        log.close(7, np.zeros(L.N_STATE))
    finally:
        os.write, os.pwrite = real_write, real_pwrite
    assert threading.get_ident() not in writers and writers
    assert took_s <= COMMAND_LOG_FLUSH_S + 0.5  # scheduling slack on a loaded machine
    kinds = [next(k for k in e if k != "step") for e in read_command_log(path)[1:]]
    assert kinds == ["inputs", "set_road", "end"]


def _open_in_thread(path: Path) -> BaseException | int | None:
    """``open_log_file(path)`` in a thread: its result, an exception, or None if it is
    still blocked after 5 s."""
    from simserver.server.logfile import open_log_file

    got: list[BaseException | int] = []

    def run() -> None:
        try:
            got.append(open_log_file(path, "command log"))
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            got.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(5.0)
    return got[0] if got else None


def test_open_log_file_refuses_links_fifos_devices_and_hard_links(tmp_path):
    """At the open itself (a path swapped after the start-up check): ``O_NOFOLLOW``,
    ``O_NONBLOCK`` and ``fstat`` before anything is truncated."""
    target = tmp_path / "target.txt"
    target.write_text("keep\n")
    link = tmp_path / "link.jsonl"
    link.symlink_to(target)
    dangling = tmp_path / "dangling.jsonl"
    dangling.symlink_to(tmp_path / "would_be_created.txt")
    fifo = tmp_path / "fifo.jsonl"
    os.mkfifo(fifo)
    hard = tmp_path / "hard.jsonl"
    os.link(target, hard)
    cases = {link: "symbolic link", dangling: "symbolic link", fifo: "FIFO",
             Path("/dev/full"): "character device", hard: "hard link",
             tmp_path: "folder"}
    for path, words in cases.items():
        result = _open_in_thread(path)
        assert result is not None, f"open_log_file blocked on {path}"
        assert isinstance(result, ConfigError), (path, result)
        assert str(path) in str(result) and words in str(result), str(result)
    assert target.read_text() == "keep\n"
    assert not (tmp_path / "would_be_created.txt").exists()
    # a FIFO with a reader: opened without blocking, then refused by its type
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    try:
        result = _open_in_thread(fifo)
        assert isinstance(result, ConfigError) and "FIFO" in str(result), result
    finally:
        os.close(reader)
    # a regular file is truncated and written from its start
    plain = tmp_path / "plain.jsonl"
    plain.write_text("old content\n")
    fd = _open_in_thread(plain)
    assert isinstance(fd, int)
    os.close(fd)
    assert plain.read_bytes() == b""


def test_a_recording_target_is_refused_through_a_link_or_at_a_fifo(tmp_path):
    """The live viewer's ``save:FILE`` sink truncated the file with a plain ``open``
    (following a planted link, blocking on a FIFO); it now opens it like a log."""
    from simserver.adapters.rerun_sink import RerunSinkError, open_recording

    target = tmp_path / "precious.txt"
    target.write_text("keep\n")
    link = tmp_path / "run.rrd"
    link.symlink_to(target)
    fifo = tmp_path / "fifo.rrd"
    os.mkfifo(fifo)
    for path, words in ((link, "symbolic link"), (fifo, "FIFO")):
        got: list[BaseException | None] = []

        def run(p: Path = path, got: list[BaseException | None] = got) -> None:
            try:
                open_recording("save", p, announce=None)
                got.append(None)
            except BaseException as exc:  # noqa: BLE001 - handed to the test
                got.append(exc)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        t.join(10.0)
        assert got, f"open_recording blocked on {path}"
        assert isinstance(got[0], RerunSinkError) and words in str(got[0]), got
    assert target.read_text() == "keep\n"
