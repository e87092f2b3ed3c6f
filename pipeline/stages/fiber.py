"""Stage ``fiber``: tabulate the single-fiber model of a config and draw it.

Writes, under ``artifacts/<name>/fiber/``:

* ``fiber_table.npz``  the :class:`models.fiber.FiberTable` the baker looks up;
* ``summary.json``     energy (albedo) and extinction per (theta_i, lambda), timing;
* ``theta_i_XX.png``   f over (dphi, theta_o) at the tabulated theta_i nearest every
  15 deg, all wavelengths combined into sRGB (CIE 1931, D65), log tone-mapped so
  that the diffraction peak and the faint chromatic fringes show together;
* ``energy.png``       albedo (and extinction ratio) against theta_i per wavelength.
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize

from models import fiber as fiber_models
from models.fiber.base import FiberTable
from models.grid import linear

from ..artifacts import stage_dir
from ..config import FIBER_SECTIONS
from ..metrics import write_metrics
from ..plots import save_figure, slice_nodes, spectral_image
from ..summaries import FiberSummary


def run(cfg, out_root="artifacts") -> Path:
    out = stage_dir(cfg, "fiber", out_root)
    wl = cfg.wavelengths.grid()
    theta_i = cfg.tabulate.theta_i()

    # -- Tabulate ---------------------------------------------------------
    t0 = time.perf_counter()
    model = fiber_models.build(cfg.fiber, wl)
    table = model.tabulate(theta_i)
    seconds = time.perf_counter() - t0
    table.meta.update(config_name=cfg.name, config_hash=cfg.hash(*FIBER_SECTIONS),
                      config=cfg.model_dump(mode="json"))
    table.validate()
    table.save(out / "fiber_table.npz")

    # -- Energy and extinction --------------------------------------------
    energy = table.energy()
    ext = model.extinction(table.theta_i)
    summary = FiberSummary(
        model=cfg.fiber.model, config_hash=cfg.hash(*FIBER_SECTIONS), tabulate_seconds=seconds,
        theta_i_deg=np.rad2deg(table.theta_i).tolist(), wavelength_nm=table.wavelength.tolist(),
        shape={lobe.name: list(lobe.azimuthal.shape) for lobe in table.lobes},
        energy=energy.tolist(), extinction_ratio=None if ext is None else ext.tolist(),
    )
    summary.write(out / "summary.json")
    write_metrics(cfg, out_root, "fiber", {"albedo_min": energy.min(), "albedo_max": energy.max(),
                                           "tabulate_seconds": seconds})

    # -- Pictures -----------------------------------------------------------
    for i in slice_nodes(table.theta_i):
        plot_slice(table, i, out / f"theta_i_{np.rad2deg(table.theta_i[i]):04.1f}.png")
    plot_energy(table.theta_i, table.wavelength, energy, ext, out / "energy.png", cfg.fiber.model)
    print(f"[fiber] {cfg.fiber.model}: {len(table.theta_i)} theta_i x {len(table.phi)} phi x "
          f"{len(table.wavelength)} wavelengths in {seconds:.2f} s; albedo "
          f"{energy.min():.4f}..{energy.max():.4f}; wrote {out}")
    return out


def slice_at_node(table: FiberTable, i: int, theta_o: np.ndarray, group: int = 1) -> np.ndarray:
    """``f[theta_o, phi, lambda]`` at the table's i-th theta_i, on its own phi grid, or
    averaged over ``group`` adjacent azimuths (before the product with the longitudinal
    lobe, which does not depend on the azimuth: the same numbers, fewer of them)."""
    ti = table.theta_i[i]
    n_cols = len(table.phi) // group

    def grouped(N):  # [..., phi, lambda] -> [..., phi / group, lambda]
        N = N[..., : n_cols * group, :]
        return N.reshape(N.shape[:-2] + (n_cols, group, N.shape[-1])).mean(axis=-2)

    f = np.zeros((len(theta_o), n_cols, len(table.wavelength)))
    for lobe in table.lobes:
        M = lobe.longitudinal(ti, theta_o)[:, None, None]
        if lobe.dense:
            a, b, w = linear(table.theta_o, theta_o)
            Ni = grouped(lobe.azimuthal[i])
            N = (1 - w)[:, None, None] * Ni[a] + w[:, None, None] * Ni[b]
        else:
            N = grouped(lobe.azimuthal[i, 0])[None]
        f += M * N
    return f


def plot_slice(table: FiberTable, i: int, path: Path, max_columns: int = 1440) -> None:
    theta_o = np.linspace(-np.pi / 2, np.pi / 2, 361)
    # adjacent azimuth samples averaged down to at most max_columns (keeps the energy)
    f = slice_at_node(table, i, theta_o, group=int(np.ceil(len(table.phi) / max_columns)))
    n_cols = f.shape[1]
    # Roll so that dphi runs over [0, 360): forward scattering (180) in the middle
    f = np.roll(f, n_cols // 2, axis=1)
    spectral_image(f, table.wavelength, path,
                   f"{table.meta.get('model', 'fiber')}: theta_i = {np.rad2deg(table.theta_i[i]):.1f} deg, "
                   f"{len(table.wavelength)} wavelengths in sRGB (log tone map)")


def plot_energy(theta_i, wavelength, energy, ext, path, model_name) -> None:

    n = 2 if ext is not None else 1
    fig, axes = plt.subplots(1, n, figsize=(5.8 * n, 4), dpi=110, squeeze=False, layout="constrained")
    cmap, norm = plt.get_cmap("turbo"), Normalize(float(np.min(wavelength)), float(np.max(wavelength)) + 1e-9)
    for j, lam in enumerate(wavelength):
        c = cmap(norm(lam))
        axes[0, 0].plot(np.rad2deg(theta_i), energy[:, j], color=c, lw=1)
        if ext is not None:
            axes[0, 1].plot(np.rad2deg(theta_i), ext[:, j], color=c, lw=1)
    axes[0, 0].set(xlabel="theta_i [deg]", ylabel="albedo = integral f d omega_o", title=f"{model_name}: energy")
    lo, hi = float(np.min(energy)), float(np.max(energy))
    if hi - lo < 0.02:  # a lossless fiber: show float rounding as the flat line it is
        axes[0, 0].set_ylim(lo - 0.01, hi + 0.01)
    if ext is not None:
        axes[0, 1].set(xlabel="theta_i [deg]", ylabel="Q_ext / sin(zeta)", title="extinction per geometric hit")
    if len(wavelength) > 1:  # one line per wavelength: the colour bar is their legend
        fig.colorbar(ScalarMappable(norm, cmap), ax=axes[0, :], label="wavelength [nm]", pad=0.02)
    else:
        axes[0, 0].set_title(f"{model_name}: energy at {wavelength[0]:.0f} nm")
    save_figure(fig, path)
