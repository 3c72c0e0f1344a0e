"""A sweep's plots say what their axes show, in words with units, and keep points that
coincide visible (issue 32 item 5): read from the matplotlib objects the PNGs are drawn
from (``sweep.report.metric_figure``), on real runs of the paper's Example 2.

The sweep varies the grade, which changes the stopping distance, and the kinematic
model's ``u_min``, which the default (lagged) slip model never reads: the three runs of
each grade stop at one distance, bit for bit, and drawn at one x they were one dot with
one colour of the colour bar's three."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from simserver.adapters.history import result_columns  # noqa: E402
from simserver.sim.scenario import load_scenario, resolve_scenario, run_scenario
from simserver.sweep.metrics import METRIC_KINDS, METRIC_LABELS, evaluate  # noqa: E402
from simserver.sweep.report import PLOT_DIR, metric_figure, plot_metrics  # noqa: E402
from simserver.sweep.resolved import with_overrides  # noqa: E402
from simserver.sweep.spec import load_sweep  # noqa: E402
from simserver.testing import CONFIGS  # noqa: E402

E2 = CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml"
GRADE, U_MIN = "road.grade_pct", "model.kinematic_u_min_mps"


def sweep_rows(tmp_path):
    path = tmp_path / "plots.yaml"
    path.write_text(yaml.safe_dump({
        "name": "plots", "scenarios": [str(E2)],
        "grid": {GRADE: [-3.0, -5.0, -8.0], U_MIN: [0.3, 0.6, 0.9]},
        "metrics": [{"stopping_distance": {"from_s": 0.7}}, "resting_forces",
                    {"column": "u_mps", "stat": "max"}]}))
    sweep = load_sweep(path)
    rows = []
    for case in sweep.cases:
        resolved = with_overrides(resolve_scenario(case.base), case.params, "test")
        cols = result_columns(run_scenario(load_scenario(case.base, resolved)))
        rows.append({"status": "ok", **case.params, **evaluate(sweep.metrics, cols)})
    return sweep, rows


def test_axes_in_words_with_units_and_coinciding_points_visible(tmp_path):
    sweep, rows = sweep_rows(tmp_path)
    by_grade = {}
    for r in rows:
        by_grade.setdefault(r[GRADE], set()).add(r["stopping_distance_m"])
    assert all(len(v) == 1 for v in by_grade.values())  # u_min has no effect: coincide

    fig = metric_figure(sweep, rows, "stopping_distance_m", GRADE)
    try:
        ax, bar = fig.axes
        labels = [ax.get_xlabel(), ax.get_ylabel(), bar.get_ylabel()]
        print("\nlabels:", labels)
        assert ax.get_xlabel() == "road grade (%)"
        assert ax.get_ylabel() == "stopping distance (m)"
        assert bar.get_ylabel().endswith("(m/s)") and "u_min" not in bar.get_ylabel()
        for text in labels:
            assert "_" not in text and "." not in text.split("(")[0], text
        (points,) = ax.collections
        xy = points.get_offsets()
        assert len(xy) == len(rows) == 9
        # no two runs on one spot: the runs of a grade are spread sideways, within 2 %
        # of the grade's range, and keep their order of u_min
        assert len({(round(x, 9), round(y, 9)) for x, y in xy}) == 9
        for grade in by_grade:
            mine = [i for i, r in enumerate(rows) if r[GRADE] == grade]
            xs = xy[mine, 0]
            assert np.ptp(xs) > 0 and np.abs(xs - grade).max() <= 0.02 * 5.0 + 1e-12
            order = np.argsort([rows[i][U_MIN] for i in mine])
            assert (np.diff(xs[order]) > 0).all()
        # translucent markers with an edge: three colours at each grade, all drawn
        fig.canvas.draw()  # the colours of a mapped scatter are set when drawn
        face = points.get_facecolors()
        assert points.get_alpha() < 1.0 and len(points.get_edgecolors()) > 0
        assert points.get_linewidths()[0] > 0
        assert len({tuple(np.round(c, 6)) for c in face}) == 3
    finally:
        plt.close(fig)

    # the files are these figures: one per metric column and numeric parameter
    metric_columns = [k for k in rows[0] if k not in ("status", GRADE, U_MIN)]
    written = plot_metrics(sweep, rows, metric_columns, tmp_path)
    assert len(written) == 2 * len(metric_columns)
    assert all(p.parent == tmp_path / PLOT_DIR and p.stat().st_size > 0 for p in written)
    assert plt.imread(written[0]).shape[2] in (3, 4)


def test_every_metric_column_is_labelled_in_words():
    """Each kind's columns (evaluated on a real run) have their words in METRIC_LABELS."""
    cols = result_columns(run_scenario(load_scenario(E2)))
    for name, kind in METRIC_KINDS.items():
        options = {k: 1.0 for k in kind.required}
        out = kind.function(cols, **options)
        missing = set(out) - set(METRIC_LABELS)
        assert not missing, (name, missing)
