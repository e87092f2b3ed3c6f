"""The camera estimator (``models.bake.camera``): the ``curve`` exit's table traced from the
camera, as Mitsuba's path tracer renders explicit ``hair`` fibers (the comparison with those
renders: ``tests/test_hair_closure.py``)."""

import numpy as np
import pytest

from models.bake import BakeSpec, Tally, bake_unreduced
from models.fiber.ray import RayFiber
from pipeline.bench.hair import BETA_M, BETA_N, ETA, THETA_I, TILT, ply_of, ray_fiber


def bin_average(fiber: RayFiber, spec: BakeSpec, theta_i: float, n: int = 4) -> np.ndarray:
    """``fiber``'s value averaged over each output bin of ``spec`` (n x n points, uniform in
    solid angle): [phi_o, theta_o]."""
    u = (np.arange(n) + 0.5) / n
    pe, te = spec.phi_o_edges, spec.theta_o_edges
    phi = pe[:-1, None] + np.diff(pe)[:, None] * u[None, :]                          # [phi_o, n]
    s0, s1 = np.sin(te[:-1]), np.sin(te[1:])
    theta = np.arcsin(s0[:, None] + (s1 - s0)[:, None] * u[None, :])                  # [theta_o, n]
    P = phi[:, None, :, None] + 0 * theta[None, :, None, :]
    T = theta[None, :, None, :] + 0 * phi[:, None, :, None]
    f = fiber.eval(phi_i=0.0, theta_i=theta_i, phi_o=P, theta_o=T, wavelength=550.0)
    return f.mean(axis=(2, 3))


def test_one_fiber_traced_from_the_camera_is_the_adjoint_averaged_over_the_offset(mono):
    """A fiber alone: the bundle table is the fiber's own camera-transport value, the adjoint
    averaged over the camera's offset ``h`` (``RayFiber(transport="camera")``, its own
    quadrature over ``h``), bin by bin within the bake's standard errors; the light
    transport (what a mistaken side or cosine would give) is far outside them."""
    spec = BakeSpec(np.deg2rad(THETA_I), [0.0], 18, 36, exit="curve", estimator="camera")
    table = bake_unreduced(ply_of("one"), ray_fiber("camera"), spec, 1_300_000, seed=4)
    lam = list(table.wavelength).index(550.0)
    z_camera, z_light = [], []
    for j, ti in enumerate(np.deg2rad(THETA_I)):
        S, se = table.values[0, j, ..., lam], table.stderr[0, j, ..., lam]
        ok = S > 0.05 * S.max()   # the bins with light, whose standard errors are estimated well
        for transport, z in (("camera", z_camera), ("light", z_light)):
            fiber = RayFiber([550.0], ETA, 0.0, BETA_M, BETA_N, TILT, n_h=64, transport=transport)
            z.append(((S - bin_average(fiber, spec, ti)) / se)[ok])
    z_camera, z_light = np.concatenate(z_camera), np.concatenate(z_light)
    print(f"camera: mean z {z_camera.mean():.3f}, rms {np.sqrt(np.mean(z_camera**2)):.3f}, "
          f"light: rms {np.sqrt(np.mean(z_light**2)):.1f}")
    # the reference's own error (4 x 4 points a bin) is below a tenth of the bake's noise
    assert abs(z_camera.mean()) < 4 / np.sqrt(len(z_camera)) + 0.1
    assert np.sqrt(np.mean(z_camera**2)) < 1.25
    assert np.mean(np.abs(z_camera) > 4) < 0.005
    assert np.sqrt(np.mean(z_light**2)) > 5


def test_the_camera_estimator_is_asked_for_by_the_config_and_refused_where_it_cannot_trace():
    from pipeline.build import exit_model, tracer
    from pipeline.config import ConfigError
    from pipeline.loading import load_config

    camera = ["fiber.model=ray", "fiber.ray.transport=camera", "bake.estimator=camera"]
    cfg = load_config("configs/ray_ply.yaml", camera)
    assert cfg.bake.estimator == "camera" and exit_model("auto", ray_fiber("camera"), "camera") == "curve"
    for wrong in (["fiber.ray.transport=light"], ["bake.exit=uniform"], ["bake.orders=4"], ["bake.offsets=4"]):
        with pytest.raises(ConfigError):
            load_config("configs/ray_ply.yaml", camera + wrong)
    assert load_config("configs/twisted_cotton1.yaml", camera).bake.estimator == "camera"   # traced in 3D
    with pytest.raises(ConfigError, match="not thesis"):
        load_config("configs/twisted_cotton1.yaml", camera[:2] + ["bake.estimator=thesis"])
    with pytest.raises(ValueError, match="exit 'curve'"):
        BakeSpec([0.1], [0.0], estimator="camera", exit="uniform")
    with pytest.raises(ValueError, match="camera transport"):
        tracer(ply_of("one"), ray_fiber("light"), BakeSpec([0.1], [0.0], estimator="camera", exit="curve"))


def test_camera_tallies_keep_their_paths_per_bin_through_a_checkpoint_and_add_only_to_their_own(mono):
    spec = BakeSpec(np.deg2rad(THETA_I), [0.0], 6, 12, exit="curve", estimator="camera")
    from models.bake import CameraBaker

    baker = CameraBaker(ply_of("six"), ray_fiber("camera"), spec)
    a, b = baker.trace(0, 7200, 1), baker.trace(0, 7200, 2)
    again = Tally.from_arrays(a.arrays())
    assert np.array_equal(again.bin_paths, a.bin_paths) and np.all(a.bin_paths == 100)
    again.add(b)
    assert np.all(again.bin_paths == 200) and np.allclose(again.sum, a.sum + b.sum)
    fast = Tally.zeros(BakeSpec(np.deg2rad(THETA_I), [0.0], 6, 12, exit="curve"), 3)
    with pytest.raises(ValueError, match="estimators do not add"):
        again.add(fast)
    assert np.all(np.isfinite(again.sum)) and np.all(again.sum >= 0)


def test_the_bake_stage_traces_from_the_camera_and_resumes_to_the_same_table(tmp_path, mi_llvm):
    """Through the stages, an elliptical ply (absolute azimuths, mirrored): interrupted and
    resumed, the same table bit for bit; finite, its balance closed, its passthrough the
    light side's count."""
    import yaml

    from models.bundle_table import BundleTable
    from pipeline.loading import load_config
    from pipeline.stages import bake as bake_stage
    from pipeline.stages import fiber as fiber_stage

    cfg = {"name": "cam", "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
           "fiber": {"model": "ray", "radius_um": 20.0, "ior": {"k": 2e-4},
                     "ray": {"scale_tilt_deg": 0.0, "n_h": 32, "n_phi": 90, "transport": "camera"}},
           "tabulate": {"theta_i_step_deg": 15},
           "bundle": {"arrangement": "poisson", "shape": "ellipse", "semi_axes_um": [160, 100], "seed": 2},
           "bake": {"estimator": "camera", "paths_per_phi_i": 20_000, "batch_paths": 4096, "theta_i_step_deg": 30,
                    "phi_i_step_deg": 45, "n_theta_o": 12, "n_phi_o": 24}}
    path = tmp_path / "cam.yaml"
    path.write_text(yaml.safe_dump(cfg))
    cfg = load_config(path)
    for run in ("a", "b"):
        fiber_stage.run(cfg, tmp_path / run)
    bake_stage.run(cfg, tmp_path / "a")
    bake_stage.run(cfg, tmp_path / "b", stop_after=3)
    bake_stage.run(cfg, tmp_path / "b")
    ta, tb = (BundleTable.load(tmp_path / run / "cam" / "bake" / "bundle_table.npz") for run in ("a", "b"))
    assert np.array_equal(ta.values, tb.values) and np.array_equal(ta.stderr, tb.stderr)
    ta.validate()
    assert np.all(ta.values >= 0) and np.all(ta.stderr > 0)
    # closed where the adjoint keeps energy, beyond 1 where it makes more light than arrives; the
    # values are stored in half precision (2^-11 relative): their sum within a few of that
    total = ta.energy_balance()["total"]
    assert np.all(total > 1.0 - 2.0**-9), total.min()
    assert not np.any(np.isclose(np.rad2deg(np.abs(ta.theta_i)), 90.0))   # no pole: the adjoint has none
    assert 0.0 < ta.passthrough.min() <= ta.passthrough.max() < 0.5
    full = BundleTable.load(tmp_path / "a" / "cam" / "bake" / "bundle_table.npz", expand=True)
    assert len(full.phi_i) == 8 and np.all(np.isfinite(full.values))


def test_one_helical_fiber_traced_from_the_camera_is_the_camera_fiber_rotated(mi_llvm):
    """The twisted ply's camera estimator (``models.bake.twisted_camera``) on one helical fiber
    (leaning 14 deg, tilted 2 deg) against the camera-transport fiber rotated into the ply frame
    along its turn (``tests.test_twisted.rotated_fiber``), bin by bin; the light transport
    outside it in many bins."""
    from models.bake.twisted_camera import TwistedCameraBaker
    from models.bake import tally_to_table
    from models.bundle import Bundle, TwistedBundle
    from tests.test_twisted import agree, check_rotated_fiber, rotated_fiber

    rho, r, Rb, pitch = 60.0, 20.0, 80.0, 1500.0
    ply = TwistedBundle(Bundle(np.array([[rho, 0.0]]), r, (Rb, Rb)), pitch)
    args = ([450.0, 650.0], [1.56, 1.54], [0.6, 0.05], 0.25, 0.35, 2.0)
    camera = RayFiber(*args, n_h=64, transport="camera")
    spec = BakeSpec(np.deg2rad([0.0, 30.0, 50.0]), [0.0], 12, 24, exit="curve", estimator="camera")
    tabulated = camera.tabulate(np.deg2rad(np.arange(0, 91, 5.0)))
    tally = TwistedCameraBaker(ply, tabulated, spec).trace(0, 4_000_000, 2)
    table = tally_to_table(tally, spec, tabulated, {"theta_i": None, "phi_i": None, "phi_o": "relative"})
    check_rotated_fiber(table, ply, camera, spec, 650.0)
    light = RayFiber(*args, n_h=64)
    got, err = table.values[0, 1, :, :, 1], table.stderr[0, 1, :, :, 1]
    assert (~agree(got, rotated_fiber(ply, light, table, spec.theta_i[1], 650.0), err)).sum() >= 10
