"""Every command the README gives, run as written, or named here with why it is not.

One server runs the README's main job as written (``readme_server`` of conftest: the
default config), its endpoint moved from the README's ``tcp/127.0.0.1:7447`` to a free
loopback port so that the tests pass while the README's own server runs; the README's
client commands and its Python driver then run against it, word for word but for that
endpoint (``--connect``, or the snippet's endpoint string), with ``.venv/bin/`` meaning the
environment running these tests and relative output paths landing in a temporary
directory. ``test_readme_defaults_are_one_endpoint`` checks that, as written, they all
meet on the README's endpoint. ``test_every_readme_command_is_accounted_for`` fails when the README
gains a command that is neither run here nor listed in ``NOT_RUN_HERE``.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys

import pyarrow.parquet as pq
import pytest

from simserver.testing import Client, OutputProcess, client_env, wait_until
from tests.conftest import (
    README_ENDPOINT,
    REPO,
    as_written,
    readme_client,
    readme_on,
    readme_without_performance_block,
)
from tests.test_clients import PtyProcess, hold_until

README = (REPO / "README.md").read_text()

RUN_HERE = {
    ".venv/bin/simserver-driver": "test_keyboard_driver_as_written",
    ".venv/bin/simserver-recorder --out out/live": "test_recorder_and_python_driver_as_written",
    ".venv/bin/simserver-player configs/scenarios/e5_hold_restart_uphill.yaml --load":
        "test_player_as_written",
    "simserver soak --duration 3600 --seed 11": "test_soak_as_written",
}
"""README command -> the test below that runs it."""

RUN_ELSEWHERE = {
    "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/simserver serve":
        "test_readme.py::test_main_command_job_runs (and the server of this module)",
    "simserver serve": "readme_server, the server of this module",
    "simserver ros2": "test_ros2.py runs the adapter against a live server",
    'python3 -m venv .venv && .venv/bin/pip install -q -e ".[test]" && '
    '.venv/bin/python -m pytest -q -n 2': "CI: .ci/run runs it verbatim (test_readme.py)",
    ".venv/bin/simserver run-scenario configs/scenarios/e2_stop_downslope_paper_damping.yaml"
    " --out out/e2": "test_readme.py::test_scenario_command_runs",
    ".venv/bin/simserver compare out/e2 out/e1 --out out/e2_vs_e1":
        "test_compare.py::test_readme_command_as_written (beside runs of E2 and E1)",
    "python -m pytest tests/test_scenarios.py -s": "the default suite runs that file",
    "python -m tests.suite_record": "test_suite_record.py runs it on a record of its own",
    ".venv/bin/python -m pytest -q -m long": "CI: .ci/run runs it after the test command "
                                             "(test_readme.py)",
    "python -m tests.long_form": "test_long_form.py checks the listing it prints "
                                 "(long_form.describe)",
    ".venv/bin/simserver run-scenario configs/scenarios/iso7401_step_steer.yaml --out "
    "out/iso7401": "test_manoeuvres.py::test_one_command_writes_the_figures_and_the_report "
                   "(into a temporary folder)",
    "simserver router --listen tcp/127.0.0.1:7450 --connect tcp/127.0.0.1:7447 --connect "
    "tcp/127.0.0.1:7448": "test_router.py runs it joining two servers (on free ports, not "
                          "these fixed ones)",
}

NOT_RUN_HERE = {
    '.venv/bin/pip install -e ".[joystick]"': "an install step; the test extra has pygame",
    ".venv/bin/simserver-driver --input joystick --profile configs/clients/wheel.yaml":
        "needs a device: test_clients.py drives it with that profile on SDL's virtual "
        "joystick",
    "docker build -t simserver .": "no container engine here: test_dockerfile.py runs the "
                                   "image's steps",
    "docker run --rm -p 127.0.0.1:7447:7447 simserver": "no container engine here",
    "simserver serve --config /etc/simserver/server/default.yaml --listen tcp/0.0.0.0:7447 "
    "--viewer off": "the image's command, on all interfaces: test_dockerfile.py runs it on "
                    "loopback",
    "rerun rerun+http://127.0.0.1:9876/proxy": "the native viewer needs a display",
    "rerun DIR/scene.rrd": "a placeholder, and a display",
    "simserver run-scenario SCENARIO.yaml --out DIR --rrd DIR/scene.rrd":
        "a placeholder: test_rerun.py runs it on a scenario",
    "simserver tire-curves TIRE.yaml --out FILE.png": "a placeholder: test_cli.py runs it on "
                                                      "both tires",
    "simserver serve --command-log run.jsonl": "a second server on the default port: "
                                               "test_server.py logs and replays a run",
    "simserver replay run.jsonl": "the same",
    "simserver replay run.*.jsonl": "a placeholder for a multi-car server's logs: "
                                    "test_multicar_session.py replays a live 4-car session "
                                    "with that command",
    "simserver view": "the main command already runs the view on its default port",
    "simserver view --sink serve --web-port 9090": "Rerun binds the web viewer to every "
                                                   "interface; tests listen on loopback only",
    "simserver sweep SWEEP.yaml --out DIR": "a placeholder: test_sweep.py runs sweeps",
    "simserver sweep configs/sweeps/relaxation_study.yaml --out out/relax":
        "225 runs: python -m benchmarks.bench_sweep runs its finer form "
        "(relaxation_study_dense.yaml); test_sweep.py runs smaller sweeps on the same engine",
    "python -m benchmarks": "minutes long, run by hand; test_readme.py checks the README's "
                            "table is its report",
    "python -m benchmarks.bench_step": "the same",
    "python -m benchmarks --only step --only startup --only suite": "the same",
    "python -m benchmarks.bench_server": "the same",
    "python -m benchmarks.bench_clock": "the same",
    "python -m benchmarks.bench_sweep": "the same",
    "python benchmarks/bench_tire.py": "the same",
    "python docs/figures.py": "regenerates the README's figures (minutes)",
    "python docs/rooms.py --write README.md": "rewrites the README's rooms table: "
                                              "test_import_cycles.py runs its --check",
}


def readme_commands() -> set[str]:
    """Every command of the README: indented command lines, fenced Python excluded, and
    inline code that starts like a command. The generated performance table is left out:
    its commands are the ones ``python -m benchmarks`` runs to write it, and
    ``test_readme.py`` checks the table is that report."""
    prose, _ = readme_without_performance_block(README)
    prose = re.sub(r"```.*?```", "", prose, flags=re.S)
    found = {ln.strip() for ln in prose.splitlines()
             if re.match(r" {4}(\.venv/bin/|python3? |docker |simserver |rerun )", ln)}
    flat = re.sub(r"\n\s*", " ", prose)
    found |= {m.group(1).strip() for m in
              re.finditer(r"`((?:\.venv/bin/|simserver |rerun |python )[^`]*)`", flat)}
    found.discard(".venv/bin/python")  # "run it with .venv/bin/python": not a command
    return found


def test_every_readme_command_is_accounted_for():
    accounted = set(RUN_HERE) | set(RUN_ELSEWHERE) | set(NOT_RUN_HERE)
    found = readme_commands()
    assert found - accounted == set(), "README commands no test runs or explains"
    assert accounted - found == set(), "listed here but no longer in the README"


def python_driver_snippet() -> str:
    """The README's minimal Python driver."""
    blocks = re.findall(r"```python\n(.*?)```", README, flags=re.S)
    (snippet,) = [b for b in blocks if "encode_command" in b]
    return snippet


def test_readme_defaults_are_one_endpoint():
    """The commands above run on a moved endpoint; as written, with nothing running here,
    they meet on the README's: the server's default listen (the default config as ``serve``
    reads it), every client's default connect (their own parsers, no flags), the Python
    driver's endpoint, and the live view's default port that the README's ``rerun`` command
    opens."""
    from clients import driver, player, recorder
    from clients.common import endpoints_text
    from simserver.adapters.rerun_sink import DEFAULT_GRPC_PORT
    from simserver.server.config import DEFAULT_SERVER_CONFIG, load_server_config

    assert f"`{README_ENDPOINT}`" in README
    cfg = load_server_config(DEFAULT_SERVER_CONFIG)
    assert cfg.listen == [README_ENDPOINT]
    required = {player: ["x.yaml"], recorder: ["--out", "x"]}  # parsed, never opened
    for client in (driver, player, recorder):
        args = client.build_parser().parse_args(required.get(client, []))
        assert endpoints_text(args) == README_ENDPOINT, client.__name__
    assert python_driver_snippet().count(f'"{README_ENDPOINT}"') == 1
    assert cfg.viewer == "serve"
    assert f"rerun rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy" in README


def test_recorder_and_python_driver_as_written(readme_server, tmp_path):
    """The recorder records while the README's Python driver drives (10 s at throttle 0.3):
    the file holds the car speeding up; Ctrl-C closes it."""
    watcher = Client(readme_server, state_capacity=1 << 15, keep_history=True)
    assert watcher.ep.request("reset")["ok"]
    recorder = OutputProcess(readme_client(".venv/bin/simserver-recorder --out out/live",
                                           readme_server),
                             ready="recording simserver/car0", env=client_env(), cwd=tmp_path)
    try:
        assert recorder.wait_ready(60), recorder.text()
        snippet = readme_on(readme_server.endpoint, python_driver_snippet())
        driver = subprocess.run([sys.executable, "-c", snippet], cwd=REPO,
                                capture_output=True, text=True, timeout=120)
        assert driver.returncode == 0, driver.stderr
    finally:
        code = recorder.stop(signal.SIGINT, timeout_s=60)
        watcher.poll()
        states = watcher.history
        watcher.close()
    assert code == 0, recorder.text()
    table = pq.read_table(tmp_path / "out" / "live" / "history.parquet")
    u = table.column("u_mps").to_numpy()
    throttle = table.column("input_throttle").to_numpy()
    print(f"\nREADME driver: {table.num_rows} rows recorded, u up to {u.max():.2f} m/s")
    assert table.num_rows > 5000  # > 5 s of 1 kHz states
    assert throttle.max() == pytest.approx(0.3, abs=1e-6)  # the snippet's throttle
    assert u.max() > 1.0 and max(float(s["u_mps"]) for s in states) > 1.0


def test_keyboard_driver_as_written(readme_server):
    watcher = Client(readme_server)
    drv = PtyProcess(readme_client(".venv/bin/simserver-driver", readme_server))
    try:
        drv.wait_for("connected to simserver/car0", 30)
        drv.wait_for("health", 10)
        pressed = hold_until(drv, b"w", watcher, lambda s: float(s["throttle"]) > 0.1, 10.0)
        drv.send(b"q")
        assert drv.wait(15) == 0, drv.text()
    finally:
        drv.close()
        watcher.close()
    assert float(pressed["throttle"]) > 0.1


def test_player_as_written(readme_server):
    """The player loads the E5 scenario (10 % uphill) and plays it; the first seconds are
    the brake-to-a-stop: it must be the scenario's scene and the car must be braked.
    Ctrl-C ends it cleanly."""
    watcher = Client(readme_server, state_capacity=1 << 15, keep_history=True)
    player = subprocess.Popen(
        readme_client(".venv/bin/simserver-player configs/scenarios/e5_hold_restart_uphill.yaml "
                      "--load", readme_server), cwd=REPO, env=client_env(), stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    try:
        wait_until(lambda: watcher.request("get_config", timeout_s=2.0),
                   lambda r: r.get("ok") and r["config"]["road"]["grade_pct"] == 10.0,
                   timeout_s=60, what="the scenario's scene loaded", interval_s=0.2)
        watcher.wait_state(lambda s: int(s["last_cmd_seq"]) > 0 and float(s["brake"]) > 0.1,
                           timeout_s=30, what="the player braking")
    finally:
        player.send_signal(signal.SIGINT)
        out, _ = player.communicate(timeout=30)
        watcher.poll()
        states = watcher.history
        watcher.close()
    assert player.returncode in (0, 130), out
    played = [s for s in states if int(s["last_cmd_seq"]) > 0]
    assert played and max(float(s["brake"]) for s in played) > 0.1, out


SOAK_AS_WRITTEN = "simserver soak --duration 3600 --seed 11"
SOAK_SHORT_S = 360
"""The default suite's soak: the README's line with a tenth of its simulated hour (the same
seed, so the same drive's first six minutes; the hour is 3.6 M steps, some 40 s of CPU,
the suite's longest single command); ``-m slow`` / ``SIMSERVER_SLOW=1`` runs it as written
(issue 33 item 3)."""


@pytest.mark.slow  # selected by -m slow, where it runs as written; by default the short form
def test_soak_as_written(tmp_path, request):
    """One simulated hour of seeded random driving, as the README quotes it (the long
    form; the default suite runs its first six simulated minutes, ``SOAK_SHORT_S``)."""
    from tests.conftest import slow_enabled

    assert SOAK_AS_WRITTEN in README
    command, duration_s = SOAK_AS_WRITTEN, 3600.0
    if not slow_enabled(request.config.getoption("markexpr")):
        command = command.replace("--duration 3600", f"--duration {SOAK_SHORT_S}")
        duration_s = float(SOAK_SHORT_S)
    proc = subprocess.run(as_written(command), cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr  # exit 1 on any violation
    summary = json.loads(proc.stdout)
    print(f"\nsoak: {summary}")
    assert summary["violations"] == []
    assert summary["simulated_s"] >= duration_s, summary  # it ends on a finished manoeuvre
