"""Every benchmark in one command, and the performance table.

Run from the repository root::

    python -m benchmarks                      # the full runs (about 30 minutes)
    python -m benchmarks --quick              # short runs: a smoke test, not figures
    python -m benchmarks --only startup --only memory
    python -m benchmarks --only step --only startup --only suite   # issue 33's figures,
                                                  # beside the step cost (about 10 minutes)
    python -m benchmarks --only suite --run-suite 3   # the test suite run now, 3 times

In order:

1. ``benchmarks.bench_step``: step cost per tire model and the headless real-time factor of
   the compiled loop; ``commonroad``: ``benchmarks.bench_commonroad``, our step rate against
   CommonRoad's multi-body model with RK4 at our step, measured in the same run (CommonRoad
   runs in the benchmark's own environment, ``.bench-venv/``, made on first use);
2. ``benchmarks.bench_server``: the live server with its viewer off, driven over zenoh at
   200 Hz: tick lateness p50/p99/max, ticks more than 1 ms late, overruns, drift, command-to-
   state latency p50/p99. While it runs, this harness samples the server's peak resident
   memory (``VmHWM`` in ``/proc/PID/status``);
   ``busy``: the same beside two CPU-bound processes (``--hogs 2``), the server and the
   client under their default real-time scheduling (issue 13);
   ``load``: ``benchmarks.bench_load``, 20 state subscribers and 10 clients joining and
   leaving a second, a driver at 1 kHz;
   ``hostile``: ``benchmarks.bench_load --hostile``, the largest gap in the state stream
   while hostile loads, terrain loads and resets at speed are prepared, beside
   no-load baseline windows of the same run (issues 13 and 17);
3. ``benchmarks.bench_viewer``: the same with the live viewer off, saving to a file and
   streaming to a stalled viewer (also sampling the viewer process's peak memory);
4. ``benchmarks.bench_ros2``: the same with the server's ROS 2 adapter off and on (its
   topics received by a ROS node through a router), in 8 rounds of 12 s beside the VM's
   stall floor (``benchmarks.interleaved``);
5. ``benchmarks.bench_tls_front`` (``tls_front``): command-to-state latency over TLS with
   zenoh's listener direct and behind the accept-filtering TLS front, and the front's hop
   alone (issue 14);
6. start-up: ``simserver serve`` from launch to its ``ready`` line (physics compiled or
   loaded, zenoh session open, before the first tick), cold = the kernel caches
   (``NUMBA_CACHE_DIR``, ``SIMSERVER_CACHE_DIR``) an empty
   temporary directory, warm = the same directory again; the median of the repeats; and
   ``benchmarks.bench_compile`` once: the physics' cold compile alone, per entry point;
   then, with that warm cache, the wall time from launch to exit of the README's headless
   commands (``run-scenario`` of E2 with and without its plots, ``tire-curves``), the median
   of the warm repeats;
7. memory of a headless run: peak RSS (``ru_maxrss`` from ``wait4``) of the README's
   ``simserver run-scenario`` example, which also reports its real-time factor;
8. ``image``: ``benchmarks.bench_image``: the container image's environment built as
   ``tests/test_dockerfile.py`` builds it (the Dockerfile's own steps: ``pip install .`` in a
   fresh venv, the warm-up pre-compiling every kernel into its ``SIMSERVER_CACHE_DIR``), then
   its ``ENTRYPOINT`` + ``CMD`` started to ``ready`` as many times as the cold start-ups, the
   median; a start that compiles is an error (not in ``--quick``: the build takes minutes);
9. ``suite``: the README's test command (``python -m pytest -q -n 2``). By default the row reads
   the last three recorded runs of that command (every run of the whole default suite
   records its wall and CPU time and whether the kernel cache was empty at its start,
   ``tests/suite_record.py``), so the row costs nothing and says when and at which commit
   each run was; with ``--run-suite N`` it runs the command N times now, each from empty
   kernel caches (the main half's and the beside half's: a fresh clone's cold compile
   included), and reports their median.

Then it prints a markdown table (figure, value, the target the issues set, the command that
reproduces it) with the machine's description, and writes it to ``--out`` (default
``docs/performance.md`` for a full run; a ``--quick`` run writes a file only when ``--out`` is
given). A full run also rewrites the README's performance block (between the
``README_BEGIN`` and ``README_END`` markers) from the same report, so the two never
disagree (``tests/test_readme.py`` checks it). ``--json FILE`` keeps every raw result.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import platform
import re
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.bench_compile import cache_env
from benchmarks.interleaved import CLOCK_FLOOR
from simserver.testing import ServerProcess, free_port, serve_args

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "docs" / "performance.md"
README = REPO / "README.md"
README_BEGIN = "<!-- BEGIN GENERATED: performance (python -m benchmarks) -->"
README_END = "<!-- END GENERATED: performance -->"
TABLE_HEADER = ("| figure | value | target | command |", "|---|---|---|---|")
HEADLESS_SCENARIO = "configs/scenarios/e2_stop_downslope_paper_damping.yaml"
"""The README's headless example, run for the headless memory figure."""

SECTIONS = ("step", "commonroad", "server", "busy", "load", "hostile", "viewer", "ros2",
            "tls_front", "multicar", "startup", "memory", "image", "suite")
"""Benchmarks in the order they run (``--only`` takes these names)."""


@dataclass(frozen=True)
class Settings:
    """Run lengths of one mode (full or quick)."""

    step_args: tuple[str, ...]
    commonroad_args: tuple[str, ...]
    server_seconds: float
    busy_runs: int
    load_seconds: float
    viewer_seconds: float
    viewer_rounds: int
    hostile_rounds: int
    ros2_args: tuple[str, ...]
    multicar_args: tuple[str, ...]
    startup_cold: int
    startup_warm: int
    suite_runs: int
    """Runs of the README's test command now (``--run-suite N``); 0: read the record."""
    startup_python: str | None = None
    """The interpreter of the start-up section's commands (``--python``); None: this one."""


FULL = Settings(step_args=(), commonroad_args=(), server_seconds=60.0, busy_runs=3,
                load_seconds=30.0, viewer_seconds=60.0, viewer_rounds=2, hostile_rounds=3,
                ros2_args=("--seconds", "12", "--rounds", "8"),
                multicar_args=("--seconds", "20", "--rounds", "2"),
                startup_cold=3, startup_warm=5, suite_runs=0)
QUICK = Settings(step_args=("--seconds", "5", "--repeats", "5"),
                 commonroad_args=("--rounds", "1", "--seconds", "2", "--steps", "300"),
                 server_seconds=8.0,
                 busy_runs=1, load_seconds=8.0, viewer_seconds=6.0, viewer_rounds=1,
                 hostile_rounds=1,
                 ros2_args=("--seconds", "6", "--rounds", "2", "--floor-seconds", "3"),
                 multicar_args=("--seconds", "5"),
                 startup_cold=1, startup_warm=3, suite_runs=0)
"""Short runs: long enough for the server's 4096-tick statistics window, no longer."""


@dataclass
class Row:
    """One line of the performance table."""

    figure: str
    value: str
    command: str
    target: str = ""
    """The issue's target for this figure, if it sets one."""

    def markdown(self) -> str:
        """The row as a line of the table (``TABLE_HEADER``)."""
        return f"| {self.figure} | {self.value} | {self.target} | `{self.command}` |"


@dataclass
class Report:
    """Every row, every raw result, and the machine they came from."""

    machine: dict[str, str]
    mode: str
    rows: list[Row] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------ the machine
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "cpu model", "hardware")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _mem_total_gib() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return f"{int(line.split()[1]) / 1024**2:.1f} GiB"
    except OSError:
        pass
    return "unknown"


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "not installed"


def _git_commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=REPO, capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}{' (with local changes)' if dirty.strip() else ''}" if head else "unknown"


def machine_description() -> dict[str, str]:
    """nproc, CPU model, RAM, OS, Python and library versions, load, commit, date."""
    load = os.getloadavg()
    return {
        "nproc": str(len(os.sched_getaffinity(0))),
        "CPU": _cpu_model(),
        "RAM": _mem_total_gib(),
        "OS": f"{platform.system()} {platform.release()} {platform.machine()}",
        "Python": f"{platform.python_version()} ({platform.python_implementation()})",
        "numpy": _version("numpy"),
        "numba": f"{_version('numba')} (llvmlite {_version('llvmlite')})",
        "eclipse-zenoh": _version("eclipse-zenoh"),
        "rerun-sdk": _version("rerun-sdk"),
        "load average at start": " / ".join(f"{x:.2f}" for x in load) + " (1/5/15 min)",
        "commit": _git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


# --------------------------------------------------------------------- peak memory
def _vm_hwm_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def _children(pid: int) -> list[int]:
    kids: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            kids += [int(k) for k in (task / "children").read_text().split()]
    except OSError:
        pass
    return kids


class PeakRss:
    """Samples, once a second, the peak RSS (``VmHWM``) of every descendant process.

    ``VmHWM`` is the kernel's own high-water mark, so a sample close to the end catches the
    peak; sampling once a second costs next to nothing beside a 1 kHz loop. Each process is
    kept with its command line and its parent, so a result can be told apart by role
    (``serve`` and its ``--viewer``, or ``view``).
    """

    def __init__(self, interval_s: float = 1.0) -> None:
        self.interval_s = interval_s
        self.procs: dict[int, dict[str, Any]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> PeakRss:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _sample(self) -> None:
        todo = [(os.getpid(), 0)]
        while todo:
            parent, _ = todo.pop()
            for pid in _children(parent):
                todo.append((pid, parent))
                hwm = _vm_hwm_kib(pid)
                if hwm is None:
                    continue
                info = self.procs.get(pid)
                if info is None:
                    try:
                        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
                    except OSError:
                        continue
                    info = {"argv": [a.decode(errors="replace") for a in argv if a],
                            "ppid": parent, "hwm_kib": 0}
                    self.procs[pid] = info
                info["hwm_kib"] = max(info["hwm_kib"], hwm)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def peaks(self, role: Callable[[list[str], list[str] | None], str | None]
              ) -> dict[str, int]:
        """The highest peak (KiB) per role; ``role(argv, parent_argv)`` names a process."""
        out: dict[str, int] = {}
        for info in self.procs.values():
            parent = self.procs.get(info["ppid"], {}).get("argv")
            name = role(info["argv"], parent)
            if name is not None:
                out[name] = max(out.get(name, 0), info["hwm_kib"])
        return out


def _floor_row(r: dict, cmd: str, prefix: str = "") -> Row:
    """The clock floor measured before and after a bench_server run (same command)."""
    f = r["clock_floor"]
    return Row(f"{prefix}clock floor: the bare pacer as the tick thread, {f['seconds'] / 2:g} s "
               "before and after the server in the same command: ticks > 1 ms late / "
               "lateness p99",
               f"{100 * f['before']['late_fraction']:.2f} % / "
               f"{100 * f['after']['late_fraction']:.2f} %; {f['before']['lateness_p99_us']:.0f}"
               f" / {f['after']['lateness_p99_us']:.0f} us (the server: "
               f"{100 * r['late_fraction']:.2f} %, {r['lateness_p99_us']:.0f} us)", cmd)


def _nanmax(values: list[float]) -> str:
    """The largest of ``values`` that is a number, two decimals ("-" if none)."""
    numbers = [v for v in values if v == v]
    return f"{max(numbers):.2f}" if numbers else "-"


def _ms_max(r: dict, key: str) -> str:
    """The largest ``key`` over the hostile actions and rounds, in ms."""
    return _nanmax([v for e in r["actions"].values() for v in e[key]])


def simserver_role(argv: list[str], parent: list[str] | None) -> str | None:
    """``serve (viewer off|save|connect)`` or ``view (save|connect)`` for simserver processes."""
    def viewer_mode(args: list[str]) -> str:
        if "--viewer" in args:
            return args[args.index("--viewer") + 1].split(":", 1)[0]
        return "config"

    # the subcommand follows `simserver` (python -m simserver ...) or the console script
    sub = next((argv[i + 1] for i, a in enumerate(argv[:-1])
                if a == "simserver" or a.endswith("/simserver")), None)
    if sub == "serve":
        return f"serve (viewer {viewer_mode(argv)})"
    if sub == "view":
        mode = viewer_mode(parent) if parent else "?"
        return f"view (viewer {mode})"
    return None


def _mib(kib: int) -> str:
    return f"{kib / 1024:.0f} MiB"


# --------------------------------------------------------------------- start-up
def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (``/proc/PID/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def startup_env(numba_cache_dir: Path) -> dict[str, str]:
    """The environment of a timed start: the kernel caches in ``numba_cache_dir``
    (``cache_env``) and Python's bytecode cache on, as a user's checkout or install has it
    (pip byte-compiles an install; Python writes a checkout's ``__pycache__`` on first
    import). A ``PYTHONDONTWRITEBYTECODE`` of the shell running the benchmarks is dropped:
    with it every start would compile simserver's own sources again (about 0.2 s of CPU
    for run-scenario's 54 modules on this VM), a cost no warm start of a user has."""
    env = cache_env(numba_cache_dir)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def time_to_ready(numba_cache_dir: Path, timeout_s: float = 300.0,
                  cpu: list[float] | None = None, python: str = sys.executable) -> float:
    """Launch ``simserver serve`` (viewer off, free loopback port), return the seconds to its
    ``ready`` line, then stop it with SIGTERM. With ``cpu``, the server's CPU seconds at
    its ready line are appended to it (on a shared machine the steadier figure: the compile
    is single-threaded)."""
    listen = [f"tcp/127.0.0.1:{free_port()}"]
    argv = serve_args(vehicle_id="car0", scene=None, listen=listen, viewer="off",
                      log_level="WARNING", command_log=None, config=None, extra_args=())
    server = ServerProcess(argv=[python, *argv[1:]], listen=listen,
                           ready_timeout_s=timeout_s, env=startup_env(numba_cache_dir))
    if cpu is not None:
        cpu.append(_cpu_s(server.pid))
    server.stop()
    return server.ready_s


HEADLESS_COMMANDS: dict[str, tuple[str, ...]] = {
    "run-scenario E2, with plots": ("run-scenario", HEADLESS_SCENARIO, "--out", "{out}/e2",
                                    "--quiet"),
    "run-scenario E2, --no-plots": ("run-scenario", HEADLESS_SCENARIO, "--out", "{out}/e2",
                                    "--quiet", "--no-plots"),
    "tire-curves": ("tire-curves", "configs/tires/paper_sti.yaml", "--out",
                    "{out}/curves.png"),
}
"""The warm headless commands timed from launch to exit (``simserver`` subcommand and its
arguments; ``{out}`` is a scratch directory): the README's E2 example with and without its
PNG plots, and the README's ``tire-curves`` (issue 33's targets 1.2, 0.6 and 2 s)."""
HEADLESS_TARGETS = {"run-scenario E2, with plots": "<= 1.2 s",
                    "run-scenario E2, --no-plots": "<= 0.6 s", "tire-curves": "<= 2 s"}
NUMBA_FLOOR_CODE = ("import numba\n"
                    "from numba.core.registry import cpu_target\n"
                    "cpu_target.target_context.refresh()\n")
"""What every warm path that runs a kernel pays before any of simserver's code: Python,
numpy, numba and numba's CPU target, which numba's cache initialises before it loads the
first cached kernel (``numba.core.caching.Cache.load_overload`` refreshes the target
context: every lowering registry, and through ``numba.np.arraymath``'s BLAS check all of
``scipy.linalg`` where scipy is installed). Timed beside the warm commands, it shows which
part of their time is numba's own."""
NUMBA_FLOOR = "floor: python -c 'import numba' and numba's CPU target"


def time_command(args: tuple[str, ...], numba_cache_dir: Path,
                 python_args: tuple[str, ...] = ("-m", "simserver"),
                 python: str = sys.executable) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, the process and its children) from launch to
    exit of ``python -m simserver ARGS`` (``{out}`` in ARGS a fresh scratch directory; or
    ``python PYTHON_ARGS ARGS``) with the kernel caches in ``numba_cache_dir``; raises if
    it fails. On a shared machine the CPU seconds are the steadier figure."""
    out = Path(tempfile.mkdtemp(prefix="simserver_startup_"))
    argv = [python, *python_args, *(a.format(out=out) for a in args)]
    try:
        cpu0 = _children_cpu_s()
        t0 = time.perf_counter()
        proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=600,
                              env=startup_env(numba_cache_dir))
        wall_s = time.perf_counter() - t0
        cpu_s = _children_cpu_s() - cpu0
    finally:
        shutil.rmtree(out, ignore_errors=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv[1:])} exited {proc.returncode}:\n"
                           f"{proc.stdout}{proc.stderr}")
    return wall_s, cpu_s


def startup(cold: int, warm: int, python: str = sys.executable) -> dict[str, Any]:
    """Median launch-to-ready time of the server with an empty and with a warm numba cache,
    then the median wall time of each warm headless command (``HEADLESS_COMMANDS``; one
    unmeasured run first, which compiles what the server's warm-up did not); each command
    run by the interpreter ``python``."""
    cold_s: list[float] = []
    warm_s: list[float] = []
    cold_cpu_s: list[float] = []
    warm_cpu_s: list[float] = []
    headless: dict[str, list[float]] = {name: [] for name in (*HEADLESS_COMMANDS, NUMBA_FLOOR)}
    headless_cpu: dict[str, list[float]] = {name: [] for name in headless}
    dirs = [Path(tempfile.mkdtemp(prefix="simserver_numba_")) for _ in range(cold)]
    try:
        for d in dirs:
            cold_s.append(time_to_ready(d, cpu=cold_cpu_s, python=python))
            print(f"start-up, cold numba cache: {cold_s[-1]:.2f} s ({cold_cpu_s[-1]:.1f} s CPU; "
                  f"load average {os.getloadavg()[0]:.1f})", flush=True)
        for _ in range(warm):
            warm_s.append(time_to_ready(dirs[-1], cpu=warm_cpu_s, python=python))
            print(f"start-up, warm numba cache: {warm_s[-1]:.2f} s ({warm_cpu_s[-1]:.2f} s CPU)",
                  flush=True)
        for args in HEADLESS_COMMANDS.values():
            time_command(args, dirs[-1], python=python)  # compiles what the server's did not
        commands = {**{name: (args, ("-m", "simserver"))
                       for name, args in HEADLESS_COMMANDS.items()},
                    NUMBA_FLOOR: ((), ("-c", NUMBA_FLOOR_CODE))}
        for _ in range(warm):  # interleaved: a slow minute of the VM spreads over all four
            for name, (args, python_args) in commands.items():
                wall_s, cpu_s = time_command(args, dirs[-1], python_args, python)
                headless[name].append(wall_s)
                headless_cpu[name].append(cpu_s)
                print(f"warm {name}: {wall_s:.2f} s ({cpu_s:.2f} s CPU; load average "
                      f"{os.getloadavg()[0]:.1f})", flush=True)
    finally:
        for d in dirs:
            shutil.rmtree(d, ignore_errors=True)
    return {"cold_s": cold_s, "warm_s": warm_s,
            "cold_cpu_s": cold_cpu_s, "warm_cpu_s": warm_cpu_s,
            "cold_median_s": statistics.median(cold_s),
            "warm_median_s": statistics.median(warm_s),
            "cold_median_cpu_s": statistics.median(cold_cpu_s),
            "warm_median_cpu_s": statistics.median(warm_cpu_s),
            "headless_s": headless, "headless_cpu_s": headless_cpu,
            "headless_median_s": {k: statistics.median(v) for k, v in headless.items()},
            "headless_median_cpu_s": {k: statistics.median(v) for k, v in headless_cpu.items()}}


# --------------------------------------------------------------------- the test suite
def _children_cpu_s() -> float:
    """User + system CPU seconds of this process's reaped children so far."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def suite_time(runs: int) -> dict[str, Any]:
    """Wall time of the README's test command (``python -m pytest -q -n 2`` as the README
    writes it), each run from empty kernel caches as a fresh clone has (the cold compile
    included: the beside half's own cache, ``tests.long_form.beside_kernel_cache``, is
    emptied too); its closing line and exit code per run."""
    from tests.long_form import beside_kernel_cache

    command = next(ln.strip() for ln in README.read_text(encoding="utf-8").splitlines()
                   if ln.startswith("    python3 -m venv .venv") and "pytest" in ln)
    job = shlex.split(command.split("&&")[-1])  # .venv/bin/python -m pytest ...
    argv = [sys.executable, *job[1:]]
    results = []
    for _ in range(runs):
        cache = Path(tempfile.mkdtemp(prefix="simserver_numba_suite_"))
        shutil.rmtree(beside_kernel_cache(), ignore_errors=True)
        load = os.getloadavg()[0]
        try:
            cpu0 = _children_cpu_s()
            t0 = time.perf_counter()
            proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True,
                                  env=cache_env(cache))
            wall_s = time.perf_counter() - t0
            cpu_s = _children_cpu_s() - cpu0  # the tree's CPU: on a shared machine the
            # wall time mostly measures the other users
        finally:
            shutil.rmtree(cache, ignore_errors=True)
        closing = next((ln.strip("= ") for ln in reversed(proc.stdout.splitlines())
                        if " in " in ln and ("passed" in ln or "failed" in ln)), "")
        results.append({"wall_s": wall_s, "cpu_s": cpu_s, "returncode": proc.returncode,
                        "closing": closing,
                        "loadavg_1min_start": load, "loadavg_1min_end": os.getloadavg()[0]})
        print(f"test suite: {wall_s:.0f} s ({cpu_s:.0f} s of CPU, load "
              f"{load:.1f}-{os.getloadavg()[0]:.1f}), exit {proc.returncode}: {closing}",
              flush=True)
    return {"runs": results, "median_s": statistics.median(r["wall_s"] for r in results),
            "argv": argv}


SUITE_RECORDED = 3
"""How many of the last recorded runs of the README's test command the suite row reads."""


def recorded_suite_runs(n: int = SUITE_RECORDED) -> dict[str, Any]:
    """The last ``n`` recorded runs of the README's test command (``tests/suite_record.py``:
    every such run appends its wall and CPU time), with their median wall time."""
    from tests import suite_record

    runs = suite_record.read()[-n:]
    return {"runs": runs, "record": str(suite_record.RECORD),
            "median_s": statistics.median(r["wall_s"] for r in runs) if runs else None}


def suite_record_row(r: dict[str, Any]) -> Row:
    """The suite row from the recorded runs (``recorded_suite_runs``)."""
    figure = "the README's test command (recorded runs"
    cmd = "python -m pytest -q -n 2 (recorded); python -m benchmarks --only suite"
    runs = r["runs"]
    if not runs:
        return Row(figure + ")", "no recorded run: run the README's test command, or "
                   "`python -m benchmarks --only suite --run-suite 3`", cmd, "<= 300 s")
    return Row(f"{figure}, median of the last {len(runs)})", f"{r['median_s']:.0f} s (runs: "
               + ", ".join(f"{x['wall_s']:.0f} s" + (" cold" if x["cold"] else " warm")
                           + ("" if x["exitstatus"] == 0 else f" exit {x['exitstatus']}")
                           + f" at {x['commit']}, {x['date']}, load "
                           f"{x['loadavg_1min_start']:.1f}-{x['loadavg_1min_end']:.1f}"
                           for x in runs)
               + f"; CPU {statistics.median(x['cpu_s'] for x in runs):.0f} s; "
               + ", ".join(f"{v} {k}" for k, v in runs[-1]["counts"].items()) + ")",
               cmd, "<= 300 s")


# --------------------------------------------------------------------- headless
def headless_run() -> dict[str, Any]:
    """Peak RSS and real-time factor of the README's ``run-scenario`` example."""
    out = Path(tempfile.mkdtemp(prefix="simserver_headless_"))
    argv = [sys.executable, "-m", "simserver", "run-scenario", HEADLESS_SCENARIO,
            "--out", str(out / "e2"), "--quiet"]
    try:
        proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT)
        assert proc.stdout is not None
        text = proc.stdout.read().decode(errors="replace")
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        proc.stdout.close()
    finally:
        shutil.rmtree(out, ignore_errors=True)
    if proc.returncode != 0:
        raise RuntimeError(f"run-scenario exited {proc.returncode}:\n{text}")
    print(text.strip(), flush=True)
    rtf = re.search(r"([\d,]+) ?x real time", text)
    return {"peak_rss_kib": usage.ru_maxrss, "output": text.strip(),
            "real_time_factor": float(rtf.group(1).replace(",", "")) if rtf else None}


# --------------------------------------------------------------------- the table
def _us(x: float) -> str:
    if x < 10:
        return f"{x:.2f} us"
    return f"{x:,.1f} us" if x < 1000 else f"{x / 1000:,.2f} ms"


def lateness_rows(summary: dict[str, dict], what: str, cmd: str) -> list[Row]:
    """The rows of a ``compare_modes`` summary: each mode's tick lateness against off's."""
    return [Row(f"tick lateness p50 / p99, {what}: {mode}",
                f"{_us(s['p50_us'])} / {_us(s['p99_us'])} ({s['p99_vs_off']:.2f} x off"
                + (f", {s['p99_paired_vs_off']:.2f} x paired by round"
                   if "p99_paired_vs_off" in s and mode != "off" else "") + "); "
                f"{100 * s['late_fraction']:.2f} % ticks > 1 ms late", cmd,
                "" if mode in ("off", CLOCK_FLOOR) else "p99 <= 1.10 x off")
            for mode, s in summary.items()]


def run_all(settings: Settings, sections: list[str], quick: bool) -> Report:
    """Run the chosen benchmarks in order; collect the rows of the table."""
    from benchmarks import bench_ros2, bench_server, bench_step, bench_viewer

    report = Report(machine=machine_description(), mode="quick" if quick else "full")
    rows, raw = report.rows, report.raw
    suffix = " --quick" if quick else ""

    if "step" in sections:
        print("== bench_step", flush=True)
        argv = list(settings.step_args)
        cmd = " ".join(["python -m benchmarks.bench_step", *argv])
        raw["step"] = results = bench_step.main(argv)
        for r in results:
            mf61 = r["tire_model"].startswith("mf61")
            rows.append(Row(f"step cost, {r['tire_model']} tires",
                            f"{r['ns_per_step_median'] / 1e3:.2f} us median "
                            f"(p10 {r['p10'] / 1e3:.2f}, p90 {r['p90'] / 1e3:.2f})", cmd,
                            "<= 2.0 us" if mf61 else "<= 1.2 us"))  # issue 16
        for r in results:
            mf61 = r["tire_model"].startswith("mf61")
            rows.append(Row(f"headless real-time factor, {r['tire_model']}",
                            f"{r['real_time_factor']:,.0f} x", cmd,
                            ">= 200 x" if mf61 else ""))

    if "commonroad" in sections:
        from benchmarks import bench_commonroad

        print("== bench_commonroad", flush=True)
        argv = list(settings.commonroad_args)
        cmd = " ".join(["python -m benchmarks.bench_commonroad", *argv])
        raw["commonroad"] = r = bench_commonroad.main(argv)
        figure = "step rate against CommonRoad's multi-body model + RK4, MF 6.1 tires"
        target = f">= {bench_commonroad.TARGET_RATIO_MF61:.0f} x"
        if "skipped" in r:
            rows.append(Row(figure, f"not measured: {r['skipped']}", cmd, target))
        else:
            (mf,), (brush,) = ([v for k, v in r["ours"].items() if k.startswith(m)]
                               for m in ("mf61", "simple"))
            theirs = r["commonroad_us_per_step"]
            judged, other = bench_commonroad.STATE_FORMS
            rows.append(Row(figure, f"{mf['ratio'][judged]:,.0f} x against its {judged} state "
                            f"({mf['ratio'][other]:,.0f} x against its {other} state; ours "
                            f"{mf['us_per_step']:.2f} us, CommonRoad {theirs[judged]:.0f} and "
                            f"{theirs[other]:.0f} us per step, CPU time; brush tires "
                            f"{brush['ratio'][judged]:,.0f} and {brush['ratio'][other]:,.0f} x)",
                            cmd, f"{target} ({judged} state)"))

    if "server" in sections:
        print("== bench_server", flush=True)
        argv = ["--seconds", f"{settings.server_seconds:g}"]
        cmd = " ".join(["python -m benchmarks.bench_server", *argv])
        with PeakRss() as rss:
            raw["server"] = r = bench_server.main(argv)
        peaks = rss.peaks(simserver_role)
        raw["server"]["peak_rss_kib"] = peaks
        span = f"{settings.server_seconds:g} s, viewer off"
        rows += [
            Row(f"tick lateness p50 / p99 ({span})",
                f"{_us(r['lateness_p50_us'])} / {_us(r['lateness_p99_us'])}", cmd,
                "p99 < 100 us"),
            Row("tick lateness max", _us(r["lateness_max_us"]), cmd),
            Row("ticks > 1 ms late", f"{r['late_ticks']} of {r['ticks']} "
                f"({100 * r['late_fraction']:.2f} %); overruns {r['overruns']}, "
                f"skipped {r['skipped_ticks']}", cmd, "< 1 %"),
            Row("drift of simulated from wall time",
                f"{r['drift_ms']:+.2f} ms over {r['wall_s']:.0f} s", cmd,
                "none (within a tick)"),
            Row("command-to-state latency p50 / p99 (200 Hz commands, random phase)",
                f"{_us(r['latency_p50_us'])} / {_us(r['latency_p99_us'])} "
                f"(max {_us(r['latency_max_us'])})", cmd, "< 1 ms / < 2 ms"),
            Row("server CPU", f"{r['cpu_percent']:.0f} % of one core", cmd),
        ]
        if "clock_floor" in r:
            rows.append(_floor_row(r, cmd))
        if "serve (viewer off)" in peaks:
            rows.append(Row(f"server peak RSS ({span})", _mib(peaks["serve (viewer off)"]),
                            "python -m benchmarks --only server" + suffix))

    if "busy" in sections:
        print("== bench_server --hogs 2", flush=True)
        argv = ["--seconds", f"{settings.server_seconds:g}", "--hogs", "2"]
        cmd = " ".join(["python -m benchmarks.bench_server", *argv])
        runs = [bench_server.main(argv) for _ in range(settings.busy_runs)]
        raw["busy"] = runs

        def med(key: str) -> float:
            return statistics.median(r[key] for r in runs)

        loads = ", ".join(f"{r['loadavg_1min']:.1f}" for r in runs)
        rows += [
            Row(f"busy machine (2 CPU hogs, median of {len(runs)} runs): ticks > 1 ms late",
                f"{100 * med('late_fraction'):.2f} % (runs: " + ", ".join(
                    f"{100 * r['late_fraction']:.2f}" for r in runs)
                + f"; load average {loads})", cmd, "<= 0.5 %"),
            Row("busy machine: tick lateness p99", _us(med("lateness_p99_us")) + " (runs: "
                + ", ".join(_us(r["lateness_p99_us"]) for r in runs) + ")", cmd, "< 50 us"),
            Row("busy machine: command-to-state latency p50 / p99",
                f"{_us(med('latency_p50_us'))} / {_us(med('latency_p99_us'))} (p99 runs: "
                + ", ".join(_us(r["latency_p99_us"]) for r in runs) + ")", cmd, "p99 < 1.5 ms"),
            Row("busy machine: states the tick put itself (not handed to its state-tx thread)",
                f"{100 * med('states_inline_fraction'):.1f} % (runs: " + ", ".join(
                    f"{100 * r['states_inline_fraction']:.1f}" for r in runs) + "; hand-offs "
                + ", ".join(str(r["publish_handoffs"]) for r in runs) + ")", cmd),
        ]
        rows += [_floor_row(r, cmd, f"busy machine, run {i + 1}: ")
                 for i, r in enumerate(runs) if "clock_floor" in r]

    if "load" in sections:
        from benchmarks import bench_load

        print("== bench_load", flush=True)
        argv = ["--seconds", f"{settings.load_seconds:g}"]
        cmd = " ".join(["python -m benchmarks.bench_load", *argv])
        raw["load"] = r = bench_load.main(argv)
        rows += [
            Row("20 state subscribers + 10 clients joining and leaving per s: ticks > 1 ms "
                "late", f"{r['late_ticks']} of {r['ticks']} ({100 * r['late_fraction']:.2f} "
                f"%), skipped {r['skipped_ticks']}; load average {r['loadavg_1min']:.1f}",
                cmd, "<= 1 %"),
            Row("the same: states lost by the 20 subscribers",
                f"{r['subscriber_missing_total']} ({r['joined']} clients joined, "
                f"{r['config_ok']} get_config answered)", cmd, "0"),
            Row("the same: states the tick put itself (the rest by its state-tx thread), "
                "hand-offs to that thread", f"{r['publish_inline_puts']} of the server run's "
                f"{r['server_final']['ticks']}, {r['publish_handoffs']} hand-offs", cmd),
        ]
        lc = r.get("late_causes")
        if lc:
            cpu50, cpu99, _ = lc["work_cpu_us_p50_p99_max"]
            rows.append(Row(
                "the same: what made the late ticks late (the server's tick trace; ms in "
                "the late episodes, episodes dominated)", "; ".join(
                    f"{k} {v:.0f} ({lc['dominated'][k]})" for k, v in lc["totals_ms"].items()
                    if v >= 0.5) + f"; a tick's work {cpu50:.0f} us CPU p50, {cpu99:.0f} us "
                f"p99; GC {lc['gc_ms_total']:.1f} ms in all", cmd))

    if "hostile" in sections:
        from benchmarks import bench_load

        print("== bench_load --hostile", flush=True)
        argv = ["--hostile", "--rounds", str(settings.hostile_rounds)]
        cmd = " ".join(["python -m benchmarks.bench_load", *argv])
        raw["hostile"] = r = bench_load.main(argv)
        raw["pieces"] = work = bench_load.main(["--pieces", "--rounds",
                                                str(2 + settings.hostile_rounds)])
        piece_us = max(max(v) for row in work.values() for v in row.values())
        cmd += "; python -m benchmarks.bench_load --pieces"
        gaps = {label: max(e["gap_ms"]) for label, e in r["actions"].items()}
        worst = max(gaps, key=gaps.get)
        base = sorted(r["baseline_gap_ms"])
        rows.append(Row(
            "largest gap in the 1 kHz state stream during hostile loads (10 MB, alias bomb, "
            "deep nesting, FIFO), terrain loads and resets at speed",
            f"{gaps[worst]:.2f} ms ({worst}), server tick lateness max "
            f"{max(max(e['lateness_ms']) for e in r['actions'].values()):.2f} ms; no-load "
            f"baseline windows: median "
            f"{base[len(base) // 2]:.2f}, max {base[-1]:.2f} ms; commands {r['cmd_sent']} "
            f"sent, {r['cmd_received']} received + {r['cmd_dropped']} counted; the "
            f"largest piece of work a tick does for them {piece_us:.0f} us CPU",
            cmd, "<= 2 ms"))
        if all("own_ms" in e for e in r["actions"].values()):
            own = {label: max(e["own_ms"], key=lambda v: -1.0 if v != v else v)
                   for label, e in r["actions"].items()}  # NaN (no ticks traced) last
            worst_own = max(own, key=own.get)
            split = r["baseline_split"]
            rows.append(Row(
                "the same, the loop's stalls by whose they are (the server's tick trace and "
                "a clock-floor peer process in the same run; max over the actions)",
                f"the server's own work and waits {own[worst_own]:.2f} ms ({worst_own}); "
                "tick-start gap " + _ms_max(r, "tick_gap_ms") + ", the VM "
                + _ms_max(r, "vm_ms") + ", run-queue wait " + _ms_max(r, "others_ms")
                + ", clock-floor peer " + _ms_max(r, "peer_ms") + "; no-load baselines: "
                "own " + _nanmax(split["own_ms"]) + ", tick-start gap "
                + _nanmax(split["tick_gap_ms"]) + ", peer " + _nanmax(split["peer_ms"])
                + " ms",
                cmd, "own <= 2 ms"))

    if "viewer" in sections:
        print("== bench_viewer", flush=True)
        argv = ["--seconds", f"{settings.viewer_seconds:g}",
                "--rounds", str(settings.viewer_rounds)]
        cmd = " ".join(["python -m benchmarks.bench_viewer", *argv])
        with PeakRss() as rss:
            raw["viewer"] = summary = bench_viewer.main(argv)
        peaks = rss.peaks(simserver_role)
        raw["viewer_peak_rss_kib"] = peaks
        rows += lateness_rows(summary, "live viewer", cmd)
        for name, label in (("view (viewer save)", "viewer process peak RSS, saving to .rrd"),
                            ("view (viewer connect)",
                             "viewer process peak RSS, stalled viewer")):
            if name in peaks:
                rows.append(Row(f"{label} ({settings.viewer_seconds:g} s)",
                                _mib(peaks[name]), "python -m benchmarks --only viewer" + suffix))

    if "ros2" in sections:  # measured as the viewer's is (benchmarks.interleaved)
        print("== bench_ros2", flush=True)
        argv = list(settings.ros2_args)
        cmd = " ".join(["python -m benchmarks.bench_ros2", *argv])
        raw["ros2"] = summary = bench_ros2.main(argv)
        rows += lateness_rows(summary, "ROS 2 adapter", cmd)

    if "tls_front" in sections:  # issue 14: the accept-filtering front's cost over TLS
        print("== bench_tls_front", flush=True)
        from benchmarks import bench_tls_front

        argv = ["--seconds", f"{settings.viewer_seconds / 3:g}",
                "--rounds", str(2 * settings.viewer_rounds - 1)]
        cmd = " ".join(["python -m benchmarks.bench_tls_front", *argv])
        raw["tls_front"] = r = bench_tls_front.main(argv)
        d, f = r["summary"]["direct"], r["summary"]["front"]
        rows.append(Row("command-to-state latency over TLS p50 / p99, zenoh direct vs "
                        "behind the TLS front", f"{d['p50_us']:.0f} / {d['p99_us']:.0f} us vs "
                        f"{f['p50_us']:.0f} / {f['p99_us']:.0f} us", cmd))
        if r["hop"] is not None:
            h = r["hop"]
            rows.append(Row("TLS front alone: round-trip time it adds, p50 / p99 (320 B "
                            "ping-pong)", f"{h['added_p50_us']:+.0f} / {h['added_p99_us']:+.0f}"
                            " us", cmd))

    if "multicar" in sections:  # issue 30: several cars in one live world
        print("== bench_multicar", flush=True)
        from benchmarks import bench_multicar

        argv = list(settings.multicar_args)
        cmd = " ".join(["python -m benchmarks.bench_multicar", *argv])
        raw["multicar"] = results = bench_multicar.main(argv)
        for n, hogs in ((8, True), (1, True), (32, False), (1, False)):
            w = bench_multicar.worst(results, n, hogs)
            if w is None:
                continue
            clients = min(n, len(bench_multicar.DRIVEN))
            where = (f"{n} car{'s' if n > 1 else ''}, {clients} driven by client process"
                     f"{'es' if clients > 1 else ''}" + (
                         f", beside {w['hogs']} CPU hogs" if hogs else ", quiet")
                     + f"; worst of {w['rounds']}")
            p99 = " / ".join("n/a" if w[f"{c}_p99_us"] is None else f"{w[f'{c}_p99_us']:.0f}"
                             for c in bench_multicar.DRIVEN[:min(n, 2)])
            baseline = n == 1
            rows.append(Row(f"live world: ticks > 1 ms late; command-to-state p99 "
                            f"({'the baseline: ' if baseline else ''}{where})",
                            f"{w['late_percent']:.2f} %; {p99} us", cmd,
                            "" if baseline else "<= 0.5 %" + ("; <= 1500 us" if hogs else "")))

    if "startup" in sections:
        print("== start-up", flush=True)
        python = settings.startup_python or sys.executable
        raw["startup"] = s = startup(settings.startup_cold, settings.startup_warm, python)
        cmd = "python -m benchmarks --only startup" + suffix
        where = ""
        if settings.startup_python:
            cmd += f" --python {settings.startup_python}"
            where = f", run by {settings.startup_python}"
        rows.append(Row(f"start-up to ready, cold numba cache (median of {len(s['cold_s'])}"
                        f"{where})",
                        f"{s['cold_median_s']:.2f} s ({s['cold_median_cpu_s']:.1f} s CPU)",
                        cmd, "<= 15 s"))
        rows.append(Row(f"start-up to ready, warm numba cache (median of {len(s['warm_s'])}"
                        f"{where})",
                        f"{s['warm_median_s']:.2f} s ({s['warm_median_cpu_s']:.2f} s CPU)",
                        cmd, "<= 0.6 s"))
        for name, runs in s["headless_s"].items():
            rows.append(Row(f"warm {name}, launch to exit (median of {len(runs)}{where})",
                            f"{s['headless_median_s'][name]:.2f} s "
                            f"({s['headless_median_cpu_s'][name]:.2f} s CPU; runs: "
                            + ", ".join(f"{x:.2f}" for x in runs) + ")", cmd,
                            HEADLESS_TARGETS.get(name, "")))
        from benchmarks import bench_compile

        raw["compile"] = c = bench_compile.measure(1, 0, bench_compile.DEFAULT_SCENE)["cold"]
        rows.append(Row("cold compile of the physics alone, wall (CPU): imports, "
                        "Simulation.warm_up and tire_forces / of which the step",
                        f"{c['total']['wall_s']:.1f} "
                        f"({c['total']['cpu_s']:.1f}) s / {c['step']['wall_s']:.1f} "
                        f"({c['step']['cpu_s']:.1f}) s", "python -m benchmarks.bench_compile"))

    if "memory" in sections:
        print("== headless run", flush=True)
        raw["headless"] = h = headless_run()
        cmd = "python -m benchmarks --only memory" + suffix
        rows.append(Row("headless run peak RSS (README's E2 example, Parquet and plots)",
                        _mib(h["peak_rss_kib"]), cmd))
        if h["real_time_factor"] is not None:
            rows.append(Row("headless run-scenario real-time factor (E2, 10 s simulated)",
                            f"{h['real_time_factor']:,.0f} x",
                            f"simserver run-scenario {HEADLESS_SCENARIO} --out out/e2"))
    if "image" in sections:
        print("== the container image's start", flush=True)
        if quick:
            print("not in a --quick run (building the image's environment takes minutes): "
                  "python -m benchmarks --only image", flush=True)
        else:
            from benchmarks import bench_image

            raw["image"] = r = bench_image.main(["--starts", str(settings.startup_cold)])
            rows.append(Row(f"start-up to ready from the container image's environment, its "
                            f"pre-compiled cache (median of {len(r['ready_s'])})",
                            f"{r['ready_median_s']:.2f} s ({r['cpu_median_s']:.2f} s CPU; "
                            "runs: " + ", ".join(f"{x:.2f}" for x in r["ready_s"])
                            + f"; environment built in {r['build_s']:.0f} s)",
                            "python -m benchmarks.bench_image", "< 2 s"))

    if "suite" in sections:
        print("== the test suite", flush=True)
        if settings.suite_runs:
            raw["suite"] = r = suite_time(settings.suite_runs)
            runs = r["runs"]
            rows.append(Row(f"the README's test command, cold numba cache (median of "
                            f"{len(runs)}, run now)", f"{r['median_s']:.0f} s (runs: "
                            + ", ".join(f"{x['wall_s']:.0f} s" + ("" if x["returncode"] == 0
                                        else f" exit {x['returncode']}") for x in runs)
                            + f"; CPU {statistics.median(x['cpu_s'] for x in runs):.0f} s"
                            + f"; {runs[-1]['closing']}; load average "
                            + ", ".join(f"{x['loadavg_1min_start']:.1f}-"
                                        f"{x['loadavg_1min_end']:.1f}" for x in runs) + ")",
                            f"python -m benchmarks --only suite --run-suite {len(runs)}",
                            "<= 300 s"))
        else:
            raw["suite"] = r = recorded_suite_runs()
            rows.append(suite_record_row(r))
        # the slowest tests of the last recorded run (a --run-suite run records itself too):
        # where the suite's time goes, before and after a change (issue 33 item 3)
        from tests import suite_record

        last = suite_record.read()[-1:]
        if last:
            raw["suite"]["slowest_of_last_run"] = last[0].get("slowest")
            raw["suite"]["most_cpu_of_last_run"] = last[0].get("most_cpu")
            print("the last recorded run of the README's test command (python -m "
                  "tests.suite_record prints every recorded run):\n"
                  + suite_record.describe(last[0]), flush=True)
    report.machine["load average at end"] = " / ".join(
        f"{x:.2f}" for x in os.getloadavg()) + " (1/5/15 min)"
    return report


def render(report: Report, sections: list[str]) -> str:
    """The markdown document: machine, table, method."""
    lines = ["# Performance", ""]
    if report.mode == "quick":
        lines += ["> **Quick run** (`python -m benchmarks --quick`): short runs for a smoke "
                  "test. These are not the published figures: regenerate with "
                  "`python -m benchmarks` on a quiet machine.", ""]
    lines += ["Generated by `python -m benchmarks"
              + (" --quick" if report.mode == "quick" else "")
              + "".join(f" --only {s}" for s in sections if len(sections) < len(SECTIONS))
              + "`; every figure can be reproduced on its own by the command beside it.",
              "", "## Machine", ""]
    lines += [f"- **{k}**: {v}" for k, v in report.machine.items()]
    lines += ["", "## Figures", "", *TABLE_HEADER]
    lines += [r.markdown() for r in report.rows]
    lines += [
        "", "## Method", "",
        "- Step cost: the compiled `simulate` loop over a driving cycle (accelerate and "
        "steer, brake to rest, hold), after compilation; real-time factor = 1 ms / median "
        "step cost.",
        "- CommonRoad: `commonroad-vehicle-models`' multi-body model (`vehicle_dynamics_mb`, "
        "pure Python) with classic RK4 at our 1 ms step, in the benchmark's own virtual "
        "environment (`.bench-venv/commonroad/`, made on first use); rounds interleaved with "
        "our compiled step, both timed by process CPU time; ratio of the medians. Its state "
        "in two forms: a numpy array (as a numpy RK4 or scipy's integrators pass it; its cost "
        "matches issue 16's 227 us a step, so the target is judged against it) and a list of "
        "Python floats (the fastest form, about 2.7 x faster).",
        "- Server: `simserver serve` in its own process, state published every tick, driven "
        "at 200 Hz over zenoh on loopback. Lateness p50/p99: median over the server's "
        "4096-tick diagnostic windows; max, late ticks, overruns: the whole run. Latency: "
        "command sent to the first state that reflects it, on the shared monotonic clock, "
        "each command sent at a random offset (uniform over one tick) in its 5 ms slot: a "
        "driver's clock has no fixed phase to the server's ticks.",
        "- Busy machine: the server run beside two CPU-bound Python processes at normal "
        "priority (`--hogs 2`); the server and the benchmark's client use their default "
        "real-time scheduling (SCHED_FIFO where permitted, `simserver serve --realtime`; "
        "the server also holds `/dev/cpu_dma_latency` at 0 where permitted). The server puts "
        "a state in the tick while puts are cheap and hands it to its `state-tx` thread "
        "otherwise (the share is in the table).",
        "- Load: `benchmarks.bench_load`: a driver at 1 kHz, 20 state subscribers (each its "
        "own zenoh session) checking every tick arrives, and 10 sessions a second joining "
        "(state subscription, `get_config`) and leaving a second later; late ticks from the "
        "server's diagnostics over the loaded period. Their causes from the server's tick "
        "trace (`SIMSERVER_TICK_TRACE`, `simserver.server.realtime.TickTrace`: per tick the tick "
        "thread's CPU time, run-queue wait and switches from `/proc/thread-self/schedstat`, "
        "the pacer's sleep, GC): per episode of late ticks, the time in the ticks' own CPU, "
        "in run-queue waits (other processes at its priority or above), blocked in the work "
        "(never switched out: the vCPU not running), and the sleeps' overshoot.",
        "- Hostile loads: `benchmarks.bench_load --hostile`: a driver at 1 kHz and a state "
        "subscriber stamping each state's arrival; per round a 1 s no-load window, then each "
        "`load` (10 MB scene, alias bomb, deep nesting, FIFO, two OpenDRIVE terrains, flat) "
        "and `reset` at 1 and 20 m/s from request to reply + 0.1 s; the largest gap between "
        "two states received (1 ms when nothing stalls) and the server's worst tick lateness. "
        "The baseline windows show what the machine stalls by itself. The stalls are split "
        "by whose they are: the server's tick trace gives the gaps between tick starts and "
        "per tick the server's own part (its CPU time, and waits for the GIL or a lock after "
        "being switched out) apart from run-queue waits and the VM's (blocked while never "
        "switched out, sleeps returning late with no other wake-up); the bare pacer "
        "(`benchmarks.bench_clock`) runs beside it in a process of its own as a peer that "
        "the VM's stalls delay too.",
        "- Clock floor of the server rows: `benchmarks.bench_server` runs the bare pacer, "
        "scheduled as the tick thread and beside the same hogs, 10 s just before and after "
        "the server (`--floor-seconds`): the VM's own lateness in the same minutes.",
        "- Live world (issue 30): `benchmarks.bench_multicar`: `simserver serve` with n cars on "
        "the crest-curve road, `car0` and `car1` driven by client processes (their own zenoh "
        "sessions, commands at 200 Hz each at a random instant of its slot), the others by "
        "the built-in driver; late ticks over the whole run from the server's `stopped` "
        "line, each driven car's command-to-state p99 as the server rows'; the worst of the "
        "rounds; 1-car runs of the same command beside them are the machine's baseline.",
        "- Start-up: launch of `python -m simserver serve --viewer off` to its `ready` line "
        "(kernels compiled or loaded, zenoh open, before the first tick), and the server's "
        "CPU seconds at that line (`/proc/PID/stat`; on a shared machine the steadier "
        "figure). Cold: `NUMBA_CACHE_DIR` and `SIMSERVER_CACHE_DIR` an empty directory "
        "(Python's bytecode cache on, as a user has it: a `PYTHONDONTWRITEBYTECODE` of the "
        "benchmark's shell is not passed on, so only the first cold start compiles "
        "simserver's sources); warm: the same directory again (the image's "
        "start: every kernel from the cache). Where a cold compile goes: "
        "`python -m benchmarks.bench_compile --warm 0 --by-function 25`. Headless commands: "
        "`python -m simserver run-scenario` (E2, "
        "with and without `--no-plots`) and `tire-curves` from launch to exit with that warm "
        "cache (one unmeasured run first), interleaved, median of the repeats, with their "
        "CPU seconds (the process and its children); interleaved with them numba's floor, "
        "`python -c` importing numba and initialising the CPU target that numba's cache "
        "initialises before it loads a first kernel (scipy.linalg included, through "
        "numba's BLAS check, where scipy is installed): every warm path that runs a "
        "kernel pays it before simserver's own imports and work. Rows \"run by PATH\" "
        "(`--python PATH`) ran every command with that interpreter: the README's "
        "`.venv` holds the project's dependencies only, while this machine's shared "
        "interpreter also has scipy, which numba imports at start when it is there.",
        "- Test suite: the README's test command. The row reads the last three recorded "
        "runs of it (each run of the whole default suite appends its wall and CPU time, "
        "whether the kernel cache was empty at its start, the commit and the load: "
        "`tests/suite_record.py`); `--run-suite N` runs it N times in the benchmark's own "
        "run instead, each with `NUMBA_CACHE_DIR` and `SIMSERVER_CACHE_DIR` an empty "
        "directory (the cold compile a fresh clone pays is included).",
        "- Container image: `python -m benchmarks.bench_image` builds the image's "
        "environment without a container engine (the Dockerfile's own COPY, ENV, WORKDIR and "
        "RUN steps below a scratch root, as `tests/test_dockerfile.py` does: `pip install .` "
        "in a fresh venv, the warm-up pre-compiling every kernel into the image's "
        "`SIMSERVER_CACHE_DIR`) and times its ENTRYPOINT + CMD to `ready`; a start that "
        "compiles or writes to the cache is an error.",
        "- Memory: peak resident set (`VmHWM`, sampled once a second from "
        "`/proc/PID/status`) of the server during the server run, and `ru_maxrss` of the "
        "headless run.",
        "- This is a shared VM: it stalls 0.3-0.7 % of 1 ms periods by itself "
        "(`python -m benchmarks.bench_clock` measures that floor). Compare runs by their "
        "medians, and look at the load average above.",
        "",
    ]
    return "\n".join(lines)


def readme_block(report: Report) -> str:
    """The README's performance section body: the machine in one line, then the table."""
    m = report.machine
    lines = [README_BEGIN, "",
             f"Measured {m['date']} on {m['nproc']} vCPUs ({m['CPU']}, {m['RAM']}), "
             f"Python {m['Python'].split()[0]}, commit {m['commit']}; load average "
             f"{m['load average at start'].split(' (')[0]} at the start. The whole table, "
             "with the method: [docs/performance.md](docs/performance.md).", "",
             *TABLE_HEADER, *(r.markdown() for r in report.rows), "", README_END]
    return "\n".join(lines)


def merge_rows(text: str, rows: list[Row]) -> str:
    """``text`` (a document with the performance table) with the rows of the same figure
    replaced by ``rows`` and the new ones appended to the table: a partial run
    (``--only ... --merge``) refreshes its own rows and keeps the others."""
    lines = text.split("\n")
    try:
        start = lines.index(TABLE_HEADER[1]) + 1
    except ValueError:
        raise SystemExit("the performance table is missing") from None
    end = start
    while end < len(lines) and lines[end].startswith("| "):
        end += 1
    fresh = {r.figure: r.markdown() for r in rows}
    table = [fresh.pop(line.split(" | ")[0][2:], line) for line in lines[start:end]]
    return "\n".join(lines[:start] + table + list(fresh.values()) + lines[end:])


def update_readme(text: str, block: str) -> str:
    """``text`` with its performance block replaced by ``block``."""
    try:
        head, rest = text.split(README_BEGIN, 1)
        _, tail = rest.split(README_END, 1)
    except ValueError:
        raise SystemExit(f"{README}: the performance markers are missing") from None
    return head + block + tail


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmarks, print the table, write it; return every raw result."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="short runs for a smoke test (about 2 minutes)")
    parser.add_argument("--only", action="append", choices=SECTIONS, default=None,
                        help="run only this benchmark (repeatable)")
    parser.add_argument("--out", type=Path, default=None, metavar="FILE",
                        help=f"markdown file to write (default {DEFAULT_OUT.relative_to(REPO)} "
                             "for a full run of every benchmark; none for --quick or --only)")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE",
                        help="also write every raw result as JSON")
    parser.add_argument("--merge", action="store_true",
                        help="with --only: put this run's rows into the README's table and "
                             f"{DEFAULT_OUT.relative_to(REPO)} (same figure replaced, new "
                             "ones appended), keeping the other rows")
    parser.add_argument("--run-suite", type=int, default=0, metavar="N",
                        help="run the README's test command N times now, each from an empty "
                             "kernel cache (default: the suite row reads the last recorded "
                             "runs of that command, tests/suite_record.py)")
    parser.add_argument("--python", default=None, metavar="PATH",
                        help="run the start-up section's commands with this interpreter, "
                             "for example the README's .venv/bin/python (an environment with "
                             "the project's dependencies only; this one may hold more, such "
                             "as scipy, which numba imports at start when it is there); its "
                             "rows say so (default: this interpreter)")
    args = parser.parse_args(argv)
    sections = [s for s in SECTIONS if args.only is None or s in args.only]
    settings = dataclasses.replace(QUICK if args.quick else FULL, suite_runs=args.run_suite,
                                   startup_python=args.python)
    t0 = time.monotonic()
    report = run_all(settings, sections, args.quick)
    text = render(report, sections)
    print()
    print(text)
    out = args.out
    if out is None and not args.quick and args.only is None:
        out = DEFAULT_OUT
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text, encoding="utf-8")
        print(f"wrote {out}")
    if out == DEFAULT_OUT:
        README.write_text(update_readme(README.read_text(encoding="utf-8"),
                                        readme_block(report)), encoding="utf-8")
        print(f"wrote the performance block of {README}")
    elif args.merge and not args.quick:
        for path in (README, DEFAULT_OUT):
            path.write_text(merge_rows(path.read_text(encoding="utf-8"), report.rows),
                            encoding="utf-8")
            print(f"merged {len(report.rows)} rows into {path}")
    result = {"machine": report.machine, "mode": report.mode, "rows": [vars(r) for r in
              report.rows], "raw": report.raw, "wall_s": time.monotonic() - t0}
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2, default=str) + "\n", encoding="utf-8")
        print(f"wrote {args.json}")
    print(f"benchmarks: {time.monotonic() - t0:.0f} s", flush=True)
    return result


if __name__ == "__main__":
    main()
