"""Training schedules side by side (``make bench-train``): held-out error against wall time.

For each model size of the config, in one run on the same folded table, split and seed:

* a long **reference** schedule (:data:`OLD`: 1500 epochs of batch 1024 at lr 3e-3,
  patience 300; the rows call it ``old``) and
* the config's own ``train:`` schedule (**new**),

each trained by :func:`models.fit.fit`, the code ``bcsdf train`` runs. During
phase 1 the best state so far is copied at about 12 log-spaced moments; their held-out
relative L1 (bin averages, 4 x 4 points, the ``summary.json`` metric) is computed after the
clock has stopped, so measuring costs the schedules nothing. After the energy gain: the final
held-out L1, the worst albedo error and the seconds of each phase. First, where a minibatch
step's time goes (points and features, forward, backward, optimizer) for each size.

Prints one table, recorded as ``benchmarks/train.json`` (``pipeline.bench.results``), and
draws ``docs/images/train_schedules.png`` (held-out L1 against seconds, one panel per size). ``--sizes`` limits
the sizes; ``--quick`` trains 1/10 of each schedule's epochs (a smoke run, not a measurement).
``--calibration 4 8`` instead compares the energy gain with the model's albedo integrated at
4 x 4 and 8 x 8 midpoints per bin, from one phase-1 state per size (seconds, held-out L1,
worst albedo error integrated at 16 x 16 midpoints).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch

from models import fit as fitting
from models.fit import BinFit, adam, fit, held_out_metrics, prepare
from models.neural import make_torch_model
from pipeline.artifacts import load_bundle_table
from pipeline.config import TRAIN_SECTIONS
from pipeline.loading import load_config
from pipeline.plots import save_figure

from . import results

IMAGES = Path(__file__).resolve().parents[2] / "docs" / "images"

# the reference schedule: long and slow, the yardstick of the config's own
OLD = {"epochs": 1500, "batch_size": 1024, "lr": 3e-3, "patience": 300, "bin_strata": 2}


def measure_schedule(cfg, problem, name, hidden, schedule: dict, quick=False) -> dict:
    """Train one size under one schedule; its curve and final figures."""

    if quick:
        schedule = {**schedule, "epochs": max(2, schedule["epochs"] // 10)}
    c = cfg.train.model_copy(update=schedule)
    spec = dataclasses.replace(problem.base, hidden=list(hidden))
    marks = iter(np.geomspace(0.5, 2000.0, 40))
    next_mark = [next(marks)]
    snapshots = []

    def on_epoch(epoch, seconds, best_state):
        if seconds >= next_mark[0] and best_state is not None:
            snapshots.append((epoch + 1, seconds, copy.deepcopy(best_state)))
            while seconds >= next_mark[0]:
                next_mark[0] = next(marks, np.inf)

    model, history, _, seconds, calibration = fit(spec, problem, c, name, on_epoch)
    final = held_out_metrics(spec, model, problem.data, problem.val_idx)
    curve = []
    probe = copy.deepcopy(model)
    for epoch, t, state in snapshots:
        probe.load_state_dict(state)
        curve.append({"epoch": epoch, "seconds": t,
                      "relative_l1": held_out_metrics(spec, probe, problem.data, problem.val_idx)["relative_l1"]})
    cal_s = calibration.get("calibration_seconds", 0.0)
    return {"schedule": schedule, "epochs": len(history), "seconds": seconds, "phase1_seconds": seconds - cal_s,
            "calibration_seconds": cal_s, "relative_l1": final["relative_l1"],
            "worst_albedo_error": calibration.get("worst_albedo_error_after"), "curve": curve}


def equal_accuracy_speedup(old: dict, new: dict):
    """How much sooner the config's schedule reaches its accuracy than the reference one
    does. The old schedule's seconds to its first phase-1 snapshot at or below the
    new one's final held-out L1, plus its energy gain, over the new schedule's seconds
    (the snapshots are ~24% of time apart: as coarse); ``None`` if no snapshot gets there."""
    reached = [p["seconds"] for p in old["curve"] if p["relative_l1"] <= new["relative_l1"]]
    return (reached[0] + old["calibration_seconds"]) / new["seconds"] if reached else None


def profile_steps(cfg, problem, name, hidden, steps=30) -> dict:
    """Milliseconds per minibatch step by phase (points and features, forward, backward,
    optimizer) and of one held-out evaluation, under the config's batch size and strata."""
    c = cfg.train
    spec = dataclasses.replace(problem.base, hidden=list(hidden))
    p = BinFit(spec, problem)
    model = make_torch_model(spec)
    opt = adam(model, c.lr)
    gen = torch.Generator().manual_seed(0)
    T = dict.fromkeys(("data", "forward", "backward", "optimizer"), 0.0)
    for k in range(steps + 3):
        b = p.tr[torch.randperm(len(p.tr), generator=gen)[:c.batch_size]]
        t0 = time.perf_counter()
        x = p.encode(b, p.stratified(len(b), c.bin_strata, gen))
        t1 = time.perf_counter()
        loss = p.loss(b, p.bin_means(b, model(x))[0])
        t2 = time.perf_counter()
        opt.zero_grad()
        loss.backward()
        t3 = time.perf_counter()
        opt.step()
        t4 = time.perf_counter()
        if k >= 3:  # the first steps warm the allocator
            for key, dt in zip(T, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                T[key] += dt * 1e3 / steps
    x_val = p.encode(p.va, p.stratified(len(p.va), c.bin_strata, gen))
    t0 = time.perf_counter()
    with torch.no_grad():
        p.loss(p.va, p.bin_means(p.va, model(x_val))[0])
    steps_per_epoch = -(-len(p.tr) // c.batch_size)
    return {**T, "validation": (time.perf_counter() - t0) * 1e3, "steps_per_epoch": steps_per_epoch,
            "epoch": sum(T.values()) * steps_per_epoch}


def compare_calibration(cfg, problem, sizes, strata) -> dict:
    """Phase 1 once per size, then the energy gain from that same state with the model's
    albedo integrated at each k x k midpoints per bin: its seconds, the held-out L1 and the
    worst albedo error, the latter integrated at 16 x 16 midpoints (not the gain's own)."""
    c = cfg.train
    rows = {}
    for name in sizes:
        spec = dataclasses.replace(problem.base, hidden=list(c.models[name]))
        torch.manual_seed(c.seed)
        model, p = make_torch_model(spec), fitting.BinFit(spec, problem)
        fitting.fit_bins(model, p, c, name)
        rows[name] = {}
        for k in strata:
            t0 = time.perf_counter()
            fitting.energy_gain(model, spec, p, strata=k)
            seconds = time.perf_counter() - t0
            albedo = p.model_albedo(fitting.model_bin_averages(spec, model, problem.data.cell, k=16))
            r = {"seconds": seconds, "relative_l1": fitting.held_out_metrics(spec, model, problem.data,
                                                                       problem.val_idx)["relative_l1"],
                 "worst_albedo_error": p.worst_albedo_error(albedo)}
            rows[name][k] = r
            print(f"{name:8s} energy gain at {k} x {k} points: {seconds:5.1f} s, held-out L1 {r['relative_l1']:.2%}, "
                  f"worst albedo error {r['worst_albedo_error']:.2%}", flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    parser.add_argument("--sizes", nargs="*", help="model names of train.models (default: all)")
    parser.add_argument("--quick", action="store_true", help="a tenth of the epochs: a smoke run")
    parser.add_argument("--calibration", type=int, nargs="+", metavar="K",
                        help="instead: the energy gain at K x K points per bin, side by side from one phase 1")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                    help="change a config key, as `bcsdf run --set` (make run-sizes: the three model sizes)")
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    with results.recorded("train-calibration" if args.calibration else "train", smoke=args.quick):
        return schedules(args)


def schedules(args):

    cfg = load_config(args.config, args.overrides)
    torch.set_num_threads(cfg.train.threads)
    table, table_path = load_bundle_table(cfg, args.artifacts)
    problem = prepare(table, table_path, cfg.train, cfg.hash(*TRAIN_SECTIONS))
    new = {k: getattr(cfg.train, k) for k in OLD}
    sizes = args.sizes or list(cfg.train.models)
    if args.calibration:
        return compare_calibration(cfg, problem, sizes, args.calibration)
    profile = {}
    print(f"where a step's time goes (ms; batch {cfg.train.batch_size}, {cfg.train.bin_strata}^2 points per bin):")
    for name in sizes:
        profile[name] = q = profile_steps(cfg, problem, name, cfg.train.models[name])
        print(f"  {name:8s} " + ", ".join(f"{k} {q[k]:.2f}" for k in ("data", "forward", "backward", "optimizer"))
              + f"; {q['steps_per_epoch']} steps = {q['epoch']:.0f} ms per epoch, held-out loss {q['validation']:.1f} ms")
    rows = {}
    print(f"{'size':8s} {'schedule':8s} {'epochs':>6s} {'phase 1 s':>9s} {'gain s':>8s} {'total s':>8s} "
          f"{'rel. L1':>8s} {'albedo':>7s}")
    for name in sizes:
        hidden = cfg.train.models[name]
        rows[name] = {}
        for label, schedule in (("old", OLD), ("new", new)):
            r = measure_schedule(cfg, problem, name, hidden, schedule, args.quick)
            rows[name][label] = r
            albedo = f"{r['worst_albedo_error']:.2%}" if r["worst_albedo_error"] is not None else "-"
            print(f"{name:8s} {label:8s} {r['epochs']:6d} {r['phase1_seconds']:9.1f} {r['calibration_seconds']:8.1f} "
                  f"{r['seconds']:8.1f} {r['relative_l1']:8.2%} {albedo:>7s}", flush=True)
        old, cur = rows[name]["old"], rows[name]["new"]
        at = equal_accuracy_speedup(old, cur)
        print(f"{name:8s} speed-up x{old['seconds'] / cur['seconds']:.1f}; held-out L1 {cur['relative_l1']:.2%} "
              f"against {old['relative_l1']:.2%}; at the new schedule's accuracy "
              + (f"x{at:.1f}" if at else "- (the old schedule's phase 1 never gets there)"), flush=True)
        cur["equal_accuracy_speedup"] = at
    total = {label: sum(rows[n][label]["seconds"] for n in sizes) for label in ("old", "new")}
    print(f"all sizes: old {total['old']:.0f} s, new {total['new']:.0f} s (x{total['old'] / total['new']:.1f})")
    if not args.quick:
        plot(rows, IMAGES / "train_schedules.png")
    return rows


def plot(rows: dict, path: Path) -> None:

    fig, axes = plt.subplots(1, len(rows), figsize=(4.6 * len(rows), 4), dpi=110, squeeze=False)
    for ax, (name, by) in zip(axes[0], rows.items()):
        for label, color in (("old", "0.45"), ("new", "tab:red")):
            r = by[label]
            c = r["curve"]
            ax.plot([p["seconds"] for p in c], [p["relative_l1"] for p in c], "o-", ms=3, color=color,
                    label=f"{label}: phase 1")
            ax.plot([r["seconds"]], [r["relative_l1"]], "*", ms=12, color=color,
                    label=f"{label}: with its energy gain, {r['seconds']:.0f} s")
        ax.axhline(by["old"]["relative_l1"], color="0.45", ls=":", lw=1)
        ax.set(xscale="log", yscale="log", xlabel="wall time [s] (2 threads)", ylabel="held-out relative L1",
               title=f"model {name}")
        ax.legend(fontsize=7)
    fig.suptitle("training schedules: held-out error against time" + ("\n" if len(rows) < 2 else ", ")
                 + "same table, split and seed", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
