"""The vehicle's packed parameter vector: one table per subsystem, named slots, one array.

Every vehicle parameter is a row of one ``ParamTable`` below (core/param_table.py): its
YAML key (units in the name), unit, accepted range or named choices, default and meaning,
and its slot in the packed float64 vector. The slot constants (``VP_*``), the config
loader's keys and checks (``simserver.adapters.config``) and ``docs/configuration.md`` are
all derived from these tables.

Parameters are packed once (by ``simserver.adapters.config``) and handed to the compiled
kernels. The road and the model options live in the same vector so that one array
describes "what is being simulated"; ``core.road.set_road`` updates the road slots and
the gravity components derived from them at run time. The slot order is historical (slots
are grouped as the kernels were written, not as the files are); it is kept so that packed
vectors stay bit-identical.
"""

from __future__ import annotations

from simserver.core.damping import (
    DAMPING_MODEL_NAMES,
    PAPER_DAMPING_RATIO,
    PAPER_TRIGGER_LATERAL_SPEED_MPS,
)
from simserver.core.param_table import Param, ParamTable, slot_count, slot_layout
from simserver.core.slip import SLIP_MODEL_NAMES

DRIVEN_FRONT, DRIVEN_REAR, DRIVEN_BOTH = 0, 1, 2
DRIVEN_AXLE_NAMES = {"front": DRIVEN_FRONT, "rear": DRIVEN_REAR, "both": DRIVEN_BOTH}
POWERTRAIN_SIMPLE, POWERTRAIN_AUTOMATIC = 0, 1
POWERTRAIN_KIND_NAMES = {"simple": POWERTRAIN_SIMPLE, "automatic": POWERTRAIN_AUTOMATIC}
HILL_START_ASSIST_NAMES = {"off": 0, "on": 1}
ENGINE_CURVE_POINTS = 12  # most points of the engine's full-load curve
CONVERTER_CURVE_POINTS = 12  # most points of the converter's K and torque-ratio curves
GEARS_MAX = 10  # most forward gears

# --- the vehicle's subsystem files (every key required)
CHASSIS = ParamTable("chassis", "mass, inertias, geometry, aerodynamics", (
    Param("mass_kg", "kg", 50.0, 60000.0, "total mass, wheels included", slot=0),
    Param("sprung_mass_kg", "kg", 10.0, 60000.0,
          "mass on the springs (body); at most mass_kg", slot=1),
    Param("yaw_inertia_kgm2", "kg m^2", 1.0, 1e6,
          "whole car about the vertical axis through the CG", slot=2),
    Param("roll_inertia_kgm2", "kg m^2", 1.0, 1e6,
          "sprung mass about its own CG, roll axis", slot=3),
    Param("pitch_inertia_kgm2", "kg m^2", 1.0, 1e6,
          "sprung mass about its own CG, pitch axis", slot=4),
    Param("cg_height_m", "m", 0.05, 3.0, "CG height above the ground", slot=5),
    Param("cg_to_front_axle_m", "m", 0.1, 10.0, "CG to front axle, along x", slot=6),
    Param("cg_to_rear_axle_m", "m", 0.1, 10.0, "CG to rear axle, along x", slot=7),
    Param("track_front_m", "m", 0.3, 4.0, "front track width", slot=8),
    Param("track_rear_m", "m", 0.3, 4.0, "rear track width", slot=9),
    Param("drag_area_m2", "m^2", 0.0, 20.0, "aerodynamic drag area Cd A", slot=28),
    Param("air_density_kg_per_m3", "kg/m^3", 0.0, 2.0, "air density (0 switches drag off)",
          slot=29, const="VP_AIR_DENSITY_KGPM3"),
    # the body's footprint box and its contact with other cars (issue 30, core/contact.py,
    # docs/model.md section 16): slots appended after the historical ones; the defaults
    # are the reference car's (paper_sedan: the viewer's 0.85 m overhangs, track + 0.2 m)
    Param("body_front_overhang_m", "m", 0.0, 5.0,
          "body's front bumper ahead of the front axle (footprint box, contact; default "
          "0.85, the reference car's)",
          default=0.85, slot=168),
    Param("body_rear_overhang_m", "m", 0.0, 5.0,
          "body's rear bumper behind the rear axle (footprint box, contact; default 0.85)",
          default=0.85, slot=169),
    Param("body_width_m", "m", 0.3, 5.0,
          "body's width (footprint box, contact; default 1.78: track + 0.2)",
          default=1.78, slot=170),
    Param("bumper_height_m", "m", 0.0, 3.0,
          "height above the ground at which a contact with another car acts "
          "(default 0.5)",
          default=0.5, slot=171),
    Param("contact_stiffness_n_per_m", "N/m", 1e4, 1e9,
          "body's stiffness against another car's (two cars: in series; default 1e7, "
          "docs/model.md section 16)",
          default=1.0e7, slot=172),
    Param("contact_damping_ratio", "-", 0.0, 0.95,
          "damping of a contact, fraction of critical for the pair (two cars: the mean; "
          "default 0.36)",
          default=0.36, slot=173),
    Param("contact_friction", "-", 0.0, 2.0,
          "Coulomb friction between the bodies at a contact (two cars: the mean; "
          "default 0.3)",
          default=0.3, slot=174),
))
SUSPENSION = ParamTable("suspension", "springs, dampers, anti-roll bars (rates at the wheel)", (
    Param("spring_front_n_per_m", "N/m", 1e3, 1e7,
          "suspension spring rate at each front wheel", slot=10, const="VP_SPRING_FRONT_NPM"),
    Param("spring_rear_n_per_m", "N/m", 1e3, 1e7,
          "suspension spring rate at each rear wheel", slot=11, const="VP_SPRING_REAR_NPM"),
    Param("damper_front_n_s_per_m", "N s/m", 0.0, 1e6, "damper rate at each front wheel",
          slot=12, const="VP_DAMPER_FRONT_NSPM"),
    Param("damper_rear_n_s_per_m", "N s/m", 0.0, 1e6, "damper rate at each rear wheel",
          slot=13, const="VP_DAMPER_REAR_NSPM"),
    Param("antiroll_front_n_per_m", "N/m", 0.0, 1e7,
          "front anti-roll bar, as a rate at the wheel (0: none)", slot=14,
          const="VP_ANTIROLL_FRONT_NPM"),
    Param("antiroll_rear_n_per_m", "N/m", 0.0, 1e7,
          "rear anti-roll bar, as a rate at the wheel (0: none)", slot=15,
          const="VP_ANTIROLL_REAR_NPM"),
    # wheel attitude (issue 16): slots appended after the historical ones
    Param("camber_static_front_rad", "rad", -0.2, 0.2,
          "static camber of each front wheel (negative: the top leans inboard)", slot=38),
    Param("camber_static_rear_rad", "rad", -0.2, 0.2,
          "static camber of each rear wheel (negative: the top leans inboard)", slot=39),
    Param("toe_front_rad", "rad", -0.05, 0.05,
          "static toe of each front wheel (positive: toe-in, its front points inboard)",
          slot=40),
    Param("toe_rear_rad", "rad", -0.05, 0.05,
          "static toe of each rear wheel (positive: toe-in, its front points inboard)",
          slot=41),
    Param("camber_roll_gain_front", "rad/rad", -2.0, 2.0,
          "front wheels' inclination to the road per rad of body roll, in the roll's sense "
          "(1: they lean with the body, 0: they stay upright)", slot=42),
    Param("camber_roll_gain_rear", "rad/rad", -2.0, 2.0,
          "rear wheels' inclination to the road per rad of body roll, in the roll's sense "
          "(1: they lean with the body, 0: they stay upright)", slot=43),
    Param("camber_heave_gain_front_rad_per_m", "rad/m", -20.0, 20.0,
          "camber change of a front wheel per metre of its suspension's compression "
          "(negative: the top leans inboard in bump)", slot=44,
          const="VP_CAMBER_HEAVE_GAIN_FRONT_RADPM"),
    Param("camber_heave_gain_rear_rad_per_m", "rad/m", -20.0, 20.0,
          "camber change of a rear wheel per metre of its suspension's compression "
          "(negative: the top leans inboard in bump)", slot=45,
          const="VP_CAMBER_HEAVE_GAIN_REAR_RADPM"),
))
STEERING = ParamTable("steering", "steering ratio and range, kingpin geometry, assist, column", (
    Param("steering_ratio", "-", 1.0, 50.0,
          "steering-wheel angle / road-wheel angle (parallel steer)", slot=18),
    Param("steering_wheel_max_rad", "rad", 0.05, 30.0, "steering-wheel angle at steer = 1",
          slot=19),
    # the steering system (issue 17, core/steering.py, docs/model.md section 12): slots
    # appended after the historical ones; the torque is an output, the motion is unchanged
    Param("caster_trail_m", "m", -0.1, 0.2,
          "mechanical trail: the contact patch's centre behind the kingpin axis' ground "
          "point", slot=46),
    Param("scrub_radius_m", "m", -0.1, 0.1,
          "kingpin offset at the ground: the patch centre outboard of the axis' ground "
          "point (negative: inboard)", slot=47),
    Param("kingpin_inclination_rad", "rad", 0.0, 0.4,
          "kingpin axis leaning inboard at the top, seen from the front (0: no weight "
          "lift)", slot=48),
    Param("patch_torsion_stiffness_nm_per_rad", "N m/rad", 1.0, 1e6,
          "torsional stiffness of a front tire's contact patch (rim turned against a patch "
          "that sticks)", slot=49, const="VP_PATCH_TORSION_STIFFNESS_NM_PER_RAD"),
    Param("patch_bore_arm_m", "m", 0.0, 0.5,
          "bore (turning at rest) torque limit per newton of load and unit friction scale: "
          "(2/3) mu r of a disc patch of radius r", slot=50),
    Param("assist_boost_parking", "-", 0.0, 100.0,
          "power assist torque per unit driver torque at rest (0: no assist)", slot=51),
    Param("assist_boost_highway", "-", 0.0, 100.0,
          "power assist torque per unit driver torque at high speed", slot=52),
    Param("assist_fade_speed_mps", "m/s", 0.1, 100.0,
          "speed at which the boost is halfway from its parking to its highway value",
          slot=53),
    Param("assist_torque_max_nm", "N m", 0.0, 1000.0,
          "most torque the assist adds, at the steering column", slot=54),
    Param("column_friction_nm", "N m", 0.0, 50.0,
          "Coulomb friction of column and rack, at the steering wheel", slot=55),
    Param("column_friction_stiffness_nm_per_rad", "N m/rad", 0.1, 1e5,
          "Dahl stiffness of that friction: its slope when the motion reverses", slot=56,
          const="VP_COLUMN_FRICTION_STIFFNESS_NM_PER_RAD"),
    Param("column_damping_nm_s_per_rad", "N m s/rad", 0.0, 50.0,
          "viscous damping of column and rack, at the steering wheel", slot=57,
          const="VP_COLUMN_DAMPING_NMS_PER_RAD"),
    Param("column_rate_filter_s", "s", 0.0, 1.0,
          "time constant of the low-pass filter on the steering-wheel rate the damping "
          "acts on (commands arrive in steps)", slot=58),
))
BRAKES = ParamTable("brakes", "service and parking brakes", (
    Param("brake_torque_max_nm", "N m", 0.0, 1e6,
          "brake torque of all four wheels together at pedal = 1", slot=20),
    Param("brake_front_fraction", "-", 0.0, 1.0,
          "share of the brake torque on the front axle (70/30 is the paper's pattern at "
          "rest, docs/model.md section 4b item 4)", slot=21),
    Param("parking_brake_torque_nm", "N m", 0.0, 1e6, "parking-brake torque per rear wheel",
          slot=22),
    # hill-start assist (issue 17, docs/model.md section 12)
    Param("hill_start_assist", "-", None, None,
          "hill-start assist: releasing the brake at rest on a grade keeps the brakes on "
          "until the drive overcomes the grade or for hill_start_assist_hold_s",
          choices=HILL_START_ASSIST_NAMES, slot=60),
    Param("hill_start_assist_hold_s", "s", 0.0, 10.0,
          "longest hold after the pedal is released (production cars: about 2 s)", slot=61),
    Param("hill_start_assist_min_grade_pct", "%", 0.0, 50.0,
          "the assist acts on grades steeper than this, against the selected direction",
          slot=62),
))
POWERTRAIN = ParamTable("powertrain", "drive torque and power, driven axles, wheel inertias", (
    Param("drive_torque_max_nm", "N m", 0.0, 1e6,
          "drive torque at the wheels, all driven wheels together, gear D", slot=23),
    Param("drive_power_max_w", "W", 1.0, 1e8,
          "power cap: torque <= P / |mean driven-wheel spin| above 1 rad/s", slot=24),
    Param("reverse_torque_max_nm", "N m", 0.0, 1e6, "drive torque at the wheels in gear R",
          slot=25),
    Param("driven_axle", "-", None, None,
          "front, rear or both (open differential on each driven axle)",
          choices=DRIVEN_AXLE_NAMES, slot=26),
    Param("drive_front_fraction", "-", 0.0, 1.0,
          "torque share of the front axle when both are driven", slot=27),
    Param("wheel_inertia_front_kgm2", "kg m^2", 0.05, 500.0,
          "spin inertia of a front wheel with disc and driveline share", slot=16),
    Param("wheel_inertia_rear_kgm2", "kg m^2", 0.05, 500.0,
          "spin inertia of a rear wheel with disc and driveline share", slot=17),
    Param("kind", "-", None, None,
          "simple (a torque map at the wheels: the drive_* and reverse_* keys) or "
          "automatic (engine, torque converter, automatic gearbox: the file's "
          "`automatic:` section)", default="simple", choices=POWERTRAIN_KIND_NAMES, slot=59,
          const="VP_POWERTRAIN_KIND"),
))
VEHICLE_SUBSYSTEMS = (CHASSIS, SUSPENSION, STEERING, BRAKES, POWERTRAIN)

# --- the powertrain file's ``automatic:`` section (required with ``kind: automatic``)
_RPM_MAX = 20000.0
AUTOMATIC = ParamTable("automatic", "engine, torque converter and automatic gearbox "
                       "(docs/model.md section 12)", (
    Param("engine_idle_speed_rpm", "rpm", 300.0, 3000.0,
          "idle speed the idle controller holds", slot=63),
    Param("engine_speed_max_rpm", "rpm", 1000.0, _RPM_MAX,
          "fuel cut: no throttle torque above this speed", slot=64),
    Param("engine_inertia_kgm2", "kg m^2", 0.01, 10.0,
          "engine, flywheel and converter pump about the crankshaft", slot=65),
    Param("engine_curve_speed_rpm", "rpm", 0.0, _RPM_MAX,
          "engine speeds of the full-load curve's points, increasing", slot=66,
          size=ENGINE_CURVE_POINTS),
    Param("engine_full_load_torque_nm", "N m", 0.0, 1e5,
          "full-load (wide-open throttle) torque at those speeds, net of the drag torque "
          "(linear between points, constant beyond)", slot=78, size=ENGINE_CURVE_POINTS),
    Param("engine_drag_torque_nm", "N m", 0.0, 1e4,
          "friction and pumping torque at idle speed, throttle closed", slot=90),
    Param("engine_drag_torque_per_krpm_nm", "N m", 0.0, 1e4,
          "drag torque added per 1000 rpm above idle", slot=91),
    Param("idle_control_gain_nm_per_rpm", "N m/rpm", 0.0, 100.0,
          "idle controller, proportional: torque per rpm below idle speed", slot=92),
    Param("idle_control_integral_time_s", "s", 0.01, 10.0,
          "idle controller, integral time", slot=93),
    Param("idle_control_torque_max_nm", "N m", 0.0, 1e4,
          "idle controller's authority (more than the drag plus the converter's load at "
          "idle and stall: the engine never stalls)", slot=94),
    Param("converter_speed_ratio", "-", 0.0, 1.0,
          "turbine / pump speed at the converter curves' points, increasing from 0; "
          "above the last point K rises to infinity at 1 and the torque ratio is 1",
          slot=95, size=CONVERTER_CURVE_POINTS),
    Param("converter_k_factor_rpm_per_sqrt_nm", "rpm/sqrt(N m)", 1.0, 1e4,
          "capacity factor K = pump speed / sqrt(pump torque) at those points", slot=107,
          size=CONVERTER_CURVE_POINTS),
    Param("converter_torque_ratio", "-", 0.5, 10.0,
          "turbine / pump torque at those points (about 2 at stall, 1 at coupling)",
          slot=119, size=CONVERTER_CURVE_POINTS),
    Param("lockup_engage_speed_rpm", "rpm", 0.0, _RPM_MAX,
          "the lock-up clutch closes above this turbine speed (in gear lockup_gear_min or "
          "higher, not in kick-down)", slot=131),
    Param("lockup_release_speed_rpm", "rpm", 0.0, _RPM_MAX,
          "and opens below this one (below lockup_engage_speed_rpm: hysteresis)", slot=132),
    Param("lockup_gear_min", "-", 1.0, GEARS_MAX, "lowest gear with the lock-up closed",
          slot=133),
    Param("gear_ratios", "-", 0.2, 10.0, "forward gear ratios, first gear first", slot=134,
          size=GEARS_MAX),
    Param("gear_count", "-", None, None, "number of forward gears (the list's length)",
          slot=144),
    Param("reverse_gear_ratio", "-", 0.2, 10.0, "reverse gear ratio (a magnitude)", slot=145),
    Param("final_drive_ratio", "-", 0.5, 20.0, "final drive (differential) ratio", slot=146),
    Param("upshift_speed_light_mps", "m/s", 0.0, 150.0,
          "vehicle speed of each upshift (1-2, 2-3, ...) at closed throttle: one fewer than "
          "the gears", slot=147, size=GEARS_MAX - 1),
    Param("upshift_speed_full_mps", "m/s", 0.0, 150.0,
          "the same at full throttle (linear in the throttle between them)", slot=156,
          size=GEARS_MAX - 1),
    Param("downshift_hysteresis_mps", "m/s", 0.0, 50.0,
          "a downshift waits until the speed is this far below the upshift speed", slot=165),
    Param("kickdown_throttle", "-", 0.5, 1.0,
          "throttle beyond this is kick-down: the full-throttle schedule at once (no "
          "shift delay, several gears if need be) and the lock-up open", slot=166),
    Param("shift_delay_s", "s", 0.0, 10.0, "shortest time between two gear changes",
          slot=167),
))

# --- the scenario's or scene's ``road:`` section. Not vehicle parameters: the road is the
# world's, shared by every car on it, and lives in its terrain (``core.terrain.Terrain.road``,
# slots ROAD_*); ``core.road.set_road`` writes it and keeps the gravity slots in step.
ROAD = ParamTable("road", "the road plane under the car", (
    Param("road_grade_pct", "%", -100.0, 100.0,
          "the road rises grade_pct m per 100 m along world x", default=0.0, slot=0,
          key="grade_pct", const="ROAD_GRADE_PCT"),
    Param("road_cross_slope_pct", "%", -100.0, 100.0,
          "the road rises cross_slope_pct m per 100 m along world y", default=0.0, slot=1,
          key="cross_slope_pct", const="ROAD_CROSS_SLOPE_PCT"),
    Param("road_friction_scale", "-", 0.0, 3.0, "scales every tire's friction", default=1.0,
          slot=2, key="friction_scale", const="ROAD_FRICTION_SCALE"),
    Param("gravity_e1_mps2", "m/s^2", None, None,
          "gravity resolved along the road plane's e1", slot=3),
    Param("gravity_e2_mps2", "m/s^2", None, None,
          "gravity resolved along the road plane's e2", slot=4),
    Param("gravity_n_mps2", "m/s^2", None, None,
          "gravity component pressing the car onto the road (> 0)", slot=5),
))

# --- the ``model:`` section of a scenario or scene (every key optional)
MODEL_OPTIONS = ParamTable("model", "slip and damping variants, gravity", (
    Param("slip_model", "-", None, None, "slip states (core/slip.py)",
          default="lagged_passive", choices=SLIP_MODEL_NAMES, slot=31),
    Param("damping_model", "-", None, None, "low-speed damping (core/damping.py)",
          default="patch", choices=DAMPING_MODEL_NAMES, slot=32),
    Param("damping_ratio", "-", 0.0, 5.0,
          "zeta of the paper's Appendix A (docs/model.md section 4)",
          default=PAPER_DAMPING_RATIO, slot=33),
    Param("damping_trigger_v_mps", "m/s", 0.0, 10.0,
          "eps of the paper's Appendix A: its trigger needs |v| below it",
          default=PAPER_TRIGGER_LATERAL_SPEED_MPS, slot=34),
    Param("damping_fade_speed_mps", "m/s", 0.01, 50.0,
          "the patch damping (docs/model.md section 4b item 2) fades out by this hub speed",
          default=2.0, slot=35),
    Param("kinematic_u_min_mps", "m/s", 0.01, 50.0,
          "u_min of the paper's eq. (1) patch (docs/model.md section 1; kinematic only)",
          default=0.5, slot=36),
    Param("slide_widen_speed_mps", "m/s", 0.01, 100.0,
          "passive slip states (docs/model.md section 4b item 1): the sliding limit widens "
          "above this hub speed", default=0.5, slot=37),
    Param("gravity_mps2", "m/s^2", 0.1, 30.0, "gravitational acceleration", default=9.81,
          slot=30),
))

VEHICLE_PARAM_TABLES = (*VEHICLE_SUBSYSTEMS, AUTOMATIC, MODEL_OPTIONS)
VEHICLE_PARAMS = slot_layout(VEHICLE_PARAM_TABLES)  # every parameter, in slot order
VEHICLE_PARAM_NAMES = tuple(p.name for p in VEHICLE_PARAMS)
N_VEHICLE_PARAM = slot_count(VEHICLE_PARAMS)  # a list parameter takes several slots
N_ROAD = slot_count(slot_layout((ROAD,)))  # slots of a terrain's road (Terrain.road)

# The slot constants, generated from the tables above (a test fails when they drift):
# python -m simserver.adapters.config --write --slots simserver/core/params.py
# --- generated slot constants
VP_MASS_KG = 0  # kg, chassis
VP_SPRUNG_MASS_KG = 1  # kg, chassis
VP_YAW_INERTIA_KGM2 = 2  # kg m^2, chassis
VP_ROLL_INERTIA_KGM2 = 3  # kg m^2, chassis
VP_PITCH_INERTIA_KGM2 = 4  # kg m^2, chassis
VP_CG_HEIGHT_M = 5  # m, chassis
VP_CG_TO_FRONT_AXLE_M = 6  # m, chassis
VP_CG_TO_REAR_AXLE_M = 7  # m, chassis
VP_TRACK_FRONT_M = 8  # m, chassis
VP_TRACK_REAR_M = 9  # m, chassis
VP_SPRING_FRONT_NPM = 10  # N/m, suspension
VP_SPRING_REAR_NPM = 11  # N/m, suspension
VP_DAMPER_FRONT_NSPM = 12  # N s/m, suspension
VP_DAMPER_REAR_NSPM = 13  # N s/m, suspension
VP_ANTIROLL_FRONT_NPM = 14  # N/m, suspension
VP_ANTIROLL_REAR_NPM = 15  # N/m, suspension
VP_WHEEL_INERTIA_FRONT_KGM2 = 16  # kg m^2, powertrain
VP_WHEEL_INERTIA_REAR_KGM2 = 17  # kg m^2, powertrain
VP_STEERING_RATIO = 18  # -, steering
VP_STEERING_WHEEL_MAX_RAD = 19  # rad, steering
VP_BRAKE_TORQUE_MAX_NM = 20  # N m, brakes
VP_BRAKE_FRONT_FRACTION = 21  # -, brakes
VP_PARKING_BRAKE_TORQUE_NM = 22  # N m, brakes
VP_DRIVE_TORQUE_MAX_NM = 23  # N m, powertrain
VP_DRIVE_POWER_MAX_W = 24  # W, powertrain
VP_REVERSE_TORQUE_MAX_NM = 25  # N m, powertrain
VP_DRIVEN_AXLE = 26  # -, powertrain
VP_DRIVE_FRONT_FRACTION = 27  # -, powertrain
VP_DRAG_AREA_M2 = 28  # m^2, chassis
VP_AIR_DENSITY_KGPM3 = 29  # kg/m^3, chassis
VP_GRAVITY_MPS2 = 30  # m/s^2, model
VP_SLIP_MODEL = 31  # -, model
VP_DAMPING_MODEL = 32  # -, model
VP_DAMPING_RATIO = 33  # -, model
VP_DAMPING_TRIGGER_V_MPS = 34  # m/s, model
VP_DAMPING_FADE_SPEED_MPS = 35  # m/s, model
VP_KINEMATIC_U_MIN_MPS = 36  # m/s, model
VP_SLIDE_WIDEN_SPEED_MPS = 37  # m/s, model
VP_CAMBER_STATIC_FRONT_RAD = 38  # rad, suspension
VP_CAMBER_STATIC_REAR_RAD = 39  # rad, suspension
VP_TOE_FRONT_RAD = 40  # rad, suspension
VP_TOE_REAR_RAD = 41  # rad, suspension
VP_CAMBER_ROLL_GAIN_FRONT = 42  # rad/rad, suspension
VP_CAMBER_ROLL_GAIN_REAR = 43  # rad/rad, suspension
VP_CAMBER_HEAVE_GAIN_FRONT_RADPM = 44  # rad/m, suspension
VP_CAMBER_HEAVE_GAIN_REAR_RADPM = 45  # rad/m, suspension
VP_CASTER_TRAIL_M = 46  # m, steering
VP_SCRUB_RADIUS_M = 47  # m, steering
VP_KINGPIN_INCLINATION_RAD = 48  # rad, steering
VP_PATCH_TORSION_STIFFNESS_NM_PER_RAD = 49  # N m/rad, steering
VP_PATCH_BORE_ARM_M = 50  # m, steering
VP_ASSIST_BOOST_PARKING = 51  # -, steering
VP_ASSIST_BOOST_HIGHWAY = 52  # -, steering
VP_ASSIST_FADE_SPEED_MPS = 53  # m/s, steering
VP_ASSIST_TORQUE_MAX_NM = 54  # N m, steering
VP_COLUMN_FRICTION_NM = 55  # N m, steering
VP_COLUMN_FRICTION_STIFFNESS_NM_PER_RAD = 56  # N m/rad, steering
VP_COLUMN_DAMPING_NMS_PER_RAD = 57  # N m s/rad, steering
VP_COLUMN_RATE_FILTER_S = 58  # s, steering
VP_POWERTRAIN_KIND = 59  # -, powertrain
VP_HILL_START_ASSIST = 60  # -, brakes
VP_HILL_START_ASSIST_HOLD_S = 61  # s, brakes
VP_HILL_START_ASSIST_MIN_GRADE_PCT = 62  # %, brakes
VP_ENGINE_IDLE_SPEED_RPM = 63  # rpm, automatic
VP_ENGINE_SPEED_MAX_RPM = 64  # rpm, automatic
VP_ENGINE_INERTIA_KGM2 = 65  # kg m^2, automatic
VP_ENGINE_CURVE_SPEED_RPM = 66  # rpm, automatic, 12 slots
VP_ENGINE_FULL_LOAD_TORQUE_NM = 78  # N m, automatic, 12 slots
VP_ENGINE_DRAG_TORQUE_NM = 90  # N m, automatic
VP_ENGINE_DRAG_TORQUE_PER_KRPM_NM = 91  # N m, automatic
VP_IDLE_CONTROL_GAIN_NM_PER_RPM = 92  # N m/rpm, automatic
VP_IDLE_CONTROL_INTEGRAL_TIME_S = 93  # s, automatic
VP_IDLE_CONTROL_TORQUE_MAX_NM = 94  # N m, automatic
VP_CONVERTER_SPEED_RATIO = 95  # -, automatic, 12 slots
VP_CONVERTER_K_FACTOR_RPM_PER_SQRT_NM = 107  # rpm/sqrt(N m), automatic, 12 slots
VP_CONVERTER_TORQUE_RATIO = 119  # -, automatic, 12 slots
VP_LOCKUP_ENGAGE_SPEED_RPM = 131  # rpm, automatic
VP_LOCKUP_RELEASE_SPEED_RPM = 132  # rpm, automatic
VP_LOCKUP_GEAR_MIN = 133  # -, automatic
VP_GEAR_RATIOS = 134  # -, automatic, 10 slots
VP_GEAR_COUNT = 144  # -, automatic
VP_REVERSE_GEAR_RATIO = 145  # -, automatic
VP_FINAL_DRIVE_RATIO = 146  # -, automatic
VP_UPSHIFT_SPEED_LIGHT_MPS = 147  # m/s, automatic, 9 slots
VP_UPSHIFT_SPEED_FULL_MPS = 156  # m/s, automatic, 9 slots
VP_DOWNSHIFT_HYSTERESIS_MPS = 165  # m/s, automatic
VP_KICKDOWN_THROTTLE = 166  # -, automatic
VP_SHIFT_DELAY_S = 167  # s, automatic
VP_BODY_FRONT_OVERHANG_M = 168  # m, chassis
VP_BODY_REAR_OVERHANG_M = 169  # m, chassis
VP_BODY_WIDTH_M = 170  # m, chassis
VP_BUMPER_HEIGHT_M = 171  # m, chassis
VP_CONTACT_STIFFNESS_N_PER_M = 172  # N/m, chassis
VP_CONTACT_DAMPING_RATIO = 173  # -, chassis
VP_CONTACT_FRICTION = 174  # -, chassis
# the terrain's road (core.terrain.Terrain.road)
ROAD_GRADE_PCT = 0  # %, road
ROAD_CROSS_SLOPE_PCT = 1  # %, road
ROAD_FRICTION_SCALE = 2  # -, road
ROAD_GRAVITY_E1_MPS2 = 3  # m/s^2, road
ROAD_GRAVITY_E2_MPS2 = 4  # m/s^2, road
ROAD_GRAVITY_N_MPS2 = 5  # m/s^2, road
# --- end of generated slot constants
