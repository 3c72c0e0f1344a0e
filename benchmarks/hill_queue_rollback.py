"""The hill queue's rollback with the lagged and the kinematic slip (issue 30 acceptance).

Run from the repository root::

    python -m benchmarks.hill_queue_rollback

Runs ``configs/scenarios/hill_queue_15pct.yaml`` headless twice: as shipped (the paper's
lagged slip states, docs/model.md section 5) and with the kinematic slip variant on both
cars (``model: {slip_model: kinematic}``). On a 15 % grade a traffic car (the built-in
driver) queues 1.0 m behind a held car; at 25 s the held car drives off, the traffic car
after it. Printed per variant, from the histories' road-plane positions (the cars drive
along x, no cross-slope: x is the distance along the road):

- ``creep``: each car's travel over the queue's hold, 22 s to 25 s (``np.ptp`` of x);
- ``rollback``: each car's largest travel down the grade after the drive-off (from its
  position at 25 s to its lowest after);
- ``min gap``: the smallest bumper-to-bumper gap over the run (the bodies: the contact
  stage's boxes, ``core.contact.body_box``, which the built-in driver's gap keeping uses
  too).

``tests/test_driver.py`` asserts on these very figures (:func:`hill_queue_figures`) and
prints them. Figures are simulated, not timed: the same on any machine (docs/model.md
section 15 quotes them).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from simserver.adapters.validate import read_yaml
from simserver.core import layout as L
from simserver.core.contact import body_box
from simserver.sim.scenario import WorldResult, load_world_scenario, run_world_scenario
from simserver.testing import REPO

HILL = REPO / "configs" / "scenarios" / "hill_queue_15pct.yaml"
HOLD_S = (22.0, 25.0)  # the queue's hold: from a second after the traffic car's stop
GO_S = 25.0  # the driven car's drive-off (the scenario's keyframes)
VARIANTS = {"lagged": None, "kinematic": "kinematic"}
"""Variant name -> the slip model set on both cars (None: the scenario as shipped)."""


def bumper_gap(result_lead: Any, result_follow: Any, vp: np.ndarray) -> np.ndarray:
    """Bumper-to-bumper gap along road-plane x (cars driving along x, no cross-slope: the
    road-plane x is the distance along the road, on the flat and on a grade), between
    the bodies' boxes (``core.contact.body_box``; both cars the same vehicle ``vp``)."""
    front_m, rear_m, _ = body_box(vp)
    return ((result_lead.states[:, L.X_M] - rear_m)
            - (result_follow.states[:, L.X_M] + front_m))


def run_hill_queue(slip_model: str | None = None) -> WorldResult:
    """The hill queue run headless, with ``slip_model`` on both cars (None: as shipped)."""
    data = copy.deepcopy(read_yaml(HILL))
    if slip_model is not None:
        for car in data["cars"]:
            car["model"] = {"slip_model": slip_model}
    return run_world_scenario(load_world_scenario(HILL, data))


def hill_queue_figures(result: WorldResult) -> dict[str, float]:
    """Each car's creep over the hold and rollback after the drive-off, and the smallest
    gap (module docstring), in metres."""
    figures = {}
    for cid in ("driven", "traffic"):
        car = result.cars[cid]
        t, x = car.time_s, car.states[:, L.X_M]
        held = (t >= HOLD_S[0]) & (t < HOLD_S[1])
        off = t >= GO_S
        figures[f"{cid}_creep_m"] = float(np.ptp(x[held]))
        figures[f"{cid}_rollback_m"] = float(x[off][0] - x[off].min())
    traffic = result.cars["traffic"]
    figures["gap_min_m"] = float(bumper_gap(result.cars["driven"], traffic,
                                            traffic.scenario.scene.vehicle.vp).min())
    return figures


def figures_line(variant: str, f: dict[str, float]) -> str:
    """One variant's figures, in millimetres (to the nanometre) but the gap."""
    mm = {k: f"{1e3 * v:10.6f} mm" for k, v in f.items()}
    return (f"{variant:<10} rollback driven {mm['driven_rollback_m']}, traffic "
            f"{mm['traffic_rollback_m']}; creep over the hold (22-25 s) driven "
            f"{mm['driven_creep_m']}, traffic {mm['traffic_creep_m']}; "
            f"min gap {f['gap_min_m']:.4f} m")


def main() -> int:
    print(f"hill queue on 15 % ({HILL.relative_to(REPO)}), drive-off at {GO_S:g} s")
    for variant, slip_model in VARIANTS.items():
        print(figures_line(variant, hill_queue_figures(run_hill_queue(slip_model))),
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
