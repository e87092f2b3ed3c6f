"""Evaluate an exported bundle MLP: through onnxruntime, or as Dr.Jit arithmetic.

Both take raw angles in radians and return ``S`` in 1/sr for every table wavelength,
agreeing with PyTorch to float32 rounding. :func:`check_compatible` refuses a model
whose metadata does not match the table, wavelengths or bundle it is used with.

Example::

    import drjit as dr, mitsuba as mi
    mi.set_variant("llvm_ad_mono")
    from mitsuba_ext.neural import DrJitMLP
    mlp = DrJitMLP("artifacts/default/export/medium/weights.npz")
    S = mlp.eval(phi_i, theta_i, phi_o, theta_o)   # list of n_lambda mi.Float
"""

from __future__ import annotations

import copy
import json
import zipfile

import drjit as dr
import drjit.llvm
import drjit.nn as nn
import mitsuba as mi
import numpy as np

from models import lines as fl
from models.jit import to_drjit
from models.neural import NeuralSpec, azimuth_gain, check_inputs, energy_gain, features, order_sum, stable_expm1
from models.queries import directions


def load_weights(path):
    """``(spec, [(W, b), ...], lines)`` from a ``weights.npz`` written by ``bcsdf export``;
    ``lines`` the feature lines' nodes ``[n_k, C]`` (``L0, L1, L2``; none for a plain MLP); the
    azimuthal gain, where the model has one, is an array of its own put back into ``spec``."""
    if str(path).endswith(".onnx"):  # np.load would advise unpickling it
        raise ValueError(f"{path}: an ONNX graph, not the plain weights the Dr.Jit evaluator reads; give its "
                         "weights.npz (beside it), or evaluate the graph with OnnxMLP (backend 'onnx')")
    try:
        with np.load(path, allow_pickle=False) as z:
            text = z["spec"]  # UTF-8 bytes; an older export's numpy str
            meta = json.loads(text.item().decode("utf-8") if text.dtype.kind == "S" else str(text))
            for name in ("azimuth_gain", "azimuth_gain_basis"):   # arrays beside the metadata (save_weights)
                if name in z:
                    meta[name] = z[name].astype(np.float64).tolist()
            spec = NeuralSpec.from_dict(meta)
            layers = []
            while f"W{len(layers)}" in z:
                k = len(layers)
                layers.append((z[f"W{k}"].astype(np.float32), z[f"b{k}"].astype(np.float32)))
            lines = [z[f"L{k}"].astype(np.float32) for k in range(3)] if spec.lines else []
    except (OSError, EOFError, KeyError, ValueError, json.JSONDecodeError, zipfile.BadZipFile) as e:
        # numpy's words for a file that is no .npz archive advise unpickling it: not for a user
        why = "not a .npz archive of arrays" if "pickle" in str(e) else str(e)
        raise ValueError(f"{path}: not a readable model weights file ({why}); re-run `bcsdf export`") from e
    widths = [spec.n_inputs] + list(spec.hidden) + [spec.n_outputs]
    if [W.shape for W, _ in layers] != list(zip(widths[1:], widths[:-1])):
        raise ValueError(f"{path}: weight shapes {[W.shape for W, _ in layers]} do not match the metadata")
    if [L.shape for L in lines] != [(n, spec.line_channels) for n in spec.lines]:
        raise ValueError(f"{path}: feature line shapes {[L.shape for L in lines]} do not match the metadata")
    if not all(np.all(np.isfinite(a)) for a in [*lines, *(a for layer in layers for a in layer)]):
        raise ValueError(f"{path}: weights hold NaN or Inf")
    return spec, layers, lines


def check_compatible(spec: NeuralSpec, *, table_hash=None, wavelength=None, relative_phi=None) -> None:
    """Refuse a model made for another table, other wavelengths or another bundle shape."""
    if table_hash is not None and spec.table_hash != table_hash:
        raise ValueError(f"model was trained on table {spec.table_hash}, not on this table ({table_hash}); "
                         "re-run `bcsdf train` and `bcsdf export` for this scene")
    if wavelength is not None and not np.allclose(np.asarray(wavelength, float), spec.wavelength):
        raise ValueError(f"model predicts {len(spec.wavelength)} wavelengths {spec.wavelength[0]:.0f}.."
                         f"{spec.wavelength[-1]:.0f} nm, the scene asks for {len(wavelength)}; re-export")
    if relative_phi is not None and bool(relative_phi) != spec.relative_phi:
        kind = "rotation-invariant (circular)" if spec.relative_phi else "elliptical"
        raise ValueError(f"model was trained for a {kind} bundle; this bundle is not")


class OnnxMLP:
    """The exported ONNX graph on onnxruntime (CPU); numpy in, numpy out."""

    def __init__(self, path, threads: int = 0):
        import onnxruntime as ort

        self.path = str(path)
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own types for corrupt files
            raise ValueError(f"{path}: onnxruntime cannot load it ({e}); re-run `bcsdf export`") from e
        meta = self.session.get_modelmeta().custom_metadata_map
        if "bcsdf_spec" not in meta:
            raise ValueError(f"{path}: no bcsdf metadata; not a model written by `bcsdf export`")
        try:
            self.spec = NeuralSpec.from_dict(json.loads(meta["bcsdf_spec"]))
        except (ValueError, TypeError) as e:
            raise ValueError(f"{path}: {e}; re-run `bcsdf export`") from None
        names = [o.name for o in self.session.get_outputs()]
        if names != (["S", "orders"] if self.spec.orders else ["S"]):
            raise ValueError(f"{path}: the graph's outputs {names} are not those its metadata names; "
                             "re-run `bcsdf export`")
        probe = (0.0, 0.3, 1.0, -0.3, *[0.0] * len(self.spec.inputs))  # the graph must predict what its metadata says
        for orders, n in [(False, len(self.spec.wavelength))] + ([(True, self.spec.n_outputs)] if self.spec.orders
                                                                 else []):
            out = self.eval(*probe, orders=orders)
            if out.shape != (n,) or not np.all(np.isfinite(out)):
                raise ValueError(f"{path}: the graph returns {out.shape[-1] if out.ndim else 0} values per query, "
                                 f"its metadata names {n}; re-run `bcsdf export`")

    def eval(self, phi_i, theta_i, phi_o, theta_o, *extra, orders: bool = False) -> np.ndarray:
        """``S`` at every table wavelength, ``[..., n_lambda]`` (radians in, checked:
        :func:`models.queries.directions`; ``extra``: the model's extra inputs, ``spec.inputs``);
        ``orders``: a model's orders of scattering instead, ``[..., K x n_lambda]``."""
        queries = np.stack(np.broadcast_arrays(*directions(phi_i, theta_i, phi_o, theta_o),
                                               *checked_extra(self.spec, extra)), -1).astype(np.float32)
        return self.session.run(["orders" if orders else "S"], {"angles": queries.reshape(-1, self.spec.n_queries)}
                                )[0].reshape(queries.shape[:-1] + (-1,))


def checked_extra(spec: NeuralSpec, extra) -> list:
    """The extra inputs of a numpy query, one per ``spec.inputs``, finite (a wrong count or a NaN
    is refused by name)."""
    check_inputs(spec, len(extra))
    out = [np.asarray(v, np.float64) for v in extra]
    for name, v in zip(spec.inputs, out):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"the model's input {name!r} holds NaN or Inf")
    return out


def _default_float():
    """The active Mitsuba variant's ``Float``, else Dr.Jit's LLVM ``Float``."""
    if mi.variant() is not None:
        return mi.Float

    return drjit.llvm.Float


# Networks with more weights than this are evaluated with cooperative vectors outside
# symbolic loops and calls on the LLVM backend, where that is faster to compile and to run
# (docs/BENCHMARKS.md, "The Dr.Jit MLP: literal weights or cooperative vectors").
LITERAL_WEIGHTS_MAX = 16384


class DrJitMLP:
    """The MLP as Dr.Jit arithmetic, fused into the caller's kernel.

    Any Dr.Jit float type works (the inputs' type is used): LLVM or CUDA, scalar or AD.
    Two formulations of the same arithmetic, which agree with PyTorch to float32 rounding:

    * ``literal``: every weight a Python float, so a literal in the traced kernel. The
      fastest inside a symbolic loop or call (a render: several times faster than
      cooperative vectors there), but LLVM's compile time grows faster than the network:
      a [128, 128, 128] network takes most of a minute to compile, [64, 64, 64] seconds.
    * ``cooperative``: the layers as ``drjit.nn`` matrix-vector products on packed
      weights (LLVM backend only; literal elsewhere). Compiles in about a second at any
      size; in a plain kernel (a batch of queries) the large network also runs faster.

    ``form="auto"`` (the default) is ``cooperative`` for a network of more than
    :data:`LITERAL_WEIGHTS_MAX` weights evaluated outside a symbolic scope on the LLVM
    backend, ``literal`` otherwise: renders always trace literal weights.
    """

    FORMS = ("auto", "literal", "cooperative")

    def __init__(self, path, form: str = "auto"):
        if form not in self.FORMS:
            raise ValueError(f"form={form!r}: choose one of {', '.join(self.FORMS)}")
        self.spec, self.layers, self.lines = load_weights(path)
        self._stored = [fl.stored(L, w).ravel() for L, w in zip(self.lines, fl.periodic(self.spec.folds))]
        self._nodes = {}  # Float type -> the lines' nodes as flat arrays of that type
        self.form = form
        # Python floats become literals in the traced kernel
        self._layers = [(W.astype(float).tolist(), b.astype(float).tolist()) for W, b in self.layers]
        self._packed = {}  # tensor type -> the packed matrix and bias views of every layer

    def with_spec(self, spec: NeuralSpec) -> "DrJitMLP":
        """This network read with other metadata of the same model (a family's at two of
        its trained packings: :func:`models.neural.bracketed`); the weights are shared."""
        view = copy.copy(self)
        view.spec = spec
        return view

    def cooperative(self, Float) -> bool:
        """Whether inputs of type ``Float`` are evaluated with cooperative vectors here
        (the answer of ``auto`` depends on whether a symbolic loop or call is being traced)."""
        if self.form == "literal" or dr.backend_v(Float) != dr.JitBackend.LLVM:
            return False
        if self.form == "cooperative":
            return True
        return not dr.flag(dr.JitFlag.SymbolicScope) and sum(W.size for W, _ in self.layers) > LITERAL_WEIGHTS_MAX

    def eval(self, phi_i, theta_i, phi_o, theta_o, *extra, orders: bool = False):
        """``S`` at every table wavelength (radians in; never negative); ``extra``: the
        model's extra inputs (``spec.inputs``, e.g. the exit line's offset ``h``); ``orders``:
        a model's orders of scattering instead, ``K x n_lambda`` (order-major).

        Dr.Jit arrays in (any float type, e.g. ``mi.Float``): a list of ``n_lambda``
        arrays of that type, traced into the caller's kernel. numpy arrays (or floats)
        in: a numpy array ``[..., n_lambda]``, computed with the active Mitsuba
        variant's ``Float`` (Dr.Jit's LLVM backend if none is set); numpy arguments are
        checked (:func:`models.queries.directions`), traced ones are the caller's to check.
        """
        args = (phi_i, theta_i, phi_o, theta_o, *extra)
        if not any(dr.is_array_v(a) for a in args):
            Float = _default_float()
            checked = np.broadcast_arrays(*directions(phi_i, theta_i, phi_o, theta_o), *checked_extra(self.spec, extra))
            shape = checked[0].shape
            flat = [to_drjit(Float, np.ascontiguousarray(a, np.float32).ravel()) for a in checked]
            return np.stack([np.asarray(s) for s in self.eval(*flat, orders=orders)], -1).reshape(shape + (-1,))
        Float = type(next(a for a in args if dr.is_array_v(a)))
        x = features(dr, self.spec, phi_i, theta_i, phi_o, theta_o, *extra)
        if self.spec.lines:
            x = x[:-3] + self._line_products(Float, x[-3:])
        y = self._matvec(Float, x) if self.cooperative(Float) else self._literal(x)
        s0, y_max = self.spec.s0, self.spec.y_max
        S = [s0 * stable_expm1(dr, dr.clip(v, 0.0, y_max)) for v in y]
        gain = energy_gain(dr, self.spec, theta_i, *extra)
        S = S if gain is None else [s * g for s, g in zip(S, gain)]
        azimuthal = azimuth_gain(dr, self.spec, theta_i, phi_i, phi_o)
        S = S if azimuthal is None else [s * g for s, g in zip(S, azimuthal)]
        return S if orders else order_sum(self.spec, S)

    def _line_products(self, Float, coords):
        """``A_c B_c D_c`` at the line coordinates: a gather and a lerp per line and channel,
        the arithmetic of models/lines.py's PyTorch module."""
        if Float not in self._nodes:
            self._nodes[Float] = [Float(a) for a in self._stored]
        C, UInt = self.spec.line_channels, dr.uint32_array_t(Float)
        product = None
        for nodes, coord, n, wraps in zip(self._nodes[Float], coords, self.spec.lines, fl.periodic(self.spec.folds)):
            i0, t = fl.node_position(dr, coord, n, wraps)
            first = UInt(i0) * C
            v = []
            for c in range(C):
                a, b = dr.gather(Float, nodes, first + c), dr.gather(Float, nodes, first + (C + c))
                v.append(a + t * (b - a))
            product = v if product is None else [p * q for p, q in zip(product, v)]
        return product

    def _literal(self, x):
        for k, (W, b) in enumerate(self._layers):
            last = k == len(self._layers) - 1
            out = []
            for row, bias in zip(W, b):
                acc = x[0] * row[0] + bias
                for xi, w in zip(x[1:], row[1:]):
                    acc = dr.fma(xi, w, acc)
                out.append(acc if last else dr.maximum(acc, 0.0))
            x = out
        return x

    def _matvec(self, Float, x):
        Tensor = dr.tensor_t(Float)
        if Tensor not in self._packed:
            self._packed[Tensor] = nn.pack(*(Tensor(np.ascontiguousarray(a)) for layer in self.layers for a in layer))
        views = self._packed[Tensor]
        v = nn.CoopVec(*(x_k + dr.zeros(Float, 1) for x_k in x))  # a feature may be a Python float
        for k in range(len(self.layers)):
            v = nn.matvec(views[2 * k], v, views[2 * k + 1])
            if k < len(self.layers) - 1:
                v = dr.maximum(v, 0.0)
        return list(v)

    @property
    def nbytes(self) -> int:
        return sum(W.nbytes + b.nbytes for W, b in self.layers) + sum(L.nbytes for L in self.lines) + \
            4 * self.spec.azimuth_gain_values
