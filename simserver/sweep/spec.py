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

A soak sweep (``kind: soak``) runs ``simserver.sim.soak.run_soak`` on each base (a scene or
a scenario file, of which only the scene counts) for every seed 0 .. seeds-1::

    kind: soak
    scenarios: [../scenes/flat_paper_sedan.yaml, ../scenes/flat_mf_hatchback.yaml]
    soak: {duration_s: 300, seeds: 32}

Its metrics are the soak's own (``worker.SOAK_METRICS``); the seed is the parameter
``soak.seed`` and, like the duration, part of the run's resolved configuration.

Paths are relative to the sweep file; parameters are dotted paths into a run's resolved
configuration (``simserver.sweep.resolved``). Every base scenario is run with every
parameter set; with no ``grid``/``cases``/``random`` each base scenario runs once.

A base may be an OpenSCENARIO ``.xosc`` (docs/openscenario.md). Its resolved
configuration is ``{openscenario: {file, road_file}, duration_s, dt_s, parameters}``
(``resolve_xosc``): the file's own ``<ParameterDeclarations>`` are varied as
``parameters.<Name>`` (set before the file's expressions are evaluated, as esmini's
``--param``; the others keep their declared values), ``duration_s`` (default
``xosc_run.DEFAULT_DURATION_S``; the stop trigger may end a run sooner) and ``dt_s`` as
for YAML. ``kind: scenario`` plays the file headless as ``run-scenario`` does and
computes the metrics from the *ego's* history (``xosc_run.ego_name``: the entity named
``Ego``, else the first); a run is ``non_finite`` if any car is. ``kind: soak`` soaks its
scene (the ego's start, ``xosc_run.xosc_scene``), as ``simserver soak --scene`` does::

    scenarios: [../openscenario/simserver/hill_queue_15pct.xosc]
    grid: {parameters.Speed: [8, 10, 12], parameters.Headway: [1.0, 1.5]}
    metrics: [time_to_rest, {column: u_mps, stat: max}]

An undeclared parameter name or a value of the wrong type for its ``parameterType``
(``openscenario.override_text``), and any other path an ``.xosc``'s configuration does
not have, is an error naming the sweep file and the parameter, before any run.
"""

from __future__ import annotations

import glob
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.history import HISTORY_COLUMNS
from simserver.adapters.openscenario import load_openscenario
from simserver.adapters.validate import (
    ConfigError,
    check_keys,
    confined_to,
    is_path_text,
    number,
    read_yaml,
    short_repr,
)
from simserver.sim.scenario import resolve_scenario
from simserver.sim.scene_files import OPENSCENARIO_SUFFIX
from simserver.sweep.metrics import Metric, parse_metrics
from simserver.sweep.resolved import file_digest, run_id, with_overrides

KEYS = ("name", "description", "kind", "scenarios", "grid", "cases", "random", "metrics",
        "histories", "soak")
KINDS = ("scenario", "soak")
SOAK_KEYS = ("duration_s", "seeds")
MAX_RUNS = 1_000_000
"""Most runs a sweep may have (base scenarios x parameter sets x seeds), counted first."""
MAX_RANDOM_VALUES = 10_000_000
"""Most random values a ``random:`` section draws (samples x ranges)."""
DEFAULT_CONFIG_DIRS = (Path(__file__).resolve().parents[2] / "configs",)
"""Where a sweep's files may lie, beside the sweep file's own folder (the project's
``configs/``, like the server's default ``config_dirs``); ``--config-dir`` sets others."""


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


def _axis_size(origin: str, key: str, spec: Any) -> int:
    """How many values a grid axis has (checked before any is made)."""
    if isinstance(spec, list) and spec:
        return len(spec)
    if isinstance(spec, dict):
        check_keys(f"{origin} (grid.{key})", spec, ("from", "to", "num"),
                   required=("from", "to", "num"))
        num = spec["num"]
        if isinstance(num, bool) or not isinstance(num, int) or not 1 <= num <= MAX_RUNS:
            raise ConfigError(f"{origin}: key 'grid.{key}.num': expected an integer in "
                              f"[1, {MAX_RUNS}], got {short_repr(num)}")
        return num
    raise ConfigError(f"{origin}: key 'grid.{key}': expected a non-empty list or "
                      f"{{from, to, num}}")


def _values(origin: str, key: str, spec: Any) -> list[Any]:
    if isinstance(spec, list):
        return list(spec)
    lo = number(origin, f"grid.{key}.from", spec["from"], -1e12, 1e12)
    hi = number(origin, f"grid.{key}.to", spec["to"], -1e12, 1e12)
    return [float(v) for v in np.linspace(lo, hi, spec["num"])]


def _check_runs(origin: str, key: str, sets: int, per_set: int, what: str) -> None:
    """``sets`` parameter sets, each run ``per_set`` times (``what``), within ``MAX_RUNS``
    (checked before the sets are made: a grid's product is counted, not built)."""
    if sets * per_set > MAX_RUNS:
        raise ConfigError(f"{origin}: key '{key}': {sets} parameter sets x {per_set} "
                          f"({what}) = {sets * per_set} runs, more than {MAX_RUNS}")


def parameter_sets(origin: str, data: dict[str, Any], per_set: int = 1,
                   what: str = "base scenarios") -> list[dict[str, Any]]:
    """The parameter sets of the file's ``grid``, ``cases`` or ``random`` (one of them),
    each to be run ``per_set`` times (``what``: once per base scenario, per seed): more
    than ``MAX_RUNS`` runs in all are refused before a set is made."""
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
        count = 1
        for k, v in grid.items():
            count *= _axis_size(origin, str(k), v)
            _check_runs(origin, "grid", count, per_set, what)  # stops before it grows more
        axes = [_values(origin, str(k), v) for k, v in grid.items()]
        return [dict(zip(map(str, grid), combo, strict=True))
                for combo in itertools.product(*axes)]
    if "cases" in data:
        cases = data["cases"]
        if not isinstance(cases, list) or not cases or not all(isinstance(c, dict)
                                                                for c in cases):
            raise ConfigError(f"{origin}: key 'cases': expected a list of mappings")
        _check_runs(origin, "cases", len(cases), per_set, what)
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
        raise ConfigError(f"{origin}: key 'random.samples': expected an integer in "
                          f"[1, {MAX_RUNS}], got {short_repr(samples)}")
    _check_runs(origin, "random.samples", samples, per_set, what)
    if not isinstance(ranges, dict) or not ranges:
        raise ConfigError(f"{origin}: key 'random.ranges': expected a mapping path: [lo, hi]")
    if samples * len(ranges) > MAX_RANDOM_VALUES:
        raise ConfigError(f"{origin}: key 'random': {samples} samples x {len(ranges)} ranges "
                          f"= {samples * len(ranges)} values, more than {MAX_RANDOM_VALUES}")
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


def _confined(origin: str, key: str, file: Path, roots: tuple[Path, ...]) -> Path:
    """``file`` resolved, if it lies in one of ``roots``; else an error that names the key
    and the folders, never anything read from the file."""
    resolved = file.resolve()
    if not any(resolved.is_relative_to(r) for r in roots):
        raise ConfigError(f"{origin}: key '{key}': {short_repr(str(file), 200)} is outside "
                          f"the config directories ({', '.join(map(str, roots))}; "
                          "--config-dir adds one)")
    return resolved


def _file_overrides(origin: str, sets: list[dict[str, Any]], base_dir: Path,
                    roots: tuple[Path, ...]) -> None:
    """Each override of a ``file`` or ``*_file`` key: a regular file in ``roots``, at most
    ``resolved.MAX_HASHED_BYTES`` (its contents are part of the run id), given relative
    to the sweep file; replaced by its absolute path (what the runs read). Checked once
    per distinct value."""
    checked: dict[tuple[str, str], str] = {}
    for params in sets:
        for key, value in params.items():
            last = key.rsplit(".", 1)[-1]
            if last != "file" and not last.endswith("_file"):
                continue
            if not is_path_text(value):
                raise ConfigError(f"{origin}: parameter '{key}': expected a file path, got "
                                  f"{short_repr(value)}")
            seen = checked.get((key, value))
            if seen is None:
                target = _confined(origin, key, base_dir / value, roots)
                try:
                    file_digest(target)
                except ConfigError as exc:
                    raise ConfigError(f"{origin}: parameter '{key}': {exc}") from None
                seen = checked[(key, value)] = str(target)
            params[key] = seen


def resolve_xosc(base: Path, sc: Any) -> dict[str, Any]:
    """An ``.xosc`` base's resolved configuration (module docstring; ``sc``: the file
    read, ``openscenario.Scenario``), its files by absolute path (a run's hash covers their
    contents, ``resolved.run_id``; the vehicle catalogs are not hashed)."""
    from simserver.sim.xosc_run import DEFAULT_DURATION_S

    files = {"file": str(base)}
    if sc.road_file is not None:  # without one, each run says so (xosc_run.setup)
        files["road_file"] = str(sc.road_file)
    return {"openscenario": files, "duration_s": DEFAULT_DURATION_S, "dt_s": 0.001,
            "parameters": {}}


def check_xosc_parameters(origin: str, base: Path, sc: Any,
                          sets: list[dict[str, Any]]) -> None:
    """Every ``parameters.<Name>`` of ``sets`` is one of the file's declared parameters
    and of its type (``openscenario.override_text``): else ``ConfigError`` naming
    ``origin`` and the parameter. Each distinct value is checked once."""
    from simserver.adapters.openscenario import override_text

    checked: set[tuple[str, str]] = set()
    for params in sets:
        for key, value in params.items():
            name = key.removeprefix("parameters.")
            if name == key or (key, repr(value)) in checked:
                continue
            if name not in sc.parameter_types:
                raise ConfigError(f"{origin}: parameter {key!r}: {base.name} declares no "
                                  f"parameter {name!r} (it declares: "
                                  f"{', '.join(sc.parameter_types) or 'none'})")
            try:
                override_text(sc.parameter_types[name], value)
            except ValueError as exc:
                raise ConfigError(f"{origin}: parameter {key!r}: {exc}") from None
            checked.add((key, repr(value)))


def load_sweep(path: str | Path, config_dirs: Sequence[Path | str] | None = None) -> Sweep:
    """Read and validate a sweep file and expand it into resolved cases.

    Every file it names (base scenarios, what they name, vehicle and ``*_file``
    overrides) must lie in ``config_dirs`` (default ``DEFAULT_CONFIG_DIRS`` and the sweep
    file's own folder): a sweep file cannot read or quote files elsewhere. The number of
    runs is counted, and refused above ``MAX_RUNS``, before any is made.
    """
    path = Path(path)
    roots = tuple(Path(d).resolve() for d in (
        config_dirs if config_dirs is not None else (*DEFAULT_CONFIG_DIRS, path.parent)))
    data = read_yaml(path)
    with confined_to(roots):
        return _load_sweep(path, data, roots)


def _load_sweep(path: Path, data: dict[str, Any], roots: tuple[Path, ...]) -> Sweep:
    kind = data.get("kind", "scenario")
    if kind not in KINDS:
        raise ConfigError(f"{path}: key 'kind': expected one of {', '.join(KINDS)}")
    check_keys(path, data, KEYS,
               required=("scenarios", "soak") if kind == "soak" else ("scenarios", "metrics"))
    origin = str(path)
    soak: dict[str, Any] | None = None
    seeds = 1
    if kind == "soak":
        if "metrics" in data:
            raise ConfigError(f"{origin}: key 'metrics': a soak sweep's metrics are the "
                              f"soak's own")
        if not isinstance(data["soak"], dict):
            raise ConfigError(f"{origin}: key 'soak': expected {{duration_s, seeds}}")
        check_keys(f"{origin} (soak)", data["soak"], SOAK_KEYS, required=SOAK_KEYS)
        seeds = data["soak"]["seeds"]
        if isinstance(seeds, bool) or not isinstance(seeds, int) or not 1 <= seeds <= MAX_RUNS:
            raise ConfigError(f"{origin}: key 'soak.seeds': expected an integer in "
                              f"[1, {MAX_RUNS}], got {short_repr(seeds)}")
        soak = {"duration_s": number(origin, "soak.duration_s", data["soak"]["duration_s"],
                                     0.01, 1e7), "seed": 0}
    elif "soak" in data:
        raise ConfigError(f"{origin}: key 'soak': only with 'kind: soak'")
    scen = data["scenarios"]
    scen = [scen] if isinstance(scen, str) else scen
    if not isinstance(scen, list) or not scen or not all(is_path_text(s) for s in scen):
        raise ConfigError(f"{origin}: key 'scenarios': expected a list of files or globs")
    bases: list[Path] = []
    for pattern in scen:
        full = str(path.parent / pattern)
        found = sorted(itertools.islice(glob.iglob(full), MAX_RUNS + 1)) \
            if glob.has_magic(pattern) else [full]
        if not found:
            raise ConfigError(f"{origin}: key 'scenarios': {short_repr(pattern)} matches no "
                              "file")
        bases += [_confined(origin, "scenarios", Path(f), roots) for f in found]
        if len(bases) > MAX_RUNS:
            raise ConfigError(f"{origin}: key 'scenarios': more than {MAX_RUNS} files")
    sets = parameter_sets(origin, data, len(bases) * seeds,
                          "base scenarios x seeds" if soak is not None else "base scenarios")
    if soak is not None:
        sets = [{**params, "soak.seed": seed} for params in sets for seed in range(seeds)]
    _file_overrides(origin, sets, path.parent, roots)
    parameters = tuple(dict.fromkeys(k for s in sets for k in s))
    metrics = () if soak is not None else parse_metrics(origin, data["metrics"],
                                                         HISTORY_COLUMNS)
    histories = data.get("histories", False)
    if not isinstance(histories, bool):
        raise ConfigError(f"{origin}: key 'histories': expected true or false")
    cases: list[Case] = []
    for base in bases:
        xosc = base.suffix.lower() == OPENSCENARIO_SUFFIX
        try:
            if xosc:
                sc = load_openscenario(base)
                resolved_base = resolve_xosc(base, sc)
            else:
                resolved_base = resolve_scenario(base)
        except ConfigError as exc:
            raise ConfigError(f"{origin}: key 'scenarios': {exc}") from None
        if xosc:
            check_xosc_parameters(origin, base, sc, sets)
        if soak is not None:
            resolved_base["soak"] = dict(soak)
        for params in sets:
            index = len(cases)
            where = f"{origin}: case {index} ({base.name})"
            try:
                resolved = with_overrides(resolved_base, params, where, path.parent)
            except ConfigError as exc:
                if xosc:  # its configuration's paths are known: a typo, not a case
                    raise
                key = {"base": str(base), "params": params}
                cases.append(Case(index, str(base), params, None, run_id(key), str(exc)))
                continue
            try:
                rid = run_id(resolved)
            except ConfigError as exc:  # a file of the run too large or gone meanwhile
                raise ConfigError(f"{where}: {exc}") from None
            cases.append(Case(index, str(base), params, resolved, rid))
    name = data.get("name", path.stem)
    return Sweep(name=str(name), description=str(data.get("description", "")), path=path,
                 parameters=parameters, metrics=metrics, histories=histories, cases=cases)
