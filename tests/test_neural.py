"""Neural compression: training, export, backend parity, refusal of mismatches, extremes.

The table is synthetic (an analytic ridge along the specular cone with a 1e5:1
dynamic range, 1% noise) so that these tests need no bake.
"""

import numpy as np
import pytest
import yaml

from models.bundle_table import BundleTable
from pipeline import export as export_stage
from pipeline import train as train_stage
from pipeline.config import BAKE_SECTIONS, load_config

WL = [450.0, 550.0, 650.0]


def synthetic_table(cfg, path, relative=True, dynamic_range=1e5):
    theta_i = np.deg2rad(np.arange(0, 91, 15.0))
    phi_i = np.zeros(1) if relative else np.deg2rad([0.0, 45.0, 90.0])
    pe, te = np.linspace(-np.pi, np.pi, 37), np.linspace(-np.pi / 2, np.pi / 2, 19)
    pc, tc = 0.5 * (pe[1:] + pe[:-1]), 0.5 * (te[1:] + te[:-1])
    PI, TI, PO, TO = np.meshgrid(phi_i, theta_i, pc, tc, indexing="ij")
    ridge = np.exp(-(((np.sin(TO) + np.sin(TI)) / 0.12) ** 2))
    lobe = 0.6 + 0.4 * np.cos(PO - (0 if relative else PI))
    spectral = np.array([0.6, 0.8, 1.0])
    S = (1.0 / dynamic_range + ridge * lobe)[..., None] * spectral
    rng = np.random.default_rng(0)
    E = 0.01 * S
    S = S + E * rng.standard_normal(S.shape)
    shape_pi = (len(phi_i), len(theta_i), len(WL))
    table = BundleTable(
        values=S.astype(np.float32), stderr=E.astype(np.float32), passthrough=np.zeros(len(phi_i)),
        passthrough_stderr=np.zeros(len(phi_i)), absorbed=np.zeros(shape_pi), lost=np.zeros(shape_pi),
        phi_i=phi_i, theta_i=theta_i, phi_o_edges=pe, theta_o_edges=te, wavelength=np.array(WL),
        meta={"reductions": {"theta_i": "mirror", "phi_i": "rotation" if relative else None,
                             "phi_o": "relative" if relative else "absolute"},
              "config_hash": cfg.hash(*BAKE_SECTIONS)})
    table.save(path)
    return table


def make_config(tmp_path, name="n", **train):
    cfg = {"name": name, "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
           "fiber": {"model": "isotropic"},
           "bundle": {"shape": "circle", "radius_um": 100},
           "train": {"models": {"tiny": [16, 16], "wide": [32, 32, 32]}, "epochs": 60, "batch_size": 512,
                     "patience": 60, **train}}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return load_config(path)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("neural")
    cfg = make_config(tmp)
    synthetic_table(cfg, tmp / "n" / "bake" / "bundle_table.npz")
    train_stage.run(cfg, tmp)
    export_stage.run(cfg, tmp)
    return cfg, tmp


def reference(tmp, name):
    import torch

    from models.neural import NeuralSpec, make_export_module, make_torch_model

    ckpt = torch.load(tmp / "n" / "train" / name / "model.pt", weights_only=True)
    spec = NeuralSpec.from_dict(ckpt["spec"])
    mlp = make_torch_model(spec)
    mlp.load_state_dict(ckpt["state"])
    module = make_export_module(spec, mlp).eval()

    def run(angles):
        with torch.no_grad():
            return module(torch.from_numpy(angles)).numpy().astype(np.float64)
    return spec, run


def query_set(n=50_000, seed=1):
    rng = np.random.default_rng(seed)
    A = np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n),
                  rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n)], -1)
    edges = [[0, np.pi / 2, np.pi, -np.pi / 2], [0, -np.pi / 2, 0, np.pi / 2], [np.pi, 0, -np.pi, 0],
             [2 * np.pi, 0.3, 2 * np.pi + 1e-6, -0.3], [-np.pi, 1.0, np.pi, -1.0],
             [100.0, 3.0, -100.0, -3.0], [7.0, -2.0, -7.0, 2.0]]  # beyond the domain: clamped / wrapped
    return np.concatenate([A, edges]).astype(np.float32)


@pytest.mark.parametrize("name", ["tiny", "wide"])
def test_backends_agree_with_pytorch(trained, mi_llvm, name):
    import drjit as dr

    from mitsuba_ext.neural import DrJitMLP, OnnxMLP

    cfg, tmp = trained
    spec, torch_eval = reference(tmp, name)
    A = query_set()
    ref = torch_eval(A)
    onnx_out = OnnxMLP(tmp / "n" / "export" / name / "model.onnx").eval(*A.T).astype(np.float64)
    mlp = DrJitMLP(tmp / "n" / "export" / name / "weights.npz")
    out = mlp.eval(*(mi_llvm.Float(a) for a in A.T))
    dr.eval(out)
    drjit_out = np.stack([o.numpy() for o in out], -1).astype(np.float64)
    # float32 rounding: relative 1e-5, with a floor of 1e-5 of the table's mean value s0
    # (near S = 0 the log-space output y ~ S / s0 is rounded absolutely, not relatively)
    tol = 1e-5 * np.abs(ref) + 1e-5 * spec.s0
    for out_ in (onnx_out, drjit_out):
        assert out_.shape == ref.shape
        assert np.all(np.isfinite(out_)) and np.all(out_ >= 0)
        assert np.all(np.abs(out_ - ref) <= tol)


def test_onnx_model_is_valid_with_dynamic_batch(trained):
    import onnx

    from mitsuba_ext.neural import OnnxMLP

    cfg, tmp = trained
    path = tmp / "n" / "export" / "tiny" / "model.onnx"
    onnx.checker.check_model(onnx.load(path))
    m = OnnxMLP(path)
    assert m.eval(0.1, 0.2, 0.3, -0.2).shape == (3,)
    assert m.eval(*query_set(1000).T).shape == (1007, 3)
    assert m.spec.wavelength == WL and m.spec.reductions["phi_o"] == "relative"


def test_training_is_deterministic_and_fits_a_stiff_table(trained, tmp_path):
    import json

    import torch

    cfg, tmp = trained
    again = make_config(tmp_path)
    synthetic_table(again, tmp_path / "n" / "bake" / "bundle_table.npz")
    train_stage.run(again, tmp_path)
    a = torch.load(tmp / "n" / "train" / "wide" / "model.pt", weights_only=True)["state"]
    b = torch.load(tmp_path / "n" / "train" / "wide" / "model.pt", weights_only=True)["state"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    summary = json.loads((tmp / "n" / "train" / "wide" / "summary.json").read_text())
    assert np.isfinite(summary["val_weighted_loss"])
    assert summary["relative_l1"] < 0.15  # 1e5:1 dynamic range, 60 epochs
    assert (tmp / "n" / "train" / "wide" / "loss.png").stat().st_size > 1000


def test_mismatched_models_are_refused(trained, tmp_path):
    from mitsuba_ext.neural import OnnxMLP, check_compatible, load_weights

    cfg, tmp = trained
    spec, _ = load_weights(tmp / "n" / "export" / "tiny" / "weights.npz")
    check_compatible(spec, table_hash=spec.table_hash, wavelength=WL, relative_phi=True)
    with pytest.raises(ValueError, match="trained on table"):
        check_compatible(spec, table_hash="0123456789abcdef")
    with pytest.raises(ValueError, match="wavelengths"):
        check_compatible(spec, wavelength=[550.0])
    with pytest.raises(ValueError, match="circular"):
        check_compatible(spec, relative_phi=False)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="re-run `bcsdf export`"):
        load_weights(bad)
    with pytest.raises(ValueError, match="onnxruntime cannot load"):
        OnnxMLP(bad)
    # a model trained with other settings is refused at export
    other = make_config(tmp_path, epochs=61)
    with pytest.raises(ValueError, match="different settings"):
        export_stage.run(other.model_copy(update={"name": "n"}), tmp)


def test_absolute_phi_encoding_for_ellipses(tmp_path, mi_llvm):
    import drjit as dr

    from mitsuba_ext.neural import DrJitMLP, OnnxMLP

    cfg = make_config(tmp_path, name="e", models={"tiny": [16]}, epochs=5)
    synthetic_table(cfg, tmp_path / "e" / "bake" / "bundle_table.npz", relative=False)
    train_stage.run(cfg, tmp_path)
    export_stage.run(cfg, tmp_path)
    A = query_set(2000)
    on = OnnxMLP(tmp_path / "e" / "export" / "tiny" / "model.onnx")
    assert on.spec.n_inputs == 7
    out = DrJitMLP(tmp_path / "e" / "export" / "tiny" / "weights.npz").eval(*(mi_llvm.Float(a) for a in A.T))
    dr.eval(out)
    assert np.allclose(np.stack([o.numpy() for o in out], -1), on.eval(*A.T), rtol=1e-5, atol=1e-5 * on.spec.s0)
