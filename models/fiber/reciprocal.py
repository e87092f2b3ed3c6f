"""The reciprocal form of a separable lobe: ``N`` at the half angle, a symmetric scale.

A smooth cylinder scatters light from ``w_i`` onto the cone ``theta_o = -theta_i`` with
an azimuthal pattern ``N(dphi; |theta_i|)``; a rough fiber spreads that cone with a
longitudinal lobe ``M``. Taking ``N`` at ``theta_i`` off the cone (the lobe-separable
form of pbrt's hair) breaks reciprocity: a physical fiber obeys

    f(w_i -> w_o) cos(theta_i) = f(w_o -> w_i) cos(theta_o)        (Helmholtz, per unit length)

and the d'Eon lobe alone misses it by ``cos(theta_o) / cos(theta_i)``. The form here
keeps it exactly:

    f(w_i -> w_o) = c(theta_i) c(theta_o) M(theta_i, theta_o) N(dphi; |theta_d|) cos(theta_o) / cos(theta_d)

with the half angle ``theta_d = (theta_i - theta_o) / 2`` (``= theta_i`` on the cone,
``-theta_d`` when ``i`` and ``o`` swap), ``M`` d'Eon's symmetric lobe, ``N`` even in
``dphi`` (the Mie pattern is), so ``f cos(theta_i)`` is symmetric term by term. The
weight ``cos(theta_o) / cos(theta_d)`` is one on the cone. Off it, and near grazing
incidence where the cone's cosines change fastest, the form would no longer integrate to
the pattern's albedo (by half as much again near grazing, for a lobe of a few degrees), so the symmetric scale ``c``
(one number per node and wavelength) is solved for by symmetric Sinkhorn iteration
so that ``integral f d omega_o = integral N d phi`` at every node: scaling by
``c(theta_i) c(theta_o)`` keeps the symmetry whatever ``c`` is.

:func:`half_angle` is written once for numpy and Dr.Jit (array-module parameter).
"""

from __future__ import annotations

import numpy as np

from ..grid import linear


def half_angle(theta_i, theta_o, xp):
    """``(|theta_d|, cos(theta_o) / cos(theta_d))`` for numpy (``xp=np``) or Dr.Jit (``xp=dr``)."""
    theta_d = 0.5 * (theta_i - theta_o)
    # |theta_d| <= pi/2, so cos(theta_d) >= 0; it is 0 only for (pi/2, -pi/2), where cos(theta_o) is 0 too
    return xp.abs(theta_d), xp.cos(theta_o) / xp.maximum(xp.cos(theta_d), 1e-7)


def scale_nodes(c) -> np.ndarray:
    """The scale's own nodes: uniform in ``|theta|`` over [0, pi/2] (finer than the table's:
    the scale changes fastest near grazing incidence, where the cone closes)."""
    return np.linspace(0.0, np.pi / 2, len(c))


def scale_at(c, abs_theta):
    """``c`` interpolated linearly in ``|theta|`` (numpy): [..., n_lambda]."""
    i0, i1, w = linear(scale_nodes(c), abs_theta)
    return (1 - w)[..., None] * c[i0] + w[..., None] * c[i1]


def composite_gauss(n_panels: int = 720, order: int = 4):
    """Nodes and weights on [-pi/2, pi/2]: Gauss-Legendre of ``order`` on ``n_panels`` panels."""
    x, w = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(-np.pi / 2, np.pi / 2, n_panels + 1)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    return (mid[:, None] + half[:, None] * x[None, :]).ravel(), (half[:, None] * w[None, :]).ravel()


def symmetric_scale(nodes, longitudinal, albedo, n_scale: int = 181, tol: float = 1e-10,
                    max_iter: int = 50) -> np.ndarray:
    """Scale ``c[n_scale, lambda]`` so that the reciprocal form integrates to the albedo.

    ``nodes``: the table's ``|theta_i|`` nodes; ``longitudinal``: the lobe's ``M``;
    ``albedo[node, lambda]``: ``integral N d phi`` per table node, interpolated linearly
    as the table does. ``c`` lives on its own :func:`scale_nodes` (half a degree
    apart by default) and is interpolated linearly; the energy at scale node ``k`` is
    ``E_k = c_k sum_j B_kj c_j`` (``B``: composite Gauss-Legendre over ``theta_o`` of the unscaled
    form against the hat functions of the nodes); ``E = albedo`` is solved by Newton's
    method from ``c = 1`` (symmetric Sinkhorn scaling, converging in a few steps).
    """
    def albedo_at(abs_theta):
        i0, i1, w = linear(np.asarray(nodes, np.float64), abs_theta)
        return (1 - w)[..., None] * albedo[i0] + w[..., None] * albedo[i1]

    albedo = np.asarray(albedo, np.float64)
    s_nodes = np.linspace(0.0, np.pi / 2, n_scale)
    theta_o, w_o = composite_gauss()      # 0.25 deg panels: resolves a lobe of 1 deg
    n_quad = len(theta_o)
    ti = s_nodes[:, None]
    abs_d, weight = half_angle(ti, theta_o[None, :], np)
    # the unscaled form integrated over phi: M A(theta_d) w cos(theta_o) d theta_o
    K = (longitudinal(ti, theta_o[None, :]) * weight * np.cos(theta_o)[None, :] * w_o[None, :])[..., None] \
        * albedo_at(abs_d)                                                # [node, quad, lambda]
    target = albedo_at(s_nodes)                                           # [node, lambda]
    j0, j1, wj = linear(s_nodes, np.abs(theta_o))                        # hat functions at the points
    H = np.zeros((n_quad, n_scale))
    np.add.at(H, (np.arange(n_quad), j0), 1 - wj)
    np.add.at(H, (np.arange(n_quad), j1), wj)
    B = np.einsum("nql,qj->lnj", K, H)                                    # [lambda, node, node]
    c = np.ones((albedo.shape[1], n_scale))
    for _ in range(max_iter):
        Bc = np.einsum("lnj,lj->ln", B, c)
        F = c * Bc - target.T
        if np.max(np.abs(F)) < tol * max(1.0, albedo.max()):
            break
        J = B * c[:, :, None] + np.eye(n_scale)[None] * Bc[:, :, None]
        c = c - np.linalg.solve(J, F[..., None])[..., 0]
    else:
        raise FloatingPointError("the reciprocal scale did not converge; is the lobe resolvable on the nodes?")
    if np.any(c <= 0) or not np.all(np.isfinite(c)):
        raise FloatingPointError("the reciprocal scale is not positive")
    return c.T
