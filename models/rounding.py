"""What "float32 rounding" allows: forward error bounds, derived from the arithmetic.

A check that two evaluations agree "to rounding" needs a bound that follows from the
operations performed, evaluated on the inputs checked; a number that passed on one
machine fails on the next CPU whose kernels sum in another order. The bounds here are
the standard model of floating-point arithmetic (Higham, *Accuracy and Stability of
Numerical Algorithms*, 2002):

* every basic operation is exact, then rounded: ``fl(a op b) = (a op b)(1 + delta)``,
  ``|delta| <= u`` with the unit roundoff ``u = 2^-24`` (float32) or ``2^-53`` (float64);
* a dot product of ``n`` terms plus a bias, in any summation order, with or without
  FMA (Higham eq. 3.5): ``|fl(w.x + b) - (w.x + b)| <= gamma_{n+1} (|w|.|x| + |b|)``,
  ``gamma_n = n u / (1 - n u)``;
* an elementary function (sin, cos, exp) is within ``ELEMENTARY_ULPS`` units in the
  last place of its exact value: SLEEF's ``u10`` functions (torch's vectorized
  kernels) and MKL's HA mode document 1 ulp, glibc at most 1-2 for these, Eigen and
  MLAS (onnxruntime) and Dr.Jit's CEPHES ports about 2 on their domains (Dr.Jit's sin
  and cos: ``|x| < 8192``). One ulp of ``z`` is at most ``2 u |z|``.

Errors already in an operand propagate to first order through the operation's
derivative (bounded here by its maximum over the operand's error interval), so a bound
is an ordinary evaluation that carries ``err`` beside ``value``: :class:`Bounded`, and
:data:`BOUNDED`, the array module to hand to a formula written once with an array-module
parameter (``models.neural.features``, ``models.neural.stable_expm1``). The bound is
then of the very code that the backends run.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

U32 = 2.0 ** -24
U64 = 2.0 ** -53
ELEMENTARY_ULPS = 2.0


def gamma(n, u: float = U32) -> float:
    """Higham's ``gamma_n = n u / (1 - n u)``: the relative error bound of n roundings."""
    n = np.asarray(n, np.float64)
    return n * u / (1.0 - n * u)


def _constant_error(c: float, u: float) -> float:
    """A Python float becomes a constant of the working precision: its representation
    error (exact for float32; at most ``u |c|`` for a coarser one; none for float64)."""
    if u == U32:
        return float(np.abs(float(np.float32(c)) - c))
    return u * float(np.abs(c)) if u > U32 else 0.0


class Bounded:
    """An array with an absolute error bound: the floating-point evaluation (unit
    roundoff ``u``) of the expression that made it differs from the exact value at most
    by ``err``. ``value`` is the expression evaluated in float64 (the exact value to
    within ``2^-53``, which the bound's own second-order terms cover)."""

    __array_priority__ = 100  # numpy arrays defer to Bounded's operators

    def __init__(self, value, err=0.0, u: float = U32):
        self.value = np.asarray(value, np.float64)
        self.err = np.broadcast_to(np.asarray(err, np.float64), self.value.shape).copy()
        self.u = u

    @classmethod
    def exact(cls, value, u: float = U32) -> "Bounded":
        """An input, exactly representable in the working precision."""
        return cls(value, 0.0, u)

    def _lift(self, other) -> "Bounded":
        if isinstance(other, Bounded):
            return other
        c = float(other)
        return Bounded(c, _constant_error(c, self.u), self.u)

    def _rounded(self, value, err) -> "Bounded":
        """The exact result of an operation on the operands, then one rounding."""
        return Bounded(value, err + self.u * (np.abs(value) + err), self.u)

    def __add__(self, other):
        o = self._lift(other)
        return self._rounded(self.value + o.value, self.err + o.err)

    __radd__ = __add__

    def __neg__(self):
        return Bounded(-self.value, self.err, self.u)

    def __sub__(self, other):
        return self + (-self._lift(other))

    def __rsub__(self, other):
        return self._lift(other) + (-self)

    def __mul__(self, other):
        o = self._lift(other)
        err = np.abs(self.value) * o.err + np.abs(o.value) * self.err + self.err * o.err
        return self._rounded(self.value * o.value, err)

    __rmul__ = __mul__

    def __truediv__(self, other):
        o = self._lift(other)
        if np.any(np.abs(o.value) <= o.err):
            raise ValueError("a divisor's error interval holds 0: no bound")
        q = self.value / o.value
        # first order, the divisor's interval kept off zero: |d(a/b)| <= (e_a + |q| e_b) / (|b| - e_b)
        err = (self.err + np.abs(q) * o.err) / (np.abs(o.value) - o.err)
        return self._rounded(q, err)

    def __lt__(self, other):
        o = self._lift(other)
        d = self.value - o.value
        return BoundedMask(d < 0, np.abs(d) <= self.err + o.err)

    def __gt__(self, other):
        return self._lift(other) < self


class BoundedMask:
    """A comparison of bounded values: its exact outcome, and where rounding could flip it."""

    def __init__(self, value, ambiguous):
        self.value = np.asarray(value, bool)
        self.ambiguous = np.asarray(ambiguous, bool)


def _elementary(x: Bounded, f, slope) -> Bounded:
    """``f(x)`` within ELEMENTARY_ULPS ulp, the operand's error carried by ``slope``, the
    largest |f'| over the error interval."""
    value = f(x.value)
    err = slope(x) * x.err
    return Bounded(value, err + ELEMENTARY_ULPS * 2 * x.u * (np.abs(value) + err), x.u)


def sin(x: Bounded) -> Bounded:
    return _elementary(x, np.sin, lambda x: np.minimum(1.0, np.abs(np.cos(x.value)) + x.err))


def cos(x: Bounded) -> Bounded:
    return _elementary(x, np.cos, lambda x: np.minimum(1.0, np.abs(np.sin(x.value)) + x.err))


def exp(x: Bounded) -> Bounded:
    return _elementary(x, np.exp, lambda x: np.exp(x.value + x.err))


def floor(x: Bounded) -> Bounded:
    """An integer, exact. Where ``x``'s error reaches an integer the floor may differ by
    one; the only use (wrapping an azimuth by 2 pi, models/lines.py) feeds a periodic or
    mirrored line whose values agree across that seam."""
    return Bounded(np.floor(x.value), 0.0, x.u)


def absolute(x: Bounded) -> Bounded:
    return Bounded(np.abs(x.value), x.err, x.u)


def clip(x: Bounded, lo, hi) -> Bounded:
    """Clamping is 1-Lipschitz; a float bound itself is rounded to the working precision."""
    lo_, hi_ = x._lift(lo), x._lift(hi)
    value = np.clip(x.value, lo_.value, hi_.value)
    at_bound = np.where(x.value <= lo_.value, lo_.err, np.where(x.value >= hi_.value, hi_.err, 0.0))
    return Bounded(value, x.err + at_bound, x.u)


def where(mask: BoundedMask, a, b) -> Bounded:
    """``mask ? a : b``; where rounding could flip the mask, either branch may be taken."""
    a, b = (v if isinstance(v, Bounded) else Bounded(v) for v in (a, b))
    value = np.where(mask.value, a.value, b.value)
    err = np.where(mask.value, a.err, b.err)
    both = np.maximum(a.err, b.err) + np.abs(a.value - b.value)
    return Bounded(value, np.where(mask.ambiguous, np.maximum(err, both), err), a.u)


def maximum(x: Bounded, c: float) -> Bounded:
    """``max(x, c)`` (ReLU for c = 0): 1-Lipschitz."""
    return Bounded(np.maximum(x.value, c), x.err, x.u)


def relu_mlp(x: Bounded, layers) -> Bounded:
    """A ReLU network ``[(W, b), ...]`` (ReLU between layers, none after the last) on
    ``x [n, k]``, with an error bound propagated through the network's own Jacobian.

    Carrying errors layer after layer through ``|W|`` ignores that the network's weights
    cancel, and so grows like the product of the layers' absolute row sums: correct, but
    often 1000x the actual error. Here each error source (the
    inputs' error, and every layer's own rounding ``gamma_{n+1} (|W| |x| + |b|)``) is
    carried to the output by the Jacobian of the rest of the network at the exact
    activations, as midpoint-radius intervals: a ReLU whose input lies within the crude
    bound of its kink may have slope 0 or 1 and gets the interval [0, 1]. First order in
    the errors (terms in ``u^2`` dropped, as in Higham's running error analyses).
    """
    u = x.u
    # forward: exact activations, each layer's own rounding, a crude bound to find kinks
    acts, own, crude, kinks = [x.value], [x.err], x.err, []
    for k, (W, b) in enumerate(layers):
        W, b = np.asarray(W, np.float64), np.asarray(b, np.float64)
        aW = np.abs(W)
        z = acts[-1] @ W.T + b
        rounding = gamma(W.shape[1] + 1, u) * ((np.abs(acts[-1]) + crude) @ aW.T + np.abs(b))
        crude = crude @ aW.T + rounding
        own.append(rounding)
        if k < len(layers) - 1:
            kinks.append((z > 0, np.abs(z) <= crude))  # (slope 1, slope uncertain)
            acts.append(np.maximum(z, 0.0))
    y = z
    # backward: d y / d source as intervals c +- r, one source per layer
    n, m = y.shape
    c = np.broadcast_to(np.eye(m), (n, m, m)).copy()
    r = np.zeros_like(c)
    err = np.einsum("nij,nj->ni", c, own[-1])  # the last layer's rounding, as it is
    for k in range(len(layers) - 1, -1, -1):
        W = np.asarray(layers[k][0], np.float64)
        c, r = c @ W, r @ np.abs(W)  # d y / d (input of layer k)
        if k > 0:  # that input is relu(z) of the layer before
            on, unsure = kinks[k - 1]
            lo, hi = np.minimum(c - r, 0.0), np.maximum(c + r, 0.0)  # slope in [0, 1]
            c = np.where(unsure[:, None], 0.5 * (lo + hi), np.where(on[:, None], c, 0.0))
            r = np.where(unsure[:, None], 0.5 * (hi - lo), np.where(on[:, None], r, 0.0))
        err = err + np.einsum("nij,nj->ni", np.abs(c) + r, own[k])
    return Bounded(y, err, u)


def stack(columns, u: float = U32) -> Bounded:
    """A list of bounded arrays (or floats) as the columns of one ``[n, k]`` array."""
    cols = [c if isinstance(c, Bounded) else Bounded(c, 0.0, u) for c in columns]
    shape = np.broadcast_shapes(*(c.value.shape for c in cols))
    return Bounded(np.stack([np.broadcast_to(c.value, shape) for c in cols], -1),
                   np.stack([np.broadcast_to(c.err, shape) for c in cols], -1), u)


# The array module of bounded arithmetic, for formulas written with an array-module parameter.
BOUNDED = SimpleNamespace(sin=sin, cos=cos, exp=exp, abs=absolute, clip=clip, where=where, maximum=maximum,
                          floor=floor)
