"""The highlight's resolution: explicit fibers against the table's lookup at single
directions on the specular cone, for theta_o layouts side by side.

    python -m pipeline.bench.highlight [CONFIG] [--artifacts DIR] [--paths N] [--spp N]
                                       [--layouts L ...] [--measures {550 nm,luminance} ...]
                                       [--theta-i DEG ...] [--models ROOT ...]

The config's ply (its fiber table from ``bcsdf run`` / ``bcsdf fiber``) is baked once per
layout (``--layouts``) with the same paths and seed: ``uniform 36`` (36 equal 5 deg bins,
the layout before the cone one), ``cone 35`` (a 2 deg bin on every node's cone, one bin
between; theta_i nodes every 10 deg, as these two), ``graded cone 35`` (as many theta_i
nodes, graded: 15 deg apart up to 60, 5 deg from 60 to 80, and a pole node at 90;
``--graded`` takes other nodes, the bins following them), ``held cone 43`` (the default's:
85 and 87.5 instead of the pole node 90, the last node held along its cone up to the
pole) and ``uniform 180`` (1 deg bins, five times the bytes: what finer bins alone buy);
bytes are those of the values as a table file holds them (half precision). Every fiber of
the ply is then rendered as its own cylinder with ``fiber_table`` (16 turns of the arrangement) at directions exactly on the cone ``theta_o =
-theta_i``: ``theta_i`` on bake nodes and between them (each table's errors are split by its
own nodes), ``dphi`` at the middle of a phi_o bin and on its edge; then again with each turn
seen at its own azimuth across a phi_o bin's width (theta_o still exactly on the cone),
against the lookup averaged over the same azimuths: a Mie fiber's azimuthal glints are finer
than any phi_o bin, and this isolates the theta_o axis. Each is measured (``--measures``)
at 550 nm (mono renders, the lookups at the table's 550 nm) and in the luminance a picture
shows (spectral renders under a flat sun, ``llvm_ad_spectral``'s luminance film, against
the lookups weighted by ``closure.luminance_weights``): one wavelength's interference
ripples wash out over the spectrum. For each measure the explicit fibers at single
directions are also compared with their own mean over a phi_o bin's azimuths: structure
that no table with these bins can hold, a floor under its single-direction errors.
``--models ROOT ...``: the table baked and the models exported under those artifacts roots
(``bcsdf bake``, ``train`` and ``export`` of this config there, e.g. with another
``bake.theta_o_layout``) are compared too, evaluated as the plugin does. Printed:
``lookup / explicit - 1`` per direction and layout (or model), and for each the median and
largest error (also for theta_i >= 65 deg), how many directions lie within 5%, and its bytes.
Written: ``artifacts/<name>/closure/bench_highlight.json`` and ``highlight.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
import yaml

import mitsuba_ext
from models.bake import bake_unreduced
from models.bundle_table import BundleTable, from_half, lookup, to_half
from models.fiber.base import FiberTable
from models.grid import cone_bin_counts
from models.io import write_text
from pipeline.bench import results

from .. import closure
from ..artifacts import bundle_table_path, stage_dir
from ..build import build_bundle, make_spec
from ..loading import load_config
from ..plots import save_figure

GRADED = "[0, 15, 30, 45, 60, 65, 70, 75, 80, 90]"  # as many theta_i nodes as every 10 deg, with a pole node
HELD = "[0, 15, 30, 45, 60, 65, 70, 75, 80, 85, 87.5]"  # the default's now: no pole node
EVERY_10 = ["bake.theta_i_deg=null", "bake.theta_i_step_deg=10"]    # theta_i nodes every 10 deg
CONE = ["bake.theta_o_layout=cone", "bake.cone_bin_deg=2"]  # one bin between two cones: n_theta_o 2 G - 1
LAYOUTS = {"uniform 36": EVERY_10 + ["bake.theta_o_layout=uniform", "bake.n_theta_o=36"],
           "cone 35": EVERY_10 + CONE + ["bake.n_theta_o=35"],
           "graded cone 35": ["bake.theta_i_step_deg=null", f"bake.theta_i_deg={GRADED}"] + CONE
                             + ["bake.n_theta_o=35"],
           "held cone 43": ["bake.theta_i_step_deg=null", f"bake.theta_i_deg={HELD}"] + CONE + ["bake.n_theta_o=43"],
           "uniform 180": EVERY_10 + ["bake.theta_o_layout=uniform", "bake.n_theta_o=180"]}
# deg: nodes of the layouts, and between them (65, 72.5, 77.5, 82.5 near grazing; 85, 87.5 and
# 88.75 between the last node and the pole, whichever they are)
THETA_I = (20.0, 30.0, 45.0, 60.0, 65.0, 72.5, 75.0, 77.5, 82.5, 85.0, 87.5, 88.75)
DPHI = (32.5, 92.5, 152.5, 30.0, 90.0, 150.0)  # deg: phi_o bin middles, then edges (5 deg bins)
LAM = 550.0


def layout_overrides(name: str, graded: str = GRADED) -> list:
    """The ``--set`` overrides of a layout; ``graded``: the nodes of ``graded cone 35``, its
    bins following them (one between every two cones)."""

    sets = [s.replace(GRADED, graded) for s in LAYOUTS[name]]
    if name == "graded cone 35" and graded != GRADED:
        n_theta_o = cone_bin_counts(np.deg2rad(yaml.safe_load(graded)))[0]
        sets = [f"bake.n_theta_o={n_theta_o}" if s.startswith("bake.n_theta_o=") else s for s in sets]
    return sets


def bake_layouts(config, artifacts, paths: int, layouts=tuple(LAYOUTS), graded: str = GRADED) -> dict:
    """``{layout: (table, bake seconds, bytes of its values as a file holds them)}``: the config's
    ply baked once per layout (``graded``: the graded layout's theta_i nodes, a YAML list in
    degrees), its values rounded as ``BundleTable.save`` stores them (half precision)."""
    mi.set_variant("llvm_ad_rgb")
    tables, warm = {}, False
    for name in layouts:
        cfg = load_config(config, layout_overrides(name, graded))
        fiber = FiberTable.load(stage_dir(cfg, "fiber", artifacts) / "fiber_table.npz")
        bundle = build_bundle(cfg)
        spec, _ = make_spec(cfg, bundle, fiber)
        if not warm:  # the kernels compiled before any bake is timed
            bake_unreduced(bundle, fiber, spec, 20_000, seed=cfg.bake.seed)
            warm = True
        t0 = time.perf_counter()
        table = bake_unreduced(bundle, fiber, spec, paths, seed=cfg.bake.seed)
        seconds = time.perf_counter() - t0
        half, scale = to_half(table.values)
        table.values = from_half(half, scale)  # what its file holds
        tables[name] = (table, seconds, half.nbytes)
        print(f"[highlight] {name}: {paths:.3g} paths in {seconds:.1f} s, "
              f"{half.nbytes / 2**20:.2f} MiB of values as stored")
    return tables


def explicit_on_cone(cfg, artifacts, spp: int, spread_deg: float = 0.0, wavelength_nm: float | None = LAM,
                     theta_i=THETA_I) -> list:
    """``[(theta_i, dphi, S, S_err)]``: the explicit fibers' far field (1/sr) on the cone at
    ``theta_i`` (degrees) and every :data:`DPHI`;
    ``spread_deg``: turn ``k`` of the 16 is seen at ``dphi + spread ((k + 0.5) / 16 - 0.5)``
    (the mean over that azimuth range, theta_o still exactly on the cone). At one
    wavelength (a mono render), or, for ``wavelength_nm=None``, the luminance of a
    spectral render under a flat sun (``llvm_ad_spectral``, what a picture shows)."""
    mi.set_variant("llvm_ad_mono" if wavelength_nm is not None else "llvm_ad_spectral")
    mitsuba_ext.register()
    bundle = build_bundle(cfg)
    fiber = closure.explicit_fiber(stage_dir(cfg, "fiber", artifacts) / "fiber_table.npz", "uniform", wavelength_nm)
    cases = [(ti, dp) for ti in theta_i for dp in DPHI]
    turns = 16
    requests = [(closure.direction(0.0, np.deg2rad(ti)), [closure.direction(np.deg2rad(dp + o), -np.deg2rad(ti))
                                                          for o in spread(spread_deg, turns)])
                for ti, dp in cases]
    measured = closure.explicit_intensities(mi, bundle, fiber, requests, spp=spp, resolution=48)
    rows = []
    for (ti, dp), (I, se) in zip(cases, measured):
        norm = closure.predicted_intensity(1.0, bundle.bounding_radius * 1e-3, np.deg2rad(ti), 1.0)
        rows.append((ti, dp, I / norm, se / norm))
    return rows


def spread(width_deg: float, n: int = 16) -> np.ndarray:
    """``n`` azimuth offsets (deg) evenly over ``width_deg`` about 0 (all 0 for no width)."""
    return width_deg * ((np.arange(n) + 0.5) / n - 0.5)


def table_entries(mi, tables: dict, wavelength_nm: float | None = LAM) -> dict:
    """``{layout: (S_of, bytes, bake seconds, theta_i nodes)}``: each baked table's lookup at
    ``wavelength_nm``, or its luminance in a spectral render (``None``)."""

    def reader(t):
        w = closure.spectrum_weights(mi, t.wavelength, wavelength_nm)
        return lambda *angles: lookup(t, *angles) @ w
    return {name: (reader(t), nbytes, seconds, t.theta_i) for name, (t, seconds, nbytes) in tables.items()}


def model_entries(mi, cfg, roots, wavelength_nm: float | None = LAM) -> dict:
    """``{"table (ROOT)" | "mlp SIZE (ROOT)": (S_of, bytes, None)}``: the baked table and the
    models exported under each artifacts root (``bcsdf bake`` / ``train`` / ``export`` of this
    config there), evaluated as the plugin does (at ``wavelength_nm``, or the luminance)."""

    entries = {}
    for root in roots:
        table = bundle_table_path(cfg, root)
        nodes = BundleTable.load(table, expand=True).theta_i
        entries[f"table ({root})"] = (closure.evaluator(mi, "table", table, wavelength_nm), table.stat().st_size,
                                      None, nodes)
        for weights in sorted((stage_dir(cfg, "export", root)).glob("*/weights.npz")):
            entries[f"mlp {weights.parent.name} ({root})"] = (closure.evaluator(mi, "mlp", weights, wavelength_nm),
                                                            weights.stat().st_size, None, nodes)
    return entries


def compare(entries: dict, explicit: list, spread_deg: float) -> dict:
    """Each entry (a layout's lookup, a model) against the explicit fibers, averaged alike
    over the spread of azimuths."""
    result = {"spread_deg": spread_deg, "layouts": {},
              "directions": [{"theta_i": ti, "dphi": dp, "explicit": S, "explicit_err": se}
                             for ti, dp, S, se in explicit]}
    for ti, dp, S, se in explicit:
        line = f"  theta_i {ti:5.1f}  dphi {dp:5.1f}: explicit {S:.3f} +- {se:.3f} /sr:"
        for name, (S_of, *_) in entries.items():
            dphi = np.deg2rad(dp + spread(spread_deg))
            err = float(np.mean(S_of(0.0, np.deg2rad(ti), dphi, -np.deg2rad(ti))) / S - 1)
            result["layouts"].setdefault(name, {"errors": []})["errors"].append(err)
            line += f" {err:+.3f}"
        print(line)
    theta_i = np.deg2rad([ti for ti, *_ in explicit])
    for name, (_, nbytes, seconds, nodes) in entries.items():
        node = np.min(np.abs(theta_i[:, None] - np.asarray(nodes)[None, :]), 1) < 1e-6  # this table's own nodes
        e = np.abs(result["layouts"][name]["errors"])
        grazing = theta_i >= np.deg2rad(65.0) - 1e-9
        summary = {"bytes": nbytes, "bake_seconds": seconds, "median": float(np.median(e)),
                   "max": float(e.max()), "within_5pct": int(np.sum(e <= 0.05)), "n": len(e),
                   "median_at_nodes": _stat(np.median, e[node]), "median_between": _stat(np.median, e[~node]),
                   "median_grazing": _stat(np.median, e[grazing]), "max_grazing": _stat(np.max, e[grazing])}
        result["layouts"][name].update(summary, theta_i_nodes=np.rad2deg(nodes).round(6).tolist(),
                                       at_node=node.tolist())
        pct = {k: "-" if v is None else f"{v:.1%}" for k, v in summary.items() if k.startswith(("median", "max"))}
        print(f"[highlight] {name:11}: |error| median {pct['median']} (nodes {pct['median_at_nodes']}, between "
              f"{pct['median_between']}; theta_i >= 65: {pct['median_grazing']}, largest {pct['max_grazing']}), max "
              f"{pct['max']}, within 5% at {summary['within_5pct']} of {summary['n']}; "
              f"{summary['bytes'] / 2**20:.2f} MiB")
    return result


def _stat(f, e):
    """``f`` of the errors ``e`` (a float), or ``None`` where there are none (directions
    given by ``--theta-i`` may miss the nodes or grazing incidence)."""
    return float(f(e)) if len(e) else None


MEASURES = {"550 nm": LAM, "luminance": None}   # what the explicit fibers and the lookups are compared in


def within_bin(single: list, phi_bin: list) -> dict:
    """How far the explicit fibers at single directions lie from their own mean over a
    phi_o bin's azimuths: azimuthal structure that no table with these bins can hold, a
    floor under its single-direction errors."""
    e = np.abs([s[2] / b[2] - 1 for s, b in zip(single, phi_bin)])
    return {"median": float(np.median(e)), "max": float(e.max()), "within_5pct": int(np.sum(e <= 0.05)),
            "n": len(e)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", nargs="?", default="configs/default.yaml")
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--paths", type=int, default=8_000_000, help="paths of each layout's bake")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of each explicit render")
    p.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=list(LAYOUTS), metavar="LAYOUT",
                   help="the layouts baked (" + ", ".join(map(repr, LAYOUTS)) + ")")
    p.add_argument("--graded", default=GRADED, metavar="NODES",
                   help=f"the graded layout's theta_i nodes in degrees, a YAML list (default {GRADED})")
    p.add_argument("--measures", nargs="+", default=list(MEASURES), choices=list(MEASURES), metavar="MEASURE",
                   help="compare at 550 nm (mono renders) and/or in the luminance of spectral renders "
                        "(default both)")
    p.add_argument("--theta-i", nargs="+", type=float, default=list(THETA_I), metavar="DEG",
                   help="incident longitudes of the directions, degrees below 90 (default "
                        + " ".join(f"{t:g}" for t in THETA_I) + ")")
    p.add_argument("--models", nargs="*", default=[], metavar="ROOT",
                   help="artifacts roots whose exported models of this config are compared too")
    args = p.parse_args(argv)
    if not all(0.0 <= t < 90.0 for t in args.theta_i):
        p.error(f"--theta-i: degrees in [0, 90), got {args.theta_i}")
    cfg = load_config(args.config)
    if cfg.bake.exit not in ("auto", "uniform") or cfg.fiber.model == "ray" or cfg.bundle.twist is not None:
        raise SystemExit("bench.highlight compares a parallel ply with the uniform exit (fiber_table explicit fibers)")

    tables = bake_layouts(args.config, args.artifacts, args.paths, args.layouts, args.graded)
    result = {"paths": args.paths, "measures": {}}
    for measure in args.measures:
        wavelength_nm = MEASURES[measure]
        part = result["measures"][measure] = {"wavelength_nm": wavelength_nm}
        # single directions, then the mean over a phi_o bin's width of azimuths (theta_o still
        # exactly on the cone): a Mie fiber's azimuthal glints at one wavelength are finer than
        # any phi_o bin, so the second isolates the theta_o axis
        explicit, entries = {}, None
        for key, spread_deg in (("single", 0.0), ("phi_bin", 360.0 / cfg.bake.n_phi_o)):
            t0 = time.perf_counter()
            explicit[key] = explicit_on_cone(cfg, args.artifacts, args.spp, spread_deg, wavelength_nm, args.theta_i)
            if entries is None:  # once per measure, in the variant its renders chose (the models run in it)
                entries = table_entries(mi, tables, wavelength_nm)
                entries.update(model_entries(mi, cfg, args.models, wavelength_nm))
            print(f"[highlight] {measure}: explicit fibers at {len(explicit[key])} directions (azimuths over "
                  f"{spread_deg:g} deg) in {time.perf_counter() - t0:.0f} s; lookup / explicit - 1 on the cone ("
                  + ", ".join(entries) + ")")
            part[key] = compare(entries, explicit[key], spread_deg)
        part["within_bin"] = floor = within_bin(explicit["single"], explicit["phi_bin"])
        print(f"[highlight] {measure}: the explicit fibers at single directions against their own mean over a "
              f"phi_o bin: median {floor['median']:.1%}, largest {floor['max']:.1%}, within 5% at "
              f"{floor['within_5pct']} of {floor['n']} (structure finer than the bins)")
    out = stage_dir(cfg, "closure", args.artifacts)
    write_text(out / "bench_highlight.json", json.dumps(result, indent=2))
    plot(result, out / "highlight.png")
    print(f"[highlight] wrote {out / 'bench_highlight.json'}")
    return 0


def plot(result: dict, path) -> None:
    """``lookup / explicit - 1`` per direction, one marker per layout; a panel per measure
    (single directions, a phi_o bin's azimuths) and spectrum (550 nm, luminance)."""

    panels = [(measure, key) for measure in result["measures"] for key in ("single", "phi_bin")]
    fig, axes = plt.subplots(len(panels), 1, figsize=(12, 3.75 * len(panels)), dpi=110, sharex=True,
                             squeeze=False)
    for ax, (measure, key) in zip(axes[:, 0], panels):
        r_ = result["measures"][measure][key]
        d = r_["directions"]
        x = np.arange(len(d))
        for (name, r), m in zip(r_["layouts"].items(), "os^Dv<>pPXd*"):
            at_nodes = "" if r["median_at_nodes"] is None else f", at nodes {r['median_at_nodes']:.1%}"
            ax.plot(x, np.array(r["errors"]) * 100, m,
                    label=f"{name} ({r['bytes'] / 2**20:.2f} MiB): median {r['median']:.1%}{at_nodes}")
        ax.axhspan(-5, 5, color="0.9", zorder=0)
        ax.axhline(0, color="k", lw=0.5)
        ax.set(ylabel="lookup / explicit - 1 (%)",
               title=f"{measure}: " + ("single directions" if key == "single" else
                                       f"azimuths averaged over {r_['spread_deg']:g} deg (a phi_o bin), "
                                       "theta_o on the cone"))
        ax.legend(fontsize=8)
    axes[-1, 0].set_xticks(x, [f"{r['theta_i']:g}/{r['dphi']:g}" for r in d], rotation=90, fontsize=7)
    axes[-1, 0].set_xlabel("theta_i / dphi (deg), on the cone theta_o = -theta_i")
    fig.suptitle(f"the highlight: table lookups against explicit fibers ({result['paths']:.3g} paths per bake; "
                 "luminance: spectral renders under a flat sun)")
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    with results.recorded("highlight", smoke="--quick" in sys.argv):
        raise SystemExit(main())
