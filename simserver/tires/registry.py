"""The tire-model registry: one entry per model, the one list of tire models.

An entry (``TireModel``) holds everything that is particular to a model:

- ``id`` (the value of ``tp[TP_MODEL]``, dense: the index of its kernels) and ``name``
  (the ``model:`` key of a tire file);
- ``load``: the parameter loader, from the tire file's mapping to the packed
  model-specific slots and the common ones (radius, relaxation lengths);
- ``prepare`` and ``evaluate``: the compiled kernels, compiled with the explicit
  signatures ``core.tire_layout.PREPARE_SIGNATURE`` and ``EVALUATE_SIGNATURE``, taking
  the whole packed tire vector (common slots, then the model's from ``TP_MODEL_BASE``).
  The built-in models' kernels are the exception: the step calls those models' bodies
  directly (``core.tire``), never their kernels, so they are compiled on first use only
  (compiled at import they cost 10-12 s of every start from an empty numba cache);
- ``nominal_load_n``: the load at which its stiffnesses are reported
  (``stiffness_report``, the CLI's ``tire-curves``).

Everything else reads the registry: the config loader (``adapters.config.load_tire``),
the simulation (``tire_kernels()``, handed to the compiled step), the CLI and the docs.
A new tire model is its compiled body plus one module holding its tire-file keys (a
``ParamTable``), its loader and its ``register_tire_model`` call, as the built-in ones
(``simserver.tires.simple``, ``simserver.tires.mf61``); an unknown name or id is an error
(``UnknownTireModelError``), never a fallback. This module knows no model.

Workspace. A model declares how many coefficient slots (``n_coef``) its ``prepare``
writes and ``evaluate`` reads, and how many model-specific parameter slots (``n_params``,
from ``TP_MODEL_BASE``) its loader packs. The compiled step has room for
``core.tire_layout.N_TIRE_COEF`` coefficients (a scratch on its stack, no bounds check)
and ``N_MODEL_PARAM_MAX`` parameters (a row of ``tp``): a declaration beyond either is
refused at registration (``TireWorkspaceError``, naming the model and the numbers), and a
loader that packs more parameters than its model declared is refused when the file loads.

Where a registration must live. Every process that reads a vehicle or runs the step needs
the same registry, with the same ids (``tp[TP_MODEL]`` crosses processes: the server's
load worker packs the tire vectors its loop then steps). The load worker is *spawned*
(``simserver.server.load_worker``: a fresh interpreter that imports ``simserver`` anew), and so
are a sweep's workers when their nanny restarts them or with ``--numba-cache``, and a
remote Dask worker shares nothing with the process that submitted the sweep. A
``register_tire_model`` call made in a script's ``__main__``, a test or a notebook is
therefore seen only by that process (and by workers forked from it): a plug-in model must
be registered by a module that every process imports. That is what the entry point group
:data:`ENTRY_POINT_GROUP` is for: an installed distribution declares, in its
``pyproject.toml``::

    [project.entry-points."simserver.tire_models"]
    my_tire = "my_package.my_tire:register"

and the package ``simserver.tires``, on import (so in every process, after the built-in
models), calls each such function with no argument (it calls ``register_tire_model``), in
the order of the entry point names, so that every process gives the same model the same
id. A plug-in that fails to load is an error naming it (``TirePluginError``), never
skipped (the ids of the others would shift).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import numpy as np
from numba.core.errors import NumbaExperimentalFeatureWarning

from simserver.adapters.validate import check_keys, number
from simserver.core.param_table import Param, ParamTable
from simserver.core.tire import N_BUILTIN_TIRE_MODELS, N_TIRE_PARAM, tire_forces
from simserver.core.tire_layout import (
    EVALUATE_SIGNATURE,
    N_TIRE_COEF,
    N_TIRE_OUT,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FX_PEAK,
    OUT_FY_PEAK,
    OUT_KAPPA_SLIDE,
    OUT_TAN_ALPHA_SLIDE,
    PREPARE_SIGNATURE,
    TP_MODEL,
    TP_MODEL_BASE,
    TireKernels,
)

# Tuples of first-class function pointers are what makes the kernels a cacheable argument
# of the compiled step; numba flags the feature as experimental on every such call.
warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning,
                        message="First-class function type feature is experimental")

N_MODEL_PARAM_MAX = N_TIRE_PARAM - TP_MODEL_BASE
"""Model-specific slots a tire vector has room for."""


ENTRY_POINT_GROUP = "simserver.tire_models"
"""The package entry point group of plug-in tire models (module docstring)."""


class UnknownTireModelError(ValueError):
    """A tire model name or id that the registry does not list."""


class TireWorkspaceError(ValueError):
    """A tire model that declares more coefficient or parameter slots than the step has."""


class TirePluginError(ImportError):
    """A plug-in tire model (an entry point of :data:`ENTRY_POINT_GROUP`) that failed."""


@dataclass(frozen=True)
class LoadedTire:
    """What a model's loader makes of a tire file."""

    model_params: np.ndarray  # the model-specific slots, tp[TP_MODEL_BASE:]
    rolling_radius_m: float
    relax_lat_m: float  # b, paper eq. 16
    relax_long_m: float  # B, paper eq. 26
    side: str | None = None  # "left"/"right": the side the tire was measured on; None: symmetric


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
    n_coef: int  # coefficient slots prepare writes and evaluate reads (<= N_TIRE_COEF)
    n_params: int  # model-specific slots from TP_MODEL_BASE (<= N_MODEL_PARAM_MAX)
    params: ParamTable | None = None  # the tire file's numeric keys (docs, validation)
    path_keys: tuple[tuple[str, str], ...] = ()  # (key, meaning) of its file-path keys


_REGISTRY: list[TireModel] = []
TIRE_MODEL_NAMES: dict[str, int] = {}
"""Name -> id of every registered model (kept up to date by ``register_tire_model``)."""


def _check_kernel(name: str, kernel: Any, signature: Any, what: str) -> None:
    sigs = getattr(kernel, "nopython_signatures", None)
    if not sigs or len(sigs) != 1 or sigs[0].args != signature.args:
        raise TypeError(f"tire model {name!r}: {what} must be compiled with exactly the "
                        f"signature {signature} (nb.njit({what.upper()}_SIGNATURE, ...))")


def _check_workspace(name: str, n_coef: Any, n_params: Any) -> None:
    """Refuse a declaration the compiled step has no room for (module docstring)."""
    for what, value, room, where in (
            ("coefficient slots (n_coef)", n_coef, N_TIRE_COEF,
             "core.tire_layout.N_TIRE_COEF, the step's stack scratch"),
            ("parameter slots (n_params)", n_params, N_MODEL_PARAM_MAX,
             "N_MODEL_PARAM_MAX, a tire vector's model-specific slots")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise TireWorkspaceError(f"tire model {name!r}: {what} must be an integer, got "
                                     f"{value!r}")
        if not 0 <= value <= room:
            raise TireWorkspaceError(f"tire model {name!r}: declares {value} {what}, but the "
                                     f"workspace holds 0 to {room} ({where})")


def register_tire_model(name: str, description: str, load: Callable[[Path, dict], LoadedTire],
                        prepare: Any, evaluate: Any,
                        nominal_load_n: Callable[[np.ndarray], float],
                        *, n_coef: int, n_params: int,
                        params: ParamTable | None = None,
                        path_keys: tuple[tuple[str, str], ...] = (),
                        _builtin: bool = False) -> TireModel:
    """Add a tire model; it gets the next id. Returns its entry.

    ``prepare`` and ``evaluate`` are ``numba.njit`` functions compiled with the explicit
    signatures ``PREPARE_SIGNATURE`` and ``EVALUATE_SIGNATURE`` (core.tire_layout); they
    receive the whole packed tire vector, their own slots from ``TP_MODEL_BASE`` on.
    ``n_coef`` is the number of ``coef`` slots they use (at most ``N_TIRE_COEF``),
    ``n_params`` the number of model-specific slots its loader packs (at most
    ``N_MODEL_PARAM_MAX``); more is refused (``TireWorkspaceError``): the step's scratch
    and the tire vector have no room for them, and nothing checks an index at run time.
    ``params`` (a ``ParamTable``) lists the tire file's numeric keys with units, ranges and
    meanings, ``path_keys`` its file-path keys: both go into docs/configuration.md, and
    ``read_tire_params`` validates a file against them. Where the call must live so that
    every process sees it: the module docstring.
    """
    if name in TIRE_MODEL_NAMES:
        raise ValueError(f"tire model {name!r} is already registered")
    _check_workspace(name, n_coef, n_params)
    if not _builtin:  # the built-in models' kernels compile on first use (module docstring)
        _check_kernel(name, prepare, PREPARE_SIGNATURE, "prepare")
        _check_kernel(name, evaluate, EVALUATE_SIGNATURE, "evaluate")
    entry = TireModel(id=len(_REGISTRY), name=name, description=description, load=load,
                      prepare=prepare, evaluate=evaluate, nominal_load_n=nominal_load_n,
                      n_coef=int(n_coef), n_params=int(n_params), params=params,
                      path_keys=path_keys)
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


# ------------------------------------------------------- what every model's tire file has
def relaxation_param(name: str, which: str, default: str | None) -> Param:
    """A relaxation-length row of a model's ``ParamTable`` (m, 0.005-5 m)."""
    return Param(name, "m", 0.005, 5.0, which, default=default)


RADIUS_MEANING = "effective rolling radius R"
RELAX_LAT_MEANING = "lateral relaxation length b (paper eq. 16)"
RELAX_LONG_MEANING = "longitudinal relaxation length B (paper eq. 26)"


def read_tire_params(path: Path, data: dict[str, Any], table: ParamTable,
                     path_keys: tuple[str, ...] = ()) -> dict[str, float]:
    """Validate a tire file's keys against its model's table: key -> number.

    ``model`` and the ``path_keys`` are allowed besides the table's keys (the path keys
    required). Every number is checked against its range, the error naming file and key.
    Optional keys absent from the file are absent from the result when their default is a
    text (a value the loader computes), else they take their default.
    """
    check_keys(path, data, ("model", *path_keys, *table.keys),
               required=("model", *path_keys, *table.required_keys))
    values: dict[str, float] = {}
    for param in table:
        key = param.yaml_key
        if key in data:
            values[key] = number(path, key, data[key], param.lo, param.hi)
        elif param.default is not None and not isinstance(param.default, str):
            values[key] = float(param.default)
    return values


def load_plugin_tire_models(group: str = ENTRY_POINT_GROUP) -> tuple[str, ...]:
    """Call every entry point of ``group``, in name order (each registers its model);
    returns their names. Run once when ``simserver.tires`` is imported (module docstring).

    Raises
    ------
    TirePluginError
        Naming the entry point (and its distribution) whose loading or call failed.
    """
    found = sorted(entry_points(group=group), key=lambda ep: ep.name)
    for ep in found:
        dist = getattr(ep.dist, "name", None) or "an unknown distribution"
        try:
            register = ep.load()
            if not callable(register):
                raise TypeError(f"{ep.value} is not callable")
            register()
        except Exception as exc:  # noqa: BLE001 - any failure of a plug-in is reported as one
            raise TirePluginError(f"tire model plug-in {ep.name!r} = {ep.value!r} (entry point "
                                  f"group {group!r}, from {dist}) failed: {exc}") from exc
    return tuple(ep.name for ep in found)
