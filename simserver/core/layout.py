"""Flat array layouts of the vehicle: state, driver inputs and per-step outputs.

Every array the compiled core uses is a plain float64 vector indexed by the named
constants below; the constants are the one definition of each layout (the column names of
the output files and the wire payloads are derived from them).

Wheel order everywhere: front-left, front-right, rear-left, rear-right.
Frames (docs/model.md section 2, ISO 8855): body x forward, y left, z up; the road is a
plane, and ``X_M``/``Y_M``/``YAW_RAD`` are the pose within that plane (see ``core.road``).

Slots added later are appended (after ``TIME_S``), so an older layout is a prefix of this
one: the ``end`` state of an older command log still compares on the common slots.
"""

from __future__ import annotations

N_WHEELS = 4
WHEEL_NAMES = ("fl", "fr", "rl", "rr")
FL, FR, RL, RR = 0, 1, 2, 3
N_FRONT_WHEELS = 2  # wheels 0 .. N_FRONT_WHEELS-1 are on the front axle
N_AXLES = 2
WHEELS_PER_AXLE = 2  # left, then right


# ---------------------------------------------------------------- state vector
# Integrated states (0 .. N_INTEGRATED-1)
X_M = 0  # position along the road plane's first axis e1 (m)
Y_M = 1  # position along e2 (m)
YAW_RAD = 2  # heading in the road plane, from e1 toward e2 (rad)
U_MPS = 3  # body longitudinal velocity (m/s)
V_MPS = 4  # body lateral velocity (m/s)
YAW_RATE_RADPS = 5  # (rad/s)
HEAVE_M = 6  # sprung-mass displacement along the road normal from static (m)
HEAVE_RATE_MPS = 7
ROLL_RAD = 8  # sprung-mass roll, positive = left side up (rad)
ROLL_RATE_RADPS = 9
PITCH_RAD = 10  # sprung-mass pitch, positive = nose down (rad)
PITCH_RATE_RADPS = 11
OMEGA0 = 12  # wheel spin rates (rad/s), 4 slots
TAN_ALPHA0 = 16  # lagged slip states tan a' (paper eq. 16), 4 slots
KAPPA0 = 20  # lagged slip states k' (paper eq. 26), 4 slots
N_INTEGRATED = 24
# Discrete states, updated once per step (not integrated)
DAMPING_ACTIVE0 = 24  # Appendix A damping latched on (0/1), 4 slots
HUB_U_PREV0 = 28  # hub longitudinal speed at the previous step (sign-change trigger), 4 slots
WHEEL_HELD0 = 32  # 1 when the brake held the wheel at zero spin over the last step, 4 slots
TIME_S = 36  # simulated time (s)
N_STATE_V1 = 37  # the layout of the first release (command logs' ``end`` states)
# Appended after TIME_S: memory carried from one step to the next
FZ_PREV0 = 37  # normal load at the start of the previous step (N; -1: none yet), 4 slots
# Appended for terrains (core.terrain, docs/model.md section 11): the reference plane the
# planar states live on, Z = grade/100 X + cross/100 Y + height (on the plane kind, the
# road itself), and which wheels touch the ground
REF_GRADE_PCT = 41  # reference plane's rise along world x (%)
REF_CROSS_SLOPE_PCT = 42  # its rise along world y (%)
REF_HEIGHT_M = 43  # its height at the world origin (m)
IN_CONTACT0 = 44  # 1 when the wheel carried load at the start of the last step, 4 slots
# Appended for the steering system (issue 17, core.steering, docs/model.md section 12): an
# output of the step (from the forces at the start of the last step, the outputs O_*; the
# per-wheel aligning moments are the outputs O_MZ), fed back into nothing
STEERING_WHEEL_ANGLE_RAD = 48  # steering-wheel angle, + = left (rad)
STEERING_WHEEL_RATE_RADPS = 49  # its rate, low-pass filtered (rad/s)
STEERING_WHEEL_TORQUE_NM = 50  # torque on the driver's hands, + = toward the left (N m)
STEERING_FRICTION_NM = 51  # column friction (Dahl), with the sign of the motion (N m)
PATCH_TWIST0 = 52  # front tires' contact-patch torsion, rim against patch (rad), 2 slots
STEERING_PRIMED = 54  # 1 once a step has set the steering-wheel angle (0: fresh state)
# Appended for the automatic powertrain and hill-start assist (core.powertrain,
# docs/model.md section 13); discrete states, updated once per step
ENGINE_SPEED_RADPS = 55  # engine (pump) speed (rad/s); 0 on the simple powertrain
GEAR_ENGAGED = 56  # gear engaged: 1 .. n forward, -1 reverse, 0 none (P, N)
LOCKUP_ENGAGED = 57  # 1 while the converter's lock-up clutch is closed
IDLE_CONTROL_NM = 58  # the idle speed controller's integral term (N m)
SHIFT_TIMER_S = 59  # time since the last gear change (s)
HILL_HOLD_PEDAL = 60  # brake pedal the hill-start assist keeps (0: not armed)
HILL_HOLD_ACTIVE = 61  # 1 while the assist holds the brakes beyond the driver's pedal
HILL_HOLD_TIME_S = 62  # time since the driver released the pedal under the hold (s)
N_STATE = 63
FZ_PREV_NONE = -1.0  # FZ_PREV value of a fresh start: no previous load to extrapolate from

STATE_NAMES = (
    ("x_m", "y_m", "yaw_rad", "u_mps", "v_mps", "yaw_rate_radps")
    + ("heave_m", "heave_rate_mps", "roll_rad", "roll_rate_radps", "pitch_rad", "pitch_rate_radps")
    + tuple(f"omega_{w}_radps" for w in WHEEL_NAMES)
    + tuple(f"tan_alpha_lag_{w}" for w in WHEEL_NAMES)
    + tuple(f"kappa_lag_{w}" for w in WHEEL_NAMES)
    + tuple(f"damping_active_{w}" for w in WHEEL_NAMES)
    + tuple(f"hub_u_prev_{w}_mps" for w in WHEEL_NAMES)
    + tuple(f"wheel_held_{w}" for w in WHEEL_NAMES)
    + ("time_s",)
    + tuple(f"fz_prev_{w}_n" for w in WHEEL_NAMES)
    + ("ref_grade_pct", "ref_cross_slope_pct", "ref_height_m")
    + tuple(f"in_contact_{w}" for w in WHEEL_NAMES)
    + ("steering_wheel_angle_rad", "steering_wheel_rate_radps", "steering_wheel_torque_nm",
       "steering_friction_nm")
    + tuple(f"patch_twist_{w}_rad" for w in WHEEL_NAMES[:N_FRONT_WHEELS])
    + ("steering_primed",)
    + ("engine_speed_radps", "gear_engaged", "lockup_engaged", "idle_control_nm",
       "shift_timer_s", "hill_hold_pedal", "hill_hold_active", "hill_hold_time_s")
)

# ---------------------------------------------------------------- driver inputs
IN_STEER = 0  # normalised steering-wheel position [-1, 1], +1 = full left
IN_THROTTLE = 1  # [0, 1]
IN_BRAKE = 2  # [0, 1]
IN_PARKING_BRAKE = 3  # 0 or 1
IN_GEAR = 4  # GEAR_* below
N_INPUT = 5
INPUT_NAMES = ("steer", "throttle", "brake", "parking_brake", "gear")

GEAR_P, GEAR_R, GEAR_N, GEAR_D = 0, 1, 2, 3
GEAR_NAMES = ("P", "R", "N", "D")

# ---------------------------------------------------------------- per-step outputs
# Evaluated at the state at the start of the step (consistent with that state).
O_AX_MPS2 = 0  # CG acceleration along body x (m/s^2)
O_AY_MPS2 = 1  # CG acceleration along body y (m/s^2)
O_YAW_ACC_RADPS2 = 2
O_GRAVITY_X_MPS2 = 3  # gravity resolved into body x
O_GRAVITY_Y_MPS2 = 4
O_FX0 = 5  # tire Fx, wheel frame (N), incl. damping, 4 slots
O_FY0 = 9  # tire Fy, wheel frame (N), incl. damping, 4 slots
O_FZ0 = 13  # normal load (N), 4 slots
O_MZ0 = 17  # aligning moment (N m), 4 slots
O_HUB_U0 = 21  # hub velocity in the wheel frame (m/s), 4 slots
O_HUB_V0 = 25
O_STEER0 = 29  # road-wheel angle (rad), 4 slots
O_DRIVE_TORQUE0 = 33  # (N m), 4 slots
O_BRAKE_TORQUE0 = 37  # brake + rolling-resistance torque applied (N m, signed), 4 slots
O_FRICTION_USE0 = 41  # |F_shear| / available friction, 4 slots
O_DAMPING_FX0 = 45  # auxiliary damping share of Fx (N), 4 slots
O_DAMPING_FY0 = 49  # auxiliary damping share of Fy (N), 4 slots
O_KAPPA0 = 53  # slip fed to the tire model (k' or the kinematic slip), 4 slots
O_TAN_ALPHA0 = 57
O_FX_BODY_SUM_N = 61  # sum of tire forces along body x (N)
O_FY_BODY_SUM_N = 62
# appended by issue 16 (wheel attitude)
O_CAMBER0 = 63  # inclination angle fed to the tire, ISO 8855 (rad), 4 slots
N_OUT = 67

OUTPUT_NAMES = (
    ("ax_mps2", "ay_mps2", "yaw_acc_radps2", "gravity_x_mps2", "gravity_y_mps2")
    + tuple(f"fx_{w}_n" for w in WHEEL_NAMES)
    + tuple(f"fy_{w}_n" for w in WHEEL_NAMES)
    + tuple(f"fz_{w}_n" for w in WHEEL_NAMES)
    + tuple(f"mz_{w}_nm" for w in WHEEL_NAMES)
    + tuple(f"hub_u_{w}_mps" for w in WHEEL_NAMES)
    + tuple(f"hub_v_{w}_mps" for w in WHEEL_NAMES)
    + tuple(f"steer_{w}_rad" for w in WHEEL_NAMES)
    + tuple(f"drive_torque_{w}_nm" for w in WHEEL_NAMES)
    + tuple(f"brake_torque_{w}_nm" for w in WHEEL_NAMES)
    + tuple(f"friction_use_{w}" for w in WHEEL_NAMES)
    + tuple(f"damping_fx_{w}_n" for w in WHEEL_NAMES)
    + tuple(f"damping_fy_{w}_n" for w in WHEEL_NAMES)
    + tuple(f"kappa_{w}" for w in WHEEL_NAMES)
    + tuple(f"tan_alpha_{w}" for w in WHEEL_NAMES)
    + ("fx_body_sum_n", "fy_body_sum_n")
    + tuple(f"camber_{w}_rad" for w in WHEEL_NAMES)
)

# per-wheel blocks: ``x[OMEGA]`` is the four spins (a slice, usable in compiled code too)
OMEGA = slice(OMEGA0, OMEGA0 + N_WHEELS)
TAN_ALPHA = slice(TAN_ALPHA0, TAN_ALPHA0 + N_WHEELS)
KAPPA = slice(KAPPA0, KAPPA0 + N_WHEELS)
DAMPING_ACTIVE = slice(DAMPING_ACTIVE0, DAMPING_ACTIVE0 + N_WHEELS)
HUB_U_PREV = slice(HUB_U_PREV0, HUB_U_PREV0 + N_WHEELS)
WHEEL_HELD = slice(WHEEL_HELD0, WHEEL_HELD0 + N_WHEELS)
FZ_PREV = slice(FZ_PREV0, FZ_PREV0 + N_WHEELS)
IN_CONTACT = slice(IN_CONTACT0, IN_CONTACT0 + N_WHEELS)
PATCH_TWIST = slice(PATCH_TWIST0, PATCH_TWIST0 + N_FRONT_WHEELS)
O_FX = slice(O_FX0, O_FX0 + N_WHEELS)
O_FY = slice(O_FY0, O_FY0 + N_WHEELS)
O_FZ = slice(O_FZ0, O_FZ0 + N_WHEELS)
O_MZ = slice(O_MZ0, O_MZ0 + N_WHEELS)
O_HUB_U = slice(O_HUB_U0, O_HUB_U0 + N_WHEELS)
O_HUB_V = slice(O_HUB_V0, O_HUB_V0 + N_WHEELS)
O_STEER = slice(O_STEER0, O_STEER0 + N_WHEELS)
O_DRIVE_TORQUE = slice(O_DRIVE_TORQUE0, O_DRIVE_TORQUE0 + N_WHEELS)
O_BRAKE_TORQUE = slice(O_BRAKE_TORQUE0, O_BRAKE_TORQUE0 + N_WHEELS)
O_FRICTION_USE = slice(O_FRICTION_USE0, O_FRICTION_USE0 + N_WHEELS)
O_DAMPING_FX = slice(O_DAMPING_FX0, O_DAMPING_FX0 + N_WHEELS)
O_DAMPING_FY = slice(O_DAMPING_FY0, O_DAMPING_FY0 + N_WHEELS)
O_KAPPA = slice(O_KAPPA0, O_KAPPA0 + N_WHEELS)
O_TAN_ALPHA = slice(O_TAN_ALPHA0, O_TAN_ALPHA0 + N_WHEELS)
O_CAMBER = slice(O_CAMBER0, O_CAMBER0 + N_WHEELS)

# ---------------------------------------------------------------- world pose
# ``core.pose.world_pose`` writes the CG position and the body attitude in world axes
POSE_X_M, POSE_Y_M, POSE_Z_M = 0, 1, 2
POSE_YAW_RAD, POSE_PITCH_RAD, POSE_ROLL_RAD = 3, 4, 5
N_POSE = 6

assert len(STATE_NAMES) == N_STATE
assert len(OUTPUT_NAMES) == N_OUT
assert len(INPUT_NAMES) == N_INPUT


# ---- how the step's stages and their helpers are compiled
STEP_JIT_OPTIONS = {"cache": True, "_nrt": False, "error_model": "numpy", "forceinline": True}
"""Compile options of the step's stages and helpers (``core.integrator.step`` and what it
calls, ``core.chassis``, ``core.terrain``, ...): the step's own options (no reference
counting, numpy's error model: ``core.integrator.step``), and inlined by LLVM
(``forceinline``: LLVM's ``alwaysinline``) instead of by numba (``inline="always"``).
numba's inlining copies, re-translates and re-types a callee's body at every call site,
nested ones again inside each copy: about half of a cold compile of the step went to its
``inline_inlinables`` pass (``python -m benchmarks.bench_compile --by-function``). Typed
once as a function of its own, the body is compiled once, and LLVM inlines the compiled
code at each call, with the same arithmetic (no fast-math flags here, nor in the step):
the same bits and the same step cost. Functions that return an array keep numba's
inlining (an array returned without reference counting to a caller that counts them
would lose a reference)."""
