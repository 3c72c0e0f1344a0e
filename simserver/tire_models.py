"""The tire-model registry: one entry per model, the one list of tire models.

An entry (``TireModel``) holds everything that is particular to a model:

- ``id`` (the value of ``tp[TP_MODEL]``, dense: the index of its kernels) and ``name``
  (the ``model:`` key of a tire file);
- ``load``: the parameter loader, from the tire file's mapping to the packed
  model-specific slots and the common ones (radius, relaxation lengths);
- ``prepare`` and ``evaluate``: the compiled kernels, compiled with the explicit
  signatures ``core.tire_layout.PREPARE_SIGNATURE`` and ``EVALUATE_SIGNATURE``, taking
  the whole packed tire vector (common slots, then the model's from ``TP_MODEL_BASE``);
- ``nominal_load_n``: the load at which its stiffnesses are reported
  (``stiffness_report``, the CLI's ``tire-curves``).

Everything else reads the registry: the config loader (``adapters.config.load_tire``),
the simulation (``tire_kernels()``, handed to the compiled step), the CLI and the docs.
A new tire model is one module (its kernels and loader) plus one ``register_tire_model``
call; an unknown name or id is an error (``UnknownTireModelError``), never a fallback.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numba.core.errors import NumbaExperimentalFeatureWarning

from simserver.core.tire import N_BUILTIN_TIRE_MODELS, N_TIRE_PARAM, tire_forces
from simserver.core.tire_layout import (
    EVALUATE_SIGNATURE,
    N_TIRE_OUT,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FX_PEAK,
    OUT_FY_PEAK,
    OUT_KAPPA_SLIDE,
    OUT_TAN_ALPHA_SLIDE,
    PREPARE_SIGNATURE,
    TIRE_MODEL_MF61,
    TIRE_MODEL_SIMPLE,
    TP_MODEL,
    TP_MODEL_BASE,
    TireKernels,
)
from simserver.core.tire_mf61 import (
    P_FNOMIN,
    mf61_evaluate_kernel,
    mf61_param_vector,
    mf61_prepare_kernel,
)
from simserver.core.tire_simple import (
    SIMPLE_PARAM_NAMES,
    SP_FZ_NOM,
    simple_evaluate_kernel,
    simple_param_vector,
    simple_prepare_kernel,
)

# Tuples of first-class function pointers are what makes the kernels a cacheable argument
# of the compiled step; numba flags the feature as experimental on every such call.
warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning,
                        message="First-class function type feature is experimental")

N_MODEL_PARAM_MAX = N_TIRE_PARAM - TP_MODEL_BASE
"""Model-specific slots a tire vector has room for."""


class UnknownTireModelError(ValueError):
    """A tire model name or id that the registry does not list."""


@dataclass(frozen=True)
class LoadedTire:
    """What a model's loader makes of a tire file."""

    model_params: np.ndarray  # the model-specific slots, tp[TP_MODEL_BASE:]
    rolling_radius_m: float
    relax_lat_m: float  # b, paper eq. 16
    relax_long_m: float  # B, paper eq. 26


@dataclass(frozen=True)
class TireModel:
    """One registered tire model (see the module docstring)."""

    id: int
    name: str
    description: str
    load: Callable[[Path, dict[str, Any]], LoadedTire]
    prepare: Any  # numba dispatcher compiled with PREPARE_SIGNATURE
    evaluate: Any  # numba dispatcher compiled with EVALUATE_SIGNATURE
    nominal_load_n: Callable[[np.ndarray], float]  # from the model-specific slots


_REGISTRY: list[TireModel] = []
TIRE_MODEL_NAMES: dict[str, int] = {}
"""Name -> id of every registered model (kept up to date by ``register_tire_model``)."""


def _check_kernel(name: str, kernel: Any, signature: Any, what: str) -> None:
    sigs = getattr(kernel, "nopython_signatures", None)
    if not sigs or len(sigs) != 1 or sigs[0].args != signature.args:
        raise TypeError(f"tire model {name!r}: {what} must be compiled with exactly the "
                        f"signature {signature} (nb.njit({what.upper()}_SIGNATURE, ...))")


def register_tire_model(name: str, description: str, load: Callable[[Path, dict], LoadedTire],
                        prepare: Any, evaluate: Any,
                        nominal_load_n: Callable[[np.ndarray], float]) -> TireModel:
    """Add a tire model; it gets the next id. Returns its entry.

    ``prepare`` and ``evaluate`` are ``numba.njit`` functions compiled with the explicit
    signatures ``PREPARE_SIGNATURE`` and ``EVALUATE_SIGNATURE`` (core.tire_layout); they
    receive the whole packed tire vector, their own slots from ``TP_MODEL_BASE`` on.
    """
    if name in TIRE_MODEL_NAMES:
        raise ValueError(f"tire model {name!r} is already registered")
    _check_kernel(name, prepare, PREPARE_SIGNATURE, "prepare")
    _check_kernel(name, evaluate, EVALUATE_SIGNATURE, "evaluate")
    entry = TireModel(id=len(_REGISTRY), name=name, description=description, load=load,
                      prepare=prepare, evaluate=evaluate, nominal_load_n=nominal_load_n)
    _REGISTRY.append(entry)
    TIRE_MODEL_NAMES[name] = entry.id
    return entry


def unregister_tire_model(name: str) -> None:
    """Remove the most recently registered model (ids stay dense: only the last one can go,
    and never a built-in one). For plugins' tests, so that a toy model does not outlive them
    (the registry is what the config loader, the CLI and the docs read)."""
    if not _REGISTRY or _REGISTRY[-1].name != name or len(_REGISTRY) <= N_BUILTIN_TIRE_MODELS:
        raise ValueError(f"tire model {name!r} is not the last registered non-built-in model")
    _REGISTRY.pop()
    del TIRE_MODEL_NAMES[name]


def tire_model(key: str | float) -> TireModel:
    """The entry of a model, by name or by id (``tp[TP_MODEL]``)."""
    if isinstance(key, str):
        if key in TIRE_MODEL_NAMES:
            return _REGISTRY[TIRE_MODEL_NAMES[key]]
        raise UnknownTireModelError(
            f"unknown tire model {key!r} (registered: {', '.join(TIRE_MODEL_NAMES)})")
    if float(key).is_integer() and 0 <= int(key) < len(_REGISTRY):
        return _REGISTRY[int(key)]
    raise UnknownTireModelError(
        f"unknown tire model id {float(key):g} (registered: "
        + ", ".join(f"{m.id} {m.name}" for m in _REGISTRY) + ")")


def tire_models() -> tuple[TireModel, ...]:
    """Every registered model, in id order."""
    return tuple(_REGISTRY)


def tire_kernels() -> TireKernels:
    """The compiled step's ``kernels`` argument: the kernels of every registered model
    beyond the built-in ones (which ``core.tire`` calls directly), in id order.

    Registering a model changes the tuples' length: the step is then compiled once more
    for the new length (and cached like any other specialisation).
    """
    extra = _REGISTRY[N_BUILTIN_TIRE_MODELS:]
    return TireKernels(tuple(m.prepare for m in extra), tuple(m.evaluate for m in extra))


def check_tire_vectors(tp: np.ndarray) -> None:
    """Raise ``UnknownTireModelError`` unless every row of ``tp`` names a registered model."""
    for row in np.atleast_2d(tp):
        tire_model(float(row[TP_MODEL]))


def nominal_load_n(tp: np.ndarray) -> float:
    """The nominal load of a packed tire vector (N), from its model's entry."""
    return float(tire_model(float(tp[TP_MODEL])).nominal_load_n(tp[TP_MODEL_BASE:]))


def stiffness_report(tp: np.ndarray, fz_n: float | None = None,
                     mu_scale: float = 1.0) -> dict[str, float]:
    """The tire's stiffnesses and limits at zero slip and load ``fz_n`` (default nominal).

    Keys: ``fz_n``, ``c_kappa_n`` (dFx/dkappa), ``c_alpha_n_per_rad`` (-dFy/dtan_alpha),
    ``fx_peak_n``, ``fy_peak_n``, ``kappa_slide``, ``tan_alpha_slide``.
    """
    fz = nominal_load_n(tp) if fz_n is None else float(fz_n)
    out = np.zeros(N_TIRE_OUT)
    tire_forces(tire_kernels(), np.ascontiguousarray(tp, dtype=np.float64), 0.0, 0.0, 0.0, fz,
                mu_scale, 0.0, out)
    return {"fz_n": fz, "c_kappa_n": float(out[OUT_C_KAPPA]),
            "c_alpha_n_per_rad": float(out[OUT_C_ALPHA]),
            "fx_peak_n": float(out[OUT_FX_PEAK]), "fy_peak_n": float(out[OUT_FY_PEAK]),
            "kappa_slide": float(out[OUT_KAPPA_SLIDE]),
            "tan_alpha_slide": float(out[OUT_TAN_ALPHA_SLIDE])}


# ------------------------------------------------------------------- the built-in models
COMMON_KEYS = ("relaxation_length_lat_m", "relaxation_length_long_m", "rolling_radius_m")


def _load_simple(path: Path, data: dict[str, Any]) -> LoadedTire:
    """``model: simple`` (core.tire_simple): every key of ``SIMPLE_TIRE_RANGES`` and the
    relaxation lengths, all required."""
    from simserver.adapters.config import (
        SIMPLE_TIRE_RANGES,
        TIRE_COMMON_RANGES,
        check_keys,
        number,
    )

    keys = ("model", *SIMPLE_PARAM_NAMES, *COMMON_KEYS[:2])
    check_keys(path, data, keys, required=keys)
    vals = {k: number(path, k, data[k], *SIMPLE_TIRE_RANGES[k]) for k in SIMPLE_PARAM_NAMES}
    lat, long = COMMON_KEYS[0], COMMON_KEYS[1]
    return LoadedTire(
        model_params=simple_param_vector(vals), rolling_radius_m=vals["rolling_radius_m"],
        relax_lat_m=number(path, lat, data[lat], *TIRE_COMMON_RANGES[lat]),
        relax_long_m=number(path, long, data[long], *TIRE_COMMON_RANGES[long]))


def _load_mf61(path: Path, data: dict[str, Any]) -> LoadedTire:
    """``model: mf61`` (core.tire_mf61): a ``tir_file`` (relative to the tire file) and
    optional radius and relaxation lengths (defaults from the .tir file)."""
    from simserver.adapters.config import TIRE_COMMON_RANGES, ConfigError, check_keys, number
    from simserver.adapters.tir_file import TirError, load_tir, mf61_coefficients
    from simserver.adapters.validate import referenced_file

    check_keys(path, data, ("model", "tir_file", *COMMON_KEYS), required=("model", "tir_file"))
    tir_path = referenced_file(path, "tir_file", data["tir_file"])
    try:
        coeffs = mf61_coefficients(load_tir(tir_path))
    except TirError as exc:
        raise ConfigError(f"{path}: key 'tir_file': {exc}") from exc
    r0 = coeffs["UNLOADED_RADIUS"]
    # MF 6.1 relaxation lengths at the nominal load (Pacejka 2012, eqs. 4.E65 and 4.E67)
    pty1 = coeffs.get("PTY1", 2.0)
    pty2 = coeffs.get("PTY2", 2.0)
    default = {"relaxation_length_lat_m": pty1 * r0 * math.sin(2.0 * math.atan(1.0 / pty2)),
               "relaxation_length_long_m": coeffs.get("PTX1", 1.0) * r0,
               "rolling_radius_m": r0}
    vals = {k: number(path, k, data.get(k, default[k]), *TIRE_COMMON_RANGES[k])
            for k in COMMON_KEYS}
    return LoadedTire(model_params=mf61_param_vector(coeffs),
                      rolling_radius_m=vals["rolling_radius_m"],
                      relax_lat_m=vals["relaxation_length_lat_m"],
                      relax_long_m=vals["relaxation_length_long_m"])


_simple = register_tire_model(
    "simple", "brush (Fiala) combined-slip model with explicit stiffnesses (core/tire_simple.py)",
    _load_simple, simple_prepare_kernel, simple_evaluate_kernel, lambda p: p[SP_FZ_NOM])
_mf61 = register_tire_model(
    "mf61", "Magic Formula 6.1 from a .tir property file (core/tire_mf61.py)",
    _load_mf61, mf61_prepare_kernel, mf61_evaluate_kernel, lambda p: p[P_FNOMIN])
if (_simple.id, _mf61.id, len(_REGISTRY)) != (TIRE_MODEL_SIMPLE, TIRE_MODEL_MF61,
                                               N_BUILTIN_TIRE_MODELS):
    raise ImportError("the built-in tire models must keep the ids of core.tire_layout")
