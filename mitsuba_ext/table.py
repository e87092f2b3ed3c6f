"""Bundle-table lookups as Dr.Jit arithmetic.

``DrJitTable(table)`` uploads an expanded :class:`~models.bundle_table.BundleTable` with
its limited bin slopes and returns ``S`` at every table wavelength for Dr.Jit arrays of
directions. The lookup itself (along the specular cone, bin averages kept, or the
nearest node's bin) is :func:`models.bundle_table.cone_lookup`, the same code numpy's
``models.bundle_table.lookup`` runs; this module only gathers from the uploaded arrays.
"""

from __future__ import annotations

import drjit as dr  # the plugins import this module once a Mitsuba variant is chosen
import numpy as np

from models.bundle_table import BundleTable, bin_slopes, cell_offsets, cone_lookup, needs_expanding
from models.grid import Cells


class DrJitTable:
    """An expanded bundle table uploaded as Dr.Jit arrays, looked up by
    :func:`models.bundle_table.cone_lookup` (the algorithm numpy's lookup runs too) through a
    per-call :class:`_Reader`."""

    def __init__(self, table: BundleTable, Float, block: int | None = None):
        red = table.meta.get("reductions", {})
        if needs_expanding(red):
            raise ValueError("DrJitTable needs an expanded table: BundleTable.load(path, expand=True)")
        self.Float = Float
        self.relative = red["phi_o"] == "relative"
        self.n_lambda = table.values.shape[-1]   # channels: the wavelengths (or orders x wavelengths)
        self.block = block or self.n_lambda       # channels one lookup returns (eval's ``block``)
        self.phi_i = np.asarray(table.phi_i, float)
        self.theta_i = np.asarray(table.theta_i, float)
        self.shape = table.values.shape[:4]
        self.phi_o0 = float(table.phi_o_edges[0])
        self.theta_cells = Cells(table.theta_o_edges)
        self.theta_cells.upload(Float)
        self.u_edges = Float(np.sin(table.theta_o_edges).astype(np.float32))
        self.sin_nodes = Float(np.sin(self.theta_i).astype(np.float32))
        flat = lambda a: Float(np.ascontiguousarray(a, dtype=np.float32).ravel())  # noqa: E731
        self.values = flat(table.values)
        self.s_phi, self.s_u = (flat(a) for a in bin_slopes(table))
        self.nbytes = 3 * 4 * table.values.size   # float32 values and two slopes

    def eval(self, phi_i, theta_i, phi_o, theta_o, mode: str = "linear", block=None) -> list:
        """``S`` at every table wavelength (a list of arrays, one per channel of ``values``)
        for Dr.Jit arrays of angles; with ``block`` (a UInt32 array) the channels of that
        block of the table's ``block`` size per lane (a near-field table's offset cell)."""
        if mode not in ("nearest", "linear"):
            raise ValueError(f"lookup mode {mode!r}: use 'nearest' or 'linear'")
        if self.relative:
            phi_o = phi_o - phi_i
        reader = _Reader(self, mode == "nearest", dr.width(theta_o), block)
        cone_lookup(reader, phi_i, theta_i, phi_o, theta_o, reader.nearest, xp=dr)
        return reader.out


class _Reader:
    """One lookup's reader of an uploaded table for :func:`cone_lookup`, accumulating ``S``
    per wavelength in ``out`` (the numpy twin: ``models.bundle_table._NumpyReader``)."""

    def __init__(self, table: DrJitTable, nearest: bool, width: int, block=None):
        self.t, self.nearest = table, nearest
        self.phi_i, self.theta_i = table.phi_i, table.theta_i
        self.first = 0 if block is None else block * table.block   # the first channel read
        self.out = [dr.zeros(table.Float, width) for _ in range(table.n_lambda if block is None else table.block)]

    def sin_theta_i(self, b):
        return dr.gather(self.t.Float, self.t.sin_nodes, b)

    def read(self, a, b, phi, u, weight):
        """Add ``weight`` x node (a, b) at (phi, u): bin value plus the slopes' offsets."""
        t, Float = self.t, self.t.Float
        _, n_b, n_p, n_t = t.shape
        kp, kt, dp = cell_offsets(t.phi_o0, n_p, t.theta_cells, phi, u, xp=dr)
        base = (((a * n_b + b) * n_p + kp) * n_t + kt) * t.n_lambda + self.first
        active = weight != 0.0
        if not self.nearest:
            du = u - 0.5 * (dr.gather(Float, t.u_edges, kt, active) + dr.gather(Float, t.u_edges, kt + 1, active))
        for l in range(len(self.out)):
            v = dr.gather(Float, t.values, base + l, active)
            if not self.nearest:
                v = v + dr.gather(Float, t.s_phi, base + l, active) * dp + dr.gather(Float, t.s_u, base + l, active) * du
            self.out[l] = dr.fma(weight, v, self.out[l])
