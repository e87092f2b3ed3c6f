"""Importance sampling of outgoing directions from a tabulated marginal, in Dr.Jit.

A :class:`DirectionGrid` holds, for each condition (a node of ``phi_i`` x ``theta_i``),
a piecewise-constant density over cells of ``(phi_o, theta_o)``: within a cell the
directions are uniform in ``(phi_o, sin theta_o)``, i.e. uniform in solid angle, so

    pdf(w_o) = P[cell] / (d_phi * (sin theta_1 - sin theta_0))      (per steradian)

A fraction ``uniform`` of the samples is drawn uniformly on the sphere instead, so
that every direction where the BSDF may be non-zero has a positive density (the
neural backends are not exactly zero where the table is). ``sample`` and ``pdf``
use the same cells and the same mixture, which the chi-square test checks.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from models.grid import Cells, cell

FOUR_PI = 4.0 * np.pi


class DirectionGrid:
    """Conditional cell distributions ``mass[phi_i, theta_i, phi_o, theta_o] >= 0``.

    ``phi_i``/``theta_i``: condition nodes (radians; nearest node is used, ``phi_i``
    periodic). ``phi_o_edges``/``theta_o_edges``: cell edges; ``phi_o`` is measured
    from ``phi_i`` when ``relative``. ``mass`` is the energy per cell (any scale). A
    ``mass[phi_i, theta_i, extra, phi_o, theta_o]`` adds a condition given by index
    (``extra`` of :meth:`sample` and :meth:`pdf`: a near-field table's offset cell).
    """

    def __init__(self, mass, phi_i, theta_i, phi_o_edges, theta_o_edges, relative: bool,
                 Float, uniform: float = 0.1):

        mass = np.asarray(mass, np.float64)
        if mass.ndim not in (4, 5) or not np.all(np.isfinite(mass)) or np.any(mass < 0):
            raise ValueError("sampling grid: mass must be a finite, non-negative 4D (or 5D) array")
        self.n_extra = mass.shape[2] if mass.ndim == 5 else 1
        mass = mass.reshape(mass.shape[:2] + (self.n_extra,) + mass.shape[-2:])
        self.Float, self.UInt = Float, dr.uint32_array_t(Float)
        self.relative = relative
        self.uniform = float(uniform)
        self.phi_i = np.asarray(phi_i, float)
        self.theta_i = np.asarray(theta_i, float)
        if len(self.theta_i) > 1:
            mid = 0.5 * (self.theta_i[1:] + self.theta_i[:-1])
            self.theta_i_cells = Cells(np.concatenate([[self.theta_i[0] - 1.0], mid, [self.theta_i[-1] + 1.0]]))
            self.theta_i_cells.upload(Float)
        self.phi_o_edges = np.asarray(phi_o_edges, float)
        self.theta_o_edges = np.asarray(theta_o_edges, float)
        self.theta_cells = Cells(self.theta_o_edges)
        self.theta_cells.upload(Float)
        n_pi, n_ti, _, self.n_phi, self.n_theta = mass.shape
        self.n_cells = self.n_phi * self.n_theta
        flat = mass.reshape(n_pi * n_ti * self.n_extra, self.n_cells)
        total = flat.sum(1, keepdims=True)
        # a condition with no energy samples uniformly (mass 0 everywhere -> flat pmf)
        pmf = np.where(total > 0, flat / np.where(total > 0, total, 1), 1.0 / self.n_cells)
        cdf = np.cumsum(pmf, 1)
        cdf[:, -1] = 1.0
        self.pmf = Float(pmf.ravel().astype(np.float32))
        self.cdf = Float(cdf.ravel().astype(np.float32))
        sin_edges = np.sin(self.theta_o_edges)
        self.sin_lo = Float(sin_edges[:-1].astype(np.float32))
        self.d_sin = Float(np.diff(sin_edges).astype(np.float32))
        self.phi_lo = Float(self.phi_o_edges[:-1].astype(np.float32))
        self.d_phi = Float(np.diff(self.phi_o_edges).astype(np.float32))
        self.nbytes = 2 * pmf.size * 4

    # -- helpers -------------------------------------------------------------
    def _condition(self, phi_i, theta_i, extra=None):
        """Index of the nearest (phi_i, theta_i) node (and the ``extra`` condition)."""

        n_pi, n_ti = len(self.phi_i), len(self.theta_i)
        if n_pi == 1:
            a = self.UInt(0)
        else:  # uniform periodic nodes starting at phi_i[0]
            step = 2 * np.pi / n_pi
            t = (phi_i - float(self.phi_i[0])) / step
            a = self.UInt(dr.round(t - dr.floor(t / n_pi) * n_pi)) % n_pi
        # theta_i: the cell of theta_i between the midpoints of its (possibly graded) nodes
        b = self.UInt(0) if n_ti == 1 else self.theta_i_cells.index(theta_i, xp=dr)
        node = a * n_ti + b
        return node if self.n_extra == 1 else node * self.n_extra + extra

    def _cell_of(self, phi_o, theta_o):
        # tie 0: the cell that sample() drew from, up to its edge
        ip, _ = cell(phi_o, self.phi_o_edges[0], self.phi_o_edges[-1] - self.phi_o_edges[0], self.n_phi,
                     periodic=True, xp=dr)
        it = self.theta_cells.index(theta_o, xp=dr)
        return ip * self.n_theta + it, ip, it

    # -- the two operations --------------------------------------------------
    def sample(self, phi_i, theta_i, u_mix, u2, extra=None):
        """Outgoing ``(phi_o, theta_o)`` (phi_o absolute) and its pdf per steradian."""
        cond = self._condition(phi_i, theta_i, extra)
        base = cond * self.n_cells
        # discrete cell from u2.x, the remainder of u2.x places phi inside the cell
        k = dr.binary_search(0, self.n_cells - 1,
                             lambda j: dr.gather(self.Float, self.cdf, base + j) <= u2.x)
        cdf_hi = dr.gather(self.Float, self.cdf, base + k)
        pmf = dr.gather(self.Float, self.pmf, base + k)
        frac = dr.clip((u2.x - (cdf_hi - pmf)) / dr.maximum(pmf, 1e-30), 0.0, 1.0)
        ip, it = k // self.n_theta, k % self.n_theta
        phi_o = dr.gather(self.Float, self.phi_lo, ip) + frac * dr.gather(self.Float, self.d_phi, ip)
        sin_o = dr.gather(self.Float, self.sin_lo, it) + u2.y * dr.gather(self.Float, self.d_sin, it)
        theta_o = dr.safe_asin(dr.clip(sin_o, -1.0, 1.0))

        # uniform component of the mixture
        w_u = mi.warp.square_to_uniform_sphere(u2)
        use_uniform = u_mix < self.uniform
        theta_o = dr.select(use_uniform, dr.safe_asin(w_u.y), theta_o)
        phi_u = dr.atan2(w_u.z, w_u.x)
        if self.relative:
            phi_o = phi_o + phi_i
        phi_o = dr.select(use_uniform, phi_u, phi_o)
        return phi_o, theta_o, self.pdf(phi_i, theta_i, phi_o, theta_o, extra)

    def pdf(self, phi_i, theta_i, phi_o, theta_o, extra=None):
        """Mixture density per steradian of the absolute direction ``(phi_o, theta_o)``."""

        cond = self._condition(phi_i, theta_i, extra)
        if self.relative:
            phi_o = phi_o - phi_i
        k, ip, it = self._cell_of(phi_o, theta_o)
        pmf = dr.gather(self.Float, self.pmf, cond * self.n_cells + k)
        area = dr.gather(self.Float, self.d_phi, ip) * dr.gather(self.Float, self.d_sin, it)
        return (1.0 - self.uniform) * pmf / area + self.uniform / FOUR_PI
