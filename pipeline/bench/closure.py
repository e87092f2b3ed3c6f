"""Closure benchmark: the whole chain's error budget, measured (docs/BENCHMARKS.md).

    python -m pipeline.bench.closure [CONFIG] [--artifacts DIR] [--quick] [--spp N]

Three parts, all printed and written to ``artifacts/<name>/closure/bench_closure.json``
with a figure ``closure.png``:

1. **Reciprocity of the fiber models**: ``|a - b| / max(a, b)`` with ``a = f(i -> o) cos(theta_i)``
   and ``b = f(o -> i) cos(theta_o)``, at random direction pairs where ``f`` exceeds 1e-3 of its maximum, for the config's
   Mie fiber and for the ray fiber of ``configs/fiber_ray.yaml`` (Chiang's model is only
   approximately reciprocal: this measures how far).
2. **Far-field closure** on the config's artifacts (``bcsdf run`` first): one explicit
   fiber (``fiber_table``) and ``fiber_bundle`` with the table, the jitted MLP and ONNX,
   rendered / predicted (``pipeline.closure``) at the closure direction pairs.
4. **The ply scene** (``--ply-only`` runs this part alone): mean radiance of the bundle
   (table, MLP) against independent averages of the explicit fibers over 16 turns.
3. **Explicit fibers against the bake**, bin by bin: the config's ply, a sparse ply and
   an ellipse, each with the Mie and the ray fiber, baked here (small bakes), every fiber
   rendered as its own cylinder; a circle averaged over 16 turns of its arrangement,
   each turn seen from its own direction of a 4 x 4 stratification of the bin.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

import mitsuba_ext
from models import fiber as fibers
from models.bake import BakeSpec, bake_unreduced
from models.bundle import poisson
from models.io import write_text
from pipeline.bench import results

from .. import bsdfs, closure, scenes
from ..artifacts import config_dir, stage_dir
from ..build import build_bundle
from ..loading import load_config
from ..loading import load_config as load

LAM = 550.0


# -- 1. reciprocity ------------------------------------------------------------------
def reciprocity(table, n: int = 40_000, seed: int = 0) -> dict:
    """Departure from ``f(i->o) cos(theta_i) = f(o->i) cos(theta_o)`` of a fiber table:
    ``|a - b| / max(a, b)`` of the two sides (0: reciprocal, 1: one side dark), where
    ``f(i->o)`` exceeds 1e-3 of its maximum."""
    rng = np.random.default_rng(seed)
    ti = rng.uniform(-np.pi / 2, np.pi / 2, n)
    to = np.where(rng.uniform(size=n) < 0.5, rng.uniform(-np.pi / 2, np.pi / 2, n),
                  np.clip(-ti + rng.normal(0, 0.2, n), -np.pi / 2, np.pi / 2))
    dphi = rng.uniform(-np.pi, np.pi, n)
    a = table.eval_spectrum(ti, to, dphi) * np.cos(ti)[:, None]
    b = table.eval_spectrum(to, ti, -dphi) * np.cos(to)[:, None]
    big = a > 1e-3 * a.max()
    rel = np.abs(a[big] - b[big]) / np.maximum(a[big], b[big])
    return {"pairs": int(big.sum()), "median": float(np.median(rel)), "p95": float(np.percentile(rel, 95)),
            "max": float(rel.max())}


# -- 2. far-field closure ------------------------------------------------------------
def far_field(mi, cfg, out_root) -> dict:
    """rendered / predicted of one fiber and of the bundle in every backend (config's artifacts)."""

    root = config_dir(cfg, out_root)
    pairs = closure.direction_pairs(cone_offsets_deg=(0.0, 0.8, -1.7, -3.0))
    fiber = {"type": "fiber_table", "filename": str(root / "fiber" / "fiber_table.npz")}
    bundles = {b: bsdfs.backend_props(cfg, out_root, b) for b in ("table", "mlp", "onnx")}
    Rf, Rb = cfg.fiber.radius_um * 1e-3, build_bundle(cfg).bounding_radius * 1e-3
    cases = {"fiber_table": (fiber, Rf, closure.evaluator(mi, "fiber", fiber["filename"], LAM)),
             **{b: (p, Rb, closure.evaluator(mi, b, p.get("table") or p.get("model"), LAM))
                for b, p in bundles.items()}}
    return {name: closure.far_field_ratios(mi, {**bsdf, "wavelength": LAM, "up": closure.UP},
                                           R, S, pairs, evaluated=name == "onnx")
            for name, (bsdf, R, S) in cases.items()}


# -- 3. explicit fibers against the bake ---------------------------------------------
def explicit_vs_bake(mi, cfg, out_root, quick: bool, spp: int = 32) -> list:
    wl = np.array([450.0, 550.0, 650.0])
    nodes = np.deg2rad(np.arange(0, 91, 5.0))
    ray_cfg = load(Path(__file__).resolve().parents[2] / "configs" / "fiber_ray.yaml")
    r = cfg.fiber.radius_um
    fiber_models = {"mie": fibers.build(cfg.fiber, wl), "ray": fibers.build(ray_cfg.fiber, wl)}
    base = build_bundle(cfg)
    Rb = base.bounding_radius
    plies = {"default": base,
             "sparse": poisson((Rb, Rb), r, packing=0.15, seed=3),
             "ellipse": poisson((1.25 * Rb, 0.75 * Rb), r, packing=0.35, seed=4)}
    if quick:
        plies = {"default": plies["default"]}
    tmp = stage_dir(cfg, "closure", out_root)
    rows = []
    for fname, model in fiber_models.items():
        table_f = model.tabulate(nodes)
        fpath = tmp / f"fiber_{fname}.npz"
        table_f.save(fpath)
        for pname, bundle in plies.items():
            mi.set_variant("llvm_ad_rgb")
            phi_i = 0.0 if bundle.is_circle else 30.0
            t0 = time.perf_counter()
            spec = BakeSpec(np.deg2rad([10.0, 30.0, 60.0, 80.0]), np.deg2rad([phi_i]), 18, 36,
                            relative_phi=bundle.is_circle)
            table = bake_unreduced(bundle, table_f, spec, 400_000 if quick else 2_000_000)
            bake_s = time.perf_counter() - t0
            mi.set_variant("llvm_ad_mono")
            mitsuba_ext.register()
            bsdf = {"type": "fiber_table", "filename": str(fpath), "wavelength": LAM, "up": closure.UP}
            phi_bins = (1, 9, 15) if bundle.is_circle else (4, 12, 22)  # 15, 95, 155 deg from forward
            found = closure.explicit_bins(mi, bundle, bsdf, table, closure.cone_cases(table, phi_bins, not quick),
                                          lam=1, phi_i=np.deg2rad(phi_i), spp=spp)
            rows += [{"fiber": fname, "ply": pname, "fibers": len(bundle.centers), "bake_seconds": bake_s, **r_}
                     for r_ in found]
            print(f"[closure] {fname:3} {pname:8} ({len(bundle.centers)} fibers): explicit / bake - 1 = "
                  + " ".join(f"{r_['ratio'] - 1:+.3f}" for r_ in rows if r_["fiber"] == fname and r_["ply"] == pname))
    return rows


# -- 4. the ply scene: explicit fibers against the bundle, many seeds -------------------
def ply_scene(cfg, out_root, seeds: int = 9, spp_per_turn: int = 32) -> dict:
    """Mean radiance over the ply (render stage's scene, sun and sky, spectral): the bundle
    with the table and the MLP (256 spp) against ``seeds`` independent averages of the
    explicit fibers over 16 turns (``16 x spp_per_turn`` samples each). A Mie ply's
    explicit image is a few glints per pixel, so one average is noisy (a few per cent):
    the seeds give its standard error."""
    r = cfg.render
    mi.set_variant(r.variant)
    mitsuba_ext.register()
    bundle = build_bundle(cfg)
    fiber = stage_dir(cfg, "fiber", out_root) / "fiber_table.npz"
    rows = scenes.ply_rows(cfg, r.height)
    mean = lambda sc: float(np.asarray(mi.render(mi.load_dict(sc)))[rows].mean())  # noqa: E731
    bundle_means = {b: mean(scenes.ply_scene(mi, cfg, bsdfs.backend_props(cfg, out_root, b), 256, 5,
                                             twist_turns=0.0)) for b in ("table", "mlp")}
    # one explicit scene, its fibers turned between views (closure.TurnedFibers: one kernel)
    scene = mi.load_dict(scenes.explicit_scene(mi, cfg, bundle, fiber, spp_per_turn))
    fibers = closure.TurnedFibers(mi, scene, [1.0, 0.0, 0.0])
    explicit = []
    for s in range(seeds):
        views = []
        for k in range(16):
            fibers.place(2 * np.pi * k / 16)
            views.append(float(np.asarray(mi.render(scene, seed=1000 * (s + 1) + k))[rows].mean()))
        explicit.append(np.mean(views))
    explicit = np.array(explicit)
    out = {"explicit_means": explicit.tolist(), **{f"{b}_mean": v for b, v in bundle_means.items()}}
    for b, v in bundle_means.items():
        ratios = v / explicit
        out[f"{b}_vs_explicit"] = [float(v / explicit.mean()), float(ratios.std(ddof=1) / np.sqrt(seeds))]
        print(f"[closure] ply scene: bundle ({b}) / explicit fibers = {v / explicit.mean():.4f} "
              f"+- {out[f'{b}_vs_explicit'][1]:.4f} ({seeds} explicit averages of {16 * spp_per_turn} spp)")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", nargs="?", default="configs/default.yaml")
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--quick", action="store_true", help="the default ply only, smaller bakes")
    p.add_argument("--spp", type=int, default=32, help="samples per pixel of each explicit render")
    p.add_argument("--ply-only", action="store_true", help="only part 4: the ply scene against explicit fibers")
    args = p.parse_args(argv)
    cfg = load_config(args.config)
    if args.ply_only:
        result = ply_scene(cfg, args.artifacts)
        write_text(stage_dir(cfg, "closure", args.artifacts) / "bench_closure_ply.json", json.dumps(result, indent=2))
        return 0

    wl = np.linspace(cfg.wavelengths.start_nm, cfg.wavelengths.stop_nm, cfg.wavelengths.count)
    ray_cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / "fiber_ray.yaml")
    nodes = np.deg2rad(np.arange(0, 91, 5.0))
    result = {"reciprocity": {"mie": reciprocity(fibers.build(cfg.fiber, wl[::6]).tabulate(nodes)),
                              "ray": reciprocity(fibers.build(ray_cfg.fiber, wl[::6]).tabulate(nodes))}}
    for name, r in result["reciprocity"].items():
        print(f"[closure] reciprocity of the {name} fiber: |a - b| / max(a, b), a = f(i->o) cos ti, "
              f"b = f(o->i) cos to: median "
              f"{r['median']:.2e}, 95% {r['p95']:.2e}, max {r['max']:.2e} ({r['pairs']} pairs)")
    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    result["far_field"] = far_field(mi, cfg, args.artifacts)
    for name, rows in result["far_field"].items():
        r = np.array([row[3] for row in rows])
        print(f"[closure] far field, {name:11}: rendered / predicted {r.min():.4f} .. {r.max():.4f} "
              f"({len(r)} direction pairs)")
    result["explicit"] = explicit_vs_bake(mi, cfg, args.artifacts, args.quick, args.spp)
    out = stage_dir(cfg, "closure", args.artifacts)
    write_text(out / "bench_closure.json", json.dumps(result, indent=2))
    groups = {}
    for r_ in result["explicit"]:
        groups.setdefault(f"{r_['fiber']}, {r_['ply']} ({r_['fibers']} fibers)", []).append(r_)
    closure.plot(result["far_field"], groups, out / "closure.png", f"{cfg.name}: the chain's closure")
    z = np.array([(r["ratio"] - 1) / r["sigma"] for r in result["explicit"]])
    within = np.mean([abs(r["ratio"] - 1) <= 0.02 + 3 * r["sigma"] for r in result["explicit"]])
    print(f"[closure] explicit vs bake: {within:.0%} of {len(z)} bins within 3 sigma + 2%; |z| median "
          f"{np.median(np.abs(z)):.2f}; wrote {out}")
    return 0


if __name__ == "__main__":
    with results.recorded("closure", smoke="--quick" in sys.argv):
        raise SystemExit(main())
