import gc
import os

import pytest

# Two xdist workers share the cores: torch's OpenMP threads, spinning at their barriers while
# the other worker's Dr.Jit kernels hold the cores, made the training tests 5x slower
# (tests/test_neural.py beside tests/test_closure.py: 143 s, with sleeping waiters 26 s).
# Alone, sleeping waiters cost about 40% (22 s against 31 s), so only where there are
# workers; the stages' subprocesses inherit it.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# Modules whose tests load plugins in failing or evaluated-mode-only ways
PLUGIN_MODULES = {"test_dye", "test_plugin", "test_closure", "test_render", "test_bad_input", "test_neural", "test_stability",
                  "test_artifact_checks", "test_cloth", "test_scenes", "test_plugin_params"}


@pytest.fixture(autouse=True)
def collect_dead_plugins(request):
    """A BSDF that outlives its test (held by an exception's traceback cycle until the
    collector runs) stays in Dr.Jit's instance registry, and every later symbolic BSDF
    call traces all registered instances: an onnx BSDF, which refuses symbolic mode,
    then failed unrelated renders. Collect after each test of the modules that make them."""
    yield
    if request.module.__name__.rsplit(".", 1)[-1] in PLUGIN_MODULES:
        gc.collect()


@pytest.fixture(scope="session")
def mi_llvm():
    """Mitsuba on the LLVM backend (chosen here, at the entry point, never at import)."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return mi


@pytest.fixture(scope="session")
def ray_fiber():
    """The bake tests' ray fiber: two wavelengths, absorbing in blue, tabulated every 5 deg,
    untilted (so that the theta mirror reduction is valid)."""
    import numpy as np

    from models.fiber.ray import RayFiber

    return RayFiber(np.array([450.0, 650.0]), [1.56, 1.54], [0.6, 0.05], 0.25, 0.35, 0.0,
                    n_h=64).tabulate(np.deg2rad(np.arange(0, 91, 5.0)))


@pytest.fixture
def mi_plugins():
    """llvm_ad_rgb with the project's plugins registered, set for every test: other
    stages (the baker) choose their own variant at their entry points."""
    import mitsuba as mi

    import mitsuba_ext

    mi.set_variant("llvm_ad_rgb")
    mitsuba_ext.register()
    return mi


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """Two small MLPs trained and exported from a synthetic table (passthrough 0.3)."""
    from pipeline.stages import export as export_stage
    from pipeline.stages import train as train_stage
    from tests.synthetic import make_config, synthetic_table

    tmp = tmp_path_factory.mktemp("neural")
    cfg = make_config(tmp)
    synthetic_table(cfg, tmp / "n" / "bake" / "bundle_table.npz", passthrough=0.3)
    train_stage.run(cfg, tmp)
    export_stage.run(cfg, tmp)
    return cfg, tmp


@pytest.fixture(scope="session")
def trained_lines(tmp_path_factory):
    """The same two sizes with feature lines (models/lines.py), trained and exported."""
    from pipeline.stages import export as export_stage
    from pipeline.stages import train as train_stage
    from tests.synthetic import make_config, synthetic_table

    tmp = tmp_path_factory.mktemp("lines")
    cfg = make_config(tmp, line_nodes=[8, 16, 12], line_channels=4)
    synthetic_table(cfg, tmp / "n" / "bake" / "bundle_table.npz", passthrough=0.3)
    train_stage.run(cfg, tmp)
    export_stage.run(cfg, tmp)
    return cfg, tmp


@pytest.fixture(scope="session")
def trained_azimuth(tmp_path_factory):
    """The same two sizes on the synthetic table with a spectral ripple by azimuth bin
    (``tests.synthetic.with_ripple``), the energy gain resolved in its 18 bins of
    ``|phi_o - phi_i|`` (``train.gain_azimuth_bins``) and stored as a product of rank 2
    (``train.gain_rank``: the backends read it expanded), trained and exported."""
    from pipeline.stages import export as export_stage
    from pipeline.stages import train as train_stage
    from tests.synthetic import make_config, synthetic_table, with_ripple

    tmp = tmp_path_factory.mktemp("azimuth")
    cfg = make_config(tmp, gain_azimuth_bins=18, gain_rank=2)
    path = tmp / "n" / "bake" / "bundle_table.npz"
    with_ripple(synthetic_table(cfg, path, passthrough=0.3), 18).save(path)
    train_stage.run(cfg, tmp)
    export_stage.run(cfg, tmp)
    return cfg, tmp


@pytest.fixture(scope="session")
def trained_near(tmp_path_factory):
    """The same two sizes with the offset as an input (a near field of 4 cells), trained and
    exported."""
    from pipeline.stages import export as export_stage
    from pipeline.stages import train as train_stage
    from tests.synthetic import make_config, synthetic_table

    tmp = tmp_path_factory.mktemp("near")
    cfg = make_config(tmp, bake={"offsets": 4}, inputs=["offset"])
    synthetic_table(cfg, tmp / "n" / "bake" / "bundle_table.npz", passthrough=0.3, offsets=4)
    train_stage.run(cfg, tmp)
    export_stage.run(cfg, tmp)
    return cfg, tmp


@pytest.fixture
def spectral(mi_llvm):
    """Mitsuba's spectral variant with the plugins registered; the session's variant after."""
    import mitsuba as mi

    import mitsuba_ext

    mi.set_variant("llvm_ad_spectral")
    mitsuba_ext.register()
    yield mi
    mi.set_variant("llvm_ad_rgb")


@pytest.fixture
def mono(mi_llvm):
    """Mitsuba's mono variant with the plugins registered (the closure tests' one wavelength)."""
    import mitsuba as mi

    import mitsuba_ext

    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    yield mi
    mi.set_variant("llvm_ad_rgb")
