"""Before/after comparison of the physics, bit for bit: a sha256 per run of every array it
produced, written once from a reference tree and compared against from another.

Run from the repository root::

    python -m benchmarks.bit_compare --write digests.json [--soak-seconds S]
    python -m benchmarks.bit_compare --compare digests.json [--soak-seconds S]

The runs (issue 29's acceptance: one car gives the same bits after the world redesign):

- every single-car scenario in ``configs/scenarios`` (its recorded states, outputs and
  inputs and its final state; a scenario of several cars is checked against its cars run
  alone by ``tests/test_world_scenario.py``);
- the terrain scenes (a height map, two OpenDRIVE roads) and the MF 6.1 car, each driven
  by a short keyframed run, so the terrain and MF paths of the step are covered too;
- the seeded soak (``simserver.sim.soak.run_soak``, seed 11; every chunk's states and outputs
  are hashed as ``Simulation.run`` returns them);
- the first release's command-log replay (``tests/data/first_release_live.cmdlog``).

To record a reference from another tree (e.g. a worktree of ``main``), run this file with
that tree first on ``PYTHONPATH``: the digests come from whichever ``simserver`` is
imported. ``--compare`` exits 1 and names each run whose digest differs or is missing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SOAK_SEED = 11
# a short drive for the scenes that are not scenarios (pull away, steer, brake, hold)
SCENE_DRIVE = [{"t": 0.0, "throttle": 0.0, "brake": 0.0, "steer": 0.0, "gear": "D"},
               {"t": 0.5, "throttle": 0.4, "steer": 0.1},
               {"t": 3.0, "throttle": 0.0, "brake": 0.5, "steer": -0.1},
               {"t": 6.0, "brake": 0.5}]
SCENE_RUNS = {
    "scene:hills_paper_sedan": "configs/scenes/hills_paper_sedan.yaml",
    "scene:crest_curve_paper_sedan": "configs/scenes/crest_curve_paper_sedan.yaml",
    "scene:curves_elevation_paper_sedan": "configs/scenes/curves_elevation_paper_sedan.yaml",
    "scene:flat_mf_hatchback": "configs/scenes/flat_mf_hatchback.yaml",
    "scene:hill_10pct_paper_sedan_automatic":
        "configs/scenes/hill_10pct_paper_sedan_automatic.yaml",
}


def digest(*arrays: np.ndarray) -> str:
    """sha256 over the arrays' shapes and float64 bytes, in order."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def scenario_digest(path: Path, data: dict | None = None) -> str:
    from simserver.sim.scenario import load_scenario, run_scenario

    r = run_scenario(load_scenario(path, data))
    return digest(r.states, r.outputs, r.inputs, r.final_state)


def scene_digest(path: Path) -> str:
    from simserver.adapters.config import read_yaml

    data = dict(read_yaml(path))
    data.update(duration_s=8.0, record_every=1, inputs=SCENE_DRIVE)
    data.setdefault("name", path.stem)
    return scenario_digest(path, data)


@contextmanager
def hashing_runs() -> Iterator[hashlib._Hash]:
    """While inside: every ``Simulation.run`` feeds its states and outputs to the yielded
    hash after it returns."""
    from simserver.sim.simulation import Simulation

    h = hashlib.sha256()
    original = Simulation.run

    def run(self, inputs_per_step, states, outputs, record_every=1):  # noqa: ANN001
        original(self, inputs_per_step, states, outputs, record_every)
        h.update(np.ascontiguousarray(states).tobytes())
        h.update(np.ascontiguousarray(outputs).tobytes())

    Simulation.run = run
    try:
        yield h
    finally:
        Simulation.run = original


def soak_digest(seconds: float) -> str:
    from simserver.sim.scene import load_scene
    from simserver.sim.soak import run_soak

    scene = load_scene(REPO / "configs/scenes/flat_paper_sedan.yaml")
    with hashing_runs() as h:
        report = run_soak(scene, seconds, seed=SOAK_SEED)
    h.update(repr((report.steps, [v.name for v in report.violations])).encode())
    return h.hexdigest()


def replay_digest() -> str:
    from simserver.server.command_log import replay_command_log

    cwd = os.getcwd()
    os.chdir(REPO)  # the log's scene paths are relative to the repository
    try:
        rep = replay_command_log(REPO / "tests/data/first_release_live.cmdlog")
    finally:
        os.chdir(cwd)
    return digest(rep.final_state, np.array([rep.steps], dtype=np.float64))


def runs(soak_seconds: float) -> dict[str, Callable[[], str]]:
    """Every run by name, each a function giving its digest."""
    table: dict[str, Callable[[], str]] = {}
    for path in sorted((REPO / "configs/scenarios").glob("*.yaml")):
        if "\ncars:" in path.read_text():  # several cars: no single-car reference
            continue
        table[f"scenario:{path.stem}"] = lambda p=path: scenario_digest(p)
    for name, rel in SCENE_RUNS.items():
        table[name] = lambda p=REPO / rel: scene_digest(p)
    table[f"soak:seed{SOAK_SEED}:{soak_seconds:g}s"] = lambda: soak_digest(soak_seconds)
    table["replay:first_release_live"] = replay_digest
    return table


def compare(reference: dict[str, str], now: dict[str, str]) -> list[str]:
    """The names whose digest differs from the reference's (a run the reference lacks, a
    scenario shipped after it, is not a difference: ``new_runs``)."""
    return [f"{name}: differs" for name, value in now.items()
            if name in reference and reference[name] != value]


def new_runs(reference: dict[str, str], now: dict[str, str]) -> list[str]:
    """The runs the reference has no digest for (nothing to compare them with)."""
    return [name for name in now if name not in reference]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--write", type=Path, help="write the digests to this JSON file")
    what.add_argument("--compare", type=Path, help="compare against this JSON file")
    parser.add_argument("--soak-seconds", type=float, default=3600.0,
                        help="simulated seconds of the seed-11 soak (acceptance: 3600)")
    parser.add_argument("--only", default="", help="run only the names containing this")
    args = parser.parse_args(argv)
    import simserver

    print(f"simserver from {Path(simserver.__file__).parent}", flush=True)
    now = {}
    for name, fn in runs(args.soak_seconds).items():
        if args.only in name:
            now[name] = fn()
            print(f"{name}: {now[name][:16]}", flush=True)
    if args.write:
        old = json.loads(args.write.read_text()) if args.write.exists() else {}
        args.write.write_text(json.dumps(old | now, indent=1, sort_keys=True) + "\n")
        return 0
    reference = json.loads(args.compare.read_text())
    bad = compare(reference, now)
    for line in bad:
        print(f"DIFFERS {line}")
    new = new_runs(reference, now)
    for name in new:
        print(f"NEW {name}: not in the reference, not compared")
    print(f"{len(now) - len(new) - len(bad)} of {len(now) - len(new)} runs bit-identical to "
          f"{args.compare} ({len(new)} new)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
