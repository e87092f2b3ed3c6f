"""Encodings side by side (``make bench-encoding``): the plain MLP against MLPs with feature lines.

On the config's baked table (``bcsdf bake`` first), with its ``train:`` schedule, split and
seed, in one run: the plain MLP of the config's first model size, and the same network
with feature lines (models/lines.py) of the node counts and channels in :data:`LINES`
(and one with a narrower network behind the lines). Each is trained by
:func:`models.fit.fit`, the code ``bcsdf train`` runs, under the torch kernels of this
process (``ATEN_CPU_CAPABILITY=avx2`` for a machine without AVX-512).

Per row: parameters and their float32 bytes, training seconds, held-out relative L1 (bin
averages, the ``summary.json`` metric), the error in units of the table's noise, the
table's own noise on those bins, and the worst albedo error after the calibration. Prints
one table, recorded as ``benchmarks/encoding.json``; ``--quick`` trains a tenth of the
epochs (a smoke run, not recorded).
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import torch

from models.fit import fit, held_out_metrics, prepare
from pipeline.artifacts import load_bundle_table
from pipeline.config import TRAIN_SECTIONS
from pipeline.loading import load_config

from . import results

# (label, line nodes [theta_i, cone distance, azimuth], channels, hidden widths or None: the config's)
LINES = [("plain", [], 0, None),
         ("lines 12/32/24 x 8", [12, 32, 24], 8, None),
         ("lines 12/64/72 x 16", [12, 64, 72], 16, None),
         ("lines 12/32/24 x 8, [16, 16]", [12, 32, 24], 8, [16, 16])]


def measure(cfg, table, table_path, label, nodes, channels, hidden, quick=False) -> dict:
    update = {"line_nodes": nodes, "line_channels": max(channels, 1)}
    if quick:
        update.update(epochs=max(2, cfg.train.epochs // 10), calibration_steps=max(1, cfg.train.calibration_steps // 10))
    c = cfg.train.model_copy(update=update)
    problem = prepare(table, table_path, c, cfg.hash(*TRAIN_SECTIONS))
    hidden = hidden or next(iter(cfg.train.models.values()))
    spec = dataclasses.replace(problem.base, hidden=list(hidden))
    model, history, _, seconds, calibration = fit(spec, problem, c, label)
    m = held_out_metrics(spec, model, problem.data, problem.val_idx)
    parameters = int(sum(p.numel() for p in model.parameters()))
    return {"encoding": label, "hidden": str(list(hidden)), "parameters": parameters, "bytes": 4 * parameters,
            "epochs": len(history), "train_s": seconds, "relative_l1": m["relative_l1"],
            "error_over_noise": m["noise_ratio"], "table_noise_l1": m["table_noise_l1"],
            "worst_albedo": calibration.get("worst_albedo_error_after")}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    parser.add_argument("--quick", action="store_true", help="a tenth of the epochs: a smoke run")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                        help="change a config key, as `bcsdf run --set`")
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    cfg = load_config(args.config, args.overrides)
    torch.set_num_threads(cfg.train.threads)
    table, table_path = load_bundle_table(cfg, args.artifacts)
    rows = [measure(cfg, table, table_path, *variant, quick=args.quick) for variant in LINES]
    table_md = results.rows_table(rows)
    print(f"{cfg.name}: {cfg.train.epochs} epochs, torch {torch.backends.cpu.get_cpu_capability()} kernels\n{table_md}")
    if not args.quick:
        results.save("encoding", table_md, {"rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
