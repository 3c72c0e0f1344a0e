"""Powertrain and brakes: driver pedals to wheel torques.

Powertrain: the throttle scales a drive torque at the wheels limited by a torque cap
(first gear) and a power cap (``T <= P_max / |omega|``), with gears P, R, N, D. The driven
axle has an open differential: equal torque to its two wheels, whatever their speeds.
With both axles driven the split between them is fixed (a centre differential).
P locks the driven wheels (modelled as a brake of unlimited capacity on them).

Brakes: a capacity per wheel. The pedal's torque is split front/rear by
``brake_front_fraction``; the parking brake acts on the rear wheels. How the capacity is
applied (static friction at zero spin) is the integrator's job, see
``core.integrator.step``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from simserver.core.layout import (
    GEAR_D,
    GEAR_P,
    GEAR_R,
    IN_BRAKE,
    IN_GEAR,
    IN_PARKING_BRAKE,
    IN_THROTTLE,
    N_FRONT_WHEELS,
    N_WHEELS,
    OMEGA0,
)
from simserver.core.params import (
    DRIVEN_BOTH,
    DRIVEN_FRONT,
    VP_BRAKE_FRONT_FRACTION,
    VP_BRAKE_TORQUE_MAX_NM,
    VP_DRIVE_FRONT_FRACTION,
    VP_DRIVE_POWER_MAX_W,
    VP_DRIVE_TORQUE_MAX_NM,
    VP_DRIVEN_AXLE,
    VP_PARKING_BRAKE_TORQUE_NM,
    VP_REVERSE_TORQUE_MAX_NM,
)

PARK_LOCK_TORQUE_NM = 1.0e9
"""Capacity standing for the parking pawl: nothing a tire can do overcomes it."""
POWER_LIMIT_MIN_SPEED_RADPS = 1.0
"""Below this wheel speed the power cap is not applied (T_max governs at launch)."""


@nb.njit(cache=True)
def axle_torque_shares(vp: np.ndarray, share: np.ndarray) -> None:
    """Fraction of the total drive torque each wheel receives (open differentials)."""
    axle = int(vp[VP_DRIVEN_AXLE])
    if axle == DRIVEN_FRONT:
        front = 1.0
    elif axle == DRIVEN_BOTH:
        front = vp[VP_DRIVE_FRONT_FRACTION]
    else:
        front = 0.0
    share[0] = share[1] = 0.5 * front
    share[2] = share[3] = 0.5 * (1.0 - front)


@nb.njit(cache=True)
def wheel_torques(
    x: np.ndarray,
    vp: np.ndarray,
    inputs: np.ndarray,
    drive_nm: np.ndarray,
    brake_cap_nm: np.ndarray,
) -> None:
    """Drive torque and brake capacity per wheel for the current pedals, gear and spin.

    ``drive_nm`` is signed (positive drives forward); ``brake_cap_nm`` is a magnitude.
    """
    axle_torque_shares(vp, drive_nm)  # shares first, scaled below
    gear = int(inputs[IN_GEAR])
    throttle = inputs[IN_THROTTLE]

    # mean spin of the driven wheels sets the power limit
    omega_driven = 0.0
    for i in range(N_WHEELS):
        omega_driven += drive_nm[i] * x[OMEGA0 + i]
    torque_cap = vp[VP_DRIVE_TORQUE_MAX_NM]
    direction = 0.0
    if gear == GEAR_D:
        direction = 1.0
    elif gear == GEAR_R:
        direction = -1.0
        torque_cap = vp[VP_REVERSE_TORQUE_MAX_NM]
    if abs(omega_driven) > POWER_LIMIT_MIN_SPEED_RADPS:
        torque_cap = min(torque_cap, vp[VP_DRIVE_POWER_MAX_W] / abs(omega_driven))
    total = direction * throttle * torque_cap

    brake_total = inputs[IN_BRAKE] * vp[VP_BRAKE_TORQUE_MAX_NM]
    front = vp[VP_BRAKE_FRONT_FRACTION]
    park = inputs[IN_PARKING_BRAKE] * vp[VP_PARKING_BRAKE_TORQUE_NM]
    for i in range(N_WHEELS):
        share = drive_nm[i]
        drive_nm[i] = total * share
        if i < N_FRONT_WHEELS:
            brake_cap_nm[i] = 0.5 * front * brake_total
        else:
            brake_cap_nm[i] = 0.5 * (1.0 - front) * brake_total + park
        if gear == GEAR_P and share > 0.0:
            brake_cap_nm[i] = PARK_LOCK_TORQUE_NM
