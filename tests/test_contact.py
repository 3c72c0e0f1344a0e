"""Cars that touch (issue 30 item 3; ``core.contact``, docs/model.md section 16).

Every check is computed from the histories, independently of the contact stage's own
numbers:

- momentum: each car's planar states (u, v body velocities, yaw) are the whole car's CG
  velocity in the road plane (section 7: heave, roll and pitch are motions of the sprung
  mass along the normal and about the CG that the model does not couple to the planar
  momentum), so a car's momentum in the plane is ``m (u cos psi - v sin psi, u sin psi +
  v cos psi)``; with the road's friction scale at 0 the tires give no shear force, and
  the only other force in the plane is the air drag ``0.5 rho C_d A u |u|`` along body x,
  whose impulse is integrated from the same histories (trapezoid on the 1 ms rows);
- penetration: the bumpers' positions from the CGs and the vehicle's overhangs;
- energy: the pair's planar kinetic energy (translation and yaw) and the drag's work.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from simserver.core import layout as L
from simserver.core import params as P
from simserver.core.contact import (
    CC_ACTIVE,
    N_CAR_CONTACT,
    POLY_MAX,
    footprint,
    pair_contact,
)
from simserver.sim.scenario import load_world_scenario, run_scenario, run_world_scenario
from simserver.testing import REPO

SCENARIOS = REPO / "configs" / "scenarios"
REAR_END = SCENARIOS / "contact_rear_end_flat.yaml"
HELD = SCENARIOS / "contact_rest_on_held_car_15pct.yaml"


def _vp(result, cid):
    return result.cars[cid].scenario.scene.vehicle.vp


def _momentum(result) -> np.ndarray:
    """The pair's momentum in the road plane per row (kg m/s, columns e1, e2)."""
    total = 0.0
    for cid, r in result.cars.items():
        st = r.states
        m = _vp(result, cid)[P.VP_MASS_KG]
        c, s = np.cos(st[:, L.YAW_RAD]), np.sin(st[:, L.YAW_RAD])
        u, v = st[:, L.U_MPS], st[:, L.V_MPS]
        total = total + m * np.stack([u * c - v * s, u * s + v * c], axis=1)
    return total


def _drag(result, cid) -> np.ndarray:
    """The drag force on a car in the road plane per row (N, columns e1, e2)."""
    st = result.cars[cid].states
    vp = _vp(result, cid)
    u = st[:, L.U_MPS]
    d = 0.5 * vp[P.VP_AIR_DENSITY_KGPM3] * vp[P.VP_DRAG_AREA_M2] * u * np.abs(u)
    return -np.stack([d * np.cos(st[:, L.YAW_RAD]), d * np.sin(st[:, L.YAW_RAD])], axis=1)


def _trapezoid(t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Running integral of ``f`` (rows) over ``t`` from the first row."""
    steps = 0.5 * (f[1:] + f[:-1]) * np.diff(t)[:, None]
    return np.concatenate([np.zeros((1, f.shape[1])), np.cumsum(steps, axis=0)])


def _kinetic(result) -> np.ndarray:
    """The pair's planar kinetic energy per row (J): translation and yaw."""
    total = 0.0
    for cid, r in result.cars.items():
        st = r.states
        vp = _vp(result, cid)
        total = total + 0.5 * vp[P.VP_MASS_KG] * (st[:, L.U_MPS] ** 2 + st[:, L.V_MPS] ** 2) \
            + 0.5 * vp[P.VP_YAW_INERTIA_KGM2] * st[:, L.YAW_RATE_RADPS] ** 2
    return total


def _drag_work(result) -> np.ndarray:
    """Energy the drag took out so far, per row (J, >= 0)."""
    total = 0.0
    for cid, r in result.cars.items():
        st = r.states
        vp = _vp(result, cid)
        u = st[:, L.U_MPS]
        power = 0.5 * vp[P.VP_AIR_DENSITY_KGPM3] * vp[P.VP_DRAG_AREA_M2] * np.abs(u) ** 3
        total = total + _trapezoid(r.time_s, power[:, None])[:, 0]
    return total


def _bumper_overlap(result) -> np.ndarray:
    """How far the striking car's front bumper is past the struck car's rear bumper, per
    row (m; both drive along the road plane's e1 at yaw 0)."""
    struck, striking = result.cars["struck"].states, result.cars["striking"].states
    vs, vk = _vp(result, "struck"), _vp(result, "striking")
    rear = struck[:, L.X_M] - vs[P.VP_CG_TO_REAR_AXLE_M] - vs[P.VP_BODY_REAR_OVERHANG_M]
    front = striking[:, L.X_M] + vk[P.VP_CG_TO_FRONT_AXLE_M] + vk[P.VP_BODY_FRONT_OVERHANG_M]
    return front - rear


@pytest.fixture(scope="module")
def rear_end():
    return run_world_scenario(load_world_scenario(REAR_END))


def test_rear_end_conserves_the_pairs_momentum(rear_end):
    """Friction scale 0: the tires push nothing, so the pair's momentum changes only by
    the drag's impulse. Tolerance 1e-6 of the momentum (the acceptance); the error of the
    drag's trapezoid on 1 ms rows is about 1e-9 of it (its second derivative, 2 c
    (du/dt)^2 at 30 m/s^2 of contact deceleration, times h^2/12 over the run), the
    rounding of 1500 steps about 1e-13."""
    r = rear_end
    for cid in r.cars:  # the premise: no tire force, no yaw (the RK4 frame is not turning)
        assert np.abs(r.cars[cid].outputs[:, L.O_FX_BODY_SUM_N]).max() == 0.0
        assert np.abs(r.cars[cid].states[:, L.YAW_RAD]).max() < 1e-9
    p = _momentum(r)
    t = r.cars["struck"].time_s
    impulse = _trapezoid(t, _drag(r, "struck") + _drag(r, "striking"))
    p0 = np.linalg.norm(p[0])
    assert p0 == pytest.approx(2041.0 * 3.0)
    residual = np.linalg.norm(p - p[0] - impulse, axis=1) / p0
    assert residual.max() < 1e-6, residual.max()
    # and the contact did exchange momentum: the struck car now carries most of it
    share = _vp(r, "struck")[P.VP_MASS_KG] * r.cars["struck"].states[-1, L.U_MPS] / p0
    assert share > 0.5, share


def test_rear_end_penetration_flags_and_count(rear_end):
    r = rear_end
    overlap = _bumper_overlap(r)
    assert 0.0 < overlap.max() < 0.05, overlap.max()  # they touched, under 5 cm deep
    for cid in r.cars:
        st = r.cars[cid].states
        assert np.isfinite(st).all() and np.isfinite(r.cars[cid].outputs).all()
        flag = r.contact(cid, "contact") > 0.5
        # flagged exactly on the rows the boxes overlap (the rows are the contact stage's
        # states), and the depth it reports is the bumpers' overlap
        np.testing.assert_array_equal(flag, overlap > 0.0)
        pen = r.contact(cid, "contact_penetration_m")
        np.testing.assert_allclose(pen[flag], overlap[flag], rtol=0, atol=1e-9)
        assert r.contact(cid, "contact_events")[-1] == 1
    f_struck = r.contact("struck", "contact_force_x_n")
    f_striking = r.contact("striking", "contact_force_x_n")
    np.testing.assert_array_equal(f_struck, -f_striking)  # equal and opposite, to the bit
    assert f_struck.max() > 0.0 and f_struck.min() >= 0.0  # it pushes, never pulls
    # one event: the two ids, when the 0.5 m gap closed at 3 m/s, at about 3 m/s
    assert len(r.contact_events) == 1 and r.contact_events_lost == 0
    e = r.contact_events[0]
    assert {e["car_a"], e["car_b"]} == {"struck", "striking"}
    first = np.argmax(overlap > 0.0)
    assert e["time_s"] == r.cars["struck"].time_s[first]
    assert e["time_s"] == pytest.approx(0.5 / 3.0, abs=2e-3)
    assert e["closing_speed_mps"] == pytest.approx(3.0, abs=2e-3)  # less the drag's


def test_rear_end_creates_no_energy(rear_end):
    """The pair's planar kinetic energy plus what the drag took never exceeds the start's:
    after the contact it is below it (the contact's damping), and at no row above it."""
    r = rear_end
    energy = _kinetic(r) + _drag_work(r)
    e0 = energy[0]
    assert energy.max() <= e0 * (1.0 + 1e-9)
    assert energy[-1] < 0.95 * e0  # the damping took its share
    # restitution: the cars part slower than they met
    u_struck = r.cars["struck"].states[-1, L.U_MPS]
    u_striking = r.cars["striking"].states[-1, L.U_MPS]
    assert 0.0 < u_struck - u_striking < 3.0


@pytest.mark.parametrize("speed_mps", [1.0, 3.0, 8.0])
def test_an_undamped_contact_creates_no_energy(speed_mps):
    """With no contact damping (zeta 0) the spring alone, solved exactly over each step: the
    pair parts at most as fast as it met (the last step, where the solution would pull,
    pushes less), and nearly as fast. Before the spring was relaxed at the depth of the
    step the pair met, that step's overlap (up to v h) was energy given for nothing: the
    pair parted 0.2 % faster than it met at 1 m/s."""
    world = load_world_scenario(REAR_END)
    for sc in world.cars.values():
        sc.scene.vehicle.vp[P.VP_CONTACT_DAMPING_RATIO] = 0.0
    world.cars["striking"].scene.initial["u_mps"] = speed_mps
    r = run_world_scenario(world)
    parting = r.cars["struck"].states[-1, L.U_MPS] - r.cars["striking"].states[-1, L.U_MPS]
    assert r.contact_events and not (r.contact("struck", "contact")[-1] > 0.5)  # apart again
    assert 0.97 * speed_mps < parting <= speed_mps, parting / speed_mps
    energy = _kinetic(r) + _drag_work(r)
    assert energy.max() <= energy[0] * (1.0 + 1e-9)


def test_the_order_of_the_cars_changes_no_bit(rear_end):
    world = load_world_scenario(REAR_END)
    world.cars = dict(reversed(world.cars.items()))
    swapped = run_world_scenario(world)
    for cid in rear_end.cars:
        a, b = rear_end.cars[cid], swapped.cars[cid]
        for name in ("states", "outputs", "final_state"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (cid, name)
        assert np.array_equal(rear_end.contact(cid, "contact_force_x_n"),
                              swapped.contact(cid, "contact_force_x_n"))
    assert rear_end.contact_events[0]["time_s"] == swapped.contact_events[0]["time_s"]


def _footprints(dx_m: float, dy_m: float, dyaw_rad: float = 0.0):
    vp = load_world_scenario(REAR_END).first.scene.vehicle.vp
    cars = []
    for x_m, y_m, yaw in ((0.0, 0.0, 0.0), (dx_m, dy_m, dyaw_rad)):
        x = np.zeros(L.N_STATE)
        x[L.X_M], x[L.Y_M], x[L.YAW_RAD] = x_m, y_m, yaw
        cc = np.zeros(N_CAR_CONTACT)
        footprint(vp, x, np.zeros((3, 3)), True, cc)
        cars.append(cc)
    return vp, cars


@pytest.mark.parametrize(("dx_m", "dy_m", "touch"), [
    (4.6 + 1e-3, 0.0, False),  # bumper to bumper, 1 mm apart
    (4.6 - 1e-3, 0.0, True),  # 1 mm into each other
    (0.0, 1.78 + 1e-3, False),  # side by side, 1 mm apart
    (0.0, 1.78 - 1e-3, True),
    (3.0, 1.9, False),  # corner to corner, apart
])
def test_the_force_is_zero_for_separated_boxes(dx_m, dy_m, touch):
    """The paper sedan's box: 1.35 + 0.85 m ahead of the CG, 1.55 + 0.85 m behind, 1.78 m
    wide; two of them at rest."""
    vp, (ca, cb) = _footprints(dx_m, dy_m)
    event = np.zeros(8)
    # the spring relaxed at zero depth (as if the pair had met there)
    depth = pair_contact(vp, vp, ca, cb, np.zeros((2, POLY_MAX, 2)), 0.001, event, 0.0)
    assert (depth > 0.0) == touch
    assert ca[CC_ACTIVE] == cb[CC_ACTIVE] == float(touch)
    if not touch:
        assert np.count_nonzero(ca[:6]) == 0 and np.count_nonzero(cb[:6]) == 0
    else:  # at rest, 1 mm deep: about the spring's push k d (the two springs in series),
        # less the damper's share over the step as the pair starts to part (zeta w h, 2.5 %)
        k = 0.5 * vp[P.VP_CONTACT_STIFFNESS_N_PER_M]
        force = np.hypot(cb[1], cb[2])
        assert force == pytest.approx(k * 1e-3, rel=0.05)
        np.testing.assert_array_equal(ca[1:3], -cb[1:3])


def test_cars_that_do_not_touch_step_as_alone():
    """Two cars 1 cm apart bumper to bumper, both braked: no contact, and each car's
    history is that car alone, bit for bit (the contact stage leaves them untouched)."""
    world = load_world_scenario(REAR_END)
    world.cars["striking"].scene.initial.update(u_mps=0.0, x_m=0.49)
    world.cars["striking"].keyframes = world.cars["struck"].keyframes
    r = run_world_scenario(world)
    assert not r.contact_events
    for cid, sc in world.cars.items():
        alone = run_scenario(sc)
        assert np.array_equal(r.cars[cid].states, alone.states), cid
        assert np.array_equal(r.cars[cid].outputs, alone.outputs), cid
        assert not r.contact(cid, "contact").any()


def test_a_car_resting_on_a_held_car_adds_no_creep():
    """15 % grade: the held car's brakes carry the resting car too (its push through the
    contact); from 10 s to 70 s the held car moves less than 1 micrometre (the acceptance:
    under 1 micrometre per minute), and so does the car resting on it."""
    r = run_world_scenario(load_world_scenario(HELD))
    held, resting = r.cars["held"], r.cars["resting"]
    t = held.time_s
    i10, i70 = np.searchsorted(t, 10.0), np.searchsorted(t, 70.0)
    assert t[i70] - t[i10] == pytest.approx(60.0)
    for res in (held, resting):
        assert np.isfinite(res.states).all()
        moved = np.hypot(*(res.states[i10:i70 + 1, k] - res.states[i10, k]
                           for k in (L.X_M, L.Y_M)))
        assert moved.max() < 1e-6, moved.max()
    # it does rest on it: in contact from the bounce on, pushing with about the resting
    # car's weight along the slope (m g sin(atan 0.15) = 2970 N; the split with the
    # resting car's own tires at rest is statically indeterminate)
    assert (r.contact("held", "contact")[i10:] > 0.5).all()
    assert (r.contact("resting", "contact")[i10:] > 0.5).all()
    push = -r.contact("held", "contact_force_x_n")[i10:]  # downhill on the held car (-e1)
    weight = 2041.0 * 9.81 * np.sin(np.arctan(0.15))
    assert (push > 0.5 * weight).all() and (push < 1.5 * weight).all()
    assert len(r.contact_events) == 1


def test_run_scenario_writes_the_contacts_section(tmp_path):
    """The headless runner's summary lists the contact events (ids, time, closing speed)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, "-m", "simserver", "run-scenario", str(REAR_END),
                    "--out", str(tmp_path), "--no-plots"], check=True, env=env,
                   capture_output=True, timeout=900)
    summary = json.loads((tmp_path / "summary.json").read_text())
    contacts = summary["contacts"]
    assert contacts["count"] == 1 and contacts["lost"] == 0
    (event,) = contacts["events"]
    assert {event["car_a"], event["car_b"]} == {"struck", "striking"}
    assert event["time_s"] == pytest.approx(0.167, abs=1e-3)
    assert event["closing_speed_mps"] == pytest.approx(3.0, abs=2e-3)
    for cid in ("struck", "striking"):
        car = contacts["cars"][cid]
        assert car["events"] == 1 and car["rows_in_contact"] > 10
        assert 0.0 < car["max_penetration_m"] < 0.05


def test_the_live_api_drains_the_events_with_the_ids():
    """The world stepped as the live loop steps it (``World.step``): the event ring drained
    with the cars' ids, the per-car output block, the count; an overrun ring says how many
    it lost."""
    from simserver.core.contact import EV_SEQ, EVENT_RING, K_EVENTS, drain_events
    from simserver.sim.scenario import start_run

    scenario = load_world_scenario(REAR_END)
    runs = {cid: start_run(sc, car_id=cid) for cid, sc in scenario.cars.items()}
    world = runs["struck"][0].world
    runs["striking"][0].move_to(world)
    for k in range(190):  # to 0.19 s: the boxes met at 0.167 s and still touch
        for sim, inputs in runs.values():
            sim.inputs[:] = inputs[k]
        world.step()
    events, seen, lost = world.contact_events(0)
    assert seen == world.contact_count() == 1 and lost == 0
    assert {events[0]["car_a"], events[0]["car_b"]} == {"struck", "striking"}
    assert world.contact_events(seen) == ([], 1, 0)
    for cid in ("struck", "striking"):
        block = world.car_contact(cid)
        assert block[0] == 1.0 and block[5] == 1.0  # in contact, one event
    assert world.car_contact("struck")[1] == -world.car_contact("striking")[1] > 0.0
    # a ring overrun: 70 events written, 64 kept, the 6 oldest reported lost
    contacts = world.data.contacts
    for n in range(1, 71):
        contacts.events[(n - 1) % EVENT_RING, EV_SEQ] = n
    contacts.count[K_EVENTS] = 70
    events, seen, lost = drain_events(contacts, 0)
    assert (seen, lost) == (70, 6)
    assert [e["seq"] for e in events] == list(range(7, 71))
