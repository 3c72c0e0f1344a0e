"""Issue 34 item 7: sweep specs and client profiles held to the rules of scenes.

Each case runs the real command line as a subprocess (``simserver sweep``,
``simserver-driver``) and reads its stderr: one ``error:`` line naming the file and the
key, no traceback, exit code 2; and its peak resident memory (``os.wait4`` of that child,
``tests/measure.py``) stays under ``PEAK_MB`` while it refuses: sizes are
capped before anything is built or read, so the refusal costs what the imports cost (the
sweep's 150 MB are numpy, numba and pyarrow; the driver's about 60 MB).

Before the fixes: the grid and ``num`` cases died with a MemoryError traceback (a list of
10^12 parameter sets; a 7 TiB ``linspace``), the 4 GiB override was read whole (MemoryError
under the 4 GiB address-space guard), a sweep naming a scenario outside the project ran it
and wrote that file's key names into its results; the profiles gave RecursionError,
ValueError, OverflowError and UnicodeDecodeError tracebacks, read ``/dev/zero`` until the
guard stopped them, waited on the FIFO until killed, and took a 1 MiB profile.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import yaml
from measure import run_measured

from simserver.testing import CONFIGS, REPO, client_command, client_env

PEAK_MB = 200.0
E2 = CONFIGS / "scenarios" / "e2_stop_downslope_paper_damping.yaml"


def check_refused(run, file: Path, needles: tuple[str, ...], prog: str) -> None:
    """One error line naming ``file`` and each of ``needles``; exit 2; under PEAK_MB."""
    assert run.returncode == 2, (run.returncode, run.stderr[-2000:])
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert lines[0].startswith(f"{prog}error: ") and file.name in lines[0], lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert run.peak_rss_mb < PEAK_MB, f"peak {run.peak_rss_mb:.0f} MB while refusing"


# ----------------------------------------------------------------------------- sweeps
def sweep_cli(path: Path, out: Path):
    return run_measured([sys.executable, "-m", "simserver", "sweep", str(path), "--out",
                         str(out), "--quiet", "--no-plots"], timeout_s=180.0, cwd=REPO)


def write(path: Path, body: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(body))
    return path


@pytest.mark.parametrize("grid, key", [
    # 10^12 parameter sets: counted, not built (was a list built to 2.6 GB, then MemoryError)
    ({"road.grade_pct": {"from": -5.0, "to": 5.0, "num": 1_000_000},
      "road.friction_scale": {"from": 0.3, "to": 1.0, "num": 1_000_000}}, "'grid'"),
    # num: 10^12 (a 7 TiB linspace)
    ({"road.grade_pct": {"from": -5.0, "to": 5.0, "num": 10**12}},
     "'grid.road.grade_pct.num'"),
])
def test_a_huge_sweep_is_refused_before_it_is_built(tmp_path, grid, key):
    path = write(tmp_path / "huge.yaml", {"scenarios": [str(E2)], "grid": grid,
                                          "metrics": ["stopping_distance"]})
    run = sweep_cli(path, tmp_path / "out")
    check_refused(run, path, (key, "1000000"), "")
    assert not (tmp_path / "out").exists()


def test_a_file_override_too_large_to_hash_is_refused_unread(tmp_path):
    """A ``file`` override is hashed into the run id: a 4 GiB file is refused by its size
    (a sparse file: nothing of it is ever in memory unless read)."""
    flat = tmp_path / "flat.npy"
    import numpy as np

    np.save(flat, np.zeros((8, 8)))
    scenario = yaml.safe_load(E2.read_text())
    scenario["vehicle"] = str((E2.parent / scenario["vehicle"]).resolve())
    scenario["terrain"] = {"kind": "heightmap", "file": "flat.npy", "cell_m": 1.0}
    write(tmp_path / "base.yaml", scenario)
    huge = tmp_path / "huge.npy"
    with open(huge, "wb") as f:
        f.truncate((4 << 30) + 1)
    path = write(tmp_path / "override.yaml", {
        "scenarios": ["base.yaml"], "grid": {"terrain.file": [str(flat), str(huge)]},
        "metrics": ["stopping_distance"]})
    run = sweep_cli(path, tmp_path / "out")
    check_refused(run, path, ("parameter 'terrain.file'", "huge.npy", str((4 << 30) + 1)), "")


def test_a_sweep_cannot_read_or_quote_a_file_outside_its_folders(tmp_path):
    """The base scenario lies outside the project's configs/ and the sweep's folder: refused
    by its path, never opened (was: read, and its key names quoted in the error)."""
    secret = write(tmp_path / "elsewhere" / "secret.yaml", {"secret_token_xyz": 1})
    path = write(tmp_path / "sweeps" / "outside.yaml", {
        "scenarios": [f"../elsewhere/{secret.name}"], "metrics": ["stopping_distance"]})
    run = sweep_cli(path, tmp_path / "out")
    check_refused(run, path, ("key 'scenarios'", "outside the config directories"), "")
    assert "secret_token_xyz" not in run.stdout + run.stderr
    assert not (tmp_path / "out").exists()
    # a scenario there runs once its folder is configured
    scenario = yaml.safe_load(E2.read_text())
    scenario["vehicle"] = str((E2.parent / scenario["vehicle"]).resolve())
    write(tmp_path / "elsewhere" / "base.yaml", scenario)
    path = write(tmp_path / "sweeps" / "allowed.yaml", {
        "scenarios": ["../elsewhere/base.yaml"], "metrics": ["stopping_distance"]})
    run = run_measured([sys.executable, "-m", "simserver", "sweep", str(path), "--out",
                        str(tmp_path / "out"), "--quiet", "--no-plots", "--workers", "1",
                        "--config-dir", str(tmp_path / "elsewhere"), "--config-dir",
                        str(CONFIGS)], timeout_s=300.0, cwd=REPO)
    assert run.returncode == 0 and "1 runs (0 failed" in run.stdout, run.stderr[-2000:]


# ----------------------------------------------------------------------------- profiles
GAMEPAD = (CONFIGS / "clients" / "gamepad.yaml").read_text()


def profile_cases(tmp_path: Path) -> list[tuple[str, Path, tuple[str, ...]]]:
    """(name, profile file, what its error says)."""
    def file(name: str, data: bytes) -> Path:
        path = tmp_path / name
        path.write_bytes(data)
        return path

    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    return [
        ("deep", file("deep.yaml", b"kind: joystick\nsteer: " + b"[" * 100_000
                      + b"]" * 100_000 + b"\n"), ("nested deeper than 64", "line 2")),
        ("5000 digits", file("digits.yaml", GAMEPAD.replace(
            "dead_zone: 0.08", "dead_zone: " + "9" * 5000).encode()),
         ("integer of 5000 characters", "line")),
        ("400 digits", file("big.yaml", GAMEPAD.replace(
            "dead_zone: 0.08", "dead_zone: " + "9" * 400).encode()),
         ("key 'steer.dead_zone'", "expected a number")),
        ("not UTF-8", file("latin1.yaml", GAMEPAD.replace(
            'name_contains: ""', 'name_contains: "\xe9"').encode("latin-1")),
         ("not UTF-8",)),
        ("/dev/zero", Path("/dev/zero"), ("not a regular file",)),
        ("FIFO", fifo, ("not a regular file",)),
        ("1 MiB", file("padded.yaml", b"#" * (1 << 20) + b"\n" + GAMEPAD.encode()),
         ("larger than 262144 bytes",)),
    ]


def test_hostile_profiles_get_one_line_errors_and_bounded_memory(tmp_path):
    for name, path, needles in profile_cases(tmp_path):
        run = run_measured(client_command("driver", "--input", "joystick", "--profile",
                                          str(path)), timeout_s=60.0, cwd=REPO,
                           env=client_env())
        assert run.returncode is not None, f"{name}: still running after 60 s"
        check_refused(run, path, needles, "simserver-driver: ")


def test_a_keyboard_profile_number_of_hundreds_of_digits_is_out_of_range(tmp_path):
    """The keyboard's profile goes through the same reader (was an OverflowError)."""
    from clients.keyboard import load_keyboard_profile
    from clients.profile import ProfileError

    keyboard = (CONFIGS / "clients" / "keyboard.yaml").read_text()
    path = tmp_path / "keyboard.yaml"
    path.write_text(keyboard.replace("rate_per_s: 0.8", "rate_per_s: " + "9" * 400))
    with pytest.raises(ProfileError, match=r"key 'throttle.rate_per_s': expected a number"):
        load_keyboard_profile(path)
