"""The `bake` stage: resumable, refuses bad input clearly, finite at the extremes."""

import numpy as np
import pytest
import yaml

from models.bake import Baker, BakeSpec, tally_to_table
from models.bundle import Bundle, poisson
from models.bundle_table import BundleTable
from models.fiber.patterns import PatternFiber
from pipeline.stages import bake as bake_stage
from pipeline.stages import fiber as fiber_stage
from pipeline.artifacts import load_fiber_table
from pipeline.config import ConfigError
from pipeline.loading import load_config
from tests.test_cli import ROOT, bcsdf


def config(tmp_path, name="b", **bake):
    cfg = {"name": name,
           "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
           "fiber": {"model": "ray", "radius_um": 20.0, "ior": {"k": 2e-4},
                     "ray": {"scale_tilt_deg": 0.0, "n_h": 32, "n_phi": 90}},
           "tabulate": {"theta_i_step_deg": 15},
           "bundle": {"arrangement": "poisson", "shape": "ellipse", "semi_axes_um": [160, 100], "seed": 2},
           "bake": {"paths_per_phi_i": 20_000, "batch_paths": 4096, "theta_i_step_deg": 30,
                    "phi_i_step_deg": 45, "n_theta_o": 12, "n_phi_o": 24, **bake}}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return load_config(path)


def test_resume_gives_the_same_table(tmp_path, mi_llvm):
    cfg = config(tmp_path, orders=4)   # the orders of scattering kept too: checkpointed and expanded alike
    fiber_stage.run(cfg, tmp_path / "a")
    fiber_stage.run(cfg, tmp_path / "b")
    bake_stage.run(cfg, tmp_path / "a")
    # interrupted after 3 of 15 batches, then run again: continues from the checkpoint
    bake_stage.run(cfg, tmp_path / "b", stop_after=3)
    assert (tmp_path / "b" / "b" / "bake" / "checkpoint.npz").exists()
    assert not (tmp_path / "b" / "b" / "bake" / "bundle_table.npz").exists()
    bake_stage.run(cfg, tmp_path / "b")
    ta = BundleTable.load(tmp_path / "a" / "b" / "bake" / "bundle_table.npz")
    tb = BundleTable.load(tmp_path / "b" / "b" / "bake" / "bundle_table.npz")
    assert np.array_equal(ta.values, tb.values) and np.array_equal(ta.stderr, tb.stderr)
    assert np.array_equal(ta.passthrough, tb.passthrough) and np.array_equal(ta.single, tb.single)
    assert np.array_equal(ta.orders, tb.orders) and np.array_equal(ta.tail_ratio, tb.tail_ratio)
    assert not (tmp_path / "b" / "b" / "bake" / "checkpoint.npz").exists()
    # the table describes itself and expands its reductions
    assert ta.meta["reductions"] == {"theta_i": "mirror", "phi_i": "mirror_xz", "phi_o": "absolute"}
    full = BundleTable.load(tmp_path / "a" / "b" / "bake" / "bundle_table.npz", expand=True)
    assert len(full.phi_i) == 8 and np.allclose(np.rad2deg(full.theta_i), [-90, -60, -30, 0, 30, 60, 90])
    # mirror in z: S(-phi_i, -phi_o) = S(phi_i, phi_o)
    a45, a315 = np.argmin(abs(full.phi_i - np.pi / 4)), np.argmin(abs(full.phi_i - 7 * np.pi / 4))
    assert np.array_equal(full.values[a315], full.values[a45][:, ::-1])
    # mirror along the axis: S(-theta_i, -theta_o) = S(theta_i, theta_o)
    assert np.array_equal(full.values[:, 2], full.values[:, 4][:, :, ::-1])
    assert full.single.shape == full.absorbed.shape and np.array_equal(full.single[:, 2], full.single[:, 4])
    assert np.array_equal(full.single[a315], full.single[a45])
    assert np.array_equal(full.orders[:, a315], full.orders[:, a45][:, :, ::-1])
    assert np.array_equal(full.orders[:, :, 2], full.orders[:, :, 4][:, :, :, ::-1])
    # each order in half precision (2^-11), their sum the table's (itself in half precision)
    assert np.all(np.abs(full.orders.sum(0) - full.values) <= 2.0**-9 * full.values + 1e-6 * full.values.max())
    pictures = list((tmp_path / "a" / "b" / "bake" / "slices").glob("*.png"))
    assert len(pictures) == 3 * 4 and (tmp_path / "a" / "b" / "bake" / "energy.png").exists()


def test_bake_refuses_a_fiber_table_from_other_settings(tmp_path, mi_llvm):
    cfg = config(tmp_path, name="c")
    fiber_stage.run(cfg, tmp_path)
    other = config(tmp_path, name="c", estimator="thesis")  # bake settings only: fiber table still valid
    load_fiber_table(other, tmp_path)
    changed = cfg.model_copy(update={"fiber": cfg.fiber.model_copy(update={"radius_um": 10.0})})
    with pytest.raises(ValueError, match="re-run `bcsdf fiber`"):
        load_fiber_table(changed, tmp_path)


@pytest.mark.parametrize("make,match", [
    (lambda: Bundle([[0, 0], [30, 0]], 20, (100, 100)), "overlap"),
    (lambda: Bundle([[90, 0]], 20, (100, 100)), "leave the bound"),
    (lambda: Bundle(np.zeros((0, 2)), 20, (100, 100)), "no fibers"),
    (lambda: Bundle([[0, 0]], 20, (10, 10)), "larger than the bundle"),
    (lambda: poisson((15, 15), 20), "does not fit"),
    (lambda: poisson((100, 100), 20, gap=300), "empty"),
    (lambda: poisson((100, 100), 20, packing=0.85), "not reachable"),
])
def test_bad_bundles_are_refused(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bounce_cap_zero_refused(tmp_path):
    path = tmp_path / "cap.yaml"
    cfg = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    cfg["bake"]["max_bounces"] = 0
    path.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ConfigError, match="bake.max_bounces"):
        load_config(path)
    r = bcsdf("bake", str(path), cwd=ROOT)
    assert r.returncode == 2 and "max_bounces" in r.stderr
    with pytest.raises(ValueError, match="bounce cap"):
        BakeSpec([0.0], [0.0], max_bounces=0)


def test_bake_without_fiber_table_says_what_to_run(tmp_path):
    """The advice names the config as the user did, its ``--set`` included: a command that
    runs (``--set name=...`` renames the folder, not the file)."""
    config(tmp_path, name="nofiber")
    path = tmp_path / "nofiber.yaml"
    r = bcsdf("--artifacts", str(tmp_path / "empty"), "bake", str(path), cwd=ROOT)
    assert r.returncode == 2 and f"bcsdf fiber {path}`" in r.stderr, r.stderr
    r = bcsdf("--artifacts", str(tmp_path / "empty"), "bake", str(path), "--set", "name=trial", cwd=ROOT)
    assert r.returncode == 2 and f"bcsdf fiber {path} --set name=trial`" in r.stderr, r.stderr


@pytest.mark.parametrize("estimator", ["fast", "thesis"])
def test_extremes_are_finite(mi_llvm, estimator):
    """Touching fibers, grazing incidence, directions along the axis, a dense lossless bundle."""
    wl = np.array([500.0])
    iso = PatternFiber(wl, "isotropic").tabulate(np.deg2rad(np.arange(0, 91, 10.0)))
    r = 20.0
    touching = Bundle([[-r, 0], [r, 0], [0, 2 * r * np.sqrt(0.75) * 1.0000001]], r, (3 * r, 3 * r))
    spec = BakeSpec(np.deg2rad([0.0, 89.9, 90.0]), [0.0], 12, 16, estimator=estimator, max_bounces=3000)
    for bundle in (touching, poisson((150, 150), 20, seed=9)):
        tally = Baker(bundle, iso, spec).trace(0, 20_000, 1)
        table = tally_to_table(tally, spec, iso, {"theta_i": None, "phi_i": None, "phi_o": "relative"})
        table.validate()  # finite everywhere
        assert np.all(table.values >= 0)
        assert np.allclose(table.energy_balance()["total"], 1, atol=0.05)


def test_sigint_and_kill_9_mid_bake_then_resume_give_the_same_table(tmp_path, mi_llvm):
    """Through the CLI: Ctrl-C exits 130 and keeps the checkpoint, kill -9 loses at most the
    batches since the last checkpoint, and the resumed table is the uninterrupted one."""
    import signal
    import subprocess
    import sys
    import time

    # enough batches that the bake cannot finish between the checkpoint seen and the signal
    cfg = config(tmp_path, name="k", paths_per_phi_i=320_000, checkpoint_every_s=0.01)
    path = tmp_path / "k.yaml"
    fiber_stage.run(cfg, tmp_path / "ref")
    bake_stage.run(cfg, tmp_path / "ref")
    fiber_stage.run(cfg, tmp_path / "cut")
    ckpt = tmp_path / "cut" / "k" / "bake" / "checkpoint.npz"

    def bake_until(done_at_least, sig):
        # SIGINT at its default in the child, as a shell gives it: an ignored SIGINT is inherited
        # (Python then installs no KeyboardInterrupt), and an earlier test of the suite may leave one
        p = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "--artifacts", str(tmp_path / "cut"), "bake",
                              str(path)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        start = time.time()
        while time.time() - start < 120:
            try:
                with np.load(ckpt) as z:
                    if int(z["done"]) >= done_at_least:
                        break
            except (OSError, ValueError, KeyError):
                pass
            time.sleep(0.05)
        p.send_signal(sig)
        out, err = p.communicate(timeout=60)
        return p.returncode, err

    rc, err = bake_until(3, signal.SIGINT)
    assert rc == 130 and "interrupted" in err and "Traceback" not in err, err
    assert ckpt.exists()
    rc, err = bake_until(int(np.load(ckpt)["done"]) + 3, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    assert not (tmp_path / "cut" / "k" / "bake" / "bundle_table.npz").exists()
    bake_stage.run(cfg, tmp_path / "cut")
    a = BundleTable.load(tmp_path / "ref" / "k" / "bake" / "bundle_table.npz")
    b = BundleTable.load(tmp_path / "cut" / "k" / "bake" / "bundle_table.npz")
    assert np.array_equal(a.values, b.values) and np.array_equal(a.stderr, b.stderr)
    assert not list((tmp_path / "cut" / "k" / "bake").glob(".*.tmp"))  # no torn temporary files left
