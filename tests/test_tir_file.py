"""Tests of the .tir reader and of the MF 6.1 coefficient check.

Broken variants of the real sample file are written into ``tmp_path``; every rejection
must name the file and, where one is involved, the line and the key.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import pytest

from simserver.adapters.tir_file import (
    MF61_DEFAULTS,
    MF61_REQUIRED,
    TirError,
    load_tir,
    mf61_coefficients,
)
from simserver.core.tire_mf61 import MF61_PARAM_NAMES
from tests.conftest import SAMPLE_TIR

SAMPLE = SAMPLE_TIR
SAMPLE_TEXT = SAMPLE.read_text().rstrip("\n") + "\n"


def _line_of(key: str) -> int:
    """1-based line number of ``key`` in the sample (first match)."""
    for i, line in enumerate(SAMPLE_TEXT.splitlines(), start=1):
        if re.match(rf"\s*{key}\s*=", line):
            return i
    raise AssertionError(key)


def _variant(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _replace_line(key: str, new_line: str | None) -> str:
    """The sample with the line of ``key`` replaced (or removed if ``new_line`` is None)."""
    lines = SAMPLE_TEXT.splitlines()
    idx = _line_of(key) - 1
    if new_line is None:
        del lines[idx]
    else:
        lines[idx] = new_line
    return "\n".join(lines) + "\n"


# --- the sample, unchanged -------------------------------------------------------------


def test_sample_loads_unchanged() -> None:
    tir = load_tir(SAMPLE)
    assert tir.path == SAMPLE
    assert list(tir.sections)[:3] == ["MDI_HEADER", "UNITS", "MODEL"]
    assert tir.sections["LATERAL_COEFFICIENTS"]["PKY1"] == -15.324
    assert tir.values["PKY1"] == -15.324
    assert tir.values["FITTYP"] == 61.0
    assert tir.values["FILE_VERSION"] == 3.0
    assert tir.values["FILE_TYPE"] == "tir"
    assert tir.values["TYRESIDE"] == "Left"
    assert tir.values["USE_MODE"] == 14.0  # trailing "$Tyre use switch" stripped
    assert tir.values["BOTTOM_STIFF"] == 3.0e6
    # [UNITS] MASS = 'kg' stays in its section; the flat view has the tyre mass
    assert tir.sections["UNITS"]["MASS"] == "kg"
    assert tir.values["MASS"] == 9.3
    assert tir.ambiguous == frozenset()
    assert tir.lines["PKY1"] == _line_of("PKY1")
    assert tir.where("PKY1") == f"{SAMPLE}:{_line_of('PKY1')}"


def test_sample_coefficients_complete() -> None:
    coeffs = mf61_coefficients(load_tir(SAMPLE))
    assert set(coeffs) == set(MF61_PARAM_NAMES)
    assert coeffs["PKY1"] == -15.324
    assert coeffs["FNOMIN"] == 4000.0
    assert coeffs["INFLPRES"] == coeffs["NOMPRES"] == 200000.0
    assert all(isinstance(v, float) for v in coeffs.values())


def test_required_and_defaults_are_model_keys() -> None:
    """Required keys and non-zero defaults refer to packed parameters, and never overlap."""
    assert set(MF61_REQUIRED) <= set(MF61_PARAM_NAMES)
    assert set(MF61_DEFAULTS) <= set(MF61_PARAM_NAMES)
    assert not set(MF61_REQUIRED) & set(MF61_DEFAULTS)


def test_optional_keys_take_documented_defaults(tmp_path: Path) -> None:
    text = SAMPLE_TEXT
    for key in ("LKY", "PKY4", "QSY7", "PPX1", "RVY6", "FZMIN", "FZMAX", "INFLPRES"):
        text = "\n".join(line for line in text.splitlines() if not re.match(rf"\s*{key}\s*=", line))
    coeffs = mf61_coefficients(load_tir(_variant(tmp_path, "optional.tir", text)))
    assert coeffs["LKY"] == 1.0  # scaling factor
    assert coeffs["PKY4"] == 2.0  # MF 5.2's fixed factor
    assert coeffs["QSY7"] == 1.0  # rolling resistance proportional to load
    assert coeffs["PPX1"] == 0.0  # pressure coefficient
    assert coeffs["RVY6"] == 0.0  # combined-slip coefficient
    assert coeffs["FZMIN"] == 0.0
    assert coeffs["FZMAX"] == 3.0 * coeffs["FNOMIN"]
    assert coeffs["INFLPRES"] == coeffs["NOMPRES"]


def test_fittyp_62_is_accepted(tmp_path: Path) -> None:
    path = _variant(tmp_path, "mf62.tir", _replace_line("FITTYP", "FITTYP = 62"))
    assert mf61_coefficients(load_tir(path))["PKY1"] == -15.324


# --- syntax -------------------------------------------------------------------------------


def test_syntax_variants(tmp_path: Path) -> None:
    text = (
        "[Model]\n"
        "fittyp = 61 ! lower-case key, '!' comment\n"
        "   FILE_FORMAT = ASCII\n"
        "TYRESIDE = 'Le$ft' $ a '$' inside quotes is not a comment\n"
        '\tNAME = "double quoted"\n'
        "[VERTICAL]\n"
        "FNOMIN = 4.0D+03\n"
        "X1 = -.5e-1\n"
        "$ comment line\n"
        "! another comment line\n"
        "\n"
        "[SHAPE]\n"
        "{radial width}\n"
        " 1.0  0.0\n"
        " 0.9  0.4  $ row comment\n"
        "[NEXT]\n"
        "Y = +3\n"
    )
    tir = load_tir(_variant(tmp_path, "syntax.tir", text))
    assert tir.sections["MODEL"]["FITTYP"] == 61.0
    assert tir.values["FILE_FORMAT"] == "ASCII"
    assert tir.values["TYRESIDE"] == "Le$ft"
    assert tir.values["NAME"] == "double quoted"
    assert tir.values["FNOMIN"] == 4000.0
    assert tir.values["X1"] == -0.05
    assert tir.values["Y"] == 3.0
    assert tir.tables["SHAPE"] == [(1.0, 0.0), (0.9, 0.4)]


def test_latin1_comment_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "latin1.tir"
    path.write_bytes(b"[VERTICAL]\nFNOMIN = 4000 $ Nennlast \xb5 \xe4\n")
    assert load_tir(path).values["FNOMIN"] == 4000.0


def test_key_ambiguous_across_sections(tmp_path: Path) -> None:
    text = SAMPLE_TEXT + "[EXTRA]\nPKY1 = -12.0\n"
    path = _variant(tmp_path, "ambiguous.tir", text)
    tir = load_tir(path)
    assert "PKY1" in tir.ambiguous and "PKY1" not in tir.values
    with pytest.raises(TirError, match=rf"{re.escape(str(path))}.*PKY1"):
        mf61_coefficients(tir)


# --- rejected files: the message names the file, the line and the key -----------------------


def _assert_error(exc: pytest.ExceptionInfo[TirError], path: Path, *parts: str) -> None:
    msg = str(exc.value)
    assert str(path) in msg, msg
    for part in parts:
        assert part in msg, (part, msg)


def test_unreadable_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.tir"
    with pytest.raises(TirError) as exc:
        load_tir(missing)
    _assert_error(exc, missing, "cannot read")
    with pytest.raises(TirError) as exc:
        load_tir(tmp_path)  # a directory
    _assert_error(exc, tmp_path, "cannot read")


def test_missing_required_key(tmp_path: Path) -> None:
    path = _variant(tmp_path, "no_pky1.tir", _replace_line("PKY1", None))
    tir = load_tir(path)  # syntactically fine
    with pytest.raises(TirError) as exc:
        mf61_coefficients(tir)
    _assert_error(exc, path, "PKY1", "missing")


def test_all_missing_required_keys_are_named(tmp_path: Path) -> None:
    text = _replace_line("PKY1", None)
    text = "\n".join(line for line in text.splitlines() if not re.match(r"\s*QCZ1\s*=", line))
    path = _variant(tmp_path, "no_two.tir", text)
    with pytest.raises(TirError) as exc:
        mf61_coefficients(load_tir(path))
    _assert_error(exc, path, "PKY1", "QCZ1")


@pytest.mark.parametrize(
    ("key", "line", "expect"),
    [
        ("PKY1", "PKY1 = abc", "non-numeric"),
        ("PKY1", "PKY1 = -15.324 N", "non-numeric"),
        ("PKY1", "PKY1 = '-15.324'", "non-numeric"),
        ("PDX1", "PDX1 = nan", "not finite"),
        ("PDX1", "PDX1 = NaN $ comment", "not finite"),
        ("PDX1", "PDX1 = inf", "not finite"),
        ("PDX1", "PDX1 = -Infinity", "not finite"),
        ("PDX1", "PDX1 = 1e999", "not finite"),
        ("PDX1", "PDX1 =", "missing value"),
        ("PDX1", "PDX1 = $ only a comment", "missing value"),
        ("TYRESIDE", "TYRESIDE = 'Left", "quoted"),
    ],
)
def test_bad_value(tmp_path: Path, key: str, line: str, expect: str) -> None:
    path = _variant(tmp_path, "bad_value.tir", _replace_line(key, line))
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, f":{_line_of(key)}:", key, expect)


@pytest.mark.parametrize(
    "line",
    [
        "PKY1 -15.324",  # no '='
        "PKY1: -15.324",
        "[LATERAL_COEFFICIENTS",  # unterminated header
        "1PKY = 3",  # key must start with a letter
        "P KY1 = 3",
    ],
)
def test_malformed_line(tmp_path: Path, line: str) -> None:
    path = _variant(tmp_path, "malformed.tir", _replace_line("PKY1", line))
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, f":{_line_of('PKY1')}:", "malformed")


def test_malformed_line_names_its_key(tmp_path: Path) -> None:
    path = _variant(tmp_path, "malformed_key.tir", _replace_line("PKY1", "PKY1 -15.324"))
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, "PKY1 -15.324")


def test_duplicate_key_in_section(tmp_path: Path) -> None:
    lines = SAMPLE_TEXT.splitlines()
    first = _line_of("PKY2")
    lines.insert(first, "pky2 = 1.8")  # right after PKY2, same section, other case
    path = _variant(tmp_path, "dup.tir", "\n".join(lines) + "\n")
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, f":{first + 1}:", "PKY2", "duplicate", f"line {first}")


def test_key_before_any_section(tmp_path: Path) -> None:
    path = _variant(tmp_path, "nosection.tir", "FNOMIN = 4000\n" + SAMPLE_TEXT)
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, ":1:", "FNOMIN")


def test_bad_table_row(tmp_path: Path) -> None:
    path = _variant(tmp_path, "table.tir", SAMPLE_TEXT + "[SHAPE]\n{radial width}\n 1.0 x\n")
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, f":{len(SAMPLE_TEXT.splitlines()) + 3}:", "table row")


def test_empty_file(tmp_path: Path) -> None:
    path = _variant(tmp_path, "empty.tir", "$ nothing here\n")
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, "no [SECTION]")


@pytest.mark.parametrize("fittyp", ["6", "21", "52", "'61'"])
def test_wrong_fittyp(tmp_path: Path, fittyp: str) -> None:
    path = _variant(tmp_path, "fittyp.tir", _replace_line("FITTYP", f"FITTYP = {fittyp}"))
    with pytest.raises(TirError) as exc:
        mf61_coefficients(load_tir(path))
    _assert_error(exc, path, "FITTYP")


def test_missing_fittyp(tmp_path: Path) -> None:
    path = _variant(tmp_path, "nofittyp.tir", _replace_line("FITTYP", None))
    with pytest.raises(TirError) as exc:
        mf61_coefficients(load_tir(path))
    _assert_error(exc, path, "FITTYP", "missing")


@pytest.mark.parametrize(
    ("key", "line"),
    [
        ("PKY2", "PKY2 = 0"),
        ("FNOMIN", "FNOMIN = -4000"),
        ("UNLOADED_RADIUS", "UNLOADED_RADIUS = 0"),
        ("LMUY", "LMUY = 0"),
        ("PCX1", "PCX1 = -1.5"),
        ("NOMPRES", "NOMPRES = -1"),
        # issue 14: accepted before, and every state of a run with them was NaN
        ("FNOMIN", "FNOMIN = 1e-320"),
        ("NOMPRES", "NOMPRES = 1e-320"),
        ("LMUX", "LMUX = 1e300"),
        ("NOMPRES", "NOMPRES = 1e-300"),
        ("FNOMIN", "FNOMIN = 1e-300"),
        ("PDX1", "PDX1 = 1e300"),
        ("QBZ1", "QBZ1 = 1e-310"),
        ("UNLOADED_RADIUS", "UNLOADED_RADIUS = 1e5"),
        ("LFZO", "LFZO = 1e-200"),
        ("FZMAX", "FZMAX = 1e9"),
        ("PKX3", "PKX3 = 500"),
    ],
)
def test_out_of_range_value(tmp_path: Path, key: str, line: str) -> None:
    path = _variant(tmp_path, "range.tir", _replace_line(key, line))
    with pytest.raises(TirError) as exc:
        mf61_coefficients(load_tir(path))
    _assert_error(exc, path, key, f":{_line_of(key)}")


def test_fz_range_inverted(tmp_path: Path) -> None:
    path = _variant(tmp_path, "fzrange.tir", _replace_line("FZMAX", "FZMAX = 50"))
    with pytest.raises(TirError) as exc:
        mf61_coefficients(load_tir(path))
    _assert_error(exc, path, "FZMIN", "FZMAX")


def test_longvl_needed_by_speed_terms(tmp_path: Path) -> None:
    path = _variant(tmp_path, "nolongvl.tir", _replace_line("LONGVL", None))
    with pytest.raises(TirError) as exc:
        mf61_coefficients(load_tir(path))
    _assert_error(exc, path, "LONGVL")
    # without speed terms LONGVL is not needed
    text = _replace_line("LONGVL", None)
    text = re.sub(r"(?m)^QSY3\s*=.*$", "QSY3 = 0", text)
    text = re.sub(r"(?m)^QSY4\s*=.*$", "QSY4 = 0", text)
    coeffs = mf61_coefficients(load_tir(_variant(tmp_path, "nolongvl_ok.tir", text)))
    assert coeffs["LONGVL"] == MF61_DEFAULTS["LONGVL"]


def test_string_for_coefficient_in_flat_view(tmp_path: Path) -> None:
    """A coefficient given as a bare word of STRING_KEYS style is caught by the check."""
    path = _variant(tmp_path, "strcoef.tir", _replace_line("QSY1", "QSY1 = 'abc'"))
    with pytest.raises(TirError) as exc:
        load_tir(path)
    _assert_error(exc, path, "QSY1", f":{_line_of('QSY1')}:")


SAMPLE_TIR_SHA256 = "4ac343c7ff09675cbaa5bc1f013b0cb72c5f522833927332a167a066c7bab208"
"""Digest of the third-party sample file as published (taken when it was added)."""


def test_the_shipped_sample_is_the_reference_file_unchanged():
    """The repository's copy is the third-party file byte for byte (loaded unchanged)."""
    assert hashlib.sha256(SAMPLE_TIR.read_bytes()).hexdigest() == SAMPLE_TIR_SHA256


@pytest.mark.parametrize("line", ["FNOMIN = 1e-320", "NOMPRES = 1e-320", "LMUX = 1e300"])
def test_a_tire_that_would_run_non_finite_is_refused_headless(tmp_path: Path, line: str):
    """Issue 14 item 3 headless: such a .tir made `simserver run` produce NaN states."""
    from simserver.adapters.config import ConfigError, load_tire

    key = line.split()[0]
    tir = _variant(tmp_path, "bad.tir", _replace_line(key, line))
    tire = tmp_path / "tire.yaml"
    tire.write_text(f"model: mf61\ntir_file: {tir.name}\n")
    with pytest.raises(ConfigError, match=rf"{tire}: key 'tir_file': .*{key}"):
        load_tire(tire)
