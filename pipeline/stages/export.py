"""Stage ``export``: each trained model to ONNX and to plain weights for Dr.Jit.

Writes under ``artifacts/<name>/export/<model>/``:

* ``model.onnx``   raw angles ``[batch, 4] = (phi_i, theta_i, phi_o, theta_o)`` in
  radians, then the model's extra inputs (``train.inputs``: ``[batch, 5]`` with the
  exit line's offset ``h``) -> ``S [batch, n_lambda]`` in 1/sr, encoding and output transform inside the
  graph, batch axis dynamic, checked by ``onnx.checker``; its metadata
  (``bcsdf_spec``) holds the encoding, output transform, wavelengths, table hash and
  symmetry reductions. Runs on onnxruntime alone.
* ``weights.npz``  the same network as arrays ``W0, b0, W1, b1, ...`` (float32, ``W``
  shaped [out, in]), the feature lines' nodes ``L0, L1, L2`` ([n_k, C], models/lines.py)
  where the model has them, with the same metadata, for :class:`mitsuba_ext.neural.DrJitMLP`.
"""

from __future__ import annotations

from pathlib import Path


from models.fit import load_checkpoint
from models.neural import NeuralSpec, make_torch_model, save_onnx, save_weights

from .. import error_vs_time
from ..artifacts import checkpoint_path, stage_dir
from ..config import TRAIN_SECTIONS
from ..metrics import folder as metrics_folder
from ..metrics import write_curve, write_metrics


def run(cfg, out_root="artifacts") -> Path:

    out = stage_dir(cfg, "export", out_root)
    for name in cfg.train.models:
        ckpt_path = checkpoint_path(cfg, name, out_root)
        ckpt = load_checkpoint(ckpt_path)
        spec = NeuralSpec.from_dict(ckpt["spec"])
        if spec.config_hash != cfg.hash(*TRAIN_SECTIONS):
            raise ValueError(f"{ckpt_path} was trained with different settings; re-run `bcsdf train`")
        mlp = make_torch_model(spec)
        mlp.load_state_dict(ckpt["state"])
        d = out / name
        save_onnx(d / "model.onnx", spec, mlp)
        size = save_weights(d / "weights.npz", spec, mlp)
        print(f"[export] {name}: {d / 'model.onnx'} ({(d / 'model.onnx').stat().st_size} bytes), "
              f"weights.npz ({(d / 'weights.npz').stat().st_size} bytes, of them float32 parameters {size})")

    # -- error against run time of the table and every export (the report's figure) ----
    result = error_vs_time.measure(cfg, out_root, cfg.report.queries)
    rows = result["rows"]
    write_curve(metrics_folder(cfg, out_root) / "error_vs_time.csv",
                [{"method": f"{r['method']} ({r['backend']})", "ns_per_query": r["ns_per_query"],
                  "relative_l1": r["relative_l1"], "albedo_error": r["albedo_error"]} for r in rows])
    write_metrics(cfg, out_root, "export", {
        f"{r['method']} ({r['backend']})": {k: r[k] for k in ("ns_per_query", "relative_l1", "albedo_error", "bytes")}
        for r in rows})
    return out
