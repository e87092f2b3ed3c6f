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


def core_l1(pred, true, omega, fraction: float = 0.9) -> float:
    """Relative L1 over the bins that hold ``fraction`` of each row's energy in ``true``.

    ``pred`` and ``true`` are ``[rows, bins]`` (a row: one incident direction and wavelength;
    its bins: the outgoing directions), ``omega [bins]`` the bins' solid angles. A row's
    energy is ``sum S omega``; its core is the smallest set of its bins, largest first,
    holding ``fraction`` of it; the figure is ``sum |pred - true| omega / sum true omega``
    over every row's core, pooled (so rows weigh as their energy). The bins left out are the
    floor, where a relative error says little and the light is ~``1 - fraction``."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    e = true * np.asarray(omega, np.float64)
    order = np.argsort(-e, axis=1)
    sorted_e = np.take_along_axis(e, order, 1)
    before = np.cumsum(sorted_e, 1) - sorted_e  # energy of the larger bins
    keep_sorted = before < fraction * sorted_e.sum(1, keepdims=True)
    keep = np.zeros_like(keep_sorted)
    np.put_along_axis(keep, order, keep_sorted, 1)
    d = np.abs(pred - true) * np.asarray(omega, np.float64)
    return float(d[keep].sum() / max(e[keep].sum(), 1e-300))
