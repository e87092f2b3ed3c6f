"""The grids every table shares: node interpolation and the solid angle of a bin.

Written once for the whole project; the tables of single fibers (``models.fiber``), the
bundle tables (``models.bundle_table``), the baker's tallies and the plugins' uploads
all use these.
"""

from __future__ import annotations

import numpy as np


def linear(grid: np.ndarray, x: np.ndarray, periodic: bool = False):
    """Indices and weights of linear interpolation on a sorted grid: ``(i0, i1, w)`` with
    ``value = (1 - w) v[i0] + w v[i1]``.

    Periodic grids are uniform over ``[grid[0], grid[0] + 2 pi)``; other grids clamp
    ``x`` to their range (a constant extension at the ends).
    """
    n = len(grid)
    if n == 1:
        z = np.zeros(np.shape(x), dtype=np.int64)
        return z, z, np.zeros(np.shape(x))
    if periodic:
        step = 2 * np.pi / n
        t = np.mod(x - grid[0], 2 * np.pi) / step
        i0 = np.floor(t).astype(np.int64) % n
        return i0, (i0 + 1) % n, t - np.floor(t)
    x = np.clip(x, grid[0], grid[-1])
    i0 = np.clip(np.searchsorted(grid, x, side="right") - 1, 0, n - 2)
    w = (x - grid[i0]) / (grid[i0 + 1] - grid[i0])
    return i0, i0 + 1, w


def bin_solid_angle(phi_edges, theta_edges) -> np.ndarray:
    """Solid angle of each (phi, theta) bin, ``[n_phi, n_theta]``: ``d(phi) d(sin theta)``
    (theta measured from the normal plane, as every direction in the project)."""
    return np.outer(np.diff(np.asarray(phi_edges, np.float64)), np.diff(np.sin(np.asarray(theta_edges, np.float64))))
