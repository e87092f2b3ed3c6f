"""The highlight's resolution: explicit fibers against the table's lookup at single
directions on the specular cone, for theta_o layouts side by side (docs/BENCHMARKS.md).

    python -m pipeline.bench.highlight [CONFIG] [--artifacts DIR] [--paths N] [--spp N]

The config's ply (its fiber table from ``bcsdf run`` / ``bcsdf fiber``) is baked once per
layout with the same paths and seed: ``uniform 36`` (36 equal 5 deg bins, the layout before
the cone one), ``cone 35`` (a 2 deg bin on every node's cone, one 8 deg bin between: the
default's) and ``uniform 180`` (1 deg bins, five times the bytes: what finer bins alone
buy). Every fiber of the ply is then rendered as its own cylinder with ``fiber_table`` (16
turns of the arrangement) at directions exactly on the cone ``theta_o = -theta_i``:
``theta_i`` on bake nodes and between them, ``dphi`` at the middle of a phi_o bin and on its
edge. Printed: ``lookup / explicit - 1`` per direction and layout, and per layout the
median and largest error, how many directions lie within 5%, and the table's bytes.
Written: ``artifacts/<name>/closure/bench_highlight.json`` and ``highlight.png``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from models.io import write_text

from ..artifacts import stage_dir
from ..config import load_config

LAYOUTS = {"uniform 36": ["bake.theta_o_layout=uniform", "bake.n_theta_o=36"],
           "cone 35": ["bake.theta_o_layout=cone", "bake.n_theta_o=35", "bake.cone_bin_deg=2"],
           "uniform 180": ["bake.theta_o_layout=uniform", "bake.n_theta_o=180"]}
THETA_I = (20.0, 30.0, 45.0, 60.0, 75.0)     # deg: nodes of a 10 deg bake, and between them
DPHI = (32.5, 92.5, 152.5, 30.0, 90.0, 150.0)  # deg: phi_o bin middles, then edges (5 deg bins)
LAM = 550.0


def bake_layouts(config, artifacts, paths: int) -> dict:
    """``{layout: (table, bake seconds)}``: the config's ply baked once per layout."""
    import mitsuba as mi

    from models.fiber.base import FiberTable

    from ..build import build_bundle, make_spec
    from ..stages.bake import bake_unreduced

    mi.set_variant("llvm_ad_rgb")
    tables = {}
    for name, sets in LAYOUTS.items():
        cfg = load_config(config, sets)
        fiber = FiberTable.load(stage_dir(cfg, "fiber", artifacts) / "fiber_table.npz")
        bundle = build_bundle(cfg)
        spec, _ = make_spec(cfg, bundle, fiber)
        t0 = time.perf_counter()
        tables[name] = (bake_unreduced(bundle, fiber, spec, paths, seed=cfg.bake.seed), time.perf_counter() - t0)
        print(f"[highlight] {name}: {paths:.3g} paths in {tables[name][1]:.1f} s, "
              f"{tables[name][0].values.nbytes / 2**20:.2f} MiB of values")
    return tables


def explicit_on_cone(cfg, artifacts, spp: int) -> list:
    """``[(theta_i, dphi, S, S_err)]``: the explicit fibers' far field (1/sr) on the cone."""
    import mitsuba as mi

    import mitsuba_ext

    from .. import closure
    from ..build import build_bundle

    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    bundle = build_bundle(cfg)
    fiber = closure.explicit_fiber(stage_dir(cfg, "fiber", artifacts) / "fiber_table.npz", "uniform", LAM)
    cases = [(ti, dp) for ti in THETA_I for dp in DPHI]
    turns = 16
    requests = [(closure.direction(0.0, np.deg2rad(ti)), [closure.direction(np.deg2rad(dp), -np.deg2rad(ti))] * turns)
                for ti, dp in cases]
    measured = closure.explicit_intensities(mi, bundle, fiber, requests, spp=spp, resolution=48)
    rows = []
    for (ti, dp), (I, se) in zip(cases, measured):
        norm = closure.predicted_intensity(1.0, bundle.bounding_radius * 1e-3, np.deg2rad(ti), 1.0)
        rows.append((ti, dp, I / norm, se / norm))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", nargs="?", default="configs/default.yaml")
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--paths", type=int, default=8_000_000, help="paths of each layout's bake")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of each explicit render")
    args = p.parse_args(argv)
    from models.bundle_table import lookup

    cfg = load_config(args.config)
    if cfg.bake.exit not in ("auto", "uniform") or cfg.fiber.model == "ray" or cfg.bundle.twist is not None:
        raise SystemExit("bench.highlight compares a parallel ply with the uniform exit (fiber_table explicit fibers)")
    tables = bake_layouts(args.config, args.artifacts, args.paths)
    t0 = time.perf_counter()
    explicit = explicit_on_cone(cfg, args.artifacts, args.spp)
    print(f"[highlight] explicit fibers at {len(explicit)} directions in {time.perf_counter() - t0:.0f} s")
    result = {"paths": args.paths, "wavelength_nm": LAM, "layouts": {}}
    print("[highlight] lookup / explicit - 1 on the cone (" + ", ".join(tables) + ")")
    for ti, dp, S, se in explicit:
        line = f"  theta_i {ti:4.0f}  dphi {dp:5.1f}: explicit {S:.3f} +- {se:.3f} /sr:"
        for name, (t, _) in tables.items():
            lam = int(np.argmin(np.abs(t.wavelength - LAM)))
            err = float(lookup(t, 0.0, np.deg2rad(ti), np.deg2rad(dp), -np.deg2rad(ti))[lam] / S - 1)
            result["layouts"].setdefault(name, {"errors": []})["errors"].append(err)
            line += f" {err:+.3f}"
        print(line)
    result["directions"] = [{"theta_i": ti, "dphi": dp, "explicit": S, "explicit_err": se} for ti, dp, S, se in explicit]
    for name, (t, seconds) in tables.items():
        e = np.abs(result["layouts"][name]["errors"])
        node = np.array([ti % 10 == 0 for ti, *_ in explicit])
        summary = {"bytes": int(t.values.nbytes), "bake_seconds": seconds, "median": float(np.median(e)),
                   "max": float(e.max()), "within_5pct": int(np.sum(e <= 0.05)), "n": len(e),
                   "median_at_nodes": float(np.median(e[node])), "median_between": float(np.median(e[~node]))}
        result["layouts"][name].update(summary)
        print(f"[highlight] {name:11}: |error| median {summary['median']:.1%} (nodes {summary['median_at_nodes']:.1%}, "
              f"between {summary['median_between']:.1%}), max {summary['max']:.1%}, within 5% at "
              f"{summary['within_5pct']} of {summary['n']}; {summary['bytes'] / 2**20:.2f} MiB")
    out = stage_dir(cfg, "closure", args.artifacts)
    write_text(out / "bench_highlight.json", json.dumps(result, indent=2))
    plot(result, out / "highlight.png")
    print(f"[highlight] wrote {out / 'bench_highlight.json'}")
    return 0


def plot(result: dict, path) -> None:
    """``lookup / explicit - 1`` per direction, one marker per layout."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    d = result["directions"]
    x = np.arange(len(d))
    fig, ax = plt.subplots(figsize=(12, 4), dpi=110)
    for (name, r), m in zip(result["layouts"].items(), "os^"):
        ax.plot(x, np.array(r["errors"]) * 100, m, label=f"{name} ({r['bytes'] / 2**20:.2f} MiB): median "
                f"{r['median']:.1%}")
    ax.axhspan(-5, 5, color="0.9", zorder=0)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(x, [f"{r['theta_i']:.0f}/{r['dphi']:g}" for r in d], rotation=90, fontsize=7)
    ax.set(xlabel="theta_i / dphi (deg), on the cone theta_o = -theta_i", ylabel="lookup / explicit - 1 (%)",
           title=f"the highlight: table lookups against explicit fibers at single directions ({result['paths']:.3g} "
                 "paths per bake)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
