"""Issue 16, tires an engineer can trust: relaxation lengths from the .tir file, mirrored
sides (TYRESIDE), no Magic Formula offsets at standstill.

The vehicle runs are short scenarios through ``run_scenario`` (the same Simulation as every
runner); the expected values are computed here from the .tir file's own keys.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from simserver.adapters.config import ConfigError, load_tire, load_vehicle
from simserver.adapters.tir_file import load_tir
from simserver.core import layout as L
from simserver.core.tire import BUILTIN_KERNELS, tire_forces
from simserver.core.tire_layout import (
    N_TIRE_OUT,
    OUT_FX,
    OUT_FY,
    OUT_MZ,
    TP_MIRRORED,
    TP_MODEL_BASE,
    TP_RELAX_LAT_M,
    TP_RELAX_LONG_M,
)
from simserver.core.tire_mf61 import P_VXLOW
from simserver.sim.scenario import load_scenario, run_scenario
from tests.conftest import CONFIGS, SAMPLE_TIR

SAMPLE_TEXT = SAMPLE_TIR.read_text()
HATCH = CONFIGS / "vehicles" / "mf_hatchback" / "vehicle.yaml"
SEDAN = CONFIGS / "vehicles" / "paper_sedan" / "vehicle.yaml"
MF_SAMPLE, _ = load_tire(CONFIGS / "tires" / "mf61_sample.yaml")


def tir_value(key: str) -> float:
    return float(load_tir(SAMPLE_TIR).values[key])


def tire_with_tir(tmp_path: Path, tir_text: str, **yaml_keys: float) -> Path:
    """A tire file on a .tir with ``tir_text``, plus extra tire-file keys."""
    (tmp_path / "t.tir").write_text(tir_text)
    path = tmp_path / "tire.yaml"
    path.write_text(yaml.safe_dump({"model": "mf61", "tir_file": "t.tir", **yaml_keys}))
    return path


def with_line(key: str, line: str | None) -> str:
    """The sample .tir with the line that sets ``key`` replaced (None: removed)."""
    lines = SAMPLE_TEXT.splitlines()
    (idx,) = [i for i, text in enumerate(lines) if text.split("=")[0].strip() == key]
    if line is None:
        del lines[idx]
    else:
        lines[idx] = line
    return "\n".join(lines) + "\n"


# --- relaxation lengths ----------------------------------------------------------------------
def test_sample_relaxation_lengths_are_the_files():
    """MF 6.1 at the nominal load (LFZO = LSGKP = LSGAL = 1 in the sample):
    B = PTX1 R0, b = PTY1 sin(2 atan(1 / PTY2)) R0."""
    r0, ptx1 = tir_value("UNLOADED_RADIUS"), tir_value("PTX1")
    pty1, pty2 = tir_value("PTY1"), tir_value("PTY2")
    assert MF_SAMPLE[TP_RELAX_LONG_M] == pytest.approx(ptx1 * r0, rel=1e-15)
    assert MF_SAMPLE[TP_RELAX_LAT_M] == pytest.approx(
        pty1 * math.sin(2.0 * math.atan(1.0 / pty2)) * r0, rel=1e-15)
    # the figures of issue 16 (the defaults that used to be taken: 0.5016 m and 0.3135 m)
    assert MF_SAMPLE[TP_RELAX_LAT_M] == pytest.approx(0.4791, abs=5e-5)
    assert MF_SAMPLE[TP_RELAX_LONG_M] == pytest.approx(0.6207, abs=5e-5)


def test_relaxation_scaling_factors_apply(tmp_path):
    tp, _ = load_tire(tire_with_tir(tmp_path, with_line("LSGAL", "LSGAL = 0.5")))
    assert tp[TP_RELAX_LAT_M] == pytest.approx(0.5 * MF_SAMPLE[TP_RELAX_LAT_M], rel=1e-15)
    assert tp[TP_RELAX_LONG_M] == MF_SAMPLE[TP_RELAX_LONG_M]
    tp, _ = load_tire(tire_with_tir(tmp_path, with_line("LSGKP", "LSGKP = 2")))
    assert tp[TP_RELAX_LONG_M] == pytest.approx(2.0 * MF_SAMPLE[TP_RELAX_LONG_M], rel=1e-15)


@pytest.mark.parametrize("key, line, words", [
    ("PTY2", "PTY2 = 0", ("PTY2", "must be > 0")),
    ("PTY2", "PTY2 = 'abc'", ("PTY2", "non-numeric")),
    ("PTY1", "PTY1 = -1.8", ("PTY1", "must be > 0")),
    ("PTX1", "PTX1 = abc", ("PTX1",)),
    ("PTY2", None, ("missing key PTY2", "relaxation_length_lat_m")),
    ("PTX1", None, ("missing key PTX1", "relaxation_length_long_m")),
    ("PTX1", "PTX1 = 40", ("relaxation_length_long_m", "outside")),
])
def test_a_broken_relaxation_key_is_an_error_naming_it(tmp_path, key, line, words):
    path = tire_with_tir(tmp_path, with_line(key, line))
    with pytest.raises(ConfigError) as exc:
        load_tire(path)
    msg = str(exc.value)
    assert str(path) in msg and "t.tir" in msg, msg
    for word in words:
        assert word in msg, (word, msg)


def test_the_tire_file_overrides_the_tir(tmp_path):
    # a missing .tir key is fine when the tire file gives the length
    path = tire_with_tir(tmp_path, with_line("PTY2", None), relaxation_length_lat_m=0.3,
                         relaxation_length_long_m=0.2)
    tp, _ = load_tire(path)
    assert (tp[TP_RELAX_LAT_M], tp[TP_RELAX_LONG_M]) == (0.3, 0.2)


# --- TYRESIDE and mirroring ----------------------------------------------------------------
def test_a_left_tire_is_mirrored_on_the_right_corners():
    vehicle = load_vehicle(HATCH)  # the sample .tir: TYRESIDE = 'Left'
    assert list(vehicle.tp[:, TP_MIRRORED]) == [0.0, 1.0, 0.0, 1.0]  # FL, FR, RL, RR
    sedan = load_vehicle(SEDAN)  # the brush tire is symmetric: never mirrored
    assert not sedan.tp[:, TP_MIRRORED].any()


@pytest.mark.parametrize("side, mirrored", [("'Right'", [1.0, 0.0, 1.0, 0.0]),
                                            ("'left'", [0.0, 1.0, 0.0, 1.0]),
                                            ("'Symmetric'", [0.0, 0.0, 0.0, 0.0]),
                                            (None, [0.0, 1.0, 0.0, 1.0])])
def test_tyreside_decides_which_corners_are_mirrored(tmp_path, side, mirrored):
    line = None if side is None else f"TYRESIDE = {side}"
    tire = tire_with_tir(tmp_path, with_line("TYRESIDE", line))
    top = yaml.safe_load(HATCH.read_text())
    for key in ("chassis", "suspension", "steering", "brakes", "powertrain"):
        top[key] = str(HATCH.parent / top[key])
    top["tires"] = {"front": str(tire), "rear": str(tire)}
    (tmp_path / "vehicle.yaml").write_text(yaml.safe_dump(top))
    assert list(load_vehicle(tmp_path / "vehicle.yaml").tp[:, TP_MIRRORED]) == mirrored


def test_a_bad_tyreside_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match=r"TYRESIDE = 'Middle'"):
        load_tire(tire_with_tir(tmp_path, with_line("TYRESIDE", "TYRESIDE = 'Middle'")))


def forces(tp: np.ndarray, kappa: float, tan_alpha: float, gamma: float, vx: float = 20.0,
           fz: float = 4000.0) -> np.ndarray:
    out = np.full(N_TIRE_OUT, np.nan)
    tire_forces(BUILTIN_KERNELS, tp, kappa, tan_alpha, gamma, fz, 1.0, vx, out)
    return out


@pytest.mark.parametrize("kappa, tan_alpha, gamma", [
    (0.0, 0.0, 0.0), (0.05, 0.03, 0.02), (-0.1, -0.08, -0.04), (0.02, 0.2, 0.0)])
def test_the_mirrored_tire_is_the_mirror_image(kappa, tan_alpha, gamma):
    """Mirrored: Fy and Mz of the tire at the mirrored slip angle and camber, with their
    signs changed; Fx as at the mirrored point."""
    mirrored = MF_SAMPLE.copy()
    mirrored[TP_MIRRORED] = 1.0
    a = forces(mirrored, kappa, tan_alpha, gamma)
    b = forces(MF_SAMPLE, kappa, -tan_alpha, -gamma)
    assert a[OUT_FX] == b[OUT_FX]
    assert a[OUT_FY] == -b[OUT_FY] and a[OUT_MZ] == -b[OUT_MZ]
    # the sample's shifts make the left tire pull at zero slip; its mirror pulls the other way
    if kappa == tan_alpha == gamma == 0.0:
        assert abs(b[OUT_FY]) > 10.0


# --- the vehicle: straight, turning both ways, at rest -----------------------------------------
def run(tmp_path: Path, vehicle: Path, u_mps: float, steer: float, duration_s: float,
        grade_pct: float = 0.0, brake: float = 0.0):
    path = tmp_path / "probe.yaml"
    path.write_text(f"""name: probe
vehicle: {vehicle}
road: {{grade_pct: {grade_pct}}}
initial: {{u_mps: {u_mps}}}
duration_s: {duration_s}
inputs:
  - {{t: 0.0, gear: N, steer: {steer}, brake: {brake}}}
""")
    return run_scenario(load_scenario(path))


def test_mf_hatchback_runs_straight_at_zero_steer(tmp_path):
    """Issue 16: with four left tires it crabbed (tan a' = +0.00147, v = 0.031 m/s)."""
    r = run(tmp_path, HATCH, 20.0, 0.0, 3.0)
    assert np.abs(r.states[:, L.V_MPS]).max() < 1e-4
    assert np.abs(r.outputs[:, L.O_TAN_ALPHA]).max() < 1e-4
    assert r.states[-1, L.U_MPS] > 15.0  # it did drive


def test_mf_hatchback_turns_alike_both_ways(tmp_path):
    """Issue 16: steer +-0.03 gave yaw rates 0.10421 and -0.10483 rad/s."""
    left = run(tmp_path, HATCH, 20.0, 0.03, 4.0).final_state[L.YAW_RATE_RADPS]
    right = run(tmp_path, HATCH, 20.0, -0.03, 4.0).final_state[L.YAW_RATE_RADPS]
    assert left > 0.05
    assert abs(left + right) <= 1e-6 * abs(left)


@pytest.mark.parametrize("vehicle", [HATCH, SEDAN], ids=["mf_hatchback", "paper_sedan"])
def test_a_car_at_rest_stays_at_rest(tmp_path, vehicle):
    """Placed at rest in neutral on the flat, relaxed slip states: it moves less than a
    micrometre in 10 s (the MF shifts used to push the hatchback 0.70 mm)."""
    r = run(tmp_path, vehicle, 0.0, 0.0, 10.0)
    moved = np.hypot(r.states[:, L.X_M] - r.states[0, L.X_M],
                     r.states[:, L.Y_M] - r.states[0, L.Y_M])
    assert moved.max() < 1e-6


def test_shifts_fade_only_below_vxlow():
    """At |vx| >= VXLOW the forces are those without the low-speed rule, bit for bit; at
    standstill and zero slip there is no shear force; in between it is monotonic."""
    vxlow = MF_SAMPLE[TP_MODEL_BASE + P_VXLOW]
    assert vxlow == tir_value("VXLOW") > 0.0
    off = MF_SAMPLE.copy()
    off[TP_MODEL_BASE + P_VXLOW] = 0.0
    for vx in (vxlow, 2.0 * vxlow, -5.0, 30.0):
        for slip in ((0.0, 0.0, 0.0), (0.04, -0.02, 0.01)):
            np.testing.assert_array_equal(forces(MF_SAMPLE, *slip, vx=vx),
                                          forces(off, *slip, vx=vx))
    at_rest = forces(MF_SAMPLE, 0.0, 0.0, 0.0, vx=0.0)
    assert at_rest[OUT_FX] == 0.0 and at_rest[OUT_FY] == 0.0
    moving = forces(off, 0.0, 0.0, 0.0)
    assert abs(moving[OUT_FX]) > 10.0 and abs(moving[OUT_FY]) > 10.0  # 18.8 N, 69.9 N
    fy = [abs(forces(MF_SAMPLE, 0.0, 0.0, 0.0, vx=v)[OUT_FY]) for v in np.linspace(0, vxlow, 9)]
    assert all(a < b for a, b in zip(fy, fy[1:], strict=False))


@pytest.mark.parametrize("vehicle", [HATCH, SEDAN], ids=["mf_hatchback", "paper_sedan"])
def test_braked_on_a_10pct_grade_it_holds(tmp_path, vehicle):
    """Placed at rest on a 10 % grade, brakes full on: the slip states take up the slope
    within a few millimetres (more with the hatchback's longer, now the file's, B =
    0.62 m), then the car holds: nothing moves from 5 s to 10 s (measured 1e-12 m)."""
    r = run(tmp_path, vehicle, 0.0, 0.0, 10.0, grade_pct=10.0, brake=1.0)
    moved = np.hypot(r.states[:, L.X_M] - r.states[0, L.X_M],
                     r.states[:, L.Y_M] - r.states[0, L.Y_M])
    assert moved.max() < 5e-3
    held = moved[len(moved) // 2:]
    assert held.max() - held.min() < 1e-9


def test_a_tir_file_is_a_tire_file():
    """``load_tire`` (and so a vehicle's ``tires:`` and ``simserver tire-curves``) reads a
    .tir directly, as the mf61 tire file that names it with every default."""
    tp, name = load_tire(SAMPLE_TIR)
    assert name == "mf61"
    np.testing.assert_array_equal(tp, MF_SAMPLE)


# --- camber from the suspension ---------------------------------------------------------------
def fy_closed_form(fz: float, gamma: float) -> float:
    """MF 6.1 pure side force at zero slip, (4.E19)-(4.E30) at nominal pressure: at kappa = 0
    the combined-slip weight is 1 and the kappa-induced side force 0."""
    from tests.test_tire_mf61 import C, dfz_of, kya_ref, muy_ref, shy_ref

    d, gs = dfz_of(fz), math.sin(gamma)
    cy = C["PCY1"] * C["LCY"]
    dy = muy_ref(fz) * (1.0 - C["PDY3"] * gs * gs) * fz
    by = kya_ref(fz, gamma) / (cy * dy)
    alpha_y = shy_ref(fz, gamma)
    ey = ((C["PEY1"] + C["PEY2"] * d)
          * (1.0 + C["PEY5"] * gs * gs - (C["PEY3"] + C["PEY4"] * gs) * math.copysign(1.0, alpha_y))
          * C["LEY"])
    svy = fz * (C["PVY1"] + C["PVY2"] * d) * C["LVY"] * C["LMUY"] + (
        fz * (C["PVY3"] + C["PVY4"] * d) * gs * C["LKYC"] * C["LMUY"])
    x = by * alpha_y
    return dy * math.sin(cy * math.atan(x - ey * (x - math.atan(x)))) + svy


@pytest.mark.parametrize("fz", [3000.0, 4500.0])
def test_camber_thrust_is_mf61s_closed_form(fz):
    """A left tire at a small inclination (top toward -y) pushes toward -y by the closed
    form's amount; the mirrored (right-hand) tire at the mirrored camber pushes the other
    way by the same amount."""
    gamma = 0.02
    thrust = forces(MF_SAMPLE, 0.0, 0.0, gamma, fz=fz)[OUT_FY] - forces(
        MF_SAMPLE, 0.0, 0.0, 0.0, fz=fz)[OUT_FY]
    expect = fy_closed_form(fz, gamma) - fy_closed_form(fz, 0.0)
    assert thrust == pytest.approx(expect, rel=1e-9)
    assert thrust < -0.001 * fz  # toward -y, and not negligible
    mirrored = MF_SAMPLE.copy()
    mirrored[TP_MIRRORED] = 1.0
    thrust_right = forces(mirrored, 0.0, 0.0, -gamma, fz=fz)[OUT_FY] - forces(
        mirrored, 0.0, 0.0, 0.0, fz=fz)[OUT_FY]
    assert thrust_right == pytest.approx(-expect, rel=1e-12)


def test_a_steady_turn_shows_roll_camber_in_the_history(tmp_path):
    """The camber columns are the suspension's: static camber, heave gain times the
    corner's compression, roll gain times the roll (mf_hatchback: front 0.8, rear 0.9)."""
    from simserver.core import params as P

    vehicle = load_vehicle(HATCH)
    vp = vehicle.vp
    r = run(tmp_path, HATCH, 20.0, 0.03, 4.0)
    roll = r.states[:, L.ROLL_RAD]
    assert roll[-1] > 0.005  # a left turn lifts the left side: the body leans outward
    for i, (static, roll_gain, heave_gain, half_track, x_axle) in enumerate([
        (P.VP_CAMBER_STATIC_FRONT_RAD, P.VP_CAMBER_ROLL_GAIN_FRONT,
         P.VP_CAMBER_HEAVE_GAIN_FRONT_RADPM, P.VP_TRACK_FRONT_M, P.VP_CG_TO_FRONT_AXLE_M),
    ] * 2 + [
        (P.VP_CAMBER_STATIC_REAR_RAD, P.VP_CAMBER_ROLL_GAIN_REAR,
         P.VP_CAMBER_HEAVE_GAIN_REAR_RADPM, P.VP_TRACK_REAR_M, P.VP_CG_TO_REAR_AXLE_M),
    ] * 2):
        y = 0.5 * vp[half_track] * (1.0 if i % 2 == 0 else -1.0)
        px = vp[x_axle] * (1.0 if i < 2 else -1.0)
        compression = -(r.states[:, L.HEAVE_M] + y * roll - px * r.states[:, L.PITCH_RAD])
        camber = vp[static] + vp[heave_gain] * compression
        inboard = -1.0 if y > 0.0 else 1.0
        expect = vp[roll_gain] * roll + inboard * camber
        np.testing.assert_allclose(r.outputs[:, L.O_CAMBER0 + i], expect, rtol=1e-12,
                                   atol=1e-15)
    roll_part = vp[P.VP_CAMBER_ROLL_GAIN_FRONT] * roll[-1]
    assert abs(roll_part) > 0.004  # the roll-induced camber is there, a quarter degree


def test_tire_curves_show_camber_where_the_model_has_it():
    """``tire_curve_data(gamma_rad=...)`` (``simserver tire-curves --camber-deg``): the MF
    side force at zero slip moves by the camber thrust; the brush model has no camber."""
    from simserver.cli import tire_curve_data

    fz, gamma = 4000.0, 0.02
    kwargs = {"n_points": 3, "alpha_max_deg": 1.0}  # the middle point is alpha = 0
    flat = tire_curve_data(MF_SAMPLE, [fz], **kwargs)["fy_alpha"][0, 1]
    cambered = tire_curve_data(MF_SAMPLE, [fz], gamma_rad=gamma, **kwargs)["fy_alpha"][0, 1]
    assert cambered - flat == pytest.approx(
        fy_closed_form(fz, gamma) - fy_closed_form(fz, 0.0), rel=1e-9)
    brush, _ = load_tire(CONFIGS / "tires" / "paper_sti.yaml")
    np.testing.assert_array_equal(tire_curve_data(brush, [fz], **kwargs)["fy_alpha"],
                                  tire_curve_data(brush, [fz], gamma_rad=gamma,
                                                  **kwargs)["fy_alpha"])
