"""Which hill car does what when the driver lets go (issue 32 item 1; the table in
docs/clients.md section 2 and docs/model.md section 13): the two hill scenes the README
and docs point a person to, stopped with the foot brake on their 10 % grade in D, then
the brake released with no throttle, or the parking brake on.

- ``hill_10pct_paper_sedan`` (the simple powertrain: no drive without throttle) rolls
  back at once when the brake is released;
- ``hill_10pct_paper_sedan_automatic`` creeps in D (1.6 kN at rest), less than the 10 %
  grade's pull (2.0 kN): its hill-start assist holds it for its 2 s, then it rolls back,
  slower than the manual car; on the flat it creeps forward, and on 7 % its creep holds
  it (the creep holds up to about 8 %, docs/model.md section 13);
- with the parking brake on and the pedals released both hold (after settling back a
  few millimetres onto the rear tires: the parking brake is on the rear wheels).

The auto hold of the driver clients (the brake kept after a braked stop until the
throttle) is a client's: tests/test_clients.py drives it in a terminal.
"""

from __future__ import annotations

import numpy as np
import pytest

from simserver.core import layout as L
from simserver.sim.scene import load_scene
from simserver.sim.simulation import Simulation
from simserver.testing import CONFIGS

DT_S = 0.001
MANUAL = CONFIGS / "scenes" / "hill_10pct_paper_sedan.yaml"
AUTOMATIC = CONFIGS / "scenes" / "hill_10pct_paper_sedan_automatic.yaml"


def let_go(scene_path, seconds: float, parking_brake: bool = False,
           grade_pct: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Hold the foot brake 2 s at rest in D, then release it over 0.2 s (the parking
    brake on or off) and wait ``seconds``: (time after the release began, x along the
    grade from the stop)."""
    scene = load_scene(scene_path)
    if grade_pct is not None:
        scene.road["grade_pct"] = grade_pct
    sim = Simulation(scene, DT_S)
    n_hold, n = int(2.0 / DT_S), int((2.0 + seconds) / DT_S)
    inputs = np.zeros((n, L.N_INPUT))
    inputs[:, L.IN_GEAR] = L.GEAR_D
    inputs[:, L.IN_PARKING_BRAKE] = float(parking_brake)
    t = np.arange(n) * DT_S - 2.0
    inputs[:, L.IN_BRAKE] = np.clip(1.0 - t / 0.2, 0.0, 1.0)
    states, outs = np.zeros((n, L.N_STATE)), np.zeros((n, L.N_OUT))
    sim.run(inputs, states, outs, 1)
    x = states[n_hold:, L.X_M] - states[n_hold, L.X_M]
    return t[n_hold:], x


def test_the_manual_car_rolls_back_at_once_the_automatic_after_its_assist():
    t, manual = let_go(MANUAL, 6.0)
    _, automatic = let_go(AUTOMATIC, 6.0)
    moved_manual = t[np.argmax(manual < -1e-3)]
    moved_automatic = t[np.argmax(automatic < -1e-3)]
    print(f"\n10 %, brake released in D: manual back 1 mm after {moved_manual:.2f} s, "
          f"{manual[-1]:+.2f} m at 6 s; automatic back 1 mm after {moved_automatic:.2f} s "
          f"(assist 2 s), {automatic[-1]:+.2f} m at 6 s")
    assert moved_manual < 0.5 and manual[-1] < -1.0
    assert 2.0 < moved_automatic < 2.5 and manual[-1] < automatic[-1] < -0.05


@pytest.mark.parametrize("grade_pct, creeps", [(0.0, "forward"), (7.0, "holds")])
def test_the_automatics_creep_moves_it_on_the_flat_and_holds_it_on_7pct(grade_pct, creeps):
    _, x = let_go(AUTOMATIC, 8.0, grade_pct=grade_pct)
    print(f"\nautomatic on {grade_pct:g} %, brake released in D: {x[-1]:+.4f} m after 8 s")
    if creeps == "forward":
        assert x[-1] > 5.0
    else:
        assert abs(x[-1]) < 0.1 and np.all(x > -0.1)


@pytest.mark.parametrize("scene_path", [MANUAL, AUTOMATIC], ids=["manual", "automatic"])
def test_the_parking_brake_holds_either_car_with_the_pedals_released(scene_path):
    """The parking brake acts on the rear wheels only: as the foot brake lets go the load
    moves onto them and the car settles back a few millimetres (the rear tires' stiffness
    taking the whole pull), then holds; the creep is counted from 1 s after the last
    brake let go (the automatic's hill-start assist keeps the foot brake 2 s after the
    pedal), as summary.json's holds count it from 1 s after a stop (analysis.holds)."""
    t, x = let_go(scene_path, 30.0, parking_brake=True)
    settled = t >= 3.5
    creep = x[settled] - x[settled][0]
    print(f"\n{scene_path.stem}, parking brake: settles {1e3 * x[settled][0]:+.3f} mm, "
          f"then {1e3 * creep.min():+.5f} .. {1e3 * creep.max():+.5f} mm over 26.5 s")
    assert -5e-3 < x[settled][0] < 0.0
    assert np.abs(creep).max() < 1e-5  # 10 micrometres
