"""The few places where numpy and Dr.Jit spell an operation differently.

Formulas needed on both sides are written once with an array-module parameter ``xp``
(``numpy`` or ``drjit``), as ``models.neural.features`` does; these helpers bridge the
names that differ.
"""

from __future__ import annotations

import numpy as np


def select(xp):
    """``where(mask, a, b)``: ``np.where`` or ``dr.select``."""
    return np.where if xp is np else xp.select


def asin(x, xp):
    """``arcsin`` of ``x`` clamped to [-1, 1] (rounding can step just outside)."""
    return np.arcsin(np.clip(x, -1.0, 1.0)) if xp is np else xp.safe_asin(x)  # which clamps


def sqrt0(x, xp):
    """``sqrt(max(x, 0))``."""
    return np.sqrt(np.maximum(0.0, x)) if xp is np else xp.safe_sqrt(x)
