"""A family of plies and its one model: the sweep's members by packing, the seeds' mean table,
the model measured against it, the family figure and the render strip.

A family is a sweep of one ply type over ``bundle.packing``, several Poisson draws
(``bundle.seed``) at each: one draw differs from the next by many times one bake's Monte
Carlo error, so the truth at a packing is the **seeds' mean** and its uncertainty their
**arrangement spread** (the standard deviation of the seeds' tables). The family stage
(``bcsdf family``) and the packing bench (``make bench-packing``) both measure with this.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import colour
import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np

import mitsuba_ext
from mitsuba_ext.neural import OnnxMLP
from models import errors
from models.bundle_table import BundleTable, dyed
from models.neural import between, bin_average, order_channels, order_sum, table_cells

from . import scenes
from .images import exposure_of, flip_and_psnr, render_timed, to_srgb
from .loading import sweep_members
from .plots import save_figure

THETA_FIGURE = (10.0, 40.0, 70.0)   # incident longitudes of the family figure, degrees
# k x k midpoints per bin where the model is averaged to be measured: across the specular
# ridge 4 x 4 midpoints are a coarse quadrature, and its error (tenths of a percent of a row's
# albedo, more than the model's own at a trained packing) would be counted as the model's.
# The midpoint rule's error falls as 1 / k^2; 12 shares no point with the energy gain's 8 x 8
# grid (models.fit.GAIN_STRATA), so a trained packing is not measured where its gain was set
QUADRATURE = 12


def dyes(wavelength) -> dict:
    """The three dyes, per-event albedos at ``wavelength`` (nm): a grey, a published red (the
    ColorChecker's red patch, Ohta's measurement, as colour-science ships it) and a dark grey."""
    red = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]["red"]
    wl = np.asarray(wavelength, float)
    return {"grey 0.95": np.full(len(wl), 0.95), "ColorChecker red": np.interp(wl, red.wavelengths, red.values),
            "dark 0.3": np.full(len(wl), 0.3)}


def members(cfg, root: Path) -> list[tuple[float, BundleTable]]:
    """``[(packing, expanded table)]`` of every member of ``cfg``'s sweep, baked under ``root``
    (``artifacts/<name>/sweep``); a member not baked yet is named with the command that bakes it."""
    out = []
    for point, m in sweep_members(cfg):
        path = root / m.name / "bake" / "bundle_table.npz"
        if not path.exists():
            raise FileNotFoundError(f"{path}: sweep member {m.name} is not baked; run `bcsdf sweep {cfg.name}` first")
        out.append((float(point["bundle.packing"]), BundleTable.load(path, expand=True)))
    return out


def at(family, packing: float) -> list[BundleTable]:
    """The members of ``family`` at ``packing`` (its seeds)."""
    return [t for p, t in family if np.isclose(p, packing)]


def seed_mean(family, packing: float) -> BundleTable:
    """The seeds' mean at ``packing``: the direct table a model of the family is measured
    against (its values, orders, tail ratio, passthrough and balance averaged; its standard
    error the Monte Carlo error of that mean)."""
    tables = at(family, packing)
    mean = lambda name: np.mean([getattr(t, name).astype(np.float64) for t in tables], 0)  # noqa: E731
    n = len(tables)
    orders = {} if tables[0].orders is None else dict(
        orders=mean("orders").astype(np.float32), orders_stderr=(mean("orders_stderr") / np.sqrt(n)).astype(np.float32),
        tail_ratio=mean("tail_ratio"))
    return tables[0]._replace(
        values=mean("values").astype(np.float32), stderr=(mean("stderr") / np.sqrt(n)).astype(np.float32),
        passthrough=mean("passthrough"), passthrough_stderr=mean("passthrough_stderr"),
        absorbed=mean("absorbed"), lost=mean("lost"), single=None if tables[0].single is None else mean("single"),
        **orders)


def measure(model: OnnxMLP, family, packing: float) -> dict:
    """The model file (read by onnxruntime: what a renderer is given) at ``packing`` against
    the seeds' mean there:

    * the worst albedo error over incident directions and wavelengths (``models.errors``),
      and (two seeds or more) the seeds' mean albedo's own standard error, the arrangement
      spread over the root of their number (its median over the rows), with the model's
      error in its units (rms over the rows: about 1 where the model is as near as the truth
      is known);
    * with orders, the same dyed by each of :func:`dyes` (the tail's ratio linear between the
      trained packings, as the plugin reads it) against the seeds' mean recoloured;
    * the share of the core's bins where the model lies within the arrangement spread;
    * the core's relative L1 against the seeds' mean, beside one seed's own distance from it
      (the spread in the same units; needs two seeds or more).
    """
    tables = at(family, packing)
    values = [t.values.astype(np.float64) for t in tables]
    mean = np.mean(values, 0)
    t0 = tables[0]
    cells = table_cells(t0)
    extra = np.full((len(cells), 1, 2), packing)
    spec = model.spec
    out = bin_average(lambda *q: model.eval(*(np.asarray(a, np.float32) for a in q), orders=bool(spec.orders))
                      .astype(np.float64), cells, QUADRATURE, extra)
    S = order_sum(spec, out).reshape(mean.shape)
    omega = t0.solid_angle.ravel()
    rows = errors.by_rows
    core = errors.core_mask(rows(mean), omega)
    integral = lambda a: (a * t0.solid_angle[None, None, :, :, None]).sum((2, 3))  # noqa: E731
    flat = lambda a: a.reshape(-1, a.shape[-1])  # noqa: E731
    albedo = integral(S)                                  # [phi_i, theta_i, lambda]
    seeds = np.array([t.scattered for t in tables])
    record = {"packing": packing, "seeds": len(tables),
              "worst albedo error": errors.albedo_error(flat(albedo), flat(seeds.mean(0)))}
    if len(tables) > 1:
        # the truth's own uncertainty: the seeds' mean albedo varies by the arrangement spread
        # over sqrt(seeds), and an error below it cannot be told from zero
        se = seeds.std(0, ddof=1) / np.sqrt(len(tables))
        held = se > 0
        record["seeds' mean albedo se (median)"] = float(np.median(se[held] / seeds.mean(0)[held]))
        record["albedo error over se (rms)"] = float(np.sqrt(np.mean(((albedo - seeds.mean(0))[held] / se[held]) ** 2)))
    if spec.orders:
        orders = order_channels(spec, out.reshape(mean.shape[:-1] + (-1,)))
        rho = between(np.clip, packing, spec.packings, [np.asarray(r) for r in spec.tail_ratio], False)  # the plugin's
        # a recoloured table's scattered fraction is the dye applied to its orders' integrals (linear)
        order_albedos = [np.einsum("kabpql,pq->kabl", t.orders.astype(np.float64), t.solid_angle) for t in tables]
        record["worst dyed albedo error"] = max(
            errors.albedo_error(flat(integral(dyed(orders, a, rho[:, :, None, None, :]))),
                                flat(np.mean([dyed(list(o), a, t.tail_ratio) for o, t in zip(order_albedos, tables)],
                                             0)))
            for a in dyes(t0.wavelength).values())
    spread = np.std(values, 0, ddof=1) if len(values) > 1 else None
    if spread is not None:
        record["core bins within the spread"] = float((np.abs(rows(S) - rows(mean)) <= rows(spread))[core].mean())
    record["core L1 vs seed mean"] = errors.core_l1(rows(S), rows(mean), omega)
    if spread is not None:
        record["one seed's core L1 vs the mean"] = float(np.mean([errors.core_l1(rows(v), rows(mean), omega)
                                                                  for v in values]))
    return record


def figure(onnx_path: Path, family: list, held_out, path: Path, title: str = "a family of plies") -> None:
    """The family against packing: the scattered fraction (at :data:`THETA_FIGURE`, mean over
    wavelengths) and the passthrough, the seeds' means with the arrangement spread (the seeds'
    standard deviation) as error bars, trained and ``held_out`` packings (grey lines), and the
    model read from its file (onnxruntime) across its whole range."""
    model = OnnxMLP(onnx_path)
    spec, t0 = model.spec, family[0][1]
    packings = sorted({p for p, _ in family})
    lo, hi = spec.input_range["packing"]
    grid = np.linspace(lo, hi, 25)
    rows = [int(np.argmin(np.abs(np.rad2deg(t0.theta_i) - t))) for t in THETA_FIGURE]
    cells = table_cells(t0).reshape(len(t0.phi_i), len(t0.theta_i), -1, 6)[0]
    spread = lambda v: np.std(v, ddof=1) if len(v) > 1 else 0.0  # noqa: E731
    fig, (ax_a, ax_p) = plt.subplots(1, 2, figsize=(10, 3.8))
    for j, colour_ in zip(rows, ("C0", "C1", "C2")):
        at_p = lambda p: bin_average(  # noqa: E731
            lambda *q: model.eval(*(np.asarray(a, np.float32) for a in q)).astype(np.float64),
            cells[j], 4, np.full((len(cells[j]), 1, 2), p))
        albedo = [float((at_p(p) * t0.solid_angle.ravel()[:, None]).sum(0).mean()) for p in grid]
        ax_a.plot(grid, albedo, color=colour_, label=f"model, theta_i {np.rad2deg(t0.theta_i[j]):.0f} deg")
        per_seed = {p: [t.scattered[0, j].mean() for t in at(family, p)] for p in packings}
        ax_a.errorbar(packings, [np.mean(v) for v in per_seed.values()], [spread(v) for v in per_seed.values()],
                      fmt="o", color=colour_, capsize=3)
    passthrough = {p: [t.passthrough.mean() for t in at(family, p)] for p in packings}
    ax_p.errorbar(packings, [np.mean(v) for v in passthrough.values()], [spread(v) for v in passthrough.values()],
                  fmt="o", color="k", capsize=3, label="direct bakes (seeds' mean +- spread)")
    at_nodes = [float(np.mean(q)) for q in spec.passthrough_packing]
    ax_p.plot(grid, [between(np.clip, p, spec.packings, at_nodes, False) for p in grid], "k-",
              label="model (its packing nodes, linear between)")
    for ax, what in ((ax_a, "scattered fraction (mean over wavelengths)"), (ax_p, "passthrough probability")):
        ax.set_xlabel("packing fraction")
        ax.set_ylabel(what)
        for p in held_out:
            ax.axvline(p, color="0.85", zorder=0)
    ax_a.legend(fontsize=8)
    ax_p.legend(fontsize=8)
    fig.suptitle(f"{title}: direct bakes (points, arrangement spread as bars; grey lines: held-out packings) "
                 "and one model", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def yarn(cfg, backend: str, path: Path, folder: Path, **extra) -> dict:
    """The render stage's yarn with ``fiber_bundle`` of ``backend`` reading ``path`` (``extra``:
    the plugin's ``packing``, and ``albedo`` as ``[(nm, value)]``)."""
    bsdf = {"type": "fiber_bundle", "backend": backend, ("table" if backend == "table" else "model"): str(path),
            **({"albedo": {"type": "spectrum", "value": extra.pop("albedo")}} if "albedo" in extra else {}),
            **extra}
    return scenes.named_scene(mi, cfg, "yarn", bsdf, cfg.render.spp, folder)


def strip(cfg, model_path: Path, wavelength, packings, dyed: bool, path: Path, folder: Path) -> None:
    """The yarn at ``packings`` (columns) and, where the model holds the orders (``dyed``),
    :func:`dyes` at the model's ``wavelength`` (rows; else undyed), all from the one model file,
    at one exposure (the middle packing's, first row's). Renders in ``cfg.render.variant``."""
    spectra = ({name: [(float(w), float(v)) for w, v in zip(wavelength, a)] for name, a in dyes(wavelength).items()}
               if dyed else {"undyed": None})
    with mitsuba_ext.variant(cfg.render.variant):
        images = {(dye, p): render_timed(mi, yarn(cfg, "mlp", model_path, folder, packing=float(p),
                                                  **({} if a is None else {"albedo": a})), "mlp", warm=False)[0]
                  for dye, a in spectra.items() for p in packings}
    exposure = exposure_of(images[next(iter(spectra)), packings[len(packings) // 2]])
    fig, axes = plt.subplots(len(spectra), len(packings), squeeze=False,
                             figsize=(2.4 * len(packings), 1.5 * len(spectra) + 0.4))
    for (i, dye), (j, p) in itertools.product(enumerate(spectra), enumerate(packings)):
        ax = axes[i, j]
        ax.imshow(to_srgb(images[dye, p], exposure))
        ax.set_xticks([]), ax.set_yticks([])
        if i == 0:
            ax.set_title(f"packing {p:.2f}", fontsize=9)
        if j == 0:
            ax.set_ylabel(dye, fontsize=9)
    fig.suptitle(f"one model file ({model_path.name}): fiber_bundle's packing"
                 + (" and albedo" if dyed else "") + " at render time", fontsize=10)
    save_figure(fig, path)


def render_against_table(cfg, model_path: Path, table_path: Path, packing: float, folder: Path,
                         albedo=None) -> dict:
    """The yarn with the model at ``packing`` against the same yarn with the direct table
    (FLIP at the table's exposure), and both render times."""
    extra = {} if albedo is None else {"albedo": albedo}
    with mitsuba_ext.variant(cfg.render.variant):
        table, t_table, _ = render_timed(mi, yarn(cfg, "table", table_path, folder, **dict(extra)), "table")
        model, t_model, _ = render_timed(mi, yarn(cfg, "mlp", model_path, folder, packing=packing, **dict(extra)),
                                         "mlp")
    flip, psnr, _ = flip_and_psnr(table, model, exposure_of(table))
    return {"FLIP vs direct table": flip, "PSNR dB": psnr, "model s": t_model, "table s": t_table}
