"""``bcsdf render-scene SCENE.xml -o OUT.exr``: any Mitsuba XML scene, with this project's
plugins registered (``fiber_bundle``, ``fiber_table``, ``fiber_ray``, ``bundle_path``).

Mitsuba's own ``mitsuba scene.xml`` cannot load them (they are Python plugins: it says
``Plugin "bundle_path" not found``); this is the same habit with them available. ``-D
NAME=VALUE`` sets the scene's ``$NAME`` parameters, as Mitsuba's ``-D`` does; ``--spp``
overrides the sensor's sample count. Writes ``OUT`` (EXR, linear) and a PNG beside it
(sRGB, exposed so that the 99.5th percentile of luminance is at 0.85), and refuses an
image with NaN or Inf.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import mitsuba_ext
from mitsuba_ext.crossing import check_integrator
from models.io import atomic_path
from pipeline.images import check_film, exposure_of, save_png, to_srgb


def output_paths(out) -> tuple[Path, Path]:
    """The EXR and PNG that ``-o OUT`` names, checked before any rendering: not a folder, and
    in a folder this process can write into (made if missing)."""
    out = Path(out)
    exr, png = out.with_suffix(".exr"), out.with_suffix(".png")
    for p in (out, exr, png):
        if p.is_dir():
            raise ValueError(f"-o {out}: {p} is a folder; give the image's file name, e.g. -o {out / 'scene.exr'}")
    try:
        exr.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=exr.parent):
            pass
    except OSError as e:
        raise ValueError(f"-o {out}: cannot write into {exr.parent} ({e.strerror}); choose another folder") from None
    return exr, png


def render_scene(scene_path, out, spp=None, variant="llvm_ad_spectral", defines=()) -> dict:
    scene_path = Path(scene_path)
    if not scene_path.is_file():
        raise FileNotFoundError(f"{scene_path}: no such scene file")
    exr, png = output_paths(out)
    params = {}
    for item in defines:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"-D {item!r}: write NAME=VALUE, e.g. -D spp=16")
        params[name] = value
    if variant not in mi.variants():
        raise ValueError(f"variant {variant!r} is not available here; choose one of {', '.join(mi.variants())}")
    mi.set_variant(variant)
    mitsuba_ext.register()
    try:
        scene = mi.load_file(str(scene_path), **params)
    except Exception as e:  # Mitsuba's loader raises RuntimeError/ValueError with the XML's line
        text = str(e)
        if "Traceback" in text:  # a plugin's own error inside Mitsuba's message: where, then what
            where, _, rest = text.partition("Traceback")
            text = where.strip().rstrip(":") + ": " + rest.strip().splitlines()[-1]
        raise ValueError(f"{scene_path}: {text}") from None

    problem = check_integrator(scene)
    if problem:
        raise ValueError(f"{scene_path}: {problem}")
    for sensor in scene.sensors():
        check_film(sensor.film(), str(scene_path))
    t0 = time.perf_counter()
    with mitsuba_ext.evaluated_mode() if mitsuba_ext.needs_evaluated_mode(scene) else contextlib.nullcontext():
        img = mi.render(scene, spp=int(spp) if spp else 0)
        dr.eval(img)
        dr.sync_thread()
    seconds = time.perf_counter() - t0
    image = np.array(img, dtype=np.float32)
    if not np.all(np.isfinite(image)):
        raise FloatingPointError(f"{scene_path}: the render holds {np.sum(~np.isfinite(image))} NaN or Inf values")
    with atomic_path(exr) as tmp:
        mi.Bitmap(image).write(str(tmp), mi.Bitmap.FileFormat.OpenEXR)
    rgb = image[..., :3] if image.ndim == 3 and image.shape[-1] >= 3 else np.repeat(image.reshape(
        image.shape[:2] + (-1,))[..., :1], 3, -1)
    save_png(to_srgb(rgb, exposure_of(rgb)), png)
    print(f"[render-scene] {scene_path} -> {exr} and .png, {image.shape[1]} x {image.shape[0]}, "
          f"{seconds:.1f} s ({variant})")
    return {"seconds": seconds, "shape": list(image.shape)}
