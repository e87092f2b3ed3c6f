"""A path's weight at a fiber event, shared by the parallel and the twisted tracers.

``B[lambda]`` carries ``f cos(theta_out) / pdf`` over the path's events (``pdf`` per
``d theta_out d phi``, the fiber's importance sampler), ``R[lambda]`` the weight absorbed on
the way (the expected loss ``B (1 - albedo)`` at each event); Russian roulette from
``rr_start`` events on keeps a path with probability ``min(1, max_lambda B)`` and divides
its weight by it, so the estimate stays unbiased.
"""

from __future__ import annotations

import drjit as dr


def scatter(B: list, R: list | None, f: list, albedo: list | None, theta_out, pdf, go, depth, rr_start: int, u_rr):
    """The weights after one event of the lanes ``go``: ``(B, R, kept, roulette)``; ``kept``
    is false where the sample was invalid or the roulette stopped the path, ``roulette``
    where it played (its uniform ``u_rr`` is spent there). ``R`` None: no absorption kept
    (a camera path's throughput, ``models.bake.camera``)."""
    L = len(B)
    scale = dr.cos(theta_out) / dr.maximum(pdf, 1e-30)
    valid = go & (pdf > 0)
    if R is not None:
        R = [dr.select(go, R[l] + B[l] * (1 - albedo[l]), R[l]) for l in range(L)]
    B = [dr.select(go, B[l] * f[l] * scale, B[l]) for l in range(L)]
    roulette = depth > rr_start
    q = B[0]
    for l in range(1, L):
        q = dr.maximum(q, B[l])
    q = dr.minimum(q, 1.0)
    survive = ~roulette | (u_rr < q)
    B = [dr.select(go & roulette, B[l] / dr.maximum(q, 1e-30), B[l]) for l in range(L)]
    return B, R, valid & survive, roulette


def curve_value(lob, theta_in, theta_out, dphi, h_out, w, f):
    """The ``curve`` exit's value (both bakers): ``w`` times the adjoint of the h-resolved
    ray fiber ``lob`` at ``h_out`` (``None``: the far field ``f``)."""
    value = f if lob is None else lob.adjoint(theta_in, h_out, theta_out, dphi)
    return [v * w for v in value]


def curve_event(lob, theta_in, theta_out, dphi, h_out, w, f, alb):
    """``(f, albedo)`` of an event with the ``curve`` exit: its value, and the albedo scaled
    as the value is scaled from the sampled ``f`` (so that ``weights.scatter`` books the
    difference as absorbed and the balance stays closed)."""
    value = curve_value(lob, theta_in, theta_out, dphi, h_out, w, f)
    ratio = [dr.select(a > 0, v / dr.maximum(a, 1e-30), 0.0) for v, a in zip(value, f)]
    return value, [a * q for a, q in zip(alb, ratio)]
