"""Warm paths without a tax (issue 33 item 2): each headless command imports only the
heavy packages it uses. matplotlib only for a plot, pyarrow only for a Parquet table, rerun
only for a recording, dask only for a cluster, zenoh never off the network.

Each command runs for real in a fresh interpreter (``simserver.cli.main``, as the console
script calls it), then reports which of the heavy packages ended up in ``sys.modules``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from simserver.testing import CONFIGS, REPO

E2 = CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml"
FLAT = CONFIGS / "scenes" / "flat_paper_sedan.yaml"
TIRE = CONFIGS / "tires" / "paper_sti.yaml"
CMDLOG = REPO / "tests" / "data" / "first_release_live.cmdlog"
HEAVY = ("matplotlib", "pyarrow", "dask", "distributed", "rerun", "zenoh", "tqdm",
         "simserver.server.app", "simserver.server.command_log",
         "simserver.adapters.tls_front", "simserver.adapters.router")
"""Packages (and the real-time server's modules) that cost start-up time and that some warm
path does not need; ``simserver.server.app`` pulls in the tick loop, the workers and the
ROS 2 supervisor; ``simserver.server.command_log`` is the replay's (the sign it ran); tqdm
draws a progress bar only on a terminal; the TLS front and the router are subcommands of
their own (their arguments come from their modules: only ``tls-front`` and ``router``
build them)."""
NOT_NEEDED_ANYWHERE = {"dask", "distributed", "zenoh", "simserver.server.app", "tqdm",
                       "simserver.adapters.tls_front", "simserver.adapters.router"}
"""None of these commands needs any of these (a headless run, off the network, its output
piped: no bar)."""

REPORT = "import json, sys\nprint(json.dumps(sorted(m for m in {heavy!r} if m in sys.modules)))\n"


def _loaded(body: str) -> set[str]:
    """Run ``body`` in a fresh interpreter; the heavy modules it imported."""
    code = body + "\n" + REPORT.format(heavy=HEAVY)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def _cli(*argv: str) -> str:
    """Code that runs ``simserver ARGV`` in-process and fails if the command does."""
    return ("import contextlib, io\nfrom simserver.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    rc = main({list(argv)!r})\n"
            "assert rc == 0, rc\n")


@pytest.mark.parametrize(("argv", "needed", "not_needed"), [
    (("run-scenario", str(E2), "--out", "{tmp}", "--no-plots"),
     {"pyarrow"}, {"matplotlib", "rerun"}),
    (("run-scenario", str(E2), "--out", "{tmp}", "--quiet", "--rrd", "{tmp}/e2.rrd"),
     {"pyarrow", "matplotlib", "rerun"}, set()),
    (("tire-curves", str(TIRE), "--out", "{tmp}/curves.png"),
     {"matplotlib"}, {"pyarrow", "rerun"}),
    (("soak", "--scene", str(FLAT), "--duration", "0.2"),
     set(), {"matplotlib", "pyarrow", "rerun"}),
    (("replay", str(CMDLOG)),
     {"simserver.server.command_log"}, {"matplotlib", "pyarrow", "rerun"}),
], ids=["run-scenario-no-plots", "run-scenario-plots-rrd", "tire-curves", "soak", "replay"])
def test_a_warm_command_imports_only_what_it_uses(tmp_path, argv, needed, not_needed):
    """(Without ``--quiet`` where it is a choice: the output here is not a terminal, so a
    bar is not drawn either way.)"""
    not_needed = not_needed | NOT_NEEDED_ANYWHERE
    loaded = _loaded(_cli(*(a.format(tmp=tmp_path) for a in argv)))
    assert needed <= loaded, f"the command did not run what it should: {sorted(loaded)}"
    assert not loaded & not_needed, f"imported without need: {sorted(loaded & not_needed)}"


def test_a_sweep_worker_without_histories_loads_no_table_plot_or_recording_library():
    """A Dask worker's case, run as ``run_batch`` runs it, with no history directory: its
    row comes from the metrics alone, so no Parquet, no plot, no recording."""
    body = (
        "from simserver.sim.scenario import resolve_scenario\n"
        "from simserver.sweep.metrics import Metric\n"
        "from simserver.sweep.spec import Case\n"
        "from simserver.sweep.worker import OK, run_batch\n"
        f"case = Case(index=0, base={str(E2)!r}, params={{}}, "
        f"resolved=resolve_scenario({str(E2)!r}), run_id='x')\n"
        "[row] = run_batch([case], (Metric('stopping_distance', (('from_s', 0.7),)),), None)\n"
        "assert row['status'] == OK, row\n"
    )
    loaded = _loaded(body)
    assert "distributed" in loaded  # the worker plugin's module: a worker runs in dask
    assert not loaded & {"matplotlib", "pyarrow", "rerun", "zenoh", "simserver.server.app"}, \
        sorted(loaded)
