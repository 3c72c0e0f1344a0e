"""Parameter tables: one row per parameter, the single source of its name, unit, range, meaning.

A ``ParamTable`` is one configuration section (a vehicle subsystem file, the ``model:``
options, the scenario's ``road:``). Each ``Param`` row says what the key means, its unit,
the accepted range (or the named choices), its default (none: the key is required) and,
for parameters packed into a float64 vector for the compiled core, its slot there.

Pure Python (no numba, no numpy, no YAML): the core derives its slot constants from these
tables (``slot_constants_source``, checked by a test), the config adapter validates files
against them and generates ``docs/configuration.md`` from them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Param:
    """One parameter: a YAML key with its unit, accepted range and meaning.

    ``lo``/``hi`` bound a number (inclusive); ``choices`` maps the accepted names of a named
    choice to the number stored for it (then ``lo``/``hi`` stay None). A parameter with
    neither is *derived*: computed by the code, never read from a file. ``default`` None
    means the key is required; a text default on a numeric parameter describes a value the
    loader computes when the key is absent (e.g. "from the .tir file"). ``slot`` is the
    index in the packed vector the table belongs to; ``const`` names its slot constant when
    that is not ``prefix + NAME``. ``size`` > 1 makes the key a list (a curve's points, the
    gear ratios) of 1 .. ``size`` numbers, each within ``lo``/``hi``, packed into ``size``
    consecutive slots and padded with its last value (``pad_list``).
    """

    name: str
    unit: str
    lo: float | None
    hi: float | None
    meaning: str
    default: float | str | None = None
    choices: Mapping[str, int] | None = None
    slot: int | None = None
    const: str | None = None
    key: str | None = None  # the YAML key when it differs from the slot name
    size: int = 1  # > 1: a list of 1 .. size numbers in slots slot .. slot + size - 1

    @property
    def yaml_key(self) -> str:
        return self.key or self.name

    @property
    def derived(self) -> bool:
        return self.choices is None and self.lo is None

    @property
    def required(self) -> bool:
        return self.default is None and not self.derived

    def range_text(self) -> str:
        """The accepted values as printed in the docs."""
        if self.choices is not None:
            return ", ".join(f"`{name}`" for name in self.choices)
        if self.derived:
            return "derived"
        return f"{self.lo:g} .. {self.hi:g}"


@dataclass(frozen=True)
class ParamTable:
    """The parameters of one configuration section, in the order its docs list them."""

    name: str  # the section: a subsystem file key ("chassis"), "model", "road", ...
    title: str  # one line for the docs: what the section holds
    params: tuple[Param, ...]
    _by_name: dict[str, Param] = field(init=False, repr=False, compare=False)
    _by_key: dict[str, Param] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        by_name: dict[str, Param] = {}
        by_key: dict[str, Param] = {}
        for p in self.params:
            where = f"parameter table '{self.name}', '{p.name}'"
            if p.name in by_name or p.yaml_key in by_key:
                raise ValueError(f"{where}: listed twice")
            if not p.unit or not p.meaning:
                raise ValueError(f"{where}: needs a unit and a meaning")
            if p.choices is not None:
                if p.lo is not None or p.hi is not None or not p.choices:
                    raise ValueError(f"{where}: a named choice takes choices, not a range")
                if p.default is not None and p.default not in p.choices:
                    raise ValueError(f"{where}: default {p.default!r} is not a choice")
            elif (p.lo is None) != (p.hi is None):
                raise ValueError(f"{where}: give both ends of the range or neither")
            elif p.lo is not None:
                if not (math.isfinite(p.lo) and math.isfinite(p.hi) and p.lo <= p.hi):
                    raise ValueError(f"{where}: bad range [{p.lo}, {p.hi}]")
                # a text default names a value the loader computes (e.g. from a .tir file)
                if (p.default is not None and not isinstance(p.default, str)
                        and not p.lo <= p.default <= p.hi):
                    raise ValueError(f"{where}: default {p.default} outside its range")
            by_name[p.name] = p
            by_key[p.yaml_key] = p
        object.__setattr__(self, "_by_name", by_name)
        object.__setattr__(self, "_by_key", by_key)

    def __iter__(self) -> Iterator[Param]:
        return iter(self.params)

    def __len__(self) -> int:
        return len(self.params)

    def __getitem__(self, name: str) -> Param:
        return self._by_name[name]

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def by_key(self, key: str) -> Param:
        """The parameter read from YAML key ``key``."""
        return self._by_key[key]

    @property
    def keys(self) -> tuple[str, ...]:
        """The YAML keys a file of this section may hold (derived slots excluded)."""
        return tuple(p.yaml_key for p in self.params if not p.derived)

    @property
    def required_keys(self) -> tuple[str, ...]:
        return tuple(p.yaml_key for p in self.params if p.required)

    @property
    def defaults(self) -> dict[str, float | str]:
        """YAML key -> default of every optional key."""
        return {p.yaml_key: p.default for p in self.params if p.default is not None}


def pad_list(values: list[float], size: int) -> list[float]:
    """A list parameter's values padded to ``size`` with its last value."""
    return list(values) + [values[-1]] * (size - len(values))


def slot_layout(tables: tuple[ParamTable, ...]) -> tuple[Param, ...]:
    """Every parameter of ``tables`` in slot order; the slots (a list parameter takes
    ``size`` of them) must be exactly 0 .. n-1."""
    params = sorted((p for t in tables for p in t), key=lambda p: -1 if p.slot is None
                    else p.slot)
    slots = [p.slot + k if p.slot is not None else None for p in params for k in range(p.size)]
    if slots != list(range(len(slots))):
        raise ValueError(f"the slots of tables {[t.name for t in tables]} are not 0 .. "
                         f"{len(slots) - 1} each once: {slots}")
    return tuple(params)


def slot_count(params: tuple[Param, ...]) -> int:
    """How many slots ``params`` (from ``slot_layout``) take."""
    return sum(p.size for p in params)


def slot_const(param: Param, prefix: str) -> str:
    """The name of a parameter's slot constant, e.g. ``VP_MASS_KG``."""
    return param.const or prefix + param.name.upper()


def slot_constants_source(tables: tuple[ParamTable, ...], prefix: str) -> str:
    """The slot-constant assignments for ``tables``, one plain int per line.

    Numba reads module globals as compile-time constants, so the slots are written out as
    literal ints (a test checks this text against the module that holds them).
    """
    by_slot = {p.slot: (t, p) for t in tables for p in t}
    lines = []
    for param in slot_layout(tables):
        table, _ = by_slot[param.slot]
        size = f", {param.size} slots" if param.size > 1 else ""
        lines.append(f"{slot_const(param, prefix)} = {param.slot}  # {param.unit}, "
                     f"{table.name}{size}")
    return "\n".join(lines) + "\n"


GENERATED_BEGIN = "# --- generated slot constants"
GENERATED_END = "# --- end of generated slot constants"


def with_slot_constants(source: str, generated: str) -> str:
    """``source`` (a module's text) with its generated slot-constant block replaced."""
    lines = source.splitlines(keepends=True)
    starts = [i for i, line in enumerate(lines) if line.rstrip() == GENERATED_BEGIN]
    ends = [i for i, line in enumerate(lines) if line.rstrip() == GENERATED_END]
    if len(starts) != 1 or len(ends) != 1 or ends[0] < starts[0]:
        raise ValueError(f"expected one '{GENERATED_BEGIN}' ... '{GENERATED_END}' block")
    return "".join(lines[:starts[0] + 1]) + generated + "".join(lines[ends[0]:])
