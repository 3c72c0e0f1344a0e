"""Regenerate the README's figures from real runs of the scenario files.

    python docs/figures.py

Writes docs/img/lagged_vs_kinematic_e2.png, docs/img/lagged_vs_kinematic_e5.png,
docs/img/e4_trajectory.png. The tire curves come from
``simserver tire-curves configs/tires/paper_sti.yaml --out docs/img/tire_curves_paper.png``.
"""

from __future__ import annotations

from pathlib import Path

from simserver.adapters.plots import plot_comparison, plot_trajectory
from simserver.sim.scenario import load_scenario, run_scenario

REPO = Path(__file__).resolve().parents[1]
SCEN = REPO / "configs" / "scenarios"
IMG = REPO / "docs" / "img"


def run(name: str):
    return run_scenario(load_scenario(SCEN / f"{name}.yaml"))


def main() -> None:
    IMG.mkdir(parents=True, exist_ok=True)
    plot_comparison(
        {"lagged slip (paper, Appendix A damping)": run("e2_stop_downslope_paper_damping"),
         "kinematic slip, eq. (1) patch": run("e6_kinematic_stop_downslope")},
        IMG / "lagged_vs_kinematic_e2.png",
        signals=("u_mps", "x_m", "fx_body_sum_n"),
        title="Example 2: braked stop on a 5 % downslope",
    )
    plot_comparison(
        {"lagged slip (default model)": run("e5_hold_restart_uphill"),
         "kinematic slip, eq. (1) patch": run("e6_kinematic_hold_restart_uphill")},
        IMG / "lagged_vs_kinematic_e5.png",
        signals=("u_mps", "x_m", "fx_body_sum_n"),
        title="E5: stop, hold 60 s and restart facing up a 10 % grade",
    )
    plot_trajectory(run("e4_spinout_sideslope"), IMG / "e4_trajectory.png")
    print("figures written to", IMG)


if __name__ == "__main__":
    main()
