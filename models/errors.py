"""Figures of merit of a model against a table: one definition per name, used by
training, the export stage's error against run time, the report and the benchmarks.

**A model's error** is :func:`core_l1`: the relative L1 of its bin averages against a
table's bins over the *core*, the bins that hold 90% of each row's energy (a row: one
incident direction and wavelength; :func:`core_mask`), pooled over rows by energy. Against
the baked table it is measured on the held-out bins of the core (training, export, report);
against an independent bake of the same config (another seed, more paths) it is the
distance from the truth (``bench.encoding``).

**The table's noise** is :func:`noise_l1` over the same bins: ``sqrt(2 / pi) sum E omega /
sum S omega``, the expected relative L1 of the table from its own expectation (``E`` its
standard errors, ``sqrt(2 / pi) E`` the mean ``|N(0, E)|``). So a model equal to the truth
scores about the table's noise against the table; a model's error over the table's noise
(:func:`error_over_noise`) is near 1 when the model is as good as the bake can tell, more
when it is biased.

``weights`` (of :func:`relative_l1`, :func:`log_mae`) count how many bins a row stands for,
so a class-weighted figure is the bin-weighted one of the expanded table.
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


CORE = 0.9  # the share of each row's energy its core holds


def core_mask(true, omega, fraction: float = CORE) -> np.ndarray:
    """``[rows, bins]``: the bins that hold ``fraction`` of each row's energy in ``true``.

    ``true`` is ``[rows, bins]`` (a row: one incident direction and wavelength; its bins: the
    outgoing directions), ``omega [bins]`` the bins' solid angles. A row's energy is ``sum S
    omega``; its core is the smallest set of its bins, largest first, holding ``fraction`` of
    it. The bins left out are the floor, where a relative error says little and the light is
    ~``1 - fraction``."""
    e = np.asarray(true, np.float64) * np.asarray(omega, np.float64)
    order = np.argsort(-e, axis=1)
    sorted_e = np.take_along_axis(e, order, 1)
    before = np.cumsum(sorted_e, 1) - sorted_e  # energy of the larger bins
    keep_sorted = before < fraction * sorted_e.sum(1, keepdims=True)
    keep = np.zeros_like(keep_sorted)
    np.put_along_axis(keep, order, keep_sorted, 1)
    return keep


def core_l1(pred, true, omega, fraction: float = CORE, where=None) -> float:
    """A model's error: ``sum |pred - true| omega / sum true omega`` over every row's core
    (:func:`core_mask`; and ``where``, ``[rows, bins]``, e.g. the held-out bins), pooled, so
    rows weigh as their energy. ``pred`` and ``true`` are ``[rows, bins]``."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    keep = core_mask(true, omega, fraction) & (True if where is None else np.asarray(where, bool))
    w = np.broadcast_to(np.asarray(omega, np.float64), true.shape)
    return float((np.abs(pred - true) * w)[keep].sum() / max((true * w)[keep].sum(), 1e-300))


def noise_l1(true, stderr, omega, fraction: float = CORE, where=None) -> float:
    """The table's noise on the bins :func:`core_l1` measures: ``sqrt(2 / pi) sum E omega /
    sum S omega`` over the core (and ``where``), the expected relative L1 of a table from its
    own expectation."""
    true = np.asarray(true, np.float64)
    keep = core_mask(true, omega, fraction) & (True if where is None else np.asarray(where, bool))
    w = np.broadcast_to(np.asarray(omega, np.float64), true.shape)
    return float(np.sqrt(2 / np.pi) * (np.asarray(stderr, np.float64) * w)[keep].sum()
                 / max((true * w)[keep].sum(), 1e-300))


def error_over_noise(error: float, noise: float) -> float:
    """A model's error in units of the table's noise on the same bins (about 1: as close as
    the bake can tell; 0 where the table has no noise estimate)."""
    return float(error / noise) if noise > 0 else 0.0


def by_rows(a) -> np.ndarray:
    """An expanded table's array ``[phi_i, theta_i, *bins, lambda]`` as ``[rows, bins]``, a row
    per incident direction and wavelength (the layout of :func:`core_l1`)."""
    a = np.asarray(a)
    return np.moveaxis(a, -1, 2).reshape(a.shape[0] * a.shape[1] * a.shape[-1], -1)
