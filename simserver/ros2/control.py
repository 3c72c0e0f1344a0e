"""Speed and steering targets (ROS commands) to the car's pedals, gear and steer.

ROS stacks command a car by targets: a speed and a road-wheel angle
(``ackermann_msgs/AckermannDrive``) or a speed and a yaw rate (``geometry_msgs/Twist``).
simserver takes pedals and a steering-wheel position. This module is the driver in
between, run by the adapter at its rate on the newest state.

Speed controller (:class:`SpeedController`), per sample of period ``dt``:

1. **Direction.** A target above ``STOP_TARGET_MPS`` in magnitude selects gear D (> 0) or
   R (< 0). If the car still moves the other way faster than ``SHIFT_SPEED_MPS``, it
   first brakes as for a zero target, then shifts.
2. **Reference.** The reference speed moves toward the target at the command's
   ``acceleration`` (a ramp), or jumps to it when that is 0 ("as fast as possible",
   ackermann_msgs' meaning). Entering drive it starts from the measured speed.
3. **Demand.** An acceleration demand along the direction of travel, in m/s^2:
   feed-forward of the grade (``-g sin(pitch)``, pitch positive nose down) and of the
   aerodynamic drag (``rho CdA u^2 / 2m``), plus a PI on the speed error
   (``KP_PER_S``, ``KI_PER_S2``). Anti-windup twice over: the integral only runs within
   ``INTEGRAL_BAND_MPS`` of the reference (it trims the small steady offset the
   feed-forward leaves, such as rolling losses; the approach to a new speed is the
   proportional term's, so a step does not wind it up into an overshoot), and it does not
   grow while the pedal it drives is saturated in the error's direction (conditional
   integration); it is bounded by ``INTEGRAL_MAX_MPS2``.
4. **Pedals, blended.** A positive demand is throttle, ``demand / a_drive_max`` (the
   acceleration of full throttle: drive torque cap / (wheel radius x mass); reverse
   torque in R); a negative demand is brake, ``-demand / a_brake_max`` (full-pedal brake
   torque / (radius x mass)). Never both at once; each clipped to [0, 1].
5. **Zero target: stop and hold.** With a target within ``STOP_TARGET_MPS`` of zero the
   throttle is 0 and the brake pedal is held at
   ``clip((a_stop + g |sin(pitch)|) / a_brake_max, HOLD_PEDAL_MIN, 1)``, with ``a_stop``
   the command's ``acceleration`` or ``STOP_DECEL_MPS2``: the car decelerates at about
   ``a_stop`` and, once stopped, the same pedal keeps it still through the car's own
   brake hold (the model holds a braked wheel at zero spin, VehicleState ``brake_held``),
   the way a driver keeps the pedal down. The PI integral is cleared, so a later drive
   starts without a stale wind-up.

Steering (:func:`steer_command`): the road-wheel angle target (rate-limited by
``steering_angle_velocity`` when it is positive) times the vehicle's steering ratio,
divided by its steering-wheel angle at full lock, clipped to [-1, 1] (the protocol's
normalised steer, + left, as ROS's). A Twist's yaw rate becomes a road-wheel angle
through the kinematic bicycle model, ``atan(wheelbase x yaw_rate / speed)``, limited to
the car's lock (:func:`twist_steer_angle`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from simserver.wire.protocol import Gear

KP_PER_S = 1.5
"""Proportional gain: m/s^2 of demand per m/s of speed error."""
KI_PER_S2 = 0.6
"""Integral gain: m/s^2 of demand per m of integrated speed error."""
INTEGRAL_BAND_MPS = 0.5
"""The integral runs only while the speed is this close to the reference."""
INTEGRAL_MAX_MPS2 = 4.0
"""Bound of the integral term (beyond any grade the car can climb, to end wind-up)."""
STOP_TARGET_MPS = 0.01
"""A target speed within this of zero is a stop-and-hold request."""
SHIFT_SPEED_MPS = 0.1
"""The car shifts between D and R only below this speed."""
STOP_DECEL_MPS2 = 3.0
"""Deceleration of a stop when the command gives none (a firm, ordinary stop)."""
HOLD_PEDAL_MIN = 0.3
"""Least brake pedal of a stop and hold (well above what a 10 % grade needs)."""


@dataclass(frozen=True)
class VehicleLimits:
    """The few vehicle numbers the controller needs (from the server's vehicle)."""

    steering_ratio: float
    steering_wheel_max_rad: float
    wheelbase_m: float
    drive_accel_max_mps2: float
    reverse_accel_max_mps2: float
    brake_decel_max_mps2: float
    drag_per_speed2_per_m: float  # rho CdA / 2m: drag deceleration per (m/s)^2
    gravity_mps2: float

    @property
    def max_road_wheel_rad(self) -> float:
        """Road-wheel angle at full steering lock."""
        return self.steering_wheel_max_rad / self.steering_ratio

    @classmethod
    def from_vehicle(cls, vp: Any, tp: Any) -> VehicleLimits:
        """From a packed vehicle (``adapters.config.load_vehicle``'s ``vp`` and ``tp``)."""
        from simserver.core import params as P
        from simserver.core.layout import N_WHEELS
        from simserver.core.tire_layout import TP_RADIUS_M

        mass = float(vp[P.VP_MASS_KG])
        radius = float(sum(tp[i][TP_RADIUS_M] for i in range(N_WHEELS)) / N_WHEELS)
        return cls(
            steering_ratio=float(vp[P.VP_STEERING_RATIO]),
            steering_wheel_max_rad=float(vp[P.VP_STEERING_WHEEL_MAX_RAD]),
            wheelbase_m=float(vp[P.VP_CG_TO_FRONT_AXLE_M] + vp[P.VP_CG_TO_REAR_AXLE_M]),
            drive_accel_max_mps2=float(vp[P.VP_DRIVE_TORQUE_MAX_NM]) / (radius * mass),
            reverse_accel_max_mps2=float(vp[P.VP_REVERSE_TORQUE_MAX_NM]) / (radius * mass),
            brake_decel_max_mps2=float(vp[P.VP_BRAKE_TORQUE_MAX_NM]) / (radius * mass),
            drag_per_speed2_per_m=0.5 * float(vp[P.VP_AIR_DENSITY_KGPM3])
            * float(vp[P.VP_DRAG_AREA_M2]) / mass,
            gravity_mps2=float(vp[P.VP_GRAVITY_MPS2]),
        )


@dataclass
class DriveTarget:
    """What a ROS command asks for (SI units, ROS signs)."""

    speed_mps: float = 0.0
    accel_limit_mps2: float = 0.0  # 0: as fast as possible
    steer_rad: float = 0.0  # road-wheel angle, + left
    steer_rate_limit_radps: float = 0.0  # 0: no limit


@dataclass(frozen=True)
class Pedals:
    """One command for the server."""

    steer: float
    throttle: float
    brake: float
    gear: int


def _clip(value: float, lo: float, hi: float) -> float:
    return lo if value < lo else hi if value > hi else value


def twist_steer_angle(speed_mps: float, yaw_rate_radps: float, limits: VehicleLimits) -> float:
    """Road-wheel angle that gives ``yaw_rate`` at ``speed`` (kinematic bicycle), at lock most.

    A car cannot turn on the spot: with a target speed of (nearly) zero the angle is 0.
    """
    if abs(speed_mps) < STOP_TARGET_MPS:
        return 0.0
    angle = math.atan(limits.wheelbase_m * yaw_rate_radps / speed_mps)
    return _clip(angle, -limits.max_road_wheel_rad, limits.max_road_wheel_rad)


def steer_command(road_wheel_rad: float, limits: VehicleLimits) -> float:
    """Normalised steer for a road-wheel angle: angle x ratio / steering-wheel max."""
    return _clip(road_wheel_rad * limits.steering_ratio / limits.steering_wheel_max_rad,
                 -1.0, 1.0)


class SpeedController:
    """The speed controller and steering of the module docstring; one per adapter."""

    def __init__(self, limits: VehicleLimits) -> None:
        self.limits = limits
        self.gear = int(Gear.D)
        self.integral_mps2 = 0.0
        self.reference_mps: float | None = None  # None: not driving (stopped or holding)
        self.steer_rad = 0.0

    def reset(self) -> None:
        """Forget the integral and the reference (no command, or a server reset)."""
        self.integral_mps2 = 0.0
        self.reference_mps = None

    def _steer(self, target: DriveTarget, dt: float) -> float:
        goal = _clip(target.steer_rad, -self.limits.max_road_wheel_rad,
                     self.limits.max_road_wheel_rad)
        if target.steer_rate_limit_radps > 0.0:
            step = target.steer_rate_limit_radps * dt
            goal = _clip(goal, self.steer_rad - step, self.steer_rad + step)
        self.steer_rad = goal
        return steer_command(goal, self.limits)

    def _hold(self, target: DriveTarget, pitch_rad: float, steer: float) -> Pedals:
        self.reset()
        lim = self.limits
        a_stop = target.accel_limit_mps2 if target.accel_limit_mps2 > 0.0 else STOP_DECEL_MPS2
        pedal = (a_stop + lim.gravity_mps2 * abs(math.sin(pitch_rad))) / lim.brake_decel_max_mps2
        return Pedals(steer, 0.0, _clip(pedal, HOLD_PEDAL_MIN, 1.0), self.gear)

    def update(self, target: DriveTarget, speed_mps: float, pitch_rad: float,
               dt: float) -> Pedals:
        """Pedals for ``target`` given the measured body speed ``u`` and pitch.

        Parameters
        ----------
        target : DriveTarget
            The newest ROS command.
        speed_mps : float
            Body longitudinal velocity (VehicleState ``u_mps``).
        pitch_rad : float
            Pitch, positive nose down (VehicleState ``pitch_rad``, road grade included).
        dt : float
            Time since the previous update (s); 0 freezes the integral and the ramp.
        """
        lim = self.limits
        steer = self._steer(target, dt)
        if abs(target.speed_mps) < STOP_TARGET_MPS:
            return self._hold(target, pitch_rad, steer)
        want = int(Gear.D) if target.speed_mps > 0.0 else int(Gear.R)
        direction = 1.0 if want == int(Gear.D) else -1.0
        if want != self.gear:
            if abs(speed_mps) > SHIFT_SPEED_MPS:  # still rolling the other way: stop first
                return self._hold(DriveTarget(), pitch_rad, steer)
            self.gear = want
            self.reset()
        speed_dir = direction * speed_mps  # speed along the direction of travel
        goal = abs(target.speed_mps)
        if self.reference_mps is None:
            self.reference_mps = max(0.0, speed_dir)
        if target.accel_limit_mps2 > 0.0:
            step = target.accel_limit_mps2 * dt
            self.reference_mps = _clip(goal, self.reference_mps - step, self.reference_mps + step)
        else:
            self.reference_mps = goal
        error = self.reference_mps - speed_dir
        feed_forward = (-direction * lim.gravity_mps2 * math.sin(pitch_rad)
                        + lim.drag_per_speed2_per_m * speed_mps * speed_mps)
        a_drive_max = lim.drive_accel_max_mps2 if want == int(Gear.D) \
            else lim.reverse_accel_max_mps2
        demand = feed_forward + KP_PER_S * error + self.integral_mps2
        saturated_up = demand >= a_drive_max and error > 0.0
        saturated_down = demand <= -lim.brake_decel_max_mps2 and error < 0.0
        if abs(error) < INTEGRAL_BAND_MPS and not (saturated_up or saturated_down):
            self.integral_mps2 = _clip(self.integral_mps2 + KI_PER_S2 * error * dt,
                                       -INTEGRAL_MAX_MPS2, INTEGRAL_MAX_MPS2)
        if demand >= 0.0:
            return Pedals(steer, _clip(demand / max(a_drive_max, 1e-9), 0.0, 1.0), 0.0,
                          self.gear)
        return Pedals(steer, 0.0, _clip(-demand / lim.brake_decel_max_mps2, 0.0, 1.0),
                      self.gear)
