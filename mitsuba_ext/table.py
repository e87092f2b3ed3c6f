"""Bundle-table lookups as Dr.Jit arithmetic (the numpy twin: ``models.bundle_table.lookup``).

``DrJitTable(table)`` uploads an expanded :class:`~models.bundle_table.BundleTable` and
returns ``S`` at every table wavelength for Dr.Jit arrays of directions, by nearest or
multilinear lookup in (phi_i, theta_i, phi_o, theta_o): azimuths periodic, longitudes
clamped, wavelengths gathered from the same row.
"""

from __future__ import annotations

import numpy as np

from models.bundle_table import BundleTable, lookup_axes


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

        red = table.meta.get("reductions", {})
        if red.get("theta_i") == "mirror" or red.get("phi_i") == "mirror_xz":
            raise ValueError("DrJitTable needs an expanded table: BundleTable.load(path, expand=True)")
        self.Float = Float
        self.UInt = dr.uint32_array_t(Float)
        self.relative = red["phi_o"] == "relative"
        self.n_lambda = len(table.wavelength)
        self.axes = [(np.asarray(g, float), p) for g, p in lookup_axes(table)]
        self.shape = table.values.shape[:4]
        self.values = Float(np.ascontiguousarray(table.values, dtype=np.float32).ravel())
        self.nbytes = table.values.astype(np.float32).nbytes

    def eval(self, phi_i, theta_i, phi_o, theta_o, mode: str = "linear") -> list:
        import drjit as dr

        if self.relative:
            phi_o = phi_o - phi_i
        half_pi = float(np.pi / 2)
        coords = [phi_i, dr.clip(theta_i, -half_pi, half_pi), phi_o, dr.clip(theta_o, -half_pi, half_pi)]
        idx = [axis_corners(self.Float, x, g, p) for x, (g, p) in zip(coords, self.axes)]
        strides = [int(np.prod(self.shape[k + 1:])) * self.n_lambda for k in range(4)]
        if mode == "nearest":
            base = sum((dr.select(w < 0.5, i0, i1) * s for (i0, i1, w), s in zip(idx, strides)), self.UInt(0))
            return [dr.gather(self.Float, self.values, base + l) for l in range(self.n_lambda)]
        if mode != "linear":
            raise ValueError(f"lookup mode {mode!r}: use 'nearest' or 'linear'")
        out = [dr.zeros(self.Float, dr.width(phi_i)) for _ in range(self.n_lambda)]
        for corner in range(16):
            base, weight = self.UInt(0), self.Float(1.0)
            for axis, ((i0, i1, w), s) in enumerate(zip(idx, strides)):
                hi = (corner >> axis) & 1
                base = base + (i1 if hi else i0) * s
                weight = weight * (w if hi else 1.0 - w)
            for l in range(self.n_lambda):
                out[l] = dr.fma(weight, dr.gather(self.Float, self.values, base + l), out[l])
        return out
