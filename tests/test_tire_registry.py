"""The model registries: a new tire model is one module plus one registry entry, and an
unknown tire, slip or damping model is an error, never a fallback.

The toy model below is this file's own "module": a linear tire saturating at the friction
limit, registered through ``simserver.tires.registry.register_tire_model`` and run in a
scenario through the ordinary config loader and ``run_scenario``; nothing else is changed.
(Registering lasts for the process: the compiled step is specialised once more for the
longer kernel tuple and cached like any other specialisation.)
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba as nb
import numpy as np
import pytest

from simserver.adapters.config import ConfigError, load_tire
from simserver.core import layout as L
from simserver.core.damping import DAMPING_MODEL_NAMES, DAMPING_MODELS
from simserver.core.integrator import step
from simserver.core.params import VP_DAMPING_MODEL, VP_SLIP_MODEL
from simserver.core.slip import SLIP_MODEL_NAMES, SLIP_MODELS
from simserver.core.tire_layout import (
    EVALUATE_SIGNATURE,
    OUT_C_ALPHA,
    OUT_C_KAPPA,
    OUT_FX,
    OUT_FX_PEAK,
    OUT_FY,
    OUT_FY_PEAK,
    OUT_KAPPA_SLIDE,
    OUT_MY,
    OUT_MZ,
    OUT_TAN_ALPHA_SLIDE,
    PREPARE_SIGNATURE,
    TP_MODEL,
    TP_MODEL_BASE,
)
from simserver.core.variants import UnknownVariantError
from simserver.sim.scenario import load_scenario, run_scenario
from simserver.sim.scene import load_scene
from simserver.sim.simulation import Simulation
from simserver.tires.registry import (
    LoadedTire,
    UnknownTireModelError,
    register_tire_model,
    tire_model,
    tire_models,
    unregister_tire_model,
)
from tests.conftest import CONFIGS, REPO

# ---------------------------------------------------------------- the toy tire "module"
LIN_C_KAPPA, LIN_C_ALPHA, LIN_FZ_NOM, LIN_MU = 0, 1, 2, 3  # its slots from TP_MODEL_BASE
LIN_FZ = 0  # coefficient slot: the prepared load


@nb.njit(PREPARE_SIGNATURE, cache=True)
def linear_prepare(tp, gamma_rad, fz_n, mu_scale, coef):  # noqa: ANN001, ANN201
    coef[LIN_FZ] = max(fz_n, 1.0)


@nb.njit(EVALUATE_SIGNATURE, cache=True)
def linear_evaluate(tp, coef, kappa, tan_alpha, fz_n, vx_mps, out):  # noqa: ANN001, ANN201
    scale = fz_n / tp[TP_MODEL_BASE + LIN_FZ_NOM]
    c_kappa = tp[TP_MODEL_BASE + LIN_C_KAPPA] * scale
    c_alpha = tp[TP_MODEL_BASE + LIN_C_ALPHA] * scale
    limit = tp[TP_MODEL_BASE + LIN_MU] * fz_n
    out[OUT_FX] = min(max(c_kappa * kappa, -limit), limit)
    out[OUT_FY] = min(max(-c_alpha * tan_alpha, -limit), limit)
    out[OUT_MZ] = 0.0
    out[OUT_MY] = 0.0
    out[OUT_C_KAPPA] = c_kappa
    out[OUT_C_ALPHA] = c_alpha
    out[OUT_KAPPA_SLIDE] = limit / c_kappa
    out[OUT_TAN_ALPHA_SLIDE] = limit / c_alpha
    out[OUT_FX_PEAK] = limit
    out[OUT_FY_PEAK] = limit


LINEAR_KEYS = ("longitudinal_stiffness_n", "cornering_stiffness_n_per_rad", "nominal_load_n",
               "friction_coefficient")


def load_linear(path, data):  # noqa: ANN001, ANN201
    return LoadedTire(
        model_params=np.array([float(data[k]) for k in LINEAR_KEYS]),
        rolling_radius_m=float(data["rolling_radius_m"]),
        relax_lat_m=float(data["relaxation_length_lat_m"]),
        relax_long_m=float(data["relaxation_length_long_m"]))


@pytest.fixture
def linear_model():
    """The toy model, registered for one test and removed after it (the registry is
    global: the docs and the config loader of later tests read it, and while it is
    registered every new ``Simulation`` compiles the step once more for the longer kernel
    tuple, a minute on CI's machine)."""
    entry = register_tire_model("toy_linear", "linear tire, saturating at mu Fz (a test)",
                                load_linear, linear_prepare, linear_evaluate,
                                lambda p: p[LIN_FZ_NOM], n_coef=1, n_params=len(LINEAR_KEYS))
    yield entry
    unregister_tire_model("toy_linear")
    assert "toy_linear" not in {m.name for m in tire_models()}


TOY_TIRE = """\
model: toy_linear
longitudinal_stiffness_n: 22500
cornering_stiffness_n_per_rad: 51000
nominal_load_n: 5005
friction_coefficient: 0.9
rolling_radius_m: 0.33
relaxation_length_lat_m: 0.91
relaxation_length_long_m: 0.091
"""

SEDAN = CONFIGS / "vehicles" / "paper_sedan"
TOY_VEHICLE = f"""\
name: toy_sedan
chassis: {SEDAN / "chassis.yaml"}
suspension: {SEDAN / "suspension.yaml"}
steering: {SEDAN / "steering.yaml"}
brakes: {SEDAN / "brakes.yaml"}
powertrain: {SEDAN / "powertrain.yaml"}
tires: {{front: toy_tire.yaml, rear: toy_tire.yaml}}
"""

TOY_SCENARIO = """\
name: toy_linear_stop
vehicle: toy_vehicle.yaml
initial: {u_mps: 15.0}
duration_s: 6.0
inputs:
  - {t: 0.0, gear: D}
  - {t: 0.5, steer: 0.0}
  - {t: 1.5, steer: 0.1}
  - {t: 2.0, brake: 0.0}
  - {t: 2.3, brake: 0.6}
"""


@pytest.fixture
def only_when_slow(request: pytest.FixtureRequest) -> None:
    """Skip the long form unless asked for (``-m slow`` or ``SIMSERVER_SLOW=1``)."""
    from tests.conftest import slow_enabled

    if not slow_enabled(request.config.getoption("markexpr")):
        pytest.skip("long form: run with -m slow or SIMSERVER_SLOW=1")


def test_a_registered_toy_tire_gives_its_forces_through_the_compiled_dispatch(
        tmp_path, linear_model):
    """The short form of the scenario test below (which compiles the whole step once more
    for the longer kernel tuple, a minute on CI's machine): the toy loaded through the
    config loader and evaluated through ``tire_forces`` with the registry's kernels, the
    compiled dispatch the step and ``simserver tire-curves`` use, over slips on both sides
    of the friction limit and at two loads."""
    from simserver.core.tire import tire_forces
    from simserver.core.tire_layout import N_TIRE_OUT
    from simserver.tires.registry import tire_kernels

    (tmp_path / "toy_tire.yaml").write_text(TOY_TIRE)
    tp, name = load_tire(tmp_path / "toy_tire.yaml")
    assert name == "toy_linear" and tp[TP_MODEL] == linear_model.id >= 2
    tp = np.ascontiguousarray(tp)
    out = np.full(N_TIRE_OUT, np.nan)
    kernels = tire_kernels()
    for fz in (2500.0, 5005.0):
        limit = 0.9 * fz
        for kappa, tan_alpha in ((0.01, 0.0), (0.0, -0.02), (0.2, 0.3), (-0.5, 0.01)):
            tire_forces(kernels, tp, kappa, tan_alpha, 0.0, fz, 1.0, 10.0, out)
            # the toy's own law: linear in the slip, scaled with the load, clipped at mu Fz
            assert out[OUT_FX] == pytest.approx(
                np.clip(22500.0 * fz / 5005.0 * kappa, -limit, limit), rel=1e-12)
            assert out[OUT_FY] == pytest.approx(
                np.clip(-51000.0 * fz / 5005.0 * tan_alpha, -limit, limit), rel=1e-12)
            assert out[OUT_FX_PEAK] == out[OUT_FY_PEAK] == pytest.approx(limit)


@pytest.mark.slow
@pytest.mark.usefixtures("only_when_slow")
def test_a_registered_toy_tire_runs_a_scenario(tmp_path, linear_model):
    (tmp_path / "toy_tire.yaml").write_text(TOY_TIRE)
    (tmp_path / "toy_vehicle.yaml").write_text(TOY_VEHICLE)
    (tmp_path / "toy.yaml").write_text(TOY_SCENARIO)
    tp, name = load_tire(tmp_path / "toy_tire.yaml")
    assert name == "toy_linear" and tp[TP_MODEL] == linear_model.id >= 2

    r = run_scenario(load_scenario(tmp_path / "toy.yaml"))
    assert np.isfinite(r.states).all() and np.isfinite(r.outputs).all()
    assert abs(r.final_state[L.U_MPS]) < 0.05  # braked to rest
    assert r.states[:, L.YAW_RATE_RADPS].max() > 0.05  # it turned left on the steer
    # the forces are the toy's: linear in the slip fed to the tire, clipped at mu Fz
    fz = r.outputs[:, L.O_FZ]
    tire_fx = r.outputs[:, L.O_FX] - r.outputs[:, L.O_DAMPING_FX]
    tire_fy = r.outputs[:, L.O_FY] - r.outputs[:, L.O_DAMPING_FY]
    limit = 0.9 * fz
    expect_fx = np.clip(22500.0 * fz / 5005.0 * r.outputs[:, L.O_KAPPA], -limit, limit)
    expect_fy = np.clip(-51000.0 * fz / 5005.0 * r.outputs[:, L.O_TAN_ALPHA], -limit, limit)
    np.testing.assert_allclose(tire_fx, expect_fx, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(tire_fy, expect_fy, rtol=1e-12, atol=1e-9)
    assert np.abs(tire_fx).max() > 1000.0 and np.abs(tire_fy).max() > 100.0


def test_an_unknown_tire_model_name_is_a_config_error(tmp_path):
    path = tmp_path / "tire.yaml"
    path.write_text(TOY_TIRE.replace("toy_linear", "no_such_model"))
    with pytest.raises(ConfigError, match=r"tire\.yaml: key 'model': expected one of"):
        load_tire(path)


def test_an_unknown_tire_model_id_is_an_error():
    scene = load_scene(CONFIGS / "scenes" / "flat_paper_sedan.yaml")
    scene.vehicle.tp[2, TP_MODEL] = 99.0
    with pytest.raises(UnknownTireModelError,
                       match=r"unknown tire model id 99 \(registered: 0 simple, 1 mf61"):
        Simulation(scene, 0.001)
    with pytest.raises(UnknownTireModelError, match="unknown tire model 'nope'"):
        tire_model("nope")


@pytest.mark.parametrize(("slot", "error"), [
    (VP_SLIP_MODEL, r"unknown slip model id 7 \(known: 0 lagged_passive"),
    (VP_DAMPING_MODEL, r"unknown damping model id 7 \(known: 0 off"),
])
def test_an_unknown_variant_id_is_an_error(slot, error):
    scene = load_scene(CONFIGS / "scenes" / "flat_paper_sedan.yaml")
    scene.vehicle.vp[slot] = 7.0
    with pytest.raises(UnknownVariantError, match=error):
        Simulation(scene, 0.001)


@pytest.mark.parametrize(("slot", "error"), [(VP_SLIP_MODEL, "unknown slip model id"),
                                             (VP_DAMPING_MODEL, "unknown damping model id")])
def test_the_compiled_step_rejects_an_unknown_variant_too(slot, error):
    """Past the registry check (the parameter vector changed under a running simulation),
    the compiled step raises instead of running some other variant."""
    sim = Simulation(load_scene(CONFIGS / "scenes" / "flat_paper_sedan.yaml"), 0.001)
    sim.vp[slot] = 7.0
    with pytest.raises(ValueError, match=error):
        step(sim.model, sim.data)


def test_unknown_variant_names_are_errors():
    assert SLIP_MODELS.by_name("kinematic").id == SLIP_MODEL_NAMES["kinematic"]
    assert DAMPING_MODELS.by_name("patch").id == DAMPING_MODEL_NAMES["patch"]
    with pytest.raises(UnknownVariantError, match="unknown slip model 'lagged'"):
        SLIP_MODELS.by_name("lagged")
    with pytest.raises(UnknownVariantError, match="unknown damping model 'on'"):
        DAMPING_MODELS.by_name("on")


def test_registry_rejects_kernels_without_the_registered_signature():
    @nb.njit
    def untyped(tp, gamma_rad, fz_n, mu_scale, coef):  # noqa: ANN001, ANN202
        coef[0] = fz_n

    with pytest.raises(TypeError, match="prepare must be compiled with exactly the signature"):
        register_tire_model("untyped", "", load_linear, untyped, linear_evaluate,
                            lambda p: 1.0, n_coef=1, n_params=4)
    with pytest.raises(ValueError, match="already registered"):
        register_tire_model("simple", "", load_linear, linear_prepare, linear_evaluate,
                            lambda p: 1.0, n_coef=1, n_params=4)


def test_builtin_kernels_compile_on_first_use_and_match_the_step_dispatch():
    """The step calls the built-in models' bodies directly (core.tire), never their registry
    kernels: those are not compiled at import (they cost 10-12 s of every start from an
    empty numba cache), and once called they give the forces of the dispatch the step
    uses, to the bit (the same inlined body, the same compile options)."""
    from simserver.core.tire import tire_forces
    from simserver.core.tire_layout import N_TIRE_COEF, N_TIRE_OUT
    from simserver.tires.registry import tire_kernels

    mf61 = tire_model("mf61")
    assert not mf61.prepare.signatures and not mf61.evaluate.signatures
    simple = tire_model("simple")
    tp, _ = load_tire(CONFIGS / "tires" / "paper_sti.yaml")
    tp = np.ascontiguousarray(tp)
    coef, via_kernels, via_dispatch = np.zeros(N_TIRE_COEF), np.zeros(N_TIRE_OUT), np.zeros(
        N_TIRE_OUT)
    for kappa, tan_alpha in ((0.02, 0.0), (-0.3, 0.1), (0.0, -0.05)):
        simple.prepare(tp, 0.0, 4000.0, 1.0, coef)
        simple.evaluate(tp, coef, kappa, tan_alpha, 4000.0, 20.0, via_kernels)
        tire_forces(tire_kernels(), tp, kappa, tan_alpha, 0.0, 4000.0, 1.0, 20.0, via_dispatch)
        np.testing.assert_array_equal(via_kernels, via_dispatch)


# ---------------------------------------------------------------- the workspace


def test_a_model_needing_more_than_the_workspace_is_refused_by_name_and_numbers():
    """The step's coefficient scratch (N_TIRE_COEF floats on its stack) and a tire
    vector's model slots (N_MODEL_PARAM_MAX) are not bounds-checked at run time: a model
    declaring one slot more than either is refused, naming itself and both numbers, and
    the registry is left as it was."""
    from simserver.core.tire_layout import N_TIRE_COEF
    from simserver.tires.registry import N_MODEL_PARAM_MAX, TireWorkspaceError

    before = tire_models()
    cases = ((N_TIRE_COEF + 1, 4, f"declares {N_TIRE_COEF + 1} coefficient slots",
              f"0 to {N_TIRE_COEF}"),
             (1, N_MODEL_PARAM_MAX + 1, f"declares {N_MODEL_PARAM_MAX + 1} parameter slots",
              f"0 to {N_MODEL_PARAM_MAX}"),
             (-1, 4, "declares -1 coefficient slots", "0 to"))
    for n_coef, n_params, says, room in cases:
        with pytest.raises(TireWorkspaceError) as err:
            register_tire_model("too_big", "", load_linear, linear_prepare, linear_evaluate,
                                lambda p: 1.0, n_coef=n_coef, n_params=n_params)
        message = str(err.value)
        assert "'too_big'" in message and says in message and room in message, message
    with pytest.raises(TireWorkspaceError, match="'too_big': coefficient slots .* integer"):
        register_tire_model("too_big", "", load_linear, linear_prepare, linear_evaluate,
                            lambda p: 1.0, n_coef=2.5, n_params=4)
    assert tire_models() == before


def test_a_model_at_the_workspace_limit_is_accepted_and_its_loader_held_to_it(tmp_path):
    """Exactly N_TIRE_COEF coefficients and N_MODEL_PARAM_MAX parameters fit; a file
    loads when its loader packs the declared count, and a loader packing one more than
    the model declared is a config error naming the file, the model and the numbers."""
    from simserver.core.tire_layout import N_TIRE_COEF
    from simserver.tires.registry import N_MODEL_PARAM_MAX

    packed = {"n": N_MODEL_PARAM_MAX}

    def load_full(path, data):  # noqa: ANN001, ANN202
        return LoadedTire(model_params=np.arange(packed["n"], dtype=np.float64),
                          rolling_radius_m=0.3, relax_lat_m=0.5, relax_long_m=0.1)

    entry = register_tire_model("at_limit", "fills the workspace (a test)", load_full,
                                linear_prepare, linear_evaluate, lambda p: 1.0,
                                n_coef=N_TIRE_COEF, n_params=N_MODEL_PARAM_MAX)
    try:
        assert (entry.n_coef, entry.n_params) == (N_TIRE_COEF, N_MODEL_PARAM_MAX)
        assert tire_model("at_limit") is entry
        (tmp_path / "full.yaml").write_text("model: at_limit\n")
        tp, name = load_tire(tmp_path / "full.yaml")
        assert name == "at_limit" and tp[TP_MODEL] == entry.id
        np.testing.assert_array_equal(tp[TP_MODEL_BASE:], np.arange(N_MODEL_PARAM_MAX))
        packed["n"] = N_MODEL_PARAM_MAX + 1
        with pytest.raises(ConfigError) as err:
            load_tire(tmp_path / "full.yaml")
        assert str(err.value).startswith(f"{tmp_path / 'full.yaml'}: tire model 'at_limit' "
                                         f"packs {N_MODEL_PARAM_MAX + 1} parameters, more "
                                         f"than the {N_MODEL_PARAM_MAX} it declared")
    finally:
        unregister_tire_model("at_limit")


def test_builtin_models_declare_their_own_counts():
    from simserver.core.tire_layout import N_MF61_COEF, N_SIMPLE_COEF
    from simserver.core.tire_mf61 import N_MF61_PARAM
    from simserver.core.tire_simple import N_SIMPLE_PARAM

    assert (tire_model("simple").n_coef, tire_model("simple").n_params) == (
        N_SIMPLE_COEF, N_SIMPLE_PARAM)
    assert (tire_model("mf61").n_coef, tire_model("mf61").n_params) == (
        N_MF61_COEF, N_MF61_PARAM)


# ---------------------------------------------------------------- plug-ins (entry points)

PLUGIN_MODULE = '''\
"""A plug-in tire model, installed the way a distribution installs one."""
import numba as nb
import numpy as np

from simserver.core.tire_layout import (EVALUATE_SIGNATURE, OUT_FX, PREPARE_SIGNATURE,
                                        TP_MODEL_BASE)
from simserver.tires.registry import LoadedTire, register_tire_model


@nb.njit(PREPARE_SIGNATURE)
def prepare(tp, gamma_rad, fz_n, mu_scale, coef):
    coef[0] = fz_n


@nb.njit(EVALUATE_SIGNATURE)
def evaluate(tp, coef, kappa, tan_alpha, fz_n, vx_mps, out):
    out[:] = 0.0
    out[OUT_FX] = tp[TP_MODEL_BASE] * kappa * coef[0]


def load(path, data):
    return LoadedTire(model_params=np.array([float(data["gain"])]), rolling_radius_m=0.3,
                      relax_lat_m=0.5, relax_long_m=0.1)


def register():
    register_tire_model("plugged", "a plug-in (a test)", load, prepare, evaluate,
                        lambda p: 4000.0, n_coef=1, n_params=1)
'''

PLUGIN_CHECK = '''\
import sys
from pathlib import Path

from simserver.adapters.config import load_tire
from simserver.server.load_worker import ProcessPreparer, opened
from simserver.tires import PLUGINS
from simserver.tires.registry import tire_model

if __name__ == "__main__":
    here = tire_model("plugged").id
    worker = ProcessPreparer()
    try:  # the server's load worker: a spawned process, which imports simserver anew
        tp, name = opened(worker.submit(load_tire, Path(sys.argv[1])).result(timeout=120))
    finally:
        worker.close()
    print(PLUGINS, here, name, int(tp[0]), tp[5])
'''


def _install_plugin(site: Path, value: str) -> None:
    """An installed distribution as pip leaves it: its module and a ``.dist-info`` with
    ``METADATA`` and ``entry_points.txt`` on the path (importlib.metadata reads those)."""
    (site / "toy_tire_plugin.py").write_text(PLUGIN_MODULE)
    info = site / "toy_tire_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-tire-plugin\n"
                                   "Version: 0.1\n")
    (info / "entry_points.txt").write_text(f"[simserver.tire_models]\nplugged = {value}\n")


def _python(site: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(REPO)]))
    return subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True,
                          timeout=300, cwd=site)


def test_an_entry_point_registers_a_model_in_every_process_the_load_worker_too(tmp_path):
    """An installed plug-in (entry point group ``simserver.tire_models``) is registered on
    import of the registry, so the server's spawned load worker, which shares nothing with
    the process that started it, knows the model and gives it the same id."""
    _install_plugin(tmp_path, "toy_tire_plugin:register")
    (tmp_path / "plugged.yaml").write_text("model: plugged\ngain: 2.5\n")
    (tmp_path / "check.py").write_text(PLUGIN_CHECK)
    proc = _python(tmp_path, "check.py", str(tmp_path / "plugged.yaml"))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["('plugged',)", "2", "plugged", "2", "2.5"]


def test_a_broken_plugin_is_an_error_naming_it(tmp_path):
    _install_plugin(tmp_path, "toy_tire_plugin:no_such_function")
    proc = _python(tmp_path, "-c", "import simserver.tires.registry")
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("simserver.tires.registry.TirePluginError: tire model plug-in "
                           "'plugged' = 'toy_tire_plugin:no_such_function' (entry point group "
                           "'simserver.tire_models', from toy-tire-plugin) failed"), last
