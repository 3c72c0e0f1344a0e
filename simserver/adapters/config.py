"""Vehicle configuration: YAML files, one per subsystem, composed by path.

A vehicle is a top-level YAML file naming its subsystem files (paths relative to it)::

    name: paper_sedan
    chassis: chassis.yaml          # mass, inertias, geometry, aero
    suspension: suspension.yaml    # springs, dampers, anti-roll bars
    steering: steering.yaml
    brakes: brakes.yaml
    powertrain: powertrain.yaml
    tires: {front: ../../tires/paper_sti.yaml, rear: ../../tires/paper_sti.yaml}

Each subsystem file holds exactly the keys of its parameter table in ``core/params.py``
(units in the key names), each checked against the range or the named choices given there
(``read_params``). Tire files are described in ``load_tire``. Every error names the file
and the key (``ConfigError``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simserver.adapters.opendrive import START_KEYS
from simserver.adapters.validate import (  # re-exported: callers import them from here
    ConfigError,
    check_keys,
    choice,
    number,
    read_yaml,
    referenced_file,
)
from simserver.core import params as P
from simserver.core.param_table import (
    ParamTable,
    pad_list,
    slot_constants_source,
    with_slot_constants,
)
from simserver.core.tire import N_TIRE_PARAM
from simserver.core.tire_layout import (
    TP_MIRRORED,
    TP_MODEL,
    TP_MODEL_BASE,
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)
from simserver.tires.registry import N_MODEL_PARAM_MAX, TIRE_MODEL_NAMES, tire_model, tire_models

# The vehicle file's subsystem keys, one file each, and the ``model:`` section's defaults,
# from the parameter tables (core/params.py).
SUBSYSTEMS: tuple[str, ...] = tuple(table.name for table in P.VEHICLE_SUBSYSTEMS)
MODEL_OPTION_DEFAULTS: dict[str, Any] = P.MODEL_OPTIONS.defaults
TIR_SUFFIX = ".tir"  # a tire path with this suffix is an MF-Tyre file (load_tire)

@dataclass
class VehicleConfig:
    """A loaded, validated vehicle: packed parameters plus where they came from."""

    name: str
    path: Path
    vp: np.ndarray  # float64[N_VEHICLE_PARAM]
    tp: np.ndarray  # float64[4, N_TIRE_PARAM]
    tire_models: tuple[str, str]  # front, rear
    sources: dict[str, str] = field(default_factory=dict)


def read_params(path: Path | str, data: dict[str, Any], table: ParamTable,
                section: str | None = None) -> dict[str, float]:
    """Validate one section against its parameter table: YAML key -> number.

    Unknown keys and missing required keys are errors; optional keys take their defaults;
    a named choice becomes the number stored for it. ``section`` names a section inside
    the file (``model``, ``road``) so that errors say ``model.damping_ratio``.
    """
    check_keys(path if section is None else f"{path} ({section})", data, table.keys,
               required=table.required_keys)
    values: dict[str, float] = {}
    for param in table:
        if param.derived:
            continue
        key = param.yaml_key
        label = key if section is None else f"{section}.{key}"
        value = data.get(key, param.default)
        if isinstance(value, bool) and param.choices is not None and set(param.choices) == {
                "off", "on"}:
            value = "on" if value else "off"  # YAML reads a bare on/off as a boolean
        if param.choices is not None:
            values[key] = choice(path, label, value, param.choices)
        elif param.size > 1:
            values[key] = number_list(path, label, value, param)
        else:
            values[key] = number(path, label, value, param.lo, param.hi)
    return values


def number_list(path: Path | str, label: str, value: Any, param: Any) -> list[float]:
    """A list parameter: 1 .. ``param.size`` numbers, each in range (unpadded)."""
    if not isinstance(value, list) or not 1 <= len(value) <= param.size:
        raise ConfigError(f"{path}: key '{label}': expected a list of 1 to {param.size} "
                          f"numbers")
    return [number(path, f"{label}[{k}]", v, param.lo, param.hi) for k, v in enumerate(value)]


def pack_params(vp: np.ndarray, table: ParamTable, values: dict[str, Any]) -> None:
    """Write values keyed as ``read_params`` returns them into their slots of ``vp`` (a list
    padded with its last value, ``core.param_table.pad_list``)."""
    for key, value in values.items():
        param = table.by_key(key)
        if param.size > 1:
            vp[param.slot:param.slot + param.size] = pad_list(value, param.size)
        else:
            vp[param.slot] = value


AUTOMATIC_SECTION = "automatic"  # the powertrain file's section for ``kind: automatic``


def read_powertrain(path: Path | str, data: dict[str, Any], vp: np.ndarray) -> None:
    """The powertrain file: its own keys, and with ``kind: automatic`` its ``automatic:``
    section (``core.params.AUTOMATIC``), checked for consistent list lengths."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping")
    data = dict(data)
    section = data.pop(AUTOMATIC_SECTION, None)
    values = read_params(path, data, P.POWERTRAIN)
    pack_params(vp, P.POWERTRAIN, values)
    if values["kind"] != P.POWERTRAIN_AUTOMATIC:
        if section is not None:
            raise ConfigError(f"{path}: key '{AUTOMATIC_SECTION}': only with kind: automatic")
        return
    if not isinstance(section, dict):
        raise ConfigError(f"{path}: key '{AUTOMATIC_SECTION}': kind: automatic needs this "
                          "section (a mapping; docs/configuration.md)")
    auto = read_params(path, section, P.AUTOMATIC, section=AUTOMATIC_SECTION)

    def fail(key: str, why: str) -> None:
        raise ConfigError(f"{path}: key '{AUTOMATIC_SECTION}.{key}': {why}")

    for xs_key, ys_key in (("engine_curve_speed_rpm", "engine_full_load_torque_nm"),
                           ("converter_speed_ratio", "converter_k_factor_rpm_per_sqrt_nm"),
                           ("converter_speed_ratio", "converter_torque_ratio")):
        if len(auto[ys_key]) != len(auto[xs_key]):
            fail(ys_key, f"expected {len(auto[xs_key])} values, one per {xs_key}")
        if any(b <= a for a, b in zip(auto[xs_key], auto[xs_key][1:], strict=False)):
            fail(xs_key, "expected increasing values")
    if auto["converter_speed_ratio"][0] != 0.0:
        fail("converter_speed_ratio", "expected the first point at 0 (stall)")
    if auto["converter_speed_ratio"][-1] >= 1.0:
        fail("converter_speed_ratio", "expected the last point below 1 (the coupling)")
    n_gears = len(auto["gear_ratios"])
    if any(b >= a for a, b in zip(auto["gear_ratios"], auto["gear_ratios"][1:],
                                        strict=False)):
        fail("gear_ratios", "expected decreasing ratios, first gear first")
    for key in ("upshift_speed_light_mps", "upshift_speed_full_mps"):
        if len(auto[key]) != max(n_gears - 1, 1):
            fail(key, f"expected {max(n_gears - 1, 1)} values: one per upshift of the "
                 f"{n_gears} gears")
        if any(b <= a for a, b in zip(auto[key], auto[key][1:], strict=False)):
            fail(key, "expected increasing speeds")
    if any(f < lo for lo, f in zip(auto["upshift_speed_light_mps"],
                                   auto["upshift_speed_full_mps"], strict=True)):
        fail("upshift_speed_full_mps", "an upshift at full throttle comes before the same "
             "upshift at closed throttle")
    if auto["lockup_release_speed_rpm"] > auto["lockup_engage_speed_rpm"]:
        fail("lockup_release_speed_rpm", "exceeds lockup_engage_speed_rpm")
    if auto["engine_speed_max_rpm"] <= auto["engine_idle_speed_rpm"]:
        fail("engine_speed_max_rpm", "not above engine_idle_speed_rpm")
    pack_params(vp, P.AUTOMATIC, auto)
    vp[P.VP_GEAR_COUNT] = n_gears


def model_option_values(options: dict[str, Any] | None, source: str) -> dict[str, float]:
    """Validate a ``model:`` section against ``core.params.MODEL_OPTIONS``: key -> value."""
    options = options or {}
    if not isinstance(options, dict):
        raise ConfigError(f"{source}: key 'model': expected a mapping")
    return read_params(source, options, P.MODEL_OPTIONS, section="model")


def apply_model_options(vp: np.ndarray, values: dict[str, float]) -> None:
    """Write validated model options into the parameter vector."""
    pack_params(vp, P.MODEL_OPTIONS, values)


def load_tire(path: Path, data: dict[str, Any] | None = None) -> tuple[np.ndarray, str]:
    """Load a tire file into a packed ``float64[N_TIRE_PARAM]`` vector; returns it and the
    model's name.

    The file's ``model`` key names a registered tire model (``simserver.tires.registry``),
    whose loader reads the rest. A ``.tir`` file is read as a tire file holding only
    ``model: mf61`` and ``tir_file: <itself>``. The two built-in forms::

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
        relaxation_length_lat_m: 0.48       # optional, default from PTY1, PTY2, R0
        relaxation_length_long_m: 0.62      # optional, default from PTX1, R0

    Every key with its unit, range and meaning: the model's parameter table
    (``TireModel.params``, docs/configuration.md). The vector is the tire as its file
    describes it (``tp[TP_MIRRORED] = 0``); ``load_vehicle`` mirrors the corners on the
    other side (``load_tire_sided``).

    ``data``: the file's mapping already read (a resolved vehicle, ``resolve_vehicle``).
    """
    tp, name, _ = load_tire_sided(path, data)
    return tp, name


def load_tire_sided(path: Path, data: dict[str, Any] | None = None
                    ) -> tuple[np.ndarray, str, str | None]:
    """``load_tire`` and the side the file's tire is meant for: ``"left"``, ``"right"`` or
    None (a symmetric tire, never mirrored)."""
    path = Path(path)
    if data is None and path.suffix.lower() == TIR_SUFFIX:  # an MF-Tyre file itself
        data = {"model": "mf61", "tir_file": path.name}  # its defaults throughout
    elif data is None:
        data = read_yaml(path)
    model = tire_model(choice(path, "model", data.get("model"), TIRE_MODEL_NAMES))
    loaded = model.load(path, data)
    if loaded.model_params.size > model.n_params:  # n_params <= N_MODEL_PARAM_MAX: registry
        raise ConfigError(f"{path}: tire model {model.name!r} packs {loaded.model_params.size} "
                          f"parameters, more than the {model.n_params} it declared (a tire "
                          f"vector holds {N_MODEL_PARAM_MAX})")
    tp = np.zeros(N_TIRE_PARAM, dtype=np.float64)
    tp[TP_MODEL] = model.id
    tp[TP_RADIUS_M] = loaded.rolling_radius_m
    tp[TP_RELAX_LAT_M] = loaded.relax_lat_m
    tp[TP_RELAX_LONG_M] = loaded.relax_long_m
    tp[TP_MODEL_BASE:TP_MODEL_BASE + loaded.model_params.size] = loaded.model_params
    return tp, model.name, loaded.side


def load_vehicle(path: str | Path, model_options: dict[str, Any] | None = None,
                 options_source: str = "model options",
                 resolved: dict[str, Any] | None = None) -> VehicleConfig:
    """Load and validate a vehicle file and its subsystem files.

    ``resolved``: the vehicle as ``resolve_vehicle`` returns it (its files' contents
    inline); then ``path`` only labels the errors.
    The road is not the vehicle's: it is the terrain's (``core.terrain.Terrain.road``),
    which the simulation writes from the scene's ``road:`` section (``core.road.set_road``).
    """
    path = Path(path)
    top = read_yaml(path) if resolved is None else resolved
    allowed = ("name", "description", "tires", *SUBSYSTEMS)
    check_keys(path, top, allowed, required=("name", "tires", *SUBSYSTEMS))
    vp = np.zeros(P.N_VEHICLE_PARAM, dtype=np.float64)
    sources: dict[str, str] = {}
    for table in P.VEHICLE_SUBSYSTEMS:
        subsystem = table.name
        ref = top[subsystem]
        if isinstance(ref, dict) and resolved is not None:
            sources[subsystem] = f"{path}.{subsystem}"
            if table is P.POWERTRAIN:
                read_powertrain(sources[subsystem], ref, vp)
            else:
                pack_params(vp, table, read_params(sources[subsystem], ref, table))
            continue
        sub_path = referenced_file(path, subsystem, ref)
        sources[subsystem] = str(sub_path)
        try:
            sub_data = read_yaml(sub_path)
        except ConfigError as exc:  # unreadable or not YAML: name the key that refers to it
            raise ConfigError(f"{path}: key '{subsystem}': {exc}") from None
        if table is P.POWERTRAIN:
            read_powertrain(sub_path, sub_data, vp)
        else:
            pack_params(vp, table, read_params(sub_path, sub_data, table))
    if vp[P.VP_SPRUNG_MASS_KG] > vp[P.VP_MASS_KG]:
        raise ConfigError(f"{sources['chassis']}: key 'sprung_mass_kg': exceeds mass_kg")

    tires = top["tires"]
    if not isinstance(tires, dict):
        raise ConfigError(f"{path}: key 'tires': expected a mapping with 'front' and 'rear'")
    check_keys(f"{path} (tires)", tires, ("front", "rear"), required=("front", "rear"))
    tp = np.zeros((4, N_TIRE_PARAM), dtype=np.float64)
    names = []
    for axle, rows in (("front", (0, 1)), ("rear", (2, 3))):
        if isinstance(tires[axle], dict) and resolved is not None:  # inline (resolved)
            sources[f"tire_{axle}"] = f"{path}.tires.{axle}"
            vec, model_name, side = load_tire_sided(Path(sources[f"tire_{axle}"]),
                                                    tires[axle])
        else:
            tire_path = referenced_file(path, f"tires.{axle}", tires[axle])
            sources[f"tire_{axle}"] = str(tire_path)
            try:
                vec, model_name, side = load_tire_sided(tire_path)
            except ConfigError as exc:  # name the key that refers to the tire file too
                raise ConfigError(f"{path}: key 'tires.{axle}': {exc}") from None
        for row in rows:
            tp[row] = vec
            # one file per axle: the corner on the other side gets the mirror image
            # (docs/configuration.md, "Tire files"); rows are left, right (core.layout)
            corner_side = "left" if row % 2 == 0 else "right"
            tp[row, TP_MIRRORED] = 1.0 if side is not None and side != corner_side else 0.0
        names.append(model_name)

    apply_model_options(vp, model_option_values(model_options, options_source))
    name = top["name"]
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{path}: key 'name': expected a non-empty string")
    return VehicleConfig(name=name, path=path, vp=vp, tp=tp,
                         tire_models=(names[0], names[1]), sources=sources)


def resolve_vehicle(path: str | Path) -> dict[str, Any]:
    """A vehicle file with every file it names read inline: subsystem and tire mappings
    instead of paths (``load_vehicle(..., resolved=...)`` loads it). A tire key ending in
    ``_file`` (``tir_file``) becomes an absolute path."""
    path = Path(path)
    top = dict(read_yaml(path))
    for subsystem in SUBSYSTEMS:
        if isinstance(top.get(subsystem), str):
            top[subsystem] = dict(read_yaml((path.parent / top[subsystem]).resolve()))
    tires = top.get("tires")
    if isinstance(tires, dict):
        top["tires"] = dict(tires)
        for axle, ref in tires.items():
            if isinstance(ref, str):
                tire_path = (path.parent / ref).resolve()
                tire = dict(read_yaml(tire_path))
                for key, value in tire.items():
                    if key.endswith("_file") and isinstance(value, str):
                        tire[key] = str((tire_path.parent / value).resolve())
                top["tires"][axle] = tire
    return top


# ----------------------------------------------------------------- the reference doc
def _param_rows(table: ParamTable, with_default: bool) -> list[str]:
    """A markdown table of a section's keys, from its parameter table."""
    if with_default:
        lines = ["| key | unit | default | accepted | meaning |", "|---|---|---|---|---|"]
    else:
        lines = ["| key | unit | accepted | meaning |", "|---|---|---|---|"]
    for param in table:
        if param.derived:
            continue
        if not with_default:
            default = ""
        elif param.default is None:
            default = " required |"
        elif isinstance(param.default, str) and param.choices is None:
            default = f" {param.default} |"  # computed by the loader
        else:
            default = f" `{param.default}` |"
        meaning = param.meaning.replace("|", "\\|")  # |v| would end the markdown cell
        lines.append(f"| `{param.yaml_key}` | {param.unit} |{default} {param.range_text()} | "
                     f"{meaning} |")
    return lines


def config_reference_markdown() -> str:
    """The configuration reference (docs/configuration.md), from the parameter tables."""
    lines = [
        "# Configuration reference",
        "",
        "Generated from the parameter tables in `simserver/core/params.py` (`python -m "
        "simserver.adapters.config --write docs/configuration.md`; a test fails when it "
        "drifts). Every key is required unless it has a default; a key that is unknown, "
        "missing, not a number, not finite, out of range or not one of the named choices is "
        "rejected with the file and the key named. Units are in the key names, and in the "
        "unit column (`-`: a pure number).",
        "",
        "## The vehicle file",
        "",
        "`name` (string), `description` (optional), one path per subsystem file (relative to "
        "the vehicle file): " + ", ".join(f"`{s}`" for s in SUBSYSTEMS)
        + ", and `tires: {front: PATH, rear: PATH}`.",
    ]
    for table in P.VEHICLE_SUBSYSTEMS:
        lines += ["", f"## `{table.name}` file", "", f"{table.title.capitalize()}.", ""]
        lines += _param_rows(table, with_default=table is P.POWERTRAIN)
    lines += ["", f"### `{AUTOMATIC_SECTION}:` section of the powertrain file", "",
              f"{P.AUTOMATIC.title.capitalize()}: required with `kind: automatic`, refused "
              "otherwise; every key required. A list key takes 1 to the number of values "
              "shown; the curves' lists are as long as their points' list (the engine's "
              "speeds, the converter's speed ratios), the upshift speeds one fewer than the "
              "gears.", ""]
    lines += _param_rows(P.AUTOMATIC, with_default=False)
    lines += ["", "## Tire files", "",
              f"`model`: one of {', '.join(f'`{m.name}`' for m in tire_models())}; the "
              "other keys are the model's (from its parameter table, in its module of "
              "`simserver/tires/`). A default in words is computed by the loader "
              "when the key is absent. Wherever a tire file is named (a vehicle's `tires:`, "
              "`simserver tire-curves`), an MF-Tyre `.tir` file may be named instead: it is "
              "read as `model: mf61` with `tir_file` itself and every default.",
              "",
              "A tire file describes the tire as measured on one side of a car (`mf61`: the "
              ".tir's `TYRESIDE`, `Left` when absent; `simple`: symmetric). The vehicle's "
              "`tires: {front, rear}` gives one file per axle: the corner on the file's side "
              "uses the tire as described, the corner on the other side its mirror image "
              "(slip angle, camber, side force and aligning moment mirrored, as MF-Tyre "
              "does), so a left tire's shifts (SHy, SVy, conicity, ply steer) pull the car "
              "to neither side."]
    for model in tire_models():
        if model.params is None:
            continue
        lines += ["", f"### `model: {model.name}`", "", f"{model.description}.", ""]
        lines += [f"- `{key}` (path): {meaning}." for key, meaning in model.path_keys]
        if model.path_keys:
            lines.append("")
        lines += _param_rows(model.params, with_default=True)
    for table, where in ((P.ROAD, "road"), (P.MODEL_OPTIONS, "model")):
        lines += ["", f"## `{where}:` section of a scenario or scene", "",
                  f"{table.title.capitalize()}; every key is optional.", ""]
        lines += _param_rows(table, with_default=True)
    lines += ["", "## `start:` of a scenario or scene on an OpenDRIVE road", "",
              "The car's start by road, s and lane (instead of `initial`'s `x_m`, `y_m`, "
              "`yaw_rad`; `initial`'s speeds still apply): at rest on the lane's centre, "
              "heading along the lane's direction of travel (right-hand traffic unless the "
              "road says `rule=\"LHT\"`), on the surface. Every key is required; a road, s "
              "or lane the file does not have is an error naming the key. The `reset` "
              "control takes the same keys as `lane` (docs/protocol.md).", "",
              "| key | unit | meaning |", "|---|---|---|"]
    lines += [f"| `{key}` | {unit} | {meaning} |" for key, (unit, meaning) in START_KEYS.items()]
    lines += _terrain_section()
    lines += _driver_section()
    lines += ["", "Scenario files (initial state, duration, input keyframes) are described in "
              "the README; the server's own config, key by key, in "
              "`configs/server/default.yaml`.", ""]
    return "\n".join(lines)


def _terrain_section() -> list[str]:
    """The ``terrain:`` keys of each kind, from ``adapters.terrain_files.TERRAIN_SCHEMAS``."""
    from simserver.adapters.terrain_files import TERRAIN_SCHEMAS
    from simserver.core.terrain import TERRAIN_KINDS

    lines = ["", "## `terrain:` section of a scenario or scene", "",
             "The ground under the wheels; optional (default `kind: plane`). Files are "
             "relative to the scene or scenario file and, on a server, must lie in its "
             "config folders like every other file a config names. Keys by `kind`:"]
    for variant in TERRAIN_KINDS:
        schema = TERRAIN_SCHEMAS[variant.name]
        meaning = variant.meaning[0].upper() + variant.meaning[1:]
        lines += ["", f"### `kind: {variant.name}`", "", f"{meaning}."]
        if variant.name == "plane":
            lines[-1] += " No other key: the `road:` section gives them."
            continue
        lines.append("")
        for k in schema.other_keys:
            unit = "path" if k.kind == "file" else "`[x, y]`, m"
            presence = "required" if k.required else (
                "optional" if k.default is None else f"default `{k.default}`")
            lines.append(f"- `{k.key}` ({unit}, {presence}): {k.meaning}.")
        lines.append("")
        lines += _param_rows(schema.numbers, with_default=True)
        if variant.name == "opendrive":
            lines += _xodr_bounds()
    return lines


def _driver_section() -> list[str]:
    """A scenario car's ``driver:`` keys, from ``core.driver``'s tables and
    ``adapters.driver_config``."""
    from simserver.core import driver as D

    lines = ["", "## `driver:` of a scenario's car", "",
             "The built-in driver (docs/model.md section 15) drives the car through its steer, "
             "throttle, brake, parking brake and gear: a car of `cars:` (or a single car's "
             "scenario) with a `driver:` needs no `inputs`; a car added to a running world "
             "by `add_car` takes the same block as JSON (`\"driver\"`, with "
             "`\"driven_by\": \"driver\"`; docs/protocol.md section 5.1). Required: "
             "`path`, either "
             "`{points: [[x, y], ...]}` (a polyline in world x, y, m; 2 or more points) or "
             "`{road, lane}` (a lane of the scene's OpenDRIVE terrain, optional `s_from_m`, "
             "`s_to_m` along the road's reference line and `step_m`, the samples' spacing, "
             "default 0.5 m; the path runs in the lane's direction of travel). Stations are "
             "distances along the path (over the terrain's surface) from its first point; the "
             "car stops at the path's end. A path that leaves the road (OpenDRIVE: beyond the "
             "outer lanes' edges; a height map: off its grid) is refused. Optional: "
             "`speed_profile` (`[{s_m, v_mps}, ...]`, stations increasing: the desired speed "
             "along the path, linear between, `idm.v0_mps` without one), `stop_s_m` (the "
             "front bumper stops at this station and holds), `go_t_s` (the simulated time "
             "the stop point is released), `idm:` (below) and the driver's keys (below).", "",
             "### `idm:` of a `driver:`", "", f"{D.IDM.title[0].upper()}{D.IDM.title[1:]}.", ""]
    lines += _param_rows(D.IDM, with_default=True)
    lines += ["", "### The driver's keys", "", f"{D.CONTROL.title[0].upper()}"
              f"{D.CONTROL.title[1:]}.", ""]
    lines += _param_rows(D.CONTROL, with_default=True)
    return lines


def _xodr_bounds() -> list[str]:
    """What an ``.xodr`` file may hold, from ``adapters.opendrive.XODR_BOUNDS``."""
    from simserver.adapters import opendrive as od

    lines = ["", "The file is read as it streams (at most "
             f"{od.MAX_XODR_BYTES >> 20} MiB). Every number it gives must be finite and "
             "within these bounds, or the load is refused with an error naming the file, the "
             "line, the element and the attribute (`road.xodr:7: road r1 <geometry> #0 "
             "<poly3>: attribute 'c'=...`); a cubic is checked by its largest value over its "
             "piece, up to the next piece or the road's (section's) end. Rasterised, the "
             f"roads may take at most {od.MAX_RASTER_SAMPLES} reference samples (a quarter "
             f"of a cell apart) and {od.MAX_RASTER_CELLS} grid cells.", "",
             "| bound | applies to | unit | accepted | note |", "|---|---|---|---|---|"]
    for name, bound in od.XODR_BOUNDS.items():
        lines.append(f"| {name} | {bound.applies_to} | {bound.unit} | {bound.lo:g} .. "
                     f"{bound.hi:g} | {bound.why} |")
    return lines


def slot_constants() -> str:
    """The generated ``VP_*`` and ``ROAD_*`` blocks of ``core/params.py``, from the
    parameter tables (``ROAD_*``: the slots of a terrain's road, ``Terrain.road``)."""
    return (slot_constants_source(P.VEHICLE_PARAM_TABLES, "VP_")
            + "# the terrain's road (core.terrain.Terrain.road)\n"
            + slot_constants_source((P.ROAD,), "ROAD_"))


def main(argv: list[str] | None = None) -> int:
    """``python -m simserver.adapters.config [--write] [--slots] PATH``: check or write.

    PATH is the configuration reference (docs/configuration.md) or, with ``--slots``, the
    module holding the generated slot constants (simserver/core/params.py).
    """
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("path", type=Path)
    parser.add_argument("--write", action="store_true", help="rewrite the file")
    parser.add_argument("--slots", action="store_true",
                        help="PATH is core/params.py: its generated VP_* slot constants")
    args = parser.parse_args(argv)
    current = args.path.read_text(encoding="utf-8") if args.path.is_file() else None
    if args.slots:
        if current is None:
            print(f"{args.path}: no such file")
            return 1
        text = with_slot_constants(current, slot_constants())
    else:
        text = config_reference_markdown()
    if args.write:
        args.path.write_text(text, encoding="utf-8")
        return 0
    if current != text:
        flags = "--write --slots" if args.slots else "--write"
        print(f"{args.path} is out of date: run python -m simserver.adapters.config {flags} "
              f"{args.path}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
