"""The arguments of every evaluator of a scattering function, checked in one place: a fiber
table or model, a bundle table's lookup, and the exported MLP in onnxruntime and Dr.Jit
(numpy in). Angles are radians, as everywhere in the project; a wrong argument is a
``ValueError`` that names it and says what it should be, never a NaN or a silent clamp.
"""

from __future__ import annotations

import numpy as np

NAMES = ("phi_i", "theta_i", "phi_o", "theta_o")
# the largest longitude: pi/2, and pi/2 rounded to float32 (half an ulp above it) or a float32
# sum near the pole (a few ulps: 2^-21 relative covers four)
THETA_MAX = np.pi / 2 * (1 + 2.0**-21)


def real(value, name: str) -> np.ndarray:
    """``value`` as a float64 array of finite numbers, or a ValueError naming ``name``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or an array of numbers (got {type(value).__name__})") from None
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds {np.count_nonzero(~np.isfinite(a))} values that are not finite numbers")
    return a


def check_theta(theta: np.ndarray, name: str) -> None:
    """A longitude lies in [-pi/2, pi/2] radians (a value beyond is most likely degrees)."""
    if np.any(~np.isfinite(theta)) or np.any(np.abs(theta) > THETA_MAX):
        raise ValueError(f"{name} must lie in [-pi/2, pi/2] radians (got values up to "
                         f"{np.nanmax(np.abs(theta)):.4g}); angles are radians, not degrees")


def directions(phi_i, theta_i, phi_o, theta_o) -> tuple[np.ndarray, ...]:
    """The four angles checked (finite; each theta within [-pi/2, pi/2]) and broadcast."""
    arrays = [real(v, n) for v, n in zip((phi_i, theta_i, phi_o, theta_o), NAMES)]
    check_theta(arrays[1], "theta_i")
    check_theta(arrays[3], "theta_o")
    try:
        return tuple(np.broadcast_arrays(*arrays))
    except ValueError:
        raise ValueError("phi_i, theta_i, phi_o and theta_o do not broadcast together (shapes "
                         f"{', '.join(str(a.shape) for a in arrays)})") from None


def wavelengths(wavelength, have, name: str = "wavelength") -> np.ndarray:
    """``wavelength`` (nm) checked against the tabulated ``have``: within their range (to a
    thousandth of a nanometre), or a ValueError that gives the range."""
    wl = real(wavelength, name)
    lo, hi = float(np.min(have)), float(np.max(have))
    if np.any(wl < lo - 1e-3) or np.any(wl > hi + 1e-3):
        raise ValueError(f"{name} {wl.min():g}..{wl.max():g} nm lies outside the table's {lo:g}..{hi:g} nm "
                         "(wavelengths are nanometres)")
    return wl


def check_albedo(albedo, n_lambda: int) -> np.ndarray:
    """A per-event albedo as one value per wavelength, or a ValueError saying what is wrong."""
    a = real(albedo, "albedo")
    if a.ndim > 1 or (a.ndim == 1 and len(a) not in (1, n_lambda)):
        raise ValueError(f"albedo: give one value or one per wavelength ({n_lambda}); got shape {a.shape}")
    if np.any((a < 0) | (a > 1)):
        raise ValueError(f"albedo must lie in [0, 1] (a fraction of the fiber's scattering kept per event); got "
                         f"{np.round(a, 4).tolist()}")
    return np.broadcast_to(a, (n_lambda,)).astype(np.float64)
