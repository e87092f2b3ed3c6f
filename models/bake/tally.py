"""What a bake tabulates and what it sums: :class:`BakeSpec` and :class:`Tally`.

A bake is a list of batches whose tallies add (in a fixed order, so that a sharded bake
is the serial one bit for bit); ``pipeline.stages.bake`` turns the sum into a
:class:`~models.bundle_table.BundleTable`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..grid import Cells, bin_solid_angle, cell

# exit models: where scattered light leaves a fiber (models.bake.baker)
EXITS = ("uniform", "entry", "lobe", "curve")
# estimators (models.bake.baker; camera: models.bake.camera)
ESTIMATORS = ("fast", "thesis", "camera")
MAX_ORDERS = 64
MAX_OFFSETS = 64


@dataclass
class BakeSpec:
    """What to tabulate and how. Angles in radians, wavelengths from the fiber table."""

    theta_i: np.ndarray                # incident longitudes (nodes)
    phi_i: np.ndarray                  # incident azimuths (nodes)
    n_theta_o: int = 36                # bins over [-pi/2, pi/2]
    n_phi_o: int = 72                  # bins over [-pi, pi)
    relative_phi: bool = True          # tabulate phi_o - phi_i (rotation-invariant bundles)
    estimator: str = "fast"
    max_bounces: int = 1000
    rr_start: int = 8                  # fast: Russian roulette from this bounce on
    exit: str = "uniform"              # where scattered light leaves a fiber (module docstring)
    # theta_o bin edges (radians); None: n_theta_o equal bins (other layouts: models.grid.cone_edges)
    theta_o_edges: np.ndarray | None = None
    # the orders of scattering kept apart (dye, docs/DESIGN.md "Order-resolved tables"):
    # 0 none; K >= 2: paths of k = 1 .. K-1 fiber events each, and the tail k >= K
    orders: int = 0
    # the near field (docs/DESIGN.md "Near-field tables"): 0 none; N >= 2 cells of the exit
    # offset h_o in [-1, 1] (the escaping ray's line's signed distance from the ply axis over
    # the bounding radius), and the passthrough per entry offset
    offsets: int = 0

    def __post_init__(self):
        self.theta_i = np.atleast_1d(np.asarray(self.theta_i, dtype=np.float64))
        self.phi_i = np.atleast_1d(np.asarray(self.phi_i, dtype=np.float64))
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator {self.estimator!r}: use one of {', '.join(ESTIMATORS)}")
        if self.estimator == "camera" and (self.exit != "curve" or self.orders or self.offsets):
            raise ValueError("the camera estimator traces the curve exit's table from the camera (exit 'curve'), "
                             "without orders or offsets")
        if self.exit not in EXITS:
            raise ValueError(f"exit {self.exit!r}: use one of {', '.join(EXITS)}")
        if self.exit != "uniform" and self.estimator == "thesis":
            raise ValueError(f"exit {self.exit!r} needs the fast estimator (the thesis baseline leaves uniformly)")
        if self.orders and not 2 <= self.orders <= MAX_ORDERS:
            raise ValueError(f"orders: 0 (none) or 2 .. {MAX_ORDERS} (got {self.orders})")
        if self.orders and self.estimator != "fast":
            raise ValueError("orders need the fast estimator")
        if self.offsets and not 2 <= self.offsets <= MAX_OFFSETS:
            raise ValueError(f"offsets: 0 (none) or 2 .. {MAX_OFFSETS} cells (got {self.offsets})")
        if self.offsets and (self.estimator != "fast" or not self.relative_phi or self.orders):
            raise ValueError("offsets need the fast estimator and a circular ply, without orders")
        if self.max_bounces < 1:
            raise ValueError(f"the bounce cap must be at least 1 (got {self.max_bounces})")
        if np.any(np.abs(self.theta_i) > np.pi / 2):
            raise ValueError("theta_i must lie in [-pi/2, pi/2] radians")
        if self.theta_o_edges is None:
            self.theta_o_edges = np.linspace(-np.pi / 2, np.pi / 2, self.n_theta_o + 1)
        self.theta_o_edges = np.asarray(self.theta_o_edges, np.float64)
        self.n_theta_o = len(self.theta_o_edges) - 1
        if abs(self.theta_o_edges[0] + np.pi / 2) > 1e-12 or abs(self.theta_o_edges[-1] - np.pi / 2) > 1e-12:
            raise ValueError("theta_o bins must span [-pi/2, pi/2]")
        self.theta_cells = Cells(self.theta_o_edges)

    @property
    def phi_o_edges(self):
        return np.linspace(-np.pi, np.pi, self.n_phi_o + 1)

    def bin_solid_angle(self):
        """Solid angle of each (phi_o, theta_o) bin: [n_phi_o, n_theta_o]."""
        return bin_solid_angle(self.phi_o_edges, self.theta_o_edges)


@dataclass
class Tally:
    """Running sums of one bake; adding two tallies merges batches.

    ``paths`` and ``passthrough`` count every path of an incident azimuth; a path of the
    parallel bake carries every ``theta_i`` at once, one of the twisted bake a single
    one, so the counts per ``theta_i`` node are kept too (``paths_theta``,
    ``passthrough_theta``): the passthrough of a twisted ply depends on ``theta_i``.
    ``single`` is the part of ``sum`` (over every output bin) that left after exactly one
    fiber event: the singly scattered light.

    With ``BakeSpec.orders = K`` the escaping weight is also kept by its number of fiber
    events ``k``: ``orders[o]`` (``sum``'s layout) holds the paths of ``k = o + 1`` for
    ``o < K - 1``, the last one every ``k >= K`` (the tail), ``orders_sq`` their squares,
    and ``tail_excess`` the tail's weight times ``k - K`` over every bin, per (phi_i,
    theta_i, lambda): its mean order, from which the table's tail ratio follows.

    With ``BakeSpec.offsets = N`` the escaping weight is also kept by the cell of its exit
    offset ``h_o`` (``near``, ``near_sq``; ``sum``'s layout after a leading cell axis), and
    the paths and passthrough by the cell of their entry offset (``paths_h``,
    ``passthrough_h``, [phi_i, theta_i, N]).

    The camera estimator (``models.bake.camera``) traces paths from the camera, each in one
    output bin: ``sum`` then holds each bin's estimates of ``S`` times the bin's solid angle,
    ``bin_paths`` [phi_i, theta_i, phi_o, theta_o] the paths each bin's sums are over.
    """

    sum: np.ndarray        # [phi_i, theta_i, phi_o, theta_o, lambda]
    sum_sq: np.ndarray
    absorbed: np.ndarray   # [phi_i, theta_i, lambda]
    lost: np.ndarray
    paths: np.ndarray      # [phi_i] paths launched (entering the bounding width)
    passthrough: np.ndarray  # [phi_i]
    paths_theta: np.ndarray  # [phi_i, theta_i] paths that carried each theta_i
    passthrough_theta: np.ndarray  # [phi_i, theta_i]
    single: np.ndarray     # [phi_i, theta_i, lambda]
    vertices: int = 0
    extra: dict = field(default_factory=dict)
    orders: np.ndarray | None = None       # [K, phi_i, theta_i, phi_o, theta_o, lambda]
    orders_sq: np.ndarray | None = None
    tail_excess: np.ndarray | None = None  # [phi_i, theta_i, lambda]
    near: np.ndarray | None = None         # [N, phi_i, theta_i, phi_o, theta_o, lambda]
    near_sq: np.ndarray | None = None
    paths_h: np.ndarray | None = None      # [phi_i, theta_i, N]
    passthrough_h: np.ndarray | None = None
    bin_paths: np.ndarray | None = None    # [phi_i, theta_i, phi_o, theta_o]: the camera estimator's paths per bin

    SUMS = ("sum", "sum_sq", "absorbed", "lost", "paths", "passthrough", "paths_theta", "passthrough_theta",
            "single")
    ORDER_SUMS = ("orders", "orders_sq", "tail_excess")
    NEAR_SUMS = ("near", "near_sq", "paths_h", "passthrough_h")
    CAMERA_SUMS = ("bin_paths",)

    @classmethod
    def zeros(cls, spec: BakeSpec, n_lambda: int):
        shape = (len(spec.phi_i), len(spec.theta_i))
        bins = shape + (spec.n_phi_o, spec.n_theta_o, n_lambda)
        orders = {}
        if spec.orders:
            orders = {"orders": np.zeros((spec.orders,) + bins), "orders_sq": np.zeros((spec.orders,) + bins),
                      "tail_excess": np.zeros(shape + (n_lambda,))}
        if spec.offsets:
            N = spec.offsets
            orders |= {"near": np.zeros((N,) + bins), "near_sq": np.zeros((N,) + bins),
                       "paths_h": np.zeros(shape + (N,)), "passthrough_h": np.zeros(shape + (N,))}
        if spec.estimator == "camera":
            orders["bin_paths"] = np.zeros(shape + (spec.n_phi_o, spec.n_theta_o))
        return cls(np.zeros(bins), np.zeros(bins),
                   np.zeros(shape + (n_lambda,)), np.zeros(shape + (n_lambda,)),
                   np.zeros(len(spec.phi_i)), np.zeros(len(spec.phi_i)), np.zeros(shape), np.zeros(shape),
                   np.zeros(shape + (n_lambda,)), **orders)

    def _present(self) -> tuple:
        return (self.SUMS + (self.ORDER_SUMS if self.orders is not None else ())
                + (self.NEAR_SUMS if self.near is not None else ())
                + (self.CAMERA_SUMS if self.bin_paths is not None else ()))

    def count(self, phi_index: int, n_paths: int, passed: int) -> None:
        """Paths launched and passed through at azimuth ``phi_index``, each carrying every theta_i."""
        self.paths[phi_index] += n_paths
        self.passthrough[phi_index] += passed
        self.paths_theta[phi_index] += n_paths
        self.passthrough_theta[phi_index] += passed

    def add(self, other: "Tally") -> None:
        if ((self.orders is None) != (other.orders is None) or (self.near is None) != (other.near is None)
                or (self.bin_paths is None) != (other.bin_paths is None)):
            raise ValueError("tallies of other resolutions (orders, offsets) or estimators do not add")
        for name in self._present():
            getattr(self, name).__iadd__(getattr(other, name))
        self.vertices += other.vertices

    def arrays(self) -> dict:
        return {k: getattr(self, k) for k in self._present()} | {"vertices": np.array(self.vertices)}

    @classmethod
    def from_arrays(cls, a) -> "Tally":
        names = a.files if hasattr(a, "files") else a.keys()
        return cls(*(np.array(a[k]) for k in cls.SUMS), int(a["vertices"]),
                   **{k: np.array(a[k]) for k in cls.ORDER_SUMS + cls.NEAR_SUMS + cls.CAMERA_SUMS if k in names})

    def add_orders(self, phi_index: int, order, flat_bin, theta_index, W) -> None:
        """Tally escaped paths by order: ``order`` their fiber events ``k`` (>= 1), ``flat_bin``
        their output bins (``output_bin``), ``theta_index`` their theta_i nodes and ``W``
        their weights [path, lambda] (numpy, float64 sums)."""
        K, n_ti = len(self.orders), self.orders.shape[2]
        _add_split(self.orders, self.orders_sq, phi_index, np.minimum(order, K) - 1, flat_bin, theta_index, W)
        excess = np.maximum(order - K, 0).astype(np.float64)
        for l in range(W.shape[1]):
            self.tail_excess[phi_index, :, l] += np.bincount(theta_index, W[:, l] * excess, n_ti)

    def add_offsets(self, phi_index: int, cell, flat_bin, theta_index, W) -> None:
        """Tally escaped paths by the cell of their exit offset (``offset_cell``), as
        :meth:`add_orders` by order."""
        _add_split(self.near, self.near_sq, phi_index, cell, flat_bin, theta_index, W)


def _add_split(sums, squares, phi_index, part, flat_bin, theta_index, W) -> None:
    """Add weights ``W`` [path, lambda] to ``sums[part, phi_index, theta_index, bin]`` (and
    their squares): float64 sums, one ``bincount`` per wavelength."""
    K, (n_ti, n_p, n_t, L) = len(sums), sums.shape[2:]
    flat = (part * n_ti + theta_index) * (n_p * n_t) + flat_bin
    size = K * n_ti * n_p * n_t
    for l in range(L):
        w = W[:, l]
        sums[:, phi_index, ..., l] += np.bincount(flat, w, size).reshape(K, n_ti, n_p, n_t)
        squares[:, phi_index, ..., l] += np.bincount(flat, w * w, size).reshape(K, n_ti, n_p, n_t)


def line_offset(x, z, phi, radius: float, xp=np):
    """``h = (x sin(phi) - z cos(phi)) / radius``: the signed distance from the ply axis of
    the line through ``(x, z)`` along azimuth ``phi``, over the radius (numpy or Dr.Jit; the
    plugin takes the camera ray's line the same way, ``mitsuba_ext.frame.line_offset``)."""
    return (x * xp.sin(phi) - z * xp.cos(phi)) * (1.0 / radius)


def cell_of_offset(h, n_cells: int, xp=np):
    """The cell of ``h`` in [-1, 1] among ``n_cells`` equal cells (ends clamped)."""
    c = xp.clip(xp.floor((h + 1.0) * (0.5 * n_cells)), 0, n_cells - 1)
    return c.astype(np.int64) if xp is np else xp.uint32_array_t(type(c))(c)


def offset_cell(n_cells: int, ox, oz, phi, bounding_radius: float, xp=np):
    """The offset cell of a ray from ``(x, z)`` along azimuth ``phi`` (the near-field tally)."""
    return cell_of_offset(line_offset(ox, oz, phi, bounding_radius, xp), n_cells, xp)


def output_bin(spec: BakeSpec, phi, theta, phi_i, xp=np, start=None, bounding_radius: float = 1.0):
    """The output bin (flat ``phi_o x theta_o`` index) of light leaving along azimuth ``phi``
    at longitude ``theta``, for a path that arrived from ``phi_i`` (numpy or Dr.Jit). With
    ``spec.offsets``, the cell of the escaping ray's line (from ``start = (x, z)``) rides
    above the bins, ``cell * n_bins + bin`` (:func:`split_bins` takes it apart)."""
    phi_rel = phi - phi_i if spec.relative_phi else phi
    a, _ = cell(phi_rel, -np.pi, 2 * np.pi, spec.n_phi_o, periodic=True, xp=xp)
    b = spec.theta_cells.index(theta, xp=xp)
    out = a * spec.n_theta_o + b
    if spec.offsets:
        out = out + offset_cell(spec.offsets, start[0], start[1], phi, bounding_radius, xp) * (
            spec.n_phi_o * spec.n_theta_o)
    return out


def split_bins(spec: BakeSpec, bins):
    """``(cells, bins)`` of :func:`output_bin`'s indices (``cells`` None without offsets)."""
    if not spec.offsets:
        return None, bins
    return np.divmod(bins, spec.n_phi_o * spec.n_theta_o)
