"""Micro-benchmark of the MF 6.1 tire kernel: median ns per ``mf61_forces`` call.

Run from the repository root::

    python -m benchmarks.bench_tire [--tir FILE] [--calls N] [--repeats R]

The calls are looped inside a compiled function (no Python call overhead) over a table of
operating points made beforehand, one column per argument (the timed loop makes no array
views and allocates nothing). Two tables:

- ``driving``: a smooth trajectory, slips, load, camber and speed varying as in a
  simulation (successive calls alike, as for one wheel from step to step);
- ``random``: independent random points, the worst case for branch prediction.

Each repeat times ``--calls`` calls; reported are the median and the minimum over the
repeats (the minimum is the least disturbed by other processes on a shared machine).
"""

from __future__ import annotations

import argparse
import platform
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


# Not cached on purpose: numba's cache of a caller does not notice a change in a callee in
# another file, and a cached loop would keep timing an old mf61_forces.
@nb.njit(cache=False)
def _loop(
    p: np.ndarray,
    kappa: np.ndarray,
    tan_alpha: np.ndarray,
    gamma: np.ndarray,
    fz: np.ndarray,
    mu: np.ndarray,
    vx: np.ndarray,
    n_calls: int,
    out: np.ndarray,
) -> float:
    """Call ``mf61_forces`` ``n_calls`` times cycling over the table; return a checksum."""
    acc = 0.0
    n_rows = kappa.shape[0]
    j = 0
    for _ in range(n_calls):
        mf61_forces(p, kappa[j], tan_alpha[j], gamma[j], fz[j], mu[j], vx[j], out)
        acc += out[OUT_FX] + out[OUT_FY] + out[OUT_MZ]
        j += 1
        if j == n_rows:
            j = 0
    return acc


def operating_points(kind: str, n: int = 4096, seed: int = 1) -> tuple[np.ndarray, ...]:
    """Columns (kappa, tan_alpha, gamma, fz, mu, vx) of ``n`` operating points."""
    if kind == "random":
        rng = np.random.default_rng(seed)
        return (
            rng.uniform(-0.15, 0.15, n),
            rng.uniform(-0.15, 0.15, n),
            rng.uniform(-0.05, 0.05, n),
            rng.uniform(1500.0, 7000.0, n),
            rng.uniform(0.5, 1.0, n),
            rng.uniform(1.0, 40.0, n),
        )
    t = np.linspace(0.0, 8.0 * np.pi, n)
    return (
        0.06 * np.sin(t),
        0.08 * np.sin(0.7 * t + 1.0),
        -0.02 + 0.01 * np.sin(0.3 * t),
        4000.0 + 1500.0 * np.sin(0.5 * t),
        np.full(n, 0.9),
        20.0 + 10.0 * np.sin(0.1 * t),
    )


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tir", type=Path, default=DEFAULT_TIR)
    parser.add_argument("--calls", type=int, default=100_000, help="calls per repeat")
    parser.add_argument("--repeats", type=int, default=31)
    args = parser.parse_args(argv)

    p = mf61_param_vector(mf61_coefficients(load_tir(args.tir)))
    out = np.zeros(N_TIRE_OUT)
    print(f"machine: {platform.machine()}, Python {platform.python_version()}")
    medians = {}
    for kind in ("driving", "random"):
        cols = operating_points(kind)
        _loop(p, *cols, 10, out)  # compile, or load from the cache
        per_call = []
        for _ in range(args.repeats):
            t0 = time.perf_counter_ns()
            _loop(p, *cols, args.calls, out)
            per_call.append((time.perf_counter_ns() - t0) / args.calls)
        per_call.sort()
        medians[kind] = per_call[len(per_call) // 2]
        print(
            f"mf61_forces, {kind:7s} inputs: median {medians[kind]:6.1f} ns/call, "
            f"min {per_call[0]:6.1f} ({args.repeats} x {args.calls} calls)"
        )
    return medians


if __name__ == "__main__":
    main()
