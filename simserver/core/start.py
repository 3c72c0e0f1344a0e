"""Starting on the move: the wheels, slip states and powertrain relaxed at a velocity.

A state built from a pose and a velocity has the wheels spinning at ``omega = u / R`` and
the lagged slip states at zero. At speed that is not the steady state: rolling resistance,
the drag and the drive torque need a small longitudinal slip, so the slip states would
relax toward it in the first moments (``B/|u|``, ``b/|u|``, paper eqs. 16 and 26) and the
engine would have to find its speed. ``settle_at_velocity`` runs the step with the body's
motion held (pose, velocities, suspension): the wheels, slip states, brakes' latches and
the powertrain find the values they hold at that velocity, and the car starts from them
without a transient (docs/model.md section 13).

``start_powertrain`` first puts the automatic gearbox in the gear its schedule chooses for
the speed, the lock-up where its rules put it and the engine at the turbine's speed, so
that the settling only has to relax, not to shift.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from simserver.core.integrator import step
from simserver.core.layout import (
    ENGINE_SPEED_RADPS,
    GEAR_D,
    GEAR_ENGAGED,
    GEAR_R,
    IN_GEAR,
    IN_THROTTLE,
    LOCKUP_ENGAGED,
    N_WHEELS,
    OMEGA0,
    SHIFT_TIMER_S,
    TIME_S,
    U_MPS,
)
from simserver.core.model import Data, Model
from simserver.core.params import (
    POWERTRAIN_AUTOMATIC,
    VP_ENGINE_IDLE_SPEED_RPM,
    VP_LOCKUP_ENGAGE_SPEED_RPM,
    VP_LOCKUP_GEAR_MIN,
    VP_POWERTRAIN_KIND,
    VP_SHIFT_DELAY_S,
)
from simserver.core.powertrain import (
    RADPS_PER_RPM,
    axle_torque_shares,
    overall_ratio,
    scheduled_gear,
)

BODY_SLOTS = OMEGA0
"""State slots 0 .. BODY_SLOTS-1 are the body's pose, velocities and suspension: held
while the wheels settle."""
SETTLE_TIME_CONSTANTS = 5.0
"""Settling lasts this many of the slowest slip relaxation time ``b/|u|`` (e^-5 < 1 %)."""
SETTLE_STEPS_MAX = 2000
"""At most this many steps (2 s at 1 kHz: below 2.5 m/s the settling is cut short)."""


def settle_steps(model: Model, speed_mps: float) -> int:
    """How many steps ``settle_at_velocity`` takes at ``speed_mps`` (0 at rest)."""
    from simserver.core.tire_layout import TP_RELAX_LAT_M, TP_RELAX_LONG_M

    if abs(speed_mps) < 1e-9:
        return 0
    length = float(np.max(model.tp[:, [TP_RELAX_LAT_M, TP_RELAX_LONG_M]]))
    n = math.ceil(SETTLE_TIME_CONSTANTS * length / abs(speed_mps) / model.dt_s)
    return min(n, SETTLE_STEPS_MAX)


@nb.njit(cache=True)
def start_powertrain(model: Model, data: Data) -> None:
    """The automatic gearbox's gear, lock-up and engine speed for the state's speed and
    the selector (the engine at idle at rest or out of gear)."""
    x, vp = data.x, model.vp
    if int(vp[VP_POWERTRAIN_KIND]) != POWERTRAIN_AUTOMATIC:
        return
    idle = vp[VP_ENGINE_IDLE_SPEED_RPM] * RADPS_PER_RPM
    selector = int(data.inputs[IN_GEAR])
    gear = 0
    if selector == GEAR_D:
        gear = scheduled_gear(vp, 0, x[U_MPS], data.inputs[IN_THROTTLE], True)
    elif selector == GEAR_R:
        gear = -1
    x[GEAR_ENGAGED] = gear
    x[SHIFT_TIMER_S] = vp[VP_SHIFT_DELAY_S]
    share = data.ws.wheel_in[0]  # scratch: the wheels' torque shares
    axle_torque_shares(vp, share)
    omega_carrier = 0.0
    for i in range(N_WHEELS):
        omega_carrier += share[i] * x[OMEGA0 + i]
    omega_t = overall_ratio(vp, gear) * omega_carrier
    x[ENGINE_SPEED_RADPS] = max(omega_t, idle)
    x[LOCKUP_ENGAGED] = 0.0
    engage_radps = vp[VP_LOCKUP_ENGAGE_SPEED_RPM] * RADPS_PER_RPM
    if gear >= vp[VP_LOCKUP_GEAR_MIN] and omega_t >= engage_radps:
        x[LOCKUP_ENGAGED] = 1.0


@nb.njit(cache=True)
def settle_at_velocity(model: Model, data: Data, n_steps: int, body: np.ndarray) -> None:
    """``n_steps`` steps with the body's slots (``BODY_SLOTS``) and the time held at their
    values: everything else (spins, slip states, latches, powertrain) relaxes to what it
    holds at that velocity. ``body``: scratch of ``BODY_SLOTS`` floats."""
    x = data.x
    for j in range(BODY_SLOTS):
        body[j] = x[j]
    time_s = x[TIME_S]
    for _ in range(n_steps):
        step(model, data)
        for j in range(BODY_SLOTS):
            x[j] = body[j]
        x[TIME_S] = time_s
