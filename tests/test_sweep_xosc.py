"""simserver sweep over OpenSCENARIO files (issue 31: "a .xosc works wherever a scene or
scenario file is accepted"; docs/openscenario.md, docs/sweep.md).

A small hand-written ``.xosc`` declares the ego's initial speed ``V0``; a sweep varies it as
``parameters.V0`` on a real one-worker Dask cluster. Each run's metrics are the ego's, the
same numbers as ``xosc_run.play`` of the file with that parameter, and the distance the
car covers is the one computed by hand from the storyboard. A parameter the file does not
declare, or a value of the wrong type, is refused when the sweep is read, naming the
sweep file and the parameter.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml

from simserver.adapters.validate import ConfigError
from simserver.sweep.engine import RESULTS_FILE, run_sweep
from simserver.sweep.metrics import evaluate
from simserver.sweep.spec import load_sweep
from simserver.sweep.worker import HistoryColumns, run_case
from tests.test_openscenario import _at_time, _speed, _story, write
from tests.test_xosc_storyboard import ROAD, _car

pytestmark = pytest.mark.timeout(240)

DURATION_S = 8.0
METRICS = [{"column": "u_mps", "stat": "max"}, {"column": "x_m", "stat": "min"},
           {"column": "x_m", "stat": "final"}]


def ramp_xosc(tmp: Path) -> Path:
    """Ego alone on straight_500m.xodr (along +x), lane -1 at s = 20 m, starting at
    ``$V0`` (declared 20 m/s); from 1.0 s a linear speed change at 2 m/s^2 to 10 m/s. A
    second declared parameter (``Tag``, a string) is never used."""
    init = ('<Private entityRef="Ego"><PrivateAction><TeleportAction><Position>'
            '<LanePosition roadId="1" laneId="-1" offset="0" s="20"/></Position>'
            f'</TeleportAction></PrivateAction><PrivateAction>{_speed("$V0")}'
            '</PrivateAction></Private>')
    path = write(tmp, _story(0, "Ego", _speed(10.0, "linear", "rate", 2.0), _at_time(1.0)),
                 params='<ParameterDeclaration name="V0" parameterType="double" value="20"/>'
                        '<ParameterDeclaration name="Tag" parameterType="string" value="a"/>',
                 entities=_car("Ego"), road=f'<LogicFile filepath="{ROAD}"/>')
    path.write_text(path.read_text().replace("<Init><Actions/></Init>",
                                             f"<Init><Actions>{init}</Actions></Init>"))
    return path


def write_sweep(tmp: Path, **body) -> Path:
    path = tmp / "sweep.yaml"
    path.write_text(yaml.safe_dump({"name": "xosc", "scenarios": ["t.xosc"],
                                    "metrics": METRICS, **body}))
    return path


def hand_distance_m(v0: float) -> float:
    """V0 for 1 s, the ramp to 10 m/s at 2 m/s^2 (mean speed over (V0 - 10) / 2 s), then
    10 m/s to the end."""
    ramp_s = (v0 - 10.0) / 2.0
    return v0 * 1.0 + (v0 + 10.0) / 2.0 * ramp_s + 10.0 * (DURATION_S - 1.0 - ramp_s)


def test_a_swept_xosc_parameter_changes_the_egos_run_as_by_hand(tmp_path: Path) -> None:
    """V0 = 14 and 20 m/s: 88 m and 115 m by hand. The car covers that within 3 m (the
    driver's lag on a 2 m/s^2 ramp, under 0.6 m/s over at most 5 s: docs/openscenario.md)
    and starts at V0 within 0.3 m/s; the row's metrics are those of ``play`` with the
    parameter (bit for bit), and of neither the other parameter value nor the default."""
    from simserver.sim.xosc_run import play

    ramp_xosc(tmp_path)
    sweep = load_sweep(write_sweep(tmp_path, grid={"parameters.V0": [14, 20.0],
                                                   "duration_s": [DURATION_S]},
                                   histories=True))
    assert [c.params["parameters.V0"] for c in sweep.cases] == [14, 20.0]
    assert len({c.run_id for c in sweep.cases}) == 2
    outcome = run_sweep(sweep, tmp_path / "out", workers=1, quiet=True)
    assert outcome.failed == 0
    rows = {r["case"]: r for r in pq.read_table(tmp_path / "out" / RESULTS_FILE).to_pylist()}
    assert (tmp_path / "out" / "histories" / f"{sweep.cases[0].run_id}.parquet").is_file()
    distances = []
    for case in sweep.cases:
        row = rows[case.index]
        assert row["status"] == "ok", row["error"]
        v0 = float(case.params["parameters.V0"])
        run = play(case.base, duration_s=DURATION_S, parameters={"V0": v0})
        direct = evaluate(sweep.metrics, HistoryColumns(run.result.cars["Ego"]))
        for name, value in direct.items():
            assert row[name] == value, (case.index, name, row[name], value)
        assert abs(row["max_u_mps"] - v0) <= 0.3, row["max_u_mps"]
        covered = row["final_x_m"] - row["min_x_m"]
        assert abs(covered - hand_distance_m(v0)) <= 3.0, (v0, covered, hand_distance_m(v0))
        distances.append(covered)
    assert distances[1] - distances[0] > 20.0  # 27 m by hand: the parameter was applied


def test_soak_of_an_xosc_soaks_the_egos_start_with_the_parameter(tmp_path: Path) -> None:
    """``kind: soak`` on an .xosc: ``run_soak`` of ``xosc_scene`` with the case's
    parameters, the same numbers as ``simserver soak --scene`` would give that scene."""
    from simserver.sim.soak import run_soak
    from simserver.sim.xosc_run import xosc_scene

    ramp_xosc(tmp_path)
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump({"kind": "soak", "scenarios": ["t.xosc"],
                                    "cases": [{"parameters.V0": 5.0}],
                                    "soak": {"duration_s": 2.0, "seeds": 1}}))
    (case,) = load_sweep(path).cases
    row = run_case(case, (), None)
    scene = xosc_scene(tmp_path / "t.xosc", parameters={"V0": 5.0})
    assert scene.initial["u_mps"] == 5.0
    report = run_soak(scene, 2.0, seed=0)
    assert row["status"] == ("ok" if report.ok else "violation"), row["error"]
    assert row["metrics"]["max_speed_mps"] == report.max_speed_mps
    assert row["metrics"]["min_fz_n"] == report.min_fz_n


@pytest.mark.parametrize(("params", "message"), [
    ({"parameters.Speed": [10.0]},
     "parameter 'parameters.Speed': t.xosc declares no parameter 'Speed' (it declares: V0, Tag)"),
    ({"parameters.V0": [10.0, "fast"]},
     "parameter 'parameters.V0': expected a finite number (parameterType double), got 'fast'"),
    ({"parameters.V0": [True]},
     "parameter 'parameters.V0': expected a finite number (parameterType double), got True"),
    ({"parameters.Tag": [3]},
     "parameter 'parameters.Tag': expected a string (parameterType string), got 3"),
    ({"vehicle.chassis.mass_kg": [1500.0]},
     "parameter 'vehicle.chassis.mass_kg': no key 'vehicle' in the scenario"),
])
def test_a_bad_xosc_parameter_is_refused_before_any_run(tmp_path: Path, params: dict,
                                                        message: str) -> None:
    ramp_xosc(tmp_path)
    path = write_sweep(tmp_path, grid=params)
    with pytest.raises(ConfigError) as err:
        load_sweep(path)
    assert str(err.value).startswith(str(path)), err.value
    assert message in str(err.value), err.value
    assert "\n" not in str(err.value)


def test_the_shipped_xosc_sweep_reads_as_six_cases() -> None:
    """configs/sweeps/hill_queue_xosc.yaml: Speed x Gap, 3 x 2 cases of the hill queue, each
    with its own run id (read only; ``simserver sweep`` runs it in about 10 s)."""
    from simserver.testing import CONFIGS

    sweep = load_sweep(CONFIGS / "sweeps" / "hill_queue_xosc.yaml")
    assert sweep.parameters == ("parameters.Speed", "parameters.Gap")
    assert [c.resolved["parameters"] for c in sweep.cases] == [
        {"Speed": s, "Gap": g} for s in (8.0, 10.0, 12.0) for g in (25.0, 30.0)]
    assert len({c.run_id for c in sweep.cases}) == 6
