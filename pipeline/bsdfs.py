"""The ``fiber_bundle`` parameters of a config's artifacts, one backend at a time: the
baked table, or the exported MLP for Dr.Jit (``mlp``) or onnxruntime (``onnx``). Each
file is checked against the config before a scene is built on it."""

from __future__ import annotations

import numpy as np

from mitsuba_ext.neural import OnnxMLP, check_compatible, load_weights
from models.bundle_table import BundleTable

from .artifacts import config_dir, model_size
from .config import BAKE_SECTIONS, TRAIN_SECTIONS


def backend_props(cfg, out_root, backend: str) -> dict:
    """The ``fiber_bundle`` parameters of one backend, checked against this config."""
    root = config_dir(cfg, out_root)
    if backend == "table":
        path = root / "bake" / "bundle_table.npz"
        if not path.exists():
            raise ValueError(f"{path} does not exist; run `bcsdf bake` with this config first")
        if BundleTable.load(path).meta.get("config_hash") != cfg.hash(*BAKE_SECTIONS):
            raise ValueError(f"{path} was baked from different settings than this config; re-run `bcsdf bake`")
        return {"type": "fiber_bundle", "backend": "table", "table": str(path)}
    size = model_size(cfg)
    weights = root / "export" / size / "weights.npz"
    if not weights.exists():
        raise ValueError(f"{weights} does not exist; run `bcsdf export` with this config first")
    spec, _, _ = load_weights(weights)
    if spec.config_hash != cfg.hash(*TRAIN_SECTIONS):
        raise ValueError(f"{weights} was trained with different settings than this config; "
                         "re-run `bcsdf train` and `bcsdf export`")
    check_compatible(spec, wavelength=np.linspace(cfg.wavelengths.start_nm, cfg.wavelengths.stop_nm,
                                                  cfg.wavelengths.count))
    if backend == "mlp":
        return {"type": "fiber_bundle", "backend": backend, "model": str(weights)}
    onnx_path = root / "export" / size / "model.onnx"
    if not onnx_path.exists():
        raise ValueError(f"{onnx_path} does not exist; run `bcsdf export` with this config first")
    if OnnxMLP(onnx_path).spec.config_hash != cfg.hash(*TRAIN_SECTIONS):  # every artifact read is checked
        raise ValueError(f"{onnx_path} was exported from different settings than this config; re-run `bcsdf export`")
    return {"type": "fiber_bundle", "backend": backend, "model": str(onnx_path)}
