"""``bcsdf cloth CONFIG``: a yarn-level model (a ``.bcc`` file or a procedural swatch)
rendered with the bundle BSDF.

Phases:

1. **Centre lines**: the model's curves (``cloth.model``, or ``cloth.swatch``), the first
   ``cloth.curves`` of them, turned by ``cloth.rotate_deg`` and scaled by ``cloth.units_mm``;
   each curve type converted to Mitsuba's uniform cubic B-spline within ``cloth.tolerance``
   yarn radii (measured, in the summary).
2. **Plies**: every yarn wound into the plies of a Zhao et al. 2016 yarn (``cloth.yarn``,
   scaled to ``cloth.yarn_radius_mm``), in a rotation-minimizing frame; yarns that come
   nearer each other than a yarn diameter are reported with the amount (a warning: knitted
   models are compressed where yarns touch). One ``bsplinecurve`` file holds every ply.
3. **Flyaways** (``cloth.flyaways``): hair-type flyaways of the Zhao yarn about every ply
   (``models.cloth.flyaways``), explicit fibers with the single-fiber model, scaled with the
   ply as its fibers are; their share of the rendered radiance is measured on smaller renders
   with, without and with no cloth at all (``share_check_scale``).
4. **Renders**: the plies carrying ``fiber_bundle`` with each backend of ``cloth.backends``
   (the bake's table; the ``render.model`` MLP), under Mitsuba's ``sunsky`` on a floor,
   ``bundle_path`` integrator; FLIP of every neural image against the table's.

The ply's table is the bake of this config's ``bundle``: the twisted-ply bake where it has
``bundle.twist`` (its fibers then should turn against the plies' winding, as in real yarn:
a warning otherwise), the parallel-fiber bake without; the summary says which.
Outputs in ``artifacts/<name>/cloth/``.
"""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi

from .. import scenes
from ..artifacts import model_size, stage_dir
from ..bsdfs import backend_props
from ..garment import build, flyaway_share, flyaways, render_apart, yarn_spec
from ..images import exposure_of, flip_and_psnr, save_images, save_png
from ..metrics import write_metrics
from ..summaries import ClothSummary


def run(cfg, out_root="artifacts") -> Path:
    if cfg.cloth is None:
        raise ValueError("cloth: this config has no `cloth:` section (see configs/glove.yaml)")
    if cfg.bundle is None:
        raise ValueError("cloth: the plies need a bundle table; add a `bundle:` section")
    c = cfg.cloth
    props = {b: backend_props(cfg, out_root, b) for b in c.backends}  # refuse mismatches before building
    out = stage_dir(cfg, "cloth", out_root)
    out.mkdir(parents=True, exist_ok=True)

    # -- phases 1 and 2: centre lines and plies
    info, geometry = build(cfg, out)

    # -- phase 3: flyaways
    fly_info, fly_shape = flyaways(cfg, out, geometry, yarn_spec(c), out_root)
    extra = {"flyaways": fly_shape} if fly_shape else {}

    # -- phase 4: renders, each in a process of its own (garment.render_apart)
    mi.set_variant(c.variant)
    summary = {"variant": c.variant, "size": [c.width, c.height], "spp": c.spp, "exit_split": c.exit_split,
               "geometry": info,
               "model": model_size(cfg) if set(c.backends) - {"table"} else None, "backends": {}}
    if fly_shape:
        plies = {"yarn": scenes.ply_shape(out / "plies.txt", props["table"] if "table" in props
                                          else props[c.backends[0]], geometry.radius)}
        fly_info["share"] = flyaway_share(cfg, {**plies, **extra}, info["bbox_mm"])
        summary["flyaways"] = fly_info
        print(f"[cloth] flyaways' share of the radiance (with them minus without, over with; negative where they "
              f"shade the plies more than they scatter): {fly_info['share']['cloth_pixels']:.1%} on the cloth's "
              f"pixels, {fly_info['share']['frame']:.1%} of the frame")
    images = {}
    for backend in c.backends:
        shapes = {"yarn": scenes.ply_shape(out / "plies.txt", props[backend], geometry.radius), **extra}
        img, seconds = render_apart(cfg, shapes, info["bbox_mm"])
        images[backend] = img
        summary["backends"][backend] = {"seconds": seconds, "mean_radiance": img.mean(axis=(0, 1)).tolist()}
        print(f"[cloth] {backend}: {c.width} x {c.height} x {c.spp} spp in {seconds:.1f} s (compilation included)")
    reference = "table" if "table" in images else c.backends[0]
    exposure = exposure_of(images[reference])
    summary["exposure"] = exposure
    for backend, img in images.items():
        save_images(mi, img, out / f"cloth_{backend}", exposure)
        if backend != reference:
            mean_flip, psnr, error_map = flip_and_psnr(images[reference], img, exposure)
            save_png(error_map, out / f"cloth_{backend}_flip.png")
            summary["backends"][backend].update(flip=mean_flip, psnr=psnr, reference=reference)
            print(f"[cloth] {backend} vs {reference}: FLIP {mean_flip:.4f}, PSNR {psnr:.1f} dB")
    ClothSummary(**summary).write(out / "summary.json")
    write_metrics(cfg, out_root, "cloth", {"build_seconds": info["build_seconds"],
                                            "control_points": info["control_points"],
                                            **{f"{b}_seconds": e["seconds"] for b, e in summary["backends"].items()},
                                            **{f"{b}_flip": e["flip"] for b, e in summary["backends"].items()
                                               if "flip" in e},
                                            **({"flyaway_share": fly_info["share"]["cloth_pixels"],
                                                "flyaway_hairs": fly_info["hairs"]} if fly_info else {})})
    return out

