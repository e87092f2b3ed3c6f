"""Wavelength grids, dispersion, and spectral -> sRGB conversion (CIE 1931, D65)."""

from __future__ import annotations

import numpy as np


def wavelength_grid(start_nm: float, stop_nm: float, count: int) -> np.ndarray:
    """``count`` wavelengths (nm) evenly spaced from ``start_nm`` to ``stop_nm``."""
    return np.linspace(start_nm, stop_nm, count)


def cauchy(a: float, b_um2: float, wavelength_nm) -> np.ndarray:
    """Cauchy dispersion ``n(lambda) = A + B / lambda^2`` with lambda in micrometres."""
    lam_um = np.asarray(wavelength_nm, dtype=np.float64) * 1e-3
    return a + b_um2 / lam_um**2


def spectral_values(spec, wavelength_nm) -> np.ndarray:
    """A constant, or ``[[nm, value], ...]`` pairs linearly interpolated (held at the ends)."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    if np.isscalar(spec):
        return np.full(wl.shape, float(spec))
    pairs = np.asarray(spec, dtype=np.float64)
    return np.interp(wl, pairs[:, 0], pairs[:, 1])


def spectrum_to_srgb(values: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Linear sRGB of spectra ``values[..., n_lambda]`` seen under D65.

    Each spectrum is treated as a reflectance-like factor: XYZ = sum f S_D65 cmf dl,
    normalized so that f = 1 at every wavelength gives Y = 1 (white). With a single
    wavelength the result is that wavelength's grey level (Y), since colour needs more
    than one sample.
    """
    import colour

    wl = np.asarray(wavelength_nm, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if wl.size == 1:
        return np.repeat(values, 3, axis=-1)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    xyz_bar = np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, k]) for k in range(3)], -1)
    s = np.interp(wl, d65.wavelengths, d65.values)
    dl = np.gradient(wl)
    weights = xyz_bar * (s * dl)[:, None]  # (n_lambda, 3)
    weights /= weights[:, 1].sum()
    xyz = values @ weights
    return colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False)
