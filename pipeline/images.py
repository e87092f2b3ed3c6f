"""Rendered images: a timed render, exposure and the sRGB transfer curve, EXR and PNG
files, and FLIP and PSNR of one image against another. Shared by the render and cloth
stages, ``render-scene`` and the benches."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import drjit as dr
import flip_evaluator as flip
import matplotlib.pyplot as plt
import numpy as np

import mitsuba_ext
from models.io import atomic_path

from .machine import check_memory


def check_film(film, where: str) -> None:
    """Refuse, before rendering, a film that Dr.Jit cannot hold or that would not fit in
    memory. Its image block holds ``channels + 2`` float32 a pixel (alpha and the filter's
    weight beside the colour); Dr.Jit's arrays hold fewer than 2^32 entries. In memory, a pixel
    costs that block, the developed image and numpy's copy (float32 each) and the PNG's
    float64 sRGB: ``4 (c + 2) + 2 * 4 c + 8 * 4`` bytes."""
    width, height = (int(v) for v in film.crop_size())
    c = int(film.base_channels_count())
    pixels = width * height
    fix = "render a smaller film, or a crop of it (the film's crop_width, crop_height)"
    if pixels * (c + 2) >= 2**32:
        raise ValueError(f"{where}: a film of {width} x {height} pixels takes {pixels * (c + 2):,} values in Dr.Jit's "
                         f"image block, at most {2**32 - 1:,}: {fix}")
    check_memory(pixels * (4 * (c + 2) + 8 * c + 32), f"{where}: a film of {width} x {height} pixels with its copies",
                 fix)


def render_timed(mi, scene, backend: str = "table", warm: bool = True,
                 seed: int = 0) -> tuple[np.ndarray, float, float]:
    """``(image, seconds, first_seconds)`` of a scene dict or a loaded scene: the second of
    two renders (seeds ``seed`` and ``seed + 1``) is timed (warm kernels); ``warm=False``:
    one render, timed with its compilation if its kernel is new."""
    # onnxruntime computes outside Dr.Jit's traced kernels: the onnx backend renders in evaluated mode
    with mitsuba_ext.evaluated_mode() if backend == "onnx" else contextlib.nullcontext():
        scene = mi.load_dict(scene) if isinstance(scene, dict) else scene
        t0 = time.perf_counter()
        img = mi.render(scene, seed=seed)
        dr.eval(img)
        dr.sync_thread()
        first = seconds = time.perf_counter() - t0
        if warm:
            t0 = time.perf_counter()
            img = mi.render(scene, seed=seed + 1)
            dr.eval(img)
            dr.sync_thread()
            seconds = time.perf_counter() - t0
    image = np.array(img, dtype=np.float32)[..., :3]
    if not np.all(np.isfinite(image)):
        raise FloatingPointError(f"render ({backend}) produced {np.sum(~np.isfinite(image))} non-finite values")
    return image, seconds, first


def exposure_of(img: np.ndarray) -> float:
    """A scale that puts the 99.5th percentile of luminance at 0.85 (one per scene)."""
    Y = img @ np.array([0.2126, 0.7152, 0.0722])
    top = float(np.percentile(Y, 99.5))
    return 0.85 / top if top > 0 else 1.0


def to_srgb(img: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear sRGB -> display sRGB in [0, 1] (the transfer curve, clipped)."""
    x = np.clip(img * exposure, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def save_images(mi, img: np.ndarray, stem: Path, exposure: float) -> None:
    with atomic_path(stem.with_suffix(".exr")) as tmp:
        mi.Bitmap(img).write(str(tmp), mi.Bitmap.FileFormat.OpenEXR)
    save_png(to_srgb(img, exposure), stem.with_suffix(".png"))


def save_png(srgb: np.ndarray, path: Path) -> None:
    with atomic_path(path) as tmp:
        plt.imsave(tmp, np.clip(srgb, 0, 1), format="png")


def flip_and_psnr(reference: np.ndarray, test: np.ndarray, exposure: float) -> tuple[float, float, np.ndarray]:
    """Mean LDR-FLIP, PSNR (dB), both on the displayed sRGB images, and the FLIP map (magma)."""
    ref, tst = to_srgb(reference, exposure), to_srgb(test, exposure)
    error_map, mean_flip, _ = flip.evaluate(ref, tst, "LDR")
    mse = float(np.mean((ref - tst) ** 2))
    psnr = float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)
    return float(mean_flip), psnr, np.asarray(error_map, np.float32)
