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

import json
from pathlib import Path

import numpy as np
import torch

from models.fit import load_checkpoint
from models.io import atomic_path
from models.neural import NeuralSpec, make_export_module, make_torch_model

from .. import error_vs_time
from ..artifacts import checkpoint_path, stage_dir
from ..config import TRAIN_SECTIONS
from ..metrics import folder as metrics_folder
from ..metrics import write_curve, write_metrics


def run(cfg, out_root="artifacts") -> Path:
    import onnx

    out = stage_dir(cfg, "export", out_root)
    for name in cfg.train.models:
        ckpt_path = checkpoint_path(cfg, name, out_root)
        ckpt = load_checkpoint(ckpt_path)
        spec = NeuralSpec.from_dict(ckpt["spec"])
        if spec.config_hash != cfg.hash(*TRAIN_SECTIONS):
            raise ValueError(f"{ckpt_path} was trained with different settings; re-run `bcsdf train`")
        mlp = make_torch_model(spec)
        mlp.load_state_dict(ckpt["state"])
        module = make_export_module(spec, mlp).eval()
        d = out / name
        meta = json.dumps(spec.to_dict())

        # -- ONNX --------------------------------------------------------------
        with atomic_path(d / "model.onnx") as tmp:
            torch.onnx.export(module, (torch.zeros(8, spec.n_queries),), tmp, input_names=["angles"], output_names=["S"],
                              dynamic_axes={"angles": {0: "batch"}, "S": {0: "batch"}}, opset_version=17,
                              dynamo=False)
            model = onnx.load(tmp)
            model.doc_string = (f"Bundle scattering function S(phi_i, theta_i, phi_o, theta_o"
                                f"{''.join(', ' + i for i in spec.inputs)}) in 1/sr, one output per wavelength; "
                                "angles in radians")
            entry = model.metadata_props.add()
            entry.key, entry.value = "bcsdf_spec", meta
            onnx.checker.check_model(model)
            onnx.save(model, tmp)

        # -- plain weights -------------------------------------------------------
        linears = [m for m in mlp if isinstance(m, torch.nn.Linear)]
        arrays = {f"L{k}": line.detach().numpy().astype(np.float32)
                  for k, line in enumerate(mlp[0].lines)} if spec.lines else {}
        for k, lin in enumerate(linears):
            arrays[f"W{k}"] = lin.weight.detach().numpy().astype(np.float32)
            arrays[f"b{k}"] = lin.bias.detach().numpy().astype(np.float32)
        with atomic_path(d / "weights.npz") as tmp:
            with open(tmp, "wb") as fh:
                # the metadata as UTF-8 bytes (a numpy str array is UTF-32: 4 bytes a character),
                # the archive deflated (the metadata's text shrinks; the float32 weights hardly)
                np.savez_compressed(fh, spec=np.array(meta.encode("utf-8")), **arrays)
        size = sum(a.nbytes for a in arrays.values())
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
