"""The brush (Fiala) combined-slip tire, ``model: simple``: its tire-file keys, its loader
and its registration with the kernels of ``core.tire_simple`` (one place for the model
apart from its compiled body)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from simserver.core.param_table import Param, ParamTable
from simserver.core.tire_layout import N_SIMPLE_COEF
from simserver.core.tire_simple import (
    N_SIMPLE_PARAM,
    SIMPLE_PARAM_NAMES,
    SP_FZ_NOM,
    simple_evaluate_kernel,
    simple_param_vector,
    simple_prepare_kernel,
)
from simserver.tires.registry import (
    RADIUS_MEANING,
    RELAX_LAT_MEANING,
    RELAX_LONG_MEANING,
    LoadedTire,
    TireModel,
    read_tire_params,
    register_tire_model,
    relaxation_param,
)

SIMPLE_TIRE_PARAMS = ParamTable("simple", "the brush combined-slip tire (core/tire_simple.py)", (
    Param("cornering_stiffness_n_per_rad", "N/rad", 100.0, 1e7,
          "C_alpha at nominal_load_n, linear in the load"),
    Param("longitudinal_stiffness_n", "N", 100.0, 1e7,
          "C_kappa (N per unit slip) at nominal_load_n, linear in the load"),
    Param("nominal_load_n", "N", 10.0, 1e6, "load at which the stiffnesses are given"),
    Param("friction_coefficient", "-", 0.01, 3.0,
          "peak friction mu (times the road's friction scale)"),
    Param("rolling_resistance_coefficient", "-", 0.0, 0.5, "rolling-resistance force / Fz"),
    Param("pneumatic_trail_m", "m", 0.0, 0.5,
          "pneumatic trail at zero slip (Mz = -t Fy, t falls to 0 at full sliding)"),
    Param("rolling_radius_m", "m", 0.05, 2.0, RADIUS_MEANING),
    relaxation_param("relaxation_length_lat_m", RELAX_LAT_MEANING, None),
    relaxation_param("relaxation_length_long_m", RELAX_LONG_MEANING, None),
))
if tuple(p.name for p in SIMPLE_TIRE_PARAMS)[:len(SIMPLE_PARAM_NAMES)] != SIMPLE_PARAM_NAMES:
    raise ImportError("SIMPLE_TIRE_PARAMS must list core.tire_simple's slots first, in order")


def load_simple(path: Path, data: dict[str, Any]) -> LoadedTire:
    """``model: simple`` (core.tire_simple): every key of ``SIMPLE_TIRE_PARAMS``."""
    vals = read_tire_params(path, data, SIMPLE_TIRE_PARAMS)
    return LoadedTire(
        model_params=simple_param_vector(vals), rolling_radius_m=vals["rolling_radius_m"],
        relax_lat_m=vals["relaxation_length_lat_m"],
        relax_long_m=vals["relaxation_length_long_m"])


def register() -> TireModel:
    """Register the model (``simserver.tires`` does, first: id ``TIRE_MODEL_SIMPLE``)."""
    return register_tire_model(
        "simple", "brush (Fiala) combined-slip model with explicit stiffnesses "
        "(core/tire_simple.py)",
        load_simple, simple_prepare_kernel, simple_evaluate_kernel, lambda p: p[SP_FZ_NOM],
        n_coef=N_SIMPLE_COEF, n_params=N_SIMPLE_PARAM, params=SIMPLE_TIRE_PARAMS,
        _builtin=True)
