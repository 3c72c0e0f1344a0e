"""The ``simserver`` command line.

Subcommands are registered in ``SUBCOMMANDS`` (name -> ``Subcommand``: help text, an
argument-adding function and a run function returning the exit code); add new ones there.

Exit codes: 0 success; 1 the run finished but went non-finite, or an output file could
not be written; 2 a bad command line or configuration (``error: <message>`` on stderr,
naming the file and the key, without a traceback); 130 interrupted.

Heavy modules (numba-compiled core, matplotlib, pyarrow) are imported inside the run
functions, so ``simserver --help`` answers at once.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from simserver.analysis import cli as compare_cli
from simserver.errors import CliError
from simserver.ros2 import cli as ros2_cli
from simserver.sweep import cli as sweep_cli

if TYPE_CHECKING:
    from simserver.sim.scenario import Scenario
    from simserver.sim.scene import Scene

DT_RANGE_S = (1e-5, 0.01)
"""Accepted ``--dt`` values (the same range as a scenario's ``dt_s``)."""

DEFAULT_LOAD_FACTORS = (0.5, 1.0, 1.5, 2.0)
"""``tire-curves`` loads, as multiples of the tire's nominal load."""

COMBINED_SLIP_ANGLES_DEG = (0.0, 2.0, 5.0, 10.0)
"""Fixed slip angles of the ``tire-curves`` combined-slip panel."""


@dataclass(frozen=True)
class Subcommand:
    """One ``simserver`` subcommand.

    Attributes
    ----------
    help : str
        One line for ``simserver --help``.
    add_arguments : callable
        Adds the subcommand's arguments to its ``argparse`` parser.
    run : callable
        Runs it with the parsed arguments; returns the process exit code.
    description : str
        Longer text for ``simserver SUBCOMMAND --help``.
    """

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    description: str = ""


# ------------------------------------------------------------------------ run-scenario
def _add_run_scenario_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", type=Path, help="scenario YAML file")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output directory (created if missing)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--dt", type=float, default=None, metavar="S",
                        help="override the scenario's step dt_s (s)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="an OpenSCENARIO file: end here if its stop trigger has not "
                             "fired (default 60 s)")
    # --- rerun scene (issue 5) ---
    parser.add_argument("--rrd", type=Path, default=None, metavar="FILE",
                        help="also write the Rerun scene to FILE.rrd (open with `rerun FILE`)")
    # --- end rerun scene ---


def _with_dt(scenario: Scenario, dt_s: float | None) -> Scenario:
    """The scenario with its step replaced by ``--dt`` (validated like ``dt_s``)."""
    from simserver.adapters.config import ConfigError

    if dt_s is not None:
        lo, hi = DT_RANGE_S
        if not (math.isfinite(dt_s) and lo <= dt_s <= hi):
            raise ConfigError(f"--dt: {dt_s:g} is outside [{lo:g}, {hi:g}] s")
        scenario = dataclasses.replace(scenario, dt_s=float(dt_s))
        from simserver.sim.scenario import check_run_size

        check_run_size(f"{scenario.path} with --dt {dt_s:g}", scenario.duration_s,
                       scenario.dt_s, scenario.record_every)
    if scenario.n_steps < 1:
        raise ConfigError(f"{scenario.path}: key 'duration_s': {scenario.duration_s:g} s is "
                          f"shorter than one step of {scenario.dt_s:g} s")
    return scenario


@contextlib.contextmanager
def _progress_bar(show: bool, **bar_options: Any) -> Iterator[Callable[[Any, Any], None] | None]:
    """A ``progress(done, total)`` callback that draws a tqdm bar on stderr when ``show``
    (a terminal, no ``--quiet``), else None; tqdm is imported only for a bar someone sees
    (issue 33 item 2: a scripted run pays for no bar)."""
    if not show:
        yield None
        return
    from tqdm import tqdm

    with tqdm(file=sys.stderr, leave=False, **bar_options) as bar:
        yield lambda done, total: bar.update(done - bar.n)


def run_scenario_command(args: argparse.Namespace) -> int:
    """``simserver run-scenario``: run headless, write history, summary and plots.

    Parameters
    ----------
    args : argparse.Namespace
        ``scenario``, ``out``, ``no_plots``, ``dt``, ``quiet``, ``rrd``.

    Returns
    -------
    int
        0, or 1 if the run went non-finite (the files are still written).
    """
    from simserver.adapters.config import read_yaml
    from simserver.adapters.history import (
        HISTORY_FILE,
        SUMMARY_FILE,
        summarize,
        write_history,
        write_summary,
    )
    from simserver.sim.scenario import is_world_scenario, load_scenario, run_scenario

    out: Path = args.out
    if args.scenario.suffix.lower() == ".xosc":
        return _run_xosc_command(args, out)
    data = read_yaml(args.scenario)
    if is_world_scenario(data):
        return _run_world_scenario_command(args, data, out)
    scenario = _with_dt(load_scenario(args.scenario, data), args.dt)
    _make_out_dir(out)

    # Warm-up: load the compiled kernels from numba's cache (or compile them) before the
    # clock starts, so that the reported real-time factor is the simulation's own.
    run_scenario(dataclasses.replace(scenario, duration_s=scenario.dt_s, record_every=1))

    with _progress_bar(not args.quiet and sys.stderr.isatty(), total=scenario.n_steps,
                       desc=scenario.name, unit="step", unit_scale=True) as progress:
        result = run_scenario(scenario, progress=progress)

    summary = summarize(result)
    try:
        write_history(result, out / HISTORY_FILE)
        write_summary(summary, out / SUMMARY_FILE)
        written = [HISTORY_FILE, SUMMARY_FILE]
        if "manoeuvre" in summary:  # a standard manoeuvre's report (docs/manoeuvres.md)
            from simserver.adapters.history import result_columns
            from simserver.adapters.manoeuvre_report import write_manoeuvre_outputs

            written += write_manoeuvre_outputs(
                out, scenario.name, {scenario.name: summary["manoeuvre"]},
                {scenario.name: result_columns(result)}, plots=not args.no_plots)
        if not args.no_plots:
            from simserver.adapters.plots import plot_result

            written += [p.name for p in plot_result(result, out)]
    except OSError as exc:
        raise CliError(f"{out}: cannot write the results: {exc.strerror or exc}") from exc

    # --- rerun scene (issue 5): the same scene the live viewer shows, to a file ---
    if args.rrd is not None:
        from simserver.adapters.rerun_scene import log_result
        from simserver.adapters.rerun_sink import RerunSinkError, open_recording

        try:
            rec = open_recording("save", args.rrd, announce=None)
        except RerunSinkError as exc:
            raise CliError(str(exc)) from exc
        assert rec is not None
        log_result(rec, result)
        rec.disconnect()  # flushes and closes the file
        written.append(str(args.rrd))
    # --- end rerun scene ---

    rtf = summary["timing"]["real_time_factor"]
    rtf_text = f"{rtf:,.0f}x real time" if rtf is not None else "real time factor n/a"
    print(f"{scenario.name}: {scenario.n_steps} steps of {scenario.dt_s * 1e3:g} ms "
          f"({scenario.n_steps * scenario.dt_s:g} s simulated) in "
          f"{result.wall_time_s:.3g} s, {rtf_text}; wrote {out}/ "
          f"({', '.join(written)})")
    if not summary["finite"]["all"]:
        print(f"error: {scenario.path}: the run went non-finite (NaN or inf); "
              f"see {out / HISTORY_FILE}", file=sys.stderr)
        return 1
    return 0


def _make_out_dir(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{out}: cannot create the output directory: {exc.strerror}") from exc


XOSC_TRACE_FILE = "storyboard_trace.jsonl"
"""The storyboard trace of an OpenSCENARIO run, beside the summary: one JSON object a line
(time, element kind and name, from and to state, the condition values that fired it)."""


def _run_xosc_command(args: argparse.Namespace, out: Path) -> int:
    """``run-scenario FILE.xosc``: play it with physical cars (``simserver.sim.xosc_run``),
    write the history (``car_id`` column), the summary, the plots and the storyboard
    trace (:data:`XOSC_TRACE_FILE`)."""
    import json

    from simserver.adapters.history import (
        HISTORY_FILE,
        SUMMARY_FILE,
        summarize,
        write_summary,
        write_world_history,
    )
    from simserver.sim.xosc_run import DEFAULT_DURATION_S, play

    duration = DEFAULT_DURATION_S if args.duration is None else args.duration
    if not (math.isfinite(duration) and 0.0 < duration <= 3600.0):
        raise CliError(f"--duration: {duration:g} is outside (0, 3600] s")
    run = play(args.scenario, duration_s=duration, dt_s=args.dt or 0.001)
    for line in run.scenario.ignored:
        print(f"warning: {line}", file=sys.stderr)
    _make_out_dir(out)
    result = run.result
    summary = {"scenario": args.scenario.stem, "end_time_s": run.end_time_s,
               "ended_by": run.ended_by,
               "cars": {cid: summarize(r) for cid, r in result.cars.items()}}
    try:
        write_world_history(result.cars, out / HISTORY_FILE)
        write_summary(summary, out / SUMMARY_FILE)
        with open(out / XOSC_TRACE_FILE, "w") as f:
            for entry in run.trace:
                f.write(json.dumps(entry, default=float) + "\n")
        written = [HISTORY_FILE, SUMMARY_FILE, XOSC_TRACE_FILE]
        if not args.no_plots:
            from simserver.adapters.plots import plot_comparison

            written.append(plot_comparison(result.cars, out / "cars.png",
                                           signals=("u_mps", "x_m", "y_m"),
                                           title=f"{args.scenario.stem}: every car").name)
    except OSError as exc:
        raise CliError(f"{out}: cannot write the results: {exc.strerror or exc}") from exc
    print(f"{args.scenario.name}: {len(result.cars)} cars, {run.end_time_s:.2f} s simulated "
          f"({run.ended_by}) in {run.wall_time_s:.3g} s; wrote {out}/ ({', '.join(written)})")
    bad = [cid for cid, s in summary["cars"].items() if not s["finite"]["all"]]
    if bad:
        print(f"error: {args.scenario}: car(s) {bad} went non-finite (NaN or inf)",
              file=sys.stderr)
        return 1
    return 0


def _run_world_scenario_command(args: argparse.Namespace, data: dict, out: Path) -> int:
    """``run-scenario`` of a scenario with ``cars:``: one history with a ``car_id`` column
    (``history.write_world_history``), a summary per car and of the cars' contacts
    (``contacts``: ``WorldResult.contact_summary``), plots of every car (``cars.png``:
    every car's speed and position overlaid; each car's own plots in ``<out>/<id>/``)."""
    from simserver.adapters.history import (
        HISTORY_FILE,
        SUMMARY_FILE,
        summarize,
        write_summary,
        write_world_history,
    )
    from simserver.sim.scenario import load_world_scenario, run_world_scenario

    world = load_world_scenario(args.scenario, data)
    world.cars = {cid: _with_dt(sc, args.dt) for cid, sc in world.cars.items()}
    _make_out_dir(out)
    result = run_world_scenario(world)
    summary = {"scenario": world.name, "cars": {cid: summarize(r)
                                                for cid, r in result.cars.items()},
               "contacts": result.contact_summary()}
    sections = {cid: s["manoeuvre"] for cid, s in summary["cars"].items()
                if "manoeuvre" in s}
    if sections:  # a series' own figure (the double lane change's highest clean speed)
        from simserver.analysis.manoeuvres import dlc_series

        series = dlc_series(sections)
        if series is not None:
            summary["manoeuvre_series"] = series
    try:
        write_world_history(result.cars, out / HISTORY_FILE)
        write_summary(summary, out / SUMMARY_FILE)
        written = [HISTORY_FILE, SUMMARY_FILE]
        if sections:  # a standard manoeuvre's report, every car's (docs/manoeuvres.md)
            from simserver.adapters.history import result_columns
            from simserver.adapters.manoeuvre_report import write_manoeuvre_outputs

            written += write_manoeuvre_outputs(
                out, world.name, sections,
                {cid: result_columns(result.cars[cid]) for cid in sections},
                plots=not args.no_plots)
        if not args.no_plots:
            from simserver.adapters.plots import plot_comparison, plot_result

            written.append(plot_comparison(result.cars, out / "cars.png",
                                           signals=("u_mps", "x_m", "y_m"),
                                           title=f"{world.name}: every car").name)
            for cid, r in result.cars.items():
                (out / cid).mkdir(exist_ok=True)
                written += [f"{cid}/{p.name}" for p in plot_result(r, out / cid)]
    except OSError as exc:
        raise CliError(f"{out}: cannot write the results: {exc.strerror or exc}") from exc
    print(f"{world.name}: {len(result.cars)} cars, {world.n_steps} steps in "
          f"{result.wall_time_s:.3g} s; wrote {out}/ ({', '.join(written)})")
    bad = [cid for cid, s in summary["cars"].items() if not s["finite"]["all"]]
    if bad:
        print(f"error: {world.path}: car(s) {bad} went non-finite (NaN or inf); "
              f"see {out / HISTORY_FILE}", file=sys.stderr)
        return 1
    return 0


# ------------------------------------------------------------------------- tire-curves
def nominal_load_n(tp: np.ndarray) -> float:
    """Nominal load of a packed tire vector, from its model's registry entry
    (``simserver.tires.registry``): ``FNOMIN`` (mf61), ``nominal_load_n`` (simple).

    Parameters
    ----------
    tp : ndarray
        ``float64[N_TIRE_PARAM]`` from ``adapters.config.load_tire``.

    Returns
    -------
    float
        Nominal wheel load (N).
    """
    from simserver.tires.registry import nominal_load_n as registered_nominal_load_n

    return registered_nominal_load_n(tp)


def tire_curve_data(
    tp: np.ndarray,
    loads_n: Sequence[float],
    mu_scale: float = 1.0,
    alpha_max_deg: float = 20.0,
    kappa_max: float = 1.0,
    n_points: int = 241,
    combined_alpha_deg: Sequence[float] = COMBINED_SLIP_ANGLES_DEG,
    combined_load_n: float | None = None,
    vx_mps: float = 10.0,
    gamma_rad: float = 0.0,
) -> dict[str, np.ndarray]:
    """Evaluate a tire's steady-state curves with the compiled ``core.tire.tire_forces``.

    Parameters
    ----------
    tp : ndarray
        Packed tire vector (``adapters.config.load_tire``).
    loads_n : sequence of float
        Normal loads of the pure-slip curves (N).
    mu_scale : float, optional
        Road friction scale (1 = the surface the tire was measured on).
    alpha_max_deg, kappa_max : float, optional
        The slip angle runs over ``±alpha_max_deg``, kappa over ``±kappa_max``.
    n_points : int, optional
        Points per curve.
    combined_alpha_deg : sequence of float, optional
        Fixed slip angles of the combined-slip curves.
    combined_load_n : float, optional
        Load of the combined-slip curves; default the nominal load.
    vx_mps : float, optional
        Hub speed passed to the model (rolling resistance; MF 6.1's shifts fade out below
        its VXLOW, so keep it above that).
    gamma_rad : float, optional
        Inclination (camber) angle of every curve, ISO 8855 (models without camber
        terms ignore it).

    Returns
    -------
    dict of str to ndarray
        The arrays ``adapters.plots.plot_tire_curves`` draws; forces in N, Mz in N m,
        ISO 8855 signs (``Fy < 0`` for a positive slip angle).
    """
    from simserver.core.tire import tire_forces
    from simserver.core.tire_layout import N_TIRE_OUT, OUT_FX, OUT_FY, OUT_MZ
    from simserver.tires.registry import check_tire_vectors, tire_kernels

    loads = np.asarray(loads_n, dtype=np.float64)
    alpha_deg = np.linspace(-alpha_max_deg, alpha_max_deg, n_points)
    tan_alpha = np.tan(np.radians(alpha_deg))
    kappa = np.linspace(-kappa_max, kappa_max, n_points)
    comb_alpha = np.asarray(combined_alpha_deg, dtype=np.float64)
    comb_load = nominal_load_n(tp) if combined_load_n is None else float(combined_load_n)
    out = np.zeros(N_TIRE_OUT)
    check_tire_vectors(tp)
    kernels = tire_kernels()
    tp = np.ascontiguousarray(tp, dtype=np.float64)

    def forces(k: float, ta: float, fz: float) -> tuple[float, float, float]:
        tire_forces(kernels, tp, k, ta, gamma_rad, fz, mu_scale, vx_mps, out)
        return out[OUT_FX], out[OUT_FY], out[OUT_MZ]

    fy_alpha = np.zeros((loads.size, n_points))
    mz_alpha = np.zeros((loads.size, n_points))
    fx_kappa = np.zeros((loads.size, n_points))
    for i, fz in enumerate(loads):
        for j in range(n_points):
            _, fy_alpha[i, j], mz_alpha[i, j] = forces(0.0, tan_alpha[j], fz)
            fx_kappa[i, j], _, _ = forces(kappa[j], 0.0, fz)
    fx_comb = np.zeros((comb_alpha.size, n_points))
    fy_comb = np.zeros((comb_alpha.size, n_points))
    for i, alpha in enumerate(comb_alpha):
        ta = math.tan(math.radians(alpha))
        for j in range(n_points):
            fx_comb[i, j], fy_comb[i, j], _ = forces(kappa[j], ta, comb_load)
    return {
        "alpha_deg": alpha_deg, "kappa": kappa, "loads_n": loads,
        "fy_alpha": fy_alpha, "mz_alpha": mz_alpha, "fx_kappa": fx_kappa,
        "combined_alpha_deg": comb_alpha, "combined_load_n": np.asarray(comb_load),
        "fx_combined": fx_comb, "fy_combined": fy_comb,
    }


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def _camber_deg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and -15.0 <= value <= 15.0):
        raise argparse.ArgumentTypeError(f"expected -15 .. 15 degrees, got {text!r}")
    return value


def _load_list(text: str) -> list[float]:
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if not parts:
        raise argparse.ArgumentTypeError("expected loads in N, e.g. 2000,4000,6000")
    return [_positive_float(p) for p in parts]


def _add_tire_curves_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("tire", type=Path,
                        help="tire YAML file (model: simple or mf61) or an MF-Tyre .tir file")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.png",
                        help="PNG file to write")
    parser.add_argument("--loads", type=_load_list, default=None, metavar="N1,N2,...",
                        help="normal loads in N (default 0.5, 1, 1.5, 2 x nominal)")
    parser.add_argument("--mu", type=_positive_float, default=1.0,
                        help="road friction scale (default 1.0)")
    parser.add_argument("--alpha-max-deg", type=_positive_float, default=20.0, metavar="DEG",
                        help="slip-angle range ±deg (default 20)")
    parser.add_argument("--kappa-max", type=_positive_float, default=1.0, metavar="K",
                        help="longitudinal slip range ± (default 1.0)")
    parser.add_argument("--camber-deg", type=_camber_deg, default=0.0, metavar="DEG",
                        help="inclination angle of every curve, ISO 8855, -15 .. 15 "
                             "(default 0; the brush model has no camber terms)")


def tire_curves_command(args: argparse.Namespace) -> int:
    """``simserver tire-curves``: plot a tire's curves to a PNG.

    Parameters
    ----------
    args : argparse.Namespace
        ``tire``, ``out``, ``loads``, ``mu``, ``alpha_max_deg``, ``kappa_max``,
        ``camber_deg``.

    Returns
    -------
    int
        0.
    """
    from simserver.adapters.config import load_tire
    from simserver.adapters.plots import plot_tire_curves

    tp, model = load_tire(args.tire)
    nominal = nominal_load_n(tp)
    loads = args.loads or [f * nominal for f in DEFAULT_LOAD_FACTORS]
    curves = tire_curve_data(tp, loads, mu_scale=args.mu, alpha_max_deg=args.alpha_max_deg,
                             kappa_max=args.kappa_max, gamma_rad=math.radians(args.camber_deg))
    out: Path = args.out
    title = f"{args.tire.name} ({model}, nominal load {nominal:,.0f} N, friction x{args.mu:g}"
    title += f", camber {args.camber_deg:g} deg)" if args.camber_deg else ")"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        plot_tire_curves(curves, out, title)
    except OSError as exc:
        raise CliError(f"{out}: cannot write: {exc.strerror or exc}") from exc
    print(f"{args.tire}: {model} tire, loads {', '.join(f'{x:,.0f}' for x in loads)} N; "
          f"wrote {out}")
    return 0


# -------------------------------------------------------------------------- registry
# ------------------------------------------------------------------------ serve
def _add_serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="server YAML (default configs/server/default.yaml)")
    parser.add_argument("--scene", type=Path, default=None, metavar="FILE",
                        help="scene YAML (vehicle, road, initial pose), overrides the config "
                             "(an OpenSCENARIO .xosc: its ego's start)")
    parser.add_argument("--scenario", type=Path, default=None, metavar="FILE.xosc",
                        help="serve an OpenSCENARIO 1.x scenario live: every entity a car of "
                             "the world under its storyboard (docs/openscenario.md)")
    parser.add_argument("--ego-from", default="driver", choices=("driver", "zenoh"),
                        help="with --scenario: who drives the ego (the entity named Ego, "
                             "else the first): the built-in driver (default) or a client "
                             "over zenoh (a person with the keyboard client)")
    parser.add_argument("--vehicle-id", default=None, help="vehicle id in the key expressions")
    parser.add_argument("--prefix", default=None, help="key-expression prefix")
    parser.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                        help="zenoh endpoint to listen on (repeatable), e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="zenoh endpoint to connect to (a router), repeatable")
    parser.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                        help="a standard zenoh JSON5 config (TLS, access control, routers)")
    parser.add_argument("--command-log", type=Path, default=None, metavar="FILE",
                        help="write every applied input to FILE for 'simserver replay'")
    parser.add_argument("--viewer", default=None, metavar="MODE[:TARGET]",
                        help="live Rerun view in its own process: serve[:PORT] (loopback "
                             "gRPC + web viewer), save:FILE.rrd, connect:URL, spawn, off "
                             "(default: the config's 'viewer')")
    parser.add_argument("--stats-json", action="store_true",
                        help="on the stop, also print the statistics as one JSON line "
                             "('simserver: stopped {...}', for scripts) after the table")
    parser.add_argument("--viewer-fps", type=float, default=None, metavar="HZ",
                        help="frames the live view draws (and a save: recording keeps) per "
                             "simulated second (default: the config's 'viewer_fps', 50)")
    parser.add_argument("--realtime", default=None, choices=("auto", "off"),
                        help="auto (default): SCHED_FIFO for the tick thread and zenoh's "
                             "threads where the OS allows it (root, CAP_SYS_NICE or an "
                             "rtprio limit), else a warning and a nice-level fallback; "
                             "off: leave the scheduling alone")
    parser.add_argument("--rt-priority", type=int, default=None, metavar="N",
                        help="SCHED_FIFO priority of the tick thread, 2-99 (default 50; "
                             "zenoh's threads get N-1)")
    parser.add_argument("--rt-cpus", default=None, metavar="LIST",
                        help="pin the server to these CPUs (e.g. 1 or 2-3; default: any)")
    parser.add_argument("--rt-lock-memory", action="store_true", default=None,
                        help="mlockall: no page faults in the tick (needs CAP_IPC_LOCK)")
    parser.add_argument("--ros2", action=argparse.BooleanOptionalAction, default=None,
                        help="the car on ROS 2 topics: start 'simserver ros2' in its own "
                             "process, with the config's 'ros2' settings if it has any "
                             "(default: the config's 'ros2'; see docs/ros2.md)")
    parser.add_argument("--tls-front", default=None, choices=("auto", "off"),
                        help="auto: an accept-filtering front before every tls/ listen "
                             "endpoint, zenoh on loopback behind it (docs/security.md 5); "
                             "default: the config's tls_front (auto)")
    parser.add_argument("--log-level", default="INFO", help="logging level (default INFO)")


def serve_command(args: argparse.Namespace) -> int:
    """``simserver serve``: the real-time server, until SIGINT/SIGTERM."""
    from simserver.server.logfile import configure_logging

    process_log = configure_logging(args.log_level)  # no log call waits on the output
    try:
        return _serve(args)
    finally:
        process_log.close()


def _serve(args: argparse.Namespace) -> int:
    from simserver.server.app import SimServer
    from simserver.server.config import DEFAULT_SERVER_CONFIG, load_server_config

    scenario = None
    if args.scenario is not None:
        if args.scene is not None:
            raise CliError("--scenario and --scene: give one (a scenario's road is its "
                           "scene)", exit_code=2)
        from simserver.server.scenario_live import ScenarioLive

        scenario = ScenarioLive(args.scenario, args.ego_from)  # XoscError: file:line
        args.scene = args.scenario
        args.vehicle_id = args.vehicle_id or scenario.ego  # the viewer follows the ego
    cfg = load_server_config(
        args.config or DEFAULT_SERVER_CONFIG, scene=args.scene, vehicle_id=args.vehicle_id,
        prefix=args.prefix, listen=args.listen, connect=args.connect,
        zenoh_config=args.zenoh_config, command_log=args.command_log, viewer=args.viewer,
        viewer_fps=args.viewer_fps,
        realtime=args.realtime, rt_priority=args.rt_priority, rt_cpus=args.rt_cpus,
        rt_lock_memory=args.rt_lock_memory,
        ros2=args.ros2, tls_front=args.tls_front)
    from simserver.adapters.tls_front import FrontError
    from simserver.adapters.zenoh_io import ZenohConfigError, ZenohOpenError
    from simserver.server.app import DuplicateVehicleError

    try:
        SimServer(cfg, scenario).run(stats_json=args.stats_json)
    except (ZenohConfigError, ZenohOpenError, DuplicateVehicleError, FrontError) as exc:
        raise CliError(str(exc), exit_code=2) from exc
    return 0


# ------------------------------------------------------------------------ replay
def _add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, nargs="+",
                        help="command log written by 'simserver serve'; several: the logs "
                             "of every car of a multi-car server (run.<id>.jsonl), "
                             "replayed together in one world")
    parser.add_argument("--out", type=Path, default=None, metavar="FILE",
                        help="write the replayed states to FILE (.npz: states, outputs; "
                             "several logs: states_<id> for each car)")


def replay_command(args: argparse.Namespace) -> int:
    """``simserver replay``: re-run a command log headless and check the final state."""
    import numpy as np

    from simserver.server.command_log import replay_command_log

    if len(args.log) > 1:
        return _replay_world(args)
    rep = replay_command_log(args.log[0])
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.out, states=rep.states, outputs=rep.outputs)
    if rep.cut is not None:
        print(f"replayed {rep.steps} steps (the log was cut there: {rep.cut}; it holds no "
              "final state to compare)")
        return 0
    if rep.logged_final_state is None:
        print(f"replayed {rep.steps} steps (the log has no end line: the server did not "
              "stop cleanly, nothing to compare)")
        return 0
    same = rep.final_state_matches
    print(f"replayed {rep.steps} steps: final state "
          f"{'identical to' if same else 'DIFFERS from'} the live run's, bit for bit")
    return 0 if same else 1


def _replay_world(args: argparse.Namespace) -> int:
    """``simserver replay A.jsonl B.jsonl ...``: every car of a multi-car session in one
    world (``simserver.server.world_replay``); one line a car, exit 1 if one differs."""
    import numpy as np

    from simserver.server.world_replay import replay_world

    rep = replay_world(args.log, record=args.out is not None)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.out, **{f"states_{cid}": np.array(car.states)
                                         for cid, car in rep.cars.items()})
    print(f"replayed {rep.steps} world steps of {len(rep.cars)} cars in one world "
          f"({rep.contact_events} contact events)")
    for cid, car in rep.cars.items():
        where = f"joined at world step {car.joined_at}" + (
            f", left at {car.left_at}" if car.left_at is not None else "")
        if car.cut is not None or car.logged_final_state is None:
            why = f"its log was cut: {car.cut}" if car.cut else "its log has no end line"
            print(f"  {cid}: {car.steps} steps ({where}; {why}, nothing to compare)")
        else:
            same = car.final_state_matches
            print(f"  {cid}: {car.steps} steps ({where}): final state "
                  f"{'identical to' if same else 'DIFFERS from'} the live run's, bit for bit")
    return 0 if all(c.final_state_matches is not False for c in rep.cars.values()) else 1


# ------------------------------------------------------------------------ soak
def _add_soak_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=None, metavar="FILE",
                        help="scene YAML (default configs/scenes/flat_paper_sedan.yaml)")
    parser.add_argument("--duration", type=float, default=3600.0, metavar="S",
                        help="simulated seconds (default 3600)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the drive")
    parser.add_argument("--out", type=Path, default=None, metavar="FILE",
                        help="write the summary as JSON to FILE")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--cars", type=int, default=1, metavar="N",
                        help="1 (default): the single-car soak; 4 or more: the multi-car "
                             "soak (a contact pair, traffic on the built-in driver, random "
                             "drives; simserver.sim.multisoak)")


def _write_soak_summary(out: Path | None, summary: dict) -> str:
    """A soak's summary as indented JSON, written to ``--out`` when given; the text."""
    import json

    text = json.dumps(summary, indent=2, sort_keys=True)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n", encoding="utf-8")
    return text


def _multi_soak(args: argparse.Namespace, scene: Scene) -> int:
    """``simserver soak --cars N``: the multi-car soak, its summary and violations."""
    import json

    from simserver.sim.multisoak import run_multi_soak

    run_multi_soak(scene, args.cars, 0.01, seed=args.seed)  # compile before the clock
    with _progress_bar(not args.quiet and sys.stderr.isatty(), total=args.duration,
                       desc=f"soak {args.cars} cars", unit="sim s") as progress:
        report = run_multi_soak(scene, args.cars, args.duration, seed=args.seed,
                                progress=progress)
    summary = report.as_dict()
    _write_soak_summary(args.out, summary)
    brief = {k: v for k, v in summary.items() if k != "contact_events"}
    print(json.dumps(brief, indent=2, sort_keys=True))
    for v in report.violations:
        print(f"violation: {v.invariant} at step {v.step} (t = {v.time_s:.3f} s): {v.detail}",
              file=sys.stderr)
    return 0 if report.ok else 1


def soak_command(args: argparse.Namespace) -> int:
    """``simserver soak``: seeded random driving, invariants checked every tick."""
    from simserver.sim.scene_files import load_scene
    from simserver.sim.soak import run_soak

    if not (math.isfinite(args.duration) and 0.0 < args.duration <= 1e7):
        raise CliError("--duration: expected a positive number of seconds", exit_code=2)
    if args.scene is None:
        # the server module only for its configs folder: a soak with --scene needs none
        # of the real-time machinery (issue 33)
        from simserver.server.config import REPO_CONFIGS

        args.scene = REPO_CONFIGS / "scenes" / "flat_paper_sedan.yaml"
    if args.cars != 1 and not 4 <= args.cars <= 64:
        raise CliError(f"--cars: expected 1 or 4 to 64, got {args.cars}", exit_code=2)
    scene = load_scene(args.scene)
    if args.cars > 1:
        return _multi_soak(args, scene)
    run_soak(scene, 0.01, seed=args.seed)  # compile before the clock starts
    with _progress_bar(not args.quiet and sys.stderr.isatty(), total=args.duration,
                       desc="soak", unit="sim s") as progress:
        report = run_soak(scene, args.duration, seed=args.seed, progress=progress)
    summary = report.as_dict()
    text = _write_soak_summary(args.out, summary)
    print(text)
    print(report.holds_digest(), file=sys.stderr)
    if report.holds_unjudged:
        print(f"note: holds_unjudged {report.holds_unjudged}: {report.UNJUDGED_MEANING}",
              file=sys.stderr)
    for v in report.violations:
        print(f"violation: {v.invariant} at step {v.step} (t = {v.time_s:.3f} s): {v.detail}",
              file=sys.stderr)
    return 0 if report.ok else 1


# ------------------------------------------------------------------------ view
def _add_view_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sink", default="serve", metavar="MODE[:TARGET]",
                        help="serve[:PORT] (gRPC + web viewer on loopback, default), "
                             "save:FILE.rrd, connect:URL, spawn[:PORT]")
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="the server's zenoh endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                        help="a zenoh JSON5 client config (TLS, credentials, routers); its "
                             "own endpoints are used unless --connect is given")
    parser.add_argument("--wait", type=float, default=None, metavar="S",
                        help="seconds to wait for the server's first get_config reply, "
                             "retrying with backoff (default 60: at a lowered priority on a busy "
                             "machine the viewer may get no CPU for seconds)")
    parser.add_argument("--car", "--vehicle-id", dest="vehicle_id", default="car0",
                        metavar="ID",
                        help="the car followed: drawn in full, the camera and the "
                             "driver's-eye view on it; every car of a multi-car world is "
                             "drawn too (world/cars/ID, default car0)")
    parser.add_argument("--prefix", default="simserver")
    parser.add_argument("--fps", type=float, default=None,
                        help="frames drawn per simulated second (default 50, 5 with "
                             "--web-port; a save: recording grows with it, docs/clients.md "
                             "section 5b)")
    parser.add_argument("--web-port", type=int, default=None, metavar="PORT",
                        help="serve: also host Rerun's web viewer on PORT (rerun-sdk 0.41 "
                             "binds it to all interfaces; off by default)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S wall seconds (default: until Ctrl-C)")
    parser.add_argument("--no-listener-check", action="store_true",
                        help="connect: do not first check that the viewer listens (to test "
                             "a viewer that is gone: logging then buffers in this process)")
    priority = parser.add_mutually_exclusive_group()
    priority.add_argument("--normal-priority", action="store_true",
                          help="keep normal CPU priority (default: nice 10, which a "
                               "real-time server pre-empts; docs/clients.md section 5c)")
    priority.add_argument("--idle-priority", action="store_true",
                          help="idle CPU priority (SCHED_IDLE): only CPU time nothing else "
                               "wants, so beside CPU-bound processes the view may draw "
                               "nothing (serve --viewer starts its view so)")


def view_command(args: argparse.Namespace) -> int:
    """``simserver view``: the live Rerun scene of a running server (its own process)."""
    from simserver.adapters.rerun_sink import RerunSinkError
    from simserver.adapters.viewer import (
        DEFAULT_FPS,
        DEFAULT_WAIT_S,
        WEB_FPS,
        ServerWaitError,
        run_viewer,
    )
    from simserver.adapters.zenoh_io import ZenohConfigError

    # a --zenoh-config keeps its own endpoints (a TLS client's server name) unless
    # --connect is given
    connect = args.connect or (None if args.zenoh_config else ["tcp/127.0.0.1:7447"])
    wait_s = DEFAULT_WAIT_S if args.wait is None else args.wait
    if not wait_s >= 0:
        raise CliError(f"--wait {args.wait:g}: expected a number of seconds >= 0",
                       exit_code=2)
    fps = args.fps
    if fps is None:  # a web viewer gets fewer frames (docs/clients.md section 5c)
        fps = WEB_FPS if args.web_port is not None else DEFAULT_FPS
    if not 0.1 <= fps <= 1000.0:
        raise CliError(f"--fps {args.fps:g}: expected frames per simulated second from 0.1 "
                       "to 1000", exit_code=2)
    try:
        stats = run_viewer(args.sink, connect, args.prefix, args.vehicle_id, fps,
                           duration_s=args.duration, config_file=args.zenoh_config,
                           web_port=args.web_port, check_listener=not args.no_listener_check,
                           priority=("normal" if args.normal_priority else
                                     "idle" if args.idle_priority else "nice"),
                           wait_s=wait_s)
    except RerunSinkError as exc:
        raise CliError(str(exc), exit_code=2) from exc
    except ZenohConfigError as exc:
        raise CliError(f"zenoh configuration: {exc}", exit_code=2) from exc
    except ServerWaitError as exc:
        raise CliError(str(exc), exit_code=3) from exc
    print(f"viewer: {stats.states_received} states, {stats.frames_logged} frames, "
          f"{stats.states_dropped} dropped; CPU priority {stats.cpu_priority}", flush=True)
    return 0


def _add_tls_front_arguments(parser: argparse.ArgumentParser) -> None:
    from simserver.adapters import tls_front

    tls_front.add_arguments(parser)


def tls_front_command(args: argparse.Namespace) -> int:
    """``simserver tls-front``: the accept-filtering front of a zenoh TLS listener."""
    from simserver.adapters import tls_front

    try:
        return tls_front.main(args)
    except (ValueError, OSError) as exc:
        raise CliError(f"tls-front: {exc}", exit_code=2) from exc


def _add_router_arguments(parser: argparse.ArgumentParser) -> None:
    from simserver.adapters import router

    router.add_arguments(parser)


def router_command(args: argparse.Namespace) -> int:
    """``simserver router``: a zenoh router with the project's safe defaults."""
    from simserver.adapters import router
    from simserver.adapters.tls_front import FrontError
    from simserver.adapters.zenoh_io import ZenohConfigError, ZenohOpenError

    if args.duration is not None and not args.duration >= 0:
        raise CliError(f"--duration {args.duration:g}: expected seconds >= 0", exit_code=2)
    try:
        return router.main(args)
    except ZenohConfigError as exc:
        raise CliError(f"zenoh configuration: {exc}", exit_code=2) from exc
    except (ZenohOpenError, FrontError) as exc:
        raise CliError(str(exc), exit_code=2) from exc


SUBCOMMANDS: dict[str, Subcommand] = {
    "run-scenario": Subcommand(
        help="run a scenario headless; write history.parquet, summary.json and plots",
        add_arguments=_add_run_scenario_arguments,
        run=run_scenario_command,
        description="Run a scenario YAML as fast as the CPU allows (deterministic: the "
                    "same file gives the same history bytes) and write DIR/history.parquet, "
                    "DIR/summary.json and DIR/{speed,forces,trajectory,slip,inputs}.png.",
    ),
    "compare": Subcommand(help=compare_cli.HELP, add_arguments=compare_cli.add_arguments,
                          run=compare_cli.run, description=compare_cli.DESCRIPTION),
    "tire-curves": Subcommand(
        help="plot a tire's force curves (Fy-alpha, Fx-kappa, combined slip, Mz) to a PNG",
        add_arguments=_add_tire_curves_arguments,
        run=tire_curves_command,
        description="Plot Fy against slip angle at several loads (SAE 950311 Fig. 5), Fx "
                    "against longitudinal slip (Fig. 6), Fx and Fy under combined slip and "
                    "Mz against slip angle, for a simple or mf61 tire file.",
    ),
    "serve": Subcommand(
        help="the real-time server: the car at a fixed 1 kHz, driven over zenoh",
        add_arguments=_add_serve_arguments,
        run=serve_command,
        description="Load a server config, a vehicle and a scene, compile, then step the "
                    "physics at a fixed wall-clock rate on absolute deadlines; commands, "
                    "state, diagnostics and controls over zenoh (docs/protocol.md). Stops "
                    "cleanly on SIGINT/SIGTERM and prints its statistics.",
    ),
    "view": Subcommand(
        help="the live Rerun scene of a running server (a separate process)",
        add_arguments=_add_view_arguments,
        run=view_command,
        description="Subscribe to a server's state and diagnostics and log the scene to "
                    "Rerun (serve, save, connect or spawn). The physics never waits for "
                    "it: it is its own process behind a bounded queue.",
    ),
    "sweep": Subcommand(help=sweep_cli.HELP, add_arguments=sweep_cli.add_arguments,
                        run=sweep_cli.run, description=sweep_cli.DESCRIPTION),
    "ros2": Subcommand(help=ros2_cli.HELP, add_arguments=ros2_cli.add_arguments,
                       run=ros2_cli.run, description=ros2_cli.DESCRIPTION),
    "replay": Subcommand(
        help="re-run a server command log headless, bit for bit",
        add_arguments=_add_replay_arguments,
        run=replay_command,
        description="Re-run the applied inputs and controls of a 'simserver serve "
                    "--command-log' file with the same compiled step and compare the final "
                    "state with the live run's (exit 1 if it differs). Given the logs of "
                    "every car of a multi-car server (run.<id>.jsonl), steps them together "
                    "in one world, contacts included (docs/protocol.md).",
    ),
    "soak": Subcommand(
        help="headless soak: seeded random driving with invariants checked every tick",
        add_arguments=_add_soak_arguments,
        run=soak_command,
        description="Drive the scene's car for the given simulated time (accelerate, "
                    "brake to stops, hold on slopes, restart, reverse, corner, spin, park "
                    "on changing roads) as fast as the CPU allows; check every tick that "
                    "all is finite, speeds and loads bounded, loads never negative and "
                    "held cars never creep. Exit 1 on any violation.",
    ),
    "tls-front": Subcommand(
        help="the accept-filtering front of a zenoh TLS listener (docs/security.md 5)",
        add_arguments=_add_tls_front_arguments,
        run=tls_front_command,
        description="Accept TCP connections on a public address and pass each one, "
                    "unchanged, to zenoh's TLS listener on loopback only once it has sent "
                    "the start of a TLS ClientHello; silent, closed or non-TLS connections "
                    "never reach zenoh (whose TLS listener pauses 100 ms after each failed "
                    "handshake). 'simserver serve' starts one per tls/ endpoint itself.",
    ),
    "router": Subcommand(
        help="a zenoh router for servers on several machines (loopback by default)",
        add_arguments=_add_router_arguments,
        run=router_command,
        description="Run a zenoh router (this Python process, mode router) until "
                    "SIGINT/SIGTERM: servers and clients on several machines meet here. "
                    "Safe defaults as the server's: explicit endpoints only (listen on "
                    "tcp/127.0.0.1:7447 unless told), multicast scouting and gossip off, "
                    "shared memory off; a --zenoh-config file (TLS, user/password, "
                    "access control) is used as it is; every tls/ listener gets the TLS "
                    "front (docs/security.md 5.1).",
    ),
}
"""Every subcommand, by name, in ``--help`` order."""


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand of ``SUBCOMMANDS``.

    Given the command line ``argv``, only the subcommand it names gets its arguments (the
    others are listed, for ``--help`` and the error on a wrong name): a subcommand's
    arguments may import its module (``tls-front``, ``router``), and a warm command pays
    for no other's imports (issue 33 item 2). Without ``argv``, or when no subcommand is
    named, every subcommand gets its arguments.
    """
    from simserver import __version__

    named = _named_subcommand(argv)

    parser = argparse.ArgumentParser(
        prog="simserver",
        description="Driving-simulator server with Bernard & Clover lagged-slip tires "
                    "(SAE 950311).",
    )
    parser.add_argument("--version", action="version", version=f"simserver {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, command in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=command.help,
                           description=command.description or command.help)
        if named is None or name == named:
            command.add_arguments(p)
        p.set_defaults(handler=command.run)
    return parser


def _named_subcommand(argv: Sequence[str] | None) -> str | None:
    """The subcommand ``argv`` names (its first word not an option, as argparse takes it:
    the top-level parser has only flags), or None."""
    if argv is None:
        return None
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in SUBCOMMANDS else None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``simserver`` console script.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        The exit code (see the module docstring).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    from simserver.adapters.config import ConfigError

    try:
        return int(args.handler(args))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CliError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
