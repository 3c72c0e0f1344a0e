"""World pose from the road-plane state: checked against an independent rotation build."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from simserver.core import layout as L
from simserver.core.pose import road_pose, world_pose
from simserver.core.road import road_axes


def rot(axis: int, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    m = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m[i, i] = c
    m[j, j] = c
    m[i, j] = -s
    m[j, i] = s
    return m


@settings(max_examples=100, deadline=None)
@given(grade=st.floats(-30, 30), cross=st.floats(-30, 30), yaw=st.floats(-20, 20),
       pitch=st.floats(-0.2, 0.2), roll=st.floats(-0.2, 0.2), px=st.floats(-100, 100),
       py=st.floats(-100, 100), heave=st.floats(-0.1, 0.1))
def test_world_pose_matches_rotation_matrices(grade, cross, yaw, pitch, roll, px, py, heave):
    x = np.zeros(L.N_STATE)
    x[L.X_M], x[L.Y_M], x[L.YAW_RAD] = px, py, yaw
    x[L.PITCH_RAD], x[L.ROLL_RAD], x[L.HEAVE_M] = pitch, roll, heave
    axes = road_axes(grade, cross)
    pose = np.zeros(L.N_POSE)
    world_pose(x, axes, 0.5, pose)
    frame = axes.T  # columns e1, e2, n
    r_world = frame @ rot(2, yaw) @ rot(1, pitch) @ rot(0, roll)
    expected_pos = frame @ np.array([px, py, 0.5 + heave])
    np.testing.assert_allclose(pose[[L.POSE_X_M, L.POSE_Y_M, L.POSE_Z_M]], expected_pos,
                               atol=1e-9)
    r_back = (rot(2, pose[L.POSE_YAW_RAD]) @ rot(1, pose[L.POSE_PITCH_RAD])
              @ rot(0, pose[L.POSE_ROLL_RAD]))
    np.testing.assert_allclose(r_back, r_world, atol=1e-9)
    assert abs(pose[L.POSE_YAW_RAD] - yaw) < math.pi  # continuous with the road-plane heading
    back = np.zeros(L.N_STATE)
    road_pose(pose, axes, 0.5, back)  # and the inverse gives the road-plane pose again
    for k in (L.X_M, L.Y_M, L.HEAVE_M, L.YAW_RAD, L.PITCH_RAD, L.ROLL_RAD):
        assert abs(back[k] - x[k]) < 1e-8, k


def test_flat_road_is_identity():
    x = np.zeros(L.N_STATE)
    x[L.X_M], x[L.YAW_RAD] = 3.0, 7.0
    pose = np.zeros(L.N_POSE)
    world_pose(x, road_axes(0.0, 0.0), 0.5, pose)
    expected = np.zeros(L.N_POSE)
    expected[L.POSE_X_M], expected[L.POSE_Z_M], expected[L.POSE_YAW_RAD] = 3.0, 0.5, 7.0
    np.testing.assert_allclose(pose, expected, atol=1e-12)
