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


def hat_basis(wavelength_nm, fine_nm) -> np.ndarray:
    """``[len(fine_nm), n_lambda]``: each sample's hat function of linear interpolation
    between the ``wavelength_nm`` samples, held constant beyond the first and last (how the
    plugins reconstruct a table's spectrum), evaluated at ``fine_nm``."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    eye = np.eye(len(wl))
    return np.stack([np.interp(fine_nm, wl, eye[k]) for k in range(len(wl))], -1)


def spectrum_to_srgb(values: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Linear sRGB of spectra ``values[..., n_lambda]`` seen under D65.

    Each spectrum is treated as a reflectance-like factor and reconstructed piecewise
    linearly between its samples (held constant beyond the first and last), then
    integrated against the CIE 1931 2-degree observer and D65 on their own 1 nm grid.
    So a flat spectrum is exactly white (Y = 1, D65 chromaticity) at any sampling, even
    three wavelengths. A single wavelength gives that wavelength's grey level.
    """
    import colour

    wl = np.asarray(wavelength_nm, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if wl.size == 1:
        return np.repeat(values, 3, axis=-1)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    fine = cmfs.wavelengths
    s = np.interp(fine, d65.wavelengths, d65.values)
    basis = hat_basis(wl, fine)  # basis[f, k] = interpolant of the k-th unit spectrum
    weights = basis.T @ (cmfs.values * (s * np.gradient(fine))[:, None])  # (n_lambda, 3)
    weights /= weights[:, 1].sum()
    return colour.XYZ_to_sRGB(values @ weights, apply_cctf_encoding=False)
