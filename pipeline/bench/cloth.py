"""What the bundle BSDF buys on cloth, measured: scale, and explicit fibers.

Needs the config's bake and export (``bcsdf run configs/glove.yaml`` up to ``export``).

``scale``     the first N yarn curves of the model (one loop to the whole glove): ply
              construction, scene load and render time (320 x 240, 4 spp, the table;
              the second render, the first compiles) and the process's peak memory,
              each N in its own process.
``explicit``  a patch of the model (its curves within a sphere around a point on its
              surface), with its flyaways, rendered from the same camera twice: every
              fiber of every ply as its own curve with the single-fiber model (the bake's
              arrangement scaled to the ply, turned along it as the bake's helices) and
              the plies with the bundle table. Each is the mean of many seeds, so that
              the explicit reference converges; the means of its two halves against each
              other measure each side's own noise. FLIP of the bundle against the
              explicit reference, mean radiance, time *at equal noise* (variance per
              sample x seconds per sample: Monte Carlo variance falls as 1/spp) and peak
              memory, at camera distances where a ply spans 1 .. 8 pixels; FLIP again with
              both images averaged over a ply's width (``ply_scale``: the ply's own
              colour and shading, without the fibers inside it). The bundle
              is rendered with the config's exit model (``cloth.exit_split``) and again with
              each other one of ``EXITS``: ``displaced_exit`` off (all light leaves a ply
              where it entered, as single scattering does), the displaced exit for all of
              it, the singly scattered share sent from where it entered in the shadow rays:
              where the exit model moves the colour (multiply scattered light is red in the
              dyed yarn), and at what noise.
``memory``    the whole model, counted: its plies' control points with the table (or
              the MLP) against every fiber of every ply as a curve.
``overlap``   two straight plies touching and interpenetrating, explicit fibers against
              bundles, with ``bundle_path``'s ``overlaps`` off and on (far-field
              intensity, three views): where the bundle BSDF errs where yarns overlap.

Records ``benchmarks/cloth.json`` (``pipeline.bench.results``; a part not measured keeps its
rows) and draws ``docs/images/cloth_scale.png``, ``cloth_explicit.png``::

    .venv/bin/python -m pipeline.bench.cloth [CONFIG]            # configs/glove.yaml
    .venv/bin/python -m pipeline.bench.cloth --quick             # fewer sizes and distances
    .venv/bin/python -m pipeline.bench.cloth --parts explicit --ply-px 4   # one part, one distance (the others kept)
    .venv/bin/python -m pipeline.bench.cloth --parts explicit --ply-px 4 --samples 4   # 4x the samples, kept apart
    .venv/bin/python -m pipeline.bench.cloth --parts explicit --ply-px 4 --samples 4 --near 16   # a near-field table
"""

from __future__ import annotations

import argparse
import functools
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import drjit as dr
import flip_evaluator as flip
import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
from scipy.ndimage import uniform_filter

import mitsuba_ext
from mitsuba_ext.backends import load_backend
from models.bundle import zhao2016_row
from models.cloth.bcc import read_bcc
from models.cloth.curves import write_mitsuba_curves
from models.cloth.fibers import explicit_fibers, explicit_point_count, patch
from models.cloth.flyaways import tapered
from models.cloth.yarn import build_plies
from models.io import atomic_path
from pipeline import closure, scenes
from pipeline.artifacts import fiber_table_path, load_bundle_table
from pipeline.bench import results
from pipeline.bsdfs import backend_props
from pipeline.build import build_bundle, build_ply
from pipeline.loading import load_config
from pipeline.garment import build, flyaways, yarn_model, yarn_spec
from pipeline.images import exposure_of, flip_and_psnr, to_srgb

from ..graph import require
from . import baked

DOCS = Path(__file__).resolve().parents[2] / "docs"
PLY_PX = (1, 2, 4, 8)   # the camera distances: a ply's width in pixels
OVERLAPS = True         # the explicit part's bundle_path overlaps (both sides; see child_overlap)
# the explicit part's max_depth, both sides. Every fiber hit of the explicit reference is a
# bounce, and light in the dyed yarn (albedo 0.99 in the red) meets dozens of fibers: at the
# cloth config's 16 the reference lost 11% of its red (docs/BENCHMARKS.md, "Cloth"). Russian
# roulette ends the paths long before this limit (64 and 256 render the same image).
EXPLICIT_DEPTH = 256
BUNDLE_SPP = (32, 8)        # (spp, seeds) of the bundle render ...
EXPLICIT_SPP = (32, 32)     # ... and of the explicit reference: its noise measured
# the exit models the bundle is rendered with besides the config's own (bundle_path's settings)
EXITS = {"entry": {"displaced_exit": False, "exit_split": "none"},   # all light leaves where it entered
         "none": {"displaced_exit": True, "exit_split": "none"},     # all of it from the displaced exit
         "emitter": {"displaced_exit": True, "exit_split": "emitter"},  # the single share's shadow rays from entry
         "all": {"displaced_exit": True, "exit_split": "all"}}  # ... and the paths' next rays


def peak_mb() -> float:
    """This process's peak resident memory (``VmHWM``: reset by exec, where ``ru_maxrss``
    keeps the parent's peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _load(config):
    """The config a measurement runs: ``[path, *overrides]`` (JSON to the children)."""
    return load_config(config[0], config[1:])


def _setup(config, root):
    cfg = _load(config)
    props = backend_props(cfg, root, "table")
    mi.set_variant(cfg.cloth.variant)
    mitsuba_ext.register()
    return mi, cfg, props


def _render(mi, scene_dict, spp_seeds=(0, 1)):
    """Images of two seeds and the seconds of the second (kernels compiled)."""

    scene = mi.load_dict(scene_dict)
    images, seconds = [], 0.0
    for seed in spp_seeds:
        t0 = time.perf_counter()
        img = mi.render(scene, seed=seed)
        dr.eval(img)
        dr.sync_thread()
        seconds = time.perf_counter() - t0
        images.append(np.array(img, np.float64)[..., :3])
    if not all(np.all(np.isfinite(i)) for i in images):
        raise FloatingPointError("a cloth render holds NaN or Inf")
    return images, seconds


# -- children: one measurement per process (its peak memory is its own) ------------------
def child_scale(config, root, n_curves, out):
    mi, cfg, props = _setup(config, root)
    base = peak_mb()
    c = cfg.cloth.model_copy(update={"curves": n_curves, "width": 320, "height": 240})
    cfg = cfg.model_copy(update={"cloth": c})
    t0 = time.perf_counter()
    info, g = build(cfg, Path(out))
    built = time.perf_counter() - t0
    t0 = time.perf_counter()
    scene = mi.load_dict(scenes.cloth_scene(mi, c, {"yarn": scenes.ply_shape(Path(out) / "plies.txt", props, g.radius)},
                                            info["bbox_mm"], 4))
    loaded = time.perf_counter() - t0
    rendered = []
    for seed in (0, 1):  # the first compiles (the camera's framing is in the kernel: a new one per N)
        t0 = time.perf_counter()
        img = mi.render(scene, seed=seed)
        dr.eval(img)
        dr.sync_thread()
        rendered.append(time.perf_counter() - t0)
    return {"curves": n_curves, "control_points": info["control_points"], "build_s": built, "load_s": loaded,
            "first_render_s": rendered[0], "render_s": rendered[1], "peak_mb": peak_mb(), "base_mb": base}


def patch_scene(cfg, ply_px, out: Path):
    """The patch of the model (every yarn's control points within 16 yarn radii of a point
    on its upper surface), its plies, its flyaways (the cloth stage's, drawn about the
    patch's plies) and a camera at which a ply spans ``ply_px`` pixels."""

    c = cfg.cloth.model_copy(update={"curves": None, "width": 192, "height": 192, "ground": False})
    model = yarn_model(c)
    pts = np.concatenate([cv.points for cv in model.curves])
    centre = pts[np.argmax(pts @ np.array([0.3, 1.0, 0.5]))]   # a point on the upper surface
    yarn = yarn_spec(c)
    piece = patch(model, centre, 16 * yarn.radius / c.units_mm)
    g = build_plies(piece, c.units_mm, yarn, c.tolerance)
    lo, hi = np.concatenate(g.curves).min(0), np.concatenate(g.curves).max(0)
    target = c.units_mm * centre
    outward = target - c.units_mm * pts.mean(0)
    outward = outward / np.linalg.norm(outward) + np.array([0.0, 0.6, 0.0])
    outward /= np.linalg.norm(outward)
    distance = yarn.r_ply * c.width / (ply_px * np.tan(np.radians(c.fov_deg / 2)))
    return c, yarn, g, (lo, hi), (target + distance * outward, target)


def child_explicit(config, root, which, ply_px, spp, seeds, out):
    """The patch rendered ``seeds`` times at ``spp`` each: ``which`` = ``bundle`` (the plies
    with the bake's table and the config's exit model), ``bundle_<exit>`` (the same with
    another exit model of ``EXITS``) or ``explicit`` (every fiber of every
    ply as its own curve with the single-fiber model), ``bundle_far`` (a near-field table read
    as its far field, ``near_field: false``); all carry the same flyaways; ``sky``:
    nothing but the sky (which pixels the cloth changes). Saves the means of the two halves
    of the seeds (their difference is the noise of the mean)."""

    mi, cfg, props = _setup(config, root)
    base = peak_mb()
    out = Path(out)
    c, yarn, g, bbox, view = patch_scene(cfg, ply_px, out)
    fly_info, fly_shape = ({}, None) if which == "sky" else flyaways(cfg.model_copy(update={"cloth": c}), out, g,
                                                                     yarn, root)
    shapes = {"flyaways": fly_shape} if fly_shape else {}
    geometry_points = 0
    # the curves' ends at the patch's cut tapered over a short tip: Mitsuba 3.9's
    # bsplinecurve crashes now and then on rays that hit a blunt open end (its PR #1928)
    if which.startswith("bundle"):
        with atomic_path(out / "patch_plies.txt") as tmp, open(tmp, "w") as fh:
            write_mitsuba_curves(fh, (tapered(C, g.radius) for C in g.curves))
        far = {"near_field": False} if which == "bundle_far" else {}
        shapes["yarn"] = scenes.ply_shape(out / "patch_plies.txt", {**props, **far}, g.radius)
        geometry_points = g.control_points + 6 * len(g.curves)
    elif which == "explicit":
        bundle = build_bundle(cfg)
        table, _ = load_bundle_table(cfg, root)
        fiber = closure.explicit_fiber(fiber_table_path(cfg, root), table.meta.get("exit", "uniform"), 550.0)
        fiber.pop("wavelength")
        fiber.pop("up")
        twist = cfg.bundle.twist
        curves, radii = explicit_fibers(g.curves, g.radius, bundle.centers, bundle.radii, bundle.bounding_radius,
                                        per_segment=1,
                                        pitch_um=None if twist is None else twist.pitch(bundle.bounding_radius))
        # one file per fiber radius (a Poisson arrangement has one)
        for k, r in enumerate(np.unique(radii)):
            with atomic_path(out / f"patch_fibers_{k}.txt") as tmp, open(tmp, "w") as fh:
                write_mitsuba_curves(fh, (tapered(cv, float(r)) for cv, ri in zip(curves, radii) if ri == r))
            shapes[f"fibers_{k}"] = {"type": "bsplinecurve", "filename": str(out / f"patch_fibers_{k}.txt"),
                                     "bsdf": {**fiber, "radius": float(r)}}
        geometry_points = sum(len(cv) + 6 for cv in curves)  # with the tips
    scene = scenes.cloth_scene(mi, c, shapes, bbox, spp, view=view)
    scene["integrator"].update(overlaps=OVERLAPS,  # both sides alike (the patch's yarns interpenetrate)
                               max_depth=EXPLICIT_DEPTH)
    if which.startswith("bundle_") and which != "bundle_far":
        scene["integrator"].update(EXITS[which.removeprefix("bundle_")])
    scene = mi.load_dict(scene)
    loaded = peak_mb()

    # -- the renders: the first (its kernel compiled) apart, the rest timed together
    t0 = time.perf_counter()
    dr.eval(mi.render(scene, seed=10_000))
    dr.sync_thread()
    first = time.perf_counter() - t0
    halves = [0.0, 0.0]
    t0 = time.perf_counter()
    for seed in range(seeds):
        img = mi.render(scene, seed=seed)
        dr.eval(img)
        halves[seed % 2] = halves[seed % 2] + np.array(img, np.float64)[..., :3] / (seeds // 2)
    seconds = time.perf_counter() - t0
    if not all(np.all(np.isfinite(h)) for h in halves):
        raise FloatingPointError("a cloth render holds NaN or Inf")
    np.savez(out / f"{which}_{ply_px}.npz", a=halves[0], b=halves[1])
    return {"which": which, "ply_px": ply_px, "spp": spp * seeds, "seconds": seconds, "first_render_s": first,
            "seconds_per_spp": seconds / (spp * seeds), "peak_mb": peak_mb(), "base_mb": base,
            "loaded_mb": loaded, "control_points": geometry_points, "plies": len(g.curves),
            "hairs": fly_info.get("hairs", 0)}


SPEED_SIZE, SPEED_SPP = (320, 240), 8
# bundle_path's (shadow_rr, overlaps) compared: shadow_rr 0 traces every crossing; overlaps
# False lets light that leaves a ply inside another cross it unseen. The third: the plies'
# fewest samples per segment of the model's curves (2, the stage's; 8, as densely as the
# centre line is sampled: the same curves in 29% more control points on the glove). The
# fourth: the hairs' curve (cloth.flyaways.curve; the same hairs either way)
SPEED_CASES = ((0.0, True, 2, "linearcurve"), (0.1, True, 2, "linearcurve"), (0.3, True, 2, "linearcurve"),
               (0.1, False, 2, "linearcurve"), (0.1, False, 8, "linearcurve"), (0.1, False, 2, "bsplinecurve"))


def child_speed(config, root, shadow_rr, geometry, out, overlaps=True):
    """The whole model (plies and flyaways, ``geometry``: the files the parent built) at
    ``SPEED_SIZE`` x ``SPEED_SPP`` with the integrator's ``shadow_rr`` and ``overlaps``:
    seconds per render (compiled), the mean and the variance per sample (from two seeds)."""

    mi, cfg, props = _setup(config, root)
    g = json.loads(Path(geometry).read_text())
    shapes = {"yarn": scenes.ply_shape(g["plies"], props, g["radius"])}
    if g["flyaways"]:
        shapes["flyaways"] = g["flyaways"]
    c = cfg.cloth.model_copy(update={"width": SPEED_SIZE[0], "height": SPEED_SIZE[1]})
    scene = scenes.cloth_scene(mi, c, shapes, g["bbox"], SPEED_SPP)
    scene["integrator"].update(shadow_rr=shadow_rr, overlaps=overlaps)
    (a, b), seconds = _render(mi, scene)
    return {"shadow_rr": shadow_rr, "overlaps": overlaps, "seconds": seconds, "mean": float((a + b).mean() / 2),
            "variance_per_spp": variance_per_spp(a, b, SPEED_SPP)}


OVERLAP_SPACING = (2.0, 1.7, 1.4)   # centre distances of two plies, in ply radii (2: touching)
OVERLAP_VIEWS = (((0, 30), (180, -30)), ((90, 20), (90, -20)), ((45, 10), (200, -25)))  # (phi, theta) in, out, deg


def child_overlap(config, root, spacing, lam_nm, spp, turns, overlaps):
    """Two straight parallel plies ``spacing`` ply radii apart, in the closure scene (a sun,
    an orthographic camera, far-field intensity per unit length), explicit against bundle:
    every fiber a helix with ``fiber_ray`` (``turns`` turns of both arrangements) against
    two ``bsplinecurve`` plies with the twisted table, at ``lam_nm``, for each of
    ``OVERLAP_VIEWS``, with ``bundle_path``'s ``overlaps`` as given. Where the plies
    interpenetrate (spacing < 2), light that leaves one ply inside the other meets fibers of
    the other in the explicit scene, and, unless ``overlaps``, nothing in the bundle scene
    (a curve reports no hit from inside)."""

    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    cfg = _load(config)
    ply = build_ply(cfg)
    fiber = closure.explicit_fiber(fiber_table_path(cfg, root), "lobe", lam_nm)
    unit = 1e-3
    R = ply.bundle.bounding_radius * unit
    hs, xs = 4.0 * R, (-0.5 * spacing * R, 0.5 * spacing * R)
    T = mi.ScalarTransform4f()
    bundle = {**backend_props(cfg, root, "table"), "wavelength": lam_nm, "up": closure.UP}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        helices = Path(tmp) / "helices.txt"
        closure.write_curves(closure.helix_control_points(ply, 40 * hs, unit), helices)
        for k, x in enumerate(xs):
            closure.write_curves([np.array([[x, y, 0.0, R] for y in np.linspace(-40 * hs, 40 * hs, 9)])],
                                 Path(tmp) / f"axis_{k}.txt")
        for (pi_, ti), (po, to) in OVERLAP_VIEWS:
            w_i, w_o = closure.direction(*np.radians([pi_, ti])), closure.direction(*np.radians([po, to]))
            explicit = []
            for t in range(turns):
                shapes = {}
                for k, x in enumerate(xs):  # the two plies' arrangements turned apart
                    s = closure.explicit_twisted_shapes(helices, fiber, 2 * np.pi * t / turns + 1.3 * k)["ply"]
                    shapes[f"ply_{k}"] = {**s, "to_world": T.translate([x, 0.0, 0.0]) @ s["to_world"]}
                sc = closure.scene(mi, shapes, w_i, w_o, hs, resolution=64, spp=spp, seed=t)
                sc["integrator"]["overlaps"] = overlaps
                explicit.append(closure.rendered_intensity(mi, sc, w_o, hs))
            shapes = {f"ply_{k}": {"type": "bsplinecurve", "filename": str(Path(tmp) / f"axis_{k}.txt"),
                                   "bsdf": bundle} for k in range(2)}
            sc = closure.scene(mi, shapes, w_i, w_o, hs, resolution=64, spp=4 * spp)
            sc["integrator"]["overlaps"] = overlaps
            b = closure.rendered_intensity(mi, sc, w_o, hs)
            e = float(np.mean(explicit))
            rows.append({"view": [[pi_, ti], [po, to]], "explicit": e, "bundle": b, "ratio": b / e,
                         "ratio_se": float(np.std(explicit) / np.sqrt(turns)) / e})
    return {"spacing": spacing, "lam_nm": lam_nm, "overlaps": overlaps, "views": rows}


def child_memory(config, root, out):
    """The whole model's memory, counted: its plies' control points with the table (or the
    MLP), against every fiber of every ply as its own curve (the bake's fiber count, and the
    Zhao yarn's fibers per ply), at 20 bytes a control point (x, y, z, r and a segment index
    in float32 / uint32: what a curve renderer holds at least; the BVH comes on top of both)."""

    mi, cfg, props = _setup(config, root)
    _, g = build(cfg, Path(out))
    bundle = build_bundle(cfg)
    twist = cfg.bundle.twist
    pitch_um = None if twist is None else twist.pitch(bundle.bounding_radius)
    per_fiber = explicit_point_count(g.curves, g.radius, 1, bundle.bounding_radius, per_segment=1, pitch_um=pitch_um)
    # the fibers sampled as the plies are (16 a turn of their helix: both B-splines then stray
    # ~1e-4 of their helix radius) rather than as the explicit reference renders them (32)
    per_fiber_16 = explicit_point_count(g.curves, g.radius, 1, bundle.bounding_radius, per_segment=1,
                                        pitch_um=pitch_um, samples_per_turn=16)
    table = load_backend("table", mi.Float, table=props["table"])
    result = {"ply_points": g.control_points, "fiber_points_per_fiber": per_fiber,
              "fiber_points_per_fiber_16": per_fiber_16, "fibers_bake": len(bundle.radii),
              "fibers_zhao": int(zhao2016_row(cfg.cloth.yarn)["m_fibers_per_ply"]), "bytes_per_point": 20,
              "table_bytes": table.nbytes + table.sampling_grid(0.1).nbytes}
    try:
        mlp = load_backend("mlp", mi.Float, model=backend_props(cfg, root, "mlp")["model"])
        result["mlp_bytes"] = mlp.nbytes + mlp.sampling_grid(0.1).nbytes
    except (FileNotFoundError, ValueError, KeyError):  # no exported model in this root
        pass
    plies = 20 * result["ply_points"]
    for n in ("bake", "zhao"):
        for tail, count in (("", per_fiber), ("_16", per_fiber_16)):
            fibers = 20 * count * result[f"fibers_{n}"]
            result[f"explicit_bytes_{n}{tail}"] = fibers
            result[f"ratio_table_{n}{tail}"] = fibers / (plies + result["table_bytes"])
            if "mlp_bytes" in result:
                result[f"ratio_mlp_{n}{tail}"] = fibers / (plies + result["mlp_bytes"])
    return result


def _child(kind, *args):
    cmd = [sys.executable, "-m", "pipeline.bench.cloth", "--child", json.dumps([kind, *args])]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{kind} {args}: {r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


# -- the parent: the measurements, the figures --------------------------------------------
def variance_per_spp(a, b, spp: int) -> float:
    """Monte Carlo variance of one sample per pixel, from two independent images ``a``, ``b``
    of ``spp`` samples each (their difference has twice the variance of each)."""
    return spp * float(np.mean((a - b) ** 2)) / 2


def masked_flip(reference, test, exposure, mask) -> float:
    """Mean LDR-FLIP over ``mask`` (the yarn's pixels), on the displayed sRGB images."""

    error_map, _, _ = flip.evaluate(to_srgb(reference, exposure), to_srgb(test, exposure), "LDR", applyMagma=False)
    error_map = np.asarray(error_map, np.float64)
    error_map = error_map[..., 0] if error_map.ndim == 3 else error_map
    return float(np.mean(error_map[mask]))


def colour_ratio(test, reference, mask) -> dict:
    """Mean radiance of ``test`` over ``reference`` on the cloth's pixels ``mask`` (the sky's,
    equal in both, would dilute it), and per channel: multiply scattered light in the dyed
    yarn is red."""
    rgb = (test[mask].mean(0) / reference[mask].mean(0)).tolist()
    return {"mean_ratio": float(test[mask].mean() / reference[mask].mean()), "mean_ratio_rgb": rgb,
            **{f"ratio_{c}": v for c, v in zip("rgb", rgb)}}   # flat, for the record's table


def ply_scale(image, ply_px: int):
    """``image [h, w, 3]`` averaged over a ply's width (a ``ply_px`` square box): what a
    far-field BSDF claims to draw, the ply's mean radiance, without the single fibers and
    the twist's stripes inside a ply (and without most of the render noise)."""

    return uniform_filter(image, size=(ply_px, ply_px, 1), mode="nearest")


def measure_scale(config, root, quick, tmp) -> list:
    cfg = _load(config)
    total = len(read_bcc(cfg.cloth.model).curves) if cfg.cloth.model else cfg.cloth.swatch.courses
    sizes = sorted({n for n in ((1, 10, total) if quick else (1, 3, 10, 30, total)) if n <= total})
    scale = []
    for n in sizes:
        scale.append(_child("scale", config, root, n, tmp))
        print(f"[scale] {n} curves: {scale[-1]}", flush=True)
    return scale


def measure_speed(config, root, quick, tmp) -> list:
    """The whole model's render with and without the shadow rays' Russian roulette and the
    overlapping plies' entry, with plies sampled more densely (the same hairs) and with the
    hairs as B-splines (the same plies), side by side (each in its own process): seconds, and
    the time to equal noise."""
    cfg = _load(config)
    cases = SPEED_CASES[:2] if quick else SPEED_CASES
    plies, hairs, geometry = {}, {}, {}
    for per_segment in sorted({c[2] for c in cases}):  # 2 first: the hairs are drawn about the stage's plies
        d = Path(tmp) / f"plies_{per_segment}"
        d.mkdir(parents=True, exist_ok=True)
        plies[per_segment] = d, *build(cfg, d, samples_per_segment=per_segment)
    for curve in sorted({c[3] for c in cases}):
        d, _, g = plies[2]
        f = cfg.cloth.flyaways and cfg.cloth.flyaways.model_copy(update={"curve": curve})
        c = cfg.model_copy(update={"cloth": cfg.cloth.model_copy(update={"flyaways": f})})
        (d / curve).mkdir(exist_ok=True)
        hairs[curve] = flyaways(c, d / curve, g, yarn_spec(cfg.cloth), root)[1]
    for per_segment, curve in {c[2:] for c in cases}:
        d, info, g = plies[per_segment]
        geometry[per_segment, curve] = d / f"geometry_{curve}.json"
        geometry[per_segment, curve].write_text(json.dumps({"plies": str(d / "plies.txt"), "radius": g.radius,
                                                            "flyaways": hairs[curve], "bbox": info["bbox_mm"]}))
    rows = []
    for rr, ovl, per_segment, curve in cases:
        rows.append(_child("speed", config, root, rr, str(geometry[per_segment, curve]), tmp, ovl))
        rows[-1].update(ply_samples_per_segment=per_segment, ply_points=plies[per_segment][2].control_points,
                        hairs=curve)
    for r in rows:
        r["cost"] = r["seconds"] * r["variance_per_spp"]
    for r in rows:
        r["speed_up"] = rows[0]["seconds"] / r["seconds"]
        r["speed_up_equal_noise"] = rows[0]["cost"] / r["cost"]
        print(f"[speed] shadow_rr {r['shadow_rr']}, overlaps {r['overlaps']}, plies {r['ply_points']:,} control points, "
              f"hairs {r['hairs']}: "
              f"{r['seconds']:.2f} s ({SPEED_SIZE[0]} x {SPEED_SIZE[1]} x "
              f"{SPEED_SPP} spp), mean {r['mean']:.5f}, x{r['speed_up']:.2f} faster, x{r['speed_up_equal_noise']:.2f} "
              "at equal noise", flush=True)
    return rows


def measure_explicit(config, root, quick, tmp, ply_px=None, samples=1) -> list:
    cfg = _load(config)
    own = cfg.cloth.exit_split
    others = [k for k in EXITS if k != own]
    # ``samples`` times the seeds on both sides (seeds 0, 1, ...: the standard run's and more)
    bundle_spp, explicit_spp = ((spp, samples * seeds) for spp, seeds in (BUNDLE_SPP, EXPLICIT_SPP))
    renders = [("bundle", bundle_spp)] + [(f"bundle_{k}", bundle_spp) for k in others] + [("explicit", explicit_spp)]
    near = load_bundle_table(cfg, root)[0].near is not None
    if near:   # a near-field table: also read as its far field, to see what the near field changes
        renders.insert(1, ("bundle_far", bundle_spp))
    explicit = []
    for px in ((4,) if quick else ply_px or PLY_PX):
        row = {"ply_px": px, "exit_split": own}
        pair = {}
        try:
            for which, (spp, seeds) in renders:
                m = _child("explicit", config, root, which, px, spp // 4 if quick else spp, seeds, tmp)
                data = np.load(Path(tmp) / f"{which}_{px}.npz")
                pair[which] = (data["a"], data["b"])
                row[which] = {**m, "variance_per_spp": variance_per_spp(data["a"], data["b"], m["spp"] // 2),
                              "mean": float(np.mean(data["a"] + data["b"]) / 2)}
                print(f"[explicit] {px} px {which}: {row[which]}", flush=True)
        except RuntimeError as e:
            # Mitsuba 3.9's curve intersection can crash the process on touching fibers (a
            # segfault, not an error): the distance is reported as failed, the others stand
            print(f"[explicit] {px} px: the {which} render's process died ({str(e).splitlines()[0][:200]})")
            explicit.append({"ply_px": px, "failed": which})
            continue
        ref = 0.5 * (pair["explicit"][0] + pair["explicit"][1])
        test = 0.5 * (pair["bundle"][0] + pair["bundle"][1])
        exposure = exposure_of(ref)
        # FLIP over the cloth's pixels only (the sky would dilute it), at the reference's exposure
        mask = cloth_pixels(ref, test, _child_sky(config, root, px, tmp))
        row["flip_image"], row["psnr"], _ = flip_and_psnr(ref, test, exposure)
        row["flip"] = masked_flip(ref, test, exposure, mask)
        # each side's own noise in FLIP: the means of its two halves against each other (each
        # half has twice the variance of the whole: an upper bound on the whole's noise)
        row["flip_explicit_noise"] = masked_flip(*pair["explicit"], exposure, mask)
        row["flip_bundle_noise"] = masked_flip(*pair["bundle"], exposure, mask)
        # FLIP with half the samples on both sides (the halves crossed, averaged) against all
        # of them: extrapolated to noise-free images if FLIP^2 falls as 1/spp, as a squared
        # error does (an estimate: FLIP is not a squared error; both figures are kept)
        halves = np.mean([masked_flip(e, b, exposure, mask) for e in pair["explicit"] for b in pair["bundle"]])
        row["flip_half_samples"] = float(halves)
        row["flip_extrapolated"] = float(np.sqrt(max(0.0, 2 * row["flip"] ** 2 - halves ** 2)))
        # the same at the ply's scale: where the bundle and the explicit fibers differ at the
        # scale of a ply (its colour, its shading) rather than inside it (fibers, stripes)
        row["flip_ply_scale"] = masked_flip(ply_scale(ref, px), ply_scale(test, px), exposure, mask)
        row["flip_ply_scale_explicit_noise"] = masked_flip(*(ply_scale(h, px) for h in pair["explicit"]), exposure,
                                                           mask)
        row["yarn_pixels"] = int(mask.sum())
        row.update(colour_ratio(test, ref, mask))
        row["mean_ratio_image"] = row["bundle"]["mean"] / row["explicit"]["mean"]
        # what the colour bias alone costs in FLIP: the reference against itself scaled by the
        # bundle's mean ratio per channel (no noise, no structure; FLIP is steep in colour)
        row["flip_colour_only"] = masked_flip(ref, ref * np.asarray(row["mean_ratio_rgb"]), exposure, mask)
        # time to equal noise: variance per sample x seconds per sample (variance falls as 1/spp)
        cost = {w: row[w]["variance_per_spp"] * row[w]["seconds_per_spp"] for w in ("bundle", "explicit")}
        row["time_ratio_equal_noise"] = cost["explicit"] / cost["bundle"]
        row["memory_ratio"] = (row["explicit"]["peak_mb"] - row["explicit"]["base_mb"]) / max(
            1.0, row["bundle"]["peak_mb"] - row["bundle"]["base_mb"])
        row["geometry_ratio"] = row["explicit"]["control_points"] / row["bundle"]["control_points"]
        # the exit model's share of the colour, and its noise: the bundle with each other exit
        row["exits"] = {}
        for k in others:
            a, b = pair[f"bundle_{k}"]
            other = 0.5 * (a + b)
            r = row[f"bundle_{k}"]
            row["exits"][k] = {"flip": masked_flip(ref, other, exposure, mask), **colour_ratio(other, ref, mask),
                               "time_ratio_equal_noise": cost["explicit"] / (r["variance_per_spp"] *
                                                                             r["seconds_per_spp"])}
        if near:
            far = 0.5 * (pair["bundle_far"][0] + pair["bundle_far"][1])
            row["far_field"] = {"flip": masked_flip(ref, far, exposure, mask), **colour_ratio(far, ref, mask),
                                "flip_ply_scale": masked_flip(ply_scale(ref, px), ply_scale(far, px), exposure, mask)}
            row["flip_far_field"] = row["far_field"]["flip"]   # flat, for the record's table
            row.update({f"far_ratio_{c}": row["far_field"][f"ratio_{c}"] for c in "rgb"})
            print(f"[explicit] {px} px, the same table as a far field: FLIP {row['far_field']['flip']:.3f}, mean RGB "
                  f"{np.round(row['far_field']['mean_ratio_rgb'], 3).tolist()}, at the ply's scale "
                  f"{row['far_field']['flip_ply_scale']:.3f}", flush=True)
        explicit.append(row)
        np.save(Path(tmp) / f"pair_{px}.npy", np.stack([ref, test]))
        print(f"[explicit] {px} px: FLIP {row['flip']:.3f}, half the samples {row['flip_half_samples']:.3f}, "
              f"extrapolated {row['flip_extrapolated']:.3f} (noise: explicit halves {row['flip_explicit_noise']:.3f}, "
              f"bundle halves {row['flip_bundle_noise']:.3f}), mean x{row['mean_ratio']:.3f} (RGB "
              f"{np.round(row['mean_ratio_rgb'], 3).tolist()}), equal-noise time "
              f"x{row['time_ratio_equal_noise']:.1f}, memory x{row['memory_ratio']:.1f}, geometry "
              f"x{row['geometry_ratio']:.0f} (exit_split {own}); at the ply's scale FLIP {row['flip_ply_scale']:.3f} "
              f"(explicit halves {row['flip_ply_scale_explicit_noise']:.3f}); the colour bias alone "
              f"{row['flip_colour_only']:.3f}", flush=True)
        for k, x in row["exits"].items():
            print(f"[explicit] {px} px, exit {k}: FLIP {x['flip']:.3f}, mean RGB {np.round(x['mean_ratio_rgb'], 3).tolist()}, "
                  f"equal-noise time x{x['time_ratio_equal_noise']:.1f}", flush=True)
    return explicit


def _child_sky(config, root, px, tmp) -> np.ndarray:
    """The sky alone from the patch's camera at ``px``."""
    _child("explicit", config, root, "sky", px, 4, 2, tmp)
    sky = np.load(Path(tmp) / f"sky_{px}.npz")
    return 0.5 * (sky["a"] + sky["b"])


def cloth_pixels(ref, test, sky) -> np.ndarray:
    """The cloth's pixels: where the sky alone is dark (the patch is seen from above, against
    the sky below the horizon, which is black) and either image is not. The few pixels where
    the cloth stands before the bright sky are left out: at their edges the sky's own pixel
    noise is larger than the cloth's share, and counted they made the two look alike."""
    Y = (ref + test).sum(-1)
    dark = 1e-3 * Y.max()
    return (sky.sum(-1) < dark) & (Y > dark)


def measure_overlap(config, root, quick, tmp) -> list:
    """Two straight plies touching and interpenetrating, explicit fibers against bundles
    (:func:`child_overlap`): where the bundle BSDF errs on cloth whose yarns overlap."""
    rows = []
    for overlaps in (False, True):
        for spacing in (OVERLAP_SPACING[::2] if quick else OVERLAP_SPACING):
            r = _child("overlap", config, root, spacing, 650.0, 8 if quick else 16, 4 if quick else 8, overlaps)
            rows.append(r)
            print(f"[overlap] overlaps {overlaps}, centres {spacing} ply radii apart: bundle / explicit per view "
                  + "  ".join(f"{v['ratio']:.3f} +- {v['ratio_se']:.3f}" for v in r["views"]), flush=True)
    return rows


def measure_memory(config, root, quick, tmp) -> dict:
    memory = _child("memory", config, root, tmp)
    print(f"[memory] {memory}", flush=True)
    return memory


PARTS = {"scale": measure_scale, "speed": measure_speed, "explicit": measure_explicit, "memory": measure_memory,
         "overlap": measure_overlap}


def plot(result, tmp, path_scale, path_explicit):

    if result.get("scale"):
        plot_scale(plt, result["scale"], path_scale)
    if [r for r in result.get("explicit", []) if "failed" not in r]:
        if {r["ply_px"] for r in result["explicit"]} >= set(PLY_PX):
            plot_explicit(plt, result["explicit"], tmp, path_explicit)
        else:  # its pictures are of this run's renders: a part of the distances keeps the last plot
            print(f"[explicit] {path_explicit} not redrawn: it is drawn when every distance {PLY_PX} is measured")


def plot_scale(plt, s, path_scale):
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    n = [r["curves"] for r in s]
    ax[0].plot(n, [r["build_s"] for r in s], "o-", label="plies built")
    ax[0].plot(n, [r["load_s"] for r in s], "s-", label="scene loaded")
    ax[0].plot(n, [r["render_s"] for r in s], "^-", label="rendered (320 x 240 x 4 spp, compiled)")
    ax[0].set(xscale="log", yscale="log", xlabel="yarn curves", ylabel="seconds")
    ax[0].legend(fontsize=8)
    ax[1].plot(n, [r["peak_mb"] - r["base_mb"] for r in s], "o-")
    ax[1].set(xscale="log", xlabel="yarn curves", ylabel="peak memory above start (MB)")
    fig.tight_layout()
    fig.savefig(path_scale, dpi=110)
    plt.close(fig)


def plot_explicit(plt, explicit, tmp, path_explicit):
    e = [r for r in explicit if "failed" not in r]
    fig, ax = plt.subplots(1, 1 + min(2, len(e)), figsize=(4 + 4 * min(2, len(e)), 5.4))
    ax = np.atleast_1d(ax)
    ax[0].plot([r["ply_px"] for r in e], [r["flip"] for r in e], "o-",
               label=f"bundle (exit_split {e[0].get('exit_split', 'none')}) vs explicit fibers")
    ax[0].plot([r["ply_px"] for r in e], [r["flip_extrapolated"] for r in e], "o:", color="C0", alpha=0.6,
               label="bundle vs explicit, extrapolated to no noise")
    others = {"entry": ("all light leaving where it entered", "C3"), "none": ("all from the displaced exit", "C4"),
              "emitter": ("the single share's shadow rays from entry", "C5"),
              "all": ("the single share's rays from entry", "C6")}
    for k, (label, colour) in others.items():
        rows = [r for r in e if k in r.get("exits", {})]
        if rows:
            ax[0].plot([r["ply_px"] for r in rows], [r["exits"][k]["flip"] for r in rows], "s-", color=colour,
                       alpha=0.7, label=f"bundle, {label}, vs explicit")
    scaled = [r for r in e if "flip_ply_scale" in r]
    if scaled:
        ax[0].plot([r["ply_px"] for r in scaled], [r["flip_ply_scale"] for r in scaled], "D-", color="C7",
                   label="bundle vs explicit, both averaged over a ply's width")
    ax[0].plot([r["ply_px"] for r in e], [r["flip_explicit_noise"] for r in e], "x--",
               label="explicit: half vs half (its noise)")
    ax[0].plot([r["ply_px"] for r in e], [r["flip_bundle_noise"] for r in e], "+:",
               label="bundle: half vs half (its noise)")
    ax[0].axhline(0.1, color="grey", lw=0.8)
    ax[0].set(xscale="log", xlabel="ply width (pixels)", ylabel="mean FLIP over the cloth's pixels")
    ax[0].set_xticks([r["ply_px"] for r in e], [str(r["ply_px"]) for r in e])
    ax[0].minorticks_off()
    ax[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.16))  # below: the curves fill the axes
    for a, r in zip(ax[1:], [e[len(e) // 2], e[-1]][: len(ax) - 1]):
        ref, test = np.load(Path(tmp) / f"pair_{r['ply_px']}.npy")
        x = exposure_of(ref)
        a.imshow(np.concatenate([to_srgb(ref, x), to_srgb(test, x)], 1))
        a.set_title(f"ply {r['ply_px']} px: explicit fibers | bundle", fontsize=9)
        a.axis("off")
    fig.tight_layout()
    fig.savefig(path_explicit, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_pairs(explicit, tmp, path):
    """Each distance's two images side by side and their difference in luminance, relative
    to the cloth's mean: where the bundle and the explicit fibers differ (``--samples``)."""


    e = [r for r in explicit if "failed" not in r]
    if not e:
        return
    fig, ax = plt.subplots(len(e), 3, figsize=(12, 4.2 * len(e)), squeeze=False)
    for a, r in zip(ax, e):
        ref, test = np.load(Path(tmp) / f"pair_{r['ply_px']}.npy")
        x = exposure_of(ref)
        lum_ref, lum_test = ref.mean(-1), test.mean(-1)
        cloth = lum_ref > 0.01 * lum_ref.max()
        a[0].imshow(to_srgb(ref, x))
        a[0].set_title(f"explicit fibers, {r['explicit']['spp']} spp", fontsize=9)
        a[1].imshow(to_srgb(test, x))
        a[1].set_title(f"bundle, {r['bundle']['spp']} spp; FLIP {r['flip']:.3f}", fontsize=9)
        im = a[2].imshow((lum_test - lum_ref) / lum_ref[cloth].mean(), cmap="coolwarm", vmin=-1, vmax=1)
        a[2].set_title(f"ply {r['ply_px']} px: (bundle - explicit) / the cloth's mean", fontsize=9)
        fig.colorbar(im, ax=a[2], fraction=0.046)
        for b in a:
            b.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", nargs="?", default="configs/glove.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--parts", nargs="+", choices=list(PARTS), default=list(PARTS),
                        help="what to measure (default: all); the others keep their figures in benchmarks/cloth.json")
    parser.add_argument("--ply-px", type=int, nargs="+", default=None,
                        help=f"the explicit part's camera distances, a ply's width in pixels (default {PLY_PX})")
    parser.add_argument("--samples", type=int, default=1,
                        help="the explicit part with this many times the samples on both sides (how FLIP falls "
                             "with the noise): its rows go to 'explicit_x<K>' in benchmarks/cloth.json, its pictures to "
                             "docs/images/cloth_explicit_x<K>.png; the others are kept")
    parser.add_argument("--near", type=int, default=0, metavar="N",
                        help="the explicit part with the config's ply baked with N near-field cells across its "
                             "width (bake.offsets=N, under the name <config>_near<N>; baked here where missing): "
                             "its rows go to 'explicit_near<N>' (with --samples K, 'explicit_near<N>_x<K>'), each "
                             "with the same table read as its far field")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.samples < 1:
        parser.error(f"--samples {args.samples}: give a whole number of at least 1 (times the standard samples)")
    if args.near and (args.near < 2 or args.parts != ["explicit"]):
        parser.error(f"--near {args.near}: give N >= 2 cells (e.g. 16), with --parts explicit (the near field "
                     "changes the plies' look, which the explicit part measures)")
    if args.child:
        kind, *rest = json.loads(args.child)
        children = {"scale": child_scale, "explicit": child_explicit, "memory": child_memory, "speed": child_speed,
                    "overlap": child_overlap}
        print(json.dumps(children[kind](*rest)))
        return 0
    if args.near:   # its own bake, made here where missing
        config = [str(args.config), *near_field(args.config, args.near, args.artifacts)]
    else:
        require(load_config(args.config), ("bake", "train", "export"), args.artifacts,
                f".venv/bin/bcsdf run {args.config} (make cloth)")
        config = [str(args.config)]
    earlier = results.load("cloth")
    result = earlier["data"] if earlier else {}
    result["config"] = str(args.config)
    with tempfile.TemporaryDirectory() as tmp:
        parts = {**PARTS, "explicit": functools.partial(measure_explicit, ply_px=args.ply_px, samples=args.samples)}
        fresh = {part: parts[part](config, args.artifacts, args.quick, tmp) for part in args.parts}
        # parts, and a part's distances, are measured by separate commands: each row names its own
        by = results.provenance()
        for part in fresh.values():
            for row in _rows(part):
                row["by"] = by
        (DOCS / "images").mkdir(parents=True, exist_ok=True)
        if (args.samples != 1 or args.near) and "explicit" in fresh:  # beside the standard rows, not instead
            key = "explicit" + (f"_near{args.near}" if args.near else "") + \
                (f"_x{args.samples}" if args.samples != 1 else "")
            rows = fresh.pop("explicit")
            plot_pairs(rows, tmp, DOCS / "images" / f"cloth_{key}.png")
            measured = {r["ply_px"] for r in rows}
            result[key] = sorted([r for r in result.get(key, []) if r["ply_px"] not in measured] + rows,
                                 key=lambda r: r["ply_px"])
        plot(fresh, tmp, DOCS / "images" / "cloth_scale.png", DOCS / "images" / "cloth_explicit.png")
    if args.ply_px and "explicit" in fresh:  # some distances measured: the others keep their rows
        fresh["explicit"] = sorted([r for r in result.get("explicit", []) if r["ply_px"] not in args.ply_px]
                                   + fresh["explicit"], key=lambda r: r["ply_px"])
    result.update(fresh)
    if args.quick:
        print("not recorded: --quick is a smoke run")
        return 0
    results.save("cloth", markdown(result), result)
    return 0


def near_field(config, cells: int, root) -> list[str]:
    """The overrides of the config's ply baked with ``cells`` near-field cells, its fiber
    and bake stages run where their artifacts are missing (the explicit part reads the
    table; the plies' neural model is not rendered)."""
    overrides = [f"name={Path(config).stem}_near{cells}", f"bake.offsets={cells}"]
    baked(load_config(config, overrides), root)
    return overrides


def markdown(result: dict) -> str:
    """The record's tables, one per part measured (the parts not run this time keep theirs)."""
    parts = []
    for key, title in (("scale", "Scale: curves of the glove, build, load and render"),
                       ("speed", "Speed: the integrator's options on the glove"),
                       ("explicit", "The bundle against explicit fibers, by a ply's width in pixels"),
                       ("explicit_x4", "The same with four times the samples"),
                       ("overlap", "Overlapping fibers"), ("memory", "Memory")):
        if key not in result:
            continue
        parts.append(f"**{title}** (`{key}`{_by(result, key)})\n\n{results.rows_table(_rows(result[key]))}")
    for key in sorted(k for k in result if k.startswith("explicit_near")):   # --near N [--samples K]
        cells, _, times = key.removeprefix("explicit_near").partition("_x")
        more = f", {times} times the samples" if times else ""
        parts.append(f"**The plies with a near-field table of {cells} cells across their width{more}; `far`: the "
                     f"same table read as its far field** (`{key}`{_by(result, key)})\n\n"
                     f"{results.rows_table(result[key])}")
    return "\n\n".join(parts)


def _rows(part) -> list:
    """A part's rows: a list of them, or one (``memory``)."""
    return part if isinstance(part, list) else [part]


def _by(result: dict, key: str) -> str:
    """Where a part's rows come from: each command, its date and machine."""
    by = list(dict.fromkeys((r["by"]["command"], r["by"]["date"], r["by"]["machine"])
                            for r in _rows(result[key]) if "by" in r))
    return "".join(f"; `{c}`, {d}, {m}" for c, d, m in by)


if __name__ == "__main__":
    sys.exit(main())
