"""Pictures shared by the stages: spectral images in sRGB and figure saving."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.spectrum import spectrum_to_srgb


def tone_map(rgb: np.ndarray) -> np.ndarray:
    """Log tone mapping on luminance, hue kept; sRGB-encoded in [0, 1]."""
    import colour

    rgb = np.maximum(rgb, 0.0)
    Y = rgb @ np.array([0.2126, 0.7152, 0.0722])
    positive = Y[Y > 0]
    if positive.size == 0:
        return np.zeros_like(rgb)
    # Exposure at the bright band (not the lobe tails), log above it for the peak
    Y0 = max(np.percentile(positive, 97), 1e-12 * positive.max())
    mapped = np.log1p(Y / Y0) / np.log1p(positive.max() / Y0)
    out = rgb * np.where(Y > 0, mapped / np.maximum(Y, 1e-300), 0.0)[..., None]
    return np.clip(colour.cctf_encoding(np.clip(out, 0, 1)), 0, 1)


def spectral_image(f: np.ndarray, wavelength, path: Path, title: str,
                   xlabel="dphi = phi_o - phi_i [deg]  (0: back to the light, 180: forward)",
                   extent=(0, 360, -90, 90)) -> None:
    """``f[theta_o, phi_o, lambda]`` as an sRGB image (log tone map), theta_o upwards."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = tone_map(spectrum_to_srgb(f, wavelength))
    fig, ax = plt.subplots(figsize=(12, 4.2), dpi=120)
    ax.imshow(img, origin="lower", aspect="auto", interpolation="nearest", extent=extent)
    ax.set_xticks(np.arange(extent[0], extent[1] + 1, 30))
    ax.set(xlabel=xlabel, ylabel="theta_o [deg]", title=title)
    fig.tight_layout()
    save_figure(fig, path)


def save_figure(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    from models.io import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
