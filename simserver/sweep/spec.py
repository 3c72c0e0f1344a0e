"""The sweep file: base scenarios, the parameters to vary, the metrics -> a list of cases.

::

    name: relaxation_study
    description: free text
    scenarios: [../scenarios/e2_stop_downslope_paper_damping.yaml]   # files or globs
    grid:                         # every combination (or ``cases:`` or ``random:``)
      vehicle.tires.*.relaxation_length_long_m: {from: 0.02, to: 0.3, num: 15}
      vehicle.tires.*.relaxation_length_lat_m: [0.3, 0.9, 1.5]
    # cases: [{road.grade_pct: -5}, {road.grade_pct: 5, model.damping_ratio: 0.5}]
    # random: {seed: 1, samples: 100, ranges: {road.grade_pct: [-30, 30]}}
    metrics: [stopping_distance, time_to_rest, {column: u_mps, stat: min}]
    histories: false              # optional: write each run's history.parquet

A soak sweep (``kind: soak``) runs ``simserver.soak.run_soak`` on each base (a scene or
a scenario file, of which only the scene counts) for every seed 0 .. seeds-1::

    kind: soak
    scenarios: [../scenes/flat_paper_sedan.yaml, ../scenes/flat_mf_hatchback.yaml]
    soak: {duration_s: 300, seeds: 32}

Its metrics are the soak's own (``worker.SOAK_METRICS``); the seed is the parameter
``soak.seed`` and, like the duration, part of the run's resolved configuration.

Paths are relative to the sweep file; parameters are dotted paths into a run's resolved
configuration (``simserver.sweep.resolved``). Every base scenario is run with every
parameter set; with no ``grid``/``cases``/``random`` each base scenario runs once.
"""

from __future__ import annotations

import glob
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.history import HISTORY_COLUMNS
from simserver.adapters.validate import ConfigError, check_keys, number, read_yaml
from simserver.scenario import resolve_scenario
from simserver.sweep.metrics import Metric, parse_metrics
from simserver.sweep.resolved import run_id, with_overrides

KEYS = ("name", "description", "kind", "scenarios", "grid", "cases", "random", "metrics",
        "histories", "soak")
KINDS = ("scenario", "soak")
SOAK_KEYS = ("duration_s", "seeds")
MAX_RUNS = 1_000_000


@dataclass
class Case:
    """One run of a sweep: a base scenario with parameter values, resolved."""

    index: int
    base: str  # the base scenario file
    params: dict[str, Any]
    resolved: dict[str, Any] | None  # None when the overrides did not apply
    run_id: str
    error: str = ""  # why ``resolved`` is None


@dataclass
class Sweep:
    name: str
    description: str
    path: Path
    parameters: tuple[str, ...]  # the varied dotted paths, in file order
    metrics: tuple[Metric, ...]
    histories: bool
    cases: list[Case]


def _values(origin: str, key: str, spec: Any) -> list[Any]:
    if isinstance(spec, list) and spec:
        return list(spec)
    if isinstance(spec, dict):
        check_keys(f"{origin} (grid.{key})", spec, ("from", "to", "num"),
                   required=("from", "to", "num"))
        lo = number(origin, f"grid.{key}.from", spec["from"], -1e12, 1e12)
        hi = number(origin, f"grid.{key}.to", spec["to"], -1e12, 1e12)
        num = spec["num"]
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise ConfigError(f"{origin}: key 'grid.{key}.num': expected a positive integer")
        return [float(v) for v in np.linspace(lo, hi, num)]
    raise ConfigError(f"{origin}: key 'grid.{key}': expected a non-empty list or "
                      f"{{from, to, num}}")


def parameter_sets(origin: str, data: dict[str, Any]) -> list[dict[str, Any]]:
    """The parameter sets of the file's ``grid``, ``cases`` or ``random`` (one of them)."""
    given = [k for k in ("grid", "cases", "random") if k in data]
    if len(given) > 1:
        raise ConfigError(f"{origin}: give one of 'grid', 'cases', 'random', not "
                          f"{' and '.join(given)}")
    if not given:
        return [{}]
    if "grid" in data:
        grid = data["grid"]
        if not isinstance(grid, dict) or not grid:
            raise ConfigError(f"{origin}: key 'grid': expected a mapping of parameters")
        axes = [_values(origin, str(k), v) for k, v in grid.items()]
        return [dict(zip(map(str, grid), combo, strict=True))
                for combo in itertools.product(*axes)]
    if "cases" in data:
        cases = data["cases"]
        if not isinstance(cases, list) or not cases or not all(isinstance(c, dict)
                                                                for c in cases):
            raise ConfigError(f"{origin}: key 'cases': expected a list of mappings")
        return [{str(k): v for k, v in c.items()} for c in cases]
    rnd = data["random"]
    if not isinstance(rnd, dict):
        raise ConfigError(f"{origin}: key 'random': expected a mapping")
    check_keys(f"{origin} (random)", rnd, ("seed", "samples", "ranges"),
               required=("seed", "samples", "ranges"))
    seed, samples, ranges = rnd["seed"], rnd["samples"], rnd["ranges"]
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{origin}: key 'random.seed': expected a non-negative integer")
    if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= MAX_RUNS:
        raise ConfigError(f"{origin}: key 'random.samples': expected a positive integer")
    if not isinstance(ranges, dict) or not ranges:
        raise ConfigError(f"{origin}: key 'random.ranges': expected a mapping path: [lo, hi]")
    bounds = []
    for key, r in ranges.items():
        if not (isinstance(r, list) and len(r) == 2):
            raise ConfigError(f"{origin}: key 'random.ranges.{key}': expected [lo, hi]")
        lo = number(origin, f"random.ranges.{key}[0]", r[0], -1e12, 1e12)
        hi = number(origin, f"random.ranges.{key}[1]", r[1], lo, 1e12)
        bounds.append((str(key), lo, hi))
    rng = np.random.default_rng(seed)
    draws = rng.uniform(size=(samples, len(bounds)))
    return [{key: float(lo + (hi - lo) * draws[i, j]) for j, (key, lo, hi) in enumerate(bounds)}
            for i in range(samples)]


def load_sweep(path: str | Path) -> Sweep:
    """Read and validate a sweep file and expand it into resolved cases."""
    path = Path(path)
    data = read_yaml(path)
    kind = data.get("kind", "scenario")
    if kind not in KINDS:
        raise ConfigError(f"{path}: key 'kind': expected one of {', '.join(KINDS)}")
    check_keys(path, data, KEYS,
               required=("scenarios", "soak") if kind == "soak" else ("scenarios", "metrics"))
    origin = str(path)
    soak: dict[str, Any] | None = None
    if kind == "soak":
        if "metrics" in data:
            raise ConfigError(f"{origin}: key 'metrics': a soak sweep's metrics are the "
                              f"soak's own")
        if not isinstance(data["soak"], dict):
            raise ConfigError(f"{origin}: key 'soak': expected {{duration_s, seeds}}")
        check_keys(f"{origin} (soak)", data["soak"], SOAK_KEYS, required=SOAK_KEYS)
        seeds = data["soak"]["seeds"]
        if isinstance(seeds, bool) or not isinstance(seeds, int) or not 1 <= seeds <= MAX_RUNS:
            raise ConfigError(f"{origin}: key 'soak.seeds': expected a positive integer")
        soak = {"duration_s": number(origin, "soak.duration_s", data["soak"]["duration_s"],
                                     0.01, 1e7), "seed": 0}
    elif "soak" in data:
        raise ConfigError(f"{origin}: key 'soak': only with 'kind: soak'")
    scen = data["scenarios"]
    scen = [scen] if isinstance(scen, str) else scen
    if not isinstance(scen, list) or not scen or not all(isinstance(s, str) for s in scen):
        raise ConfigError(f"{origin}: key 'scenarios': expected a list of files or globs")
    bases: list[Path] = []
    for pattern in scen:
        full = str(path.parent / pattern)
        found = sorted(glob.glob(full)) if glob.has_magic(pattern) else [full]
        if not found:
            raise ConfigError(f"{origin}: key 'scenarios': {pattern!r} matches no file")
        bases += [Path(f) for f in found]
    sets = parameter_sets(origin, data)
    if soak is not None:
        sets = [{**params, "soak.seed": seed} for params in sets
                for seed in range(data["soak"]["seeds"])]
    if len(bases) * len(sets) > MAX_RUNS:
        raise ConfigError(f"{origin}: {len(bases) * len(sets)} runs, more than {MAX_RUNS}")
    parameters = tuple(dict.fromkeys(k for s in sets for k in s))
    metrics = () if soak is not None else parse_metrics(origin, data["metrics"],
                                                         HISTORY_COLUMNS)
    histories = data.get("histories", False)
    if not isinstance(histories, bool):
        raise ConfigError(f"{origin}: key 'histories': expected true or false")
    cases: list[Case] = []
    for base in bases:
        resolved_base = resolve_scenario(base)
        if soak is not None:
            resolved_base["soak"] = dict(soak)
        for params in sets:
            index = len(cases)
            where = f"{origin}: case {index} ({base.name})"
            try:
                resolved = with_overrides(resolved_base, params, where, path.parent)
            except ConfigError as exc:
                key = {"base": str(base), "params": params}
                cases.append(Case(index, str(base), params, None, run_id(key), str(exc)))
                continue
            cases.append(Case(index, str(base), params, resolved, run_id(resolved)))
    name = data.get("name", path.stem)
    return Sweep(name=str(name), description=str(data.get("description", "")), path=path,
                 parameters=parameters, metrics=metrics, histories=histories, cases=cases)
