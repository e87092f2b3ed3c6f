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


def M_deon(theta_i, theta_o, v):
    """d'Eon et al. 2011 longitudinal term with variance ``v`` (radians^2).

    ``M = kappa / (2 sinh kappa) exp(-kappa sin ti sin to) I0(kappa cos ti cos to)``,
    ``kappa = 1/v``: a lobe on the specular cone ``theta_o = -theta_i``. Evaluated as
    ``kappa / (1 - e^{-2 kappa}) * i0e(c) * exp(c - s - kappa)`` so that no factor
    overflows for small ``v`` (``c - s - kappa = kappa (cos(ti + to) - 1) <= 0``).
    """
    kappa = 1.0 / v
    ci, si = np.cos(theta_i), np.sin(theta_i)
    co, so = np.cos(theta_o), np.sin(theta_o)
    c = kappa * np.abs(ci) * co
    s = kappa * si * so
    return kappa / -np.expm1(-2.0 * kappa) * special.i0e(c) * np.exp(c - s - kappa)


def M_uniform(theta_i, theta_o):
    """Uniform over the sphere: ``M = 1/2`` (``integral cos / 2 = 1``)."""
    return np.full(np.broadcast(theta_i, theta_o).shape, 0.5)


def M_stripes(theta_i, theta_o, n_stripes):
    """Grid test pattern: ``n_stripes`` bright bands in ``theta_o``, independent of theta_i.

    The longitude range is cut into ``2 n_stripes`` equal bands, every other one lit;
    the lit bands are normalized so that the lobe integrates to one.
    """
    edges = np.linspace(-np.pi / 2, np.pi / 2, 2 * n_stripes + 1)
    lit_cos = sum(np.sin(edges[2 * k + 1]) - np.sin(edges[2 * k]) for k in range(n_stripes))
    band = np.clip(np.floor((np.asarray(theta_o) + np.pi / 2) / (np.pi / (2 * n_stripes))), 0, 2 * n_stripes - 1)
    lit = (band.astype(int) % 2) == 0
    return np.broadcast_to(np.where(lit, 1.0 / lit_cos, 0.0), np.broadcast(theta_i, theta_o).shape)


@dataclass(frozen=True)
class Longitudinal:
    """A longitudinal lobe: ``kind`` in {deon, uniform, stripes, none}.

    ``shift`` (radians) tilts the cone as cuticle scales do: the lobe is evaluated at
    ``theta_i + shift``. ``none`` is the constant 1, used by dense lobes whose
    azimuthal table already depends on theta_o.
    """

    kind: str
    v: float = 0.0
    shift: float = 0.0
    n_stripes: int = 0

    def __call__(self, theta_i, theta_o):
        if self.kind == "deon":
            return M_deon(np.asarray(theta_i) + self.shift, theta_o, self.v)
        if self.kind == "uniform":
            return M_uniform(theta_i, theta_o)
        if self.kind == "stripes":
            return M_stripes(theta_i, theta_o, self.n_stripes)
        if self.kind == "none":
            return np.ones(np.broadcast(theta_i, theta_o).shape)
        raise ValueError(f"unknown longitudinal lobe kind {self.kind!r}")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "v": self.v, "shift": self.shift, "n_stripes": self.n_stripes}
