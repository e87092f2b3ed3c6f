"""Encodings side by side (``make bench-encoding``): the plain MLP, MLPs with feature lines,
and two published architectures as baselines.

On the config's baked table (``bcsdf bake`` first), with its ``train:`` schedule, split and
seed, in one run: the plain MLP of the config's first model size, the same network with
feature lines (models/lines.py) of the node counts and channels in :data:`LINES` (and one
with a narrower network behind the lines), the energy gain resolved by azimuth
(``train.gain_azimuth_bins``: the table's 36 bins and 18, plain and with lines; its bytes
counted with the weights; and the 36 bins' stored as products of rank 2, 4 and 8 in log
space, ``train.gain_rank``), and the baselines: a neural yarn model's MLP (the Cartesian
``w_i, w_o``, three hidden layers of 21) and NBRDF's (Rusinkiewicz's half and difference
vectors, two of 21), both without the symmetry folds, as their papers have them. Each is trained by :func:`models.fit.fit`, the code ``bcsdf train`` runs (so all
share the loss, the bin averages and the energy gain: what differs is the encoding and the
network), under the torch kernels of this process (``ATEN_CPU_CAPABILITY=avx2`` for a
machine without AVX-512).

Per row: parameters and their float32 bytes, training seconds, the held-out error, the table's
noise on those bins and their ratio (:mod:`models.errors`, the ``summary.json`` figures), and
the worst albedo error after the energy gain (9 x 9 points a bin). A Pareto plot, error
against bytes and against training seconds (``docs/images/encodings_pareto.png``).

``--reference NAME``: the artifacts of an **independent bake** of the same config (another
seed, more paths; e.g. ``bcsdf bake configs/default.yaml --set name=default_ref --set
bake.seed=7 --set bake.paths_per_phi_i=16000000``, fiber first) as the truth: each model's
bin averages over *every* bin (12 x 12 midpoints: the ridge is narrower than a bin, and none
is a point of the energy gain's 8 x 8) against it, :func:`models.errors.core_l1` (the bins
holding 90% of each incident direction and wavelength's energy), and its albedo against the
reference's scattered fraction; the training table itself is the first row (its noise).
Where the error lies: the same core L1 of the spectra's means over wavelength (``grey``), and
of each bin's spectrum given the reference's shape with its own mean kept (``true spectra``):
a model that smooths the spectra's ripples (the fiber's Mie resonances, which move from one
azimuth bin and wavelength to the next) loses there what it keeps in the grey. Two rows say
how many numbers those shapes take: the reference's grey times the training table's spectral
shape averaged over each (``|theta_i|``, azimuth bin), at the table's azimuth bins and at 9
(:func:`shared_spectra`).

Prints one table, recorded as ``benchmarks/encoding.json``; ``--quick`` trains a tenth of
the epochs (a smoke run, not recorded).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

import numpy as np
import torch

from models import errors
from models.bundle_table import BundleTable
from models.fit import azimuth_bin, fit, held_out_metrics, model_bin_averages, prepare
from models.neural import table_cells
from pipeline.artifacts import bundle_table_path, load_bundle_table
from pipeline.config import TRAIN_SECTIONS
from pipeline.loading import load_config
from pipeline.plots import pareto

from . import results

# (label, line nodes [theta_i, cone distance, azimuth], channels, hidden widths or None: the config's,
# encoding of the directions[, bins of the azimuthal gain[, its rank]])
LINES = [("plain", [], 0, None, "cone"),
         ("lines 12/32/24 x 8", [12, 32, 24], 8, None, "cone"),
         ("lines 12/64/72 x 16", [12, 64, 72], 16, None, "cone"),
         ("lines 12/32/24 x 8, [16, 16]", [12, 32, 24], 8, [16, 16], "cone"),
         # the energy gain resolved by azimuth (train.gain_azimuth_bins): the table's 36 bins and 18
         ("plain, gain in 36 azimuth bins", [], 0, None, "cone", 36),
         ("plain, gain in 18 azimuth bins", [], 0, None, "cone", 18),
         # and stored as a product of rank 2, 4, 8 in log space (train.gain_rank)
         *((f"plain, gain in 36 azimuth bins, rank {r}", [], 0, None, "cone", 36, r) for r in (2, 4, 8)),
         ("lines 12/32/24 x 8, gain in 36 azimuth bins", [12, 32, 24], 8, None, "cone", 36),
         # the baselines: a neural yarn model's MLP (Cartesian w_i, w_o; 6-21-21-21) and NBRDF's
         # (Rusinkiewicz half and difference vectors; 6-21-21), trained as ours are
         ("neuralyarn-style: w_i, w_o, no folds", [], 0, [21, 21, 21], "cartesian"),
         ("NBRDF-style: half/difference vectors, no folds", [], 0, [21, 21], "halfdiff")]


def against(reference, S) -> dict:
    """``S`` (the expanded table's shape) against the reference table: core L1, worst albedo;
    and where the error lies: the core L1 of the spectra's means over wavelength (``grey``),
    and of ``S`` with each bin's spectrum given the reference's shape, its mean kept
    (``true_spectra``: what is left when the spectra's shapes are right)."""
    n_l = S.shape[-1]
    omega = reference.solid_angle.ravel()
    true = reference.values.astype(np.float64)
    albedo = (S * reference.solid_angle[None, None, :, :, None]).sum((2, 3))
    grey = lambda a: a.mean(-1, keepdims=True)  # noqa: E731
    shape = true / np.maximum(grey(true), np.finfo(float).tiny)
    core = lambda a, b: errors.core_l1(errors.by_rows(a), errors.by_rows(b), omega)  # noqa: E731
    return {"truth_core_l1": core(S, true),
            "truth_albedo": errors.albedo_error(albedo.reshape(-1, n_l), reference.scattered.reshape(-1, n_l)),
            "truth_grey_l1": core(grey(S), grey(true)), "truth_l1_true_spectra": core(grey(S) * shape, true)}


def shared_spectra(table, reference, n_azimuth: int) -> dict:
    """How many numbers the spectra's shapes take: the reference's grey (its mean over
    wavelength, as if a model had it exactly) times the training table's spectral shape
    averaged over each class of (``|theta_i|``, ``n_azimuth`` bins of ``|phi_o - phi_i|``),
    against the reference; ``bytes``: the classes' shapes in float32."""
    grey = lambda a: a.mean(-1, keepdims=True)  # noqa: E731
    S = table.values.astype(np.float64)
    weight = grey(S) * table.solid_angle[None, None, :, :, None]
    azimuth = azimuth_bin(table_cells(table), n_azimuth).reshape(S.shape[:4])   # the gain's bins of a bin
    _, incidence = np.unique(np.round(np.abs(table.theta_i), 9), return_inverse=True)
    classes = (incidence[None, :, None, None] * n_azimuth + azimuth).ravel()
    shape = S / np.maximum(grey(S), np.finfo(float).tiny)
    n_l = S.shape[-1]
    num, den = np.zeros((classes.max() + 1, n_l)), np.zeros(classes.max() + 1)
    np.add.at(num, classes, (shape * weight).reshape(-1, n_l))
    np.add.at(den, classes, weight.reshape(-1))
    mean_shape = (num / np.maximum(den, np.finfo(float).tiny)[:, None])[classes].reshape(S.shape)
    true = reference.values.astype(np.float64)
    return {"encoding": f"the truth's grey x the table's spectra per (|theta_i|, {n_azimuth} azimuth bins)",
            "bytes": int(4 * n_l * len(np.unique(classes))),
            "truth_core_l1": errors.core_l1(errors.by_rows(grey(true) * mean_shape), errors.by_rows(true),
                                            reference.solid_angle.ravel())}


def measure(cfg, table, table_path, label, nodes, channels, hidden, encoding="cone", azimuth_bins=0, rank=0,
            quick=False, reference=None) -> dict:
    update = {"line_nodes": nodes, "line_channels": max(channels, 1), "encoding": encoding,
              "gain_azimuth_bins": azimuth_bins, "gain_rank": rank}
    if quick:
        update.update(epochs=max(2, cfg.train.epochs // 10))
    c = cfg.train.model_copy(update=update)
    problem = prepare(table, table_path, c, cfg.hash(*TRAIN_SECTIONS))
    hidden = hidden or next(iter(cfg.train.models.values()))
    spec = dataclasses.replace(problem.base, hidden=list(hidden))
    model, history, _, seconds, calibration = fit(spec, problem, c, label)
    m = held_out_metrics(spec, model, problem.data, problem.val_idx)
    parameters = int(sum(p.numel() for p in model.parameters()))
    truth = ({} if reference is None else
             against(reference, model_bin_averages(spec, model, table_cells(table), k=12).reshape(table.values.shape)))
    nbytes = 4 * (parameters + spec.azimuth_gain_values)   # float32 weights and the azimuthal gain
    return {**{"encoding": label, "hidden": str(list(hidden)), "parameters": parameters, "bytes": nbytes,
            "epochs": len(history), "train_s": seconds, "relative_l1": m["relative_l1"],
            "error_over_noise": m["noise_ratio"], "table_noise_l1": m["table_noise_l1"],
            "worst_albedo": calibration.get("worst_albedo_error_after")}, **truth}


def parse_lines(text: str) -> tuple:
    """``24/32/24x8`` -> a :data:`LINES` entry (the config's hidden widths)."""
    try:
        nodes, channels = text.split("x")
        counts = [int(n) for n in nodes.split("/")]
        assert len(counts) == 3 and min(counts) >= 2 and int(channels) >= 1
    except (ValueError, AssertionError):
        raise argparse.ArgumentTypeError(f"{text!r}: give three node counts and the channels, e.g. 24/32/24x8")
    return (f"lines {nodes} x {channels}", counts, int(channels), None, "cone")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    parser.add_argument("--quick", action="store_true", help="a tenth of the epochs: a smoke run")
    parser.add_argument("--lines", nargs="+", metavar="T/X/DxC", type=parse_lines,
                        help="instead of the built-in variants: line encodings to compare with the plain MLP, "
                             "e.g. 24/32/24x8 (nodes of the theta_i, cone-distance and azimuth lines, channels)")
    parser.add_argument("--reference", metavar="NAME",
                        help="artifacts name of an independent bake of the config: the truth (see above)")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                        help="change a config key, as `bcsdf run --set`")
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    cfg = load_config(args.config, args.overrides)
    torch.set_num_threads(cfg.train.threads)
    table, table_path = load_bundle_table(cfg, args.artifacts)
    reference = None
    if args.reference:
        path = bundle_table_path(cfg.model_copy(update={"name": args.reference}), args.artifacts)
        if not path.exists():
            raise SystemExit(f"{path} does not exist: bake the reference first (see --help)")
        reference = BundleTable.load(path, expand=True)
        if reference.meta.get("config_hash") == table.meta.get("config_hash"):
            raise SystemExit(f"{args.reference} was baked with the very settings of {cfg.name}: not independent "
                             "(give it another bake.seed)")
        if reference.values.shape != table.values.shape:
            raise SystemExit(f"{args.reference}: its table {reference.values.shape} has another grid than "
                             f"{cfg.name}'s {table.values.shape}; bake it from the same config")
    rows = [{"encoding": "the training table", "bytes": int(table.values.size * 4),
             **against(reference, table.values.astype(np.float64))}] if reference is not None else []
    if reference is not None:
        rows += [shared_spectra(table, reference, n) for n in (len(table.phi_o) // 2, 9)]
    variants = [LINES[0], *args.lines] if args.lines else LINES
    rows += [measure(cfg, table, table_path, *variant, quick=args.quick, reference=reference) for variant in variants]
    table_md = results.rows_table(rows)
    print(f"{cfg.name}: {cfg.train.epochs} epochs, torch {torch.backends.cpu.get_cpu_capability()} kernels\n{table_md}")
    if not args.quick and not args.lines:  # the record is of the built-in variants
        results.save("encoding", f"{table_md}\n\n![error against bytes and training time](images/{PARETO.name})",
                     {"rows": rows})
        pareto_plot(rows, PARETO, "truth_core_l1" if reference is not None else "relative_l1")
        print(f"wrote {PARETO}")
    return 0


PARETO = Path(__file__).resolve().parents[2] / "docs" / "images" / "encodings_pareto.png"


def pareto_plot(rows, path, key: str):
    """Error (``key``) against parameter bytes and training seconds, the training table's own
    error (its noise against the truth) as a line."""
    table = next((r for r in rows if r.get("train_s") is None), None)
    pareto([{"label": r["encoding"], "bytes": r["bytes"], "train_s": r["train_s"], "error": r[key]}
            for r in rows if r.get("train_s") is not None], path,
           "relative L1 of the core against " + ("the truth" if key.startswith("truth") else "the held-out bins"),
           "Encodings of the table: error against size and training time (one run)",
           None if table is None or key not in table else (table[key], "the training table itself (its noise)"))


if __name__ == "__main__":
    raise SystemExit(main())
