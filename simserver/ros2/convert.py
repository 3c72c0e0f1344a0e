"""A VehicleState as ROS 2 messages, with REP 103 and REP 105 frames and units.

Frames. simserver's world and body axes are ISO 8855 (x forward, y left, z up; angles
right-handed), which is REP 103's convention, so no axis changes sign:

- ``odom`` (REP 105's world-fixed frame, continuous, no jumps) is simserver's world frame:
  origin at the world origin, z up, x along the road's heading 0. A ``reset`` moves the
  car in it as the server does (this adapter does not re-anchor ``odom``).
- ``base_link`` is the body frame at the centre of gravity (the point the state
  describes), x forward, y left, z up. Its attitude is the protocol's
  ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (pitch positive nose down, roll positive left side
  up: both right-handed about y left and x forward), as a quaternion.

Units are SI (m, m/s, rad, rad/s, m/s^2), stamps in the adapter's chosen clock. The state
is simulation ground truth, so covariances are zero, which ROS reads as "unknown"; a
consumer that needs a noise model adds its own.

What the wire state does not carry is not invented: the heave and pitch/roll
accelerations are not in it, so the IMU's kinematic acceleration is ``(ax, ay, 0)``
along the road-plane body axes (the small body pitch and roll relative to the road are
neglected there), and the accelerometer reads it minus gravity (specific force, REP 145:
``+g`` along z at rest on level ground).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from simserver.ros2.wire import typestore
from simserver.wire import protocol as proto

WHEEL_JOINTS = ("front_left_wheel_joint", "front_right_wheel_joint",
                "rear_left_wheel_joint", "rear_right_wheel_joint")
"""Spin joints, in the protocol's wheel order FL, FR, RL, RR (position rad, velocity rad/s)."""

STEER_JOINTS = ("front_left_steer_joint", "front_right_steer_joint")
"""Road-wheel steer angles of the front wheels (rad, + left)."""

POSE = proto.STATE_POSE_FIELDS  # x, y, z, yaw, pitch, roll: the state table's world pose
BODY_VELOCITY = ("u_mps", "v_mps", "w_mps")
BODY_RATES = ("roll_rate_radps", "pitch_rate_radps", "yaw_rate_radps")
READS = proto.check_state_reads("simserver.ros2.convert", (
    "sim_time_s", *POSE, *BODY_VELOCITY, *BODY_RATES, "ax_mps2", "ay_mps2", "omega_radps",
    "steer_rad"))
"""Every state field the messages are made of (checked against the state table)."""


def quaternion_zyx(yaw: float, pitch: float, roll: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of ``Rz(yaw) Ry(pitch) Rx(roll)`` (intrinsic z-y'-x'')."""
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def specific_force(ax: float, ay: float, pitch: float, roll: float,
                   gravity_mps2: float) -> tuple[float, float, float]:
    """Accelerometer reading in body axes: ``(ax, ay, 0) - R^T (0, 0, -g)``.

    ``R^T (0, 0, -g)`` is gravity in body axes; its negative is ``g`` times the third row
    of ``R``: ``(-sin pitch, cos pitch sin roll, cos pitch cos roll)``.
    """
    cp = math.cos(pitch)
    return (ax - gravity_mps2 * math.sin(pitch),
            ay + gravity_mps2 * cp * math.sin(roll),
            gravity_mps2 * cp * math.cos(roll))


@dataclass
class StateConverter:
    """Turns decoded VehicleState records into the four published messages.

    The wheel spin angles are integrated here from the spin rates at the rate the
    adapter samples the state (trapezoidal rule on ``sim_time_s``), which is what a
    wheel encoder gives; they restart from where they were when sim time goes back (a
    reset or a load).
    """

    odom_frame: str = "odom"
    base_frame: str = "base_link"
    gravity_mps2: float = 9.81
    wheel_angle_rad: np.ndarray = field(default_factory=lambda: np.zeros(4))
    _last_time_s: float | None = None
    _last_omega: np.ndarray = field(default_factory=lambda: np.zeros(4))
    _last_steer: np.ndarray = field(default_factory=lambda: np.zeros(2))
    _steer_rate: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self) -> None:
        t = typestore().types
        self._Time = t["builtin_interfaces/msg/Time"]
        self._Header = t["std_msgs/msg/Header"]
        self._Point = t["geometry_msgs/msg/Point"]
        self._Quaternion = t["geometry_msgs/msg/Quaternion"]
        self._Vector3 = t["geometry_msgs/msg/Vector3"]
        self._Pose = t["geometry_msgs/msg/Pose"]
        self._PoseCov = t["geometry_msgs/msg/PoseWithCovariance"]
        self._Twist = t["geometry_msgs/msg/Twist"]
        self._TwistCov = t["geometry_msgs/msg/TwistWithCovariance"]
        self._Transform = t["geometry_msgs/msg/Transform"]
        self._TransformStamped = t["geometry_msgs/msg/TransformStamped"]
        self._Odometry = t["nav_msgs/msg/Odometry"]
        self._Imu = t["sensor_msgs/msg/Imu"]
        self._JointState = t["sensor_msgs/msg/JointState"]
        self._TFMessage = t["tf2_msgs/msg/TFMessage"]
        self._Clock = t["rosgraph_msgs/msg/Clock"]

    def _integrate_wheels(self, rec: Any) -> tuple[np.ndarray, np.ndarray]:
        """Spin rates, and the steer rates differenced between samples (not on the wire)."""
        omega = np.asarray(rec["omega_radps"], dtype=np.float64)
        steer = np.asarray(rec["steer_rad"][:2], dtype=np.float64)
        time_s = float(rec["sim_time_s"])
        if self._last_time_s is not None and time_s >= self._last_time_s:
            dt = time_s - self._last_time_s
            self.wheel_angle_rad += 0.5 * dt * (omega + self._last_omega)
            if dt > 0.0:
                self._steer_rate = (steer - self._last_steer) / dt
        else:
            self._steer_rate = np.zeros(2)
        self._last_time_s = time_s
        self._last_omega = omega
        self._last_steer = steer
        return omega, steer

    def clock(self, stamp_ns: int) -> Any:
        """A ``rosgraph_msgs/Clock`` of ``stamp_ns``."""
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return self._Clock(clock=self._Time(sec=sec, nanosec=nanosec))

    def messages(self, rec: Any, stamp_ns: int) -> dict[str, tuple[str, Any]]:
        """``{topic option: (ROS type, message)}`` for one state, stamped ``stamp_ns``."""
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        stamp = self._Time(sec=sec, nanosec=nanosec)
        header = self._Header(stamp=stamp, frame_id=self.odom_frame)
        x, y, z, yaw, pitch, roll = (float(rec[name]) for name in POSE)
        qx, qy, qz, qw = quaternion_zyx(yaw, pitch, roll)
        orientation = self._Quaternion(x=qx, y=qy, z=qz, w=qw)
        p, q, r = (float(rec[name]) for name in BODY_RATES)
        rates = self._Vector3(x=p, y=q, z=r)
        u, v, w = (float(rec[name]) for name in BODY_VELOCITY)
        zeros36 = np.zeros(36)
        odom = self._Odometry(
            header=header, child_frame_id=self.base_frame,
            pose=self._PoseCov(pose=self._Pose(position=self._Point(x=x, y=y, z=z),
                                               orientation=orientation),
                               covariance=zeros36),
            twist=self._TwistCov(
                twist=self._Twist(linear=self._Vector3(x=u, y=v, z=w), angular=rates),
                covariance=zeros36))
        fx, fy, fz = specific_force(float(rec["ax_mps2"]), float(rec["ay_mps2"]), pitch, roll,
                                    self.gravity_mps2)
        base_header = self._Header(stamp=stamp, frame_id=self.base_frame)
        zeros9 = np.zeros(9)
        imu = self._Imu(header=base_header, orientation=orientation,
                        orientation_covariance=zeros9, angular_velocity=rates,
                        angular_velocity_covariance=zeros9,
                        linear_acceleration=self._Vector3(x=fx, y=fy, z=fz),
                        linear_acceleration_covariance=zeros9)
        tf = self._TFMessage(transforms=[self._TransformStamped(
            header=header, child_frame_id=self.base_frame,
            transform=self._Transform(translation=self._Vector3(x=x, y=y, z=z),
                                      rotation=orientation))])
        omega, steer = self._integrate_wheels(rec)
        joints = self._JointState(
            header=self._Header(stamp=stamp, frame_id=""),
            name=[*WHEEL_JOINTS, *STEER_JOINTS],
            position=np.concatenate([self.wheel_angle_rad, steer]),
            velocity=np.concatenate([omega, self._steer_rate]),
            effort=np.zeros(0))
        return {"odom": ("nav_msgs/msg/Odometry", odom),
                "imu": ("sensor_msgs/msg/Imu", imu),
                "tf": ("tf2_msgs/msg/TFMessage", tf),
                "joint_states": ("sensor_msgs/msg/JointState", joints)}
