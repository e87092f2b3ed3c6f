"""The near field, measured: how many offset cells a ply's profile across its width needs.

For a parallel and a twisted ply (six ray-optics fibers of 20 um in a circle of 80 um, the
closure's plies; twisted at a pitch of 1500 um), each baked with ``bake.offsets`` of 2, 4,
8 and 16 cells (and read as the far field, one cell): ``fiber_bundle`` on a cylinder against
every fiber rendered explicitly (``pipeline.closure``, the near-field closure of
``tests/test_near.py``), the profile across the width in 16 columns of equal width, side,
back- and forward-lit at two incidences, each averaged over 16 turns of the arrangement
(a twisted ply's: shifts along it) and a 4 x 4 stratification of the table bin. Per cell
count: the relative error of the profile (bundle / explicit - 1) over the columns holding
light, its median and its largest, and the share of columns within 5% + 3 standard errors
of the explicit render (its own noise: its even and odd turns). At 8 and 16 cells also a
neural model of the near field (the offset as an input, ``train.inputs: [offset]``, the
default network and schedule, :func:`train`) rendered by the ``mlp`` backend, with its
training seconds and parameter bytes. Records ``benchmarks/near.json``::

    .venv/bin/python -m pipeline.bench.near            # about 4 minutes on 2 cores
    .venv/bin/python -m pipeline.bench.near --quick    # the parallel ply, fewer paths
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import mitsuba as mi
import numpy as np

import mitsuba_ext
from models.bake import BakeSpec, bake_unreduced, tally_to_table
from models.bake.twisted import TwistedBaker
from models.bundle import TwistedBundle, poisson
from models.fiber.ray import RayFiber
from models.fit import fit, prepare
from models.neural import save_onnx, save_weights
from pipeline.config import TrainCfg

from .. import closure
from . import results

WL = np.array([450.0, 550.0, 650.0])
COLUMNS = 16
CELLS = (1, 2, 4, 8, 16)           # 1: the far field
THETA_I_DEG = {"parallel": [10, 30, 60, 80], "twisted, pitch 1500 um": [-30, 20, 60]}


def plies() -> dict:
    parallel = poisson((80.0, 80.0), 20.0, packing=0.4, seed=2)
    lean = np.arctan(2 * np.pi * (80.0 - 20.0) / 1500.0)
    twisted = TwistedBundle(poisson((80.0, 80.0), 20.0, gap=40 * (1 / np.cos(lean) - 1) + 1, packing=0.3, seed=2),
                            1500.0)
    return {"parallel": parallel, "twisted, pitch 1500 um": twisted}


def bake(ply, fiber, theta_i_deg, cells: int, paths: int):
    mi.set_variant("llvm_ad_rgb")
    spec = BakeSpec(np.deg2rad(theta_i_deg), np.zeros(1), 18, 36, offsets=max(cells, 2))
    if isinstance(ply, TwistedBundle):
        baker = TwistedBaker(ply, fiber, spec)
        tally = baker.trace(0, paths // 2, 1)
        tally.add(baker.trace(0, paths // 2, 2))
        table = tally_to_table(tally, spec, fiber, {})
    else:
        table = bake_unreduced(ply, fiber, spec, paths, seed=3)
    table.meta["reductions"] = {"theta_i": None, "phi_i": "rotation", "phi_o": "relative"}
    return table


NEURAL_CELLS = (8, 16)


def train(table, table_path, out: Path, hidden=(32, 32), epochs: int = 300) -> dict:
    """A model of ``table``'s near field (the offset as an input), fitted as ``bcsdf train``
    fits (:mod:`models.fit`) with the default schedule, written as ``out/weights.npz`` and
    ``out/model.onnx``; returns its spec, the PyTorch model, seconds and parameter bytes."""
    c = TrainCfg(models={"m": list(hidden)}, epochs=epochs, inputs=["offset"])
    problem = prepare(table, table_path, c, "")
    spec = dataclasses.replace(problem.base, hidden=list(hidden))
    model, _, _, seconds, _ = fit(spec, problem, c, "near")   # sets the spec's energy gain
    out.mkdir(parents=True, exist_ok=True)
    nbytes = save_weights(out / "weights.npz", spec, model)
    save_onnx(out / "model.onnx", spec, model)
    return {"spec": spec, "model": model, "seconds": seconds, "bytes": nbytes}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the parallel ply, fewer paths (not recorded)")
    args = ap.parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    fiber = RayFiber(WL, [1.56] * 3, [0.3, 0.1, 0.0], 0.3, 0.3, 0.0, n_h=64).tabulate(np.deg2rad(np.arange(0, 91, 5.0)))
    rows = []
    with results.recorded("near", smoke=args.quick), tempfile.TemporaryDirectory() as tmp:
        fiber_path = Path(tmp) / "fiber.npz"
        fiber.save(fiber_path)
        for name, ply in list(plies().items())[: 1 if args.quick else None]:
            theta = THETA_I_DEG[name]
            paths = 1_000_000 if args.quick else 4_000_000
            first = bake(ply, fiber, theta, 2, paths)
            cases = [(j, k_phi, int(np.floor((np.pi / 2 - first.theta_i[j]) / np.pi * 18)))
                     for j in (1, 2) for k_phi in (1, 9, 15)]
            requests = closure.bin_requests(first, cases)
            mi.set_variant("llvm_ad_mono")
            mitsuba_ext.register()
            explicit_bsdf = {"type": "fiber_table", "filename": str(fiber_path), "wavelength": 550.0,
                             "up": closure.UP}
            measured = closure.explicit_intensities(mi, ply, explicit_bsdf, requests, spp=8, resolution=64,
                                                    cells=COLUMNS)
            I = np.array([m for m, _ in measured])
            se = np.array([e for _, e in measured])
            lit = I > 0.02 * I.max(axis=1, keepdims=True)
            R = (ply.bundle if isinstance(ply, TwistedBundle) else ply).bounding_radius * 1e-3
            for cells in CELLS:
                table = first if cells <= 2 else bake(ply, fiber, theta, cells, paths)
                table.save(Path(tmp) / "near.npz")
                mi.set_variant("llvm_ad_mono")
                mitsuba_ext.register()
                bsdf = {"type": "fiber_bundle", "table": str(Path(tmp) / "near.npz"), "wavelength": 550.0,
                        "up": closure.UP, "near_field": cells > 1}
                backends = [("table", bsdf, {})]
                if cells in NEURAL_CELLS:
                    fitted = train(table, Path(tmp) / "near.npz", Path(tmp) / f"model{cells}")
                    mi.set_variant("llvm_ad_mono")
                    mitsuba_ext.register()
                    weights = Path(tmp) / f"model{cells}" / "weights.npz"
                    backends.append((f"mlp {fitted['spec'].hidden}", {**bsdf, "backend": "mlp", "model": str(weights)},
                                     {"train_s": fitted["seconds"], "bytes": fitted["bytes"]}))
                for backend, b, extra in backends:
                    rendered = closure.bundle_profiles(mi, b, R, requests, COLUMNS)
                    err = (rendered / np.where(I > 0, I, 1) - 1)[lit]
                    within = np.abs(err) <= 0.05 + 3 * (se / np.where(I > 0, I, 1))[lit]
                    rows.append({"ply": name, "cells": "far field" if cells == 1 else cells, "backend": backend,
                                 "median |error|": float(np.median(np.abs(err))),
                                 "largest |error|": float(np.abs(err).max()),
                                 "within 5% + 3 se": f"{within.sum()}/{within.size}", **extra})
                    print(rows[-1], flush=True, file=sys.stderr)   # progress (the record is the table)
        print(f"\nthe profile in {COLUMNS} columns across the width, {len(cases)} direction pairs; {paths} paths per "
              "bake; explicit: 16 turns x 16 views, 8 spp; bundle: the same views, 32 spp")
        print(results.rows_table(rows))


if __name__ == "__main__":
    main()
