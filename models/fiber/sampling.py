"""Importance sampling of a tabulated fiber: ``(theta_o, dphi)`` given ``theta_i``.

The proposal follows the lobe structure of :class:`~models.fiber.base.FiberTable`
and is gray (wavelength-averaged), so that one sampled direction serves every
wavelength; the spectral weight ``f cos(theta_o) / pdf`` then carries the colour.

For an incident ``theta_i`` between table nodes ``i0`` and ``i1`` (linear weight
``w``):

1. choose lobe ``p`` with probability proportional to its energy (interpolated);
2. choose node ``i0`` or ``i1`` with probability ``1 - w`` or ``w``;
3. separable lobe: ``theta_o`` from ``M_p`` exactly (d'Eon's cone + von Mises-Fisher
   construction, or uniform / stripes), ``dphi`` from the piecewise-constant density
   of the node's wavelength-averaged ``N_p``; dense lobe: a (theta_o, dphi) cell from
   the node's 2D table, uniform in ``(sin theta, phi)`` inside it.

:meth:`pdf` is the exact density of that procedure per ``d theta d phi``; cell values
are corner averages of the piecewise-linear table, so the proposal is positive
wherever ``f`` is.
"""

from __future__ import annotations

import numpy as np

from ..grid import linear
from .base import FiberTable

_FLOOR = 1e-12
# Keep samples this fraction of a cell away from its edges, so that float32 rounding of
# the sampled angle cannot move it into a neighbouring cell (whose pdf may be zero).
EDGE = 1e-3


class FiberSampler:
    def __init__(self, table: FiberTable):
        self.table = table
        self.n_nodes = len(table.theta_i)
        n_phi = len(table.phi)
        self.dphi = 2 * np.pi / n_phi
        energy = []
        self.cdf = []     # per lobe: flat cumulative array, node k's CDF shifted by +k
        self.cell = []    # per lobe: normalized cell probabilities [node, cells]
        for lobe in table.lobes:
            Nbar = lobe.azimuthal.astype(np.float64).mean(axis=-1)  # [node, theta_o?, phi]
            Nnext = np.roll(Nbar, -1, axis=2)
            if lobe.dense:
                sin_t = np.sin(table.theta_o)
                c = 0.25 * (Nbar[:, :-1] + Nbar[:, 1:] + Nnext[:, :-1] + Nnext[:, 1:])
                c = c * (np.diff(sin_t)[None, :, None] * self.dphi)
                c = c.reshape(self.n_nodes, -1)
            else:
                c = 0.5 * (Nbar[:, 0] + Nnext[:, 0]) * self.dphi
            total = c.sum(axis=1, keepdims=True)
            energy.append(total[:, 0])
            p = c / np.maximum(total, _FLOOR)
            self.cell.append(p)
            cdf = np.cumsum(p, axis=1)
            cdf[:, -1] = 1.0
            self.cdf.append((cdf + np.arange(self.n_nodes)[:, None]).ravel())
        self.energy = np.maximum(np.array(energy), _FLOOR)  # [lobe, node]

    # ------------------------------------------------------------------
    def _lobe_probabilities(self, abs_theta_i):
        i0, i1, w = linear(self.table.theta_i, abs_theta_i)
        E = (1 - w) * self.energy[:, i0] + w * self.energy[:, i1]  # [lobe, ...]
        return E / E.sum(axis=0), (i0, i1, w)

    def sample(self, theta_i, u):
        """``(theta_o, dphi)`` for incident ``theta_i``; ``u`` has 5 uniform rows."""
        theta_i = np.asarray(theta_i, dtype=np.float64)
        sign = np.where(theta_i < 0, -1.0, 1.0)
        P, (i0, i1, w) = self._lobe_probabilities(np.abs(theta_i))
        lobe_idx = np.minimum((np.cumsum(P, axis=0) < u[0]).sum(axis=0), len(P) - 1)
        node = np.where(u[1] < w, i1, i0)
        theta_o = np.zeros(theta_i.shape)
        dphi = np.zeros(theta_i.shape)
        for p, lobe in enumerate(self.table.lobes):
            sel = lobe_idx == p
            if not np.any(sel):
                continue
            k = np.searchsorted(self.cdf[p], node[sel] + u[2][sel], side="right")
            n_cells = self.cell[p].shape[1]
            k = np.clip(k - node[sel] * n_cells, 0, n_cells - 1)
            if lobe.dense:
                n_phi = len(self.table.phi)
                a, c = np.divmod(k, n_phi)
                s0, s1 = np.sin(self.table.theta_o[a]), np.sin(self.table.theta_o[a + 1])
                theta_o[sel] = sign[sel] * np.arcsin(s0 + np.clip(u[3][sel], EDGE, 1 - EDGE) * (s1 - s0))
                dphi[sel] = self.table.phi[c] + np.clip(u[4][sel], EDGE, 1 - EDGE) * self.dphi
            else:
                theta_o[sel] = lobe.longitudinal.sample(theta_i[sel], u[3][sel], u[4][sel])
                # the phi uniform is reused: cell chosen by u[2], position by its remainder
                lo = np.where(k > 0, self.cdf[p][node[sel] * n_cells + k - 1] - node[sel], 0.0)
                hi = self.cdf[p][node[sel] * n_cells + k] - node[sel]
                frac = np.clip((u[2][sel] - lo) / np.maximum(hi - lo, _FLOOR), EDGE, 1 - EDGE)
                dphi[sel] = self.table.phi[k] + frac * self.dphi
        return theta_o, np.mod(dphi + np.pi, 2 * np.pi) - np.pi

    def pdf(self, theta_i, theta_o, dphi):
        """Density of :meth:`sample` per ``d theta_o d dphi``."""
        theta_i, theta_o, dphi = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                       for a in (theta_i, theta_o, dphi)))
        sign = np.where(theta_i < 0, -1.0, 1.0)
        P, (i0, i1, w) = self._lobe_probabilities(np.abs(theta_i))
        n_phi = len(self.table.phi)
        c = linear(self.table.phi, dphi, periodic=True)[0]  # the azimuth's cell
        out = np.zeros(theta_i.shape)
        for p, lobe in enumerate(self.table.lobes):
            if lobe.dense:
                t = sign * theta_o
                grid = self.table.theta_o
                a = linear(grid, t)[0]
                inside = (t >= grid[0]) & (t <= grid[-1])
                k = a * n_phi + c
                cell_area = (grid[a + 1] - grid[a]) * self.dphi  # density per d theta d phi
                q = ((1 - w) * self.cell[p][i0, k] + w * self.cell[p][i1, k]) / cell_area
                out += P[p] * np.where(inside, q, 0.0)
            else:
                q_phi = ((1 - w) * self.cell[p][i0, c] + w * self.cell[p][i1, c]) / self.dphi
                out += P[p] * lobe.longitudinal(theta_i, theta_o) * np.cos(theta_o) * q_phi
        return out
