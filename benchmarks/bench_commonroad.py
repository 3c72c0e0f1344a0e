"""Our vehicle step against CommonRoad's multi-body model with RK4, measured in one run.

Run from the repository root::

    python -m benchmarks.bench_commonroad [--rounds R] [--seconds S] [--steps N]

The peer: CommonRoad's multi-body vehicle model ("MB", ``vehicle_dynamics_mb`` of the
``commonroad-vehicle-models`` package: pure Python, 29 states, Pacejka tires), integrated
with classic RK4 at our step ``bench_step.DT_S`` (1 ms) by ``commonroad_env/mb_loop.py``,
with the state in two forms, both measured:

- ``array``: a numpy array, as a numpy RK4 or scipy's integrators pass it (every ``x[i]``
  the model reads a numpy scalar). Issue 16's figure for the peer, 227 us a step, is this
  form's cost (201-208 us here; the list form's is 72-77 us), so its 100 x target is judged
  against this form.
- ``list``: Python floats, the fastest way to call the model from Python (about 2.7 x
  faster than the array form); reported beside it, so that nobody reads the ratio as
  against the best the peer can do.

That package is not a dependency of simserver: on first use this benchmark creates its own
virtual environment, ``.bench-venv/commonroad/`` (git-ignored), with this interpreter's
``venv`` and installs ``commonroad_env/requirements.txt`` into it with pip; later runs
reuse it (and reinstall when the requirements file changes). If that fails (no registry,
no network) the result says so, with pip's last lines, and gives no figure.

Each round, interleaved so that all see the same machine: our step with each vehicle
(``bench_step.bench_vehicle``: the compiled loop over the driving cycle; MF 6.1 tires on
mf_hatchback, brush tires on paper_sedan), then CommonRoad's loop in its environment in
each state form. All are timed by their own process's CPU time (on a quiet machine the
same as the wall time; on a shared one it leaves out the time other processes held the
core). A ratio is CommonRoad's median cost per step over ours. Target (issue 16): at least
100 x with MF 6.1 tires, against the array form.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
import venv
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_step import DT_S, VEHICLES, bench_vehicle

REPO = Path(__file__).resolve().parents[1]
ENV_DIR = REPO / ".bench-venv" / "commonroad"
REQUIREMENTS = Path(__file__).resolve().parent / "commonroad_env" / "requirements.txt"
LOOP_SCRIPT = Path(__file__).resolve().parent / "commonroad_env" / "mb_loop.py"
STAMP = "simserver-requirements.txt"
"""Copy of the requirements the environment was made from (reinstalled when they change)."""
TARGET_RATIO_MF61 = 100.0
STATE_FORMS = ("array", "list")
"""CommonRoad's state forms, the first the one the target is judged against."""
MEASURED = (
    "per step, four calls of vehicle_dynamics_mb as shipped (29 states, parameters_vehicle2 "
    "built once before the loop, not per step) and the RK4 sums; process CPU time. Not "
    "included: building the parameters (tens of milliseconds a call in 3.0.2: OmegaConf). "
    "State forms: 'array', a numpy array as a numpy RK4 or scipy's integrators pass it (its "
    "cost matches issue 16's 227 us a step; the target is judged against it), and 'list', "
    "Python floats, the fastest form (versions 2.0.0 and 3.0.2 run the same right-hand side: "
    "1.05 and 1.04 million instructions a step under callgrind). Ours: the compiled simulate "
    "loop over the driving cycle, CPU time."
)
PIP_TIMEOUT_S = 900.0


class EnvironmentUnavailable(RuntimeError):
    """The benchmark's own environment could not be made (the reason is the message)."""


def _env_python(env_dir: Path) -> Path:
    return env_dir / "bin" / "python"


def ensure_environment(env_dir: Path = ENV_DIR) -> Path:
    """The Python of the benchmark's environment, made and installed on first use.

    Raises
    ------
    EnvironmentUnavailable
        If the environment cannot be created or the requirements cannot be installed.
    """
    python = _env_python(env_dir)
    wanted = REQUIREMENTS.read_text(encoding="utf-8")
    stamp = env_dir / STAMP
    if python.exists() and stamp.exists() and stamp.read_text(encoding="utf-8") == wanted:
        return python
    print(f"creating the CommonRoad environment {env_dir} (pip install -r "
          f"{REQUIREMENTS.relative_to(REPO)})", flush=True)
    try:
        venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
    except (OSError, subprocess.CalledProcessError) as exc:
        raise EnvironmentUnavailable(f"cannot create a virtual environment in {env_dir}: "
                                     f"{exc}") from exc
    try:
        done = subprocess.run([str(python), "-m", "pip", "install", "--disable-pip-version-check",
                               "-q", "-r", str(REQUIREMENTS)], capture_output=True, text=True,
                              timeout=PIP_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired as exc:
        raise EnvironmentUnavailable(f"pip install timed out after {PIP_TIMEOUT_S:.0f} s") from exc
    if done.returncode != 0:
        tail = " / ".join((done.stderr or done.stdout).strip().splitlines()[-3:])
        raise EnvironmentUnavailable(f"pip install -r {REQUIREMENTS.name} failed "
                                     f"(exit {done.returncode}): {tail}")
    stamp.write_text(wanted, encoding="utf-8")
    return python


def run_commonroad(python: Path, steps: int, repeats: int, state: str) -> dict[str, Any]:
    """CommonRoad's MB model with RK4 at ``DT_S``, the state in form ``state``
    (:data:`STATE_FORMS`): the loop script's JSON result."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    done = subprocess.run([str(python), str(LOOP_SCRIPT), "--dt", repr(DT_S), "--steps",
                           str(steps), "--repeats", str(repeats), "--state", state],
                          capture_output=True,
                          text=True, env=env, timeout=600.0, check=False)
    if done.returncode != 0:
        tail = " / ".join(done.stderr.strip().splitlines()[-3:])
        raise EnvironmentUnavailable(f"the CommonRoad loop failed (exit {done.returncode}): "
                                     f"{tail}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if not result["finite"]:
        raise EnvironmentUnavailable("the CommonRoad loop ended in a non-finite state")
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    parser.add_argument("--seconds", type=float, default=5.0,
                        help="simulated s per repeat of our step")
    parser.add_argument("--steps", type=int, default=1000, help="CommonRoad steps per repeat")
    args = parser.parse_args(argv)
    try:
        python = ensure_environment(ENV_DIR)
    except EnvironmentUnavailable as exc:
        print(f"CommonRoad comparison skipped: {exc}", flush=True)
        return {"skipped": str(exc)}
    ours: dict[str, list[float]] = {name: [] for name in VEHICLES}
    theirs: dict[str, list[float]] = {state: [] for state in STATE_FORMS}
    package = ""
    t0 = time.monotonic()
    try:
        for _ in range(args.rounds):
            for name, path in VEHICLES.items():
                ours[name] += list(bench_vehicle(path, args.seconds, 3, time.process_time_ns))
            for state in STATE_FORMS:
                result = run_commonroad(python, args.steps, 3, state)
                theirs[state] += result["cpu_us_per_step"]
                package = result["package"]
    except EnvironmentUnavailable as exc:
        print(f"CommonRoad comparison skipped: {exc}", flush=True)
        return {"skipped": str(exc)}
    theirs_us = {state: float(np.median(costs)) for state, costs in theirs.items()}
    out: dict[str, Any] = {"package": package, "commonroad_us_per_step": theirs_us,
                           "commonroad_us_all": theirs, "rounds": args.rounds,
                           "wall_s": time.monotonic() - t0, "ours": {}}
    for state in STATE_FORMS:
        print(f"CommonRoad MB + RK4 ({package}, dt {DT_S * 1e3:g} ms, {state} state): "
              f"{theirs_us[state]:8.1f} us per step (CPU time, median of "
              f"{len(theirs[state])})")
    print(f"  measured: {MEASURED}")
    judged = STATE_FORMS[0]
    for name, costs in ours.items():
        us = float(np.median(costs)) / 1e3
        ratios = {state: theirs_us[state] / us for state in STATE_FORMS}
        out["ours"][name] = {"us_per_step": us, "ratio": ratios}
        target = (f" (target >= {TARGET_RATIO_MF61:.0f} x against the {judged} form)"
                  if name.startswith("mf61") else "")
        print(f"ours, {name:22s}: {us:8.2f} us per step -> "
              + ", ".join(f"{ratios[state]:6.0f} x ({state})" for state in STATE_FORMS)
              + f" CommonRoad's rate{target}")
    return out


if __name__ == "__main__":
    main()
