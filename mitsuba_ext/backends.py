"""The three ways the ``fiber_bundle`` BSDF evaluates ``S``: table, ONNX, jitted MLP.

Each backend answers the same three questions for Dr.Jit arrays of bundle-frame
angles (radians):

* ``eval(phi_i, theta_i, phi_o, theta_o)`` -> list of ``n_lambda`` arrays, ``S`` in 1/sr;
* ``passthrough(phi_i, theta_i)`` -> the probability that a ray crosses the bundle untouched;
* ``sampling_grid(Float)`` -> a :class:`~mitsuba_ext.sampling.DirectionGrid` to
  importance-sample outgoing directions;

and hold ``single_share``: per wavelength, the share of the scattered light that left the
bake's ply after one fiber event (``None`` where the table or model has none).

The table backend samples from its own bins. The neural backends have no table at
render time: they tabulate their own output on a coarse grid when the BSDF is built
(a few tens of thousands of evaluations), so sampling follows the model itself.
"""

from __future__ import annotations

import copy
import os

import drjit as dr
import numpy as np

from mitsuba_ext.neural import DrJitMLP, OnnxMLP
from mitsuba_ext.sampling import DirectionGrid
from mitsuba_ext.table import DrJitTable
from models.bake.tally import cell_of_offset
from models.bundle_table import BundleTable, dyed
from models.grid import bin_solid_angle, linear
from models.jit import to_drjit
from models.neural import between, bracketed, far_field, order_channels

BACKENDS = ("table", "mlp", "onnx")


def _periodic_linear(Float, values, nodes, phi):
    """Periodic linear interpolation of ``values`` at uniform ``nodes`` (radians)."""
    i0, i1, w = linear(np.asarray(nodes, float), phi, periodic=True, xp=dr)
    arr = Float(np.asarray(values, np.float32))
    return dr.lerp(dr.gather(Float, arr, i0), dr.gather(Float, arr, i1), w)


def passthrough_at(Float, values, phi_nodes, phi_i, theta_i, per_theta=None, theta_nodes=None):
    """``P_pass(phi_i)`` (``values`` per ``phi_nodes``, periodic), or, where it depends on
    theta_i (``per_theta[phi, theta]`` at ``theta_nodes``, a twisted ply), ``P_pass(phi_i,
    theta_i)``: bilinear, periodic in phi_i and held constant beyond the theta_i nodes."""
    if per_theta is None:
        return _periodic_linear(Float, values, phi_nodes, phi_i)
    per_theta = np.asarray(per_theta, np.float32)
    n_t = per_theta.shape[1]
    a0, a1, wa = linear(np.asarray(phi_nodes, float), phi_i, periodic=True, xp=dr)
    b0, b1, wb = linear(np.asarray(theta_nodes, float), theta_i, xp=dr)
    arr = Float(per_theta.ravel())
    out = dr.zeros(Float, dr.width(theta_i))
    for a, w_a in ((a0, 1 - wa), (a1, wa)):
        for b, w_b in ((b0, 1 - wb), (b1, wb)):
            out = dr.fma(w_a * w_b, dr.gather(Float, arr, a * n_t + b), out)
    return out


def tail_ratio_at(Float, rho, phi_nodes, theta_nodes, phi_i, theta_i) -> list:
    """The tail's ratio ``rho [phi node, theta node, lambda]`` of an order-resolved table or
    model at the incident direction, a list over wavelengths, bilinear as :func:`passthrough_at`."""
    rho = np.asarray(rho, float)
    return [passthrough_at(Float, None, phi_nodes, phi_i, theta_i, rho[..., l], theta_nodes)
            for l in range(rho.shape[-1])]


def _cell_passthrough(Float, values, theta_nodes, theta_i, cell, n_cells: int):
    """``values [theta node, cell]`` (flat, of type ``Float``) at ``theta_i``, linear between
    the nodes (held beyond them), in offset cell ``cell``: the passthrough by entry cell."""
    b0, b1, w = linear(np.asarray(theta_nodes, float), theta_i, xp=dr)
    return dr.lerp(dr.gather(Float, values, b0 * n_cells + cell), dr.gather(Float, values, b1 * n_cells + cell), w)


class TableBackend:
    """Lookup of an expanded bundle table: along the specular cone, bin averages kept
    (``linear``), or the nearest node's bin (``nearest``)."""

    name = "table"
    constants = ()  # a table holds the one ply it was baked for: no inputs beyond the directions

    def __init__(self, table_path, Float, lookup: str = "linear", dye=None, near_field: bool = True):
        if lookup not in ("linear", "nearest"):
            raise ValueError(f"fiber_bundle: lookup {lookup!r}; use 'linear' (default) or 'nearest'")
        self.Float = Float
        self.table = BundleTable.load(table_path, expand=True)
        if dye is not None:  # a uniform dye: the order-resolved table recoloured once, at load
            try:
                self.table = self.table.recolour(dye(self.table.wavelength))
            except ValueError as e:
                raise ValueError(f"fiber_bundle: 'albedo' with {table_path}: {e}") from None
        self.lookup = lookup
        self.dj = DrJitTable(self.table, Float)
        self.wavelength = np.asarray(self.table.wavelength, float)
        self.relative = self.dj.relative
        self.nbytes = self.dj.nbytes
        self.single_share = self.table.single_share()
        self.orders = None   # upload_orders: the orders of scattering, for a dye that varies over the shape
        self.near = None     # the near field, where the table holds it (eval_near, passthrough_near)
        if near_field and self.table.near is not None:
            t, N = self.table, len(self.table.near)
            self.near = self._channels(t.near)
            self.n_cells = N
            self.near_passthrough = Float(np.asarray(t.near_passthrough[0], np.float32).ravel())  # a circle: one phi_i
            self.nbytes += self.near.nbytes

    def _channels(self, split) -> DrJitTable:
        """A split of the table along a leading axis (orders, offset cells) uploaded as one
        lookup of ``parts x n_lambda`` channels: the cells and weights shared, each part with
        its own slopes; a lookup reads them all or one part (``block``)."""
        L = len(self.table.wavelength)
        channels = np.moveaxis(split, 0, -2).reshape(self.table.values.shape[:4] + (len(split) * L,))
        return DrJitTable(self.table._replace(values=channels, stderr=channels), self.Float, block=L)

    def offset_cell(self, h):
        """The near-field cell of an offset ``h`` in [-1, 1], as the bake tallies it."""
        return cell_of_offset(h, self.n_cells, dr)

    def eval_near(self, phi_i, theta_i, phi_o, theta_o, h):
        """``S_h``: the light leaving along ``phi_o, theta_o`` on the line at offset ``h``."""
        return self.near.eval(phi_i, theta_i, phi_o, theta_o, mode=self.lookup, block=self.offset_cell(h))

    def passthrough_near(self, theta_i, h):
        """``P_pass`` of a ray entering on the line at offset ``h`` (its direction of travel's),
        linear between the theta_i nodes (a twisted ply's depends on them)."""
        return _cell_passthrough(self.Float, self.near_passthrough, self.table.theta_i, theta_i,
                                 self.offset_cell(h), self.n_cells)

    def upload_orders(self):
        """Upload the table's orders as one lookup of ``K x n_lambda`` channels (the cells
        and weights are shared; each order keeps its own slopes), for a dye applied per hit
        (:meth:`eval_orders`)."""
        t = self.table
        if t.orders is None:
            raise ValueError("fiber_bundle: an 'albedo' texture recolours an order-resolved table: bake it with "
                             "`bake.orders: K` (e.g. 8) in the config")
        self.orders = self._channels(t.orders)
        self.nbytes += self.orders.nbytes

    def eval_orders(self, phi_i, theta_i, phi_o, theta_o):
        """``(S_k, rho)``: the orders ``S_1 .. S_{K-1}``, the tail ``T`` (each a list over the
        table's wavelengths) and the tail's ratio (a list over them, bilinear in the
        incident direction's nodes)."""
        t, L = self.table, len(self.table.wavelength)
        flat = self.orders.eval(phi_i, theta_i, phi_o, theta_o, mode=self.lookup)
        orders = [flat[k * L:(k + 1) * L] for k in range(len(t.orders))]
        return orders, tail_ratio_at(self.Float, t.tail_ratio, t.phi_i, t.theta_i, phi_i, theta_i)

    def eval(self, phi_i, theta_i, phi_o, theta_o):
        return self.dj.eval(phi_i, theta_i, phi_o, theta_o, mode=self.lookup)

    def passthrough(self, phi_i, theta_i):
        t = self.table
        return passthrough_at(self.Float, t.passthrough, t.phi_i, phi_i, theta_i, t.passthrough_theta, t.theta_i)

    def sampling_grid(self, uniform: float):
        t = self.table
        mass = t.values.mean(-1, dtype=np.float64) * t.solid_angle  # energy per bin
        return DirectionGrid(mass, t.phi_i, t.theta_i, t.phi_o_edges, t.theta_o_edges,
                             self.relative, self.Float, uniform)

    def camera_grid(self, uniform: float):
        """The proposal of a near-field table in radiance mode: conditioned on the camera side
        ``w_c`` (its ``theta_o`` bin) and its line's offset cell, a distribution over the light
        side ``w_l``, i.e. the table transposed: ``S_c(w_l -> w_c)`` over cells of ``phi_l -
        phi_c`` (the table's ``phi_o - phi_i`` negated) and of ``theta_l`` about its nodes."""
        t = self.table
        edges = np.concatenate([[-np.pi / 2], 0.5 * (t.theta_i[1:] + t.theta_i[:-1]), [np.pi / 2]])
        # [cell, theta_l node, dphi bin, theta_c bin] -> [1, theta_c, cell, -dphi bin, theta_l]
        S = t.near[:, 0].mean(-1, dtype=np.float64)
        mass = np.transpose(S[:, :, ::-1, :], (3, 0, 2, 1))[None]
        mass = mass * bin_solid_angle(t.phi_o_edges, edges)[None, None, None]
        return DirectionGrid(mass, np.zeros(1), t.theta_o, t.phi_o_edges, edges, True, self.Float, uniform)


class _NeuralBackend:
    """Shared by the two neural backends: metadata, passthrough, self-tabulated sampling.

    A model with an ``offset`` input (``train.inputs: [offset]``) holds the near field:
    :meth:`eval_near` feeds it the camera ray's line offset, :meth:`eval` is its far field
    (its mean over the offset cells' midpoints, :func:`models.neural.far_field`; the
    sampling grid is tabulated from it), and a ray passes with the passthrough of its entry
    cell. ``near_field=False`` reads such a model as its far field everywhere."""

    near = None   # True where the model holds the near field and it is used
    constants = ()  # the values of the inputs that hold for the whole shape (a family's packing)
    # a family's per-packing data as read: at a uniform packing the two nodes around it alone
    # (models.neural.bracketed; every node would cost a spectrum of segments each), per lane all
    nodes = None
    albedo = None   # a uniform dye: the per-event albedo at the model's wavelengths (set_dye)

    def _init_spec(self, spec, Float, near_field: bool = True, packing: float | None = None):
        if not spec.passthrough:
            raise ValueError("this model was exported without its passthrough probability; "
                             "re-run `bcsdf train` and `bcsdf export`")
        self.Float = Float
        self.spec = spec
        if "packing" in spec.inputs:
            lo, hi = spec.input_range["packing"]
            if packing is None:
                raise ValueError(f"fiber_bundle: this model takes the ply's packing fraction (trained on {lo:g} .. "
                                 f"{hi:g}); give 'packing'")
            self.set_packing(packing)
        elif packing is not None:
            raise ValueError("fiber_bundle: 'packing' is an input of a model trained on a family of bakes "
                             "(train.inputs: [packing], python -m pipeline.bench.packing); this model holds one ply")
        self.wavelength = np.asarray(spec.wavelength, float)
        self.relative = spec.relative_phi
        self.single_share = np.asarray(spec.single_share, float) if spec.single_share else None
        self.n_cells = spec.offset_cells
        self.near = True if near_field and "offset" in spec.inputs else None
        if self.near and spec.passthrough_offset:
            self.near_passthrough = Float(np.asarray(spec.passthrough_offset, np.float32).ravel())

    def check_packing(self, packing: float) -> float:
        """``packing`` within the range the family's model was trained on (it does not
        extrapolate), or a ``ValueError`` that says so; compared in float32, the precision of
        a Mitsuba parameter."""
        lo, hi = self.spec.input_range["packing"]
        if not np.float32(lo) <= np.float32(packing) <= np.float32(hi):
            raise ValueError(f"fiber_bundle: packing {packing:g} lies outside {lo:g} .. {hi:g}, the range this model "
                             "was trained on; a model does not extrapolate: bake and train a family that covers it")
        return float(np.clip(packing, lo, hi))

    def set_packing(self, packing: float) -> None:
        """Evaluate a family's model at ``packing`` everywhere (:meth:`check_packing`)."""
        # opaque: an evaluated input of the kernel, not a literal compiled into it
        packing = self.check_packing(packing)
        self.constants = (dr.opaque(self.Float, packing),)
        self.nodes = bracketed(self.spec, packing)

    def at_packing(self, packing):
        """This backend read at ``packing``, a Dr.Jit array with one value per lane (a
        texture's, per hit; clamped to the trained range: the texture was checked at load)."""
        lo, hi = self.spec.input_range["packing"]
        view = copy.copy(self)
        view.constants = (dr.clip(packing, lo, hi),)
        view.nodes = self.spec
        return view

    def _per_packing(self, at_node):
        """A family's quantity at this backend's packing (per lane), linear between its values
        at the packing nodes read (:attr:`nodes`), ``at_node(k)`` (a Dr.Jit array or a list of
        them) for the ``k``-th of them."""
        values = [at_node(k) for k in range(len(self.nodes.packings))]
        p, nodes = self.constants[0], self.nodes.packings
        if isinstance(values[0], list):
            return [between(dr.clip, p, nodes, [v[l] for v in values], False) for l in range(len(values[0]))]
        return between(dr.clip, p, nodes, values, False)

    def set_dye(self, dye) -> None:
        """Dye a model of orders of scattering (``train.orders``): ``dye`` a function of the
        model's wavelengths giving the per-event albedo (applied at every evaluation), or a
        texture (the plugin applies it per hit through :meth:`eval_orders`)."""
        if not self.spec.orders:
            raise ValueError(f"fiber_bundle: 'albedo' dyes a table or model that keeps the orders of scattering "
                             f"apart; this model ({self.name}) holds the one dye it was trained on: train it with "
                             "`train.orders: true` on a bake with `bake.orders: K`")
        if callable(dye):
            self.albedo = [float(a) for a in dye(self.wavelength)]

    def eval_orders(self, phi_i, theta_i, phi_o, theta_o):
        """``(S_k, rho)``: the model's orders ``S_1 .. S_{K-1}``, its tail ``T`` (each a list over
        the model's wavelengths) and the tail's ratio (a list over them, bilinear in the
        incident direction's nodes), as :meth:`TableBackend.eval_orders`."""
        s = self.spec
        orders = order_channels(s, self._eval(phi_i, theta_i, phi_o, theta_o, orders=True))
        rho = lambda values: tail_ratio_at(self.Float, values, s.passthrough_phi_i, s.tail_ratio_theta_i,  # noqa: E731
                                           phi_i, theta_i)
        if "packing" in s.inputs:
            return orders, self._per_packing(lambda k: rho(self.nodes.tail_ratio[k]))
        return orders, rho(s.tail_ratio)

    def eval(self, phi_i, theta_i, phi_o, theta_o):
        """The far field: the model itself, or its mean over the offset; dyed with a uniform dye."""
        if self.albedo is not None:
            orders, rho = self.eval_orders(phi_i, theta_i, phi_o, theta_o)
            return [dyed([S_k[l] for S_k in orders], a, rho[l]) for l, a in enumerate(self.albedo)]
        return far_field(self._eval, self.spec)(phi_i, theta_i, phi_o, theta_o)

    def eval_near(self, phi_i, theta_i, phi_o, theta_o, h):
        """``S_h``: the light leaving along ``phi_o, theta_o`` on the line at offset ``h``."""
        return self._eval(phi_i, theta_i, phi_o, theta_o, h)

    def offset_cell(self, h):
        return cell_of_offset(h, self.n_cells, dr)

    def passthrough_near(self, theta_i, h):
        """``P_pass`` of a ray entering on the line at offset ``h``: its entry cell's, linear
        between the theta_i nodes (the far field's where the model has none per cell)."""
        if not self.spec.passthrough_offset:
            return self.passthrough(dr.zeros(self.Float, dr.width(theta_i)), theta_i)
        return _cell_passthrough(self.Float, self.near_passthrough, self.spec.passthrough_offset_theta_i, theta_i,
                                 self.offset_cell(h), self.n_cells)

    def camera_grid(self, uniform: float):
        return None  # the far field's proposal (a model has no table to transpose)

    def passthrough(self, phi_i, theta_i):
        s = self.spec
        if "packing" in s.inputs:   # a family's: linear between its packing nodes
            return self._per_packing(lambda k: passthrough_at(self.Float, self.nodes.passthrough_packing[k],
                                                              s.passthrough_phi_i, phi_i, theta_i))
        return passthrough_at(self.Float, s.passthrough, s.passthrough_phi_i, phi_i, theta_i,
                              s.passthrough_theta or None, s.passthrough_theta_i)

    def sampling_grid(self, uniform: float, n_phi: int = 72, n_theta: int = 36, n_theta_i: int = 37):
        """Tabulate the model's mean over wavelengths at cell centres (2 x 2 per cell)."""
        phi_i = np.asarray(self.spec.passthrough_phi_i if not self.relative else [0.0], float)
        theta_i = np.linspace(-np.pi / 2, np.pi / 2, n_theta_i)
        phi_edges = np.linspace(-np.pi, np.pi, n_phi + 1)
        theta_edges = np.linspace(-np.pi / 2, np.pi / 2, n_theta + 1)
        sub = np.array([0.25, 0.75])
        po = (phi_edges[:-1, None] + sub[None, :] * np.diff(phi_edges)[:, None]).ravel()
        to = (theta_edges[:-1, None] + sub[None, :] * np.diff(theta_edges)[:, None]).ravel()
        PI, TI, PO, TO = np.meshgrid(phi_i, theta_i, po, to, indexing="ij")
        absolute_po = PO + (PI if self.relative else 0.0)
        S = self.eval(*(to_drjit(self.Float, a.ravel()) for a in (PI, TI, absolute_po, TO)))
        dr.eval(*S)  # one kernel for all wavelengths (each alone would recompute the network)
        mean = np.mean([np.asarray(s) for s in S], 0).reshape(PI.shape)
        mean = mean.reshape(len(phi_i), n_theta_i, n_phi, 2, n_theta, 2).mean((3, 5))
        solid = bin_solid_angle(phi_edges, theta_edges)
        return DirectionGrid(np.maximum(mean, 0) * solid, phi_i, theta_i, phi_edges, theta_edges,
                             self.relative, self.Float, uniform)


class MLPBackend(_NeuralBackend):
    """The MLP as Dr.Jit arithmetic (:class:`mitsuba_ext.neural.DrJitMLP`), fused into the render kernel."""

    name = "mlp"

    def __init__(self, weights_path, Float, near_field: bool = True, packing: float | None = None):
        self.mlp = DrJitMLP(weights_path)
        self.here = self.mlp   # the network as evaluated: a family's at its uniform packing (set_packing)
        self._init_spec(self.mlp.spec, Float, near_field, packing)
        self.nbytes = self.mlp.nbytes

    def set_packing(self, packing: float) -> None:
        """As :meth:`_NeuralBackend.set_packing`; the traced kernel holds the gain of the two
        packing nodes around it alone (:func:`models.neural.bracketed`): an edit within them
        recompiles nothing, one across a node compiles that pair's kernel."""
        super().set_packing(packing)
        self.here = self.mlp.with_spec(self.nodes)

    def at_packing(self, packing):
        view = super().at_packing(packing)
        view.here = self.mlp   # a packing per lane: every trained packing's gain
        return view

    def _eval(self, *queries, orders: bool = False):
        return self.here.eval(*queries, *self.constants, orders=orders)


class OnnxBackend(_NeuralBackend):
    """The ONNX model on onnxruntime: Dr.Jit arrays are evaluated and handed over as numpy.

    Needs Dr.Jit's evaluated mode (``dr.set_flag(dr.JitFlag.SymbolicLoops, False)`` and
    ``dr.set_flag(dr.JitFlag.SymbolicCalls, False)``) when rendering: a call from inside a
    symbolic loop or call is refused with that advice.
    """

    name = "onnx"

    def __init__(self, onnx_path, Float, threads: int = 0, near_field: bool = True, packing: float | None = None):
        self.model = OnnxMLP(onnx_path, threads=threads)
        self._init_spec(self.model.spec, Float, near_field, packing)
        self.nbytes = os.path.getsize(onnx_path)

    def _eval(self, *queries, orders: bool = False):
        queries = queries + self.constants
        if dr.flag(dr.JitFlag.SymbolicScope):  # inside a recorded loop or call: no numpy here
            raise RuntimeError("the onnx backend needs Dr.Jit's evaluated mode: render inside "
                               "`with mitsuba_ext.evaluated_mode():` (bcsdf render-scene does so itself), "
                               "or use the mlp backend, the same model in the megakernel")
        n = max(dr.width(a) for a in queries)
        args = [a if dr.width(a) == n else a + dr.zeros(self.Float, n) for a in queries]
        dr.eval(*args)
        out = self.model.eval(*(np.asarray(a, np.float32) for a in args), orders=orders)  # [n, outputs]
        return [to_drjit(self.Float, out[:, k]) for k in range(out.shape[1])]


def load_backend(kind: str, Float, *, table=None, model=None, lookup: str = "linear", dye=None,
                 near_field: bool = True, packing: float | None = None):
    """Build the backend ``kind`` ('table', 'mlp' or 'onnx') from its file; ``dye``: a
    function of the table's wavelengths giving the per-event albedo that recolours an
    order-resolved table once (``BundleTable.recolour``) or a model of orders at every
    evaluation, or a Mitsuba texture that varies over the shape (then the orders are read
    for a per-hit dye)."""
    if kind not in BACKENDS:
        raise ValueError(f"fiber_bundle: backend {kind!r}; use one of {', '.join(BACKENDS)}")
    if kind == "table":
        if packing is not None:
            raise ValueError("fiber_bundle: a table holds the one packing it was baked at; 'packing' is an input of "
                             "a model trained on a family of bakes (backend 'mlp' or 'onnx')")
        if not table:
            raise ValueError("fiber_bundle: backend 'table' needs the parameter 'table' "
                             "(a bundle_table.npz written by `bcsdf bake`)")
        if dye is not None and not callable(dye):   # a texture varying over the shape: per hit
            backend = TableBackend(table, Float, lookup, near_field=near_field)
            backend.upload_orders()
            return backend
        return TableBackend(table, Float, lookup, dye, near_field)
    if not model:
        what = "weights.npz" if kind == "mlp" else "model.onnx"
        raise ValueError(f"fiber_bundle: backend {kind!r} needs the parameter 'model' "
                         f"(a {what} written by `bcsdf export`)")
    if kind == "mlp":
        if str(model).endswith(".onnx"):
            raise ValueError(f"fiber_bundle: backend 'mlp' reads weights.npz, got {model}")
        backend = MLPBackend(model, Float, near_field=near_field, packing=packing)
    else:
        if not str(model).endswith(".onnx"):
            raise ValueError(f"fiber_bundle: backend 'onnx' reads model.onnx, got {model}")
        backend = OnnxBackend(model, Float, near_field=near_field, packing=packing)
    if dye is not None:
        backend.set_dye(dye)
    return backend
