"""The vehicle's pose in world axes, from its pose on the inclined road plane.

The core integrates the motion in the road plane (``X_M``, ``Y_M`` along the plane's axes
``e1``, ``e2``; ``YAW_RAD`` from ``e1`` toward ``e2``; roll and pitch of the body on its
suspension). The wire protocol and the viewer want world axes: position of the CG and
the body attitude as intrinsic z-y'-x'' angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (ISO
8855 signs: pitch positive nose down, roll positive left side up).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.layout import (
    HEAVE_M,
    PITCH_RAD,
    POSE_PITCH_RAD,
    POSE_ROLL_RAD,
    POSE_X_M,
    POSE_Y_M,
    POSE_YAW_RAD,
    POSE_Z_M,
    REF_CROSS_SLOPE_PCT,
    REF_GRADE_PCT,
    REF_HEIGHT_M,
    ROLL_RAD,
    X_M,
    Y_M,
    YAW_RAD,
)
from simserver.core.road import road_frame


@nb.njit(cache=True)
def world_pose(x: np.ndarray, axes: np.ndarray, cg_height_m: float, pose: np.ndarray) -> None:
    """Write ``(x, y, z, yaw, pitch, roll)`` of the CG in world axes into ``pose``.

    Parameters
    ----------
    x : float64[N_STATE]
        Vehicle state.
    axes : float64[3, 3]
        Rows ``e1``, ``e2``, ``n`` of the road plane in world axes
        (``core.road.road_axes``).
    cg_height_m : float
        Static CG height above the road.
    pose : float64[N_POSE]
        Written, ``core.layout.POSE_*`` slots. The yaw is continuous: it follows the
        road-plane yaw without wrapping.
    """
    lift = cg_height_m + x[HEAVE_M]
    for k in range(3):  # POSE_X_M, POSE_Y_M, POSE_Z_M
        pose[POSE_X_M + k] = x[X_M] * axes[0, k] + x[Y_M] * axes[1, k] + lift * axes[2, k]
    # body axes in the road frame: Rz(psi) Ry(theta) Rx(phi); columns = body x, y, z
    psi = x[YAW_RAD]
    cz, sz = np.cos(psi), np.sin(psi)
    cy, sy = np.cos(x[PITCH_RAD]), np.sin(x[PITCH_RAD])
    cx, sx = np.cos(x[ROLL_RAD]), np.sin(x[ROLL_RAD])
    # columns of the road-frame rotation: body x, y and z axes in (e1, e2, n) components
    bx0, bx1, bx2 = cz * cy, sz * cy, -sy
    by0, by1, by2 = cz * sy * sx - sz * cx, sz * sy * sx + cz * cx, cy * sx
    bz0, bz1, bz2 = cz * sy * cx + sz * sx, sz * sy * cx - cz * sx, cy * cx
    # world components w = b0 e1 + b1 e2 + b2 n (only those the angles need)
    wx0 = bx0 * axes[0, 0] + bx1 * axes[1, 0] + bx2 * axes[2, 0]
    wx1 = bx0 * axes[0, 1] + bx1 * axes[1, 1] + bx2 * axes[2, 1]
    wx2 = bx0 * axes[0, 2] + bx1 * axes[1, 2] + bx2 * axes[2, 2]
    wy2 = by0 * axes[0, 2] + by1 * axes[1, 2] + by2 * axes[2, 2]
    wz2 = bz0 * axes[0, 2] + bz1 * axes[1, 2] + bz2 * axes[2, 2]
    yaw_wrapped = np.arctan2(wx1, wx0)
    # continuous yaw: the road-plane yaw plus the wrapped difference
    diff = yaw_wrapped - psi
    diff = (diff + np.pi) % (2.0 * np.pi) - np.pi
    pose[POSE_YAW_RAD] = psi + diff
    pose[POSE_PITCH_RAD] = np.arcsin(min(1.0, max(-1.0, -wx2)))
    pose[POSE_ROLL_RAD] = np.arctan2(wy2, wz2)


@nb.njit(cache=True)
def world_poses(x: np.ndarray, vp: np.ndarray, cg_height_slot: int, on_plane: bool,
                axes: np.ndarray, scratch_axes: np.ndarray, rows: np.ndarray,
                poses: np.ndarray) -> None:
    """The world pose of every car of a world (``x``: float64[n_cars, N_STATE], ``vp``:
    float64[n_cars, N_VEHICLE_PARAM], its CG height at ``cg_height_slot``) into ``poses``
    (float64[n_cars, N_POSE]), by the one rule of the published pose
    (``simserver.sim.simulation.pose_of``, car by car): on the plane terrain from the road
    plane ``axes``; on another terrain from the reference plane fitted under the wheels
    in the step before (its slopes and height are states, docs/model.md section 11;
    ``scratch_axes`` float64[3, 3] takes its axes). One call for the live server's
    whole world a tick instead of one per car (``simserver.server.state_frame``). Only
    the cars ``rows`` (int64) are posed: those that publish this tick."""
    for c in rows:
        if on_plane:
            world_pose(x[c], axes, vp[c, cg_height_slot], poses[c])
        else:
            road_frame(x[c, REF_GRADE_PCT], x[c, REF_CROSS_SLOPE_PCT], scratch_axes)
            world_pose(x[c], scratch_axes, vp[c, cg_height_slot], poses[c])
            poses[c, POSE_Z_M] += x[c, REF_HEIGHT_M]


@nb.njit(cache=True)
def road_pose(pose: np.ndarray, axes: np.ndarray, cg_height_m: float, x: np.ndarray) -> None:
    """Inverse of ``world_pose``: write ``X_M``, ``Y_M``, ``YAW_RAD``, ``HEAVE_M``,
    ``PITCH_RAD`` and ``ROLL_RAD`` of ``x`` from a world pose (for the live viewer, which
    receives world poses on the wire)."""
    px, py, pz = pose[POSE_X_M], pose[POSE_Y_M], pose[POSE_Z_M]
    x[X_M] = px * axes[0, 0] + py * axes[0, 1] + pz * axes[0, 2]
    x[Y_M] = px * axes[1, 0] + py * axes[1, 1] + pz * axes[1, 2]
    x[HEAVE_M] = px * axes[2, 0] + py * axes[2, 1] + pz * axes[2, 2] - cg_height_m
    cz, sz = np.cos(pose[POSE_YAW_RAD]), np.sin(pose[POSE_YAW_RAD])
    cy, sy = np.cos(pose[POSE_PITCH_RAD]), np.sin(pose[POSE_PITCH_RAD])
    cx, sx = np.cos(pose[POSE_ROLL_RAD]), np.sin(pose[POSE_ROLL_RAD])
    # body x, y, z axes in world components (columns of Rz Ry Rx) ...
    bx = (cz * cy, sz * cy, -sy)
    by = (cz * sy * sx - sz * cx, sz * sy * sx + cz * cx, cy * sx)
    bz = (cz * sy * cx + sz * sx, sz * sy * cx - cz * sx, cy * cx)
    # ... then in road components (rows of axes are e1, e2, n)
    r00 = bx[0] * axes[0, 0] + bx[1] * axes[0, 1] + bx[2] * axes[0, 2]
    r10 = bx[0] * axes[1, 0] + bx[1] * axes[1, 1] + bx[2] * axes[1, 2]
    r20 = bx[0] * axes[2, 0] + bx[1] * axes[2, 1] + bx[2] * axes[2, 2]
    r21 = by[0] * axes[2, 0] + by[1] * axes[2, 1] + by[2] * axes[2, 2]
    r22 = bz[0] * axes[2, 0] + bz[1] * axes[2, 1] + bz[2] * axes[2, 2]
    yaw_wrapped = np.arctan2(r10, r00)
    diff = (yaw_wrapped - pose[POSE_YAW_RAD] + np.pi) % (2.0 * np.pi) - np.pi
    x[YAW_RAD] = pose[POSE_YAW_RAD] + diff
    x[PITCH_RAD] = np.arcsin(min(1.0, max(-1.0, -r20)))
    x[ROLL_RAD] = np.arctan2(r21, r22)
