"""Micro-benchmark of the tire kernels: median ns per call.

Run from the repository root::

    python -m benchmarks.bench_tire [--tir FILE] [--calls N] [--repeats R]

Timed, for the MF 6.1 file: ``mf61_forces`` (the kernel alone), and through the
dispatcher of :mod:`simserver.core.tire`: ``tire_forces`` (prepare + evaluate at one
load), ``tire_prepare``, ``tire_evaluate`` (from coefficients prepared beforehand, one
vector per operating point), and one wheel's share of an RK4 step: ``tire_prepare`` then
``tire_evaluate`` at four stages (slips and load moved a little between stages).

The calls are looped inside a compiled function (no Python call overhead) over a table of
operating points made beforehand, one column per argument (the timed loop makes no array
views and allocates nothing). Two tables:

- ``driving``: a smooth trajectory, slips, load, camber and speed varying as in a
  simulation (successive calls alike, as for one wheel from step to step);
- ``no-camber``: the same with zero camber, as ``core.chassis`` passes it (MF 6.1 then
  skips its camber-free second lateral curve, see ``tire_mf61._mf61_evaluate``);
- ``random``: independent random points, the worst case for branch prediction.

Each repeat times ``--calls`` calls; reported are the median and the minimum over the
repeats (the minimum is the least disturbed by other processes on a shared machine).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numba as nb
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simserver.adapters.tir_file import load_tir, mf61_coefficients  # noqa: E402
from simserver.core.tire import (  # noqa: E402
    BUILTIN_KERNELS,
    N_TIRE_PARAM,
    tire_evaluate,
    tire_forces,
    tire_prepare,
)
from simserver.core.tire_layout import (  # noqa: E402
    N_TIRE_COEF,
    N_TIRE_OUT,
    OUT_FX,
    OUT_FY,
    OUT_MZ,
    TIRE_MODEL_MF61,
    TP_MODEL,
    TP_MODEL_BASE,
    TP_RADIUS_M,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)
from simserver.core.tire_mf61 import (  # noqa: E402
    N_MF61_PARAM,
    P_UNLOADED_RADIUS,
    mf61_forces,
    mf61_param_vector,
)

DEFAULT_TIR = Path(__file__).resolve().parents[1] / "configs/tires/data/mf61_225_50R17_sample.tir"

# The loops are not cached on purpose: numba's cache of a caller does not notice a change
# in a callee in another file, and a cached loop would keep timing an old kernel.


@nb.njit(cache=False)
def _loop_mf61_forces(
    p: np.ndarray, tp: np.ndarray, coefs: np.ndarray, kappa: np.ndarray,
    tan_alpha: np.ndarray, gamma: np.ndarray, fz: np.ndarray, mu: np.ndarray,
    vx: np.ndarray, n_calls: int, out: np.ndarray,
) -> float:  # fmt: skip
    """``mf61_forces`` ``n_calls`` times cycling over the table; return a checksum."""
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


@nb.njit(cache=False)
def _loop_tire_forces(
    p: np.ndarray, tp: np.ndarray, coefs: np.ndarray, kappa: np.ndarray,
    tan_alpha: np.ndarray, gamma: np.ndarray, fz: np.ndarray, mu: np.ndarray,
    vx: np.ndarray, n_calls: int, out: np.ndarray,
) -> float:  # fmt: skip
    """``tire_forces`` ``n_calls`` times."""
    acc = 0.0
    n_rows = kappa.shape[0]
    j = 0
    for _ in range(n_calls):
        tire_forces(BUILTIN_KERNELS, tp, kappa[j], tan_alpha[j], gamma[j], fz[j], mu[j], vx[j], out)
        acc += out[OUT_FX] + out[OUT_FY] + out[OUT_MZ]
        j += 1
        if j == n_rows:
            j = 0
    return acc


@nb.njit(cache=False)
def _loop_tire_prepare(
    p: np.ndarray, tp: np.ndarray, coefs: np.ndarray, kappa: np.ndarray,
    tan_alpha: np.ndarray, gamma: np.ndarray, fz: np.ndarray, mu: np.ndarray,
    vx: np.ndarray, n_calls: int, out: np.ndarray,
) -> float:  # fmt: skip
    """``tire_prepare`` ``n_calls`` times, into one row of ``coefs`` per operating point."""
    acc = 0.0
    n_rows = kappa.shape[0]
    j = 0
    for _ in range(n_calls):
        tire_prepare(BUILTIN_KERNELS, tp, gamma[j], fz[j], mu[j], coefs[j])
        acc += coefs[j, 1]
        j += 1
        if j == n_rows:
            j = 0
    return acc


@nb.njit(cache=False)
def _loop_tire_evaluate(
    p: np.ndarray, tp: np.ndarray, coefs: np.ndarray, kappa: np.ndarray,
    tan_alpha: np.ndarray, gamma: np.ndarray, fz: np.ndarray, mu: np.ndarray,
    vx: np.ndarray, n_calls: int, out: np.ndarray,
) -> float:  # fmt: skip
    """``tire_evaluate`` ``n_calls`` times, each from the row prepared for its point."""
    acc = 0.0
    n_rows = kappa.shape[0]
    j = 0
    for _ in range(n_calls):
        tire_evaluate(BUILTIN_KERNELS, tp, coefs[j], kappa[j], tan_alpha[j], fz[j], vx[j], out)
        acc += out[OUT_FX] + out[OUT_FY] + out[OUT_MZ]
        j += 1
        if j == n_rows:
            j = 0
    return acc


@nb.njit(cache=False)
def _loop_wheel_step(
    p: np.ndarray, tp: np.ndarray, coefs: np.ndarray, kappa: np.ndarray,
    tan_alpha: np.ndarray, gamma: np.ndarray, fz: np.ndarray, mu: np.ndarray,
    vx: np.ndarray, n_calls: int, out: np.ndarray,
) -> float:  # fmt: skip
    """``n_calls`` wheel-steps: ``tire_prepare``, then four stages of ``tire_evaluate``."""
    acc = 0.0
    n_rows = kappa.shape[0]
    coef = coefs[0]
    j = 0
    for _ in range(n_calls):
        tire_prepare(BUILTIN_KERNELS, tp, gamma[j], fz[j], mu[j], coef)
        for stage in range(4):
            d = 1.0 + 1e-3 * stage
            tire_evaluate(BUILTIN_KERNELS, tp, coef, kappa[j] * d, tan_alpha[j] * d, fz[j] * d,
                          vx[j], out)
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
    camber = 0.0 if kind == "no-camber" else 1.0
    return (
        0.06 * np.sin(t),
        0.08 * np.sin(0.7 * t + 1.0),
        camber * (-0.02 + 0.01 * np.sin(0.3 * t)),
        4000.0 + 1500.0 * np.sin(0.5 * t),
        np.full(n, 0.9),
        20.0 + 10.0 * np.sin(0.1 * t),
    )


def mf61_tire_vector(p: np.ndarray) -> np.ndarray:
    """A dispatcher parameter vector (``N_TIRE_PARAM``) around the MF 6.1 slots ``p``."""
    tp = np.zeros(N_TIRE_PARAM)
    tp[TP_MODEL] = TIRE_MODEL_MF61
    tp[TP_RADIUS_M] = p[P_UNLOADED_RADIUS]
    tp[TP_RELAX_LAT_M] = 0.3
    tp[TP_RELAX_LONG_M] = 0.1
    tp[TP_MODEL_BASE:][:N_MF61_PARAM] = p
    return tp


LOOPS: dict[str, Callable[..., float]] = {
    "mf61_forces": _loop_mf61_forces,
    "tire_forces": _loop_tire_forces,
    "tire_prepare": _loop_tire_prepare,
    "tire_evaluate": _loop_tire_evaluate,
    "wheel-step (1 prepare + 4 evaluate)": _loop_wheel_step,
}


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tir", type=Path, default=DEFAULT_TIR)
    parser.add_argument("--calls", type=int, default=100_000, help="calls per repeat")
    parser.add_argument("--repeats", type=int, default=31)
    args = parser.parse_args(argv)

    p = mf61_param_vector(mf61_coefficients(load_tir(args.tir)))
    tp = mf61_tire_vector(p)
    out = np.zeros(N_TIRE_OUT)
    print(f"machine: {platform.machine()}, Python {platform.python_version()}")
    medians: dict[str, dict[str, float]] = {}
    for kind in ("driving", "no-camber", "random"):
        cols = operating_points(kind)
        coefs = np.zeros((cols[0].shape[0], N_TIRE_COEF))
        medians[kind] = {}
        for name, loop in LOOPS.items():
            # compile (or load), and fill coefs for the evaluate loop
            _loop_tire_prepare(p, tp, coefs, *cols, cols[0].shape[0], out)
            loop(p, tp, coefs, *cols, 10, out)
            per_call = []
            for _ in range(args.repeats):
                t0 = time.perf_counter_ns()
                loop(p, tp, coefs, *cols, args.calls, out)
                per_call.append((time.perf_counter_ns() - t0) / args.calls)
            per_call.sort()
            medians[kind][name] = per_call[len(per_call) // 2]
            print(
                f"{name:36s} {kind:9s} inputs: median {medians[kind][name]:6.1f} ns/call, "
                f"min {per_call[0]:6.1f} ({args.repeats} x {args.calls} calls)"
            )
    return medians


if __name__ == "__main__":
    main()
