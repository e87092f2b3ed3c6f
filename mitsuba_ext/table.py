"""Bundle-table lookups as Dr.Jit arithmetic (the numpy twin: ``models.bundle_table.lookup``).

``DrJitTable(table)`` uploads an expanded :class:`~models.bundle_table.BundleTable` with
its limited bin slopes and returns ``S`` at every table wavelength for Dr.Jit arrays of
directions: each bin its value plus slopes in ``phi_o`` and ``sin(theta_o)`` (so that it
averages to its value), ``theta_i`` nodes read along their own specular cone and
blended, ``phi_i`` nodes blended periodically (``linear``), or the nearest node's bin
value (``nearest``). See the comment above ``models.bundle_table.lookup``.
"""

from __future__ import annotations

import numpy as np

from models.bundle_table import BundleTable


def axis_corners(Float, x, grid, periodic: bool):
    """``(i0, i1, w)``: the two nodes of uniform ``grid`` around ``x`` and the weight of ``i1``.

    Periodic grids span 2 pi from ``grid[0]``; others clamp to their ends. A NaN ``x``
    is read as ``grid[0]`` (it must not become an index).
    """
    import drjit as dr

    UInt = dr.uint32_array_t(Float)
    x = dr.select(dr.isfinite(x), x, float(grid[0]))
    n = len(grid)
    if n == 1:
        zero = UInt(0) + dr.zeros(UInt, dr.width(x))
        return zero, zero, dr.zeros(Float, dr.width(x))
    if periodic:  # uniform over 2 pi from grid[0]
        step = 2 * np.pi / n
        t = (x - float(grid[0])) * (1.0 / step)
        t = t - dr.floor(t * (1.0 / n)) * n  # wrap into [0, n)
        i0f = dr.floor(t)
        w = t - i0f
        i0 = UInt(dr.clip(i0f, 0, n - 1))
        i1 = dr.select(i0 + 1 >= n, 0, i0 + 1)
        return i0, i1, w
    # clamped, possibly non-uniform: grids here are uniform, so use the step
    step = float(grid[1] - grid[0])
    t = dr.clip((x - float(grid[0])) * (1.0 / step), 0.0, float(n - 1))
    i0f = dr.minimum(dr.floor(t), float(n - 2))
    return UInt(i0f), UInt(i0f) + 1, t - i0f


class DrJitTable:
    def __init__(self, table: BundleTable, Float):
        import drjit as dr

        from models.bundle_table import bin_slopes

        red = table.meta.get("reductions", {})
        if red.get("theta_i") == "mirror" or red.get("phi_i") == "mirror_xz":
            raise ValueError("DrJitTable needs an expanded table: BundleTable.load(path, expand=True)")
        self.Float = Float
        self.UInt = dr.uint32_array_t(Float)
        self.relative = red["phi_o"] == "relative"
        self.n_lambda = len(table.wavelength)
        self.phi_i = np.asarray(table.phi_i, float)
        self.theta_i = np.asarray(table.theta_i, float)
        self.shape = table.values.shape[:4]
        self.phi_o0 = float(table.phi_o_edges[0])
        self.u_edges = Float(np.sin(table.theta_o_edges).astype(np.float32))
        self.sin_theta_i = Float(np.sin(self.theta_i).astype(np.float32))
        flat = lambda a: Float(np.ascontiguousarray(a, dtype=np.float32).ravel())  # noqa: E731
        self.values = flat(table.values)
        self.s_phi, self.s_u = (flat(a) for a in bin_slopes(table))
        self.nbytes = 3 * table.values.astype(np.float32).nbytes

    def _corners(self, x, grid, periodic, nearest):
        import drjit as dr

        i0, i1, w = axis_corners(self.Float, x, grid, periodic)
        if len(grid) == 1:
            return [(i0, self.Float(1.0))]
        if nearest:
            return [(dr.select(w < 0.5, i0, i1), self.Float(1.0))]
        return [(i0, 1.0 - w), (i1, w)]

    def _read(self, a, b, phi, u, weight, out, nearest):
        """Add ``weight`` x node (a, b) at (phi, u): bin value plus the slopes' offsets."""
        import drjit as dr

        _, n_b, n_p, n_t = self.shape
        L = self.n_lambda
        half_pi = float(np.pi / 2)
        t = (phi - self.phi_o0) * float(n_p / (2 * np.pi))
        t = t - dr.floor(t * (1.0 / n_p)) * n_p
        kp = dr.minimum(self.UInt(dr.floor(t)), n_p - 1)
        to = dr.safe_asin(dr.clip(u, -1.0, 1.0))
        kt = self.UInt(dr.clip(dr.floor((to + half_pi) * float(n_t / np.pi)), 0, n_t - 1))
        base = (((a * n_b + b) * n_p + kp) * n_t + kt) * L
        active = weight != 0.0
        if not nearest:
            dp = (t - self.Float(kp) - 0.5) * float(2 * np.pi / n_p)
            du = u - 0.5 * (dr.gather(self.Float, self.u_edges, kt, active) +
                            dr.gather(self.Float, self.u_edges, kt + 1, active))
        for l in range(L):
            v = dr.gather(self.Float, self.values, base + l, active)
            if not nearest:
                v = v + dr.gather(self.Float, self.s_phi, base + l, active) * dp \
                    + dr.gather(self.Float, self.s_u, base + l, active) * du
            out[l] = dr.fma(weight, v, out[l])

    def eval(self, phi_i, theta_i, phi_o, theta_o, mode: str = "linear") -> list:
        import drjit as dr

        if mode not in ("nearest", "linear"):
            raise ValueError(f"lookup mode {mode!r}: use 'nearest' or 'linear'")
        nearest = mode == "nearest"
        if self.relative:
            phi_o = phi_o - phi_i
        half_pi = float(np.pi / 2)
        theta_i = dr.clip(theta_i, -half_pi, half_pi)
        u, sin_i = dr.sin(theta_o), dr.sin(theta_i)
        out = [dr.zeros(self.Float, dr.width(u)) for _ in range(self.n_lambda)]
        for a, wa in self._corners(phi_i, self.phi_i, True, nearest):
            corners = self._corners(theta_i, self.theta_i, False, nearest)
            shifts = [sin_i - dr.gather(self.Float, self.sin_theta_i, b) for b, _ in corners]
            # each node read at the same distance from its own cone, in u = sin(theta_o) ...
            for (b, wb), s in zip(corners, shifts):
                self._read(a, b, phi_o, u + s, dr.select(dr.abs(u + s) <= 1.0, wa * wb, 0.0), out, nearest)
            # ... and its light shifted past a pole comes back over it at phi + pi. A lane
            # near the lower pole takes it from the node below (s >= 0), near the upper pole
            # from the node above (s <= 0): one read per lane, not one per node
            (b0, w0), (b1, w1) = corners[0], corners[-1]
            s0, s1 = shifts[0], shifts[-1]
            lower = u < 0.0
            s = dr.select(lower, s0, s1)
            back = dr.select(lower, (s0 > 0) & (u <= s0 - 1.0), (s1 < 0) & (u >= 1.0 + s1))
            u_back = dr.select(lower, -2.0 - u + s, 2.0 - u + s)
            self._read(a, dr.select(lower, b0, b1), phi_o + float(np.pi), u_back,
                       dr.select(back, wa * dr.select(lower, w0, w1), 0.0), out, nearest)
        return out
