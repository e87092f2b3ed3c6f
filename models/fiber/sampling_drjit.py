"""A fiber table uploaded for Dr.Jit: the sampler of :class:`~models.fiber.sampling.FiberSampler`
and the table's value, for the baker's bounce loop and the ``fiber_table`` plugin.

The baker's bounce loop runs as one fused kernel: ray cast, importance sampling, pdf,
the spectral fiber value at every wavelength and the weight update. This module holds
the fiber side of it: the CDFs and spectra uploaded as Dr.Jit arrays and the lookups
into them. The formulas are shared with numpy: node interpolation and cells
(``models.grid``), the longitudinal lobes and their sampling
(``models.fiber.longitudinal``, whose ``I0`` is a polynomial in Dr.Jit), the half angle
(``models.fiber.reciprocal``); the tests check the two sides against each other.
"""

from __future__ import annotations

import sys

import drjit as dr
import numpy as np

from ..grid import linear
from .base import FiberTable
from .reciprocal import half_angle, scale_nodes
from .sampling import EDGE, FiberSampler


class DrJitFiber:
    """A fiber table uploaded for Dr.Jit: sampling, pdf, spectral value, albedo."""

    def __init__(self, table: FiberTable, sampler: FiberSampler, Float):
        self.table, self.Float = table, Float
        self.UInt = dr.uint32_array_t(Float)
        self.n_lambda = len(table.wavelength)
        self.n_nodes = len(table.theta_i)
        steps = np.diff(table.theta_i)
        if self.n_nodes > 1 and not np.allclose(steps, steps[0]):
            raise ValueError("the Dr.Jit fiber needs uniformly spaced theta_i nodes")
        self.node_step = float(steps[0]) if self.n_nodes > 1 else 1.0
        self.n_phi = len(table.phi)
        self.dphi = 2 * np.pi / self.n_phi
        self.phi0 = float(table.phi[0])
        self.lobes = table.lobes
        # Spectra are stored padded to a power of two so that one *packet* gather reads all
        # wavelengths of a table entry (Dr.Jit turns it into a few vector loads); scalar
        # gathers, one per wavelength, made the spectral value most of a bounce's cost
        self.packet = 1 << (self.n_lambda - 1).bit_length()
        self.ArrayXf = getattr(sys.modules[Float.__module__], "ArrayXf")  # packet type of this backend
        self.N = [Float(self._padded(l.azimuthal).ravel()) for l in table.lobes]
        # the reciprocal lobes' scale c[|theta| node, lambda] on its own uniform nodes
        self.scale = [Float(self._padded(l.scale).ravel()) if l.reciprocal else None for l in table.lobes]
        self.scale_nodes = [scale_nodes(l.scale) if l.reciprocal else None for l in table.lobes]
        self.energy = Float(sampler.energy.astype(np.float32).ravel())        # [lobe, node]
        self.albedo_nodes = Float(self._padded(table.energy()).ravel())        # [node, lambda]
        # Flat CDF of every (lobe, node) row; a lane searches only its own row
        rows, cells = [], []
        self.cell_offset, self.n_cells = [], []
        offset = 0
        for p in range(len(table.lobes)):
            n_cells = sampler.cell[p].shape[1]
            self.cell_offset.append(offset)
            self.n_cells.append(n_cells)
            cdf = np.cumsum(sampler.cell[p], axis=1)
            cdf[:, -1] = 1.0
            rows.append(cdf)
            cells.append(sampler.cell[p])
            offset += self.n_nodes * n_cells
        self.cdf = Float(np.concatenate([r.ravel() for r in rows]).astype(np.float32))
        self.search_steps = int(np.ceil(np.log2(max(self.n_cells)))) + 1
        self.offsets_array = self.UInt(np.array(self.cell_offset, np.uint32))
        self.n_cells_array = self.UInt(np.array(self.n_cells, np.uint32))
        self.cell = Float(np.concatenate([c.ravel() for c in cells]).astype(np.float32))
        self.theta_o = Float(table.theta_o.astype(np.float32))
        self.sin_theta_o = Float(np.sin(table.theta_o).astype(np.float32))
        self.n_theta_o = len(table.theta_o)

    def _padded(self, a):
        a = np.asarray(a, dtype=np.float32)
        pad = [(0, 0)] * (a.ndim - 1) + [(0, self.packet - a.shape[-1])]
        return np.ascontiguousarray(np.pad(a, pad))

    def _gather_spectrum(self, source, entry) -> list:
        """The ``n_lambda`` values of table entry ``entry`` (an index in units of spectra)."""

        if self.packet == 1:
            return [dr.gather(self.Float, source, entry)]
        values = dr.gather(self.ArrayXf, source, entry, shape=(self.packet, dr.width(entry)))
        return [values[l] for l in range(self.n_lambda)]

    # -- node interpolation in |theta_i| ------------------------------------------
    def _nodes(self, abs_theta):
        return linear(self.table.theta_i, abs_theta, xp=dr)

    def _scale(self, p, abs_theta) -> list:
        """Reciprocal lobe ``p``'s scale ``c(|theta|)`` at every wavelength (linear)."""
        k0, k1, w = linear(self.scale_nodes[p], abs_theta, xp=dr)
        c0 = self._gather_spectrum(self.scale[p], k0)
        c1 = self._gather_spectrum(self.scale[p], k1)
        return [dr.lerp(a, b, w) for a, b in zip(c0, c1)]

    def _lobe_probabilities(self, i0, i1, w):

        E = [dr.gather(self.Float, self.energy, p * self.n_nodes + i0) * (1 - w) +
             dr.gather(self.Float, self.energy, p * self.n_nodes + i1) * w for p in range(len(self.lobes))]
        total = E[0]
        for e in E[1:]:
            total = total + e
        return [e / total for e in E]

    def _phi_cell(self, dphi):
        return linear(self.table.phi, dphi, periodic=True, xp=dr)[0]

    def _theta_o_interval(self, t):
        """Index a with theta_o[a] <= t < theta_o[a+1] (clamped), by binary search."""

        idx = dr.binary_search(0, self.n_theta_o - 1, lambda k: dr.gather(self.Float, self.theta_o, k) <= t)
        return dr.clip(self.UInt(idx) - 1, 0, self.n_theta_o - 2) if self.n_theta_o > 1 else dr.zeros(self.UInt, dr.width(t))

    # -- sampling ----------------------------------------------------------------
    def sample(self, theta_i, u):
        """``(theta_o, dphi)`` for incident ``theta_i``; ``u`` is a list of 5 uniforms."""

        sign = dr.select(theta_i < 0, -1.0, 1.0)
        i0, i1, w = self._nodes(dr.abs(theta_i))
        P = self._lobe_probabilities(i0, i1, w)
        node = dr.select(u[1] < w, i1, i0)
        lobe = dr.zeros(self.UInt, dr.width(theta_i))
        acc = self.Float(0.0)
        for p in range(len(self.lobes) - 1):
            acc = acc + P[p]
            lobe = dr.select(u[0] >= acc, p + 1, lobe)
        # the first cell of the lane's own (lobe, node) row whose CDF exceeds u[2]
        n_cells = dr.gather(self.UInt, self.n_cells_array, lobe)
        row_start = dr.gather(self.UInt, self.offsets_array, lobe) + node * n_cells
        first, last = row_start, row_start + n_cells - 1
        for _ in range(self.search_steps):  # per-lane bisection, unrolled
            mid = (first + last) >> 1
            below = dr.gather(self.Float, self.cdf, mid) <= u[2]
            first = dr.select(below & (first < last), mid + 1, first)
            last = dr.select(below | (first >= last), last, mid)
        k = first
        local = k - row_start
        lo = dr.select(local > 0, dr.gather(self.Float, self.cdf, k - 1, local > 0), 0.0)
        hi = dr.gather(self.Float, self.cdf, k)
        frac = dr.clip((u[2] - lo) / dr.maximum(hi - lo, 1e-12), EDGE, 1 - EDGE)

        theta_o = dr.zeros(self.Float, dr.width(theta_i))
        dphi = dr.zeros(self.Float, dr.width(theta_i))
        for p, lb in enumerate(self.lobes):
            sel = lobe == p
            if lb.dense:
                a = local // self.n_phi
                c = local - a * self.n_phi
                s0 = dr.gather(self.Float, self.sin_theta_o, a)
                s1 = dr.gather(self.Float, self.sin_theta_o, a + 1)
                th = sign * dr.safe_asin(s0 + dr.clip(u[3], EDGE, 1 - EDGE) * (s1 - s0))
                ph = self.phi0 + (self.Float(c) + dr.clip(u[4], EDGE, 1 - EDGE)) * self.dphi
            else:
                th = lb.longitudinal.sample(theta_i, u[3], u[4], xp=dr)
                ph = self.phi0 + (self.Float(local) + frac) * self.dphi
            theta_o = dr.select(sel, th, theta_o)
            dphi = dr.select(sel, ph, dphi)
        dphi = dphi - 2 * np.pi * dr.floor((dphi + np.pi) * (1 / (2 * np.pi)))
        return theta_o, dphi

    def pdf(self, theta_i, theta_o, dphi):

        sign = dr.select(theta_i < 0, -1.0, 1.0)
        i0, i1, w = self._nodes(dr.abs(theta_i))
        P = self._lobe_probabilities(i0, i1, w)
        c = self._phi_cell(dphi)
        out = dr.zeros(self.Float, dr.width(theta_i))
        for p, lb in enumerate(self.lobes):
            base0 = self.cell_offset[p] + i0 * self.n_cells[p]
            base1 = self.cell_offset[p] + i1 * self.n_cells[p]
            if lb.dense:
                t = sign * theta_o
                a = self._theta_o_interval(t)
                inside = (t >= float(self.table.theta_o[0])) & (t <= float(self.table.theta_o[-1]))
                k = a * self.n_phi + c
                area = (dr.gather(self.Float, self.theta_o, a + 1) - dr.gather(self.Float, self.theta_o, a)) * self.dphi
                q = ((1 - w) * dr.gather(self.Float, self.cell, base0 + k) +
                     w * dr.gather(self.Float, self.cell, base1 + k)) / area
                out = out + P[p] * dr.select(inside, q, 0.0)
            else:
                q = ((1 - w) * dr.gather(self.Float, self.cell, base0 + c) +
                     w * dr.gather(self.Float, self.cell, base1 + c)) * (1.0 / self.dphi)
                out = out + P[p] * lb.longitudinal(theta_i, theta_o, xp=dr) * dr.cos(theta_o) * q
        return out

    # -- values ------------------------------------------------------------------
    def eval_spectrum(self, theta_i, theta_o, dphi) -> list:
        """``f`` at every table wavelength (list), as ``FiberTable.eval_spectrum``."""

        sign = dr.select(theta_i < 0, -1.0, 1.0)
        i0, i1, w = self._nodes(dr.abs(theta_i))
        c0, c1, wc = linear(self.table.phi, dphi, periodic=True, xp=dr)
        L = self.n_lambda
        out = [dr.zeros(self.Float, dr.width(theta_i)) for _ in range(L)]
        for p, lb in enumerate(self.lobes):
            n_o = lb.azimuthal.shape[1]
            if lb.dense:
                to = sign * theta_o
                a = self._theta_o_interval(to)
                t0 = dr.gather(self.Float, self.theta_o, a)
                t1 = dr.gather(self.Float, self.theta_o, a + 1)
                wo = dr.clip((to - t0) / (t1 - t0), 0.0, 1.0)
                o_corners = ((a, 1 - wo), (a + 1, wo))
            else:
                o_corners = ((self.UInt(0), 1.0),)
            M = lb.longitudinal(theta_i, theta_o, xp=dr)
            n0, n1, wd = i0, i1, w
            if lb.reciprocal:  # N at the half angle, the symmetric weight and scale
                abs_d, weight = half_angle(theta_i, theta_o, dr)
                n0, n1, wd = self._nodes(abs_d)
                M = M * weight
            acc = [dr.zeros(self.Float, dr.width(theta_i)) for _ in range(L)]
            for node, wn in ((n0, 1 - wd), (n1, wd)):
                for o, wo_ in o_corners:
                    for cc, wcc in ((c0, 1 - wc), (c1, wc)):
                        weight = wn * wo_ * wcc
                        values = self._gather_spectrum(self.N[p], (node * n_o + o) * self.n_phi + cc)
                        acc = [dr.fma(weight, v, a_) for v, a_ in zip(values, acc)]
            if lb.reciprocal:
                acc = [a_ * ci * co for a_, ci, co in zip(acc, self._scale(p, dr.abs(theta_i)),
                                                          self._scale(p, dr.abs(theta_o)))]
            out = [o_ + M * a_ for o_, a_ in zip(out, acc)]
        return out

    def event(self, theta_in, u) -> tuple:
        """One scattering event of light at longitude ``theta_in`` (``u``: five uniforms):
        the sampled ``(theta_out, dphi)``, its pdf, ``f`` at every wavelength and the albedo."""
        theta_out, dphi = self.sample(theta_in, u)
        return (theta_out, dphi, self.pdf(theta_in, theta_out, dphi), self.eval_spectrum(theta_in, theta_out, dphi),
                self.albedo(theta_in))

    def albedo(self, theta_i) -> list:

        i0, i1, w = self._nodes(dr.abs(theta_i))
        a0 = self._gather_spectrum(self.albedo_nodes, i0)
        a1 = self._gather_spectrum(self.albedo_nodes, i1)
        return [(1 - w) * x0 + w * x1 for x0, x1 in zip(a0, a1)]
