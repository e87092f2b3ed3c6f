"""Stage ``train``: fit each MLP size of ``train.models`` to the baked table (CPU PyTorch).

For every model name, writes under ``artifacts/<name>/train/<model>/``:

* ``model.pt``      the weights and the :class:`models.neural.NeuralSpec`;
* ``loss.png``      training and validation loss per epoch;
* ``summary.json``  held-out errors, the noise ratio, time, parameter count, and the
                    worst albedo error before and after the energy gain.

The fitting itself (folds, bin averages, the noise-weighted log-space loss, the energy
gain, the held-out split) is :mod:`models.fit`; the training bench runs the same
code. Same table, seed and threads: the same weights.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch

from models.fit import fit, held_out_metrics, prepare
from models.io import atomic_path

from ..artifacts import load_bundle_table, stage_dir
from ..config import TRAIN_SECTIONS
from ..metrics import folder as metrics_folder
from ..metrics import write_curve, write_metrics
from ..plots import save_figure
from ..summaries import TrainSummary

POOR_L1 = 0.25  # a model further off than this (and than 3x the table's noise) is said to be poor


def run(cfg, out_root="artifacts") -> Path:
    c = cfg.train
    # same table, seed and threads: the same weights. Every op here is deterministic on the
    # CPU (tests/test_neural.py trains twice and compares); torch.use_deterministic_algorithms
    # left them bit for bit as they are and cost a second a process importing torch's compiler
    torch.set_num_threads(c.threads)
    table, table_path = load_bundle_table(cfg, out_root)
    problem = prepare(table, table_path, c, cfg.hash(*TRAIN_SECTIONS))
    base, data = problem.base, problem.data
    out = stage_dir(cfg, "train", out_root)
    headline = {}
    for name, hidden in c.models.items():
        spec = dataclasses.replace(base, hidden=list(hidden))
        model, history, best, seconds, calibration = fit(spec, problem, c, name)

        summary = TrainSummary(
            val_weighted_loss=best, **held_out_metrics(spec, model, data, problem.val_idx),
            folds=base.folds, fold_chi2_per_dof=data.chi2_per_dof, samples=len(data.x),
            epochs=len(history), train_seconds=seconds, parameters=int(sum(p.numel() for p in model.parameters())),
            gain_values=spec.azimuth_gain_values, **calibration)
        d = out / name
        with atomic_path(d / "model.pt") as tmp:
            torch.save({"spec": spec.to_dict(), "state": model.state_dict(), "metrics": summary.model_dump()}, tmp)
        summary.write(d / "summary.json")
        plot_loss(history, d / "loss.png", name)
        write_curve(metrics_folder(cfg, out_root) / "loss" / f"{name}.csv",
                    [{"epoch": k + 1, "train": t, "validation": v} for k, (t, v) in enumerate(history)])
        headline[name] = summary.model_dump(include={"relative_l1", "noise_ratio", "parameters", "train_seconds",
                                                     "worst_albedo_error_after"}, exclude_none=True)
        line = (f"[train] {name} {hidden}: {summary.parameters} parameters, {summary.epochs} epochs in "
                f"{seconds:.1f} s; held-out relative L1 {summary.relative_l1:.3%}, error / table noise "
                f"{summary.noise_ratio:.2f}")
        if calibration:
            line += (f"; worst albedo error {summary.worst_albedo_error_before:.2%} -> "
                     f"{summary.worst_albedo_error_after:.2%} by the energy gain")
        print(line)
        if summary.relative_l1 > max(POOR_L1, 3 * summary.table_noise_l1):
            print(f"[train] warning: {name} is {summary.relative_l1:.0%} off on the held-out bins (the table's own "
                  f"noise: {summary.table_noise_l1:.0%}): not worth rendering; train longer (train.epochs), "
                  "a wider model, or bake more paths (bake.paths_per_phi_i)")
    write_metrics(cfg, out_root, "train", headline)
    return out


def plot_loss(history, path, name) -> None:
    h = np.asarray(history)
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    ax.semilogy(h[:, 0], label="train")
    ax.semilogy(h[:, 1], label="validation (held-out bins)")
    ax.set(xlabel="epoch", ylabel="loss (weighted log-space MSE of the bin means)", title=f"model {name}")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)
