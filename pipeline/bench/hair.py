"""The bake against Mitsuba's own ``hair`` fibers on curves, in a ply (docs/DESIGN.md,
"The ray fiber and Mitsuba's hair").

Explicit plies of ``hair`` fibers (``bsplinecurve``, straight or helical; ``hair_resampled``,
Mitsuba's ``hair`` sampled as its density says: ``mitsuba_ext.hair``) rendered by
Mitsuba's ``path`` in the closure scene (``pipeline.closure``: orthographic, the whole
width, 16 turns of the ply, 2 x 8 directions per table bin, in independent passes whose turns
and directions are moved by a random share of their strata: ``closure.replicated_bins``)
against three bakes of the same ply with the mapped ray fiber
(``models.fiber.ray.mitsuba_hair``, ``closure.hair_bsdf``):

``light / lobe``       the default: the model in light transport (conserves energy), each
                       path leaving where it really leaves (agrees with exact geometry);
``camera / curve``     what Mitsuba renders: the adjoint (its path tracer takes the camera
                       side as incident), leaving as from curves (invisible from inside),
                       traced from the light (the ``fast`` estimator);
``camera, from the camera``  the same table traced from the camera (``models.bake.camera``,
                       ``models.bake.twisted_camera``): what the light side weighs by a
                       heavy-tailed change of offset, the camera side reads directly.

Per bin: bake / explicit and its standard error (the bake's, and the render's from the
spread of its passes). It also tabulates the
albedo of a lossless fiber in either transport, the reason the two differ. Records
``benchmarks/hair.json`` (``pipeline.bench.results``)::

    .venv/bin/python -m pipeline.bench.hair            # about 25 minutes on 2 cores
    .venv/bin/python -m pipeline.bench.hair --quick    # the six-fiber plies, fewer paths and samples
"""

from __future__ import annotations

import argparse
import time

import mitsuba as mi
import numpy as np
from tqdm import tqdm

import mitsuba_ext
from models.bake import BakeSpec, bake_unreduced, tally_to_table
from models.bake.twisted import TwistedBaker
from models.bake.twisted_camera import TwistedCameraBaker
from models.bundle import Bundle, TwistedBundle, poisson
from models.fiber.ray import RayFiber
from pipeline import closure

from . import results

BETA_M, BETA_N, TILT, ETA = 0.2, 0.3, 2.0, 1.5639
WL = np.array([450.0, 550.0, 650.0])
LAM = 550.0
NODES = np.deg2rad(np.arange(0, 91, 5.0))
THETA_I = (10.0, 30.0, 70.0)
# transport, exit, estimator
BAKES = {"light / lobe": ("light", "lobe", "fast"), "camera / curve": ("camera", "curve", "fast"),
         "camera, from the camera": ("camera", "curve", "camera")}


def ray_fiber(transport: str, sigma_a: float = 0.0, tilt: float = TILT):
    """The ray fiber of the comparisons (eta 1.5639, roughness 0.2 / 0.3), tabulated."""

    return RayFiber(WL, [ETA] * 3, [sigma_a] * 3, BETA_M, BETA_N, tilt, n_h=64, n_phi=180,
                    transport=transport).tabulate(NODES)


PITCH_UM = {"six": 1500.0, "default": 4000.0}   # the twisted plies' pitches


def ply_of(name: str):
    """``one``: one fiber of 20 um; ``six``: six fibers of 20 um in a circle of 80 um
    (packing 0.4); ``default``: the default config's ply (39 fibers of 20 um in 200 um);
    ``+twist``: twisted at :data:`PITCH_UM` (the default ply's Poisson disks spaced out by
    what the lean of its rim takes, as ``pipeline.build`` does)."""

    base = name.removesuffix("+twist")
    if base == "one":
        return Bundle(np.array([[0.0, 0.0]]), 20.0, (20.0, 20.0))
    R, packing, seed = (80.0, 0.4, 2) if base == "six" else (200.0, None, 1)
    if not name.endswith("+twist"):
        return poisson((R, R), 20.0, packing=packing, seed=seed)
    if base == "six":   # loose enough as it is
        return TwistedBundle(poisson((R, R), 20.0, packing=packing, seed=seed), PITCH_UM[base])
    lean = np.arctan(2 * np.pi * (R - 20.0) / PITCH_UM[base])
    gap = 2 * 20.0 * (1 / np.cos(lean) - 1) + 1.0
    return TwistedBundle(poisson((R, R), 20.0, gap=gap, packing=packing, seed=seed), PITCH_UM[base])


def cases_of(table) -> list:
    """On the cone at six azimuths (back, sides, front) and one bin off it, per theta_i."""
    n_t = len(table.theta_o_edges) - 1
    cases = []
    for j, ti in enumerate(table.theta_i):
        cone = int(np.floor((np.pi / 2 - ti) / np.pi * n_t))        # the bin just above -theta_i
        cases += [(j, k, cone) for k in (1, 9, 15, 18, 27, 34)] + [(j, 9, min(cone + 2, n_t - 1))]
    return cases


def bake_of(ply, fiber, exit_model: str, paths: int, seed: int = 1, estimator: str = "fast"):
    """A relative table of ``ply`` (a Bundle or a TwistedBundle) at :data:`THETA_I`."""

    mi.set_variant("llvm_ad_rgb")  # the baker's own variant
    spec = BakeSpec(np.deg2rad(THETA_I), [0.0], 18, 36, relative_phi=True, exit=exit_model, estimator=estimator)
    if not isinstance(ply, TwistedBundle):
        return bake_unreduced(ply, fiber, spec, paths, seed=seed)
    baker = (TwistedCameraBaker if estimator == "camera" else TwistedBaker)(ply, fiber, spec)
    tally = baker.trace(0, paths // 2, seed)
    tally.add(baker.trace(0, paths // 2, seed + 1))
    return tally_to_table(tally, spec, fiber, {"theta_i": None, "phi_i": None, "phi_o": "relative"})


def explicit_hair(ply, fiber, tables, spp: int = 16, replicates: int = 0, seed: int = 0) -> list:
    """``[ratio, sigma]`` rows per table: bake / explicit ``hair`` fibers at the bins of
    :func:`cases_of`, with the standard error of both. The render's: from ``replicates``
    independent passes of ``spp`` samples a pixel (``closure.replicated_bins``), or with
    ``replicates=0`` from the even and odd turns of one pass at the strata's midpoints (one
    degree of freedom, and the midpoints' own bias where a bin's light falls steeply)."""

    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()   # hair_resampled
    lam = list(WL).index(LAM)
    t = tables[0]
    cases = cases_of(t)
    hair = closure.hair_bsdf(fiber.meta, fiber.wavelength, LAM)
    options = {"spp": spp, "resolution": 32, "curves": True, "integrator": "path"}
    measured = (closure.replicated_bins(mi, ply, hair, t, cases, replicates, seed=seed, **options) if replicates
                else closure.explicit_intensities(mi, ply, hair, closure.bin_requests(t, cases), **options))
    R_b = getattr(ply, "bundle", ply).bounding_radius * 1e-3
    out = []
    for table in tables:
        rows = []
        for (j, k, m), (I, se) in zip(cases, measured):
            S, S_err = table.values[0, j, k, m, lam], table.stderr[0, j, k, m, lam]
            rows.append((closure.predicted_intensity(1.0, R_b, table.theta_i[j], S) / I, np.hypot(S_err / S, se / I)))
        out.append(np.array(rows))
    return out


def outside(res) -> np.ndarray:
    """The bins whose ratio lies beyond 3% + 3 standard errors of 1."""
    return np.abs(res[:, 0] - 1) > 0.03 + 3 * res[:, 1]


def albedos(betas=(0.2, 0.3, 0.5), thetas=(0.0, 30.0, 60.0, 75.0, 85.0)) -> list:
    """Albedo of a lossless ray fiber (eta 1.5639, tilt 2 deg) in either transport."""

    to = np.linspace(-np.pi / 2, np.pi / 2, 361)
    po = -np.pi + 2 * np.pi * (np.arange(180) + 0.5) / 180
    T, P = np.meshgrid(to, po, indexing="ij")
    dw = np.cos(T) * np.gradient(to)[:, None] * (2 * np.pi / len(po))
    rows = []
    for beta in betas:
        for transport in ("light", "camera"):
            f = RayFiber([LAM], ETA, 0.0, beta, BETA_N, TILT, n_h=64, transport=transport)
            rows.append({"beta_m": beta, "transport": transport,
                         "albedo": [float((f.eval(phi_i=0.0, theta_i=np.deg2rad(t), phi_o=P, theta_o=T,
                                                  wavelength=LAM) * dw).sum()) for t in thetas],
                         "theta_i": list(thetas)})
    return rows


def measure(plies, paths: int, spp: int, replicates: int) -> list:
    rows = []
    for name, sigma_a in tqdm(plies, desc="hair closure", unit="ply"):
        ply = ply_of(name)
        bakes = BAKES
        fibers = {b: ray_fiber(transport, sigma_a) for b, (transport, _, _) in bakes.items()}
        tables, t_bake = [], {}
        for b, (_, exit_model, estimator) in bakes.items():
            t0 = time.perf_counter()
            tables.append(bake_of(ply, fibers[b], exit_model, paths, estimator=estimator))
            t_bake[b] = time.perf_counter() - t0
        t0 = time.perf_counter()
        results = explicit_hair(ply, fibers["camera / curve"], tables, spp, replicates)
        t_render = time.perf_counter() - t0
        bins = [[float(np.rad2deg(tables[0].theta_i[j])), float(np.rad2deg(tables[0].phi_o[k])),
                 float(np.rad2deg(tables[0].theta_o[m]))] for j, k, m in cases_of(tables[0])]
        row = {"ply": name, "n_fibers": int(len(getattr(ply, "bundle", ply).radii)), "sigma_a": sigma_a,
               "paths": paths, "spp": spp, "replicates": replicates, "bake_s": sum(t_bake.values()),
               "render_s": t_render, "bins": bins}
        for b, res in zip(bakes, results):
            row[b] = {"seconds": t_bake[b], "ratio": res[:, 0].round(4).tolist(), "sigma": res[:, 1].round(4).tolist(),
                      "outside": int(outside(res).sum()), "worst": float(res[np.argmax(np.abs(res[:, 0] - 1)), 0]),
                      "median_dev": float(np.median(np.abs(res[:, 0] - 1))),
                      "median_sigma": float(np.median(res[:, 1]))}
        rows.append(row)
    return rows


def markdown(rows, albedo_rows) -> str:
    lines = ["| ply | sigma_a | bake | bins outside 3% + 3 se | worst bake / hair | median deviation "
             "| median se | bake s |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for b in (b for b in BAKES if b in r):
            x = r[b]
            lines.append(f"| {r['ply']} ({r['n_fibers']}) | {r['sigma_a']:g} | {b} | {x['outside']} of "
                         f"{len(x['ratio'])} | {x['worst']:.3f} | {x['median_dev']:.3f} | {x['median_sigma']:.3f} "
                         f"| {x['seconds']:.0f} |")
    lines += ["", "Albedo of a lossless fiber (eta 1.5639, azimuthal roughness 0.3, tilt 2 deg):", "",
              "| longitudinal roughness | transport | " + " | ".join(f"theta_i {t:g}" for t in albedo_rows[0]["theta_i"])
              + " |", "|---|---|" + "---|" * len(albedo_rows[0]["theta_i"])]
    for a in albedo_rows:
        lines.append(f"| {a['beta_m']:g} | {a['transport']} | " + " | ".join(f"{v:.3f}" for v in a["albedo"]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.hair", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the six-fiber plies only, 2M paths, 4 passes of 4 spp")
    ap.add_argument("--paths", type=int, default=16_000_000, help="bake paths per ply and bake")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel of each pass of the explicit renders")
    ap.add_argument("--replicates", type=int, default=8,
                    help="independent passes of the explicit renders (their spread is the render's standard error)")
    a = ap.parse_args(argv)
    plies = [("six", 0.0), ("six+twist", 0.5)] if a.quick else \
        [("one", 0.0), ("six", 0.0), ("six+twist", 0.5), ("default", 0.0), ("default", 0.5), ("default+twist", 0.0)]
    paths, spp, replicates = (2_000_000, 4, 4) if a.quick else (a.paths, a.spp, a.replicates)
    rows = measure(plies, paths, spp, replicates)
    albedo_rows = albedos()
    table = markdown(rows, albedo_rows)
    print(table)
    if not a.quick:  # a smoke run is not a measurement
        results.save("hair", table, {"rows": rows, "albedo": albedo_rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
