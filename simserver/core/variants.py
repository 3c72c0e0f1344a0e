"""Registries of the model's selectable variants: one entry (id, name, meaning) each.

The slip and damping variants (``core.slip.SLIP_MODELS``, ``core.damping.DAMPING_MODELS``)
are chosen by name in a config file and by id in the parameter vector; a registry is the
one list of both, and an unknown name or id is an error (``UnknownVariantError``), never a
fallback to another variant.
"""

from __future__ import annotations

from dataclasses import dataclass


class UnknownVariantError(ValueError):
    """A variant name or id that its registry does not list."""


@dataclass(frozen=True)
class Variant:
    """One selectable variant of a part of the model."""

    id: int  # the value in the parameter vector
    name: str  # the value in config files
    meaning: str  # one line for the docs


class VariantRegistry:
    """The variants of one part of the model (``kind``), with dense ids 0, 1, ..."""

    def __init__(self, kind: str, variants: tuple[Variant, ...]) -> None:
        ids = [v.id for v in variants]
        if ids != list(range(len(variants))):
            raise ValueError(f"{kind}: ids must be 0 .. {len(variants) - 1} in order, got {ids}")
        if len({v.name for v in variants}) != len(variants):
            raise ValueError(f"{kind}: duplicate variant names")
        self.kind = kind
        self.variants = variants

    @property
    def names(self) -> dict[str, int]:
        """Name -> id, in id order."""
        return {v.name: v.id for v in self.variants}

    def by_name(self, name: str) -> Variant:
        """The variant called ``name``; ``UnknownVariantError`` names the known ones."""
        for v in self.variants:
            if v.name == name:
                return v
        raise UnknownVariantError(
            f"unknown {self.kind} {name!r} (known: {', '.join(self.names)})")

    def by_id(self, variant_id: float) -> Variant:
        """The variant with id ``variant_id`` (a parameter-vector value)."""
        if float(variant_id).is_integer() and 0 <= int(variant_id) < len(self.variants):
            return self.variants[int(variant_id)]
        raise UnknownVariantError(
            f"unknown {self.kind} id {float(variant_id):g} (known: "
            + ", ".join(f"{v.id} {v.name}" for v in self.variants) + ")")

    def __iter__(self):  # noqa: ANN204 - an iterator of Variant
        return iter(self.variants)
