"""Property-based fuzz of the configuration loaders (issue 14): no traceback, ever.

Every loader a user or a client can point at a file (scenario, scene, vehicle and its
subsystem and tire files, .tir, server config, keyframe file, command log) is fed files
built by hypothesis: a valid file with one value replaced by a hostile one (huge and
non-finite numbers, subnormals, wrong types, deep nesting, lone surrogates, paths to
devices), or random text. The only exception allowed out is ``ConfigError`` (a
``TirError`` inside becomes one), and its message names the file. Bounded: 60
examples per loader, a few seconds on an idle machine.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from simserver.adapters.config import ConfigError, load_tire, load_vehicle
from simserver.adapters.tir_file import TirError, load_tir, mf61_coefficients
from simserver.adapters.validate import read_yaml
from simserver.server.command_log import read_command_log
from simserver.server.config import load_server_config
from simserver.sim.keyframes import load_keyframe_file
from simserver.sim.scenario import load_scenario
from simserver.testing import CONFIGS

pytestmark = pytest.mark.timeout(300)

SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])

SCENARIO = CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml"
SEDAN = CONFIGS / "vehicles" / "paper_sedan"
MF_TIRE = CONFIGS / "tires" / "mf61_sample.yaml"
SERVER = CONFIGS / "server" / "default.yaml"

hostile_scalars = st.one_of(
    st.none(), st.booleans(),
    st.integers(), st.integers(min_value=10**300, max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e-320, -1e-320, 5e-324, 1e300, -1e300, 0.0, -0.0, 1.5]),
    st.text(max_size=30), st.sampled_from(["\ud800", "/dev/zero", "/proc/self/status",
                                           ".", "..", "D", "P", "../../../etc/passwd"]),
)
hostile_values = st.recursive(
    hostile_scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4),
                            st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12,
)


def _paths(data: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a nested mapping/list (where a value can be replaced)."""
    out = [prefix] if prefix else []
    if isinstance(data, dict):
        for key, value in data.items():
            out += _paths(value, (*prefix, key))
    elif isinstance(data, list):
        for i, value in enumerate(data):
            out += _paths(value, (*prefix, i))
    return out


def _replaced(data: Any, path: tuple, value: Any) -> Any:
    """A copy of ``data`` with the value at ``path`` replaced."""
    if not path:
        return value
    copy = dict(data) if isinstance(data, dict) else list(data)
    copy[path[0]] = _replaced(data[path[0]], path[1:], value)
    return copy


def _dump(data: Any) -> str:
    try:
        return yaml.safe_dump(data, allow_unicode=False)
    except yaml.YAMLError:  # a value PyYAML cannot write: write its repr instead
        return json.dumps(data, default=repr)


def _only_config_errors(load: Callable[[Path], Any], path: Path) -> None:
    try:
        load(path)
    except ConfigError as exc:
        assert str(path.name) in str(exc) or str(path.parent) in str(exc), str(exc)
    except TirError as exc:  # the .tir reader's own error: a ValueError naming the file
        assert path.name in str(exc) or ".tir" in str(exc)


def _mutation_case(source: Path) -> st.SearchStrategy:
    data = read_yaml(source)
    return st.tuples(st.sampled_from(_paths(data)), hostile_values).map(
        lambda pv: _replaced(data, *pv))


def _copy_sedan(root: Path) -> Path:
    folder = root / "vehicle"
    folder.mkdir()
    for file in SEDAN.iterdir():
        text = file.read_text()
        if file.name == "vehicle.yaml":
            text = text.replace("../../tires/", f"{CONFIGS / 'tires'}/")
        (folder / file.name).write_text(text)
    return folder


@SETTINGS
@given(_mutation_case(SCENARIO))
def test_scenario_loader_never_tracebacks(data):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scenario.yaml"
        text = _dump(data).replace("../vehicles/", f"{CONFIGS / 'vehicles'}/")
        path.write_text(text)
        _only_config_errors(load_scenario, path)
        _only_config_errors(load_keyframe_file, path)


@SETTINGS
@given(st.sampled_from(["vehicle.yaml", "chassis.yaml", "suspension.yaml", "steering.yaml",
                        "brakes.yaml", "powertrain.yaml"]).flatmap(
    lambda name: st.tuples(st.just(name), _mutation_case(SEDAN / name))))
def test_vehicle_loader_never_tracebacks(case):
    name, data = case
    with tempfile.TemporaryDirectory() as tmp:
        folder = _copy_sedan(Path(tmp))
        text = _dump(data).replace("../../tires/", f"{CONFIGS / 'tires'}/")
        (folder / name).write_text(text)
        _only_config_errors(load_vehicle, folder / "vehicle.yaml")


@SETTINGS
@given(_mutation_case(CONFIGS / "tires" / "paper_sti.yaml"))
def test_tire_loader_never_tracebacks(data):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "tire.yaml"
        path.write_text(_dump(data))
        _only_config_errors(load_tire, path)


TIR_TEXT = (MF_TIRE.parent / read_yaml(MF_TIRE)["tir_file"]).read_text(encoding="latin-1")
TIR_NUMERIC_LINES = [i for i, line in enumerate(TIR_TEXT.splitlines())
                     if "=" in line and not line.lstrip().startswith(("$", "!", "["))]


@SETTINGS
@given(st.sampled_from(TIR_NUMERIC_LINES),
       st.one_of(st.floats(allow_nan=False, allow_infinity=False).map(repr),
                 st.sampled_from(["1e-320", "1e300", "-1e300", "nan", "inf", "1D+400",
                                  "'text'", "", "0"]),
                 st.text(max_size=12)))
def test_tir_reader_never_tracebacks(line_no, value):
    lines = TIR_TEXT.splitlines()
    key = lines[line_no].split("=", 1)[0]
    lines[line_no] = f"{key}= {value}"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.tir"
        path.write_text("\n".join(lines) + "\n", encoding="latin-1", errors="replace")
        _only_config_errors(lambda p: mf61_coefficients(load_tir(p)), path)


@SETTINGS
@given(_mutation_case(SERVER))
def test_server_config_loader_never_tracebacks(data):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "server.yaml"
        text = _dump(data).replace("../scenes/", f"{CONFIGS / 'scenes'}/")
        path.write_text(text)
        _only_config_errors(lambda p: load_server_config(p, viewer="off"), path)


LOG_LINES = [
    {"simserver_command_log": 1, "scene": str(CONFIGS / "scenes" / "flat_paper_sedan.yaml"),
     "dt_s": 0.001, "step": 0},
    {"step": 0, "inputs": [0.0, 0.0, 0.0, 0.0, 3.0]},
    {"step": 10, "set_road": {"grade_pct": 1.0, "cross_slope_pct": 0.0,
                              "friction_scale": 1.0}},
    {"step": 20, "reset": {"x_m": 1.0, "y_m": 0.0, "yaw_rad": 0.0}},
    {"end": 30, "state": [0.0.hex()] * 37},
]


@SETTINGS
@given(st.tuples(st.sampled_from(_paths(LOG_LINES)), hostile_values))
def test_command_log_reader_never_tracebacks(case):
    path_in_log, value = case
    lines = _replaced(LOG_LINES, path_in_log, value)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.jsonl"
        text = "\n".join(json.dumps(line, default=repr) for line in lines) + "\n"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        _only_config_errors(read_command_log, path)


@SETTINGS
@given(st.text(max_size=300))
def test_any_text_as_a_yaml_config_is_a_config_error_or_a_mapping(text):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "any.yaml"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        _only_config_errors(load_scenario, path)


@pytest.mark.parametrize(("text", "needle"), [
    ("a: " + "[" * 100 + "]" * 100 + "\n", "nested deeper than 64"),
    ("a: &a [*a]\n", "an alias refers to a node that contains it"),
    ("a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, c in zip("abcdef", "bcdefg", strict=True)), "expands to more than"),
    ("a: \x1f\n", "is not allowed"),
])
def test_yaml_limits_refuse_with_the_reason(tmp_path, text, needle):
    path = tmp_path / "limits.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        read_yaml(path)


def test_files_that_are_no_regular_file_or_too_large_are_refused_without_blocking(tmp_path):
    import os

    from simserver.adapters.validate import MAX_CONFIG_BYTES

    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # no writer: a plain open() would block forever
    for path, needle in ((fifo, "not a regular file"), (Path("/dev/zero"), "not a regular"),
                         (tmp_path, "not a regular file")):
        with pytest.raises(ConfigError, match=needle):
            read_yaml(path)
    big = tmp_path / "big.yaml"
    big.write_bytes(b"# " + b"x" * MAX_CONFIG_BYTES + b"\n")
    with pytest.raises(ConfigError, match="larger than"):
        read_yaml(big)
