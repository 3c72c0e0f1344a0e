"""The vehicle's packed parameter vector: named slots, one float64 array.

Parameters are packed once (by ``simserver.adapters.config``) and handed to the compiled
kernels. The road and the model options live in the same vector so that one array
describes "what is being simulated"; ``core.road.set_road`` updates the road slots and
the gravity components derived from them at run time.
"""

from __future__ import annotations

# --- mass and geometry
VP_MASS_KG = 0  # total mass
VP_SPRUNG_MASS_KG = 1
VP_YAW_INERTIA_KGM2 = 2  # total, about the CG
VP_ROLL_INERTIA_KGM2 = 3  # sprung mass, about its CG
VP_PITCH_INERTIA_KGM2 = 4  # sprung mass, about its CG
VP_CG_HEIGHT_M = 5  # above ground
VP_CG_TO_FRONT_AXLE_M = 6
VP_CG_TO_REAR_AXLE_M = 7
VP_TRACK_FRONT_M = 8
VP_TRACK_REAR_M = 9
# --- suspension (rates at the wheel)
VP_SPRING_FRONT_NPM = 10
VP_SPRING_REAR_NPM = 11
VP_DAMPER_FRONT_NSPM = 12
VP_DAMPER_REAR_NSPM = 13
VP_ANTIROLL_FRONT_NPM = 14
VP_ANTIROLL_REAR_NPM = 15
# --- wheels and steering
VP_WHEEL_INERTIA_FRONT_KGM2 = 16  # wheel + brake disc + share of driveline
VP_WHEEL_INERTIA_REAR_KGM2 = 17
VP_STEERING_RATIO = 18  # steering-wheel angle / road-wheel angle
VP_STEERING_WHEEL_MAX_RAD = 19  # steering-wheel angle at steer = 1
# --- brakes
VP_BRAKE_TORQUE_MAX_NM = 20  # all four wheels together, pedal = 1
VP_BRAKE_FRONT_FRACTION = 21
VP_PARKING_BRAKE_TORQUE_NM = 22  # per rear wheel
# --- powertrain
VP_DRIVE_TORQUE_MAX_NM = 23  # at the wheels, all driven wheels together, first gear
VP_DRIVE_POWER_MAX_W = 24
VP_REVERSE_TORQUE_MAX_NM = 25
VP_DRIVEN_AXLE = 26  # DRIVEN_FRONT / DRIVEN_REAR / DRIVEN_BOTH
VP_DRIVE_FRONT_FRACTION = 27  # torque share of the front axle when both are driven
# --- aerodynamics
VP_DRAG_AREA_M2 = 28  # Cd * A
VP_AIR_DENSITY_KGPM3 = 29
# --- road (set_road keeps the derived gravity slots consistent)
VP_ROAD_GRADE_PCT = 30  # rise along e1, per cent
VP_ROAD_CROSS_SLOPE_PCT = 31  # rise along e2, per cent
VP_ROAD_FRICTION_SCALE = 32
VP_GRAVITY_MPS2 = 33
VP_GRAVITY_E1_MPS2 = 34  # derived: gravity resolved along the road plane's axes
VP_GRAVITY_E2_MPS2 = 35
VP_GRAVITY_N_MPS2 = 36  # derived: component pressing the car onto the road (> 0)
# --- model options
VP_SLIP_MODEL = 37  # core.slip.SLIP_*
VP_DAMPING_MODEL = 38  # core.damping.DAMPING_*
VP_DAMPING_RATIO = 39  # zeta, Appendix A
VP_DAMPING_TRIGGER_V_MPS = 40  # eps, Appendix A
VP_DAMPING_FADE_SPEED_MPS = 41  # patch damping fades out by this hub speed
VP_KINEMATIC_U_MIN_MPS = 42  # u_min of the paper's eq. (1) patch (kinematic baseline)
VP_SLIDE_WIDEN_SPEED_MPS = 43  # passive slip: sliding limit widens above this hub speed
N_VEHICLE_PARAM = 44

DRIVEN_FRONT, DRIVEN_REAR, DRIVEN_BOTH = 0, 1, 2
DRIVEN_AXLE_NAMES = {"front": DRIVEN_FRONT, "rear": DRIVEN_REAR, "both": DRIVEN_BOTH}

VEHICLE_PARAM_NAMES = (
    "mass_kg",
    "sprung_mass_kg",
    "yaw_inertia_kgm2",
    "roll_inertia_kgm2",
    "pitch_inertia_kgm2",
    "cg_height_m",
    "cg_to_front_axle_m",
    "cg_to_rear_axle_m",
    "track_front_m",
    "track_rear_m",
    "spring_front_n_per_m",
    "spring_rear_n_per_m",
    "damper_front_n_s_per_m",
    "damper_rear_n_s_per_m",
    "antiroll_front_n_per_m",
    "antiroll_rear_n_per_m",
    "wheel_inertia_front_kgm2",
    "wheel_inertia_rear_kgm2",
    "steering_ratio",
    "steering_wheel_max_rad",
    "brake_torque_max_nm",
    "brake_front_fraction",
    "parking_brake_torque_nm",
    "drive_torque_max_nm",
    "drive_power_max_w",
    "reverse_torque_max_nm",
    "driven_axle",
    "drive_front_fraction",
    "drag_area_m2",
    "air_density_kg_per_m3",
    "road_grade_pct",
    "road_cross_slope_pct",
    "road_friction_scale",
    "gravity_mps2",
    "gravity_e1_mps2",
    "gravity_e2_mps2",
    "gravity_n_mps2",
    "slip_model",
    "damping_model",
    "damping_ratio",
    "damping_trigger_v_mps",
    "damping_fade_speed_mps",
    "kinematic_u_min_mps",
    "slide_widen_speed_mps",
)
assert len(VEHICLE_PARAM_NAMES) == N_VEHICLE_PARAM


def __getattr__(name: str) -> object:
    """``set_road`` and ``road_axes`` moved to ``core.road``; this forwards the old imports
    of callers not yet updated (a module cannot import ``core.road`` at its top: that
    module imports this one)."""
    if name in ("set_road", "road_axes"):
        from simserver.core import road

        return getattr(road, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
