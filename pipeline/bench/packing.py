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
import itertools
import os
import subprocess
import sys
import time
from pathlib import Path

import colour
import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
import yaml

import mitsuba_ext
from mitsuba_ext.neural import OnnxMLP
from models import errors
from models.bundle_table import BundleTable, dyed
from models.fit import fit, model_bin_averages, prepare, prepare_family
from models.neural import between, bin_average, order_channels, order_sum, save_onnx, save_weights, table_cells
from pipeline import scenes
from pipeline.artifacts import stage_dir
from pipeline.config import TRAIN_SECTIONS
from pipeline.images import exposure_of, flip_and_psnr, render_timed, to_srgb
from pipeline.loading import load_config, sweep_members
from pipeline.plots import save_figure

from . import results

BASE = "configs/packing_sweep.yaml"
TRAINED = [0.08, 0.14, 0.2, 0.26, 0.32]   # sparse to near the tightest every draw reaches (0.35)
HELD_OUT = [0.17, 0.29]
SEEDS = {"train": [1, 2, 3], "held": [4, 5, 6]}
ORDERS = 8
STRIP = "docs/images/packing_strip.png"


def dyes(wavelength) -> dict:
    """The three dyes, per-event albedos at ``wavelength`` (nm): a grey, a published red (the
    ColorChecker's red patch, Ohta's measurement, as colour-science ships it) and a dark grey."""
    red = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]["red"]
    wl = np.asarray(wavelength, float)
    return {"grey 0.95": np.full(len(wl), 0.95), "ColorChecker red": np.interp(wl, red.wavelengths, red.values),
            "dark 0.3": np.full(len(wl), 0.3)}


def family(kind: str, packings, artifacts: Path, paths: int) -> list[tuple[float, BundleTable]]:
    """Bake (or find baked) the sweep ``packings`` x :data:`SEEDS[kind]` of the base ply;
    ``[(packing, expanded table)]`` per member."""
    data = yaml.safe_load(Path(BASE).read_text())
    data["name"] = f"packing_family_{kind}"
    data["bake"]["paths_per_phi_i"] = paths
    data["bake"]["orders"] = ORDERS
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


def seed_mean(members, packing: float) -> BundleTable:
    """The seed average of ``members`` at ``packing``: the direct table a model of the family
    is measured against (its values, orders, tail ratio, passthrough and balance averaged)."""
    tables = [t for p, t in members if np.isclose(p, packing)]
    mean = lambda name: np.mean([getattr(t, name).astype(np.float64) for t in tables], 0)  # noqa: E731
    n = len(tables)
    return tables[0]._replace(
        values=mean("values").astype(np.float32), stderr=(mean("stderr") / np.sqrt(n)).astype(np.float32),
        orders=mean("orders").astype(np.float32), orders_stderr=(mean("orders_stderr") / np.sqrt(n)).astype(np.float32),
        tail_ratio=mean("tail_ratio"), passthrough=mean("passthrough"), passthrough_stderr=mean("passthrough_stderr"),
        absorbed=mean("absorbed"), lost=mean("lost"), single=None if tables[0].single is None else mean("single"))


def measure(model, spec, members, packing: float) -> dict:
    """The model at ``packing`` against the seed average of ``members`` there: undyed, and its
    orders dyed (the tail's ratio linear between the trained packings, as the plugin reads it)
    against the seed average recoloured, the worst over :func:`dyes`."""
    tables = [t for p, t in members if np.isclose(p, packing)]
    mean = np.mean([t.values.astype(np.float64) for t in tables], 0)
    spread = np.std([t.values.astype(np.float64) for t in tables], 0, ddof=1)
    t0 = tables[0]
    cells = table_cells(t0)
    extra = np.full((len(cells), 1, 2), packing)
    out = model_bin_averages(spec, model, cells, k=4, extra_cell=extra, orders=True)
    orders = order_channels(spec, out.reshape(mean.shape[:-1] + (-1,)))
    S = order_sum(spec, out).reshape(mean.shape)
    omega = t0.solid_angle.ravel()
    rows = errors.by_rows
    core = errors.core_mask(rows(mean), omega)
    within = np.abs(rows(S) - rows(mean)) <= rows(spread)
    integral = lambda a: (a * t0.solid_angle[None, None, :, :, None]).sum((2, 3))  # noqa: E731
    flat = lambda a: a.reshape(-1, a.shape[-1])  # noqa: E731
    scattered = np.mean([t.scattered for t in tables], 0)
    rho = between(np.clip, packing, spec.packings, [np.asarray(r) for r in spec.tail_ratio], False)   # the plugin's
    # a recoloured table's scattered fraction is the dye applied to its orders' integrals (linear)
    order_albedos = [np.einsum("kabpql,pq->kabl", t.orders.astype(np.float64), t.solid_angle) for t in tables]
    dyed_errors = [errors.albedo_error(flat(integral(dyed(orders, a, rho[:, :, None, None, :]))),
                                       flat(np.mean([dyed(list(o), a, t.tail_ratio)
                                                     for o, t in zip(order_albedos, tables)], 0)))
                   for a in dyes(t0.wavelength).values()]
    seeds_l1 = np.mean([errors.core_l1(rows(t.values), rows(mean), omega) for t in tables])
    return {"packing": packing, "seeds": len(tables),
            "worst albedo error": errors.albedo_error(flat(integral(S)), flat(scattered)),
            "worst dyed albedo error": max(dyed_errors),
            "core bins within the spread": float(within[core].mean()),
            "core L1 vs seed mean": errors.core_l1(rows(S), rows(mean), omega),
            "one seed's core L1 vs the mean": float(seeds_l1)}


FAMILY = "docs/images/packing_family.png"
THETA_FIGURE = (10.0, 40.0, 70.0)   # incident longitudes of the family figure, degrees


def family_figure(onnx_path: Path, members: list, path: Path) -> None:
    """The family against packing: the scattered fraction (at :data:`THETA_FIGURE`, mean over
    wavelengths) and the passthrough, the seed-averaged direct tables with the arrangement spread
    (the seeds' standard deviation) as error bars, trained and held-out packings, and the model
    read from its file (onnxruntime) across its whole range."""
    model = OnnxMLP(onnx_path)
    spec, t0 = model.spec, members[0][1]
    packings = sorted({p for p, _ in members})
    lo, hi = spec.input_range["packing"]
    grid = np.linspace(lo, hi, 25)
    rows = [int(np.argmin(np.abs(np.rad2deg(t0.theta_i) - t))) for t in THETA_FIGURE]
    cells = table_cells(t0).reshape(len(t0.phi_i), len(t0.theta_i), -1, 6)[0]
    fig, (ax_a, ax_p) = plt.subplots(1, 2, figsize=(10, 3.8))
    for j, colour_ in zip(rows, ("C0", "C1", "C2")):
        at = lambda p: bin_average(  # noqa: E731
            lambda *q: model.eval(*(np.asarray(a, np.float32) for a in q)).astype(np.float64),
            cells[j], 4, np.full((len(cells[j]), 1, 2), p))
        albedo = [float((at(p) * t0.solid_angle.ravel()[:, None]).sum(0).mean()) for p in grid]
        ax_a.plot(grid, albedo, color=colour_, label=f"model, theta_i {np.rad2deg(t0.theta_i[j]):.0f} deg")
        per_seed = {p: [t.scattered[0, j].mean() for q, t in members if q == p] for p in packings}
        ax_a.errorbar(packings, [np.mean(v) for v in per_seed.values()],
                      [np.std(v, ddof=1) for v in per_seed.values()], fmt="o", color=colour_, capsize=3)
    passthrough = {p: [t.passthrough.mean() for q, t in members if q == p] for p in packings}
    ax_p.errorbar(packings, [np.mean(v) for v in passthrough.values()],
                  [np.std(v, ddof=1) for v in passthrough.values()], fmt="o", color="k", capsize=3,
                  label="direct bakes (seed mean +- spread)")
    at_nodes = [float(np.mean(q)) for q in spec.passthrough_packing]
    ax_p.plot(grid, [between(np.clip, p, spec.packings, at_nodes, False) for p in grid], "k-",
              label="model (linear between trained packings)")
    for ax, what in ((ax_a, "scattered fraction (mean over wavelengths)"), (ax_p, "passthrough probability")):
        ax.set_xlabel("packing fraction")
        ax.set_ylabel(what)
        for p in HELD_OUT:
            ax.axvline(p, color="0.85", zorder=0)
    ax_a.legend(fontsize=8)
    ax_p.legend(fontsize=8)
    fig.suptitle("a family of plies: direct bakes (points, arrangement spread as bars; grey lines: held-out packings) "
                 "and one model", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def render_checks(cfg, out: Path, model_path: Path, plain_path: Path, strip_path: Path) -> list[dict]:
    """The yarn (the render stage's scene) with the family's model against the seed-averaged
    direct table at each held-out packing, undyed and dyed red (FLIP at the table's
    exposure); the model's render time against the default model's (one ply, no orders);
    the strip of five packings x three dyes from the one model file, at one exposure."""
    r = cfg.render
    wavelength = BundleTable.load(out / f"direct_{HELD_OUT[0]:g}.npz").wavelength
    spectra = {name: [(float(w), float(v)) for w, v in zip(wavelength, a)] for name, a in dyes(wavelength).items()}

    def yarn(backend: str, path: Path, **extra) -> dict:
        bsdf = {"type": "fiber_bundle", "backend": backend, ("table" if backend == "table" else "model"): str(path),
                **({"albedo": {"type": "spectrum", "value": extra.pop("albedo")}} if "albedo" in extra else {}),
                **extra}
        return scenes.named_scene(mi, cfg, "yarn", bsdf, r.spp, out)

    rows = []
    with mitsuba_ext.variant(r.variant):
        for p in HELD_OUT:
            for dye in ("undyed", "ColorChecker red"):
                albedo = {} if dye == "undyed" else {"albedo": spectra[dye]}
                table, t_table, _ = render_timed(mi, yarn("table", out / f"direct_{p:g}.npz", **albedo), "table")
                model, t_model, _ = render_timed(mi, yarn("mlp", model_path, packing=p, **albedo), "mlp")
                flip, psnr, _ = flip_and_psnr(table, model, exposure_of(table))
                rows.append({"render": f"yarn at held-out {p:g}, {dye}", "FLIP vs direct table": flip,
                             "PSNR dB": psnr, "model s": t_model, "table s": t_table})
        _, t_plain, _ = render_timed(mi, yarn("mlp", plain_path), "mlp")
        _, t_family, _ = render_timed(mi, yarn("mlp", model_path, packing=0.2), "mlp")
        rows.append({"render": "yarn, undyed: family's model (packing 0.2) / default model", "model s": t_family,
                     "default model s": t_plain, "time ratio": t_family / t_plain})
        # the strip: one model file, five packings, three dyes, one exposure (the grey at the middle packing's)
        packings = np.linspace(TRAINED[0], TRAINED[-1], 5)
        images = {(dye, p): render_timed(mi, yarn("mlp", model_path, packing=float(p), albedo=spectra[dye]),
                                         "mlp", warm=False)[0] for dye in spectra for p in packings}
    exposure = exposure_of(images["grey 0.95", packings[2]])
    fig, axes = plt.subplots(len(spectra), len(packings), figsize=(2.4 * len(packings), 1.5 * len(spectra) + 0.4))
    for (i, dye), (j, p) in itertools.product(enumerate(spectra), enumerate(packings)):
        ax = axes[i, j]
        ax.imshow(to_srgb(images[dye, p], exposure))
        ax.set_xticks([]), ax.set_yticks([])
        if i == 0:
            ax.set_title(f"packing {p:.2f}", fontsize=9)
        if j == 0:
            ax.set_ylabel(dye, fontsize=9)
    fig.suptitle("one model file (weights.npz): fiber_bundle's packing and albedo at render time", fontsize=10)
    save_figure(fig, strip_path)
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
        family_figure(out / "model.onnx", family("train", TRAINED, artifacts, paths) +
                      family("held", HELD_OUT, artifacts, paths), Path(FAMILY))
        return
    with results.recorded("packing", smoke=args.quick):
        trained = family("train", TRAINED, artifacts, paths)   # the sweeps' progress goes to stderr, off the record
        held = family("held", HELD_OUT, artifacts, paths)
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
        rows = [{"set": "held out", **measure(model, spec, held, p)} for p in HELD_OUT]
        rows += [{"set": "trained", **measure(model, spec, trained, p)} for p in TRAINED]
        print(f"one model {hidden} of {ORDERS} orders ({nbytes} parameter bytes) on {len(trained)} bakes at packings "
              f"{TRAINED}, trained in {seconds:.1f} s; held out: {HELD_OUT} at seeds {SEEDS['held']}; {paths} paths "
              f"per bake; dyes: {', '.join(dyes([550.0]))}")
        print(results.rows_table(rows))

        # the direct tables at the held-out packings, and the default model: one ply (the middle
        # trained packing's first seed), the default network, no orders
        for p in HELD_OUT:
            seed_mean(held, p).save(out / f"direct_{p:g}.npz")
        one = cfg.train.model_copy(update={"epochs": epochs})
        ply = next(stage_dir(cfg, "sweep", artifacts) / m.name / "bake" / "bundle_table.npz"
                   for point, m in sweep_members(cfg) if point["bundle.packing"] == 0.2)
        single = prepare(BundleTable.load(ply, expand=True), ply, one, "")
        plain_spec = dataclasses.replace(single.base, hidden=list(hidden))
        plain, *_ = fit(plain_spec, single, one, "default")
        plain_bytes = save_weights(out / "default.npz", plain_spec, plain)
        strip = (artifacts / "packing_strip.png") if args.quick else Path(STRIP)
        figure = (artifacts / "packing_family.png") if args.quick else Path(FAMILY)
        family_figure(out / "model.onnx", trained + held, figure)
        renders = render_checks(cfg, out, out / "weights.npz", out / "default.npz", strip)
        print(f"renders: the yarn of the render stage ({cfg.render.variant}, {cfg.render.width} x "
              f"{cfg.render.height}, {cfg.render.spp} spp); parameters {nbytes} bytes against the default "
              f"model's {plain_bytes} ({nbytes / plain_bytes:.1f}x)")
        print(results.rows_table(renders))
        print(f"wrote {out / 'weights.npz'}, {out / 'model.onnx'}, {strip}, {figure} "
              f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
