"""Exit models against exact geometry: where light leaves a fiber, measured.

For three plies (the default 200 um ply, a sparse ply and the thesis's 600 um ply) and
three incidences, the exact tracer (:mod:`models.exact`: smooth dielectric circles,
nothing modelled) against bakes of the same arrangement with the ``ray`` fiber in its
smooth limit (roughness 0.05, no tilt, eight explicit paths; lossless, eta 1.5639) and
each exit model:

``uniform``  the thesis's: ``h`` uniform over the outgoing side, whatever the path;
``entry``    every path leaves where the light entered (Mitsuba's ``hair`` on curves);
``lobe``     the h-resolved exit: ``h`` from the ray's real offset, each path from its
             own exit point (the default for ray fibers).

Figures per (ply, theta_i, model): albedo / exact, the energy per 30 deg sector of
|dphi| / exact, and over the 10 deg azimuth bins that hold 90% of the exact energy the
share within 2% + 3 standard errors and the worst ratio. Records ``benchmarks/exit.json``
(``pipeline.bench.results``) and draws ``docs/images/exit_models.png``::

    .venv/bin/python -m pipeline.bench.exit            # about 5 minutes on 2 cores
    .venv/bin/python -m pipeline.bench.exit --quick    # the default ply only, fewer rays
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from models import bundle, exact
from models.bake import BakeSpec, bake_unreduced
from models.fiber.ray import RayFiber

from ..plots import save_figure
from . import results

ETA = 1.5639
EXITS = ("uniform", "entry", "lobe")
PLIES = {  # name: (radius um, packing or None for Poisson-disk tight)
    "default 200 um": (200.0, None),
    "sparse 400 um, packing 0.2": (400.0, 0.2),
    "thesis 600 um": (600.0, None),
}
IMAGES = Path(__file__).resolve().parents[2] / "docs" / "images"


def folded(energy, width_bins):
    """Energy per |dphi| interval of ``width_bins`` bins (mirror intervals summed)."""
    s = energy.reshape(-1, width_bins).sum(1)
    n = len(s) // 2
    return s[n:] + s[:n][::-1]


def compare(E, V, ref, n_rays) -> dict:
    """Figures of a bake's azimuthal energy ``E`` (variance ``V``, 72 bins) against exact ``ref``."""
    ref_var = ref / n_rays
    sectors, sectors_ref = folded(E, 6), folded(ref, 6)
    E10, V10, R10 = (x.reshape(36, 2).sum(1) for x in (E, V, ref))
    Rv10 = R10 / n_rays
    order = np.argsort(R10)[::-1]
    top = order[:np.searchsorted(np.cumsum(R10[order]), 0.9 * R10.sum()) + 1]
    sigma = np.sqrt(V10[top] + Rv10[top])
    ok = np.abs(E10[top] - R10[top]) <= 0.02 * R10[top] + 3 * sigma
    ratio = E10[top] / R10[top]
    albedo_sigma = np.sqrt(V.sum() + ref_var.sum())
    return {"albedo_ratio": float(E.sum() / ref.sum()),
            "albedo_ok": bool(abs(E.sum() - ref.sum()) <= 0.02 * ref.sum() + 3 * albedo_sigma),
            "sector_ratios": (sectors / sectors_ref).round(4).tolist(),
            "bins90": int(len(top)), "bins90_ok_share": float(ok.mean()),
            "bins90_worst_ratio": float(ratio[np.argmax(np.abs(ratio - 1))])}


def measure(rays: int, paths: int, plies: dict, thetas) -> list:
    mi.set_variant("llvm_ad_mono")

    nodes = np.deg2rad(np.arange(0, 91, 5.0))
    fiber = RayFiber([550.0], ETA, 0.0, 0.05, 0.05, 0.0, n_h=512, n_phi=1440, lobes=8).tabulate(nodes)
    rows = []
    jobs = [(p, t) for p in plies for t in thetas]
    for ply, theta_deg in tqdm(jobs, desc="exit models", unit="case"):
        radius, packing = plies[ply]
        b = bundle.poisson((radius, radius), 20.0, packing=packing, seed=1)
        ti = np.deg2rad(theta_deg)
        t0 = time.perf_counter()
        ex = exact.trace(b.centers, b.radii, ETA, ti, rays, bounding_radius=radius, seed=11)
        t_exact = time.perf_counter() - t0
        row = {"ply": ply, "n_fibers": len(b.radii), "theta_i_deg": theta_deg,
               "exact": {"passthrough": ex["passthrough"], "albedo": float(ex["energy"].sum()),
                         "rays": rays, "seconds": t_exact}}
        for exit_model in EXITS:
            spec = BakeSpec([ti], [0.0], 36, 72, relative_phi=True, exit=exit_model)
            t0 = time.perf_counter()
            table = bake_unreduced(b, fiber, spec, paths, seed=12)
            sa = spec.bin_solid_angle()
            E = (table.values[0, 0, :, :, 0].astype(float) * sa).sum(1)
            V = ((table.stderr[0, 0, :, :, 0].astype(float) * sa) ** 2).sum(1)
            row[exit_model] = {**compare(E, V, ex["energy"], rays), "passthrough": float(table.passthrough[0]),
                               "seconds": time.perf_counter() - t0, "paths": paths}
        rows.append(row)
    return rows


def markdown(rows) -> str:
    lines = ["| ply | theta_i | exit | albedo / exact | 0-30 | 30-60 | 60-90 | 90-120 | 120-150 | 150-180 "
             "| 90% bins within 2% + 3 se | worst of them |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for m in EXITS:
            x = r[m]
            s = " | ".join(f"{v:.3f}" for v in x["sector_ratios"])
            lines.append(f"| {r['ply']} ({r['n_fibers']}) | {r['theta_i_deg']:.0f} | {m} | {x['albedo_ratio']:.4f} | "
                         f"{s} | {x['bins90_ok_share']:.0%} of {x['bins90']} | {x['bins90_worst_ratio']:.3f} |")
    return "\n".join(lines)


def plot(rows, path) -> None:

    cols = min(3, len(rows))
    n_rows = -(-len(rows) // cols)
    fig, axes = plt.subplots(n_rows, cols, figsize=(3.4 * cols, 2.9 * n_rows), sharey=True, squeeze=False)
    centres = np.arange(15, 180, 30)
    for ax, r in zip(axes.ravel(), rows):
        for m, style in zip(EXITS, ("o-", "s--", "^-")):
            ax.plot(centres, r[m]["sector_ratios"], style, label=m, ms=4)
        ax.axhspan(0.98, 1.02, color="0.85")
        ax.axhline(1.0, color="k", lw=0.6)
        ax.set(title=f"{r['ply']} ({r['n_fibers']} fibers), theta_i {r['theta_i_deg']:.0f}", xlabel="|dphi| sector (deg)",
               xticks=[0, 60, 120, 180])
        ax.title.set_fontsize(8)
    for ax in axes[:, 0]:
        ax.set_ylabel("bake / exact geometry")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.exit", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the default ply at theta_i 0 and 30, 100k rays and paths")
    ap.add_argument("--rays", type=int, default=400_000, help="exact rays per case")
    ap.add_argument("--paths", type=int, default=1_000_000, help="bake paths per case")
    a = ap.parse_args(argv)
    plies = {"default 200 um": PLIES["default 200 um"]} if a.quick else PLIES
    thetas = (0.0, 30.0) if a.quick else (0.0, 30.0, 60.0)
    rays, paths = (100_000, 100_000) if a.quick else (a.rays, a.paths)
    rows = measure(rays, paths, plies, thetas)
    table = markdown(rows)
    print(table)
    if not a.quick:  # a smoke run is not a measurement
        results.save("exit", table, {"rows": rows})
    plot(rows, IMAGES / "exit_models.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
