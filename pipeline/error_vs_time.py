"""Error against run time: the table and every model size (the export stage's measurement).

For the baked table (nearest and multilinear lookup, numpy and Dr.Jit) and each
trained model (PyTorch, onnxruntime, Dr.Jit), on the same queries:

* error against the ground-truth table on the held-out bins (the training split's
  validation bins, each as its average over 4 x 4 points, as the table's values are
  bin averages; the table's own lookups are measured the same way, so their rows show
  the interpolation error): the relative L1 of the core (:func:`models.errors.core_l1`,
  the held-out bins among those holding 90% of each row's energy; the table's noise
  on the same bins, :func:`models.errors.noise_l1`, is printed beside it), log-space mean
  absolute error of ``log(1 + S/s0)``, the worst bin (largest absolute error over the
  table's peak), and the albedo error: the largest relative error of
  ``integral S d omega_o`` over (phi_i, theta_i, lambda), from every output bin;
* cost: nanoseconds per query at a batch of 1M random directions (all wavelengths per
  query), best of 3, and bytes of storage.

A model of the near field (``train.inputs: [offset]``) is measured by its far field, its
mean over the offset cells (:func:`models.neural.far_field`), against the table's far field
on the far field's split (the near field's own held-out error is the train stage's); its
cost is that of one evaluation at a random offset, what a render pays.

Its own time is mostly the compilation of the Dr.Jit kernels when the kernel cache is cold:
every numpy input goes through :func:`models.jit.to_drjit`, so that each kernel compiles
once, and a large MLP is evaluated here with cooperative vectors (``DrJitMLP``'s ``auto``
form outside a render), which compile in a second where its literal weights took a minute
(docs/BENCHMARKS.md, "The Dr.Jit MLP: literal weights or cooperative vectors").

Prints a table, writes ``error_vs_time.png`` (marker area ~ bytes) and
``error_vs_time.json`` under ``artifacts/<name>/export/``. The export stage runs it on
``report.queries`` queries (the report shows its figures); ``make bench-neural``
(:mod:`pipeline.bench.neural`) on 1M.
"""

from __future__ import annotations

import dataclasses
import json
import time

import drjit as dr
import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
import torch

from mitsuba_ext.neural import DrJitMLP, OnnxMLP, check_compatible
from mitsuba_ext.table import DrJitTable
from models.bundle_table import lookup
from models.errors import albedo_error, by_rows, core_l1, log_mae, noise_l1
from models.fit import file_hash, held_out_bins, load_checkpoint
from models.io import write_text
from models.jit import to_drjit
from models.neural import NeuralSpec, bin_average, far_field, make_export_module, make_torch_model, table_cells

from .artifacts import checkpoint_path, load_bundle_table, stage_dir
from .plots import save_figure


def _best_of(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measure(cfg, artifacts="artifacts", queries=1_000_000) -> dict:
    """Run the whole comparison; print it, write the PNG and JSON, return the rows."""

    mi.set_variant(cfg.bake.variant)
    torch.set_num_threads(2)
    table, table_path = load_bundle_table(cfg, artifacts)
    n_l = len(table.wavelength)

    # -- queries: held-out bins (errors) and 1M random directions (cost) ---------------
    truth = table.values.reshape(-1, n_l).astype(np.float64)
    first = next(iter(cfg.train.models))
    first_spec = NeuralSpec.from_dict(load_checkpoint(checkpoint_path(cfg, first, artifacts))["spec"])
    # every model of a config shares the split (of the far field's bins)
    val = held_out_bins(table, dataclasses.replace(first_spec, inputs=[], offset_cells=0, passthrough_offset=[],
                                                   passthrough_offset_theta_i=[]), cfg.train)
    omega = np.broadcast_to(table.solid_angle[None, None, :, :], table.values.shape[:4]).ravel()
    scattered = table.scattered  # [phi_i, theta_i, lambda]
    s0 = float(np.mean(table.values[table.values > 0]))
    rng = np.random.default_rng(0)
    n = queries
    rand = [rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n),
            rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n)]
    rand32 = [a.astype(np.float32) for a in rand]

    cells = table_cells(table)

    held = np.zeros(len(truth), bool)
    held[val] = True
    held = by_rows(np.broadcast_to(held[:, None], truth.shape).reshape(table.values.shape))
    row_omega, truth_rows = table.solid_angle.ravel(), by_rows(table.values)

    def errors(predict, spec=None):
        """predict(list of queries) -> [n, n_lambda]; every bin's average over 4 x 4 points,
        as the table's bins are averages (at the centres alone a model may peak unseen
        between them, and its albedo at the centres says little of its worst row's); a model
        of ``spec`` by its far field (:func:`models.neural.far_field`)."""
        def angles(*q):
            return predict([np.asarray(a, np.float32) for a in q])
        pred = bin_average(angles if spec is None else far_field(angles, spec), cells).astype(np.float64)
        p, t = pred[val], truth[val]
        albedo = (pred * omega[:, None]).reshape(table.values.shape[:2] + (-1, n_l)).sum(axis=2)
        return {
            "relative_l1": core_l1(by_rows(pred.reshape(table.values.shape)), truth_rows, row_omega, where=held),
            "log_mae": log_mae(p, t, s0),
            "worst_bin": float(np.max(np.abs(p - t)) / truth.max()),
            "albedo_error": albedo_error(albedo, scattered),
        }

    rows = []

    def report(name, backend, nbytes, predict, timed, spec=None):
        err = errors(predict, spec)
        seconds = _best_of(timed)
        rows.append({"method": name, "backend": backend, "bytes": int(nbytes),
                     "ns_per_query": seconds / n * 1e9, **err})
        r = rows[-1]
        print(f"{name:14s} {backend:11s} {r['bytes']:>10d} {r['ns_per_query']:9.1f} {r['relative_l1']:9.2%} "
              f"{r['log_mae']:8.4f} {r['worst_bin']:9.2%} {r['albedo_error']:9.2%}", flush=True)

    print(f"table {table_path}: {table.values.shape} float32 = {table.values.astype(np.float32).nbytes} bytes; "
          f"{len(val)} held-out bins; cost at a batch of {n} queries x {n_l} wavelengths")
    print(f"{'method':14s} {'backend':11s} {'bytes':>10s} {'ns/query':>9s} {'rel. L1':>9s} {'log MAE':>8s} "
          f"{'worst bin':>9s} {'albedo':>9s}")

    # -- the table ------------------------------------------------------------------
    dt = DrJitTable(table, mi.Float)

    def drjit_table(mode):
        def run(q):
            out = dt.eval(*(to_drjit(mi.Float, a) for a in q), mode=mode)
            dr.eval(out)
            return np.stack([o.numpy() for o in out], -1)
        qs = [to_drjit(mi.Float, a) for a in rand32]
        dr.eval(qs)

        def timed():
            out = dt.eval(*qs, mode=mode)
            dr.eval(out)
            dr.sync_thread()
        return run, timed

    for mode in ("nearest", "linear"):
        report(f"table {mode}", "numpy", dt.nbytes, lambda q, m=mode: lookup(table, *q, mode=m),
               lambda m=mode: lookup(table, *rand, mode=m))
        run, timed = drjit_table(mode)
        report(f"table {mode}", "drjit", dt.nbytes, run, timed)

    # -- the models -------------------------------------------------------------------
    export_root = stage_dir(cfg, "export", artifacts)
    for name in cfg.train.models:
        ckpt = load_checkpoint(checkpoint_path(cfg, name, artifacts))
        spec = NeuralSpec.from_dict(ckpt["spec"])
        if spec.folds != first_spec.folds:
            raise ValueError(f"models of one config must share their folds ({name}: {spec.folds}, "
                             f"{first}: {first_spec.folds}); re-run `bcsdf train`")
        check_compatible(spec, table_hash=file_hash(table_path), wavelength=table.wavelength)
        mlp = make_torch_model(spec)
        mlp.load_state_dict(ckpt["state"])
        module = make_export_module(spec, mlp).eval()
        nbytes = sum(p.numel() * 4 for p in mlp.parameters())

        extra = [rng.uniform(-1, 1, n).astype(np.float32) for _ in spec.inputs]  # the timed queries' offsets

        def torch_eval(q, module=module):
            with torch.no_grad():
                return module(torch.from_numpy(np.stack(q, -1).astype(np.float32))).numpy()
        report(f"mlp {name}", "pytorch", nbytes, torch_eval, lambda f=torch_eval: f(rand32 + extra), spec)

        onnx = OnnxMLP(export_root / name / "model.onnx", threads=2)
        report(f"mlp {name}", "onnxruntime", nbytes, lambda q, m=onnx: m.eval(*q),
               lambda m=onnx: m.eval(*rand32, *extra), spec)

        jit = DrJitMLP(export_root / name / "weights.npz")
        qs = [to_drjit(mi.Float, a) for a in rand32 + extra]
        dr.eval(qs)

        def jit_run(q, jit=jit):
            out = jit.eval(*(to_drjit(mi.Float, np.asarray(a, np.float32)) for a in q))
            dr.eval(out)
            return np.stack([o.numpy() for o in out], -1)

        def jit_timed(jit=jit):
            out = jit.eval(*qs)
            dr.eval(out)
            dr.sync_thread()
        jit_timed()  # compile once; the kernel cache serves the timed runs
        report(f"mlp {name}", "drjit", nbytes, jit_run, jit_timed, spec)

    out = stage_dir(cfg, "export", artifacts)
    noise = noise_l1(truth_rows, by_rows(table.stderr), row_omega, where=held)
    print(f"the table's own Monte Carlo noise on these bins: relative L1 {noise:.2%}")
    write_text(out / "error_vs_time.json", json.dumps({"rows": rows, "table_noise_l1": noise,
                                                       "queries": n}, indent=1))
    plot(rows, noise, out / "error_vs_time.png", n)
    table_bytes = rows[0]["bytes"]
    lin_jit = next(r for r in rows if r["method"] == "table linear" and r["backend"] == "drjit")
    for r in rows:
        if r["method"].startswith("mlp") and r["backend"] == "drjit":
            print(f"{r['method']}: {table_bytes / r['bytes']:.0f}x smaller than the float32 table, albedo error "
                  f"{r['albedo_error']:.2%}, Dr.Jit cost {r['ns_per_query'] / lin_jit['ns_per_query']:.2f}x the "
                  f"multilinear Dr.Jit table lookup")
    print(f"wrote {out / 'error_vs_time.png'}")
    return {"rows": rows, "table_noise_l1": noise, "queries": n}


def plot(rows, noise, path, queries):
    """Two panels against the cost per query: held-out relative L1 and worst albedo error."""

    fig, axes = plt.subplots(1, 2, figsize=(13, 5), dpi=110)
    markers = {"numpy": "s", "drjit": "o", "pytorch": "^", "onnxruntime": "D"}
    methods = sorted({r["method"] for r in rows})
    colors = {m: plt.get_cmap("tab10")(k) for k, m in enumerate(methods)}
    top = max(r["bytes"] for r in rows)
    floor = 1e-4  # the nearest lookup is the reference itself: plotted at the floor
    x_text = 1.2 * min(r["ns_per_query"] for r in rows)
    for ax, key, label in ((axes[0], "relative_l1", "relative L1 on the held-out core bins"),
                           (axes[1], "albedo_error", "worst albedo error over (theta_i, lambda)")):
        for r in rows:
            ax.scatter(r["ns_per_query"], max(r[key], floor), s=30 + 600 * np.sqrt(r["bytes"] / top),
                       marker=markers[r["backend"]], color=colors[r["method"]], alpha=0.75, edgecolors="k",
                       linewidths=0.5)
        ax.set(xscale="log", yscale="log", ylabel=label,
               xlabel=f"cost [ns per query, all wavelengths, batch of {queries:,}]")
        ax.text(x_text, 1.4 * floor,
                "nearest lookup: the reference itself (plotted at 1e-4)", fontsize=8, color="0.3")
    axes[0].axhline(noise, color="0.4", ls="--", lw=1)
    axes[0].text(x_text, noise * 1.08, "the table's own Monte Carlo noise",
                 fontsize=8, color="0.3")
    axes[1].axhline(0.02, color="0.4", ls="--", lw=1)
    axes[1].text(x_text, 0.02 * 1.08, "goal: 2%", fontsize=8, color="0.3")
    for m in methods:
        axes[0].scatter([], [], color=colors[m], label=m)
    for b, mk in markers.items():
        axes[0].scatter([], [], color="0.5", marker=mk, label=b)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle("error against run time (marker area ~ bytes)")
    fig.tight_layout()
    save_figure(fig, path)
