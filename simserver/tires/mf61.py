"""Magic Formula 6.1 from an MF-Tyre .tir file, ``model: mf61``: its tire-file keys, its
loader (the .tir read by ``simserver.adapters.tir_file``, the relaxation lengths and the
tire's side taken from it) and its registration with the kernels of ``core.tire_mf61``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from simserver.adapters.tir_file import TirError, load_tir, mf61_coefficients
from simserver.adapters.validate import ConfigError, number, referenced_file
from simserver.core.param_table import Param, ParamTable
from simserver.core.tire_layout import N_MF61_COEF
from simserver.core.tire_mf61 import (
    N_MF61_PARAM,
    P_FNOMIN,
    mf61_evaluate_kernel,
    mf61_param_vector,
    mf61_prepare_kernel,
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

AT_NOMINAL = ("; its default is MF 6.1's relaxation length at the nominal load "
              "Fz = LFZO FNOMIN and zero camber (a .tir key that is missing, not a number "
              "or not > 0 is an error naming it)")

MF61_TIRE_PARAMS = ParamTable("mf61", "Magic Formula 6.1 from a .tir file (core/tire_mf61.py)", (
    Param("rolling_radius_m", "m", 0.05, 2.0, RADIUS_MEANING,
          default="the .tir's UNLOADED_RADIUS"),
    relaxation_param("relaxation_length_lat_m", RELAX_LAT_MEANING + AT_NOMINAL,
                     "PTY1 sin(2 atan(1/PTY2)) R0 LFZO LSGAL"),
    relaxation_param("relaxation_length_long_m", RELAX_LONG_MEANING + AT_NOMINAL,
                     "PTX1 R0 LFZO LSGKP"),
))
MF61_PATH_KEYS = (("tir_file", "the MF-Tyre .tir property file (MF 6.1 or 6.2), relative to "
                               "the tire file; required"),)

MF61_TYRESIDES = {"left": "left", "right": "right", "symmetric": None}
"""Accepted ``TYRESIDE`` values of a .tir file (any case); absent means ``Left``, as in
MF-Tyre."""


def mf61_relaxation_lengths(tir: Any, coeffs: dict[str, float]) -> dict[str, float]:
    """The relaxation lengths MF 6.1 defines in a .tir file, at the nominal load.

    MF-Tyre 6.1 (as in MFeval): ``sigma_kappa = Fz (PTX1 + PTX2 dfz) exp(-PTX3 dfz)
    (R0 / Fz0) LSGKP`` and ``sigma_alpha = PTY1 sin(2 atan(Fz / (PTY2 Fz0'))) (1 - PKY3
    |gamma|) R0 LFZO LSGAL``. The lagged slip states of SAE 950311 take one length each
    (paper eqs. 16 and 26), so they are evaluated at the scaled nominal load
    ``Fz = Fz0' = LFZO FNOMIN`` (``dfz = 0``) and zero camber::

        relaxation_length_long_m = PTX1 R0 LFZO LSGKP
        relaxation_length_lat_m  = PTY1 sin(2 atan(1 / PTY2)) R0 LFZO LSGAL

    Returns a dict with the keys that could be computed (a key is absent when a .tir key
    it needs is absent); raises ``TirError`` naming the .tir key for a value that is not a
    number or out of its range (``PTX1 > 0``, ``PTY1 > 0``, ``PTY2 > 0``, ``LSGKP > 0``,
    ``LSGAL > 0``).
    """
    def value(key: str, default: float | None = None) -> float | None:
        if key in tir.ambiguous:
            raise TirError(f"{tir.path}: {key}: appears in several sections with different "
                           "values")
        if key not in tir.values:
            return default
        v = tir.values[key]
        if isinstance(v, str):
            raise TirError(f"{tir.where(key)}: {key}: non-numeric value {v!r}")
        if not v > 0.0:
            raise TirError(f"{tir.where(key)}: {key} = {v:g}: must be > 0 (relaxation length)")
        return float(v)

    r0_scaled = coeffs["UNLOADED_RADIUS"] * coeffs["LFZO"]
    lengths: dict[str, float] = {}
    ptx1, lsgkp = value("PTX1"), value("LSGKP", 1.0)
    if ptx1 is not None:
        lengths["relaxation_length_long_m"] = ptx1 * r0_scaled * lsgkp
    pty1, pty2, lsgal = value("PTY1"), value("PTY2"), value("LSGAL", 1.0)
    if pty1 is not None and pty2 is not None:
        lengths["relaxation_length_lat_m"] = (
            pty1 * math.sin(2.0 * math.atan(1.0 / pty2)) * r0_scaled * lsgal)
    return lengths


def _mf61_side(tir: Any) -> str | None:
    """The tire's ``TYRESIDE`` (``MF61_TYRESIDES``): left, right or None (symmetric)."""
    raw = tir.values.get("TYRESIDE", "Left")
    if not isinstance(raw, str) or raw.strip().lower() not in MF61_TYRESIDES:
        raise TirError(f"{tir.where('TYRESIDE')}: TYRESIDE = {raw!r}: expected one of "
                       "'Left', 'Right', 'Symmetric'")
    return MF61_TYRESIDES[raw.strip().lower()]


def load_mf61(path: Path, data: dict[str, Any]) -> LoadedTire:
    """``model: mf61`` (core.tire_mf61): a ``tir_file`` (relative to the tire file) and
    optional radius and relaxation lengths (defaults from the .tir file, see
    ``mf61_relaxation_lengths``); the tire's side from the .tir's ``TYRESIDE``."""
    vals = read_tire_params(path, data, MF61_TIRE_PARAMS, path_keys=("tir_file",))
    tir_path = referenced_file(path, "tir_file", data["tir_file"])
    try:
        tir = load_tir(tir_path)
        coeffs = mf61_coefficients(tir)
        if not coeffs["VXLOW"] >= 0.0:
            raise TirError(f"{tir.where('VXLOW')}: VXLOW = {coeffs['VXLOW']:g}: must be >= 0")
        from_tir = mf61_relaxation_lengths(tir, coeffs)
        side = _mf61_side(tir)
    except TirError as exc:
        raise ConfigError(f"{path}: key 'tir_file': {exc}") from exc
    from_tir["rolling_radius_m"] = coeffs["UNLOADED_RADIUS"]
    needs = {"relaxation_length_long_m": ("PTX1",), "relaxation_length_lat_m": ("PTY1", "PTY2")}
    for param in MF61_TIRE_PARAMS:
        key = param.yaml_key
        if key in vals:
            continue  # the tire file overrides the .tir
        if key not in from_tir:
            missing = ", ".join(k for k in needs[key] if k not in tir.values)
            raise ConfigError(f"{path}: key 'tir_file': {tir_path}: missing key {missing} "
                              f"(for the {param.meaning}; or give {key} in the tire file)")
        vals[key] = number(f"{path} (from {tir_path.name})", key, from_tir[key], param.lo,
                           param.hi)
    return LoadedTire(model_params=mf61_param_vector(coeffs),
                      rolling_radius_m=vals["rolling_radius_m"],
                      relax_lat_m=vals["relaxation_length_lat_m"],
                      relax_long_m=vals["relaxation_length_long_m"], side=side)


def register() -> TireModel:
    """Register the model (``simserver.tires`` does, second: id ``TIRE_MODEL_MF61``)."""
    return register_tire_model(
        "mf61", "Magic Formula 6.1 from a .tir property file (core/tire_mf61.py)",
        load_mf61, mf61_prepare_kernel, mf61_evaluate_kernel, lambda p: p[P_FNOMIN],
        n_coef=N_MF61_COEF, n_params=N_MF61_PARAM, params=MF61_TIRE_PARAMS,
        path_keys=MF61_PATH_KEYS, _builtin=True)
