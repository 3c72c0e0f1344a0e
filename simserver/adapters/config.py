"""Vehicle configuration: YAML files, one per subsystem, composed by path.

A vehicle is a top-level YAML file naming its subsystem files (paths relative to it)::

    name: paper_sedan
    chassis: chassis.yaml          # mass, inertias, geometry, aero
    suspension: suspension.yaml    # springs, dampers, anti-roll bars
    steering: steering.yaml
    brakes: brakes.yaml
    powertrain: powertrain.yaml
    tires: {front: ../../tires/paper_sti.yaml, rear: ../../tires/paper_sti.yaml}

Each subsystem file holds exactly the keys listed for it in ``SUBSYSTEM_KEYS`` (units in
the key names); every key is checked against ``PARAM_RANGES``. Tire files are described
in ``load_tire``. Every error names the file and the key (``ConfigError``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from simserver.core import params as P
from simserver.core.damping import (
    DAMPING_MODEL_NAMES,
    PAPER_DAMPING_RATIO,
    PAPER_TRIGGER_LATERAL_SPEED_MPS,
)
from simserver.core.slip import SLIP_MODEL_NAMES
from simserver.core.tire import N_TIRE_PARAM
from simserver.core.tire_layout import (
    TP_MODEL,
    TP_MODEL_BASE,
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)
from simserver.tire_models import N_MODEL_PARAM_MAX, TIRE_MODEL_NAMES, tire_model


class ConfigError(ValueError):
    """A configuration file is missing, unreadable or invalid; the message names file and key."""


# Which vehicle-parameter keys each subsystem file holds (names = core.params names).
SUBSYSTEM_KEYS: dict[str, tuple[str, ...]] = {
    "chassis": (
        "mass_kg", "sprung_mass_kg", "yaw_inertia_kgm2", "roll_inertia_kgm2",
        "pitch_inertia_kgm2", "cg_height_m", "cg_to_front_axle_m", "cg_to_rear_axle_m",
        "track_front_m", "track_rear_m", "drag_area_m2", "air_density_kg_per_m3",
    ),
    "suspension": (
        "spring_front_n_per_m", "spring_rear_n_per_m", "damper_front_n_s_per_m",
        "damper_rear_n_s_per_m", "antiroll_front_n_per_m", "antiroll_rear_n_per_m",
    ),
    "steering": ("steering_ratio", "steering_wheel_max_rad"),
    "brakes": ("brake_torque_max_nm", "brake_front_fraction", "parking_brake_torque_nm"),
    "powertrain": (
        "drive_torque_max_nm", "drive_power_max_w", "reverse_torque_max_nm", "driven_axle",
        "drive_front_fraction", "wheel_inertia_front_kgm2", "wheel_inertia_rear_kgm2",
    ),
}

# (min, max) of every numeric parameter; a value outside is a config error.
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "mass_kg": (50.0, 60000.0),
    "sprung_mass_kg": (10.0, 60000.0),
    "yaw_inertia_kgm2": (1.0, 1e6),
    "roll_inertia_kgm2": (1.0, 1e6),
    "pitch_inertia_kgm2": (1.0, 1e6),
    "cg_height_m": (0.05, 3.0),
    "cg_to_front_axle_m": (0.1, 10.0),
    "cg_to_rear_axle_m": (0.1, 10.0),
    "track_front_m": (0.3, 4.0),
    "track_rear_m": (0.3, 4.0),
    "drag_area_m2": (0.0, 20.0),
    "air_density_kg_per_m3": (0.0, 2.0),
    "spring_front_n_per_m": (1e3, 1e7),
    "spring_rear_n_per_m": (1e3, 1e7),
    "damper_front_n_s_per_m": (0.0, 1e6),
    "damper_rear_n_s_per_m": (0.0, 1e6),
    "antiroll_front_n_per_m": (0.0, 1e7),
    "antiroll_rear_n_per_m": (0.0, 1e7),
    "steering_ratio": (1.0, 50.0),
    "steering_wheel_max_rad": (0.05, 30.0),
    "brake_torque_max_nm": (0.0, 1e6),
    "brake_front_fraction": (0.0, 1.0),
    "parking_brake_torque_nm": (0.0, 1e6),
    "drive_torque_max_nm": (0.0, 1e6),
    "drive_power_max_w": (1.0, 1e8),
    "reverse_torque_max_nm": (0.0, 1e6),
    "drive_front_fraction": (0.0, 1.0),
    "wheel_inertia_front_kgm2": (0.05, 500.0),
    "wheel_inertia_rear_kgm2": (0.05, 500.0),
}

# Model options (the scenario's or server's ``model:`` section) and their defaults.
MODEL_OPTION_DEFAULTS: dict[str, Any] = {
    "slip_model": "lagged_passive",
    "damping_model": "patch",
    "damping_ratio": PAPER_DAMPING_RATIO,
    "damping_trigger_v_mps": PAPER_TRIGGER_LATERAL_SPEED_MPS,
    "damping_fade_speed_mps": 2.0,
    "kinematic_u_min_mps": 0.5,
    "slide_widen_speed_mps": 0.5,
    "gravity_mps2": 9.81,
}
MODEL_OPTION_RANGES: dict[str, tuple[float, float]] = {
    "damping_ratio": (0.0, 5.0),
    "damping_trigger_v_mps": (0.0, 10.0),
    "damping_fade_speed_mps": (0.01, 50.0),
    "kinematic_u_min_mps": (0.01, 50.0),
    "slide_widen_speed_mps": (0.01, 100.0),
    "gravity_mps2": (0.1, 30.0),
}

SIMPLE_TIRE_RANGES: dict[str, tuple[float, float]] = {
    "cornering_stiffness_n_per_rad": (100.0, 1e7),
    "longitudinal_stiffness_n": (100.0, 1e7),
    "nominal_load_n": (10.0, 1e6),
    "friction_coefficient": (0.01, 3.0),
    "rolling_resistance_coefficient": (0.0, 0.5),
    "pneumatic_trail_m": (0.0, 0.5),
    "rolling_radius_m": (0.05, 2.0),
}
TIRE_COMMON_RANGES: dict[str, tuple[float, float]] = {
    "relaxation_length_lat_m": (0.005, 5.0),
    "relaxation_length_long_m": (0.005, 5.0),
    "rolling_radius_m": (0.05, 2.0),
}


@dataclass
class VehicleConfig:
    """A loaded, validated vehicle: packed parameters plus where they came from."""

    name: str
    path: Path
    vp: np.ndarray  # float64[N_VEHICLE_PARAM]
    tp: np.ndarray  # float64[4, N_TIRE_PARAM]
    tire_models: tuple[str, str]  # front, rear
    sources: dict[str, str] = field(default_factory=dict)


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping, with errors naming the file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys to values at the top level")
    return data


def number(path: Path | str, key: str, value: Any, lo: float, hi: float) -> float:
    """Validate one finite number within ``[lo, hi]``; errors name file and key."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{path}: key '{key}': expected a number, got {value!r}")
    try:
        val = float(value)
    except OverflowError:
        raise ConfigError(f"{path}: key '{key}': the number is too large") from None
    if not math.isfinite(val):
        raise ConfigError(f"{path}: key '{key}': must be finite, got {value!r}")
    if not lo <= val <= hi:
        raise ConfigError(f"{path}: key '{key}': {val:g} is outside [{lo:g}, {hi:g}]")
    return val


def choice(path: Path | str, key: str, value: Any, names: dict[str, int]) -> int:
    """Validate a named choice; errors list the accepted names."""
    if not isinstance(value, str) or value not in names:
        raise ConfigError(
            f"{path}: key '{key}': expected one of {sorted(names)}, got {value!r}"
        )
    return names[value]


def check_keys(path: Path | str, data: dict[str, Any], allowed: tuple[str, ...] | set[str],
               required: tuple[str, ...] | set[str] = ()) -> None:
    """Reject unknown keys and report missing ones, naming the file."""
    for key in data:
        if key not in allowed:
            raise ConfigError(
                f"{path}: unknown key '{key}' (allowed: {', '.join(sorted(allowed))})"
            )
    for key in required:
        if key not in data:
            raise ConfigError(f"{path}: missing key '{key}'")


def model_option_values(options: dict[str, Any] | None, source: str) -> dict[str, float]:
    """Validate a ``model:`` section against ``MODEL_OPTION_DEFAULTS``; returns slot values."""
    merged = dict(MODEL_OPTION_DEFAULTS)
    options = options or {}
    if not isinstance(options, dict):
        raise ConfigError(f"{source}: key 'model': expected a mapping")
    check_keys(f"{source} (model)", options, tuple(MODEL_OPTION_DEFAULTS))
    merged.update(options)
    values: dict[str, float] = {
        "slip_model": choice(source, "model.slip_model", merged["slip_model"], SLIP_MODEL_NAMES),
        "damping_model": choice(
            source, "model.damping_model", merged["damping_model"], DAMPING_MODEL_NAMES
        ),
    }
    for key, (lo, hi) in MODEL_OPTION_RANGES.items():
        values[key] = number(source, f"model.{key}", merged[key], lo, hi)
    return values


def apply_model_options(vp: np.ndarray, values: dict[str, float]) -> None:
    """Write validated model options into the parameter vector (same names as its slots)."""
    for key, value in values.items():
        vp[P.VEHICLE_PARAM_NAMES.index(key)] = value


def load_tire(path: Path) -> tuple[np.ndarray, str]:
    """Load a tire file into a packed ``float64[N_TIRE_PARAM]`` vector; returns it and the
    model's name.

    The file's ``model`` key names a registered tire model (``simserver.tire_models``),
    whose loader reads the rest. The two built-in forms::

        model: simple                       # core.tire_simple
        cornering_stiffness_n_per_rad: 51000
        longitudinal_stiffness_n: 22500
        nominal_load_n: 5005
        friction_coefficient: 0.9
        rolling_resistance_coefficient: 0.012
        pneumatic_trail_m: 0.04
        rolling_radius_m: 0.33
        relaxation_length_lat_m: 0.91       # b, paper eq. 16
        relaxation_length_long_m: 0.091     # B, paper eq. 26

        model: mf61                         # core.tire_mf61
        tir_file: ../tir/x.tir              # relative to this file
        rolling_radius_m: 0.305             # optional, default UNLOADED_RADIUS
        relaxation_length_lat_m: 0.48       # optional, default from PTY1/PTY2 at FNOMIN
        relaxation_length_long_m: 0.62      # optional, default from PTX1 at FNOMIN
    """
    path = Path(path)
    data = read_yaml(path)
    model = tire_model(choice(path, "model", data.get("model"), TIRE_MODEL_NAMES))
    loaded = model.load(path, data)
    if loaded.model_params.size > N_MODEL_PARAM_MAX:
        raise ConfigError(f"{path}: tire model {model.name!r} packs {loaded.model_params.size} "
                          f"parameters, more than the {N_MODEL_PARAM_MAX} a tire vector holds")
    tp = np.zeros(N_TIRE_PARAM, dtype=np.float64)
    tp[TP_MODEL] = model.id
    tp[TP_RADIUS_M] = loaded.rolling_radius_m
    tp[TP_RELAX_LAT_M] = loaded.relax_lat_m
    tp[TP_RELAX_LONG_M] = loaded.relax_long_m
    tp[TP_MODEL_BASE:TP_MODEL_BASE + loaded.model_params.size] = loaded.model_params
    return tp, model.name


def load_vehicle(path: str | Path, model_options: dict[str, Any] | None = None,
                 options_source: str = "model options") -> VehicleConfig:
    """Load and validate a vehicle file and its subsystem files.

    The road starts flat with friction scale 1 (``core.params.set_road`` changes it).
    """
    path = Path(path)
    top = read_yaml(path)
    allowed = ("name", "description", "tires", *SUBSYSTEM_KEYS)
    check_keys(path, top, allowed, required=("name", "tires", *SUBSYSTEM_KEYS))
    vp = np.zeros(P.N_VEHICLE_PARAM, dtype=np.float64)
    sources: dict[str, str] = {}
    for subsystem, keys in SUBSYSTEM_KEYS.items():
        ref = top[subsystem]
        if not isinstance(ref, str):
            raise ConfigError(f"{path}: key '{subsystem}': expected a file path")
        sub_path = (path.parent / ref).resolve()
        sources[subsystem] = str(sub_path)
        data = read_yaml(sub_path)
        check_keys(sub_path, data, keys, required=keys)
        for key in keys:
            slot = P.VEHICLE_PARAM_NAMES.index(key)
            if key == "driven_axle":
                vp[slot] = choice(sub_path, key, data[key], P.DRIVEN_AXLE_NAMES)
            else:
                vp[slot] = number(sub_path, key, data[key], *PARAM_RANGES[key])
    if vp[P.VP_SPRUNG_MASS_KG] > vp[P.VP_MASS_KG]:
        raise ConfigError(f"{sources['chassis']}: key 'sprung_mass_kg': exceeds mass_kg")

    tires = top["tires"]
    if not isinstance(tires, dict):
        raise ConfigError(f"{path}: key 'tires': expected a mapping with 'front' and 'rear'")
    check_keys(f"{path} (tires)", tires, ("front", "rear"), required=("front", "rear"))
    tp = np.zeros((4, N_TIRE_PARAM), dtype=np.float64)
    names = []
    for axle, rows in (("front", (0, 1)), ("rear", (2, 3))):
        if not isinstance(tires[axle], str):
            raise ConfigError(f"{path}: key 'tires.{axle}': expected a file path")
        tire_path = (path.parent / tires[axle]).resolve()
        sources[f"tire_{axle}"] = str(tire_path)
        vec, model_name = load_tire(tire_path)
        for row in rows:
            tp[row] = vec
        names.append(model_name)

    apply_model_options(vp, model_option_values(model_options, options_source))
    P.set_road(vp, 0.0, 0.0, 1.0)
    name = top["name"]
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{path}: key 'name': expected a non-empty string")
    return VehicleConfig(name=name, path=path, vp=vp, tp=tp,
                         tire_models=(names[0], names[1]), sources=sources)


# ----------------------------------------------------------------- the reference doc
PARAM_MEANING: dict[str, str] = {
    "mass_kg": "total mass, wheels included",
    "sprung_mass_kg": "mass on the springs (body); at most mass_kg",
    "yaw_inertia_kgm2": "whole car about the vertical axis through the CG",
    "roll_inertia_kgm2": "sprung mass about its own CG, roll axis",
    "pitch_inertia_kgm2": "sprung mass about its own CG, pitch axis",
    "cg_height_m": "CG height above the ground",
    "cg_to_front_axle_m": "CG to front axle, along x",
    "cg_to_rear_axle_m": "CG to rear axle, along x",
    "track_front_m": "front track width",
    "track_rear_m": "rear track width",
    "drag_area_m2": "aerodynamic drag area Cd A",
    "air_density_kg_per_m3": "air density (0 switches drag off)",
    "spring_front_n_per_m": "suspension spring rate at each front wheel",
    "spring_rear_n_per_m": "suspension spring rate at each rear wheel",
    "damper_front_n_s_per_m": "damper rate at each front wheel",
    "damper_rear_n_s_per_m": "damper rate at each rear wheel",
    "antiroll_front_n_per_m": "front anti-roll bar, as a rate at the wheel (0: none)",
    "antiroll_rear_n_per_m": "rear anti-roll bar, as a rate at the wheel (0: none)",
    "steering_ratio": "steering-wheel angle / road-wheel angle (parallel steer)",
    "steering_wheel_max_rad": "steering-wheel angle at steer = 1",
    "brake_torque_max_nm": "brake torque of all four wheels together at pedal = 1",
    "brake_front_fraction": "share of the brake torque on the front axle (70/30 is the "
                            "paper's pattern at rest, model.md 4b item 4)",
    "parking_brake_torque_nm": "parking-brake torque per rear wheel",
    "drive_torque_max_nm": "drive torque at the wheels, all driven wheels together, gear D",
    "drive_power_max_w": "power cap: torque <= P / |mean driven-wheel spin| above 1 rad/s",
    "reverse_torque_max_nm": "drive torque at the wheels in gear R",
    "driven_axle": "front, rear or both (open differential on each driven axle)",
    "drive_front_fraction": "torque share of the front axle when both are driven",
    "wheel_inertia_front_kgm2": "spin inertia of a front wheel with disc and driveline share",
    "wheel_inertia_rear_kgm2": "spin inertia of a rear wheel with disc and driveline share",
}
TIRE_MEANING: dict[str, str] = {
    "cornering_stiffness_n_per_rad": "C_alpha at nominal_load_n, linear in the load",
    "longitudinal_stiffness_n": "C_kappa (N per unit slip) at nominal_load_n, linear in "
                                "the load",
    "nominal_load_n": "load at which the stiffnesses are given",
    "friction_coefficient": "peak friction mu (times the road's friction scale)",
    "rolling_resistance_coefficient": "rolling-resistance force / Fz",
    "pneumatic_trail_m": "pneumatic trail at zero slip (Mz = -t Fy, t falls to 0 at full "
                         "sliding)",
    "rolling_radius_m": "effective rolling radius R (mf61: default UNLOADED_RADIUS)",
    "relaxation_length_lat_m": "b of paper eq. 16 (mf61: default from PTY1, PTY2 at FNOMIN)",
    "relaxation_length_long_m": "B of paper eq. 26 (mf61: default from PTX1 at FNOMIN)",
}
MODEL_OPTION_MEANING: dict[str, str] = {
    "slip_model": f"slip states: {', '.join(SLIP_MODEL_NAMES)} (core/slip.py)",
    "damping_model": f"low-speed damping: {', '.join(DAMPING_MODEL_NAMES)} (core/damping.py)",
    "damping_ratio": "zeta of Appendix A",
    "damping_trigger_v_mps": "eps of Appendix A: the paper's trigger needs |v| below it",
    "damping_fade_speed_mps": "the patch damping fades out by this hub speed",
    "kinematic_u_min_mps": "u_min of the eq. (1) patch (kinematic baseline only)",
    "slide_widen_speed_mps": "passive slip states: the sliding limit widens above this "
                             "hub speed",
    "gravity_mps2": "gravitational acceleration",
}


def _range_text(lo: float, hi: float) -> str:
    return f"{lo:g} .. {hi:g}"


def config_reference_markdown() -> str:
    """The configuration reference (docs/configuration.md), from the tables above."""
    lines = [
        "# Configuration reference",
        "",
        "Generated from `simserver/adapters/config.py` (`python -m simserver.adapters.config "
        "--write docs/configuration.md`; a test fails when it drifts). Every key is required "
        "unless marked optional; a key that is unknown, missing, not a number, not finite or "
        "out of range is rejected with the file and the key named. Units are in the key "
        "names.",
        "",
        "## The vehicle file",
        "",
        "`name` (string), `description` (optional), one path per subsystem file (relative to "
        "the vehicle file): " + ", ".join(f"`{s}`" for s in SUBSYSTEM_KEYS)
        + ", and `tires: {front: PATH, rear: PATH}`.",
    ]
    for subsystem, keys in SUBSYSTEM_KEYS.items():
        lines += ["", f"## `{subsystem}` file", "", "| key | range | meaning |", "|---|---|---|"]
        for key in keys:
            rng = ("`" + "`, `".join(P.DRIVEN_AXLE_NAMES) + "`" if key == "driven_axle"
                   else _range_text(*PARAM_RANGES[key]))
            lines.append(f"| `{key}` | {rng} | {PARAM_MEANING[key]} |")
    lines += ["", "## Tire files", "",
              f"`model`: one of {', '.join(f'`{m}`' for m in TIRE_MODEL_NAMES)}.", "",
              "`model: simple` (the brush combined-slip tire, `core/tire_simple.py`) takes "
              "every key below; `model: mf61` (Magic Formula 6.1, `core/tire_mf61.py`) takes "
              "`tir_file` (an MF-Tyre .tir property file, relative to the tire file) and, "
              "optionally, the last three.", "",
              "| key | range | meaning |", "|---|---|---|"]
    tire_keys = {**SIMPLE_TIRE_RANGES, **TIRE_COMMON_RANGES}
    for key, (lo, hi) in tire_keys.items():
        lines.append(f"| `{key}` | {_range_text(lo, hi)} | {TIRE_MEANING[key]} |")
    lines += ["", "## Model options", "",
              "The `model:` section of a scenario or scene; every key is optional.", "",
              "| key | default | range | meaning |", "|---|---|---|---|"]
    for key, default in MODEL_OPTION_DEFAULTS.items():
        rng = ("choice" if key not in MODEL_OPTION_RANGES
               else _range_text(*MODEL_OPTION_RANGES[key]))
        lines.append(f"| `{key}` | `{default}` | {rng} | {MODEL_OPTION_MEANING[key]} |")
    lines += ["", "Scenario files (road, initial state, duration, input keyframes) are "
              "described in the README; the server's own config, key by key, in "
              "`configs/server/default.yaml`.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m simserver.adapters.config [--write] PATH``: check or write the reference."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("path", type=Path)
    parser.add_argument("--write", action="store_true", help="rewrite the file")
    args = parser.parse_args(argv)
    text = config_reference_markdown()
    if args.write:
        args.path.write_text(text, encoding="utf-8")
        return 0
    if not args.path.is_file() or args.path.read_text(encoding="utf-8") != text:
        print(f"{args.path} is out of date: run python -m simserver.adapters.config --write "
              f"{args.path}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
