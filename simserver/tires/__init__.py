"""Tire models: the registry (``registry``: ids, loaders, kernels, the one list of models)
and the built-in models beside it, each in one module with its tire-file keys, its loader
and its registration (``simple``: the brush tire; ``mf61``: Magic Formula 6.1 from a .tir
file); their compiled bodies are in the core (``core.tire_simple``, ``core.tire_mf61``).

Importing this package (which any import of its modules does first) registers the built-in
models in the order of their ids and then the plug-ins of the entry point group
``simserver.tire_models`` (``registry.ENTRY_POINT_GROUP``), so every process that reads a
vehicle or runs the step has the same registry with the same ids.
"""

from __future__ import annotations

from simserver.core.tire_layout import TIRE_MODEL_MF61, TIRE_MODEL_SIMPLE
from simserver.tires import mf61, simple
from simserver.tires.registry import N_BUILTIN_TIRE_MODELS, load_plugin_tire_models, tire_models

if (simple.register().id, mf61.register().id, len(tire_models())) != (
        TIRE_MODEL_SIMPLE, TIRE_MODEL_MF61, N_BUILTIN_TIRE_MODELS):
    raise ImportError("the built-in tire models must keep the ids of core.tire_layout")

PLUGINS: tuple[str, ...] = load_plugin_tire_models()
"""The entry points of :data:`registry.ENTRY_POINT_GROUP` this process loaded."""
