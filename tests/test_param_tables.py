"""The parameter tables (core/params.py) and everything derived from them.

The slot constants, the config loader's keys and checks and docs/configuration.md all come
from the tables; these tests are parametrised from the tables too, so a new parameter is
checked here without a new test.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from simserver.adapters import config as C
from simserver.core import param_table as T
from simserver.core import params as P
from simserver.tires.registry import tire_models
from tests.conftest import CONFIGS

REPO = Path(__file__).resolve().parents[1]
VEHICLE = CONFIGS / "vehicles" / "paper_sedan"
FILE_PARAMS = [pytest.param(t, p, id=p.name) for t in P.VEHICLE_SUBSYSTEMS for p in t]
REQUIRED_FILE_PARAMS = [pytest.param(t, p, id=p.name) for t in P.VEHICLE_SUBSYSTEMS for p in t
                        if p.required]
OPTION_PARAMS = [pytest.param(p, id=p.name) for p in P.MODEL_OPTIONS]


# ------------------------------------------------------------------ slots from the tables
def test_slot_constants_are_the_generated_block():
    source = Path(P.__file__).read_text(encoding="utf-8")
    assert T.with_slot_constants(source, C.slot_constants()) == source, (
        "core/params.py's slot constants drifted from its tables: run python -m "
        "simserver.adapters.config --write --slots simserver/core/params.py")
    assert C.main(["--slots", P.__file__]) == 0


def test_slot_constants_match_the_tables():
    """Every parameter has one VP_ constant holding its slot, in order, and nothing else."""
    layout = P.VEHICLE_PARAMS
    # a list parameter (size > 1: a curve, the gear ratios) takes size consecutive slots
    assert [p.slot + k for p in layout for k in range(p.size)] == list(range(P.N_VEHICLE_PARAM))
    assert len(P.VEHICLE_PARAM_NAMES) == sum(map(len, P.VEHICLE_PARAM_TABLES))
    assert P.N_VEHICLE_PARAM == sum(p.size for p in layout)
    assert P.VEHICLE_PARAM_NAMES == tuple(p.name for p in layout)
    consts = {name: value for name, value in vars(P).items()
              if name.startswith("VP_") and type(value) is int}
    assert {T.slot_const(p, "VP_"): p.slot for p in layout} == consts


def test_every_key_has_unit_range_and_meaning():
    for table in P.VEHICLE_PARAM_TABLES:
        assert table.title
        for p in table:
            assert p.unit and p.meaning, p.name
            if p.derived:  # computed by the loader: the gear count
                assert table is P.AUTOMATIC and p.default is None, p.name
            elif p.choices is not None:
                assert all(isinstance(v, int) for v in p.choices.values()), p.name
            else:
                assert p.lo <= p.hi, p.name
    for table in P.VEHICLE_SUBSYSTEMS:  # a vehicle file has no defaults: every key required
        # but the powertrain's kind (simple by default: the files before it stay valid) and
        # the chassis' body box and contact keys (issue 30: the reference car's by default,
        # docs/model.md section 16; the files before them stay valid)
        optional = {P.POWERTRAIN.name: ("kind",),
                    P.CHASSIS.name: ("body_front_overhang_m", "body_rear_overhang_m",
                                "body_width_m", "bumper_height_m",
                                "contact_stiffness_n_per_m", "contact_damping_ratio",
                                "contact_friction")}.get(table.name, ())
        assert table.required_keys == tuple(k for k in table.keys if k not in optional)


@pytest.mark.parametrize("bad, needle", [
    (T.Param("x_m", "m", 0.0, 1.0, ""), "needs a unit and a meaning"),
    (T.Param("x_m", "", 0.0, 1.0, "x"), "needs a unit and a meaning"),
    (T.Param("x_m", "m", 1.0, 0.0, "x"), "bad range"),
    (T.Param("x_m", "m", 0.0, None, "x"), "both ends"),
    (T.Param("x_m", "m", 0.0, 1.0, "x", default=2.0), "outside its range"),
    (T.Param("x", "-", None, None, "x", default="c", choices={"a": 0}), "not a choice"),
    (T.Param("x", "-", 0.0, 1.0, "x", choices={"a": 0}), "choices, not a range"),
])
def test_a_bad_table_row_is_rejected(bad, needle):
    with pytest.raises(ValueError, match=needle):
        T.ParamTable("t", "a table", (bad,))


def test_a_table_rejects_duplicates_and_slot_gaps():
    row = T.Param("x_m", "m", 0.0, 1.0, "x", slot=0)
    with pytest.raises(ValueError, match="listed twice"):
        T.ParamTable("t", "a table", (row, row))
    gap = T.ParamTable("t", "a table", (row, T.Param("y_m", "m", 0.0, 1.0, "y", slot=2)))
    with pytest.raises(ValueError, match="not 0 .. 1"):
        T.slot_layout((gap,))


# ------------------------------------------------------------------ the vehicle loader
@pytest.fixture
def vehicle_copy(tmp_path):
    """A copy of the reference car's files that a test may break, tires left in place."""
    dest = tmp_path / "car"
    shutil.copytree(VEHICLE, dest)
    top = yaml.safe_load((dest / "vehicle.yaml").read_text())
    top["tires"] = {axle: str((VEHICLE / ref).resolve()) for axle, ref in top["tires"].items()}
    (dest / "vehicle.yaml").write_text(yaml.safe_dump(top))
    return dest


def edit(path: Path, **changes) -> None:
    data = yaml.safe_load(path.read_text())
    for key, value in changes.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    path.write_text(yaml.safe_dump(data))


def outside(p: T.Param) -> object:
    """A value the parameter must reject: past its range, or not one of its names."""
    return "no_such_choice" if p.choices is not None else p.hi + 1.0 + abs(p.hi)


def test_each_file_key_lands_in_its_slot():
    cfg = C.load_vehicle(VEHICLE / "vehicle.yaml")
    for table in P.VEHICLE_SUBSYSTEMS:
        data = yaml.safe_load((VEHICLE / f"{table.name}.yaml").read_text())
        for p in table:
            value = data.get(p.yaml_key, p.default)  # the powertrain's kind has a default
            want = p.choices[value] if p.choices is not None else value
            assert cfg.vp[p.slot] == want, p.name
    for p in P.MODEL_OPTIONS:  # the options at their defaults
        want = p.choices[p.default] if p.choices is not None else p.default
        assert cfg.vp[p.slot] == want, p.name
    from simserver.core.terrain import default_road, plane_terrain
    road = plane_terrain().road  # a terrain's road (not the vehicle's) starts flat
    assert np.array_equal(road, default_road())
    for p in P.ROAD:
        if not p.derived:
            assert road[p.slot] == p.default, p.name


@pytest.mark.parametrize("table, param", FILE_PARAMS)
def test_out_of_range_file_key_names_file_and_key(vehicle_copy, table, param):
    sub = vehicle_copy / f"{table.name}.yaml"
    edit(sub, **{param.yaml_key: outside(param)})
    with pytest.raises(C.ConfigError) as err:
        C.load_vehicle(vehicle_copy / "vehicle.yaml")
    assert str(sub.resolve()) in str(err.value) and f"'{param.yaml_key}'" in str(err.value)


@pytest.mark.parametrize("table, param", REQUIRED_FILE_PARAMS)
def test_missing_file_key_names_file_and_key(vehicle_copy, table, param):
    sub = vehicle_copy / f"{table.name}.yaml"
    edit(sub, **{param.yaml_key: None})
    with pytest.raises(C.ConfigError, match=f"missing key '{param.yaml_key}'") as err:
        C.load_vehicle(vehicle_copy / "vehicle.yaml")
    assert str(sub.resolve()) in str(err.value)


@pytest.mark.parametrize("table", P.VEHICLE_SUBSYSTEMS, ids=lambda t: t.name)
def test_unknown_file_key_names_file_and_key(vehicle_copy, table):
    sub = vehicle_copy / f"{table.name}.yaml"
    edit(sub, wheelbase_furlongs=1.0)
    with pytest.raises(C.ConfigError, match="unknown key 'wheelbase_furlongs'") as err:
        C.load_vehicle(vehicle_copy / "vehicle.yaml")
    assert str(sub.resolve()) in str(err.value)


# ------------------------------------------------------------------ model options
@pytest.mark.parametrize("param", OPTION_PARAMS)
def test_model_option_sets_its_slot(param):
    value = next(iter(param.choices)) if param.choices is not None else param.lo
    cfg = C.load_vehicle(VEHICLE / "vehicle.yaml", {param.yaml_key: value}, "scene.yaml")
    assert cfg.vp[param.slot] == (param.choices[value] if param.choices else value)


@pytest.mark.parametrize("param", OPTION_PARAMS)
def test_bad_model_option_names_source_and_key(param):
    with pytest.raises(C.ConfigError, match=f"^scene.yaml: key 'model.{param.yaml_key}'"):
        C.load_vehicle(VEHICLE / "vehicle.yaml", {param.yaml_key: outside(param)}, "scene.yaml")


def test_unknown_model_option_is_an_error():
    with pytest.raises(C.ConfigError, match=r"^scene.yaml \(model\): unknown key 'tire_mood'"):
        C.model_option_values({"tire_mood": 1}, "scene.yaml")


def test_the_scene_road_ranges_are_the_road_table():
    """scenario.py validates the ``road:`` section; the docs print the ROAD table."""
    from simserver.sim.scene import ROAD_RANGES

    assert ROAD_RANGES == {p.yaml_key: (p.lo, p.hi) for p in P.ROAD if not p.derived}


# ------------------------------------------------------------------ the reference doc
def test_configuration_reference_is_current():
    doc = (REPO / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert doc == C.config_reference_markdown(), (
        "docs/configuration.md drifted: run python -m simserver.adapters.config --write "
        "docs/configuration.md")
    assert C.main([str(REPO / "docs" / "configuration.md")]) == 0
    assert "../shared" not in doc and "](model.md" not in doc


def test_configuration_reference_lists_every_key():
    doc = C.config_reference_markdown()
    for table in P.VEHICLE_PARAM_TABLES:
        for key in table.keys:
            assert f"| `{key}` | {table.by_key(key).unit} |" in doc, key
    for model in tire_models():
        assert model.params is not None, model.name
        assert f"### `model: {model.name}`" in doc
        for param in model.params:
            assert f"| `{param.yaml_key}` | {param.unit} |" in doc, (model.name, param.name)
        for key, _ in model.path_keys:
            assert f"- `{key}` (path):" in doc


@pytest.mark.parametrize("model", [m for m in tire_models() if m.params is not None],
                         ids=lambda m: m.name)
def test_tire_tables_validate_tire_files(tmp_path, model):
    """Every numeric key of a tire table is range-checked by the loader, naming the key."""
    source = {"simple": CONFIGS / "tires" / "paper_sti.yaml",
              "mf61": CONFIGS / "tires" / "mf61_sample.yaml"}[model.name]
    data = yaml.safe_load(source.read_text())
    if "tir_file" in data:
        data["tir_file"] = str((source.parent / data["tir_file"]).resolve())
    for param in model.params:
        broken = dict(data, **{param.yaml_key: param.hi * 2.0 + 1.0})
        path = tmp_path / "tire.yaml"
        path.write_text(yaml.safe_dump(broken))
        with pytest.raises(C.ConfigError, match=rf"tire\.yaml: key '{param.yaml_key}'"):
            C.load_tire(path)


def test_stale_reference_is_reported(tmp_path, capsys):
    stale = tmp_path / "configuration.md"
    stale.write_text("# old\n", encoding="utf-8")
    assert C.main([str(stale)]) == 1
    assert "out of date" in capsys.readouterr().out
    assert C.main(["--write", str(stale)]) == 0
    assert C.main([str(stale)]) == 0

