"""The grids every table shares: node interpolation, cells (bins) and a cell's solid angle.

Written once for the whole project, for numpy (``xp=np``) and Dr.Jit (``xp=dr``): the
single-fiber tables (``models.fiber``), the baker's tallies (``models.bake``), the bundle
table's lookup (``models.bundle_table``) and the plugins' uploads (``mitsuba_ext``).

Two kinds of axis:

* **nodes** (``theta_i``, the fiber table's ``theta``, ``phi`` and wavelength): values
  live on the nodes and are read by linear interpolation (:func:`linear`);
* **cells** (the bundle table's ``phi_o`` and ``theta_o`` bins): ``n`` equal cells over a
  span, a value per cell (:func:`cell`). A cell is half open, ``[lo, hi)``: a point on an
  edge belongs to the cell above it.

A lookup reads a table at directions that a user or a renderer chose, and those are often
exactly on an edge (the specular cone at a ``theta_i`` node falls on a ``theta_o`` edge,
the forward direction ``phi_o - phi_i = pi`` on a ``phi_o`` edge). Whether the arithmetic
lands a hair below or above the edge then depends on the backend's trigonometry (numpy's
double, Dr.Jit's float32), so lookups pass ``tie=TIE``: a point within ``TIE`` cell widths
below an edge is read in the cell above, as the edge's own cell, on every backend. The
baker tallies random directions with ``tie=0``.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

# lookups: cells widths below an edge that still count as on it (float32 rounding of the
# angle is ~1e-6 cells; a direction chosen this near an edge is on it)
TIE = 1e-4


def _is_numpy(xp) -> bool:
    return xp is np


def _uint(xp, x):
    return xp.uint32_array_t(type(x))(x)


def linear(grid, x, periodic: bool = False, xp=np):
    """Indices and weights of linear interpolation on a sorted grid: ``(i0, i1, w)`` with
    ``value = (1 - w) v[i0] + w v[i1]``.

    Periodic grids are uniform over ``[grid[0], grid[0] + 2 pi)``; other grids clamp ``x``
    to their range (a constant extension at the ends) and may be graded (a bake's theta_i
    nodes, finer near grazing). numpy finds the interval by search (exactly ``w = 0`` on a
    node); Dr.Jit by arithmetic on uniform steps, else by :class:`Cells` of the nodes (the
    same to float32 rounding), and reads a NaN as ``grid[0]`` (it must not become an index).
    """
    grid = np.asarray(grid, np.float64)
    n = len(grid)
    if _is_numpy(xp):
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

    dr = xp
    Float = type(x)
    UInt = dr.uint32_array_t(Float)
    x = dr.select(dr.isfinite(x), x, float(grid[0]))
    if n == 1:
        zero = dr.zeros(UInt, dr.width(x))
        return zero, zero, dr.zeros(Float, dr.width(x))
    if periodic:
        t = (x - float(grid[0])) * float(1.0 / (2 * np.pi / n))
        t = t - dr.floor(t * (1.0 / n)) * n  # wrap into [0, n)
        i0f = dr.floor(t)
        i0 = UInt(dr.clip(i0f, 0, n - 1))
        return i0, dr.select(i0 + 1 >= n, 0, i0 + 1), t - i0f
    steps = np.diff(grid)
    if np.allclose(steps, steps[0], rtol=1e-6, atol=0):
        t = dr.clip((x - float(grid[0])) * float(1.0 / steps[0]), 0.0, float(n - 1))
        i0f = dr.minimum(dr.floor(t), float(n - 2))
        return UInt(i0f), UInt(i0f) + 1, t - i0f
    # graded nodes: the interval is the cell of x among the nodes, then its own step
    x = dr.clip(x, float(grid[0]), float(grid[-1]))
    i0 = Cells(grid).index(x, xp=dr)
    nodes = Float(grid.astype(np.float32))
    lo, hi = dr.gather(Float, nodes, i0), dr.gather(Float, nodes, i0 + 1)
    return i0, i0 + 1, dr.clip((x - lo) / (hi - lo), 0.0, 1.0)


def cell(x, lo: float, span: float, n: int, periodic: bool = False, tie: float = 0.0, xp=np):
    """``(k, t)``: the cell ``k`` of ``x`` among ``n`` equal cells over ``[lo, lo + span)``,
    and ``x``'s position ``t`` in cell units (``k <= t < k + 1`` inside the range).

    Periodic axes wrap ``x`` into the span first; others clamp ``k`` to the first and last
    cell. ``tie``: see the module docstring (0 for tallies, :data:`TIE` for lookups).
    """
    lo, span = float(lo), float(span)
    if periodic:
        x = x - span * xp.floor((x - lo) * (1.0 / span))
    t = (x - lo) * float(n / span)
    if periodic and tie:  # just below the end of the span: on the first edge
        t = (np.where if _is_numpy(xp) else xp.select)(t + tie >= n, t - n, t)
    if _is_numpy(xp):
        return np.clip(np.floor(t + tie), 0, n - 1).astype(np.int64), t
    return _uint(xp, xp.clip(xp.floor(t + tie) if tie else xp.floor(t), 0, n - 1)), t


def bin_solid_angle(phi_edges, theta_edges) -> np.ndarray:
    """Solid angle of each (phi, theta) bin, ``[n_phi, n_theta]``: ``d(phi) d(sin theta)``
    (theta measured from the normal plane, as every direction in the project)."""
    return np.outer(np.diff(np.asarray(phi_edges, np.float64)), np.diff(np.sin(np.asarray(theta_edges, np.float64))))


# ------------------------------------------------------------------------------
# Cells between any sorted edges, and the theta_o axis that follows the specular cone
# ------------------------------------------------------------------------------

def cone_nodes(nodes) -> np.ndarray:
    """The cones ``theta_o = -theta_i`` of a bake's ``theta_i`` nodes (radians), mirrored and
    with both poles: sorted, unique. ``nodes``: the nodes, or a step (nodes at its multiples)."""
    if np.ndim(nodes) == 0:
        period = float(nodes)
        P = int(round(np.pi / period))
        if P < 1 or abs(P * period - np.pi) > 1e-9:
            raise ValueError(f"a cone layout needs theta_i nodes that divide 180 deg (step {np.rad2deg(period):g} deg)")
        return -np.pi / 2 + period * np.arange(P + 1)
    t = np.abs(np.asarray(nodes, np.float64))
    if np.any(t > np.pi / 2 + 1e-9):
        raise ValueError("theta_i nodes must lie within +-90 deg")
    cones = np.concatenate([-t, t, [-np.pi / 2, np.pi / 2]])
    cones = np.sort(np.clip(cones, -np.pi / 2, np.pi / 2))
    return cones[np.concatenate([[True], np.diff(cones) > 1e-9])]


def cone_edges(nodes, cone_bin: float, coarse_per_gap: int = 1) -> np.ndarray:
    """``theta_o`` edges (radians) that follow the specular cone of parallel fibers.

    Light from ``theta_i`` leaves on the cone ``theta_o = -theta_i``, a ridge as wide as the
    fiber's longitudinal lobe. Every cone of the bake's ``theta_i`` nodes (:func:`cone_nodes`:
    ``nodes`` are the nodes, or a step for nodes at its multiples) gets a bin of width
    ``cone_bin`` centred on it, and each gap between two cones ``coarse_per_gap`` equal bins.
    At the poles (+-90 deg, the grazing nodes, whose cone has no width) the half cone bin
    joins its neighbour. The lookup reads every node at the same offset from its own cone
    (``models.bundle_table.cone_lookup``), so at and between nodes the cone's light sits in
    the middle of a narrow bin instead of on the edge of two wide ones. ``G (coarse_per_gap
    + 1) - 1`` bins for ``G`` gaps between cones (``pi / step`` for equal steps); symmetric
    about 0 (the theta mirror maps bins onto bins).
    """
    cones = cone_nodes(nodes)
    gaps = np.diff(cones)
    if not 0.0 < cone_bin < gaps.min():
        raise ValueError(f"the cone bin ({np.rad2deg(cone_bin):g} deg) must be narrower than the narrowest gap "
                         f"between theta_i nodes ({np.rad2deg(gaps.min()):g} deg)")
    if coarse_per_gap < 1:
        raise ValueError(f"a cone layout needs at least one bin between two cones (got {coarse_per_gap})")
    G = len(gaps)
    edges = [-np.pi / 2]
    for k in range(G):  # the gap between cones k and k + 1, its cone bins' halves cut off
        lo, hi = cones[k] + cone_bin / 2, cones[k + 1] - cone_bin / 2
        inner = list(np.linspace(lo, hi, coarse_per_gap + 1))
        edges += inner[(0 if k else 1):(len(inner) if k < G - 1 else -1)]
    edges.append(np.pi / 2)
    return np.array(edges)


def cone_bin_counts(nodes, max_count: int = 3600) -> list:
    """The bin counts a cone layout can have for these ``theta_i`` nodes (or this step)."""
    G = len(cone_nodes(nodes)) - 1
    return [G * (m + 1) - 1 for m in range(1, max_count // G + 1) if G * (m + 1) - 1 <= max_count]


class Cells:
    """The cells between sorted ``edges`` (half open, ``[lo, hi)``, the outer ones clamped),
    for numpy and Dr.Jit.

    Equal cells are found by arithmetic (:func:`cell`). Others by a lookup grid: ``x``'s
    slot among slots of half the narrowest cell holds the cell of the slot's start, then
    comparisons with the neighbouring edges correct it (a slot holds at most one edge;
    two comparisons each way also absorb float32 rounding of the slot index): a few
    gathers, the same on both backends.
    """

    def __init__(self, edges):
        self.edges = np.asarray(edges, np.float64)
        self.n = len(self.edges) - 1
        widths = np.diff(self.edges)
        if self.n < 1 or np.any(widths <= 0):
            raise ValueError("cell edges must be increasing")
        self.lo, self.span = float(self.edges[0]), float(self.edges[-1] - self.edges[0])
        self.min_width = float(widths.min())
        self.uniform = bool(np.ptp(widths) <= 1e-9 * self.span)
        self.slot = self.min_width / 2
        n_slots = int(np.ceil(self.span / self.slot)) + 1
        starts = self.lo + self.slot * np.arange(n_slots)
        self.lut = np.clip(np.searchsorted(self.edges, starts, side="right") - 1, 0, self.n - 1)
        self._uploads = {}

    def index(self, x, tie: float = 0.0, xp=np):
        """The cell of ``x``; ``tie``: as :func:`cell`, in units of the narrowest cell. A NaN
        reads as the first cell (it must not become an index)."""
        if self.uniform:
            return cell(x, self.lo, self.span, self.n, tie=tie, xp=xp)[0]
        if _is_numpy(xp):
            edges, lut, select = self.edges, self.lut, np.where
            take, to_index = (lambda a, i: a[i]), (lambda v: v.astype(np.int64))
        else:
            edges, lut = self.upload(type(x))
            select, to_index = xp.select, xp.uint32_array_t(type(x))
            take = lambda a, i: xp.gather(type(a), a, i)  # noqa: E731
        x = select(xp.isfinite(x), x + tie * self.min_width, self.lo)
        k = take(lut, to_index(xp.clip(xp.floor((x - self.lo) * float(1.0 / self.slot)), 0, len(self.lut) - 1)))
        for _ in range(2):
            k = select((x < take(edges, k)) & (k > 0), k - 1, k)
            k = select((x >= take(edges, k + 1)) & (k < self.n - 1), k + 1, k)
        return k

    def __getstate__(self):  # Dask ships specs to its workers: without the uploads
        return {k: v for k, v in self.__dict__.items() if k != "_uploads"} | {"_uploads": {}}

    def upload(self, Float):
        """The edges and the lookup grid as Dr.Jit arrays of ``Float``'s backend (once)."""

        key = Float.__name__ + Float.__module__
        if key not in self._uploads:
            self._uploads[key] = (Float(self.edges.astype(np.float32)),
                                  dr.uint32_array_t(Float)(self.lut.astype(np.uint32)))
        return self._uploads[key]
