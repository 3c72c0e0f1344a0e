"""Micro-benchmark of the MF 6.1 tire kernel: median ns per ``mf61_forces`` call.

Run from the repository root::

    python benchmarks/bench_tire.py [--tir FILE] [--calls N] [--repeats R]

The calls are looped inside a compiled function (no Python call overhead), over a
pre-generated table of operating points (combined slip, camber, load and speed varying
from call to call, so that branches and the peak solver see realistic inputs). The
table is made once, outside the timed region; the timed loop allocates nothing.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba as nb
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simserver.adapters.tir_file import load_tir, mf61_coefficients  # noqa: E402
from simserver.core.tire_layout import N_TIRE_OUT, OUT_FX, OUT_FY, OUT_MZ  # noqa: E402
from simserver.core.tire_mf61 import mf61_forces, mf61_param_vector  # noqa: E402

DEFAULT_TIR = Path("/work/shared/data/tires/mf61_225_50R17_sample.tir")


@nb.njit(cache=True)
def _loop(p: np.ndarray, inputs: np.ndarray, n_calls: int, out: np.ndarray) -> float:
    """Call ``mf61_forces`` ``n_calls`` times over the rows of ``inputs``; return a checksum."""
    acc = 0.0
    n_rows = inputs.shape[0]
    for i in range(n_calls):
        row = inputs[i % n_rows]
        mf61_forces(p, row[0], row[1], row[2], row[3], row[4], row[5], out)
        acc += out[OUT_FX] + out[OUT_FY] + out[OUT_MZ]
    return acc


def _operating_points(n: int, gamma_rad: float | None, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.empty((n, 6))
    pts[:, 0] = rng.uniform(-0.15, 0.15, n)  # kappa
    pts[:, 1] = rng.uniform(-0.15, 0.15, n)  # tan_alpha
    pts[:, 2] = rng.uniform(-0.05, 0.05, n) if gamma_rad is None else gamma_rad
    pts[:, 3] = rng.uniform(1500.0, 7000.0, n)  # fz_n
    pts[:, 4] = rng.uniform(0.5, 1.0, n)  # mu_scale
    pts[:, 5] = rng.uniform(1.0, 40.0, n)  # vx_mps
    return pts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tir", type=Path, default=DEFAULT_TIR)
    parser.add_argument("--calls", type=int, default=200_000, help="calls per repeat")
    parser.add_argument("--repeats", type=int, default=21)
    args = parser.parse_args(argv)

    p = mf61_param_vector(mf61_coefficients(load_tir(args.tir)))
    out = np.zeros(N_TIRE_OUT)
    for label, gamma in (("camber 0", 0.0), ("camber varying", None)):
        inputs = _operating_points(4096, gamma)
        _loop(p, inputs, 10, out)  # compile / load from cache
        per_call = []
        for _ in range(args.repeats):
            t0 = time.perf_counter_ns()
            _loop(p, inputs, args.calls, out)
            per_call.append((time.perf_counter_ns() - t0) / args.calls)
        per_call.sort()
        print(
            f"mf61_forces ({label}): median {per_call[len(per_call) // 2]:.1f} ns/call, "
            f"min {per_call[0]:.1f}, max {per_call[-1]:.1f} "
            f"({args.repeats} x {args.calls} calls)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
