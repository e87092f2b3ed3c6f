"""Longitudinal lobes M(theta_i, theta_o) of separable fiber models.

Every lobe is normalized over the outgoing longitude with the cosine of the solid
angle, ``integral_{-pi/2}^{pi/2} M(theta_i, theta_o) cos(theta_o) d theta_o = 1``, so
that a fiber function ``f = sum_p M_p N_p`` integrates over the sphere to
``sum_p integral N_p d phi`` (the project's cosine-included normalization).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special

from ..grid import cell
from ..xp import asin, select, sqrt0


def i0e(x, xp=np):
    """``exp(-|x|) I0(x)``: scipy for numpy; for Dr.Jit the Abramowitz & Stegun 9.8.1-9.8.2
    polynomials (relative error < 2e-7, below float32)."""
    if xp is np:
        return special.i0e(x)
    dr = xp
    ax = dr.abs(x)
    t = dr.square(ax * (1 / 3.75))
    small = 1 + t * (3.5156229 + t * (3.0899424 + t * (1.2067492 + t * (0.2659732 + t * (0.0360768 + t * 0.0045813)))))
    small = small * dr.exp(-ax)
    u = 3.75 / dr.maximum(ax, 3.75)
    large = (0.39894228 + u * (0.01328592 + u * (0.00225319 + u * (-0.00157565 + u * (0.00916281 + u * (
        -0.02057706 + u * (0.02635537 + u * (-0.01647633 + u * 0.00392377)))))))) * dr.rsqrt(dr.maximum(ax, 3.75))
    return dr.select(ax < 3.75, small, large)


def M_deon(theta_i, theta_o, v, xp=np):
    """d'Eon et al. 2011 longitudinal term with variance ``v`` (radians^2).

    ``M = kappa / (2 sinh kappa) exp(-kappa sin ti sin to) I0(kappa cos ti cos to)``,
    ``kappa = 1/v``: a lobe on the specular cone ``theta_o = -theta_i``. Evaluated as
    ``kappa / (1 - e^{-2 kappa}) * i0e(c) * exp(c - s - kappa)`` so that no factor
    overflows for small ``v`` (``c - s - kappa = kappa (cos(ti + to) - 1) <= 0``).
    """
    kappa = 1.0 / float(v)  # a numpy scalar times a Dr.Jit array would become an ndarray
    c = kappa * xp.abs(xp.cos(theta_i)) * xp.cos(theta_o)
    s = kappa * xp.sin(theta_i) * xp.sin(theta_o)
    return float(kappa / -np.expm1(-2.0 * kappa)) * i0e(c, xp) * xp.exp(c - s - kappa)


def M_uniform(theta_i, theta_o, xp=np):
    """Uniform over the sphere: ``M = 1/2`` (``integral cos / 2 = 1``)."""
    return 0.5 + 0.0 * (theta_i + theta_o)


def M_stripes(theta_i, theta_o, n_stripes, xp=np):
    """Grid test pattern: ``n_stripes`` bright bands in ``theta_o``, independent of theta_i.

    The longitude range is cut into ``2 n_stripes`` equal bands, every other one lit;
    the lit bands are normalized so that the lobe integrates to one.
    """
    edges = np.linspace(-np.pi / 2, np.pi / 2, 2 * n_stripes + 1)
    lit_cos = float(sum(np.sin(edges[2 * k + 1]) - np.sin(edges[2 * k]) for k in range(n_stripes)))
    band, _ = cell(theta_o + 0.0 * theta_i, -np.pi / 2, np.pi, 2 * n_stripes, xp=xp)
    return select(xp)(band % 2 == 0, 1.0 / lit_cos, 0.0)


def sample_M(lobe: "Longitudinal", theta_i, u1, u2, xp=np):
    """``theta_o`` with density ``M(theta_i, theta_o) cos(theta_o)``, from two uniforms."""
    if lobe.kind == "deon":
        v = float(lobe.v)
        theta_p = theta_i + float(lobe.shift)
        u1 = xp.maximum(u1, 1e-12)
        # d'Eon et al. 2011: a point on the cone, perturbed by a vMF of concentration 1/v
        cos_t = 1 + v * xp.log(u1 + (1 - u1) * float(np.exp(-2 / v)))
        sin_t = sqrt0(1 - cos_t * cos_t, xp)
        sin_o = -cos_t * xp.sin(theta_p) + sin_t * xp.cos(2 * np.pi * u2) * xp.abs(xp.cos(theta_p))
        return asin(sin_o, xp)
    if lobe.kind == "uniform":
        return asin(2 * u1 - 1, xp)
    if lobe.kind == "stripes":  # the lit bands, each by its share of the cosine
        n = lobe.n_stripes
        edges = np.sin(np.linspace(-np.pi / 2, np.pi / 2, 2 * n + 1))
        lo, hi = edges[0:-1:2], edges[1::2]
        cw = np.cumsum(hi - lo) / np.sum(hi - lo)
        out = 0.0 * u1
        prev = 0.0
        for k in range(n):  # n is small: unrolled band selection
            inside = (u1 >= prev) & (u1 < cw[k]) if k < n - 1 else (u1 >= prev)
            frac = (u1 - prev) / float(cw[k] - prev)
            out = select(xp)(inside, asin(float(lo[k]) + frac * float(hi[k] - lo[k]), xp), out)
            prev = float(cw[k])
        return out
    raise ValueError(f"cannot sample a longitudinal lobe of kind {lobe.kind!r}")


@dataclass(frozen=True)
class Longitudinal:
    """A longitudinal lobe: ``kind`` in {deon, uniform, stripes, none}.

    ``shift`` (radians) tilts the cone as cuticle scales do: the lobe is evaluated at
    ``theta_i + shift``. ``none`` is the constant 1, used by dense lobes whose
    azimuthal table already depends on theta_o. numpy (``xp=np``) or Dr.Jit (``xp=dr``).
    """

    kind: str
    v: float = 0.0
    shift: float = 0.0
    n_stripes: int = 0

    def __call__(self, theta_i, theta_o, xp=np):
        if xp is np:
            theta_i, theta_o = np.broadcast_arrays(np.asarray(theta_i, np.float64), np.asarray(theta_o, np.float64))
        if self.kind == "deon":
            return M_deon(theta_i + float(self.shift), theta_o, self.v, xp)
        if self.kind == "uniform":
            return M_uniform(theta_i, theta_o, xp)
        if self.kind == "stripes":
            return M_stripes(theta_i, theta_o, self.n_stripes, xp)
        if self.kind == "none":
            return 1.0 + 0.0 * (theta_i + theta_o)
        raise ValueError(f"unknown longitudinal lobe kind {self.kind!r}")

    def sample(self, theta_i, u1, u2, xp=np):
        """``theta_o`` with density ``M cos(theta_o)`` (:func:`sample_M`)."""
        return sample_M(self, theta_i, u1, u2, xp)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "v": self.v, "shift": self.shift, "n_stripes": self.n_stripes}
