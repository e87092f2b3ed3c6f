"""Dr.Jit twin of :class:`~models.fiber.sampling.FiberSampler` and of the table lookup.

The baker's bounce loop runs as one fused kernel per bounce: ray cast, importance
sampling, pdf, the spectral fiber value at every wavelength and the weight update.
This module holds the fiber side of it. It mirrors the numpy code line for line
(same lobes, same node interpolation, same piecewise-constant cells, same d'Eon
sampling), and the tests check it against that code; only ``I0`` differs, here the
Abramowitz-Stegun 9.8.1-9.8.2 polynomials (relative error < 2e-7, below float32).
"""

from __future__ import annotations

import sys

import numpy as np

from .base import FiberTable
from .reciprocal import half_angle
from .sampling import EDGE, FiberSampler


def i0e(x):
    """``exp(-|x|) I0(x)`` for Dr.Jit floats (Abramowitz & Stegun 9.8.1, 9.8.2)."""
    import drjit as dr

    ax = dr.abs(x)
    t = dr.square(ax * (1 / 3.75))
    small = 1 + t * (3.5156229 + t * (3.0899424 + t * (1.2067492 + t * (0.2659732 + t * (0.0360768 + t * 0.0045813)))))
    small = small * dr.exp(-ax)
    u = 3.75 / dr.maximum(ax, 3.75)
    large = (0.39894228 + u * (0.01328592 + u * (0.00225319 + u * (-0.00157565 + u * (0.00916281 + u * (
        -0.02057706 + u * (0.02635537 + u * (-0.01647633 + u * 0.00392377)))))))) * dr.rsqrt(dr.maximum(ax, 3.75))
    return dr.select(ax < 3.75, small, large)


def longitudinal(lobe, theta_i, theta_o):
    """``M(theta_i, theta_o)`` of a lobe, as :meth:`Longitudinal.__call__`."""
    import drjit as dr

    if lobe.kind == "deon":
        kappa = 1.0 / float(lobe.v)
        ti = theta_i + float(lobe.shift)
        c = kappa * dr.abs(dr.cos(ti)) * dr.cos(theta_o)
        s = kappa * dr.sin(ti) * dr.sin(theta_o)
        return float(kappa / -np.expm1(-2 * kappa)) * i0e(c) * dr.exp(c - s - kappa)
    if lobe.kind == "uniform":
        return dr.full(type(theta_o), 0.5, dr.width(theta_o))
    if lobe.kind == "stripes":
        n = lobe.n_stripes
        edges = np.linspace(-np.pi / 2, np.pi / 2, 2 * n + 1)
        lit_cos = float(sum(np.sin(edges[2 * k + 1]) - np.sin(edges[2 * k]) for k in range(n)))
        band = dr.clip(dr.floor((theta_o + np.pi / 2) * (2 * n / np.pi)), 0, 2 * n - 1)
        lit = (band - 2 * dr.floor(band * 0.5)) == 0
        return dr.select(lit, 1.0 / lit_cos, 0.0)
    if lobe.kind == "none":
        return dr.full(type(theta_o), 1.0, dr.width(theta_o))
    raise ValueError(f"unknown longitudinal lobe kind {lobe.kind!r}")


def sample_longitudinal(lobe, theta_i, u1, u2):
    """``theta_o`` with density ``M cos(theta_o)``, as the numpy ``sample_longitudinal``."""
    import drjit as dr

    if lobe.kind == "deon":
        v = float(lobe.v)
        theta_p = theta_i + float(lobe.shift)
        u1 = dr.maximum(u1, 1e-12)
        cos_t = 1 + v * dr.log(u1 + (1 - u1) * float(np.exp(-2 / v)))
        sin_t = dr.safe_sqrt(1 - dr.square(cos_t))
        sin_o = -cos_t * dr.sin(theta_p) + sin_t * dr.cos(2 * np.pi * u2) * dr.abs(dr.cos(theta_p))
        return dr.safe_asin(dr.clip(sin_o, -1, 1))
    if lobe.kind == "uniform":
        return dr.safe_asin(2 * u1 - 1)
    if lobe.kind == "stripes":
        n = lobe.n_stripes
        edges = np.sin(np.linspace(-np.pi / 2, np.pi / 2, 2 * n + 1))
        lo, hi = edges[0:-1:2], edges[1::2]
        cw = np.cumsum(hi - lo) / np.sum(hi - lo)
        out = dr.zeros(type(u1), dr.width(u1))
        prev = 0.0
        for k in range(n):  # n is small: unrolled band selection
            inside = (u1 >= prev) & (u1 < cw[k]) if k < n - 1 else (u1 >= prev)
            frac = (u1 - prev) / float(cw[k] - prev)
            out = dr.select(inside, dr.safe_asin(dr.clip(float(lo[k]) + frac * float(hi[k] - lo[k]), -1, 1)), out)
            prev = float(cw[k])
        return out
    raise ValueError(f"cannot sample a longitudinal lobe of kind {lobe.kind!r}")


class DrJitFiber:
    """A fiber table uploaded for Dr.Jit: sampling, pdf, spectral value, albedo."""

    def __init__(self, table: FiberTable, sampler: FiberSampler, Float):
        import drjit as dr

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
        import drjit as dr

        if self.packet == 1:
            return [dr.gather(self.Float, source, entry)]
        values = dr.gather(self.ArrayXf, source, entry, shape=(self.packet, dr.width(entry)))
        return [values[l] for l in range(self.n_lambda)]

    # -- node interpolation in |theta_i| ------------------------------------------
    def _nodes(self, abs_theta):
        import drjit as dr

        if self.n_nodes == 1:
            z = dr.zeros(self.UInt, dr.width(abs_theta))
            return z, z, dr.zeros(self.Float, dr.width(abs_theta))
        t = dr.clip(abs_theta * (1.0 / self.node_step), 0.0, float(self.n_nodes - 1))
        i0 = dr.minimum(dr.floor(t), float(self.n_nodes - 2))
        return self.UInt(i0), self.UInt(i0) + 1, t - i0

    def _scale(self, p, abs_theta) -> list:
        """Reciprocal lobe ``p``'s scale ``c(|theta|)`` at every wavelength (linear)."""
        import drjit as dr

        n = self.table.lobes[p].scale.shape[0]
        t = dr.clip(abs_theta * float((n - 1) / (np.pi / 2)), 0.0, float(n - 1))
        k0 = dr.minimum(dr.floor(t), float(n - 2))
        w = t - k0
        c0 = self._gather_spectrum(self.scale[p], self.UInt(k0))
        c1 = self._gather_spectrum(self.scale[p], self.UInt(k0) + 1)
        return [dr.lerp(a, b, w) for a, b in zip(c0, c1)]

    def _lobe_probabilities(self, i0, i1, w):
        import drjit as dr

        E = [dr.gather(self.Float, self.energy, p * self.n_nodes + i0) * (1 - w) +
             dr.gather(self.Float, self.energy, p * self.n_nodes + i1) * w for p in range(len(self.lobes))]
        total = E[0]
        for e in E[1:]:
            total = total + e
        return [e / total for e in E]

    def _phi_cell(self, dphi):
        import drjit as dr

        t = (dphi - self.phi0) * (1.0 / self.dphi)
        t = t - dr.floor(t * (1.0 / self.n_phi)) * self.n_phi
        return dr.minimum(self.UInt(dr.floor(t)), self.n_phi - 1)

    def _theta_o_interval(self, t):
        """Index a with theta_o[a] <= t < theta_o[a+1] (clamped), by binary search."""
        import drjit as dr

        idx = dr.binary_search(0, self.n_theta_o - 1, lambda k: dr.gather(self.Float, self.theta_o, k) <= t)
        return dr.clip(self.UInt(idx) - 1, 0, self.n_theta_o - 2) if self.n_theta_o > 1 else dr.zeros(self.UInt, dr.width(t))

    # -- sampling ----------------------------------------------------------------
    def sample(self, theta_i, u):
        """``(theta_o, dphi)`` for incident ``theta_i``; ``u`` is a list of 5 uniforms."""
        import drjit as dr

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
                th = sample_longitudinal(lb.longitudinal, theta_i, u[3], u[4])
                ph = self.phi0 + (self.Float(local) + frac) * self.dphi
            theta_o = dr.select(sel, th, theta_o)
            dphi = dr.select(sel, ph, dphi)
        dphi = dphi - 2 * np.pi * dr.floor((dphi + np.pi) * (1 / (2 * np.pi)))
        return theta_o, dphi

    def pdf(self, theta_i, theta_o, dphi):
        import drjit as dr

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
                out = out + P[p] * longitudinal(lb.longitudinal, theta_i, theta_o) * dr.cos(theta_o) * q
        return out

    # -- values ------------------------------------------------------------------
    def eval_spectrum(self, theta_i, theta_o, dphi) -> list:
        """``f`` at every table wavelength (list), as ``FiberTable.eval_spectrum``."""
        import drjit as dr

        sign = dr.select(theta_i < 0, -1.0, 1.0)
        i0, i1, w = self._nodes(dr.abs(theta_i))
        t = (dphi - self.phi0) * (1.0 / self.dphi)
        t = t - dr.floor(t * (1.0 / self.n_phi)) * self.n_phi
        c0 = dr.minimum(self.UInt(dr.floor(t)), self.n_phi - 1)
        wc = t - dr.floor(t)
        c1 = dr.select(c0 + 1 >= self.n_phi, 0, c0 + 1)
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
            M = longitudinal(lb.longitudinal, theta_i, theta_o)
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

    def albedo(self, theta_i) -> list:
        import drjit as dr

        i0, i1, w = self._nodes(dr.abs(theta_i))
        a0 = self._gather_spectrum(self.albedo_nodes, i0)
        a1 = self._gather_spectrum(self.albedo_nodes, i1)
        return [(1 - w) * x0 + w * x1 for x0, x1 in zip(a0, a1)]
