"""Output files of a headless run: the time history (Parquet) and a summary (JSON).

``history.parquet``
    One row per recorded step, one float64 column per quantity. The column names come
    from ``core.layout`` (the one definition of every state, output and input slot):

    - ``time_s`` first;
    - every name of ``STATE_NAMES`` except the internal ``hub_u_prev_*`` slots (the hub
      speed of the previous step, kept only for the damping trigger; it is ``hub_u_*`` of
      the row before, so writing it would add four columns of noise);
    - every name of ``OUTPUT_NAMES`` (forces and accelerations evaluated at the row's
      state);
    - every name of ``INPUT_NAMES`` prefixed with ``input_`` (the driver inputs applied
      over the step that starts at the row's time; ``input_gear`` holds the code of
      ``core.layout.GEAR_NAMES``: 0 P, 1 R, 2 N, 3 D);
    - the world pose of each row's state, ``world_`` and the names of ``core.layout``'s
      ``POSE_*`` slots (``world_x_m``, ``world_y_m``, ``world_z_m``, ``world_yaw_rad``,
      ``world_pitch_rad``, ``world_roll_rad``): what the server publishes as the state's
      pose (``simulation.pose_of``). The states' ``x_m``, ``y_m`` are on the road plane,
      and on a terrain on the reference plane under the wheels, which moves from row to
      row; ``world_*`` place the car on the terrain (its files' axes, z up).

    Units are carried in the names (``_m``, ``_mps``, ``_n``, ...; no suffix means
    dimensionless) and, with a description, in each Arrow field's metadata (keys
    ``unit`` and ``description``; ``column_doc()`` yields the same text). The file is
    deterministic: the same result gives the same bytes (no timestamps, no paths; the
    writer's ``created_by`` string names the pyarrow version).

``summary.json``
    A small, sorted, rounded digest of the run (``summarize``). Everything in it is
    deterministic except the ``timing`` section (wall time, real-time factor).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from simserver.analysis.holds import holds_summary
from simserver.core import layout as L
from simserver.wire.protocol import WORLD_CAR_ID_COLUMN

if TYPE_CHECKING:  # scenario imports the compiled core; keep this module light to import
    import pyarrow as pa

    from simserver.sim.scenario import ScenarioResult

HISTORY_FILE = "history.parquet"
SUMMARY_FILE = "summary.json"
INPUT_PREFIX = "input_"
WORLD_PREFIX = "world_"
SKIPPED_STATE_PREFIXES = ("hub_u_prev_",)
"""State slots left out of the history (internal bookkeeping, see the module docstring)."""

REST_SPEED_MPS = 1e-3
"""``|u|`` below this counts as at rest in the summary (1 mm/s)."""

SUMMARY_SIGNIFICANT_DIGITS = 7
"""Floats in ``summary.json`` are rounded to this many significant digits."""

# Unit of a column from its name's suffix; longest suffixes are tried first.
_SUFFIX_UNITS = {
    "_radps2": "rad/s^2",
    "_mps2": "m/s^2",
    "_radps": "rad/s",
    "_mps": "m/s",
    "_rad": "rad",
    "_nm": "N m",
    "_n": "N",
    "_m": "m",
    "_s": "s",
}
DIMENSIONLESS = "1"

_WHEEL_LONG = {"fl": "front-left", "fr": "front-right", "rl": "rear-left", "rr": "rear-right"}

# Descriptions keyed by the column name with the wheel replaced by ``{w}``.
_DESCRIPTIONS: dict[str, str] = {
    "time_s": "simulated time at the start of the step",
    # --- states
    "x_m": "position along the road plane's first axis e1 (uphill for a positive grade)",
    "y_m": "position along the road plane's second axis e2 (left of e1)",
    "yaw_rad": "heading in the road plane, from e1 toward e2 (unwrapped)",
    "u_mps": "body longitudinal velocity u (forward +)",
    "v_mps": "body lateral velocity v (left +)",
    "yaw_rate_radps": "yaw rate r (counter-clockwise seen from above +)",
    "heave_m": "sprung-mass displacement along the road normal from static (up +)",
    "heave_rate_mps": "sprung-mass heave rate",
    "roll_rad": "sprung-mass roll angle (left side up +)",
    "roll_rate_radps": "sprung-mass roll rate",
    "pitch_rad": "sprung-mass pitch angle (nose down +)",
    "pitch_rate_radps": "sprung-mass pitch rate",
    "omega_{w}_radps": "{W} wheel spin rate Omega (rolling forward +)",
    "tan_alpha_lag_{w}": "{W} lagged slip state tan a' (SAE 950311 eq. 16; hub sliding to +y > 0)",
    "kappa_lag_{w}": "{W} lagged slip state k' (SAE 950311 eq. 26 in ISO form; driving > 0)",
    "damping_active_{w}": "{W} paper's Appendix A low-speed damping latched on (0 or 1)",
    "hub_u_prev_{w}_mps": "{W} hub longitudinal speed at the previous step (damping trigger)",
    "wheel_held_{w}": "{W} wheel held at zero spin by its brake over the step (0 or 1)",
    "fz_prev_{w}_n": "{W} normal load at the start of the previous step (-1: none yet), "
                     "from which the tire coefficients are extrapolated to mid-step",
    "ref_grade_pct": "reference plane under the car (docs/model.md section 11): rise along "
                     "world x per 100 m (the road's grade on the plane terrain)",
    "ref_cross_slope_pct": "reference plane under the car: rise along world y per 100 m",
    "ref_height_m": "reference plane under the car: its height at the world origin",
    "in_contact_{w}": "{W} wheel carried load (touched the ground) at the step start (0 or 1)",
    "steering_wheel_angle_rad": "steering-wheel angle (left +; docs/model.md section 12)",
    "steering_wheel_rate_radps": "steering-wheel rate, low-pass filtered (the column damping's)",
    "steering_wheel_torque_nm": "torque the steering system applies to the driver's hands "
                                "(toward the left +), from the forces of the row before",
    "steering_friction_nm": "column friction (Dahl), with the sign of the last motion",
    "patch_twist_{w}_rad": "{W} contact-patch torsion: the rim turned against the patch "
                           "(left +), relaxing over the lateral relaxation length as it rolls",
    "steering_primed": "1 once a step has set the steering-wheel angle (0: a fresh state)",
    "engine_speed_radps": "engine speed (automatic powertrain, docs/model.md section 13; 0 "
                          "on the simple one)",
    "gear_engaged": "gear engaged: 1 .. n forward, -1 reverse, 0 none (P, N)",
    "lockup_engaged": "torque converter's lock-up clutch closed (0 or 1)",
    "idle_control_nm": "engine idle speed controller's integral term",
    "shift_timer_s": "time since the last gear change",
    "hill_hold_pedal": "brake pedal the hill-start assist keeps (0: not armed)",
    "hill_hold_active": "hill-start assist holds the brakes beyond the driver's pedal (0 or 1)",
    "hill_hold_time_s": "time since the pedal was released under the hill-start hold",
    # --- outputs
    "ax_mps2": "CG acceleration along body x",
    "ay_mps2": "CG acceleration along body y",
    "yaw_acc_radps2": "yaw acceleration",
    "gravity_x_mps2": "gravity resolved along body x",
    "gravity_y_mps2": "gravity resolved along body y",
    "fx_{w}_n": "{W} tire longitudinal force Fx, wheel frame, incl. auxiliary damping",
    "fy_{w}_n": "{W} tire lateral force Fy, wheel frame, incl. auxiliary damping",
    "fz_{w}_n": "{W} tire normal load Fz",
    "mz_{w}_nm": "{W} tire aligning moment Mz",
    "hub_u_{w}_mps": "{W} hub longitudinal velocity, wheel frame",
    "hub_v_{w}_mps": "{W} hub lateral velocity, wheel frame",
    "steer_{w}_rad": "{W} road-wheel steer angle (left +)",
    "drive_torque_{w}_nm": "{W} drive torque at the wheel",
    "brake_torque_{w}_nm": "{W} brake + rolling-resistance torque applied (signed)",
    "friction_use_{w}": "{W} shear force over available friction |F| / (mu Fz)",
    "damping_fx_{w}_n": "{W} auxiliary low-speed damping share of Fx",
    "damping_fy_{w}_n": "{W} auxiliary low-speed damping share of Fy",
    "kappa_{w}": "{W} longitudinal slip fed to the tire model (k', or the kinematic slip)",
    "tan_alpha_{w}": "{W} tan of the slip angle fed to the tire model (tan a', or kinematic)",
    "fx_body_sum_n": "sum of the tire forces along body x",
    "fy_body_sum_n": "sum of the tire forces along body y",
    "camber_{w}_rad": "{W} inclination angle fed to the tire model, ISO 8855 (top toward "
                      "-y +): static camber and the suspension's roll and heave gains",
    # --- inputs
    "input_steer": "driver steering-wheel position, normalised [-1, 1] (full left +1)",
    "input_throttle": "driver throttle pedal [0, 1]",
    "input_brake": "driver brake pedal [0, 1]",
    "input_parking_brake": "parking brake (0 or 1)",
    "input_gear": "gear code: 0 P, 1 R, 2 N, 3 D",
    # --- world pose
    "world_x_m": "CG position along world x (z up; a terrain's own axes)",
    "world_y_m": "CG position along world y",
    "world_z_m": "CG height along world z (up)",
    "world_yaw_rad": "heading from world x toward world y, continuous (not wrapped)",
    "world_pitch_rad": "body pitch in world axes, nose down + (R = Rz(yaw) Ry(pitch) "
                       "Rx(roll))",
    "world_roll_rad": "body roll in world axes, left side up +",
}


def _state_columns() -> tuple[tuple[str, int], ...]:
    return tuple(
        (name, idx)
        for idx, name in enumerate(L.STATE_NAMES)
        if name != "time_s" and not name.startswith(SKIPPED_STATE_PREFIXES)
    )


STATE_COLUMNS = _state_columns()
"""(column name, state index) of the states written to the history."""

POSE_COLUMNS: tuple[tuple[str, int], ...] = tuple(sorted(
    ((WORLD_PREFIX + key.removeprefix("POSE_").lower(), slot)
     for key, slot in vars(L).items() if key.startswith("POSE_")), key=lambda c: c[1]))
"""(column name, ``core.layout`` pose slot) of the world pose's columns, in slot order."""

HISTORY_COLUMNS: tuple[str, ...] = (
    ("time_s",)
    + tuple(name for name, _ in STATE_COLUMNS)
    + L.OUTPUT_NAMES
    + tuple(INPUT_PREFIX + name for name in L.INPUT_NAMES)
    + tuple(name for name, _ in POSE_COLUMNS)
)
"""Every column of ``history.parquet``, in file order."""


def column_unit(name: str) -> str:
    """Unit of a history column, read from its name's suffix (``"1"`` if dimensionless).

    Parameters
    ----------
    name : str
        A column name such as ``"fx_fl_n"``.

    Returns
    -------
    str
        ``"N"``, ``"m/s"``, ... or ``"1"``.
    """
    for suffix in sorted(_SUFFIX_UNITS, key=len, reverse=True):
        if name.endswith(suffix):
            return _SUFFIX_UNITS[suffix]
    return DIMENSIONLESS


def column_description(name: str) -> str:
    """One-line description of a history column.

    Parameters
    ----------
    name : str
        A column name; per-wheel names are matched by their ``{w}`` template.

    Returns
    -------
    str
        The description, or ``"(undocumented)"`` for a name this module does not know
        (a test keeps that from happening for the layout's names).
    """
    if name in _DESCRIPTIONS:
        return _DESCRIPTIONS[name]
    for wheel, long_name in _WHEEL_LONG.items():
        template = name.replace(f"_{wheel}", "_{w}", 1)
        if template != name and template in _DESCRIPTIONS:
            return _DESCRIPTIONS[template].replace("{W}", long_name)
    return "(undocumented)"


def column_doc(columns: tuple[str, ...] = HISTORY_COLUMNS) -> Iterator[tuple[str, str, str]]:
    """Yield ``(name, unit, description)`` for every history column, in file order.

    The README's column table and the Arrow field metadata are both generated from this.

    Parameters
    ----------
    columns : tuple of str, optional
        Column names; defaults to ``HISTORY_COLUMNS``.

    Yields
    ------
    tuple of (str, str, str)
        Column name, unit (``"1"`` = dimensionless), description.
    """
    for name in columns:
        yield name, column_unit(name), column_description(name)


def column_doc_markdown() -> str:
    """The column documentation as a Markdown table (for the README), with the
    VehicleState field that carries each column live (``protocol.STATE_FIELDS``' history
    columns; ``simserver-recorder`` writes it under the column's name)."""
    from simserver.wire.protocol import STATE_COLUMNS

    live = {c.name: f"`{c.field}`" if c.wheel is None else f"`{c.field}[{c.wheel}]`"
            for c in STATE_COLUMNS if c.history}
    lines = ["| column | unit | description | in the live state |", "|---|---|---|---|"]
    lines += [f"| `{n}` | {u} | {d} | {live.get(n, '-')} |" for n, u, d in column_doc()]
    return "\n".join(lines) + "\n"


def update_column_doc(text: str) -> str:
    """``docs/history_columns.md``'s text with its table replaced by
    :func:`column_doc_markdown` (the table runs from its header line to the first line
    that is not a table row)."""
    lines = text.splitlines(keepends=True)
    start = next(i for i, line in enumerate(lines) if line.startswith("| column | unit |"))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")),
               len(lines))
    return "".join(lines[:start]) + column_doc_markdown() + "".join(lines[end:])


def result_columns(result: ScenarioResult) -> dict[str, np.ndarray]:
    """The history columns of a result as float64 arrays (views where possible).

    Parameters
    ----------
    result : ScenarioResult
        A finished run.

    Returns
    -------
    dict of str to ndarray
        Keyed by the names of ``HISTORY_COLUMNS``, in that order.
    """
    return rows_columns(result.states, result.outputs, result.inputs, poses=result.poses)


def rows_columns(states: np.ndarray, outputs: np.ndarray, inputs: np.ndarray,
                 time_s: np.ndarray | None = None,
                 poses: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """History columns of recorded rows (the one mapping from rows to column names).

    Parameters
    ----------
    states, outputs, inputs : ndarray
        Rows ``(n, N_STATE)``, ``(n, N_OUT)``, ``(n, N_INPUT)`` as ``ScenarioResult`` holds
        them (row ``k``: the state at its time, the forces at it, the inputs of its step).
    time_s : ndarray, optional
        Each row's time; defaults to the states' ``TIME_S`` (a caller that runs in chunks,
        such as the soak, gives the absolute time of each row).
    poses : ndarray, optional
        ``(n, N_POSE)`` world poses; without them the ``world_*`` columns are left out
        (they cost 3-7 us a row to make).

    Returns
    -------
    dict of str to ndarray
        Keyed by the names of ``HISTORY_COLUMNS``, in that order (``world_*`` only with
        ``poses``).
    """
    cols: dict[str, np.ndarray] = {
        "time_s": states[:, L.TIME_S] if time_s is None else time_s}
    for name, idx in STATE_COLUMNS:
        cols[name] = states[:, idx]
    for idx, name in enumerate(L.OUTPUT_NAMES):
        cols[name] = outputs[:, idx]
    for idx, name in enumerate(L.INPUT_NAMES):
        cols[INPUT_PREFIX + name] = inputs[:, idx]
    if poses is not None:
        for name, slot in POSE_COLUMNS:
            cols[name] = poses[:, slot]
    return {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in cols.items()}


def history_schema(extra_metadata: dict[str, str] | None = None) -> pa.Schema:
    """Arrow schema of the history: float64 fields with ``unit``/``description`` metadata.

    Parameters
    ----------
    extra_metadata : dict of str to str, optional
        File-level key/value metadata (kept sorted for deterministic bytes).

    Returns
    -------
    pyarrow.Schema
    """
    import pyarrow as pa  # here, not at the top: the sweep's workers, the plots and
    # tire-curves read the column tables of this module and write no Parquet (issue 33)

    fields = [
        pa.field(name, pa.float64(), nullable=False,
                 metadata={"unit": unit, "description": desc})
        for name, unit, desc in column_doc()
    ]
    meta = dict(sorted((extra_metadata or {}).items()))
    return pa.schema(fields, metadata=meta or None)


def _file_metadata(result: ScenarioResult) -> dict[str, str]:
    sc = result.scenario
    return {
        "simserver.scenario": sc.name,
        "simserver.vehicle": sc.scene.vehicle.name,
        "simserver.dt_s": repr(float(sc.dt_s)),
        "simserver.record_every": str(int(sc.record_every)),
        "simserver.columns": "time_s, states, outputs, input_*: see simserver.adapters.history",
    }


def write_history(result: ScenarioResult, path: str | Path) -> Path:
    """Write the time history of a run as a Parquet file.

    Parameters
    ----------
    result : ScenarioResult
        A finished run.
    path : str or Path
        Target file, or a directory (then ``history.parquet`` inside it).

    Returns
    -------
    Path
        The file written.

    Notes
    -----
    Written with zstd compression over the BYTE_STREAM_SPLIT encoding (a quarter smaller
    than plain for these float columns; read by pyarrow, polars, DuckDB alike), no
    dictionary encoding, one row group per million rows. No timestamp or path goes into
    the file, so the same result gives the same bytes.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    if path.is_dir():
        path = path / HISTORY_FILE
    cols = result_columns(result)
    schema = history_schema(_file_metadata(result))
    table = pa.Table.from_arrays([pa.array(cols[f.name]) for f in schema], schema=schema)
    pq.write_table(
        table,
        path,
        compression="zstd",
        use_dictionary=False,
        column_encoding="BYTE_STREAM_SPLIT",
        write_statistics=True,
        row_group_size=1 << 20,
    )
    return path


CAR_ID_COLUMN = WORLD_CAR_ID_COLUMN  # one name for the recorder and the runner
"""The first column of a history of several cars (``write_world_history``): the car's id."""


def write_world_history(results: dict[str, ScenarioResult], path: str | Path) -> Path:
    """Write the histories of a world's cars as one Parquet file in long form: the columns
    of a single car's history (``write_history``) preceded by ``car_id``, the cars' rows
    one car after the other in the given order.

    One table with a car-id column, not a table per car: Parquet readers expect one schema
    per file (pandas, polars, DuckDB read it as one frame, and select a car with a filter,
    ``df[df.car_id == "lead"]``, or group by it); the row-group statistics of a sorted
    ``car_id`` let a reader skip the other cars; and any number of cars has the same
    columns. The same results give the same bytes (no timestamp, no path)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    if path.is_dir():
        path = path / HISTORY_FILE
    ids = list(results)
    first = results[ids[0]]
    meta = _file_metadata(first)
    meta["simserver.cars"] = json.dumps({cid: r.scenario.scene.vehicle.name
                                         for cid, r in results.items()})
    base = history_schema(meta)
    schema = base.insert(0, pa.field(CAR_ID_COLUMN, pa.string(), nullable=False,
                                     metadata={"unit": "-",
                                               "description": "the car's id (cars: id)"}))
    per_car = [result_columns(results[cid]) for cid in ids]
    car_ids = pa.array(np.repeat(np.array(ids, dtype=object),
                                 [len(c["time_s"]) for c in per_car]), type=pa.string())
    arrays = [car_ids] + [pa.array(np.concatenate([c[f.name] for c in per_car]))
                          for f in base]
    table = pa.Table.from_arrays(arrays, schema=schema)
    pq.write_table(table, path, compression="zstd", use_dictionary=[CAR_ID_COLUMN],
                   column_encoding={f.name: "BYTE_STREAM_SPLIT" for f in base},
                   write_statistics=True, row_group_size=1 << 20)
    return path


def read_history(path: str | Path) -> dict[str, np.ndarray]:
    """Read a history file back as float64 arrays.

    Parameters
    ----------
    path : str or Path
        ``history.parquet`` or the directory holding it.

    Returns
    -------
    dict of str to ndarray
        Column name to array, in file order (float64; ``car_id``, in the history of
        several cars, as str).
    """
    import pyarrow.parquet as pq

    path = Path(path)
    if path.is_dir():
        path = path / HISTORY_FILE
    table = pq.read_table(path)
    return {  # the car_id of a world's history as strings
        name: (np.asarray(table.column(name).to_pylist(), dtype=str) if name == CAR_ID_COLUMN
               else np.asarray(table.column(name).to_numpy(), dtype=np.float64))
        for name in table.column_names
    }


# ----------------------------------------------------------------------------- summary
def _round(value: float) -> float | None:
    """Round to ``SUMMARY_SIGNIFICANT_DIGITS``; non-finite values become ``None``."""
    value = float(value)
    if not math.isfinite(value):
        return None
    if value == 0.0:
        return 0.0  # also turns -0.0 into 0.0
    return float(f"{value:.{SUMMARY_SIGNIFICANT_DIGITS}g}")


def _rounded(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _rounded(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_rounded(v) for v in obj]
    if isinstance(obj, bool | str) or obj is None:
        return obj
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return _round(float(obj))
    return str(obj)


def _rest_times(time_s: np.ndarray, u: np.ndarray) -> tuple[float | None, float | None]:
    """First time ``|u|`` is below ``REST_SPEED_MPS``, and the time from which it stays so."""
    at_rest = np.abs(u) < REST_SPEED_MPS
    if not at_rest.any():
        return None, None
    first = float(time_s[int(np.argmax(at_rest))])
    if not at_rest[-1]:
        return first, None
    moving = np.flatnonzero(~at_rest)
    settled = float(time_s[0] if moving.size == 0 else time_s[moving[-1] + 1])
    return first, settled


def model_options(result: ScenarioResult) -> dict[str, Any]:
    """The model options a run used: its scene's, the defaults for the others."""
    # Imported here: the option defaults live with the config loader (which imports the
    # compiled core); the history writer alone does not need it.
    from simserver.adapters.config import MODEL_OPTION_DEFAULTS

    return {**MODEL_OPTION_DEFAULTS, **result.scenario.scene.model_options}


def summarize(result: ScenarioResult) -> dict[str, Any]:
    """Digest of a run for ``summary.json`` (plain JSON types, rounded, keys unsorted).

    Parameters
    ----------
    result : ScenarioResult
        A finished run.

    Returns
    -------
    dict
        Sections ``scenario``, ``vehicle``, ``road``, ``model_options``, ``initial``,
        ``run``, ``final``, ``extremes``, ``rest``, ``holds`` (every stop held, its creep
        and its restart: ``simserver.analysis.holds``), ``manoeuvre`` (when the scenario
        names an ``analysis``: ``simserver.analysis.manoeuvres``), ``finite`` and ``timing`` (the
        only non-deterministic one). ``final`` is the last recorded row of the history, the
        same numbers as the last row of ``history.parquet`` (forces are only known at
        recorded rows); its ``time_s`` says when that is.
    """
    sc = result.scenario
    cols = result_columns(result)
    n_rows = result.states.shape[0]
    n_steps = sc.n_steps
    options = model_options(result)
    simulated = n_steps * sc.dt_s
    wall = float(result.wall_time_s)

    summary: dict[str, Any] = {
        "format": "simserver.summary/1",
        "scenario": {"name": sc.name, "description": sc.description, "file": sc.path.name},
        "vehicle": {
            "name": sc.scene.vehicle.name,
            "tire_model_front": sc.scene.vehicle.tire_models[0],
            "tire_model_rear": sc.scene.vehicle.tire_models[1],
        },
        "road": dict(sc.scene.road),
        "model_options": options,
        "initial": dict(sc.scene.initial),
        "run": {
            "duration_s": sc.duration_s,
            "dt_s": sc.dt_s,
            "steps": n_steps,
            "record_every": sc.record_every,
            "rows": n_rows,
        },
        "timing": {
            "wall_time_s": wall,
            "real_time_factor": simulated / wall if wall > 0.0 else None,
            "us_per_step": 1e6 * wall / n_steps if n_steps else None,
        },
    }
    finite = {
        "states": bool(np.isfinite(result.states).all()),
        "outputs": bool(np.isfinite(result.outputs).all()),
        "final_state": bool(np.isfinite(result.final_state).all()),
    }
    finite["all"] = all(finite.values())
    summary["finite"] = finite
    if n_rows == 0:
        return _rounded(summary)

    last = {name: float(arr[-1]) for name, arr in cols.items()}
    wheels = L.WHEEL_NAMES
    final: dict[str, Any] = {
        "time_s": last["time_s"],
        "x_m": last["x_m"],
        "y_m": last["y_m"],
        "yaw_rad": last["yaw_rad"],
        "yaw_deg": math.degrees(last["yaw_rad"]),
        "u_mps": last["u_mps"],
        "v_mps": last["v_mps"],
        "speed_mps": math.hypot(last["u_mps"], last["v_mps"]),
        "yaw_rate_radps": last["yaw_rate_radps"],
        "gear": L.GEAR_NAMES[int(last["input_gear"])],
    }
    for quantity in ("fx", "fy", "fz"):
        per_wheel = {w: last[f"{quantity}_{w}_n"] for w in wheels}
        final[f"{quantity}_n"] = per_wheel
        final[f"{quantity}_sum_n"] = sum(per_wheel.values())
        final[f"{quantity}_front_n"] = per_wheel["fl"] + per_wheel["fr"]
        final[f"{quantity}_rear_n"] = per_wheel["rl"] + per_wheel["rr"]
    final["fx_body_sum_n"] = last["fx_body_sum_n"]
    final["fy_body_sum_n"] = last["fy_body_sum_n"]
    summary["final"] = final

    fz = np.stack([cols[f"fz_{w}_n"] for w in wheels], axis=1)
    with np.errstate(invalid="ignore"):
        k_min = int(np.nanargmin(fz)) if np.isfinite(fz).any() else 0
    row, wheel = divmod(k_min, len(wheels))
    u = cols["u_mps"]
    abs_u = np.abs(u)
    summary["extremes"] = {
        "max_abs_u_mps": float(np.nanmax(abs_u)) if np.isfinite(abs_u).any() else math.nan,
        "min_fz_n": float(fz[row, wheel]),
        "min_fz_wheel": wheels[wheel],
        "min_fz_time_s": float(cols["time_s"][row]),
    }
    first, settled = _rest_times(cols["time_s"], u)
    summary["rest"] = {
        "threshold_mps": REST_SPEED_MPS,
        "first_time_s": first,
        "settled_time_s": settled,
        "at_rest_at_end": bool(abs(last["u_mps"]) < REST_SPEED_MPS),
    }
    summary["holds"] = holds_summary(cols)
    if getattr(result, "driver_states", None) is not None:
        summary["driver"] = driver_summary(result.driver_states, cols["time_s"])
    if getattr(sc, "analysis", None):  # a standard manoeuvre (docs/manoeuvres.md)
        from simserver.analysis.manoeuvres import analyse, car_facts

        summary["manoeuvre"] = analyse(sc.analysis, cols, car_facts(sc.scene.vehicle.vp))
    return _rounded(summary)


def driver_summary(driver_states: np.ndarray, time_s: np.ndarray) -> dict[str, Any]:
    """What the built-in driver saw over a run (``core.driver.DS_*`` per recorded row):
    its lateral offset from the path (RMS, largest), the gap to the car ahead (smallest,
    last; None when there was none), the time held, and its mode at the end."""
    from simserver.core import driver as D

    lat = driver_states[:, D.DS_LATERAL_M]
    gap = driver_states[:, D.DS_GAP_M]
    mode = driver_states[:, D.DS_MODE]
    seen = np.isfinite(gap)
    dt = float(np.median(np.diff(time_s))) if len(time_s) > 1 else 0.0
    return {
        "lateral_rms_m": float(np.sqrt(np.mean(lat ** 2))),
        "lateral_max_m": float(np.max(np.abs(lat))),
        "gap_min_m": float(gap[seen].min()) if seen.any() else None,
        "gap_final_m": float(gap[-1]) if seen[-1] else None,
        "held_s": float(np.count_nonzero(mode == D.MODE_HOLD) * dt),
        "mode_final": D.MODE_NAMES[int(mode[-1])],
        "station_final_m": float(driver_states[-1, D.DS_STATION_M]),
    }


def summary_json(summary: dict[str, Any]) -> str:
    """Serialise a summary deterministically (sorted keys, two-space indent, final newline)."""
    return json.dumps(summary, sort_keys=True, indent=2, allow_nan=False) + "\n"


def write_summary(summary: dict[str, Any], path: str | Path) -> Path:
    """Write a run's summary (:func:`summarize`) as ``summary.json`` (:func:`summary_json`).

    Parameters
    ----------
    summary : dict
        ``summarize(result)`` of a finished run.
    path : str or Path
        Target file, or a directory (then ``summary.json`` inside it).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    if path.is_dir():
        path = path / SUMMARY_FILE
    path.write_text(summary_json(summary), encoding="utf-8")
    return path


if __name__ == "__main__":  # python -m simserver.adapters.history docs/history_columns.md
    import sys

    doc = Path(sys.argv[1])
    doc.write_text(update_column_doc(doc.read_text(encoding="utf-8")), encoding="utf-8")
