"""Packing as an input of the model, measured (``make bench-packing``).

A family of the default ply baked over its packing fraction (``bcsdf sweep``:
:data:`TRAINED` packings, three Poisson draws each, since one draw differs from the next by
many times one bake's Monte Carlo error), one model trained on all of it with the packing as
an input (``models.fit.prepare_family``; the default network and schedule), and measured at
**held-out** packings (:data:`HELD_OUT`, between the trained ones, at three new seeds)
against the seed-averaged direct bakes there:

* the worst albedo error over incident directions and wavelengths (goal: 2%);
* the share of the core's bins (``models.errors``) where the model lies within the
  arrangement spread, the standard deviation of the seeds' tables (MC error included);
* the core's relative L1 against the seed-averaged table, beside that table's own distance
  from its seeds (the spread, in the same units);

and the same at the trained packings; the bakes keep their orders of scattering
(:data:`ORDERS`) and so does the model, so that one model file is dyed too: its albedo under
three dyes (:data:`DYES`) against the seed-averaged tables recoloured.

Then renders (``render_checks``): the yarn of the render stage with the model at each held-out
packing against the same yarn with the seed-averaged direct table (FLIP; undyed and dyed red),
the model's render time against the default model's (one ply's, trained alone, no orders),
and a strip of the yarn at five packings and three dyes from the one model file
(``docs/images/packing_strip.png``). Records ``benchmarks/packing.json``::

    .venv/bin/python -m pipeline.bench.packing [--artifacts DIR] [--quick]

The sweeps' members are baked under ``DIR/packing_family_*/sweep/`` (kept: a second run
only trains and measures).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import yaml

import mitsuba_ext
from models.bundle_table import BundleTable
from models.fit import fit, prepare, prepare_family
from models.neural import save_onnx, save_weights
from pipeline import family
from pipeline.artifacts import stage_dir
from pipeline.config import TRAIN_SECTIONS
from pipeline.images import render_timed
from pipeline.loading import load_config, sweep_members

from . import results

BASE = "configs/packing_sweep.yaml"
TRAINED = [0.08, 0.14, 0.2, 0.26, 0.32]   # sparse to near the tightest every draw reaches (0.35)
HELD_OUT = [0.17, 0.29]
SEEDS = {"train": [1, 2, 3], "held": [4, 5, 6]}
ORDERS = 8
STRIP = "docs/images/packing_strip.png"
FAMILY = "docs/images/packing_family.png"


def bake_family(kind: str, packings, artifacts: Path, paths: int) -> list[tuple[float, BundleTable]]:
    """Bake (or find baked) the sweep ``packings`` x :data:`SEEDS[kind]` of the base ply;
    ``[(packing, expanded table)]`` per member."""
    data = yaml.safe_load(Path(BASE).read_text())
    data["name"] = f"packing_family_{kind}"
    data["bake"]["paths_per_phi_i"] = paths
    data["bake"]["orders"] = ORDERS
    data["sweep"] = {"bundle.packing": list(packings), "bundle.seed": SEEDS[kind]}
    data.pop("family", None)  # the bench trains and measures the family itself
    path = artifacts / f"packing_family_{kind}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    # the sweep as a user runs it (its own command: up-to-date members are skipped)
    subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(artifacts), "sweep", str(path)],
                   check=True, stdout=sys.stderr)
    return family.members(cfg, stage_dir(cfg, "sweep", artifacts))


def render_checks(cfg, out: Path, model_path: Path, plain_path: Path, strip_path: Path) -> list[dict]:
    """The yarn (the render stage's scene) with the family's model against the seeds' mean
    direct table at each held-out packing, undyed and dyed red (FLIP at the table's exposure);
    the model's render time against the default model's (one ply, no orders); the strip of
    five packings x three dyes from the one model file, at one exposure."""
    wavelength = BundleTable.load(out / f"direct_{HELD_OUT[0]:g}.npz").wavelength
    red = [(float(w), float(v)) for w, v in zip(wavelength, family.dyes(wavelength)["ColorChecker red"])]
    rows = []
    for p in HELD_OUT:
        for dye, albedo in (("undyed", None), ("ColorChecker red", red)):
            rows.append({"render": f"yarn at held-out {p:g}, {dye}",
                         **family.render_against_table(cfg, model_path, out / f"direct_{p:g}.npz", p, out, albedo)})
    with mitsuba_ext.variant(cfg.render.variant):
        _, t_plain, _ = render_timed(mi, family.yarn(cfg, "mlp", plain_path, out), "mlp")
        _, t_family, _ = render_timed(mi, family.yarn(cfg, "mlp", model_path, out, packing=0.2), "mlp")
    rows.append({"render": "yarn, undyed: family's model (packing 0.2) / default model", "model s": t_family,
                 "default model s": t_plain, "time ratio": t_family / t_plain})
    family.strip(cfg, model_path, wavelength, np.linspace(TRAINED[0], TRAINED[-1], 5), True, strip_path, out)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--artifacts", default="artifacts")
    ap.add_argument("--quick", action="store_true", help="fewer paths and epochs (a smoke run, not recorded)")
    ap.add_argument("--figure", action="store_true", help="only redraw the family figure from the baked members and "
                                                           "the model file of an earlier run")
    args = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    artifacts = Path(args.artifacts)
    paths = 200_000 if args.quick else 1_000_000
    out = artifacts / "packing_family_train" / "model"
    out.mkdir(parents=True, exist_ok=True)
    if args.figure:
        family.figure(out / "model.onnx", bake_family("train", TRAINED, artifacts, paths) +
                      bake_family("held", HELD_OUT, artifacts, paths), HELD_OUT, Path(FAMILY))
        return
    with results.recorded("packing", smoke=args.quick):
        trained = bake_family("train", TRAINED, artifacts, paths)   # the sweeps' progress goes to stderr, off the record
        held = bake_family("held", HELD_OUT, artifacts, paths)
        cfg = load_config(artifacts / "packing_family_train.yaml")
        epochs = 30 if args.quick else cfg.train.epochs
        c = cfg.train.model_copy(update={"inputs": ["packing"], "orders": True, "epochs": epochs})
        problem = prepare_family(trained, c, cfg.hash(*TRAIN_SECTIONS))
        hidden = next(iter(cfg.train.models.values()))
        spec = dataclasses.replace(problem.base, hidden=list(hidden))
        t0 = time.perf_counter()
        model, _, _, seconds, _ = fit(spec, problem, c, "packing")
        nbytes = save_weights(out / "weights.npz", spec, model)
        save_onnx(out / "model.onnx", spec, model)
        rows = [{"set": "held out", **family.measure(model, spec, held, p)} for p in HELD_OUT]
        rows += [{"set": "trained", **family.measure(model, spec, trained, p)} for p in TRAINED]
        print(f"one model {hidden} of {ORDERS} orders ({nbytes} parameter bytes) on {len(trained)} bakes at packings "
              f"{TRAINED}, trained in {seconds:.1f} s; held out: {HELD_OUT} at seeds {SEEDS['held']}; {paths} paths "
              f"per bake; dyes: {', '.join(family.dyes([550.0]))}")
        print(results.rows_table(rows))

        # the direct tables at the held-out packings, and the default model: one ply (the middle
        # trained packing's first seed), the default network, no orders
        for p in HELD_OUT:
            family.seed_mean(held, p).save(out / f"direct_{p:g}.npz")
        one = cfg.train.model_copy(update={"epochs": epochs})
        ply = next(stage_dir(cfg, "sweep", artifacts) / m.name / "bake" / "bundle_table.npz"
                   for point, m in sweep_members(cfg) if point["bundle.packing"] == 0.2)
        single = prepare(BundleTable.load(ply, expand=True), ply, one, "")
        plain_spec = dataclasses.replace(single.base, hidden=list(hidden))
        plain, *_ = fit(plain_spec, single, one, "default")
        plain_bytes = save_weights(out / "default.npz", plain_spec, plain)
        strip = (artifacts / "packing_strip.png") if args.quick else Path(STRIP)
        figure = (artifacts / "packing_family.png") if args.quick else Path(FAMILY)
        family.figure(out / "model.onnx", trained + held, HELD_OUT, figure)
        renders = render_checks(cfg, out, out / "weights.npz", out / "default.npz", strip)
        print(f"renders: the yarn of the render stage ({cfg.render.variant}, {cfg.render.width} x "
              f"{cfg.render.height}, {cfg.render.spp} spp); parameters {nbytes} bytes against the default "
              f"model's {plain_bytes} ({nbytes / plain_bytes:.1f}x)")
        print(results.rows_table(renders))
        print(f"wrote {out / 'weights.npz'}, {out / 'model.onnx'}, {strip}, {figure} "
              f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
