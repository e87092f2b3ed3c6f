"""A yarn-level model made into renderable cloth: centre lines (a ``.bcc`` file or a
procedural swatch), the plies wound about them, hair-type flyaways, and renders of them
each in a process of its own. ``bcsdf cloth`` runs these phases; the cloth bench varies
them."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import mitsuba as mi
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

import mitsuba_ext
from models.bundle import zhao2016_row
from models.bundle_table import BundleTable
from models.cloth.bcc import CurveCollection, read_bcc
from models.cloth.curves import write_mitsuba_curves
from models.cloth.flyaways import HairSpec, hair_flyaways
from models.cloth.knit import stockinette
from models.cloth.yarn import YarnSpec, build_plies, write_curves
from models.io import atomic_path

from . import closure, scenes
from .artifacts import bundle_table_path, fiber_table_path
from .config import Config
from .machine import check_memory
from .images import render_timed
from .plots import LUMINANCE


def yarn_model(c):
    """The centre lines of ``c`` (the config's cloth section), turned, in the model's units."""
    if c.model is not None:
        collection = read_bcc(c.model)
    else:
        # the swatch is drawn in yarn radii: in millimetres, one unit is the yarn radius
        collection = stockinette(c.swatch.courses, c.swatch.wales, r=c.yarn_radius_mm / c.units_mm)
    curves = collection.curves[: c.curves] if c.curves else collection.curves
    turn = Rotation.from_euler("xyz", c.rotate_deg, degrees=True).as_matrix()
    for curve in curves:
        curve.points = curve.points @ turn.T
    return CurveCollection(curves, collection.kind, collection.up)


def yarn_spec(c):
    spec = YarnSpec.from_zhao(zhao2016_row(c.yarn), c.yarn_radius_mm, K=c.plies)
    if c.ply_pitch_mm is not None:
        spec.pitch = float(c.ply_pitch_mm)
    if spec.overlap() > 0:
        raise ValueError(f"cloth: {spec.K} plies of radius {spec.r_ply:.3g} mm at {spec.R:.3g} mm from the yarn's "
                         f"centre overlap by {spec.overlap():.3g} mm; use fewer cloth.plies")
    return spec


# bytes a ply control point costs once Mitsuba holds it (curve, BVH, file parsing), with a
# margin: the glove's 1.38 M points took ~270 MB above a bare scene (docs/BENCHMARKS.md, "Cloth")
BYTES_PER_POINT = 800
# the build's peak per control point of the model's own curves (8 samples a segment, their
# frames, the B-spline fit): 2.7-4.2 kB measured on one curve of 1e5-4e5 points, 1 and 3 plies
BYTES_PER_MODEL_POINT = 4500
# placing one flyaway (its draws, samples, the piercing test): ~720 B measured on the glove;
# each of its control points in Mitsuba: 103 B (linearcurve), 136 B (bsplinecurve) measured
# on 2e5 six-point hairs, with a margin
BYTES_PER_HAIR = 800
BYTES_PER_HAIR_POINT = 200
POINTS_PER_HAIR = {"linearcurve": 6, "bsplinecurve": 12}   # models.cloth.flyaways.hair_flyaways


def estimated_points(length: float, yarn) -> int:
    """Ply control points the model will make from ``length`` mm of centre lines (before building)."""
    return int(yarn.K * max(length / abs(yarn.pitch) * 16, length / (0.25 * yarn.radius)))


def centre_length(collection, c) -> float:
    """The centre lines' length in millimetres."""
    return c.units_mm * sum(float(np.linalg.norm(np.diff(cv.points, axis=0), axis=1).sum()) for cv in collection.curves)


def estimated_hairs(c, yarn, length: float) -> int:
    """Flyaways the model will grow: Zhao's density per millimetre of ply times the plies'
    length (``K`` helices about ``length`` of centre line; the hairs that would pierce a
    neighbour, left out later, are counted)."""
    if c.flyaways is None:
        return 0
    spec = HairSpec.from_zhao(zhao2016_row(c.flyaways.yarn or c.yarn), yarn.r_ply, c.flyaways.density_scale)
    helix = np.hypot(1.0, 2 * np.pi * yarn.R / abs(yarn.pitch))
    return int(spec.density * yarn.K * length * helix)


def check_fits(collection, c, yarn) -> None:
    """Refuse, before building, a model whose plies and flyaways would not fit in memory."""
    length = centre_length(collection, c)
    points = estimated_points(length, yarn)
    model_points = sum(len(cv.points) for cv in collection.curves)
    hairs = estimated_hairs(c, yarn, length)
    per_hair = BYTES_PER_HAIR + POINTS_PER_HAIR[c.flyaways.curve] * BYTES_PER_HAIR_POINT if hairs else 0
    check_memory(points * BYTES_PER_POINT + model_points * BYTES_PER_MODEL_POINT + hairs * per_hair,
                 f"cloth: the model's {model_points:,} control points would make about {points:,} ply control points"
                 + (f" and {hairs:,} flyaways" if hairs else ""),
                 "render fewer curves (cloth.curves), a larger cloth.ply_pitch_mm, "
                 + ("a smaller cloth.flyaways.density_scale, " if hairs else "") + "or a smaller model")


def ply_table(cfg, yarn) -> str:
    """Which table the plies carry, in words; warns where a twisted ply's fibers turn the
    same way as the plies are wound (real yarn twists them against each other)."""
    twist = cfg.bundle.twist
    if twist is None:
        return "parallel fibers (bundle.twist not set)"
    pitch = twist.pitch(cfg.bundle.bounding_radius_um())
    if np.sign(pitch) == np.sign(yarn.pitch):
        warnings.warn(f"cloth: the fibers' twist (pitch {pitch:+.0f} um) turns the same way as the plies' winding "
                      f"(pitch {yarn.pitch:+.3g} mm); real yarn twists them against each other: flip the sign of "
                      "bundle.twist.pitch_um", stacklevel=2)
    return f"twisted ply (fiber pitch {pitch:+.0f} um at a {cfg.bundle.bounding_radius_um():.0f} um ply)"


def build(cfg, out: Path, samples_per_segment: int = 2) -> tuple[dict, object]:
    """Phases 1 and 2: write ``plies.txt``; return the geometry's summary and the plies.
    ``samples_per_segment``: the plies' fewest samples per segment of the model's curves
    (:func:`~models.cloth.yarn.build_plies`; the speed bench compares 8)."""
    c = cfg.cloth
    t0 = time.perf_counter()
    collection = yarn_model(c)
    yarn = yarn_spec(c)
    check_fits(collection, c, yarn)
    with tqdm(total=len(collection.curves), desc="plies", unit="yarn") as bar:
        geometry = build_plies(collection, c.units_mm, yarn, c.tolerance, samples_per_segment=samples_per_segment,
                               progress=lambda k: bar.update(1))
    write_curves(out / "plies.txt", geometry)
    warning = geometry.overlap_warning(yarn)
    if warning:
        warnings.warn(f"cloth: {warning}", stacklevel=2)
    pts = np.concatenate(geometry.curves)
    info = {"yarn_curves": len(collection.curves), "curve_type": collection.kind,
            "closed": sum(cv.closed for cv in collection.curves), "ply_curves": len(geometry.curves),
            "control_points": geometry.control_points, "plies": yarn.K, "ply_radius_mm": yarn.r_ply,
            "ply_offset_mm": yarn.R, "ply_pitch_mm": float(np.mean(np.abs(geometry.pitch_used or [yarn.pitch]))),
            "yarn_radius_mm": yarn.radius,
            "centre_deviation_yarn_radii": geometry.centre_deviation / yarn.radius,
            "closest_yarns_mm": geometry.closest_yarns, "overlapping_length": geometry.overlapping,
            "overlap_warning": warning, "bbox_mm": [pts.min(0).tolist(), pts.max(0).tolist()],
            "build_seconds": time.perf_counter() - t0, "ply_table": ply_table(cfg, yarn)}
    print(f"[cloth] {info['yarn_curves']} yarns -> {info['ply_curves']} plies, {info['control_points']:,} control "
          f"points, centre lines within {100 * info['centre_deviation_yarn_radii']:.2f}% of a yarn radius, "
          f"built in {info['build_seconds']:.1f} s")
    return info, geometry


def flyaways(cfg, out: Path, geometry, yarn, out_root) -> tuple[dict, dict | None]:
    """Phase 3: ``flyaways.txt`` and its shape (``None`` without ``cloth.flyaways``), and its summary."""
    f = cfg.cloth.flyaways
    if f is None:
        return {}, None
    t0 = time.perf_counter()
    spec = HairSpec.from_zhao(zhao2016_row(f.yarn or cfg.cloth.yarn), yarn.r_ply, f.density_scale)
    # the fibers' radius scaled with the ply, as the plies' own fibers (models.cloth.fibers)
    radius = cfg.fiber.radius_um * yarn.r_ply / cfg.bundle.bounding_radius_um()
    hairs = hair_flyaways(geometry.curves, yarn.r_ply, spec, seed=f.seed, hair_radius=radius, curve=f.curve)
    with atomic_path(out / "flyaways.txt") as tmp, open(tmp, "w") as fh:
        write_mitsuba_curves(fh, hairs)
    # the hairs leave their fibers as the bake's fibers do (closure.explicit_fiber)
    exit_model = BundleTable.load(bundle_table_path(cfg, out_root)).meta.get("exit", "uniform")
    fiber = closure.explicit_fiber(fiber_table_path(cfg, out_root), exit_model, 550.0)
    for key in ("wavelength", "up"):  # spectral renders use every wavelength; curves have their own frame
        fiber.pop(key)
    shape = {"type": f.curve, "filename": str(out / "flyaways.txt"), "bsdf": fiber}
    info = {"hairs": len(hairs), "control_points": int(sum(len(h) for h in hairs)), "fiber_radius_mm": radius,
            "hairs_per_mm": spec.density, "yarn": f.yarn or cfg.cloth.yarn, "density_scale": f.density_scale,
            "plugin": fiber["type"], "seconds": time.perf_counter() - t0}
    print(f"[cloth] flyaways: {len(hairs):,} hairs ({spec.density:.3g} per mm of ply), {info['control_points']:,} "
          f"control points, in {info['seconds']:.1f} s")
    return info, shape


def flyaway_share(cfg, shapes: dict, bbox) -> dict:
    """The flyaways' share of the rendered radiance, from three renders at ``share_check_scale``
    of the image (table backend, the same samples): the cloth with flyaways, without them, and
    no cloth at all. Over the whole frame, and over the cloth's pixels (where the render with
    flyaways differs from the empty scene by more than 2%: plies, hairs and their shadows)."""
    c = cfg.cloth
    k = c.flyaways.share_check_scale
    size = (max(8, round(c.width * k)), max(8, round(c.height * k)))
    with_, _ = render_apart(cfg, shapes, bbox, size)
    without, _ = render_apart(cfg, {"yarn": shapes["yarn"]}, bbox, size)
    empty, _ = render_apart(cfg, {}, bbox, size)

    Y = LUMINANCE if with_.shape[-1] == 3 else np.ones(1)
    w, wo, e = with_ @ Y, without @ Y, empty @ Y
    cloth = np.abs(w - e) > 0.02 * np.maximum(e, 1e-6)
    return {"size": list(size), "frame": float((w.sum() - wo.sum()) / max(w.sum(), 1e-30)),
            "cloth_pixels": float((w[cloth].sum() - wo[cloth].sum()) / max(w[cloth].sum(), 1e-30)),
            "cloth_pixel_fraction": float(cloth.mean())}


def render_apart(cfg, shapes: dict, bbox, size=None) -> tuple[np.ndarray, float]:
    """One render of ``shapes`` (Mitsuba dicts; the plies carry one backend's ``fiber_bundle``)
    in a process of its own, at ``size`` (default the config's): ``(image, seconds)``.

    Why a process: in Mitsuba 3.9 / Dr.Jit 1.5 (LLVM), a second scene of the glove's plies
    rendered with another kernel in the same process (the MLP after the table) segfaults
    reading past an array, every time at 160 x 120 (not a NaN: the process dies); each
    alone renders cleanly. A child that dies is reported, not a lost session.
    """
    with tempfile.TemporaryDirectory() as tmp:
        job = {"config": cfg.model_dump(mode="json"), "shapes": shapes, "bbox": bbox, "size": size,
               "out": str(Path(tmp) / "image.npy")}
        (Path(tmp) / "job.json").write_text(json.dumps(job))
        r = subprocess.run([sys.executable, "-m", "pipeline.garment", str(Path(tmp) / "job.json")],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if r.returncode != 0:
            backend = shapes.get("yarn", {}).get("bsdf", {}).get("backend", "empty scene")
            raise RuntimeError(f"cloth: the {backend} render failed (exit status {r.returncode}):\n"
                               f"{r.stderr[-2000:]}")
        return np.load(job["out"]), float(json.loads(r.stdout.strip().splitlines()[-1])["seconds"])


def _render_job(path) -> None:
    """The child of :func:`render_apart`."""
    job = json.loads(Path(path).read_text())
    cfg = Config.model_validate(job["config"])
    c = cfg.cloth
    if job["size"]:
        c = c.model_copy(update={"width": job["size"][0], "height": job["size"][1]})
    mi.set_variant(c.variant)
    mitsuba_ext.register()
    scene = scenes.cloth_scene(mi, c, job["shapes"], job["bbox"], c.spp)
    backend = job["shapes"].get("yarn", {}).get("bsdf", {}).get("backend", "table")
    img, seconds, _ = render_timed(mi, scene, backend, warm=False)
    np.save(job["out"], img)
    print(json.dumps({"seconds": seconds}))


if __name__ == "__main__":
    _render_job(sys.argv[1])
