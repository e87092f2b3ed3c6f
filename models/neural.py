"""A small MLP that holds a bundle table: the input encoding and output transform.

Everything here is written once and shared by every backend through the exported
metadata (``NeuralSpec``); :func:`features` is one function for numpy, PyTorch and
Dr.Jit, so the training data, the ONNX graph and the jitted evaluator encode a query
identically. torch is imported only by the PyTorch builders, which training and export
use.

Encoding of a query ``(phi_i, theta_i, phi_o, theta_o)`` in radians (any values:
angles wrap, theta is clamped to [-pi/2, pi/2]), ``c = cone_scale``:

* longitude ``[sin theta_i, cos theta_i, c (theta_o + theta_i)]``. ``theta_o +
  theta_i`` is the angular distance from the specular cone: parallel fibers keep all
  light near ``theta_o = -theta_i``, so the table is a narrow ridge along it, of about
  constant angular width. Given that coordinate directly, a model learns the ridge with
  far fewer parameters than from the raw angles (the sine form ``sin theta_o + sin
  theta_i`` narrows the ridge like ``cos theta`` at grazing angles).
* azimuth, rotation-invariant bundle (``phi_o`` relative in the table):
  ``[cos dphi, sin dphi]`` with ``dphi = phi_o - phi_i``; otherwise
  ``[cos phi_i, sin phi_i, cos phi_o, sin phi_o]``.

**Symmetry folds** (``spec.folds``). Parallel fibers give ``S(theta_i, theta_o) =
S(-theta_i, -theta_o)``; a circular bundle is (statistically) mirror symmetric,
``S(dphi) = S(-dphi)``; an ellipse is mirror symmetric in x and z. A network that is
handed these symmetries as invariant features learns each distinct value once instead
of two or four times, and cannot break them. The folded features are continuous
invariants (so no seam at theta_i = 0 or on the mirror axes):

* ``theta``: ``[|sin theta_i|, cos theta_i, c |x|, c sin(theta_i) x]`` with
  ``x = theta_o + theta_i`` (its sign relative to theta_i is recovered by the product);
* ``dphi``:  ``[cos dphi, |sin dphi|]``;
* ``xz``:    ``[|cos phi_i|, |sin phi_i|, cos phi_i cos phi_o, sin phi_i sin phi_o]``.

**Baseline encodings** (``spec.encoding``, for the benches' comparisons; ``cone`` above is
the project's): ``cartesian``, the unit vectors ``w_i, w_o`` in the bundle frame (``y`` the
axis; a rotation-invariant bundle at ``phi_i = 0``), the input of neural yarn models;
``halfdiff``, Rusinkiewicz's half and difference vectors with the fiber axis as the pole,
NBRDF's input. Neither folds nor takes feature lines or extra inputs.

**Extra inputs** (``spec.inputs``), scalar coordinates of a query beyond its directions,
each after the four angles in the order named, each with its own encoding appended to the
features above (before the line coordinates):

* ``offset``: ``h`` in [-1, 1], the signed offset of the outgoing ray's line from the
  ply's axis over its radius (a near-field table's cell coordinate, ``bake.offsets``;
  docs/DESIGN.md "Near-field tables"); clamped to [-1, 1]. A circle's mirror turns
  ``(dphi, h)`` into ``(-dphi, -h)``, so under the ``dphi`` fold its features are the
  invariants ``[|h|, h sin dphi]``; else ``[h]``. The model's far field is its mean
  over ``h`` (:func:`far_field`).
* ``packing``: the ply's packing fraction, one value per table of a family of bakes
  (``bcsdf sweep``; :func:`models.fit.prepare_family`); its feature is itself. A model
  answers only within the range it was trained on (``spec.input_range``).

**Orders of scattering** (``spec.orders``: ``K``, from an order-resolved bake, ``bake.orders``
and ``train.orders``): the network returns the table's orders ``S_1 .. S_{K-1}`` and tail
``T`` as ``K x n_lambda`` channels (order-major), each with its own energy gain, so that a
renderer dyes the model as it dyes the table (:func:`models.bundle_table.dyed`, with the
tail's ratio ``spec.tail_ratio``). Every evaluator returns their sum, the undyed fiber's
``S``, unless asked for the orders (:func:`order_sum`).

The training set is the table *folded*: bins that the features cannot tell apart are
one sample (their mean), and held-out validation bins are whole such classes, so a
held-out bin never has its mirror image in the training set.

The MLP (ReLU hidden layers) returns one value per table wavelength (per order and
wavelength with ``spec.orders``) in log space:
``y = log(1 + S / s0)``; the output transform is ``S = s0 * expm1(clip(y, 0, y_max))``
so every backend returns finite, non-negative values for any input. The network is
trained on the table with its symmetry reductions expanded, so no backend needs to
fold queries beyond the features above.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from . import lines as fl
from . import rounding as rd
from .io import atomic_path

# /6: a family's per-packing data on one list of nodes; /5: extra inputs; /4: the energy gain;
# /3: feature lines (models/lines.py)
FORMAT = "bcsdf.neural/6"
READABLE = ("bcsdf.neural/2", "bcsdf.neural/3", "bcsdf.neural/4", "bcsdf.neural/5", FORMAT)  # older: read as
# models without them (a /5 family's gain had nodes of its own: refused, :meth:`NeuralSpec.from_dict`)
FOLDS = ("theta", "dphi", "xz")
INPUTS = ("offset", "packing")  # extra scalar inputs a model may take (above)
ENCODINGS = ("cone", "cartesian", "halfdiff")  # the project's, and the benches' baselines (above)


@dataclass
class NeuralSpec:
    """What a model needs to be evaluated and checked, stored beside its weights."""

    relative_phi: bool
    hidden: list
    s0: float
    y_max: float
    wavelength: list
    table_hash: str
    config_hash: str
    reductions: dict
    cone_scale: float = 4.0
    folds: list = field(default_factory=list)              # symmetry folds of the features (above)
    passthrough: list = field(default_factory=list)       # P_pass at the phi_i nodes below
    passthrough_phi_i: list = field(default_factory=list)  # radians, uniform over 2 pi
    # where P_pass depends on theta_i (twisted plies): [phi_i node][theta_i node], and those nodes
    passthrough_theta: list = field(default_factory=list)
    passthrough_theta_i: list = field(default_factory=list)
    # per wavelength: the share of the scattered light that left after one fiber event (the
    # table's ``single_share``; empty for tables without it), for the renderer's exit choice
    single_share: list = field(default_factory=list)
    # feature lines (models/lines.py): node counts of the t, x and d lines, and channels per
    # line; empty and 0: a plain MLP on the features
    lines: list = field(default_factory=list)
    line_channels: int = 0
    # the energy gain (:func:`energy_gain`): its values [node][wavelength] at the incident
    # longitudes gain_theta_i (radians, increasing; |theta_i| where the theta fold holds); empty:
    # none
    gain: list = field(default_factory=list)
    gain_theta_i: list = field(default_factory=list)
    # its azimuthal part (:func:`azimuth_gain`): [azimuth bin][gain_theta_i node][output], the bins
    # equal over |phi_o - phi_i| in [0, pi]; empty: none. Stored as a product of rank r in log
    # space (train.gain_rank) it holds the coefficients [azimuth bin][node][r] and the basis
    # [r][output], and the gain is exp(coefficients @ basis) (:meth:`azimuth_gains`)
    azimuth_gain: list = field(default_factory=list)
    azimuth_gain_basis: list = field(default_factory=list)
    # extra scalar inputs after the four angles (INPUTS, above); with ``offset``: the near
    # field's cells (the ``h`` midpoints of the far field's mean) and the passthrough of a
    # ray by its entry cell, [passthrough_theta_i node][cell] at one phi_i (a circle)
    inputs: list = field(default_factory=list)
    offset_cells: int = 0
    passthrough_offset: list = field(default_factory=list)
    passthrough_offset_theta_i: list = field(default_factory=list)
    # a family's inputs (packing): the range trained on, {name: [lo, hi]}; the nodes of its
    # per-packing data, increasing (the trained packings, and packings between them where the
    # energy gain has set them: models.fit.energy_gain), and the passthrough
    # [packing node][passthrough_phi_i node] at them; the gain and the tail's ratio are per
    # packing node too, all read linearly between the nodes
    input_range: dict = field(default_factory=dict)
    passthrough_packing: list = field(default_factory=list)
    packings: list = field(default_factory=list)
    encoding: str = "cone"   # ENCODINGS: the directions' features (above)
    # the orders of scattering (above): K channels of the spectrum, 0: none; the tail's ratio
    # rho [passthrough_phi_i node][tail_ratio_theta_i node][wavelength] (a family's: per packing node first)
    orders: int = 0
    tail_ratio: list = field(default_factory=list)
    tail_ratio_theta_i: list = field(default_factory=list)
    format: str = FORMAT

    def __post_init__(self):
        for name in ("s0", "y_max", "cone_scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"model metadata: {name} = {v!r}; it must be a positive finite number")
        wl = np.asarray(self.wavelength, float)
        if wl.ndim != 1 or wl.size == 0 or not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
            raise ValueError("model metadata: wavelength must be a non-empty, increasing list of finite numbers")
        if not all(isinstance(h, int) and h > 0 for h in self.hidden):
            raise ValueError(f"model metadata: hidden widths {self.hidden} must be positive integers")
        p = np.asarray(self.passthrough, float)
        if len(p) != len(self.passthrough_phi_i) or not np.all(np.isfinite(p)) or np.any((p < 0) | (p > 1)):
            raise ValueError("model metadata: passthrough must hold one probability in [0, 1] per passthrough_phi_i")
        if self.passthrough_theta:
            q = np.asarray(self.passthrough_theta, float)
            if q.shape != (len(p), len(self.passthrough_theta_i)) or not np.all(np.isfinite(q)) or \
                    np.any((q < 0) | (q > 1)):
                raise ValueError("model metadata: passthrough_theta must hold a probability in [0, 1] per "
                                 "(passthrough_phi_i, passthrough_theta_i)")
        q = np.asarray(self.single_share, float)
        if q.size and (q.shape != wl.shape or not np.all(np.isfinite(q)) or np.any((q < 0) | (q > 1 + 1e-6))):
            raise ValueError("model metadata: single_share must be empty or hold a share in [0, 1] per wavelength")
        if (self.lines or self.line_channels) and not (
                len(self.lines) == 3 and all(isinstance(n, int) and n >= 2 for n in self.lines)
                and isinstance(self.line_channels, int) and self.line_channels >= 1):
            raise ValueError(f"model metadata: lines {self.lines} x {self.line_channels} channels; feature lines "
                             "need three node counts >= 2 and at least one channel (or none of either)")
        if self.gain or self.gain_theta_i:
            g, t = np.asarray(self.gain, float), np.asarray(self.gain_theta_i, float)
            shape = ((len(self.packings),) if "packing" in self.inputs else ()) + \
                (len(t), self.n_outputs)
            if g.shape != shape or not (np.all(np.isfinite(g)) and np.all(g > 0)) or \
                    not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0) or np.any(np.abs(t) > np.pi / 2):
                raise ValueError("model metadata: gain must hold a positive finite value per ([packing node,] "
                                 "gain_theta_i node, output), the nodes increasing longitudes within +-pi/2")
        if self.azimuth_gain_basis:
            a, v = np.asarray(self.azimuth_gain, float), np.asarray(self.azimuth_gain_basis, float)
            if v.ndim != 2 or v.shape[1] != self.n_outputs or a.ndim != 3 or a.shape[2] != v.shape[0] or \
                    not (np.all(np.isfinite(a)) and np.all(np.isfinite(v))):
                raise ValueError("model metadata: azimuth_gain_basis must hold finite values [rank][output], and "
                                 "azimuth_gain finite coefficients [azimuth bin][gain_theta_i node][rank]")
        if self.azimuth_gain:
            with np.errstate(over="ignore"):
                a = self.azimuth_gains()
            if a.ndim != 3 or a.shape[1:] != (len(self.gain_theta_i), self.n_outputs) or not self.gain or \
                    not (np.all(np.isfinite(a)) and np.all(a > 0)) or not self.relative_phi or self.inputs or \
                    self.orders:
                raise ValueError("model metadata: azimuth_gain must hold a positive finite value per (azimuth bin, "
                                 "gain_theta_i node, output), beside a gain, for a circular ply's model without "
                                 "extra inputs or orders")
        if [i for i in self.inputs if i not in INPUTS] or len(set(self.inputs)) != len(self.inputs):
            raise ValueError(f"model metadata: inputs {self.inputs}; known extra inputs: {INPUTS}, each once")
        if "offset" in self.inputs and not (self.relative_phi and isinstance(self.offset_cells, int)
                                            and self.offset_cells >= 1):
            raise ValueError("model metadata: an 'offset' input needs a circular ply's model and offset_cells >= 1")
        if "packing" in self.inputs:
            lo_hi = np.asarray(self.input_range.get("packing", []), float)
            q, k = np.asarray(self.passthrough_packing, float), np.asarray(self.packings, float)
            if lo_hi.shape != (2,) or not (0 < lo_hi[0] <= lo_hi[1] < 1) or \
                    q.shape != (len(k), len(self.passthrough_phi_i)) or np.any(np.diff(k) <= 0) or \
                    not np.all(np.isfinite(q)) or np.any((q < 0) | (q > 1)) or "offset" in self.inputs:
                raise ValueError("model metadata: a 'packing' input needs input_range {packing: [lo, hi]} within "
                                 "(0, 1) and passthrough_packing per (packing node, passthrough_phi_i node); "
                                 "not with an offset input")
        if self.passthrough_offset or self.passthrough_offset_theta_i:
            q, t = np.asarray(self.passthrough_offset, float), np.asarray(self.passthrough_offset_theta_i, float)
            if q.shape != (len(t), self.offset_cells) or not np.all(np.isfinite(q)) or np.any((q < 0) | (q > 1)) \
                    or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
                raise ValueError("model metadata: passthrough_offset must hold a probability per "
                                 "(passthrough_offset_theta_i node, offset cell), the nodes increasing")
        if self.orders or self.tail_ratio:
            r, t = np.asarray(self.tail_ratio, float), np.asarray(self.tail_ratio_theta_i, float)
            family = (len(self.packings),) if self.inputs == ["packing"] else ()
            if not (isinstance(self.orders, int) and self.orders >= 2) or (self.inputs and not family) or \
                    r.shape != family + (len(p), len(t), len(wl)) or not np.all(np.isfinite(r)) or \
                    np.any((r < 0) | (r >= 1)) or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
                raise ValueError("model metadata: orders K >= 2 need tail_ratio in [0, 1) per ([packing node,] "
                                 "passthrough_phi_i node, tail_ratio_theta_i node, wavelength), the nodes "
                                 "increasing; of extra inputs only with 'packing'")
        if self.encoding not in ENCODINGS or (self.encoding != "cone" and (self.folds or self.lines or self.inputs)):
            raise ValueError(f"model metadata: encoding {self.encoding!r} (known: {ENCODINGS}; the baselines "
                             "take no folds, feature lines or extra inputs)")
        bad = [f for f in self.folds if f not in FOLDS]
        if bad or ("dphi" in self.folds and not self.relative_phi) or ("xz" in self.folds and self.relative_phi):
            raise ValueError(f"folds {self.folds} do not fit a {'relative' if self.relative_phi else 'absolute'}"
                             f"-azimuth model (known: {FOLDS})")

    @property
    def n_features(self) -> int:
        """How many arrays :func:`features` returns (the line coordinates last)."""
        if self.encoding != "cone":
            return 6
        return 3 + ("theta" in self.folds) + (2 if self.relative_phi else 4) + self.n_extra_features + \
            (3 if self.lines else 0)

    @property
    def n_extra_features(self) -> int:
        """How many features the extra inputs add (:func:`extra_features`)."""
        return sum(1 + (name == "offset" and "dphi" in self.folds) for name in self.inputs)

    @property
    def n_queries(self) -> int:
        """The columns of a query: the four angles, then the extra inputs."""
        return 4 + len(self.inputs)

    @property
    def n_inputs(self) -> int:
        """The first layer's width: the features, the line coordinates replaced by the
        ``line_channels`` products of the lines."""
        return self.n_features - (3 - self.line_channels if self.lines else 0)

    @property
    def n_outputs(self) -> int:
        """The network's outputs: a spectrum, or one per order of scattering (``orders``)."""
        return len(self.wavelength) * max(1, self.orders)

    def azimuth_gains(self) -> np.ndarray:
        """The azimuthal gain ``[azimuth bin, gain_theta_i node, output]`` (float64), expanded
        from its product where it is stored as one; empty without one."""
        a = np.asarray(self.azimuth_gain, np.float64)
        if not self.azimuth_gain_basis:
            return a
        return np.exp(a @ np.asarray(self.azimuth_gain_basis, np.float64))

    @property
    def azimuth_gain_values(self) -> int:
        """How many numbers the azimuthal gain stores (its product's factors, where it is one)."""
        return int(np.size(self.azimuth_gain) + np.size(self.azimuth_gain_basis))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "NeuralSpec":
        if d.get("format") not in READABLE:
            raise ValueError(f"model format {d.get('format')!r}, expected {FORMAT!r}; re-run `bcsdf train`")
        d = dict(d)
        if d.pop("gain_packings", None):
            raise ValueError(f"model format {d.get('format')!r}: a family's model whose gain has packing nodes of "
                             f"its own, which {FORMAT!r} keeps with the passthrough's; re-run `bcsdf family`")
        return cls(**{**d, "format": FORMAT})


def check_inputs(spec: NeuralSpec, n_extra: int) -> None:
    """Refuse a query of the wrong width, naming what the model takes."""
    if n_extra != len(spec.inputs):
        raise ValueError(f"the model takes {4 + len(spec.inputs)} inputs (phi_i, theta_i, phi_o, theta_o"
                         + "".join(f", {n}" for n in spec.inputs) + f"), got {4 + n_extra}")


def features(lib, spec: NeuralSpec, phi_i, theta_i, phi_o, theta_o, *extra) -> list:
    """The encoded inputs as a list of ``spec.n_features`` arrays; ``lib`` is numpy, torch,
    drjit or :data:`models.rounding.BOUNDED`; ``extra``: the values of ``spec.inputs``. With
    feature lines, their three coordinates (:func:`models.lines.coordinates`) come last."""
    check_inputs(spec, len(extra))
    if spec.encoding != "cone":
        return baseline_features(lib, spec, phi_i, theta_i, phi_o, theta_o)
    clip = getattr(lib, "clip", None) or getattr(lib, "clamp")
    half_pi = float(np.pi / 2)
    ti = clip(theta_i, -half_pi, half_pi)
    x = clip(theta_o, -half_pi, half_pi) + ti
    sin_ti, cos_ti, c = lib.sin(ti), lib.cos(ti), spec.cone_scale
    if "theta" in spec.folds:
        out = [lib.abs(sin_ti), cos_ti, c * lib.abs(x), (c * sin_ti) * x]
    else:
        out = [sin_ti, cos_ti, c * x]
    d = phi_o - phi_i
    if spec.relative_phi:
        sin_d = lib.sin(d)
        out += [lib.cos(d), lib.abs(sin_d) if "dphi" in spec.folds else sin_d]
    else:
        ci, si, co, so = lib.cos(phi_i), lib.sin(phi_i), lib.cos(phi_o), lib.sin(phi_o)
        out += [lib.abs(ci), lib.abs(si), ci * co, si * so] if "xz" in spec.folds else [ci, si, co, so]
    out += extra_features(lib, spec, d, *extra)
    if spec.lines:
        out += fl.coordinates(lib, spec.folds, ti, x, d)
    return out


def baseline_features(lib, spec: NeuralSpec, phi_i, theta_i, phi_o, theta_o) -> list:
    """The baselines' encodings (module docstring): ``w_i, w_o`` (``cartesian``) or the half
    vector ``h`` and the difference vector ``d`` (``halfdiff``: ``w_i`` turned by ``-phi_h``
    about the axis and by ``-theta_h`` about the binormal, which takes ``h`` to the pole)."""
    clip = getattr(lib, "clip", None) or getattr(lib, "clamp")
    where = getattr(lib, "where", None) or getattr(lib, "select")
    half_pi = float(np.pi / 2)
    ti, to = clip(theta_i, -half_pi, half_pi), clip(theta_o, -half_pi, half_pi)
    a, b = (phi_i * 0.0, phi_o - phi_i) if spec.relative_phi else (phi_i, phi_o)
    wi = [lib.cos(ti) * lib.cos(a), lib.sin(ti), lib.cos(ti) * lib.sin(a)]
    wo = [lib.cos(to) * lib.cos(b), lib.sin(to), lib.cos(to) * lib.sin(b)]
    if spec.encoding == "cartesian":
        return wi + wo
    s = [p + q for p, q in zip(wi, wo)]
    norm = lib.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    norm = clip(norm, 1e-7, 4.0)   # w_o = -w_i: no half vector; any (|w_i + w_o| <= 2)
    h = [c / norm for c in s]
    sin_t = lib.sqrt(h[0] * h[0] + h[2] * h[2])
    pole = sin_t < 1e-6   # h along the axis: phi_h is any; take 0
    safe = where(pole, 1.0, sin_t)
    cos_p, sin_p = where(pole, 1.0, h[0] / safe), where(pole, 0.0, h[2] / safe)
    x1, z1 = wi[0] * cos_p + wi[2] * sin_p, wi[2] * cos_p - wi[0] * sin_p
    d = [x1 * h[1] - wi[1] * sin_t, x1 * sin_t + wi[1] * h[1], z1]
    return h + d


def extra_features(lib, spec: NeuralSpec, dphi, *extra) -> list:
    """The features of the extra inputs (module docstring), at azimuth difference ``dphi``."""
    clip = getattr(lib, "clip", None) or getattr(lib, "clamp")
    out = []
    for name, v in zip(spec.inputs, extra):
        if name == "offset":
            h = clip(v, -1.0, 1.0)
            out += [lib.abs(h), h * lib.sin(dphi)] if "dphi" in spec.folds else [h]
        elif name == "packing":
            out.append(v * 1.0)
    return out


def order_sum(spec: NeuralSpec, S):
    """The undyed fiber's ``S`` from a model's outputs: the sum of its orders of scattering
    (``spec.orders``; else ``S`` itself). ``S``: ``[..., K x n_lambda]`` (numpy, PyTorch,
    bounded arithmetic: its bound grows by the summation's ``gamma_{K-1}``, any order of
    addition) or a list over the outputs (Dr.Jit)."""
    K, L = spec.orders, len(spec.wavelength)
    if not K:
        return S
    if isinstance(S, list):
        return [sum(S[k * L + l] for k in range(1, K)) + S[l] for l in range(L)]
    if isinstance(S, rd.Bounded):
        v, e = S.value.reshape(S.value.shape[:-1] + (K, L)), S.err.reshape(S.err.shape[:-1] + (K, L))
        return rd.Bounded(v.sum(-2), e.sum(-2) + rd.gamma(K - 1, S.u) * (np.abs(v) + e).sum(-2), S.u)
    return S.reshape(S.shape[:-1] + (K, L)).sum(-2)


def order_channels(spec: NeuralSpec, S) -> list:
    """The outputs of a model of ``spec.orders`` as ``[S_1, .., S_{K-1}, T]``, each a list over
    wavelengths (Dr.Jit's list of outputs) or an array ``[..., n_lambda]`` (numpy, PyTorch)."""
    L = len(spec.wavelength)
    if isinstance(S, list):
        return [S[k * L:(k + 1) * L] for k in range(spec.orders)]
    return [S[..., k * L:(k + 1) * L] for k in range(spec.orders)]


def offset_midpoints(spec: NeuralSpec) -> np.ndarray:
    """The midpoints of the near field's cells, where :func:`far_field` averages a model."""
    return -1.0 + (np.arange(spec.offset_cells) + 0.5) * (2.0 / spec.offset_cells)


def far_field(predict, spec: NeuralSpec):
    """A function of the four angles from ``predict(*angles, *extra)``: for a model with an
    ``offset`` input its mean over the offset (the midpoint rule at the cells' midpoints: the
    far field is the mean of the near field's cells); else ``predict`` itself."""
    if "offset" not in spec.inputs:
        return predict
    if spec.inputs != ["offset"]:
        raise ValueError(f"far field of a model with inputs {spec.inputs}: only 'offset' is averaged")

    def mean(*angles):
        total = None
        for h in offset_midpoints(spec):
            v = predict(*angles, angles[1] * 0.0 + float(h))  # numpy, torch or Dr.Jit alike
            total = v if total is None else (
                [a + b for a, b in zip(total, v)] if isinstance(v, list) else total + v)
        scale = 1.0 / spec.offset_cells
        return [a * scale for a in total] if isinstance(total, list) else total * scale
    return mean


def encode_numpy(spec: NeuralSpec, phi_i, theta_i, phi_o, theta_o, *extra) -> np.ndarray:
    """Feature matrix [n, n_features] (float32) of the encoding above."""
    args = (np.asarray(a, np.float64) for a in (phi_i, theta_i, phi_o, theta_o, *extra))
    return np.stack(np.broadcast_arrays(*features(np, spec, *args)), -1).astype(np.float32)


@dataclass
class FoldedTable:
    """A bundle table as training samples: one per class of bins the features cannot tell apart.

    ``x [n, n_inputs]`` features, ``S`` and ``E [n, n_lambda]`` the members' mean value
    and its standard error, ``y``/``sigma_y`` the same in log space, ``count [n]`` the
    members per class, ``bin_class [n_bins]`` the class of every expanded bin (flat
    order phi_i, theta_i, phi_o, theta_o), and for the energy term ``group [n]`` the
    incident direction (up to symmetry) of a class and ``omega [n]`` its solid-angle
    weight, such that ``sum_c S_c omega_c`` over a group is that incident direction's
    albedo ``integral S d omega_o``; ``albedo [n_groups, n_lambda]`` is that integral
    from the table (``BundleTable.scattered``, the mean over the group's members).
    """

    x: np.ndarray
    y: np.ndarray
    sigma_y: np.ndarray
    S: np.ndarray
    E: np.ndarray
    count: np.ndarray
    bin_class: np.ndarray
    group: np.ndarray
    omega: np.ndarray
    albedo: np.ndarray
    chi2_per_dof: float  # spread of merged bins about their mean, in units of their noise (~1: consistent)
    cell: np.ndarray = None  # [n, 6] a representative bin: phi_i, theta_i, phi_o lo/hi, sin theta_o lo/hi
    extra_cell: np.ndarray = None  # [n, k, 2] its range (lo, hi) in each extra input; None without any
    # the expanded bins themselves, for the figures of models.errors: values and standard
    # errors [n_bins, n_lambda], the table's shape of them (incident directions first, then
    # the bins of a row) and the solid angle of a row's bins
    bins_S: np.ndarray = None
    bins_E: np.ndarray = None
    bins_shape: tuple = None
    row_omega: np.ndarray = None


def table_cells(table) -> np.ndarray:
    """[n_bins, 6] every (expanded) bin in flat order: phi_i, theta_i, absolute phi_o
    edges (lo, hi), sin theta_o edges (lo, hi)."""
    relative = table.meta["reductions"]["phi_o"] == "relative"
    PI, TI, PO, SO = np.meshgrid(table.phi_i, table.theta_i, np.arange(len(table.phi_o)),
                                 np.arange(len(table.theta_o)), indexing="ij")
    PI, TI, PO, SO = (a.ravel() for a in (PI, TI, PO, SO))
    offset = PI if relative else 0.0  # relative tables store phi_o - phi_i
    sin_edges = np.sin(table.theta_o_edges)
    return np.stack([PI, TI, table.phi_o_edges[PO] + offset, table.phi_o_edges[PO + 1] + offset,
                     sin_edges[SO], sin_edges[SO + 1]], -1)


def points_in_bins(lib, cell, u):
    """Angles ``(phi_i, theta_i, phi_o, theta_o)`` at uniform points ``u [n, 2]`` of the bins
    ``cell [n, 6]`` (``FoldedTable.cell``), uniform in phi_o and sin theta_o (per solid
    angle); ``lib`` is numpy or torch."""
    phi_o = cell[:, 2] + u[:, 0] * (cell[:, 3] - cell[:, 2])
    sin_o = cell[:, 4] + u[:, 1] * (cell[:, 5] - cell[:, 4])
    return cell[:, 0], cell[:, 1], phi_o, lib.arcsin(lib.clip(sin_o, -1.0, 1.0))


def bin_average(predict, cell, k: int = 4, extra_cell=None) -> np.ndarray:
    """Mean of ``predict(phi_i, theta_i, phi_o, theta_o, *extra) -> [n, ...]`` over k x k
    midpoints of each bin of ``cell`` (and, with ``extra_cell [n, m, 2]``, ``max(2, k // 2)``
    midpoints of each extra input's range, one where every range is a point: a family's
    packing): what a bin of the table (a bin average) is compared with."""
    total, count = 0.0, 0
    n_extra = 1 if extra_cell is None or np.all(extra_cell[..., 0] == extra_cell[..., 1]) else max(2, k // 2)
    extras = [[]] if extra_cell is None else \
        [[lo + t * (hi - lo) for lo, hi in np.moveaxis(extra_cell, (1, 2), (0, 1))]
         for t in (np.arange(n_extra) + 0.5) / n_extra]
    for a in (np.arange(k) + 0.5) / k:
        for b in (np.arange(k) + 0.5) / k:
            angles = points_in_bins(np, cell, np.broadcast_to([a, b], (len(cell), 2)))
            for extra in extras:
                total, count = total + predict(*angles, *extra), count + 1
    return total / count


def fold_table(table, spec: NeuralSpec, constants: dict | None = None) -> FoldedTable:
    """Group the bins of an expanded table by their (folded) features and average each group.
    ``constants``: the values of extra inputs that hold for the whole table (a family
    member's ``packing``)."""
    constants = constants or {}

    n_l = len(table.wavelength)
    # the bins, flat in the order (phi_i, theta_i, [offset cell,] phi_o, theta_o): a model with
    # an offset input learns the near field's cells, each an equal share of the ply's width
    values, stderr, N = table.values, table.stderr, 1
    if "offset" in spec.inputs:
        if table.near is None:
            raise ValueError("a model with an 'offset' input learns a near-field table: bake it with "
                             "`bake.offsets: N` (e.g. 8) in the config")
        N = len(table.near)
        values, stderr = np.moveaxis(table.near, 0, 2), np.moveaxis(table.near_stderr, 0, 2)
    if spec.orders:   # the orders as channels of the spectrum, order-major (a bin's value: their sum)
        if table.orders is None or len(table.orders) != spec.orders:
            raise ValueError(f"a model of {spec.orders} orders of scattering learns an order-resolved table: bake "
                             f"it with `bake.orders: {spec.orders}`")
        channels = lambda a: np.moveaxis(a, 0, -2).reshape(a.shape[1:-1] + (-1,))  # noqa: E731
        values, stderr = channels(table.orders), channels(table.orders_stderr)
    h_edges = np.linspace(-1.0, 1.0, N + 1)
    PI, TI, HC, PO, TO = np.meshgrid(table.phi_i, table.theta_i, np.arange(N), table.phi_o, table.theta_o,
                                     indexing="ij")
    if spec.relative_phi:
        PO = PO + PI  # relative tables store phi_o - phi_i
    extra = [0.5 * (h_edges[HC] + h_edges[HC + 1]).ravel() if name == "offset" else np.full(HC.size, constants[name])
             for name in spec.inputs]
    f = np.stack(np.broadcast_arrays(*features(np, spec, PI.ravel(), TI.ravel(), PO.ravel(), TO.ravel(), *extra)),
                 -1)
    _, first, bin_class, count = np.unique(np.round(f, 6), axis=0, return_index=True, return_inverse=True,
                                           return_counts=True)
    bin_class = bin_class.ravel()
    n, n_l = len(count), values.shape[-1]   # n_l: the outputs (wavelengths, or orders x wavelengths)
    S_bins = values.reshape(-1, n_l).astype(np.float64)
    E_bins = stderr.reshape(-1, n_l).astype(np.float64)
    S = np.zeros((n, n_l))
    np.add.at(S, bin_class, S_bins)
    S /= count[:, None]
    E2 = np.zeros((n, n_l))
    np.add.at(E2, bin_class, E_bins**2)
    E = np.sqrt(E2) / count[:, None]

    # merged bins should agree within their noise; a fold the data contradicts shows here.
    # Per class, chi^2 = sum (S_k - mean)^2 / (pooled variance mean E_k^2), n - 1 degrees of
    # freedom; only classes of independent estimates count (the copies an expanded
    # reduction makes are identical), and only where the pooled variance is known.
    pooled = E2 / count[:, None]
    spread = np.zeros((n, n_l))
    np.add.at(spread, bin_class, (S_bins - S[bin_class]) ** 2)
    independent = (spread > 0) & (pooled > 0)
    dof = (count[:, None] - 1) * independent
    chi2 = float(np.sum(spread[independent] / pooled[independent]) / dof.sum()) if dof.sum() else 0.0

    # incident directions equal up to symmetry: groups joined by a shared class
    n_bins_group = N * len(table.phi_o) * len(table.theta_o)
    bin_group = np.arange(len(bin_class)) // n_bins_group
    n_groups = bin_group[-1] + 1
    link = coo_matrix((np.ones(len(bin_class)), (bin_group, n_groups + bin_class)),
                      shape=(n_groups + n, n_groups + n))
    _, label = connected_components(link, directed=False)
    group_canonical = np.unique(label[:n_groups], return_inverse=True)[1]
    members = np.bincount(group_canonical)  # expanded incident directions per canonical one
    omega_bins = np.broadcast_to(table.solid_angle / N, values.shape[:-1]).ravel()
    omega = np.bincount(bin_class, omega_bins, n) / members[group_canonical[bin_group[first]]]
    group = group_canonical[bin_group[first]]
    # the baked scattered fraction of each canonical incident direction (its members' mean);
    # of each order, the integral of its bins
    scattered = table.scattered if not spec.orders else \
        np.einsum("kabpql,pq->abkl", table.orders.astype(np.float64), table.solid_angle)
    albedo = np.zeros((members.size, n_l))
    np.add.at(albedo, group_canonical, scattered.reshape(-1, n_l))
    albedo /= members[:, None]

    # each class's first bin, for training at points inside the bin (the table holds bin
    # averages; at the centres alone a network may peak between them, unseen)
    n_dirs = len(table.phi_i) * len(table.theta_i)
    n_out = len(table.phi_o) * len(table.theta_o)
    cell = np.broadcast_to(table_cells(table).reshape(n_dirs, 1, n_out, 6), (n_dirs, N, n_out, 6)).reshape(-1, 6)[first]
    extra_cell = np.stack([np.stack([h_edges[HC], h_edges[HC + 1]], -1).reshape(-1, 2) if name == "offset" else
                           np.full((HC.size, 2), constants[name]) for name in spec.inputs], 1)[first] \
        if spec.inputs else None

    y = np.log1p(S / spec.s0)
    sigma_y = E / (spec.s0 + S)  # first-order propagation of the standard error
    if spec.orders:   # the errors compare the table's own values (the orders' sum)
        S_bins, E_bins = (a.reshape(-1, len(table.wavelength)).astype(np.float64) for a in (table.values, table.stderr))
    return FoldedTable(x=f[first].astype(np.float32), y=y.astype(np.float32), sigma_y=sigma_y.astype(np.float32),
                       S=S, E=E, count=count, bin_class=bin_class, group=group, omega=omega, albedo=albedo,
                       chi2_per_dof=chi2, cell=cell, extra_cell=extra_cell, bins_S=S_bins, bins_E=E_bins,
                       bins_shape=table.values.shape if spec.orders else values.shape,
                       row_omega=omega_bins[:n_bins_group])


def stable_expm1(lib, y):
    """``exp(y) - 1`` written with ops every backend has (ONNX has no Expm1).

    Below 1e-2 the cubic Taylor polynomial (relative error < 5e-8), above it
    ``exp(y) - 1`` (no cancellation there). ``lib`` is torch or drjit.
    """
    series = y * (1.0 + y * (0.5 + y * (1.0 / 6.0)))
    where = getattr(lib, "where", None) or getattr(lib, "select")
    return where(y < 1e-2, series, lib.exp(y) - 1.0)


def energy_gain(lib, spec: NeuralSpec, theta_i, *extra):
    """The energy gain at incident longitudes ``theta_i`` (and the query's extra inputs
    ``extra``): one factor per output (wavelength; order and wavelength) that multiplies the
    network's spectrum, so that each incident direction's albedo (each order's) is the table's
    (:func:`models.fit.energy_gain`). Piecewise
    linear in ``theta_i`` (``|theta_i|`` under the theta fold) through ``spec.gain_theta_i``,
    constant beyond the end nodes, written as a sum of clipped segments, ``g_0 + sum_k m_k
    (clip(t, t_k, t_k+1) - t_k)``, the slopes ``m_k``: ops every backend has. A family's model
    (a ``packing`` input) holds one such gain per node of ``spec.packings`` (the trained
    packings and packings between them), piecewise linear between them the same way. ``lib``
    as :func:`features`; returns ``[..., n_lambda]`` for numpy and PyTorch (the segments
    times a matrix: one ``MatMul`` in the ONNX graph), a list over wavelengths for Dr.Jit and
    bounded arithmetic, or ``None`` without a gain."""
    if not spec.gain:
        return None
    clip = getattr(lib, "clip", None) or getattr(lib, "clamp")
    t = clip(theta_i, float(-np.pi / 2), float(np.pi / 2))
    t = lib.abs(t) if "theta" in spec.folds else t
    g = np.asarray(spec.gain, np.float64)
    if g.ndim == 2:
        return _piecewise_linear(lib, clip, t, spec.gain_theta_i, g)
    p = extra[spec.inputs.index("packing")]
    nodes = spec.packings
    rows = np.moveaxis(g, 0, 1).reshape(len(spec.gain_theta_i), -1)   # [theta node, packing node x lambda]
    per_packing = _piecewise_linear(lib, clip, t, spec.gain_theta_i, rows)   # the gain of every packing node
    L = g.shape[-1]
    if isinstance(per_packing, list):   # Dr.Jit, bounded arithmetic: a value per wavelength
        return [between(clip, p, nodes, [per_packing[k * L + l] for k in range(len(g))], False)
                for l in range(L)]
    stacked = per_packing.reshape(per_packing.shape[:-1] + (len(g), L))
    return between(clip, p, nodes, [stacked[..., k, :] for k in range(len(g))], True)


def between(clip, x, nodes, at_nodes, spectra: bool):
    """Linear between the values ``at_nodes`` (arrays, one per node; ``spectra``: ``[..., m]``
    against ``x [...]``) at ``nodes``, constant beyond, as clipped segments."""
    out = at_nodes[0]
    for k, (a, b) in enumerate(zip(nodes[:-1], nodes[1:])):
        w = (clip(x, float(a), float(b)) - float(a)) * float(1.0 / (b - a))
        out = out + (w[..., None] if spectra else w) * (at_nodes[k + 1] - at_nodes[k])
    return out


def bracketed(spec: NeuralSpec, packing: float) -> NeuralSpec:
    """A family's spec (a ``packing`` input) whose per-packing data (the energy gain, the
    passthrough, the tail's ratio) keep only the two nodes of ``spec.packings`` around
    ``packing``.

    Anywhere between those nodes it evaluates as ``spec`` does (:func:`between` is linear
    between neighbouring nodes and the segments below them sum to the lower node's value),
    to float rounding; the range trained on (``input_range``) is kept. A uniform packing
    is read through it: the gain of every node is most of what a family's evaluation costs
    beyond its network, and all but two of them have weight 0 there."""
    if "packing" not in spec.inputs or len(spec.packings) <= 2:
        return spec
    k = int(np.clip(np.searchsorted(spec.packings, packing, side="right") - 1, 0, len(spec.packings) - 2))
    pair = lambda a: list(a[k:k + 2]) if a else a  # noqa: E731
    return replace(spec, packings=pair(spec.packings), passthrough_packing=pair(spec.passthrough_packing),
                   tail_ratio=pair(spec.tail_ratio), gain=pair(spec.gain))


def azimuth_gain(lib, spec: NeuralSpec, theta_i, phi_i, phi_o):
    """The energy gain's azimuthal part (``spec.azimuth_gain``; ``None`` without): one factor
    per output in each of ``A`` equal bins of ``|phi_o - phi_i|`` over [0, pi], piecewise
    linear in ``theta_i`` (``|theta_i|`` under the theta fold) through the gain's nodes
    ``spec.gain_theta_i`` and constant beyond them, as :func:`energy_gain` is.

    It holds what a small network smooths away: the spectra's ripple (the fiber's Mie
    resonances) from one azimuth bin to the next (:func:`models.fit.energy_gain` gives each bin
    the table's energy on the training bins). It is read as ``G[b, j] + f (G[b, j + 1] - G[b,
    j])``: the bin ``b`` by a floor, the node ``j`` below ``theta_i`` by comparisons, then two
    rows of the table (Dr.Jit: two gathers per output; PyTorch and the ONNX graph: ``Gather``).
    ``lib`` as :func:`features`; returns ``[..., n_outputs]`` for numpy and PyTorch, a list over
    outputs for Dr.Jit and bounded arithmetic."""
    if not spec.azimuth_gain:
        return None
    G = spec.azimuth_gains()   # [A, T, L]
    A, T, L = G.shape
    nodes = np.asarray(spec.gain_theta_i, np.float64)
    inv = 1.0 / np.diff(nodes) if T > 1 else np.ones(1)
    clip = getattr(lib, "clip", None) or getattr(lib, "clamp")
    t = clip(theta_i, float(-np.pi / 2), float(np.pi / 2))
    t = lib.abs(t) if "theta" in spec.folds else t
    d = phi_o - phi_i
    w = d - float(2 * np.pi) * lib.floor((d + float(np.pi)) * float(1 / (2 * np.pi)))  # d wrapped to [-pi, pi)
    a = lib.abs(w) * float(A / np.pi)   # the bin's coordinate: bin b holds a in [b, b + 1)
    if lib is rd.BOUNDED:
        return _bounded_azimuth_gain(G, nodes, inv, t, a)
    if getattr(lib, "__name__", "") == "drjit":
        Float = type(t)
        UInt = lib.uint32_array_t(Float)
        j, lo, step = UInt(0), t * 0.0 + float(nodes[0]), t * 0.0 + float(inv[0])
        for k in range(1, T - 1):   # the node below t, its longitude and 1 / the segment's width: literals
            above = t >= float(nodes[k])
            j, lo, step = (lib.select(above, j + 1, j), lib.select(above, float(nodes[k]), lo),
                           lib.select(above, float(inv[k]), step))
        f = clip((t - lo) * step, 0.0, 1.0) if T > 1 else t * 0.0
        b = UInt(clip(lib.floor(a), 0.0, float(A - 1)))
        first = (b * T + j) * L
        table = Float(G.astype(np.float32).ravel())
        out = []
        for k in range(L):
            g0 = lib.gather(Float, table, first + k)
            g1 = lib.gather(Float, table, first + min(T - 1, 1) * L + k)
            out.append(g0 + f * (g1 - g0))
        return out
    dtype = t.dtype
    at = lambda v: lib.asarray(np.ascontiguousarray(v), dtype=dtype)   # noqa: E731  (constants of t's precision)
    j = (t[..., None] >= at(nodes[1:-1])).sum(-1)   # the node below t (an integer array; 0 without interior nodes)
    f = clip((t - at(nodes[:-1])[j]) * at(inv)[j], 0.0, 1.0) if T > 1 else t * 0.0
    b = clip(lib.floor(a), 0.0, float(A - 1))
    b = b.long() if hasattr(b, "long") else b.astype(np.int64)
    rows = at(G.reshape(A * T, L))
    g0, g1 = rows[b * T + j], rows[b * T + j + min(T - 1, 1)]
    return g0 + f[..., None] * (g1 - g0)


def _bounded_azimuth_gain(G, nodes, inv, t, a) -> list:
    """:func:`azimuth_gain` in bounded arithmetic: the lerp of float32 constants carried by
    :class:`models.rounding.Bounded`; where the bin's coordinate lies within its error of a
    bin's edge, the other bin may be read: the difference of the two is added; where the
    longitude lies within its error of a node, the segment on the node's other side may be
    read, whose value there is the same: the steepest neighbouring slope times the
    longitude's error is added."""
    A, T, L = G.shape
    u = t.u
    f32 = lambda v: np.asarray(v, np.float32).astype(np.float64)   # noqa: E731
    const = lambda v: rd.Bounded(v, np.abs(v - f32(v)), u)   # noqa: E731  (a float64 value as its float32 constant)
    j = np.clip(np.searchsorted(nodes, t.value, side="right") - 1, 0, max(T - 2, 0))
    step = min(T - 1, 1)
    f = rd.clip((t - const(nodes[:-1][j])) * const(inv[j]), 0.0, 1.0) if T > 1 else \
        rd.Bounded(np.zeros_like(t.value), 0.0, u)
    b = np.clip(np.floor(a.value), 0, A - 1).astype(int)
    frac = a.value - np.floor(a.value)
    other = np.where(frac < 0.5, b - 1, b + 1)   # the neighbour across the nearer edge
    flips = (np.minimum(frac, 1 - frac) <= a.err) & (other >= 0) & (other <= A - 1)
    other = np.clip(other, 0, A - 1)
    slopes = np.abs(np.diff(G, axis=1)) * inv[None, :, None] if T > 1 else np.zeros((A, 1, L))
    last = slopes.shape[1] - 1
    near = np.maximum(slopes[b, j], np.maximum(slopes[b, np.maximum(j - 1, 0)], slopes[b, np.minimum(j + 1, last)]))
    out = []
    for k in range(L):
        v = const(G[b, j, k]) + f * (const(G[b, j + step, k]) - const(G[b, j, k]))
        o0, o1 = G[other, j, k], G[other, j + step, k]
        flip = np.where(flips, np.abs(o0 + f.value * (o1 - o0) - v.value), 0.0)
        out.append(rd.Bounded(v.value, v.err + flip + near[:, k] * t.err, u))
    return out


def _piecewise_linear(lib, clip, x, nodes, values):
    """The function through the constants ``values [node, m]`` at ``nodes``, linear between
    them, constant beyond: ``v_0 + sum_k m_k (clip(x, x_k, x_k+1) - x_k)``."""
    nodes = np.asarray(nodes, np.float64)
    segments = [clip(x, float(a), float(b)) - float(a) for a, b in zip(nodes[:-1], nodes[1:])]
    g = np.asarray(values, np.float64)
    slopes = np.diff(g, axis=0) / np.diff(nodes)[:, None]
    if lib is np or getattr(lib, "__name__", "") == "torch":  # one matrix product: one MatMul in ONNX
        g0 = lib.asarray(g[0], dtype=x.dtype)  # constants of the evaluation's precision, as elsewhere
        if not segments:
            return x[..., None] * 0.0 + g0
        seg = lib.stack(segments, -1)
        return seg @ lib.asarray(slopes, dtype=seg.dtype) + g0
    out = []
    for k in range(g.shape[1]):
        acc = x * 0.0 + float(g[0, k])
        for segment, m in zip(segments, slopes[:, k]):
            acc = segment * float(m) + acc
        out.append(acc)
    return out


def rounding_bound(spec: NeuralSpec, layers, angles, u: float = None, chunk: int = 4096, lines=()):
    """``(S, err)``: the exported model at ``angles [n, spec.n_queries]`` (the four angles, then
    the extra inputs; exact, float64; the sum of its orders, :func:`order_sum`) and a bound on
    how far an evaluation of it in floating point (unit roundoff ``u``, float32 by
    default) can be from that, per query and wavelength.

    The same encoding (:func:`features`) and output transform (:func:`stable_expm1`) the
    backends run, evaluated in :mod:`models.rounding`'s bounded arithmetic, the layers
    ``[(W, b), ...]`` with Higham's dot-product bound carried by the network's Jacobian
    (:func:`models.rounding.relu_mlp`), the feature ``lines`` (``[n_k, C]`` each) sampled by
    :func:`models.lines.bounded_sample`. Two float32 evaluations (PyTorch and
    onnxruntime, say) differ by at most the sum of their bounds.
    """

    if spec.encoding != "cone":
        raise ValueError(f"no derived rounding bound for the baseline encoding {spec.encoding!r} (a bench's)")
    u = rd.U32 if u is None else u
    angles = np.asarray(angles, np.float64).reshape(-1, spec.n_queries)
    S, err = [], []
    for start in range(0, len(angles), chunk):
        a = [rd.Bounded.exact(c, u) for c in angles[start:start + chunk].T]
        x = features(rd.BOUNDED, spec, *a)
        if spec.lines:
            x = x[:-3] + line_products(spec, lines, x[-3:])
        y = rd.relu_mlp(rd.stack(x, u), layers)
        out = spec.s0 * stable_expm1(rd.BOUNDED, rd.clip(y, 0.0, spec.y_max))
        gain = energy_gain(rd.BOUNDED, spec, a[1], *a[4:])
        if gain is not None:
            out = out * rd.stack(gain, u)
        azimuthal = azimuth_gain(rd.BOUNDED, spec, a[1], a[0], a[2])
        if azimuthal is not None:
            out = out * rd.stack(azimuthal, u)
        out = order_sum(spec, out)
        S.append(out.value)
        err.append(out.err)
    return np.concatenate(S), np.concatenate(err)


def line_products(spec: NeuralSpec, lines, coords) -> list:
    """The ``line_channels`` products ``A_c B_c D_c`` of the lines ``[n_k, C]`` at the
    bounded coordinates ``coords`` (the last three features), in bounded arithmetic."""
    channels = [fl.bounded_sample(line, c, wraps) for line, c, wraps in zip(lines, coords, fl.periodic(spec.folds))]
    return [a * b * d for a, b, d in zip(*channels)]


def make_torch_model(spec: NeuralSpec):
    """The PyTorch module: encoded features -> log-space spectrum (no transform). With
    feature lines, its first element (:func:`models.lines.torch_lines`) turns the line
    coordinates into the lines' products."""
    import torch

    layers, width = [], spec.n_inputs
    if spec.lines:
        layers.append(fl.torch_lines(spec.lines, spec.line_channels, fl.periodic(spec.folds)))
    for h in spec.hidden:
        layers += [torch.nn.Linear(width, h), torch.nn.ReLU()]
        width = h
    layers.append(torch.nn.Linear(width, spec.n_outputs))
    return torch.nn.Sequential(*layers)


def save_weights(path, spec: NeuralSpec, mlp) -> int:
    """Write the PyTorch model ``mlp`` of ``spec`` as ``weights.npz`` (``W0, b0, ...``, the
    feature lines ``L0, L1, L2``, the azimuthal gain ``azimuth_gain`` [and its product's basis
    ``azimuth_gain_basis``], the metadata),
    atomically; returns the bytes of its float32 arrays."""
    import torch

    arrays = {f"L{k}": line.detach().numpy().astype(np.float32)
              for k, line in enumerate(mlp[0].lines)} if spec.lines else {}
    for k, lin in enumerate(m for m in mlp if isinstance(m, torch.nn.Linear)):
        arrays[f"W{k}"] = lin.weight.detach().numpy().astype(np.float32)
        arrays[f"b{k}"] = lin.bias.detach().numpy().astype(np.float32)
    meta = spec.to_dict()
    for name in ("azimuth_gain", "azimuth_gain_basis"):   # thousands of numbers: arrays, not text in the metadata
        if meta[name]:
            arrays[name] = np.asarray(meta.pop(name), np.float32)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            # the metadata as UTF-8 bytes (a numpy str array is UTF-32: 4 bytes a character),
            # the archive deflated (the metadata's text shrinks; the float32 weights hardly)
            np.savez_compressed(fh, spec=np.array(json.dumps(meta).encode("utf-8")), **arrays)
    return sum(a.nbytes for a in arrays.values())


def save_onnx(path, spec: NeuralSpec, mlp) -> None:
    """Write the PyTorch model ``mlp`` of ``spec`` as one ONNX graph, atomically: queries
    ``[batch, spec.n_queries]`` -> ``S [batch, n_lambda]`` (:func:`make_export_module`; a model
    of orders also ``orders [batch, K x n_lambda]``), the batch axis dynamic, the metadata
    ``bcsdf_spec``, checked by ``onnx.checker``."""
    import onnx
    import torch

    names = ["S", "orders"] if spec.orders else ["S"]
    with atomic_path(path) as tmp:
        torch.onnx.export(make_export_module(spec, mlp, orders=bool(spec.orders)).eval(),
                          (torch.zeros(8, spec.n_queries),), tmp, input_names=["angles"], output_names=names,
                          dynamic_axes={"angles": {0: "batch"}, **{n: {0: "batch"} for n in names}},
                          opset_version=17, dynamo=False)
        model = onnx.load(tmp)
        model.doc_string = (f"Bundle scattering function S(phi_i, theta_i, phi_o, theta_o"
                            f"{''.join(', ' + i for i in spec.inputs)}) in 1/sr, one output per wavelength"
                            + (f"; 'orders': its {spec.orders} orders of scattering, order-major"
                               if spec.orders else "") + "; angles in radians")
        entry = model.metadata_props.add()
        entry.key, entry.value = "bcsdf_spec", json.dumps(spec.to_dict())
        onnx.checker.check_model(model)
        onnx.save(model, tmp)


def make_export_module(spec: NeuralSpec, mlp, orders: bool = False):
    """Raw queries [n, spec.n_queries] (the four angles, then the extra inputs) -> S [n, n_lambda]:
    encoding, MLP and output transform in one graph; ``orders``: ``(S, orders [n, K x n_lambda])``
    (a model of orders of scattering, :func:`order_sum`)."""
    import torch

    class Exported(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = mlp

        def forward(self, angles):
            y = self.mlp(torch.stack(features(torch, spec, *angles.unbind(-1)), -1))
            S = spec.s0 * stable_expm1(torch, torch.clamp(y, 0.0, spec.y_max))
            gain = energy_gain(torch, spec, angles[..., 1], *angles[..., 4:].unbind(-1))
            S = S if gain is None else S * gain
            azimuthal = azimuth_gain(torch, spec, angles[..., 1], angles[..., 0], angles[..., 2])
            S = S if azimuthal is None else S * azimuthal
            return (order_sum(spec, S), S) if orders else order_sum(spec, S)

    return Exported()
