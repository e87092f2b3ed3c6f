"""Packing as an input of the model, measured (``make bench-packing``).

The family of ``configs/packing_sweep.yaml`` run as a user runs it: ``bcsdf sweep`` bakes the
default ply over its packing fraction, three Poisson draws at each (one draw differs from the
next by many times one bake's Monte Carlo error; nine at a held-out packing, so that the truth
the model is measured against there is known to well within the goal), and ``bcsdf family``
trains one model on all of them but the ``family.held_out`` packings, with the packing as an input and the orders
of scattering as outputs, and measures it at every packing against the mean of its seeds'
bakes (``pipeline.family.measure``):

* the worst albedo error over incident directions and wavelengths (goal: 2% at a held-out
  packing), and the same dyed by three dyes (``pipeline.family.dyes``);
* the share of the core's bins (``models.errors``) where the model lies within the
  arrangement spread, the standard deviation of the seeds' tables (MC error included);
* the core's relative L1 against the seeds' mean, beside one seed's own distance from it
  (the spread, in the same units).

Then what a bench adds to the stage (``render_checks``): the yarn of the render stage with the
model at each held-out packing against the same yarn with the seeds' mean table, dyed red
(FLIP; undyed is the stage's own), and the model's render time and size against the default
model's (one ply of the family, trained alone, no orders, the config's first network of
``train.models``: the default one). The family figure and the strip of
five packings and three dyes are the stage's, copied to ``docs/images/``. Records
``benchmarks/packing.json``::

    .venv/bin/python -m pipeline.bench.packing [--artifacts DIR] [--quick]

The sweep's members are baked under ``DIR/packing_sweep/sweep/`` (kept: a second run only
trains and measures; ``--quick`` bakes its own, fewer paths, under ``packing_sweep_quick``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

import mitsuba_ext
from models.bundle_table import BundleTable
from models.fit import fit, prepare
from models.neural import save_weights
from pipeline import family
from pipeline.artifacts import stage_dir
from pipeline.images import render_timed
from pipeline.loading import load_config, sweep_members
from pipeline.summaries import FamilySummary

from . import results

CONFIG = "configs/packing_sweep.yaml"
STRIP = "docs/images/packing_strip.png"
FAMILY = "docs/images/packing_family.png"
QUICK = ["name=packing_sweep_quick", "bake.paths_per_phi_i=200000", "train.epochs=30"]


def bcsdf(stage: str, artifacts: Path, sets: list[str]) -> None:
    """A stage of the family's config as a user runs it (an up-to-date one is skipped by
    ``bcsdf run``'s notion; here the command itself: a sweep skips its finished members)."""
    subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(artifacts), stage, CONFIG,
                    *(a for kv in sets for a in ("--set", kv))], check=True, stdout=sys.stderr)


TIMED_RENDERS = 5   # each model's render time: the median of this many, the two models' interleaved


def render_checks(cfg, out: Path, summary, plain_path: Path) -> list[dict]:
    """The yarn (the render stage's scene) with the family's model against the seeds' mean
    direct table at each held-out packing, dyed red (FLIP at the table's exposure); the
    model's render time against the default model's (one ply, no orders; the median of
    :data:`TIMED_RENDERS` warm renders each, interleaved)."""
    model_path = out / "weights.npz"
    wavelength = BundleTable.load(out / f"direct_{summary.held_out[0]:g}.npz").wavelength
    red = [(float(w), float(v)) for w, v in zip(wavelength, family.dyes(wavelength)["ColorChecker red"])]
    rows = [{"render": f"yarn at held-out {r['packing']:g}, undyed (the stage's)",
             **{k: v for k, v in r.items() if k != "packing"}} for r in summary.renders]
    with tempfile.TemporaryDirectory(prefix="bcsdf-bench-") as tmp:
        for p in summary.held_out:
            rows.append({"render": f"yarn at held-out {p:g}, ColorChecker red",
                         **family.render_against_table(cfg, model_path, out / f"direct_{p:g}.npz", p, Path(tmp), red)})
        middle = summary.trained[len(summary.trained) // 2]
        with mitsuba_ext.variant(cfg.render.variant):
            scenes = [mi.load_dict(family.yarn(cfg, "mlp", path, Path(tmp), **extra))
                      for path, extra in ((plain_path, {}), (model_path, {"packing": middle}))]
            for scene in scenes:   # compiled once each, before any render is timed
                render_timed(mi, scene, "mlp", warm=False)
            seconds = [[], []]
            for k in range(TIMED_RENDERS):   # interleaved: a slow spell of a shared machine hits both
                for scene, times in zip(scenes, seconds):
                    times.append(render_timed(mi, scene, "mlp", warm=False, seed=k)[1])
    t_plain, t_family = (float(np.median(t)) for t in seconds)
    rows.append({"render": f"yarn, undyed: family's model (packing {middle:g}) / default model", "model s": t_family,
                 "default model s": t_plain, "time ratio": t_family / t_plain})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--artifacts", default="artifacts")
    ap.add_argument("--quick", action="store_true", help="fewer paths and epochs (a smoke run, not recorded)")
    args = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    artifacts = Path(args.artifacts)
    sets = QUICK if args.quick else []
    cfg = load_config(CONFIG, sets)
    with results.recorded("packing", smoke=args.quick):
        t0 = time.perf_counter()
        bcsdf("sweep", artifacts, sets)      # the commands' progress goes to stderr, off the record
        bcsdf("family", artifacts, sets)
        out = stage_dir(cfg, "family", artifacts)
        summary = FamilySummary.read(out / "summary.json", CONFIG)
        seeds = len(cfg.sweep.get("bundle.seed", [cfg.bundle.seed]))
        more = len(cfg.family.held_out_seeds)
        print(f"one model {summary.hidden} of {summary.orders} orders ({summary.parameter_bytes} parameter bytes) "
              f"on {seeds * len(summary.trained)} bakes at packings {summary.trained}, trained in "
              f"{summary.train_seconds:.1f} s ({summary.epochs} epochs); held out: {summary.held_out}; "
              f"{cfg.bake.paths_per_phi_i} paths per bake; {seeds} seeds a trained packing, {seeds + more} a "
              f"held-out one; dyes: "
              f"{', '.join(family.dyes([550.0]))}; the model averaged over {family.QUADRATURE} x "
              f"{family.QUADRATURE} midpoints a bin")
        print(results.rows_table(summary.rows))

        # the default model: one ply (the middle trained packing's first seed), the default
        # network (train.models' first), no orders
        middle = summary.trained[len(summary.trained) // 2]
        ply = next(stage_dir(cfg, "sweep", artifacts) / m.name / "bake" / "bundle_table.npz"
                   for point, m in sweep_members(cfg) if np.isclose(point["bundle.packing"], middle))
        single = prepare(BundleTable.load(ply, expand=True), ply, cfg.train, "")
        default = next(iter(cfg.train.models))
        plain_spec = dataclasses.replace(single.base, hidden=list(cfg.train.models[default]))
        plain, *_ = fit(plain_spec, single, cfg.train, "default")
        plain_bytes = save_weights(out.parent / "bench_default.npz", plain_spec, plain)
        renders = render_checks(cfg, out, summary, out.parent / "bench_default.npz")
        print(f"renders: the yarn of the render stage ({cfg.render.variant}, {cfg.render.width} x "
              f"{cfg.render.height}, {cfg.render.spp} spp); parameters {summary.parameter_bytes} bytes against the "
              f"default model's {plain_bytes} ({default} {plain_spec.hidden}; {summary.parameter_bytes / plain_bytes:.1f}x)")
        print(results.rows_table(renders))
        if not args.quick:
            for src, dst in ((out / "strip.png", STRIP), (out / "family.png", FAMILY)):
                shutil.copyfile(src, dst)
        print(f"wrote {out}" + ("" if args.quick else f", {STRIP}, {FAMILY}") +
              f" ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
