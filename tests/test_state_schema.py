"""One table of the published state (issue 29 item 5): ``protocol.STATE_FIELDS`` gives each
field's layout, source and history column, and the server's fill, the viewer's inverse and
the recorder's columns are derived from it (``simserver.wire.state_schema``,
``protocol.STATE_COLUMNS``).

The fill is checked against an oracle written out by hand below from the core's layout
(the list ``vehicle_slot.fill_state`` held before the table), on the real simulation, so
a wrong row in the table cannot pass by agreeing with itself.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from clients import recorder
from simserver.adapters.history import HISTORY_COLUMNS, column_unit
from simserver.core import layout as L
from simserver.server.app import new_simulation
from simserver.server.config import DEFAULT_SERVER_CONFIG, REPO_CONFIGS, load_server_config
from simserver.server.slot import COMPUTED_STATE_FIELDS, VehicleSlot
from simserver.sim.scene import load_scene
from simserver.testing import Client, OutputProcess, ServerProcess, client_command, client_env
from simserver.wire import protocol as proto
from simserver.wire import state_schema as S


def test_every_history_column_of_the_table_is_a_history_column_with_its_unit():
    columns = [c for c in proto.STATE_COLUMNS if c.history]
    assert len(columns) > 40
    for c in columns:
        assert c.name in HISTORY_COLUMNS, c.name
        assert c.unit == column_unit(c.name), (c.name, c.unit)
    for c in proto.STATE_COLUMNS:
        if not c.history:
            assert c.name not in HISTORY_COLUMNS, c.name


def test_a_copied_field_with_a_history_column_is_that_columns_core_slot():
    """Where a field is copied from the core and the history has its column, both name
    the same slot (the history's columns are the core's names): the viewer writes the
    field back where the server read it."""
    for f in proto.STATE_FIELDS:
        kind, name = proto.state_source(f)
        if kind in ("state", "output", "input") and f.history is not None:
            assert S.history_slot(f.history) == (kind, S.core_slot(kind, name)), f.name


def test_the_slot_computes_exactly_the_server_fields():
    assert set(COMPUTED_STATE_FIELDS) == set(S.SERVER_FIELDS)
    copied = {c.field for c in S.FILL}
    every = {f.name for f in proto.STATE_FIELDS} - {"version", "reserved"}
    assert copied | set(S.SERVER_FIELDS) == every and not copied & set(S.SERVER_FIELDS)


def test_an_unknown_source_is_an_error_naming_it():
    with pytest.raises(ValueError, match=r"state:no_such_\{w\}_m: not a slot"):
        S.core_slot("state", "no_such_{w}_m")
    with pytest.raises(ValueError, match="pose:heave_m: core.layout has no POSE_HEAVE_M"):
        S.core_slot("pose", "heave_m")
    assert S.history_slot("world_x_m") is None
    assert S.history_slot("input_gear") == ("input", L.IN_GEAR)
    assert S.history_slot("fz_{w}_n") == ("output", L.O_FZ)


def _oracle(sim) -> dict[str, object]:
    """What each copied field must hold: written out from core.layout, not the table."""
    x, out, inputs, pose = sim.x, sim.out, sim.inputs, sim.pose
    return {
        "x_m": pose[L.POSE_X_M], "y_m": pose[L.POSE_Y_M], "z_m": pose[L.POSE_Z_M],
        "yaw_rad": pose[L.POSE_YAW_RAD], "pitch_rad": pose[L.POSE_PITCH_RAD],
        "roll_rad": pose[L.POSE_ROLL_RAD],
        "u_mps": x[L.U_MPS], "v_mps": x[L.V_MPS], "w_mps": x[L.HEAVE_RATE_MPS],
        "roll_rate_radps": x[L.ROLL_RATE_RADPS], "pitch_rate_radps": x[L.PITCH_RATE_RADPS],
        "yaw_rate_radps": x[L.YAW_RATE_RADPS],
        "ax_mps2": out[L.O_AX_MPS2], "ay_mps2": out[L.O_AY_MPS2],
        "steer": inputs[L.IN_STEER], "throttle": inputs[L.IN_THROTTLE],
        "brake": inputs[L.IN_BRAKE], "parking_brake": inputs[L.IN_PARKING_BRAKE],
        "gear": inputs[L.IN_GEAR],
        "omega_radps": x[L.OMEGA], "kappa_lag": x[L.KAPPA], "tan_alpha_lag": x[L.TAN_ALPHA],
        "fx_n": out[L.O_FX], "fy_n": out[L.O_FY], "fz_n": out[L.O_FZ],
        "steer_rad": out[L.O_STEER], "mz_nm": out[L.O_MZ],
        "steering_wheel_angle_rad": x[L.STEERING_WHEEL_ANGLE_RAD],
        "steering_wheel_torque_nm": x[L.STEERING_WHEEL_TORQUE_NM],
        "damping_active": x[L.DAMPING_ACTIVE], "wheel_contact": x[L.IN_CONTACT],
        "gear_engaged": x[L.GEAR_ENGAGED], "lockup_engaged": x[L.LOCKUP_ENGAGED],
        "engine_speed_radps": x[L.ENGINE_SPEED_RADPS],
    }


@pytest.mark.parametrize("scene", ["flat_paper_sedan", "hills_paper_sedan"])
def test_the_published_state_holds_the_simulations_values(scene):
    """The bytes the loop publishes (``fill_state``), decoded, hold the simulation's
    values in the wire's types, field by field, while the car drives and steers."""
    cfg = load_server_config(DEFAULT_SERVER_CONFIG, viewer="off")
    slot = VehicleSlot(cfg, new_simulation(load_scene(REPO_CONFIGS / "scenes" /
                                                      f"{scene}.yaml"), cfg.period_s))
    dtype = proto.STATE_DTYPE
    for k in range(600):
        inputs = slot.sim.inputs
        inputs[L.IN_GEAR], inputs[L.IN_THROTTLE] = L.GEAR_D, 0.5
        inputs[L.IN_STEER] = 0.4 * math.sin(0.01 * k)
        slot.advance()
        if k % 150 != 149:
            continue
        rec = proto.decode_state(slot.fill_state(0, False))
        expected = _oracle(slot.sim)
        copied = {c.field: c for c in S.FILL}
        assert set(expected) <= set(copied)
        sources = (slot.sim.x, slot.sim.out, slot.sim.inputs, slot.sim.pose)
        for name in set(copied) - set(expected):  # a field added after the oracle
            expected[name] = sources[copied[name].array][copied[name].slot]
        for name, value in expected.items():
            want = np.asarray(value).astype(dtype.fields[name][0].base)
            np.testing.assert_array_equal(rec[name], want, err_msg=name)
        assert rec["sim_time_s"] == slot.tick * slot.sim.dt_s and rec["tick"] == slot.tick
    assert rec["u_mps"] > 1.0 and abs(rec["steer"]) > 0.0  # it did drive and steer


def test_the_viewers_inverse_puts_every_field_back_in_its_slot():
    """Random core rows -> a state record (the server's fill) -> bytes -> decoded -> core
    rows (the viewer's inverse): each slot the state carries comes back as its float32
    (or integer) value; the time and the held wheels land in the history's slots."""
    rng = np.random.default_rng(29)
    x, out = rng.uniform(-50, 50, L.N_STATE), rng.uniform(-5000, 5000, L.N_OUT)
    for block in (L.DAMPING_ACTIVE, L.IN_CONTACT):
        x[block] = rng.integers(0, 2, 4)
    x[L.GEAR_ENGAGED], x[L.LOCKUP_ENGAGED] = -1, 1
    inputs = np.array([0.25, 0.5, 0.75, 1.0, L.GEAR_R])
    pose = rng.uniform(-3, 3, L.N_POSE)
    rec = proto.new_state_record()
    S.fill_record(rec, x, out, inputs, pose)
    rec["sim_time_s"], rec["brake_held"] = 12.345, [1, 0, 1, 0]
    wire = proto.decode_state(rec.tobytes())
    back_x, back_out = np.full(L.N_STATE, np.nan), np.full(L.N_OUT, np.nan)
    back_in, back_pose = np.full(L.N_INPUT, np.nan), np.full(L.N_POSE, np.nan)
    S.record_to_rows(wire, back_x, back_out, back_in)
    S.record_to_pose(wire, back_pose)
    for c in S.FILL:
        kind = S.ARRAYS[c.array]
        if kind == "pose":
            np.testing.assert_array_equal(back_pose[c.slot], pose[c.slot])
            continue
        src = {"state": x, "output": out, "input": inputs}[kind]
        dst = {"state": back_x, "output": back_out, "input": back_in}[kind]
        want = np.asarray(src[c.slot]).astype(proto.STATE_DTYPE.fields[c.field][0].base)
        np.testing.assert_array_equal(dst[c.slot], want.astype(np.float64), err_msg=c.field)
    assert back_x[L.TIME_S] == 12.345
    np.testing.assert_array_equal(back_x[L.WHEEL_HELD], [1, 0, 1, 0])


@pytest.mark.timeout(240)
def test_a_live_server_publishes_every_field_and_the_recorder_records_each(tmp_path):
    """End to end, real processes: states a client decodes while the car drives and
    steers, and the recorder's file of the same run. The file has exactly the recorder's
    columns; the row of each watched tick holds every field of the state table in its
    column (a field added to the table is published and recorded with no other change)."""
    server = ServerProcess(vehicle_id="schema", scene="flat_paper_sedan")
    out = tmp_path / "rec"
    proc = OutputProcess(client_command("recorder", "--out", str(out), "--quiet",
                                        *server.client_args()), env=client_env())
    try:
        assert proc.wait_ready(60.0), proc.text()
        with Client(server) as driver:
            driver.drive(1.0, throttle=0.5, steer=0.3)
            watched = driver.next_states(20)
            driver.drive(0.2, throttle=0.5, steer=0.3)
        assert proc.stop(timeout_s=60.0) == 0, proc.text()
    finally:
        proc.kill()
        server.stop()
    table = pq.read_table(out / "history.parquet")
    assert table.column_names == [c.name for c in recorder.COLUMNS]
    cols = {name: table.column(name).to_numpy() for name in table.column_names}
    row_of = {int(t): i for i, t in enumerate(cols["tick"])}
    found = [s for s in watched if int(s["tick"]) in row_of]
    assert len(found) >= 10, "the recorder missed most of the watched states"
    assert max(float(s["u_mps"]) for s in found) > 0.3  # it drove
    for state in found:
        i = row_of[int(state["tick"])]
        for c in proto.STATE_COLUMNS:
            sent = state[c.field] if c.wheel is None else state[c.field][c.wheel]
            want = np.asarray(sent).astype(c.dtype)
            assert cols[c.name][i] == want, (c.name, int(state["tick"]))
