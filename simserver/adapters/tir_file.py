"""Reader for MF-Tyre ``.tir`` tire property files, and their MF 6.1 coefficient set.

The format (MSC ADAMS "TeimOrbit" property files as written by MF-Tyre, MFeval, ...)::

    [SECTION]                     a section header
    KEY          = 1.234e+05      $ a number, with a trailing comment
    TYRESIDE     = 'Left'         ! a quoted string
    $------------------------     a comment line ($ or !)
    {pen  fz}                     a table header; the rows below it are numbers only
     0.0  0.0

Keys are case-insensitive and stored upper case. An unquoted value must be a number
(Fortran ``1.0D+03`` is accepted); ``nan`` and ``inf`` are rejected. A few metadata keys
(:data:`STRING_KEYS`) may also be bare words.

Every error is a :class:`TirError` whose message starts with ``<file>:<line>:`` and names
the key where one is involved.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from simserver.adapters.validate import ConfigError, read_config_bytes
from simserver.core.tire_mf61 import MF61_PARAM_NAMES

TirValue = float | str

# metadata keys that some writers leave unquoted (FILE_FORMAT = ASCII)
STRING_KEYS = frozenset(
    {
        "FILE_TYPE", "FILE_FORMAT", "TYRESIDE", "PROPERTY_FILE_FORMAT", "FUNCTION_NAME",
        "LENGTH", "FORCE", "ANGLE", "MASS", "TIME", "PRESSURE", "SPEED",
    }
)  # fmt: skip

# sections whose keys are not copied into the flat TirFile.values (MASS = 'kg' in [UNITS]
# would otherwise collide with MASS = 9.3 in [INERTIA])
FLAT_EXCLUDED_SECTIONS = frozenset({"UNITS"})

_SECTION_RE = re.compile(r"^\[\s*([A-Za-z0-9_ ]+?)\s*\]$")
_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_FORTRAN_EXP_RE = re.compile(r"^([+-]?(?:\d+\.?\d*|\.\d+))[dD]([+-]?\d+)$")


class TirError(ValueError):
    """A .tir file that cannot be read or does not hold what the model needs."""


@dataclass(frozen=True)
class TirFile:
    """Contents of a .tir property file.

    Attributes
    ----------
    path : Path
        The file read.
    sections : dict[str, dict[str, float | str]]
        ``sections["LATERAL_COEFFICIENTS"]["PKY1"] == -15.324``; names upper case.
    values : dict[str, float | str]
        Flat view of every key that is unambiguous across sections (same value wherever
        it occurs), except those of :data:`FLAT_EXCLUDED_SECTIONS`.
    lines : dict[str, int]
        Line number (1-based) of each key of ``values``, for error messages.
    tables : dict[str, list[tuple[float, ...]]]
        Numeric rows under a ``{col col}`` header, by section (``SHAPE``, ...).
    ambiguous : frozenset[str]
        Keys left out of ``values`` because sections disagree on their value.
    """

    path: Path
    sections: dict[str, dict[str, TirValue]]
    values: dict[str, TirValue]
    lines: dict[str, int] = field(default_factory=dict)
    tables: dict[str, list[tuple[float, ...]]] = field(default_factory=dict)
    ambiguous: frozenset[str] = frozenset()

    def where(self, key: str) -> str:
        """``"<path>:<line>"`` of ``key`` (or just the path if the key is absent)."""
        line = self.lines.get(key)
        return f"{self.path}:{line}" if line is not None else f"{self.path}"


def _strip_comment(text: str) -> str:
    """Drop a trailing ``$`` / ``!`` comment that is not inside quotes."""
    quote = ""
    for i, ch in enumerate(text):
        if quote:
            if ch == quote:
                quote = ""
        elif ch in "'\"":
            quote = ch
        elif ch in "$!":
            return text[:i]
    return text


def _parse_number(text: str) -> float | None:
    """``float`` of a numeric literal (Fortran ``D`` exponent allowed), else ``None``."""
    m = _FORTRAN_EXP_RE.match(text)
    if m:
        text = f"{m.group(1)}e{m.group(2)}"
    try:
        return float(text)
    except ValueError:
        return None


def _parse_value(raw: str, where: str, key: str) -> TirValue:
    value = _strip_comment(raw).strip()
    if not value:
        raise TirError(f"{where}: {key}: missing value")
    if value[0] in "'\"":
        quote = value[0]
        if len(value) < 2 or value[-1] != quote or quote in value[1:-1]:
            raise TirError(f"{where}: {key}: malformed quoted string {value!r}")
        text = value[1:-1]
        if key in MF61_PARAM_NAMES:
            raise TirError(f"{where}: {key}: non-numeric value {value!r} for a numeric key")
        return text
    number = _parse_number(value)
    if number is None:
        if key in STRING_KEYS:
            return value
        raise TirError(f"{where}: {key}: non-numeric value {value!r} (quote strings)")
    if not math.isfinite(number):
        raise TirError(f"{where}: {key}: value {value!r} is not finite")
    return number


def load_tir(path: str | Path) -> TirFile:
    """Read and check a .tir property file.

    Parameters
    ----------
    path : str or Path
        The file. UTF-8 is tried first, then Latin-1 (common in comments).

    Returns
    -------
    TirFile

    Raises
    ------
    TirError
        Unreadable file, a line that is neither a comment, a section header, a
        ``KEY = value`` pair nor a table row, a non-numeric value for a numeric key, a
        non-finite number, a key repeated within a section, a key before any section,
        or a file without any section.
    """
    path = Path(path)
    try:
        raw = read_config_bytes(path)  # a regular file of bounded size (docs/security.md)
    except ConfigError as exc:
        raise TirError(str(exc)) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")

    sections: dict[str, dict[str, TirValue]] = {}
    key_lines: dict[tuple[str, str], int] = {}
    tables: dict[str, list[tuple[float, ...]]] = {}
    section: str | None = None
    in_table = False

    for lineno, line in enumerate(text.splitlines(), start=1):
        where = f"{path}:{lineno}"
        stripped = line.strip()
        if not stripped or stripped[0] in "$!":
            continue
        if stripped.startswith("["):
            m = _SECTION_RE.match(_strip_comment(stripped).strip())
            if not m:
                raise TirError(f"{where}: malformed section header {stripped!r}")
            section = m.group(1).upper()
            if section in sections:
                raise TirError(f"{where}: section [{section}] appears twice")
            sections[section] = {}
            in_table = False
            continue
        if section is None:
            raise TirError(f"{where}: {stripped!r} before the first [SECTION]")
        if stripped.startswith("{"):
            if not _strip_comment(stripped).strip().endswith("}"):
                raise TirError(f"{where}: malformed table header {stripped!r}")
            tables.setdefault(section, [])
            in_table = True
            continue
        if "=" in stripped:
            key_text, _, value_text = stripped.partition("=")
            key = key_text.strip().upper()
            if not _KEY_RE.match(key):
                raise TirError(f"{where}: malformed key {key_text.strip()!r}")
            value = _parse_value(value_text, where, key)
            if key in sections[section]:
                first = key_lines[(section, key)]
                raise TirError(
                    f"{where}: {key}: duplicate key in [{section}] (first at line {first})"
                )
            sections[section][key] = value
            key_lines[(section, key)] = lineno
            in_table = False
            continue
        if in_table:
            tokens = _strip_comment(stripped).split()
            row = tuple(_parse_number(tok) for tok in tokens)
            if not row or any(v is None or not math.isfinite(v) for v in row):
                raise TirError(f"{where}: malformed table row {stripped!r} in [{section}]")
            tables[section].append(row)  # type: ignore[arg-type]
            continue
        raise TirError(f"{where}: malformed line {stripped!r} (expected KEY = value)")

    if not sections:
        raise TirError(f"{path}: no [SECTION] found: not a .tir property file")

    values: dict[str, TirValue] = {}
    lines: dict[str, int] = {}
    ambiguous: set[str] = set()
    for sec_name, entries in sections.items():
        if sec_name in FLAT_EXCLUDED_SECTIONS:
            continue
        for key, value in entries.items():
            if key in ambiguous:
                continue
            if key in values and values[key] != value:
                ambiguous.add(key)
                del values[key]
                del lines[key]
                continue
            if key not in values:
                values[key] = value
                lines[key] = key_lines[(sec_name, key)]
    return TirFile(
        path=path,
        sections=sections,
        values=values,
        lines=lines,
        tables=tables,
        ambiguous=frozenset(ambiguous),
    )


# --- MF 6.1 coefficient set ----------------------------------------------------------

#: FITTYP values accepted: 61 (MF 6.1) and 62 (MF 6.2, whose steady-state force and moment
#: equations are those of MF 6.1). 6 and 21 denote MF 5.x files, whose cornering stiffness
#: and camber equations differ: rejected.
MF61_FITTYPS = (61, 62)

#: Keys without which the MF 6.1 curves are undefined: the nominal load and radius, and
#: the base shape, peak, curvature and stiffness coefficient of each curve.
MF61_REQUIRED = (
    "FNOMIN", "UNLOADED_RADIUS",
    "PCX1", "PDX1", "PEX1", "PKX1", "RBX1", "RCX1",
    "PCY1", "PDY1", "PEY1", "PKY1", "PKY2", "RBY1", "RCY1",
    "QBZ1", "QCZ1", "QDZ1",
)  # fmt: skip

MF61_MAX_SCALING = 100.0
"""Largest scaling factor (``L*``): they scale a fitted tire, 1 is neutral."""
_SCALING = tuple(name for name in MF61_PARAM_NAMES if name.startswith("L") and name != "LONGVL")

#: Defaults of optional keys other than 0 (every other optional key defaults to 0:
#: variations with load, camber and pressure, shifts, combined-slip and aligning terms).
#: Entries that depend on FNOMIN or on other keys are filled in mf61_coefficients.
MF61_DEFAULTS: dict[str, float] = {
    **{name: 1.0 for name in _SCALING},  # scaling factors: neutral
    "PKY4": 2.0,  # MF 5.2's fixed factor in sin(2 atan(Fz / (PKY2 Fz0))), which PKY4 replaced
    "QSY7": 1.0,  # rolling resistance proportional to load, as in MF 5.2
    "LONGVL": 16.7,  # reference speed (60 km/h), only used if QSY3 / QSY4 are absent or 0
    "VXLOW": 1.0,  # speed below which the shifts fade out (MF-Tyre's default, m/s)
}

_POSITIVE = ("FNOMIN", "UNLOADED_RADIUS", "LFZO", "LMUX", "LMUY", "PCX1", "PCY1", "PKY2")

#: Physical ranges, inclusive, of the coefficients that have one (SI units): wide enough
#: for any real tire, narrow enough that the model stays finite (issue 14: FNOMIN = 1e-320
#: or LMUX = 1e300 made every state NaN). The nominal load and radius as the simple tire's
#: (``adapters/config.py``); pressures are 0 (pressure model off) or a tire's pressure.
MF61_RANGES: dict[str, tuple[float, float]] = {
    "FNOMIN": (10.0, 1e6),
    "UNLOADED_RADIUS": (0.05, 2.0),
    "LONGVL": (0.1, 1000.0),
    "FZMIN": (0.0, 1e7),
    "FZMAX": (0.0, 1e7),
    **{name: (0.0, MF61_MAX_SCALING) for name in _SCALING},
    "LFZO": (0.1, 10.0),  # the rated load scaled: F'z0 = LFZO FNOMIN (4.E1)
}
MF61_PRESSURE_RANGE_PA = (1e3, 1e8)
"""``NOMPRES`` and ``INFLPRES`` when not 0: 10 mbar to 1000 bar."""
MF61_MAX_ABS = 1e4
"""Largest magnitude of every other coefficient (the shape, peak, stiffness, curvature and
shift coefficients of real files are below 200)."""
MF61_MAX_EXPONENT = 700.0
"""Largest argument of ``exp`` and ``log`` of ``pow`` over the clamped load range (e^709 is
the largest double): bounds ``PKX3 dfz`` (4.E15) and ``QSY7 ln(Fz / FNOMIN)`` (4.E70)."""


def mf61_coefficients(tir: TirFile) -> dict[str, float]:
    """Check that ``tir`` is an MF 6.1 file and return every MF 6.1 coefficient.

    Parameters
    ----------
    tir : TirFile
        As returned by :func:`load_tir`.

    Returns
    -------
    dict[str, float]
        One entry per name of :data:`simserver.core.tire_mf61.MF61_PARAM_NAMES`.
        Optional keys absent from the file take their documented default: scaling
        factors 1; ``PKY4`` 2; ``QSY7`` 1; ``LONGVL`` 16.7 m/s; ``NOMPRES`` 0 (pressure
        model off) and ``INFLPRES`` = ``NOMPRES``; ``FZMIN`` 0 (the kernel floors it at
        1 % of ``FNOMIN``); ``FZMAX`` 3 ``FNOMIN``; everything else 0.

    Raises
    ------
    TirError
        ``FITTYP`` absent or not in :data:`MF61_FITTYPS`; a required key absent (all are
        named); a coefficient that is a string or ambiguous across sections; ``LONGVL``
        absent while ``QSY3`` or ``QSY4`` is non-zero; a value out of its valid range
        (non-positive load, radius, friction scale, shape factor or ``PKY2``;
        ``FZMAX <= FZMIN``; negative pressure); a subnormal coefficient or one outside
        its physical range (:data:`MF61_RANGES`, :data:`MF61_MAX_ABS`); ``PKX3`` or
        ``QSY7`` overflowing over the load range (:data:`MF61_MAX_EXPONENT`).
    """
    values = tir.values

    def number(key: str) -> float | None:
        if key in tir.ambiguous:
            raise TirError(f"{tir.path}: {key}: appears in several sections with different values")
        if key not in values:
            return None
        value = values[key]
        if isinstance(value, str):
            raise TirError(f"{tir.where(key)}: {key}: non-numeric value {value!r}")
        return value

    fittyp = number("FITTYP")
    if fittyp is None:
        raise TirError(f"{tir.path}: missing required key FITTYP (expected 61 or 62)")
    if fittyp not in MF61_FITTYPS:
        raise TirError(
            f"{tir.where('FITTYP')}: FITTYP = {fittyp:g}: not an MF 6.1 file "
            f"(accepted: {', '.join(str(f) for f in MF61_FITTYPS)})"
        )

    missing = [key for key in MF61_REQUIRED if number(key) is None]
    if missing:
        raise TirError(f"{tir.path}: missing required MF 6.1 key(s): {', '.join(missing)}")

    coeffs: dict[str, float] = {}
    for key in MF61_PARAM_NAMES:
        value = number(key)
        coeffs[key] = MF61_DEFAULTS.get(key, 0.0) if value is None else value

    fnomin = coeffs["FNOMIN"]
    if number("FZMAX") is None:
        coeffs["FZMAX"] = 3.0 * fnomin
    if number("INFLPRES") is None:
        coeffs["INFLPRES"] = coeffs["NOMPRES"]
    if number("LONGVL") is None and (coeffs["QSY3"] != 0.0 or coeffs["QSY4"] != 0.0):
        raise TirError(f"{tir.path}: missing key LONGVL (needed by QSY3 / QSY4)")

    _check_ranges(tir, coeffs)
    for key in _POSITIVE:
        if not coeffs[key] > 0.0:
            raise TirError(f"{tir.where(key)}: {key} = {coeffs[key]:g}: must be > 0")
    if coeffs["LONGVL"] <= 0.0:
        raise TirError(f"{tir.where('LONGVL')}: LONGVL = {coeffs['LONGVL']:g}: must be > 0")
    if coeffs["FZMIN"] < 0.0 or coeffs["FZMAX"] <= coeffs["FZMIN"]:
        raise TirError(
            f"{tir.where('FZMAX')}: FZMIN = {coeffs['FZMIN']:g}, FZMAX = {coeffs['FZMAX']:g}:"
            " need 0 <= FZMIN < FZMAX"
        )
    for key in ("NOMPRES", "INFLPRES"):
        if coeffs[key] < 0.0:
            raise TirError(f"{tir.where(key)}: {key} = {coeffs[key]:g}: must be >= 0")
    if coeffs["NOMPRES"] > 0.0 and coeffs["INFLPRES"] <= 0.0:
        raise TirError(f"{tir.where('INFLPRES')}: INFLPRES must be > 0 when NOMPRES is given")
    if coeffs["FZMAX"] > 100.0 * fnomin:
        raise TirError(f"{tir.where('FZMAX')}: FZMAX = {coeffs['FZMAX']:g}: must be at most "
                       "100 FNOMIN")
    _check_exponents(tir, coeffs)
    return coeffs


def _check_ranges(tir: TirFile, coeffs: dict[str, float]) -> None:
    """Every coefficient normal (or 0) and within its range (:data:`MF61_RANGES`)."""
    for key, value in coeffs.items():
        if value != 0.0 and abs(value) < sys.float_info.min:
            raise TirError(f"{tir.where(key)}: {key} = {value:g}: subnormal (use 0 or a "
                           "normal number)")
        if key in ("NOMPRES", "INFLPRES"):
            lo, hi = MF61_PRESSURE_RANGE_PA
            if value != 0.0 and not lo <= value <= hi:
                raise TirError(f"{tir.where(key)}: {key} = {value:g}: must be 0 or in "
                               f"[{lo:g}, {hi:g}] Pa")
            continue
        lo, hi = MF61_RANGES.get(key, (-MF61_MAX_ABS, MF61_MAX_ABS))
        if not lo <= value <= hi:
            raise TirError(f"{tir.where(key)}: {key} = {value:g}: outside [{lo:g}, {hi:g}]")


def _check_exponents(tir: TirFile, coeffs: dict[str, float]) -> None:
    """``exp(PKX3 dfz)`` and ``(Fz / FNOMIN)^QSY7`` finite over the loads the kernel uses
    (``Fz`` clamped to ``[max(FZMIN, 0.01 FNOMIN), FZMAX]``, ``core/tire_mf61.py``)."""
    fnomin = coeffs["FNOMIN"]
    fz0 = fnomin * coeffs["LFZO"]
    fz_lo = max(coeffs["FZMIN"], 0.01 * fnomin)
    fz_hi = max(coeffs["FZMAX"], fz_lo)
    for key, args in (("PKX3", [(fz - fz0) / fz0 for fz in (fz_lo, fz_hi)]),
                      ("QSY7", [math.log(fz / fnomin) for fz in (fz_lo, fz_hi)])):
        worst = max(abs(coeffs[key] * a) for a in args)
        if worst > MF61_MAX_EXPONENT:
            raise TirError(f"{tir.where(key)}: {key} = {coeffs[key]:g}: overflows over the "
                           f"load range FZMIN..FZMAX (exponent {worst:.3g} > "
                           f"{MF61_MAX_EXPONENT:g})")
