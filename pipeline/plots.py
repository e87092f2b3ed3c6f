"""Pictures shared by the stages: spectral images in sRGB, the models' Pareto plot, figure saving."""

from __future__ import annotations

from pathlib import Path

import colour
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import FuncNorm

from models.grid import Cells
from models.io import atomic_path
from models.spectrum import spectrum_to_srgb

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # linear sRGB -> Y


def slice_nodes(theta_i, every_deg: float = 15.0) -> list[int]:
    """The ``theta_i`` nodes (radians) whose slices a stage draws: the node nearest every
    multiple of ``every_deg`` over -90..90 deg that lies within the nodes' range, each once
    (a slice per node took most of the fiber stage: 19 figures for 5-deg nodes)."""
    theta_i = np.asarray(theta_i, np.float64)
    marks = np.deg2rad(np.arange(-90.0, 90.0 + 1e-9, every_deg))
    marks = marks[(marks >= theta_i.min() - 1e-9) & (marks <= theta_i.max() + 1e-9)]
    return sorted({int(np.argmin(np.abs(theta_i - m))) for m in marks} or {0})


def log_scale(Y: np.ndarray) -> tuple[float, float]:
    """``(Y0, Y_max)`` of the log tone map: its knee at the bright band (the 97th
    percentile of the positive values, so the lobe tails do not set the exposure) and
    its top (the peak)."""
    positive = Y[Y > 0]
    if positive.size == 0:
        return 1.0, 1.0
    Y_max = float(positive.max())
    return max(float(np.percentile(positive, 97)), 1e-12 * Y_max), Y_max


def log_map(Y, scale: tuple[float, float]):
    """Luminance -> display value in [0, 1]: ``log(1 + Y / Y0) / log(1 + Y_max / Y0)``."""
    Y0, Y_max = scale
    return np.log1p(np.maximum(Y, 0.0) / Y0) / np.log1p(Y_max / Y0)


def tone_map(rgb: np.ndarray, scale: tuple[float, float] | None = None) -> np.ndarray:
    """Log tone mapping on luminance, hue kept; sRGB-encoded in [0, 1]. ``scale`` (from
    :func:`log_scale`) shares one mapping between images that are compared."""

    rgb = np.maximum(rgb, 0.0)
    Y = rgb @ LUMINANCE
    scale = scale or log_scale(Y)
    mapped = log_map(Y, scale)
    out = rgb * np.where(Y > 0, mapped / np.maximum(Y, 1e-300), 0.0)[..., None]
    return np.clip(colour.cctf_encoding(np.clip(out, 0, 1)), 0, 1)


def theta_rows(f: np.ndarray, theta_edges) -> np.ndarray:
    """``f[theta_o, ...]`` over bins with ``theta_edges`` as rows of equal height (an image's
    rows are equal): each bin repeated over the rows it covers (rows half its narrowest bin
    high), so a cone layout's narrow bins keep their width on the page. Equal bins: ``f``."""

    cells = Cells(theta_edges)
    if cells.uniform:
        return f
    n_rows = int(np.ceil(cells.span / (cells.min_width / 2)))
    centres = cells.lo + (np.arange(n_rows) + 0.5) * cells.span / n_rows
    return np.asarray(f)[cells.index(centres)]


def spectral_image(f: np.ndarray, wavelength, path: Path, title: str,
                   xlabel="dphi = phi_o - phi_i [deg]  (0: back to the light, 180: forward)",
                   extent=(0, 360, -90, 90), unit="1/sr", scale=None) -> tuple[float, float]:
    """``f[theta_o, phi_o, lambda]`` as an sRGB image (log tone map), theta_o upwards,
    with a colour bar of its luminance in ``unit`` (a flat spectrum of value v has
    luminance v). Returns the tone map's scale, so a compared image can share it."""

    rgb = spectrum_to_srgb(f, wavelength)
    scale = scale or log_scale(np.maximum(rgb, 0.0) @ LUMINANCE)
    # Margins in inches, set rather than measured: every slice has the same labels, and
    # tight_layout's measuring of their text was a third of this function's time
    fig = plt.figure(figsize=(12, 4.2), dpi=120)
    ax = axes_in(fig, left=0.72, bottom=0.56, right=1.12, top=0.36)
    cax = axes_in(fig, left=fig.get_figwidth() - 1.07, bottom=0.56, right=0.93, top=0.36)  # 0.14 in wide
    ax.imshow(tone_map(rgb, scale), origin="lower", aspect="auto", interpolation="nearest", extent=extent)
    ax.set_xticks(np.arange(extent[0], extent[1] + 1, 30))
    ax.set(xlabel=xlabel, ylabel="theta_o [deg]", title=title)
    # The colour bar shows the tone map itself (with the sRGB encoding): the grey a pixel
    # of that luminance has
    Y0, Y_max = scale

    def forward(y):
        return colour.cctf_encoding(np.clip(log_map(y, scale), 0, 1))

    def inverse(v):
        return Y0 * np.expm1(colour.cctf_decoding(np.clip(v, 0, 1)) * np.log1p(Y_max / Y0))
    norm = FuncNorm((forward, inverse), vmin=0.0, vmax=Y_max)
    bar = fig.colorbar(ScalarMappable(norm, plt.get_cmap("gray")), cax=cax)
    ticks = [0.0]  # 0, the knee and its decades, the peak: those that are 6% of the bar apart
    for t in [Y0 * 10.0 ** k for k in range(-1, 8)]:
        if forward(ticks[-1]) + 0.06 < forward(t) < 0.94:
            ticks.append(t)
    ticks.append(Y_max)
    bar.set_ticks(ticks, labels=[f"{t:.3g}" for t in ticks])
    bar.set_label(f"luminance [{unit}]")
    save_figure(fig, path)
    return scale


def axes_in(fig, left: float, bottom: float, right: float, top: float):
    """Axes with margins of ``left``, ``bottom``, ``right`` and ``top`` inches from the
    figure's edges."""
    W, H = fig.get_size_inches()
    return fig.add_axes((left / W, bottom / H, (W - left - right) / W, (H - bottom - top) / H))


def save_figure(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def pareto(models: list[dict], path: Path, ylabel: str, title: str, line: tuple[float, str] | None = None) -> None:
    """Each model's ``error`` against its float32 parameter ``bytes`` and its training
    seconds ``train_s``, one marker per ``label``; ``line``: ``(value, text)`` drawn across
    both panels (the table's noise, or the training table's own error against the truth)."""
    legend_in = 0.2 + 0.22 * ((len(models) + 1) // 2)   # the legend below the panels: two columns
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6 + legend_in), dpi=110, sharey=True)
    for k, m in enumerate(models):   # a colour and a marker each: no two models look alike
        for ax, x in zip(axes, ("bytes", "train_s")):
            ax.scatter(m[x], m["error"], s=60, color=plt.get_cmap("tab10")(k % 10), marker="os^Dv"[k // 10 % 5],
                       label=m["label"] if ax is axes[0] else None)
    for ax, xlabel in zip(axes, ("float32 bytes of the model (weights and gain tables)", "training seconds")):
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3, which="both")
        if line is not None:
            ax.axhline(line[0], color="0.4", ls="--", lw=1)
            ax.text(ax.get_xlim()[0], line[0], " " + line[1], fontsize=8, color="0.3", va="bottom")
    top = max([m["error"] for m in models] + ([line[0]] if line is not None else []) + [1e-12])
    axes[0].set_ylim(0, 1.15 * top)
    axes[0].set_ylabel(ylabel)
    fig.legend(fontsize=8, loc="lower center", ncol=2, frameon=False)   # below the panels: it hides no model
    fig.suptitle(title)
    fig.tight_layout(rect=(0, legend_in / (4.6 + legend_in), 1, 1))
    save_figure(fig, path)
