"""The baked bundle scattering function: one self-describing ``.npz`` per bake.

``S(phi_i, theta_i, phi_o, theta_o, lambda)`` in 1/sr, normalized over the rays that
enter the bundle's bounding width ``2 R_b``: a bin's value is its summed path weight
over (rays x bin solid angle). With ``P_pass(phi_i)`` (rays touching no fiber; per
``(phi_i, theta_i)`` in ``passthrough_theta`` where it depends on ``theta_i``, as for a
twisted ply),
``absorbed`` and ``lost`` (weight dropped at the bounce cap), per (phi_i, theta_i,
lambda)::

    sum_bins S * solid_angle + P_pass + absorbed + lost = 1

``single`` (optional; tables baked before 2026-12-03 have none) is the part of the
scattered light ``sum_bins S * solid_angle`` that left after exactly one fiber event, per
(phi_i, theta_i, lambda): in a dyed yarn the blue light that leaves at all leaves after
one fiber, the red after many (docs/BENCHMARKS.md, "Cloth").

``orders`` (optional: ``bake.orders: K``) resolves ``S`` by the number of fiber events of
its paths, ``S = sum_k S_k``: ``orders[k - 1]`` is ``S_k`` for ``k = 1 .. K-1`` and
``orders[K - 1]`` the tail ``T = sum_{k >= K} S_k``, with its standard errors
(``orders_stderr``) and the tail's ratio ``rho`` per (phi_i, theta_i, lambda)
(``tail_ratio``). A fiber whose every event keeps a fraction ``a(lambda)`` of this fiber's
scattering (a dye) has the table ``S_a = sum_{k<K} a^k S_k + a^K T (1 - rho) / (1 - a rho)``:
exact but for the tail, which is taken as a geometric series of the ratio its mean order
gives (:meth:`BundleTable.recolour`; docs/DESIGN.md, "Order-resolved tables").

Axes and bins (radians, nm):

=============  =================================================================
``phi_i``      incident azimuth nodes (one node 0 for a circle: rotation reduced)
``theta_i``    incident longitude nodes (>= 0 when the mirror reduction is used)
``phi_o``      bins with ``phi_o_edges`` over [-pi, pi); ``phi_o - phi_i`` when
               ``meta["reductions"]["phi_o"] == "relative"``
``theta_o``    bins with ``theta_o_edges`` over [-pi/2, pi/2]: equal, or a narrow bin on
               every node's specular cone (``models.grid.cone_edges``)
``lambda``     the fiber table's wavelengths
=============  =================================================================

Reductions (``meta["reductions"]``): ``theta_i: "mirror"`` (S(-ti, -to) = S(ti, to),
parallel untilted fibers), ``phi_i: "rotation"`` (circle), ``"mirror_xz"`` (ellipse:
phi_i in [0, 90 deg], its x and z mirrors) or ``"half_turns"`` (twisted ellipse: phi_i in
[0, 90 deg], the half turns about y, and about x and z with theta flipped),
``phi_o: "relative" | "absolute"``. :meth:`BundleTable.expanded` undoes the theta and
ellipse reductions.

Example::

    from models.bundle_table import BundleTable
    t = BundleTable.load("artifacts/default/bake/bundle_table.npz", expand=True)
    t.values.shape   # (phi_i, theta_i, phi_o, theta_o, lambda)
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field

import numpy as np

from .grid import TIE, Cells, bin_solid_angle, cell, linear
from .io import atomic_path, check_axis
from .queries import check_albedo, directions

FORMAT = "bcsdf.bundle_table/2"  # /2: values and stderr stored in half precision (see BundleTable.save)
READABLE = ("bcsdf.bundle_table/1", FORMAT)  # /1: float32, read as before
HALF = ("values", "stderr")  # the arrays stored in half precision
HALF_TOP = 2.0**15  # a stored array's largest value after its power-of-two scale (float16's largest: 65504)
MAX_VALUE = 1e20   # 1/sr: far beyond any physical lobe, far below float32's 3.4e38
REDUCTIONS = {"theta_i": (None, "mirror"), "phi_i": (None, "rotation", "mirror_xz", "half_turns"),
              "phi_o": ("relative", "absolute")}
PHI_I_FOLDS = ("mirror_xz", "half_turns")  # the phi_i reductions that BundleTable.expanded unfolds


def needs_expanding(reductions: dict) -> bool:
    """Whether a table of these reductions must be expanded before a lookup reads it."""
    return reductions.get("theta_i") == "mirror" or reductions.get("phi_i") in PHI_I_FOLDS
ARRAYS = ("values", "stderr", "passthrough", "passthrough_stderr", "absorbed", "lost",
          "phi_i", "theta_i", "phi_o_edges", "theta_o_edges", "wavelength")
ORDER_ARRAYS = ("orders", "orders_stderr")  # stored in half precision, a scale per order
NEAR_ARRAYS = ("near", "near_stderr")       # the same, a scale per offset cell
SPLIT = ORDER_ARRAYS + NEAR_ARRAYS          # S split along a leading axis
OPTIONAL = ("passthrough_theta", "single") + SPLIT + ("tail_ratio", "near_passthrough")


def tail_factor(a, rho):
    """``sum_j (a rho)^j / sum_j rho^j = (1 - rho) / (1 - a rho)``: what a per-event albedo
    ``a`` leaves of a tail whose orders fall geometrically by ``rho`` (beyond its first
    order's ``a^K``)."""
    return (1 - rho) / (1 - a * rho)


def dyed(orders, a, rho):
    """``sum_{k<K} a^k S_k + a^K T (1 - rho) / (1 - a rho)``: the scattering of a fiber dyed
    with per-event albedo ``a`` from the orders ``[S_1, .., S_{K-1}, T]`` of the undyed one
    and the tail's ratio ``rho`` (:func:`tail_factor`). Any arithmetic: numpy arrays (the
    table's :meth:`BundleTable.recolour`), Dr.Jit arrays (a neural model's orders), Mitsuba
    spectra (the plugin's dye per hit)."""
    value, power = 0.0, 1.0
    for S_k in orders[:-1]:
        power = power * a
        value = value + power * S_k
    return value + power * a * tail_factor(a, rho) * orders[-1]


@dataclass
class BundleTable:
    values: np.ndarray              # [phi_i, theta_i, phi_o, theta_o, lambda] float32, 1/sr
    stderr: np.ndarray              # same shape: standard error of each value
    passthrough: np.ndarray         # [phi_i]
    passthrough_stderr: np.ndarray  # [phi_i]
    absorbed: np.ndarray            # [phi_i, theta_i, lambda]
    lost: np.ndarray                # [phi_i, theta_i, lambda]
    phi_i: np.ndarray
    theta_i: np.ndarray
    phi_o_edges: np.ndarray
    theta_o_edges: np.ndarray
    wavelength: np.ndarray
    meta: dict = field(default_factory=dict)
    # [phi_i, theta_i]: where the passthrough depends on theta_i (twisted plies); then
    # ``passthrough`` is its mean over theta_i
    passthrough_theta: np.ndarray | None = None
    single: np.ndarray | None = None  # [phi_i, theta_i, lambda]: scattered after one fiber event
    orders: np.ndarray | None = None         # [K, phi_i, theta_i, phi_o, theta_o, lambda]: S by fiber events
    orders_stderr: np.ndarray | None = None  # same shape
    tail_ratio: np.ndarray | None = None     # [phi_i, theta_i, lambda]: rho of the tail k >= K
    near: np.ndarray | None = None           # [N, phi_i, theta_i, phi_o, theta_o, lambda]: S by exit offset
    near_stderr: np.ndarray | None = None
    near_passthrough: np.ndarray | None = None  # [phi_i, theta_i, N]: P_pass by entry offset

    # -- derived axes --------------------------------------------------------
    @property
    def phi_o(self):
        return 0.5 * (self.phi_o_edges[1:] + self.phi_o_edges[:-1])

    @property
    def theta_o(self):
        return 0.5 * (self.theta_o_edges[1:] + self.theta_o_edges[:-1])

    @property
    def solid_angle(self):
        """[phi_o, theta_o] solid angle of each output bin."""
        return bin_solid_angle(self.phi_o_edges, self.theta_o_edges)

    @property
    def scattered(self):
        """``integral S d omega_o`` per (phi_i, theta_i, lambda)."""
        return np.einsum("abpql,pq->abl", self.values.astype(np.float64), self.solid_angle)

    def single_share(self) -> np.ndarray | None:
        """Of all the scattered light (every incidence), the share that left after one fiber
        event, per wavelength; ``None`` for a table without ``single``."""
        if self.single is None:
            return None
        return self.single.sum(axis=(0, 1)) / np.maximum(self.scattered.sum(axis=(0, 1)), 1e-300)

    def passthrough_at_nodes(self) -> np.ndarray:
        """``P_pass`` per (phi_i, theta_i) node: [phi_i, theta_i]."""
        if self.passthrough_theta is not None:
            return self.passthrough_theta
        return np.broadcast_to(self.passthrough[:, None], self.absorbed.shape[:2])

    def energy_balance(self) -> dict:
        """Scattered, passthrough, absorbed, lost, and their total, per (phi_i, theta_i, lambda)."""
        p = np.broadcast_to(self.passthrough_at_nodes()[:, :, None], self.absorbed.shape)
        s = self.scattered
        return {"scattered": s, "passthrough": p, "absorbed": self.absorbed, "lost": self.lost,
                "total": s + p + self.absorbed + self.lost}

    # -- storage -------------------------------------------------------------
    def save(self, path) -> None:
        """Write the table; ``values`` and ``stderr`` in half precision.

        Each of the two is stored as float16 times a power of two that puts its largest
        value at :data:`HALF_TOP`: a relative rounding of at most 2^-11 (0.05%) down to
        2^-24 of the largest value (then fewer digits, and 0 below 2^-39 of it), against a
        bake's Monte Carlo error of a few percent per bin. It halves the file
        (docs/BENCHMARKS.md, "The highlight"); :meth:`load` returns float32 arrays either way.
        """
        arrays = {k: getattr(self, k) for k in ARRAYS}
        scales = {}
        for name in HALF:
            arrays[name], scales[name] = to_half(arrays[name])
        for name in ("passthrough_theta", "single", "tail_ratio", "near_passthrough"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        for name in SPLIT:  # each order (offset cell) its own scale: the orders fall by decades
            if getattr(self, name) is not None:
                halves = [to_half(o) for o in getattr(self, name)]
                arrays[name] = np.stack([h for h, _ in halves])
                scales[name] = [c for _, c in halves]
        header = {"format": FORMAT, "meta": self.meta, "half_scale": scales}
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, header=np.array(json.dumps(header)), **arrays)

    @classmethod
    def load(cls, path, expand: bool = False) -> "BundleTable":
        """Read a bundle table; ``expand=True`` undoes the theta_i and ellipse reductions."""
        try:
            with np.load(path, allow_pickle=False) as z:
                header = json.loads(str(z["header"]))
                if header.get("format") not in READABLE:
                    raise ValueError(f"format {header.get('format')!r}, expected one of {READABLE}")
                arrays = {k: z[k] for k in ARRAYS}
                if header["format"] != READABLE[0]:
                    for name in HALF:
                        arrays[name] = from_half(arrays[name], header["half_scale"][name])
                optional = {k: z[k] if k in z.files else None
                            for k in ("passthrough_theta", "single", "tail_ratio", "near_passthrough")}
                for name in SPLIT:
                    if name in z.files:
                        optional[name] = np.stack([from_half(h, c) for h, c in
                                                   zip(z[name], header["half_scale"][name], strict=True)])
                table = cls(**arrays, meta=header["meta"], **optional)
            table.validate()
            if expand:  # expanded for a lookup
                table.check_lookup()
        except (OSError, KeyError, ValueError, json.JSONDecodeError, zipfile.BadZipFile) as e:
            raise ValueError(f"{path}: not a readable bundle table ({e}); re-run `bcsdf bake`") from e
        return table.expanded() if expand else table

    def validate(self) -> None:
        check_axis(self.phi_i, "phi_i", -2 * np.pi, 2 * np.pi)
        check_axis(self.theta_i, "theta_i", -np.pi / 2, np.pi / 2)
        check_axis(self.phi_o_edges, "phi_o_edges", span=2 * np.pi)
        check_axis(self.theta_o_edges, "theta_o_edges", -np.pi / 2, np.pi / 2, span=np.pi)
        check_axis(self.wavelength, "wavelength", 1.0, 1e5)
        shape = (len(self.phi_i), len(self.theta_i), len(self.phi_o_edges) - 1,
                 len(self.theta_o_edges) - 1, len(self.wavelength))
        if self.values.shape != shape or self.stderr.shape != shape:
            raise ValueError(f"values have shape {self.values.shape}, the axes give {shape}")
        optional = tuple((name, want) for name, want in (("passthrough_theta", shape[:2]),
                                                         ("single", shape[:2] + shape[4:]))
                         if getattr(self, name) is not None)
        for name, want in (("passthrough", shape[:1]), ("passthrough_stderr", shape[:1]),
                           ("absorbed", shape[:2] + shape[4:]), ("lost", shape[:2] + shape[4:])) + optional:
            if np.shape(getattr(self, name)) != want:
                raise ValueError(f"{name} has shape {np.shape(getattr(self, name))}, the axes give {want}")
        for name in ("values", "stderr", "passthrough", "passthrough_stderr", "absorbed", "lost") + \
                tuple(n for n, _ in optional):
            a = getattr(self, name)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} holds NaN or Inf")
            # a lossless fiber's albedo is 1 within float error, so its "absorbed" may be -1e-9
            if np.any(a < (0 if name in ("values", "stderr") else -1e-6)):
                raise ValueError(f"{name} holds negative numbers (S, probabilities and errors are never negative)")
        if np.any(self.values > MAX_VALUE):
            raise ValueError(f"values reach {float(self.values.max()):.3g} /sr (at most {MAX_VALUE:.0e}: a "
                             "renderer's weights would overflow float32)")
        # a table of camera transport (the adjoint Mitsuba renders of its hair) scatters more light
        # than arrives towards grazing incidence: its singly scattered light is no probability
        adjoint = self.meta.get("transport") == "camera"
        for name in ("passthrough", "absorbed", "lost") + tuple(n for n, _ in optional if not (adjoint and n == "single")):
            if np.any(getattr(self, name) > 1 + 1e-6):
                raise ValueError(f"{name} reaches {float(np.max(getattr(self, name))):.4g}; a probability is at most 1")
        if self.single is not None and np.any(self.single > self.scattered * (1 + 1e-4) + 1e-6):
            raise ValueError("single exceeds the scattered light it is a part of")
        # the orders of scattering (tail ratio in [0, 1)) and the near field (passthrough per cell)
        self._validate_split(ORDER_ARRAYS, "tail_ratio", lambda s, n: s[:2] + s[4:], lambda r: (r >= 0) & (r < 1),
                             "order-resolved")
        self._validate_split(NEAR_ARRAYS, "near_passthrough", lambda s, n: s[:2] + (n,), lambda p: (p >= 0) & (p <= 1),
                             "near-field")
        reductions = self.meta.get("reductions", {"phi_o": "relative"})
        for key, allowed in REDUCTIONS.items():
            if reductions.get(key) not in allowed:
                raise ValueError(f"meta.reductions.{key}: {reductions.get(key)!r} is not one of {allowed}")
        if reductions.get("theta_i") == "mirror" and not np.allclose(self.theta_o_edges, -self.theta_o_edges[::-1],
                                                                     atol=1e-9):
            raise ValueError("theta_o_edges are not symmetric about 0, which the theta_i mirror reduction needs")

    def _validate_split(self, names, extra: str, extra_shape, extra_ok, what: str) -> None:
        """A split of S along a leading axis (``names``: values and errors) and its ``extra``
        array: all present or none, shapes from the axes, finite and non-negative."""
        present = [getattr(self, n) is not None for n in names + (extra,)]
        if not any(present):
            return
        if not all(present):
            raise ValueError(f"{', '.join(names)} and {extra} come together (a torn {what} table)")
        shape = self.values.shape
        n = len(getattr(self, names[0]))
        for name in names:
            a = getattr(self, name)
            if a.shape != (n,) + shape or n < 2:
                raise ValueError(f"{name} has shape {a.shape}, the axes give (>= 2,) + {shape}")
            if not np.all(np.isfinite(a)) or np.any(a < 0):
                raise ValueError(f"{name} holds NaN, Inf or negative numbers")
        a, want = getattr(self, extra), extra_shape(shape, n)
        if a.shape != want or not np.all(extra_ok(a)):
            raise ValueError(f"{extra} must have shape {want} and lie in its range (got {a.shape})")

    def order(self, k: int) -> "BundleTable":
        """The table of order ``k`` alone (``1 .. K-1``; ``K``: the tail), without orders."""
        K = 0 if self.orders is None else len(self.orders)
        if not 1 <= k <= K:
            raise ValueError(f"order {k}: this table holds orders 1 .. {K}")
        return self._replace(values=self.orders[k - 1], stderr=self.orders_stderr[k - 1], orders=None,
                             orders_stderr=None, tail_ratio=None, single=None)

    def redrawn(self, rng) -> "BundleTable":
        """One draw of the bake's own noise: a table another seed might have baked, each bin
        drawn from a normal distribution about its value with its standard error (held at 0
        from below), the errors kept. A near-field or order-resolved table draws its cells or
        orders, and its values are their sum, as a bake's are. The spread of a figure over
        such draws is the table's noise in that figure: a draw differs from the table as the
        table differs from its expectation. ``single`` is dropped (a draw's scattered light
        may fall below it); ``rng``: a ``numpy.random.Generator``."""

        def draw(values, stderr):
            return np.maximum(values + stderr * rng.standard_normal(values.shape), 0.0).astype(np.float32)

        for parts, errors in (("near", "near_stderr"), ("orders", "orders_stderr")):
            if getattr(self, parts) is not None:
                split = draw(getattr(self, parts), getattr(self, errors))
                return self._replace(**{parts: split, "values": split.sum(axis=0), "single": None})
        return self._replace(values=draw(self.values, self.stderr), single=None)

    def recolour(self, albedo) -> "BundleTable":
        """The table of a dyed fiber: every fiber event keeps a fraction ``albedo`` of this
        table's fiber's scattering (a number, or one per wavelength, in [0, 1]).

        ``S_a = sum_{k<K} a^k S_k + a^K T (1 - rho) / (1 - a rho)``; the standard errors
        combine per order (a path belongs to one order, so ``sum a^2k se_k^2`` bounds the
        variance from above); ``single`` scales by ``a``, the light lost at the bounce cap as
        the tail, and ``absorbed`` takes what the dye removes, so the balance stays closed.
        The result has no orders (it is one dye's table).
        """
        if self.orders is None:
            raise ValueError("this table has no orders of scattering to recolour: bake it with `bake.orders: K` "
                             "(e.g. 8) in the config")
        a = check_albedo(albedo, len(self.wavelength))
        K = len(self.orders)
        power = a[None, :] ** np.arange(1, K)[:, None]                   # [K - 1, lambda]
        tail = a**K * tail_factor(a, self.tail_ratio)                     # [phi_i, theta_i, lambda]
        o, e = self.orders.astype(np.float64), self.orders_stderr.astype(np.float64)
        values = dyed(list(o), a, self.tail_ratio[:, :, None, None, :])
        var = np.einsum("kabpql,kl->abpql", e[:-1] ** 2, power**2) + (e[-1] * tail[:, :, None, None, :]) ** 2
        out = self._replace(values=values.astype(np.float32), stderr=np.sqrt(var).astype(np.float32),
                            single=None if self.single is None else self.single * a,
                            orders=None, orders_stderr=None, tail_ratio=None, near=None, near_stderr=None,
                            near_passthrough=None, meta=dict(self.meta, albedo=a.tolist()))
        total = self.energy_balance()["total"]
        out.lost = self.lost * tail  # paths stopped at the cap made more than K events
        out.absorbed = np.maximum(total - out.energy_balance()["passthrough"] - out.scattered - out.lost, 0.0)
        return out

    def check_lookup(self) -> None:
        """What the lookups (numpy and Dr.Jit) assume beyond :meth:`validate`: equal steps in
        phi (``phi_i`` nodes, ``phi_o`` bins); ``theta_i`` nodes may be graded and ``theta_o``
        bins unequal."""
        for name in ("phi_o_edges",) + (("phi_i",) if len(self.phi_i) > 1 else ()):
            step = np.diff(np.asarray(getattr(self, name), float))
            if len(step) and np.ptp(step) > 1e-6 * max(1.0, float(np.abs(step).max())):
                raise ValueError(f"axis {name}: steps {step.min():.6g} .. {step.max():.6g}; the lookup needs equal steps")

    # -- symmetry ------------------------------------------------------------
    def expanded(self) -> "BundleTable":
        """Undo ``theta_i: mirror`` and ``phi_i: mirror_xz``; rotation stays reduced."""
        red = self.meta.get("reductions", {})
        if self.near is not None and red.get("phi_i") in PHI_I_FOLDS:
            raise ValueError("a near-field table of a folded ply: the offset's sign turns with the mirrors (not "
                             "supported; near-field tables are baked for circular plies)")
        if (self.orders is not None or self.near is not None) and needs_expanding(red):
            # each order or offset cell (and the tail ratio, carried as ``absorbed``) as a table of its own;
            # the theta mirror keeps the offset (it mirrors along the axis, not across it)
            bare = {name: None for name in SPLIT + ("tail_ratio",)}
            t = self._replace(**bare).expanded()
            out = {}
            for values, errors, ratio in ((ORDER_ARRAYS + ("tail_ratio",)), (NEAR_ARRAYS + (None,))):
                if getattr(self, values) is None:
                    continue
                carried = getattr(self, ratio) if ratio else self.absorbed
                parts = [self._replace(values=v, stderr=e, absorbed=carried, **bare).expanded()
                         for v, e in zip(getattr(self, values), getattr(self, errors))]
                out |= {values: np.stack([p.values for p in parts]), errors: np.stack([p.stderr for p in parts])}
                if ratio:
                    out[ratio] = parts[0].absorbed
            return t._replace(**out)
        t = self
        red = dict(self.meta.get("reductions", {}))
        if red.get("theta_i") == "mirror":
            t = t._mirror_theta()
            red["theta_i"] = None
        if red.get("phi_i") in PHI_I_FOLDS:
            t = t._mirror_phi(twisted=red["phi_i"] == "half_turns")
            red["phi_i"] = None
        t.meta = dict(t.meta, reductions=red)
        return t

    def _replace(self, **kw):
        data = {k: getattr(self, k) for k in ARRAYS + OPTIONAL} | {"meta": dict(self.meta)}
        data.update(kw)
        return BundleTable(**data)

    def _mirror_theta(self):
        # S(-ti, to) = S(ti, -to): flip the theta_o bins (edges are symmetric)
        pos = self.theta_i > 0
        order = np.argsort(np.concatenate([-self.theta_i[pos][::-1], self.theta_i]))
        cat = lambda a, axis, flip=None: np.concatenate(  # noqa: E731
            [np.flip(np.take(a, np.where(pos)[0][::-1], axis=axis), flip) if flip is not None
             else np.take(a, np.where(pos)[0][::-1], axis=axis), a], axis=axis)
        return self._replace(
            theta_i=np.concatenate([-self.theta_i[pos][::-1], self.theta_i])[order],
            values=cat(self.values, 1, 3), stderr=cat(self.stderr, 1, 3),
            absorbed=cat(self.absorbed, 1), lost=cat(self.lost, 1),
            single=None if self.single is None else cat(self.single, 1),
            passthrough_theta=None if self.passthrough_theta is None else cat(self.passthrough_theta, 1),
            near_passthrough=None if self.near_passthrough is None else cat(self.near_passthrough, 1))

    def _mirror_phi(self, twisted: bool = False):
        """Ellipse: from phi_i in [0, pi/2] to [0, 2 pi) by its symmetries.

        A symmetry ``T`` of the bundle (``phi -> -phi``, ``pi - phi``, ``phi + pi``) maps it
        onto itself, so ``S(T phi_i, phi_o) = S(phi_i, T^-1 phi_o)``; with uniform phi_o bins
        of even count, ``T^-1`` maps bin centres to centres. A parallel ellipse has the x and
        z mirrors (theta unchanged). A twisted one is chiral: its symmetries are the half
        turns about y (``phi + pi``), z (``pi - phi``) and x (``-phi``), the last two
        flipping theta (``theta_i`` and ``theta_o`` both, which needs symmetric nodes and edges).
        """
        n = len(self.phi_o_edges) - 1
        step = 2 * np.pi / n
        mirrors = [(lambda p: p, lambda p: p, False), (lambda p: np.pi - p, lambda p: np.pi - p, twisted),
                   (lambda p: np.pi + p, lambda p: p - np.pi, False), (lambda p: -p, lambda p: -p, twisted)]
        if twisted and not (np.allclose(self.theta_i, -self.theta_i[::-1], atol=1e-9)
                            and np.allclose(self.theta_o_edges, -self.theta_o_edges[::-1], atol=1e-9)):
            raise ValueError("half_turns reduction: the theta_i nodes and theta_o edges must be symmetric about 0")
        rows = {}
        for forward, inverse, flip in mirrors:
            source_bin = np.floor(np.mod(inverse(self.phi_o) + np.pi, 2 * np.pi) / step).astype(int) % n
            for a, p in enumerate(self.phi_i):
                q = round(float(np.mod(forward(p), 2 * np.pi)), 12)
                rows.setdefault(q, (a, source_bin, flip))

        def pick(arr, per_bin, theta_axes=(0,)):
            out = []
            for q in phis:
                a, source_bin, flip = rows[q]
                v = arr[a][:, source_bin] if per_bin else arr[a]
                out.append(np.flip(v, theta_axes) if flip and theta_axes else v)
            return np.stack(out)

        phis = sorted(rows)
        return self._replace(phi_i=np.array(phis), values=pick(self.values, True, (0, 2)),
                             stderr=pick(self.stderr, True, (0, 2)),
                             absorbed=pick(self.absorbed, False), lost=pick(self.lost, False),
                             single=None if self.single is None else pick(self.single, False),
                             passthrough=pick(self.passthrough, False, ()),
                             passthrough_stderr=pick(self.passthrough_stderr, False, ()),
                             passthrough_theta=None if self.passthrough_theta is None
                             else pick(self.passthrough_theta, False))


# ------------------------------------------------------------------------------
# Lookup: along the specular cone, bin-average preserving (the Dr.Jit twin is mitsuba_ext/table.py)
# ------------------------------------------------------------------------------
#
# A bin's value is the average of S over the bin (per solid angle), and parallel fibers
# put their light on the cone theta_o = -theta_i, a ridge one or two bins wide. So:
#
# * within a bin, S is the bin value plus limited slopes in phi_o and in u = sin(theta_o)
#   (minmod of the neighbours' differences: never negative, never beyond a neighbour),
#   centred so that the bin's average is its value exactly (u is uniform in solid angle);
# * between theta_i nodes, each node is read at the same distance from its own cone,
#   measured in u (the cone is u_o = -u_i): u_o + u_i - u_i[node], and the two are
#   blended: the ridge moves with the cone instead of fading between two ridges. A shift
#   in u moves each node's energy unchanged (d omega = du d phi), so the albedo between
#   nodes is the nodes' blend (but for light shifted past a pole, which is dropped);
#   azimuths phi_i blend linearly.
#
# ``nearest`` reads the bin value of the nearest node (no slopes), along the cone too.

def to_half(a: np.ndarray) -> tuple[np.ndarray, float]:
    """``(h, scale)``: ``a`` (>= 0) as float16 ``h`` with ``a ~ h * scale``, ``scale`` the power
    of two that puts ``a``'s largest finite value at :data:`HALF_TOP` (NaN and Inf stay what
    they are, for the loader to refuse by name)."""
    a = np.asarray(a, np.float64)
    finite = a[np.isfinite(a)]
    top = float(finite.max()) if finite.size else 0.0
    scale = 2.0 ** int(np.ceil(np.log2(top / HALF_TOP))) if top > 0 else 1.0
    return (a / scale).astype(np.float16), scale


def from_half(h: np.ndarray, scale: float) -> np.ndarray:
    """The float32 array that :func:`to_half` stored (a power-of-two scale: exact)."""
    if h.dtype != np.float16:
        raise ValueError(f"a half-precision array holds {h.dtype}")
    return h.astype(np.float32) * np.float32(scale)


def minmod(a, b):
    """The smaller of two slopes of one sign, else zero (the classic slope limiter)."""
    return np.where(a * b > 0, np.sign(a) * np.minimum(np.abs(a), np.abs(b)), 0.0)


def bin_slopes(table: BundleTable) -> tuple[np.ndarray, np.ndarray]:
    """Limited slopes of S per bin in ``phi_o`` (per radian) and in ``u = sin(theta_o)``.

    Shapes as ``values``; ``phi_o`` is periodic, the first and last ``theta_o`` bins are flat.
    Computed in float64 one ``theta_i`` node at a time: a near-field table's channels are
    tens of MB, and whole-table float64 temporaries would cost a dozen times that.
    """
    s_phi, s_u = (np.zeros(table.values.shape, np.float32) for _ in range(2))
    u = np.sin(table.theta_o_edges)
    uc = 0.5 * (u[1:] + u[:-1])
    d_phi = 2 * np.pi / table.values.shape[2]
    for b in range(table.values.shape[1]):
        v = table.values[:, b].astype(np.float64)            # [phi_i, phi_o, theta_o, channel]
        s_phi[:, b] = minmod(np.roll(v, -1, 1) - v, v - np.roll(v, 1, 1)) / d_phi
        diff = np.diff(v, axis=2) / np.diff(uc)[:, None]
        s_u[:, b, :, 1:-1] = minmod(diff[:, :, 1:], diff[:, :, :-1])
    return s_phi, s_u


def node_corners(grid, x, periodic: bool, nearest: bool, xp=np) -> list:
    """``[(index, weight), ...]``: the nodes of ``grid`` that a lookup at ``x`` blends."""
    i0, i1, w = linear(grid, x, periodic=periodic, xp=xp)
    if len(grid) == 1:
        return [(i0, w * 0 + 1)]
    if nearest:
        return [(xp.where(w < 0.5, i0, i1) if xp is np else xp.select(w < 0.5, i0, i1), w * 0 + 1)]
    return [(i0, 1 - w), (i1, w)]


def cone_lookup(reader, phi_i, theta_i, phi_o, theta_o, nearest: bool, xp=np):
    """The lookup along the specular cone (the comment above), for numpy and Dr.Jit.

    ``reader`` holds the table on its backend: ``phi_i`` and ``theta_i`` (node grids),
    ``sin_theta_i(b)`` (the sine of node ``b``) and ``read(a, b, phi, u, weight)``, which
    adds ``weight`` x node ``(a, b)``'s reconstruction at ``(phi_o, sin theta_o) = (phi, u)``
    to its output (zero weights read nothing).
    """
    select = np.where if xp is np else xp.select
    half_pi = float(np.pi / 2)
    theta_i = xp.clip(theta_i, -half_pi, half_pi)
    u, sin_i = xp.sin(theta_o), xp.sin(theta_i)
    # the theta_i nodes and their cones' shifts are the same for every phi_i node
    corners = node_corners(reader.theta_i, theta_i, False, nearest, xp)
    shifts = [sin_i - reader.sin_theta_i(b) for b, _ in corners]
    # light shifted past a pole comes back over it at phi + pi. A lane near the lower pole
    # takes it from the node below (shift >= 0), near the upper pole from the node above
    # (shift <= 0): one read per lane, not one per node
    (b0, w0), (b1, w1) = corners[0], corners[-1]
    s0, s1 = shifts[0], shifts[-1]
    lower = u < 0.0
    s_pole = select(lower, s0, s1)
    back = select(lower, (s0 > 0) & (u <= s0 - 1.0), (s1 < 0) & (u >= 1.0 + s1))
    u_back = select(lower, -2.0 - u + s_pole, 2.0 - u + s_pole)
    b_back, w_back = select(lower, b0, b1), select(lower, w0, w1)
    for a, wa in node_corners(reader.phi_i, phi_i, True, nearest, xp):
        # each node read at the same distance from its own cone, in u = sin(theta_o) ...
        for (b, wb), s in zip(corners, shifts):
            reader.read(a, b, phi_o, u + s, select(xp.abs(u + s) <= 1.0, wa * wb, 0.0))
        # ... and the light it shifted past a pole
        reader.read(a, b_back, phi_o + float(np.pi), u_back, select(back, wa * w_back, 0.0))


def cell_offsets(phi_o0, n_phi, theta_cells: Cells, phi, u, xp=np):
    """``(kp, kt, dp)``: the output cell of ``(phi, u = sin theta_o)`` in ``phi_o`` and
    ``theta_o`` (``theta_cells``: :class:`~models.grid.Cells` of the ``theta_o`` edges), and
    the offset from the cell's centre in ``phi`` that the limited slope multiplies (a
    reader takes the offset in ``u`` from its own ``theta_o`` edges)."""
    kp, t = cell(phi, phi_o0, 2 * np.pi, n_phi, periodic=True, tie=TIE, xp=xp)
    kt = theta_cells.index(xp.arcsin(xp.clip(u, -1.0, 1.0)) if xp is np else xp.safe_asin(xp.clip(u, -1.0, 1.0)),
                           tie=TIE, xp=xp)
    dp = (t - kp - 0.5) * float(2 * np.pi / n_phi)
    return kp, kt, dp


def lookup(table: BundleTable, phi_i, theta_i, phi_o, theta_o, mode: str = "linear", slopes=None) -> np.ndarray:
    """``S`` at arbitrary directions (radians, broadcast), all wavelengths: [..., n_lambda].

    The table must be expanded (``BundleTable.load(..., expand=True)``); relative tables
    take ``phi_o - phi_i`` on their output axis. ``slopes``: :func:`bin_slopes`, if
    already computed. The Dr.Jit twin of the reader is ``mitsuba_ext.table.DrJitTable``;
    the algorithm is :func:`cone_lookup`, shared.
    """
    reductions = table.meta.get("reductions", {})
    if needs_expanding(reductions):
        raise ValueError("lookup needs an expanded table: BundleTable.load(path, expand=True)")
    if mode not in ("nearest", "linear"):
        raise ValueError(f"lookup mode {mode!r}: use 'nearest' or 'linear'")
    phi_i, theta_i, phi_o, theta_o = directions(phi_i, theta_i, phi_o, theta_o)  # checked: radians, finite
    if reductions["phi_o"] == "relative":
        phi_o = phi_o - phi_i
    reader = _NumpyReader(table, mode == "nearest", slopes, phi_i.shape)
    cone_lookup(reader, phi_i, theta_i, phi_o, theta_o, reader.nearest)
    return reader.out


class _NumpyReader:
    """The table in numpy for :func:`cone_lookup`, accumulating ``S`` in ``out`` (the Dr.Jit
    twin: ``mitsuba_ext.table._Reader``)."""

    def __init__(self, table: BundleTable, nearest: bool, slopes, shape):
        self.table, self.nearest = table, nearest
        self.phi_i, self.theta_i = table.phi_i, table.theta_i
        self.s_phi, self.s_u = (None, None) if nearest else (slopes or bin_slopes(table))
        self.n_p, self.theta_cells = len(table.phi_o_edges) - 1, Cells(table.theta_o_edges)
        self.u_edges = np.sin(table.theta_o_edges)
        self.out = np.zeros(shape + (len(table.wavelength),))

    def sin_theta_i(self, b):
        return np.sin(self.theta_i[b])

    def read(self, a, b, phi, u, weight):
        if not np.any(weight):
            return
        kp, kt, dp = cell_offsets(self.table.phi_o_edges[0], self.n_p, self.theta_cells, phi, u)
        value = self.table.values[a, b, kp, kt].astype(np.float64)
        if not self.nearest:
            du = u - 0.5 * (self.u_edges[kt] + self.u_edges[kt + 1])
            value = value + self.s_phi[a, b, kp, kt] * dp[..., None] + self.s_u[a, b, kp, kt] * du[..., None]
        self.out += weight[..., None] * value
