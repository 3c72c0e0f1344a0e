"""benchmarks/bit_compare.py: the before/after digests see a one-ulp change and name the run."""

from __future__ import annotations

import json

import numpy as np

from benchmarks import bit_compare as B


def test_a_digest_sees_one_ulp_and_the_shape():
    a = np.linspace(0.0, 1.0, 12)
    b = a.copy()
    b[5] = np.nextafter(b[5], 2.0)
    assert B.digest(a) == B.digest(a.copy())
    assert B.digest(a) != B.digest(b)
    assert B.digest(a) != B.digest(a.reshape(3, 4))  # the same bytes, another shape


def test_compare_names_each_run_that_differs_or_is_missing():
    assert B.compare({"a": "1", "b": "2"}, {"a": "1", "b": "2"}) == []
    assert B.compare({"a": "1", "b": "2"}, {"a": "1", "b": "3", "c": "4"}) == ["b: differs"]
    # a run shipped after the reference is reported as new, not as a difference
    assert B.new_runs({"a": "1", "b": "2"}, {"a": "1", "b": "3", "c": "4"}) == ["c"]


def test_write_then_compare_the_replay(tmp_path, capsys):
    """The first-release replay written, compared (same bits: exit 0), then compared with a
    tampered reference (exit 1, the run named)."""
    ref = tmp_path / "digests.json"
    assert B.main(["--write", str(ref), "--only", "replay:"]) == 0
    written = json.loads(ref.read_text())
    assert list(written) == ["replay:first_release_live"]
    assert B.main(["--compare", str(ref), "--only", "replay:"]) == 0
    ref.write_text(json.dumps({"replay:first_release_live": "0" * 64}))
    assert B.main(["--compare", str(ref), "--only", "replay:"]) == 1
    assert "DIFFERS replay:first_release_live: differs" in capsys.readouterr().out
