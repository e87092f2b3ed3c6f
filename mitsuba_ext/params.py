"""Plugin parameters read with their types checked: one reader per kind.

Mitsuba's XML and dict loaders hand a Python plugin whatever the scene says: the string
``'false'`` where a boolean belongs (truthy to ``bool()``), a float where an integer
belongs (truncated by ``int()``), a string where a vector belongs. Each reader below
accepts a value only in its own type and domain and otherwise raises a ``ValueError``
that names the plugin, the key, what it was given and what it expects, so a scene's
mistake is said when it loads, not rendered.
"""

from __future__ import annotations

import numbers

import drjit as dr
import mitsuba as mi
import numpy as np


def _refuse(plugin: str, name: str, value, expected: str):
    raise ValueError(f"{plugin}: '{name}' must be {expected}, got {value!r} ({type(value).__name__})")


def _domain(lo, hi) -> str:
    """``[lo, hi]``, ``>= lo`` or ``<= hi``; empty when both ends are open."""
    if np.isfinite(lo) and np.isfinite(hi):
        return f"[{lo:g}, {hi:g}]"
    return f">= {lo:g}" if np.isfinite(lo) else (f"<= {hi:g}" if np.isfinite(hi) else "")


def number(plugin: str, name: str, value, lo=-np.inf, hi=np.inf) -> float:
    """A finite real number within ``[lo, hi]`` (not a boolean, not a string)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        _refuse(plugin, name, value, "a number")
    x = float(value)
    if not (np.isfinite(x) and lo <= x <= hi):
        _refuse(plugin, name, value, _domain(lo, hi) or "finite")
    return x


def integer(plugin: str, name: str, value, lo=-np.inf, hi=np.inf) -> int:
    """A whole number within ``[lo, hi]``: an int, or a float without a fraction (a scene's
    ``5.0``); ``3.7`` is refused rather than truncated."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        _refuse(plugin, name, value, "an integer")
    if not (np.isfinite(float(value)) and float(value) == int(value)):
        _refuse(plugin, name, value, "an integer (no fraction)")
    k = int(value)
    if not lo <= k <= hi:
        domain = _domain(lo, hi)
        _refuse(plugin, name, value, f"an integer {'in ' if domain.startswith('[') else ''}{domain}")
    return k


def boolean(plugin: str, name: str, value) -> bool:
    """``true`` or ``false`` as a boolean (XML ``<boolean>``, Python ``True``/``False``);
    strings and numbers are refused: ``bool('false')`` is true."""
    if not isinstance(value, (bool, np.bool_)):
        _refuse(plugin, name, value, "a boolean (XML <boolean name=... value=\"true\"/>, Python True/False)")
    return bool(value)


def choice(plugin: str, name: str, value, options) -> str:
    """One of the strings ``options``."""
    if not isinstance(value, str) or value not in options:
        _refuse(plugin, name, value, "one of " + ", ".join(repr(o) for o in options))
    return value


def vector3(plugin: str, name: str, value) -> np.ndarray:
    """Three finite numbers (a list, a Mitsuba vector or point); not a string."""
    if isinstance(value, str):
        _refuse(plugin, name, value, "a 3-vector, e.g. [0, 0, 1]")
    try:
        v = np.asarray(value, float).ravel()
    except (TypeError, ValueError):
        _refuse(plugin, name, value, "a 3-vector, e.g. [0, 0, 1]")
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        _refuse(plugin, name, value, "a 3-vector of finite numbers, e.g. [0, 0, 1]")
    return v


def jit_variant_only(plugin: str) -> None:
    """The plugins are vectorized Dr.Jit code: a ``scalar_*`` variant is refused at load,
    naming the variant to use instead."""
    variant = mi.variant() or ""
    if variant.startswith("scalar"):
        raise ValueError(f"{plugin}: runs in Mitsuba's JIT variants (llvm_*, cuda_*), not {variant}: it is vectorized "
                         f"Dr.Jit code; render with {variant.replace('scalar', 'llvm_ad')}")


def srgb_upsampled(rgb, wavelength) -> np.ndarray:
    """An sRGB colour as a reflectance spectrum at ``wavelength`` (nm): Jakob and Hanika
    2019's model with Mitsuba's own coefficients (``mi.srgb_model_fetch``), the spectrum
    Mitsuba's spectral variants give the same colour: ``0.5 + x / (2 sqrt(1 + x^2))``,
    ``x = c0 lambda^2 + c1 lambda + c2``."""
    c = np.asarray(mi.srgb_model_fetch(mi.ScalarColor3f(*(float(v) for v in rgb))), np.float64)
    lam = np.asarray(wavelength, np.float64)
    x = (c[0] * lam + c[1]) * lam + c[2]
    return 0.5 + x / (2 * np.sqrt(1 + x * x))


def spectrum_property(props, name: str):
    """The property ``name`` as a number or a Mitsuba texture (a ``{"type": "spectrum", ...}``
    arrives as Mitsuba's spectrum record, which ``get_texture`` instantiates)."""
    value = props[name]
    if isinstance(value, (np.bool_, str, numbers.Real, mi.Texture)):
        return value
    return props.get_texture(name)


def spectrum_at(plugin: str, name: str, value, wavelength) -> np.ndarray:
    """A spatially uniform spectrum at the table's ``wavelength`` (nm): a number (grey), or
    a Mitsuba spectrum or texture (``{"type": "spectrum", "value": [(nm, v), ...]}``,
    ``srgb``, ``uniform``, ...). Spectral variants evaluate it at the table's wavelengths;
    RGB variants take its colour and upsample it (:func:`srgb_upsampled`); mono variants
    take its one value."""
    wl = np.asarray(wavelength, np.float64)
    if not isinstance(value, mi.Texture):
        return np.full(len(wl), number(plugin, name, value))
    if value.is_spatially_varying():
        _refuse(plugin, name, value, "a spectrum uniform over the shape (a texture that varies along the yarn is "
                                     "not supported)")
    si = dr.zeros(mi.SurfaceInteraction3f, len(wl))
    if mi.is_spectral:
        si.wavelengths = mi.Spectrum(*([mi.Float(wl)] * dr.size_v(mi.Spectrum)))
        return np.asarray(value.eval(si), np.float64).reshape(-1, len(wl))[0]  # channel 0: each lane one lambda
    out = np.asarray(value.eval(dr.zeros(mi.SurfaceInteraction3f, 1)), np.float64).reshape(-1)
    return srgb_upsampled(out, wl) if mi.is_rgb and len(out) == 3 else np.full(len(wl), out[0])


def texture_values(texture, n: int = 256) -> np.ndarray:
    """A scalar texture's values over its UV square, at the centres of ``n x n`` cells: what
    a texture on the curve's UV gives its hits, for checking its range at load (a
    ``bitmap``'s filtered values lie within its texels' range; finer features than
    ``1 / n`` may escape)."""
    u = (np.arange(n) + 0.5) / n
    U, V = np.meshgrid(u, u, indexing="ij")
    si = dr.zeros(mi.SurfaceInteraction3f, n * n)
    si.uv = mi.Point2f(mi.Float(U.ravel()), mi.Float(V.ravel()))
    return np.asarray(texture.eval_1(si), np.float64)
