"""Figures of merit of a model against a table: one definition per name, used by
training, the export stage's error against run time and the benchmarks.

Every figure is over table bins. ``weights`` count how many bins a row stands for (the
training split folds symmetric bins into one class, weighted by its bin count), so a
class-weighted figure is the bin-weighted one of the expanded table.
"""

from __future__ import annotations

import numpy as np


def _w(weights, shape):
    return np.ones(shape) if weights is None else np.broadcast_to(np.asarray(weights, np.float64), shape)


def relative_l1(pred, true, weights=None) -> float:
    """``sum |pred - true| / sum true`` over bins (and wavelengths): energy-weighted."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    w = _w(weights, true.shape)
    return float((w * np.abs(pred - true)).sum() / max((w * true).sum(), 1e-300))


def log_mae(pred, true, s0: float, weights=None) -> float:
    """Mean absolute error of ``log(1 + S / s0)`` (the training target) over bins."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    d = np.abs(np.log1p(pred / s0) - np.log1p(true / s0))
    return float(np.average(d, weights=_w(weights, d.shape)))


def albedo_error(albedo, reference) -> float:
    """Largest relative error of the scattered fraction over incidences and wavelengths."""
    albedo, reference = np.asarray(albedo, np.float64), np.asarray(reference, np.float64)
    return float(np.max(np.abs(albedo - reference) / np.maximum(reference, 1e-12)))
