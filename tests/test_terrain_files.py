"""Terrain files as configuration (issue 15): read through the confinement like every other
nested reference, written out by ``resolve_scenario`` so that a resolved scenario is
self-contained and a run's hash covers the files' contents, and their keys in
``docs/configuration.md`` from the one schema the loader checks."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from simserver.adapters.terrain_files import TERRAIN_SCHEMAS, terrain_spec
from simserver.adapters.validate import ConfigError, confined_to
from simserver.core.terrain import TERRAIN_HEIGHTMAP, TERRAIN_KINDS
from simserver.server.slot import prepare_load
from simserver.sim.scenario import load_scenario, resolve_scenario
from simserver.sim.scene import load_scene
from simserver.sweep.resolved import run_id

REPO = Path(__file__).resolve().parents[1]
VEHICLE = REPO / "configs" / "vehicles" / "paper_sedan" / "vehicle.yaml"

SCENARIO = """\
name: terrain_files_test
vehicle: {vehicle}
terrain: {{kind: heightmap, file: {file}, cell_m: 2.0, origin_m: [-20.0, -10.0]}}
initial: {{x_m: 0.0, y_m: 0.0}}
duration_s: 0.01
inputs:
  - {{t: 0.0, gear: N}}
"""


def _hill(path: Path, top_m: float = 1.5) -> None:
    """A 21 x 11 grid with a smooth hill: the heights of ``path`` (.npy)."""
    x = np.arange(21) * 2.0 - 20.0
    y = np.arange(11) * 2.0 - 10.0
    xx, yy = np.meshgrid(x, y)
    np.save(path, top_m * np.exp(-(xx**2 + yy**2) / 80.0))


def _scenario(folder: Path, file: str) -> Path:
    path = folder / "scenario.yaml"
    path.write_text(SCENARIO.format(vehicle=VEHICLE.as_posix(), file=file), encoding="utf-8")
    return path


# ------------------------------------------------------------------ confinement
def test_a_terrain_file_outside_the_config_folders_is_refused_and_not_quoted(tmp_path):
    """The server's ``load`` (its worker's ``prepare_load``, under ``confined_to``): a
    scene inside the config folders whose terrain file lies outside them, is a device, a
    FIFO or missing is refused naming the scene's key; no reply shows an absolute path
    or a byte of the file."""
    inside = tmp_path / "configs"
    inside.mkdir()
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    secret = outside / "secret.npy"
    np.save(secret, np.full((3, 3), 4242.0))
    os.mkfifo(inside / "fifo.npy")
    cases = {
        "out": (str(secret), "key 'terrain.file': refers to a file outside the server's "
                             "config directories"),
        "proc": ("/proc/self/status", "key 'terrain.file': refers to a file outside"),
        "dotdot": ("../elsewhere/secret.npy", "key 'terrain.file': refers to a file outside"),
        "fifo": ("fifo.npy", "key 'terrain.file': fifo.npy: not a regular file"),
        "missing": ("none.npy", "key 'terrain.file': none.npy: No such file"),
    }
    for name, (target, text) in cases.items():
        scene = inside / f"scene_{name}.yaml"
        scene.write_text(f"vehicle: {VEHICLE}\nterrain: {{kind: heightmap, file: '{target}', "
                         "cell_m: 1.0}\n")
        status, field, message = prepare_load(str(scene), str(VEHICLE), scene,
                                              (inside, VEHICLE.parents[2]), str(tmp_path))
        assert status == "error" and field == "scene", (name, message)
        assert f"scene_{name}.yaml: key 'terrain.file'" in message, (name, message)
        assert text in message, (name, message)
        assert str(tmp_path) not in message and "4242" not in message, (name, message)
    # the friction file is a nested reference too
    scene = inside / "scene_friction.yaml"
    np.save(inside / "h.npy", np.zeros((3, 3)))
    scene.write_text(f"vehicle: {VEHICLE}\nterrain: {{kind: heightmap, file: h.npy, "
                     f"cell_m: 1.0, friction_file: '{secret}'}}\n")
    status, field, message = prepare_load(str(scene), str(VEHICLE), scene,
                                          (inside, VEHICLE.parents[2]), str(tmp_path))
    assert status == "error" and "key 'terrain.friction_file': refers to a file outside" \
        in message and str(tmp_path) not in message, message


def test_an_opendrive_file_is_confined_too(tmp_path):
    inside = tmp_path / "configs"
    inside.mkdir()
    road = REPO / "configs" / "roads" / "crest-curve.xodr"
    scene = inside / "scene.yaml"
    scene.write_text(f"vehicle: {VEHICLE}\nterrain: {{kind: opendrive, file: '{road}'}}\n")
    configs = REPO / "configs"
    with confined_to([inside, configs / "vehicles", configs / "tires"]), \
            pytest.raises(ConfigError, match=r"scene\.yaml: key 'terrain\.file': refers to a "
                                             r"file outside"):
        load_scene(scene)


def test_a_terrain_file_inside_the_folders_loads_under_confinement(tmp_path):
    _hill(tmp_path / "hill.npy")
    scenario = _scenario(tmp_path, "hill.npy")
    with confined_to([tmp_path, VEHICLE.parents[2]]):
        scene = load_scene(scenario)
    assert scene.terrain.kind == TERRAIN_HEIGHTMAP
    assert scene.terrain_spec == {"kind": "heightmap", "file": str(tmp_path / "hill.npy"),
                                  "origin_m": [-20.0, -10.0], "cell_m": 2.0}


# ------------------------------------------------------------- resolved scenarios
def test_resolved_scenario_is_self_contained(tmp_path):
    """The resolved mapping names the terrain file by its absolute path with every default
    written out, so it loads from anywhere to the same terrain."""
    src = tmp_path / "src"
    src.mkdir()
    _hill(src / "hill.npy")
    path = _scenario(src, "hill.npy")
    resolved = resolve_scenario(path)
    assert resolved["terrain"] == {"kind": "heightmap", "file": str(src / "hill.npy"),
                                   "origin_m": [-20.0, -10.0], "cell_m": 2.0}
    elsewhere = tmp_path / "other" / "label.yaml"  # a label only: nothing relative to it
    elsewhere.parent.mkdir()
    direct, from_resolved = load_scenario(path), load_scenario(elsewhere, resolved)
    for a, b in zip(direct.scene.terrain, from_resolved.scene.terrain, strict=True):
        np.testing.assert_array_equal(a, b)
    # an OpenDRIVE scene's defaults are written out too
    od = resolve_scenario(REPO / "configs" / "scenes" / "crest_curve_paper_sedan.yaml")
    assert od["terrain"] == {"kind": "opendrive",
                             "file": str(REPO / "configs" / "roads" / "crest-curve.xodr"),
                             "cell_m": 0.5, "margin_m": 20.0}


def test_changing_the_height_map_changes_the_run_hash(tmp_path):
    """A sweep identifies a run by the hash of its resolved configuration: the same files
    give the same hash; new heights in the same file give another."""
    _hill(tmp_path / "hill.npy")
    path = _scenario(tmp_path, "hill.npy")
    first = run_id(resolve_scenario(path))
    assert run_id(resolve_scenario(path)) == first
    _hill(tmp_path / "hill.npy", top_m=1.6)
    assert run_id(resolve_scenario(path)) != first


def test_bad_terrain_sections_name_the_file_and_the_key(tmp_path):
    _hill(tmp_path / "hill.npy")
    source = tmp_path / "scene.yaml"
    cases = [
        ({"kind": "heightmap", "file": "hill.npy", "cell_m": 1.0, "height_scale_m": 2.0},
         "key 'terrain.height_scale_m': only for a .png file"),
        ({"kind": "heightmap", "file": "hill.png", "cell_m": 1.0}, "key 'terrain.file'"),
        ({"kind": "heightmap", "file": "hill.npy", "cell_m": 0.0}, "key 'terrain.cell_m'"),
        ({"kind": "heightmap", "file": "hill.npy", "cell_m": 1.0, "origin_m": [1.0]},
         "key 'terrain.origin_m': expected [x, y]"),
        ({"kind": "heightmap", "file": "hill.npy", "cell_m": 1.0, "origin_m": [1.0, "a"]},
         "key 'terrain.origin_m[1]'"),
        ({"kind": "heightmap", "file": 7, "cell_m": 1.0}, "key 'terrain.file': expected a "
                                                           "file path"),
        ({"kind": "opendrive", "file": "hill.npy", "cell_m": 1.0, "grid": 2},
         "unknown key 'grid'"),
        ({"kind": "plane", "file": "hill.npy"}, "unknown key 'file'"),
    ]
    for raw, text in cases:
        with pytest.raises(ConfigError) as err:
            terrain_spec(source, raw)
        assert str(source) in str(err.value) and text in str(err.value), (raw, err.value)
    (tmp_path / "hill.png").write_bytes(b"")
    with pytest.raises(ConfigError, match=r"key 'terrain\.height_scale_m': required for a "
                                          r"\.png"):
        terrain_spec(source, {"kind": "heightmap", "file": "hill.png", "cell_m": 1.0})


# ------------------------------------------------------------------------- docs
def test_the_terrain_keys_in_the_docs_are_the_loaders(tmp_path):
    """docs/configuration.md lists, per terrain kind, exactly the keys the loader accepts
    (the docs are generated from ``TERRAIN_SCHEMAS``; ``test_param_tables`` checks they
    are up to date), with the numbers' units and ranges."""
    doc = (REPO / "docs" / "configuration.md").read_text(encoding="utf-8")
    section = doc[doc.index("## `terrain:` section"):]
    assert set(TERRAIN_SCHEMAS) == set(TERRAIN_KINDS.names)
    for kind, schema in TERRAIN_SCHEMAS.items():
        start = section.index(f"### `kind: {kind}`")
        nxt = section.find("\n### ", start + 1)
        part = section[start:nxt if nxt > 0 else None]
        cut = part.find("\n## ")
        part = part if cut < 0 else part[:cut]
        listed = set(re.findall(r"^(?:- |\| )`([a-z_]+)`", part, flags=re.MULTILINE))
        assert listed == set(schema.keys) - {"kind"}, kind
        for p in schema.numbers:
            assert f"| `{p.name}` | {p.unit} |" in part and p.range_text() in part
        # the loader refuses a key the docs do not list
        with pytest.raises(ConfigError, match=r"unknown key 'wobble'"):
            terrain_spec(tmp_path / "s.yaml", {"kind": kind, "wobble": 1})


# ------------------------------------------------------------------------ fuzz
_hostile = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12), st.sampled_from(["hill.npy", "../x.npy", "/proc/self/status",
                                           "hill.png", "", "\0"]),
    st.lists(st.floats(allow_nan=True), max_size=3), st.dictionaries(st.text(max_size=3),
                                                                     st.integers(),
                                                                     max_size=2))


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.one_of(st.sampled_from(["plane", "heightmap", "opendrive"]), _hostile),
       values=st.dictionaries(
           st.sampled_from(["file", "cell_m", "origin_m", "height_scale_m", "height_offset_m",
                            "friction_file", "margin_m", "other"]), _hostile, max_size=5))
def test_terrain_sections_never_traceback(tmp_path, kind, values):
    """Any ``terrain:`` mapping is read or refused with a ConfigError (never another
    exception), under the confinement as the server reads it."""
    _hill(tmp_path / "hill.npy")
    with confined_to([tmp_path]):
        try:
            terrain_spec(tmp_path / "scene.yaml", {"kind": kind, **values})
        except ConfigError:
            pass
