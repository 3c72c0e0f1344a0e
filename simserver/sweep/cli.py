"""``simserver sweep SWEEP.yaml --out DIR``: the command line of simserver.sweep."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "run a parameter or regression sweep of scenarios on Dask (one laptop to a cluster)"
DESCRIPTION = ("Expand a sweep file (base scenarios x a grid, a list of cases or seeded "
               "random samples of dotted-path parameters) and run every case on Dask "
               "distributed: an embedded LocalCluster, one worker process per core, or "
               "--scheduler. Write DIR/results.parquet (a row per run: parameters, metrics, "
               "status, error, wall time), DIR/plots/*.png, DIR/report.md and, when the "
               "file asks, DIR/histories/RUN_ID.parquet. Exit 1 if any run failed.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sweep", type=Path, help="sweep YAML file")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output directory (created if missing)")
    parser.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786",
                        help="use this Dask scheduler instead of an embedded LocalCluster")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes of the LocalCluster (default: one per core)")
    parser.add_argument("--resume", action="store_true",
                        help="skip the runs already in DIR/results.parquet (by run id)")
    parser.add_argument("--batch", type=int, default=None, metavar="RUNS",
                        help="runs per Dask task (default: batches that shrink toward the end, "
                             "each lasting 0.1 s or more)")
    parser.add_argument("--numba-cache", type=Path, default=None, metavar="DIR",
                        help="NUMBA_CACHE_DIR of the LocalCluster's workers (shared: a "
                             "machine compiles once; the workers of --scheduler take theirs "
                             "from their own environment; SIMSERVER_CACHE_DIR in the "
                             "environment, shared by checkouts and the server, takes "
                             "precedence)")
    parser.add_argument("--config-dir", action="append", type=Path, default=None,
                        metavar="DIR", dest="config_dirs",
                        help="a folder the sweep's files (base scenarios, what they name, "
                             "file overrides) may lie in; repeatable (default: the "
                             "project's configs/ and the sweep file's folder)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from simserver.adapters.validate import ConfigError
    from simserver.sweep.engine import RESULTS_FILE, run_sweep
    from simserver.sweep.report import plot_metrics, write_report
    from simserver.sweep.spec import load_sweep

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: expected a positive number, got {args.workers}")
    if args.batch is not None and args.batch < 1:
        raise ConfigError(f"--batch: expected a positive number, got {args.batch}")
    sweep = load_sweep(args.sweep, args.config_dirs)
    out: Path = args.out
    outcome = run_sweep(sweep, out, scheduler=args.scheduler, workers=args.workers,
                        resume=args.resume, batch_runs=args.batch,
                        numba_cache=args.numba_cache, quiet=args.quiet)
    plots = [] if args.no_plots else plot_metrics(sweep, outcome.rows,
                                                  outcome.metric_columns, out)
    report = write_report(sweep, outcome, plots, out)
    rate = 60.0 * outcome.ran / outcome.wall_time_s if outcome.wall_time_s > 0 else 0.0
    print(f"{sweep.name}: {outcome.ran} runs ({outcome.failed} failed, {outcome.skipped} "
          f"already done) in {outcome.wall_time_s:.1f} s on {outcome.workers} workers, "
          f"{rate:.0f} runs/min; wrote {out / RESULTS_FILE}, {report}, {len(plots)} plots",
          flush=True)
    return 1 if any(r["status"] != "ok" for r in outcome.rows) else 0
