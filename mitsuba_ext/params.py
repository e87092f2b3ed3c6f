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
