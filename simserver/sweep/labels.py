"""Axis labels in words, with units, for a sweep's plots: a varied parameter's from the
parameter table that defines its key (the vehicle's subsystems, the tire models, the
road, the model options: the same rows ``docs/configuration.md`` is generated from), a
metric's from the metric registry (``sweep.metrics.METRIC_LABELS``) or, for a statistic of
a history column, from the history's column table (``adapters.history``).
"""

from __future__ import annotations

import functools
import re
import textwrap

from simserver.adapters.history import DIMENSIONLESS, column_description, column_unit

WRAP = 44
"""Characters a label's line holds before it wraps (a 6.5 in wide plot's axis)."""

_SECTION_TABLES = {"tires": "tires", "road": "road", "model": "model",
                   "initial": "initial"}
_INITIAL_WORDS = {"x_m": "initial position x", "y_m": "initial position y",
                  "yaw_rad": "initial heading", "u_mps": "initial speed",
                  "v_mps": "initial lateral speed", "yaw_rate_radps": "initial yaw rate"}


@functools.cache
def _tables() -> dict[str, dict[str, tuple[str, str]]]:
    """Every parameter table's rows as ``yaml key -> (meaning, unit)``, by section."""
    from simserver.core.params import MODEL_OPTIONS, ROAD, VEHICLE_PARAM_TABLES
    from simserver.tires.registry import tire_models

    def rows(*tables) -> dict[str, tuple[str, str]]:  # noqa: ANN002 - ParamTables
        return {p.yaml_key: (_words(p.meaning, p.name, p.unit), p.unit)
                for t in tables for p in t}

    tires = [m.params for m in tire_models() if m.params is not None]
    return {"vehicle": rows(*VEHICLE_PARAM_TABLES), "tires": rows(*tires),
            "road": rows(ROAD), "model": rows(MODEL_OPTIONS)}


def _words(meaning: str, name: str = "", unit: str = "-") -> str:
    """A parameter's meaning cut to its first clause (before a parenthesis, ';' or ':'),
    for an axis: 'longitudinal relaxation length B'; its name in words (the unit suffix
    dropped) when that clause names a key or runs long ('road grade')."""
    clause = re.split(r"\s*[(;:]", meaning, maxsplit=1)[0].strip() or meaning
    if name and ("_" in clause or len(clause) > 48):
        stem = name
        if unit not in ("-", DIMENSIONLESS):  # the name ends in its unit: _m, _pct, ...
            stem = re.sub(r"_[a-z0-9]+$", "", name)
        return stem.replace("_", " ")
    return clause


def _unit_text(unit: str) -> str:
    return "" if unit in ("-", "", DIMENSIONLESS) else f" ({unit})"


def parameter_label(path: str) -> str:
    """The axis label of a varied parameter's dotted path (``vehicle.tires.*.relaxation_
    length_long_m`` -> 'longitudinal relaxation length B, all tires (m)'); a key no table
    has is labelled by its words and the unit its name's suffix gives."""
    parts = path.split(".")
    key = parts[-1]
    where = ""
    section = "vehicle"
    if "tires" in parts[:-1]:
        section = "tires"
        which = parts[parts.index("tires") + 1] if parts.index("tires") + 1 < len(parts) - 1 \
            else "*"
        where = ", all tires" if which == "*" else f", {which} tires"
    elif parts[0] in _SECTION_TABLES:
        section = parts[0]
    if section == "initial":
        text = _INITIAL_WORDS.get(key, key.replace("_", " "))
        return _wrap(text + _unit_text(column_unit(key)))
    found = _tables().get(section, {}).get(key)
    if found is None:
        return _wrap(key.replace("_", " ") + where + _unit_text(column_unit(key)))
    words, unit = found
    return _wrap(words + where + _unit_text(unit))


def metric_label(column: str) -> str:
    """The axis label of a metric's column of the results table: its words from the
    metric registry, or for ``{min,max,final}_{history column}`` the statistic of the
    column's description; the unit from the name's suffix (as the history's)."""
    from simserver.sweep.metrics import METRIC_LABELS, STATS

    if column in METRIC_LABELS:
        return _wrap(METRIC_LABELS[column] + _unit_text(column_unit(column)))
    stat, _, name = column.partition("_")
    if stat in STATS and column_description(name) != "(undocumented)":
        words = {"min": "smallest", "max": "largest", "final": "final"}[stat]
        return _wrap(f"{words} {_words(column_description(name))}"
                     + _unit_text(column_unit(name)))
    return _wrap(column.replace("_", " ") + _unit_text(column_unit(column)))


def _wrap(text: str) -> str:
    return "\n".join(textwrap.wrap(text, WRAP)) or text
