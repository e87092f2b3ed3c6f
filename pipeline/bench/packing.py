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

and the same at the trained packings. Records ``benchmarks/packing.json``::

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

import numpy as np
import yaml

from models import errors
from models.bundle_table import BundleTable
from models.fit import fit, model_bin_averages, prepare_family
from models.neural import save_onnx, save_weights, table_cells
from pipeline.artifacts import stage_dir
from pipeline.config import TRAIN_SECTIONS
from pipeline.loading import load_config, sweep_members

from . import results

BASE = "configs/packing_sweep.yaml"
TRAINED = [0.08, 0.14, 0.2, 0.26, 0.32]   # sparse to near the tightest every draw reaches (0.35)
HELD_OUT = [0.17, 0.29]
SEEDS = {"train": [1, 2, 3], "held": [4, 5, 6]}


def family(kind: str, packings, artifacts: Path, paths: int) -> list[tuple[float, BundleTable]]:
    """Bake (or find baked) the sweep ``packings`` x :data:`SEEDS[kind]` of the base ply;
    ``[(packing, expanded table)]`` per member."""
    data = yaml.safe_load(Path(BASE).read_text())
    data["name"] = f"packing_family_{kind}"
    data["bake"]["paths_per_phi_i"] = paths
    data["sweep"] = {"bundle.packing": list(packings), "bundle.seed": SEEDS[kind]}
    path = artifacts / f"packing_family_{kind}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    # the sweep as a user runs it (its own command: up-to-date members are skipped)
    subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(artifacts), "sweep", str(path)],
                   check=True, stdout=sys.stderr)
    root = stage_dir(cfg, "sweep", artifacts)
    return [(point["bundle.packing"], BundleTable.load(root / m.name / "bake" / "bundle_table.npz", expand=True))
            for point, m in sweep_members(cfg)]


def measure(model, spec, members, packing: float) -> dict:
    """The model at ``packing`` against the seed average of ``members`` there."""
    tables = [t for p, t in members if np.isclose(p, packing)]
    mean = np.mean([t.values.astype(np.float64) for t in tables], 0)
    spread = np.std([t.values.astype(np.float64) for t in tables], 0, ddof=1)
    t0 = tables[0]
    cells = table_cells(t0)
    extra = np.full((len(cells), 1, 2), packing)
    S = model_bin_averages(spec, model, cells, k=4, extra_cell=extra).reshape(mean.shape)
    omega = t0.solid_angle.ravel()
    rows = errors.by_rows
    core = errors.core_mask(rows(mean), omega)
    within = np.abs(rows(S) - rows(mean)) <= rows(spread)
    albedo = (S * t0.solid_angle[None, None, :, :, None]).sum((2, 3))
    scattered = np.mean([t.scattered for t in tables], 0)
    seeds_l1 = np.mean([errors.core_l1(rows(t.values), rows(mean), omega) for t in tables])
    return {"packing": packing, "seeds": len(tables),
            "worst albedo error": errors.albedo_error(albedo.reshape(-1, albedo.shape[-1]),
                                                      scattered.reshape(-1, albedo.shape[-1])),
            "core bins within the spread": float(within[core].mean()),
            "core L1 vs seed mean": errors.core_l1(rows(S), rows(mean), omega),
            "one seed's core L1 vs the mean": float(seeds_l1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--artifacts", default="artifacts")
    ap.add_argument("--quick", action="store_true", help="fewer paths and epochs (a smoke run, not recorded)")
    args = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    artifacts = Path(args.artifacts)
    paths = 200_000 if args.quick else 1_000_000
    with results.recorded("packing", smoke=args.quick):
        trained = family("train", TRAINED, artifacts, paths)   # the sweeps' progress goes to stderr, off the record
        held = family("held", HELD_OUT, artifacts, paths)
        cfg = load_config(artifacts / "packing_family_train.yaml")
        c = cfg.train.model_copy(update={"inputs": ["packing"], "epochs": 30 if args.quick else cfg.train.epochs})
        problem = prepare_family(trained, c, cfg.hash(*TRAIN_SECTIONS))
        hidden = next(iter(cfg.train.models.values()))
        spec = dataclasses.replace(problem.base, hidden=list(hidden))
        t0 = time.perf_counter()
        model, _, _, seconds, _ = fit(spec, problem, c, "packing")
        out = artifacts / "packing_family_train" / "model"
        out.mkdir(parents=True, exist_ok=True)
        nbytes = save_weights(out / "weights.npz", spec, model)
        save_onnx(out / "model.onnx", spec, model)
        rows = [{"set": "held out", **measure(model, spec, held, p)} for p in HELD_OUT]
        rows += [{"set": "trained", **measure(model, spec, trained, p)} for p in TRAINED]
        print(f"one model {hidden} ({nbytes} parameter bytes) on {len(trained)} bakes at packings {TRAINED}, trained "
              f"in {seconds:.1f} s; held out: {HELD_OUT} at seeds {SEEDS['held']}; {paths} paths per bake")
        print(results.rows_table(rows))
        print(f"wrote {out / 'weights.npz'}, {out / 'model.onnx'} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
