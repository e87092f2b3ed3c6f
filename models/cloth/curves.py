"""Curves of every BCC type as the uniform cubic B-splines Mitsuba's ``bsplinecurve`` renders.

A curve's *segments* are evaluated by :func:`evaluate` at ``u`` in ``[0, n_segments)``
(segment ``floor(u)``, local parameter ``u - floor(u)``):

* ``catmull_rom`` (``C0``): uniform Catmull-Rom through every control point; an open curve
  runs from its second point to its next-to-last (the BCC specification: the end points
  only give the end tangents), so it needs at least 4;
* ``bspline`` (``BS``): the points are already uniform B-spline control points (an open
  curve does not reach its end points, as in Mitsuba);
* ``bezier`` (``BZ``): cubic Bezier segments sharing end points (``3 n + 1`` points open,
  ``3 n`` closed);
* ``polyline`` (``PL``).

:func:`to_bspline` samples a curve ``m`` times per segment and solves for the B-spline that
interpolates the samples (closed loops periodically, so there is no seam; open curves with
natural ends, so they end at the curve's ends), doubling ``m`` until the B-spline stays
within ``tol`` of the curve. The deviation is measured at matched parameters, 8 points per
B-spline segment: an upper bound of the distance between the two curves.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

KINDS = ("catmull_rom", "bspline", "bezier", "polyline")



def write_mitsuba_curves(file, curves, fmt: str = "%.6f") -> None:
    """Mitsuba's curve text format into the open text ``file``: ``x y z r`` per control point
    (``curves``: ``[n, 4]`` arrays), a blank line between curves."""
    # one %-format per curve (what np.savetxt writes, row by row, at a fraction of its cost)
    for k, C in enumerate(curves):
        C = np.asarray(C, float)
        row = " ".join([fmt] * C.shape[1]) + "\n"
        file.write(("\n" if k else "") + (row * len(C)) % tuple(C.ravel()))

# -- the four curve types --------------------------------------------------------------
def _catmull_rom(P0, P1, P2, P3, t):
    t = t[:, None]
    return 0.5 * (2 * P1 + (P2 - P0) * t + (2 * P0 - 5 * P1 + 4 * P2 - P3) * t**2
                  + (3 * P1 - P0 - 3 * P2 + P3) * t**3)


def _bspline(P0, P1, P2, P3, t):
    t = t[:, None]
    return ((1 - t) ** 3 * P0 + (3 * t**3 - 6 * t**2 + 4) * P1 + (-3 * t**3 + 3 * t**2 + 3 * t + 1) * P2
            + t**3 * P3) / 6


def _bezier(P0, P1, P2, P3, t):
    t = t[:, None]
    return (1 - t) ** 3 * P0 + 3 * (1 - t) ** 2 * t * P1 + 3 * (1 - t) * t**2 * P2 + t**3 * P3


def segment_points(points: np.ndarray, closed: bool, kind: str) -> np.ndarray:
    """The four points ``[n_segments, 4, 3]`` each segment is a cubic of (a polyline's
    segments as ``P_j, P_j, P_j+1, P_j+1``, evaluated linearly)."""
    P = np.asarray(points, np.float64)
    n = len(P)
    if kind not in KINDS:
        raise ValueError(f"curve type {kind!r} is not one of {', '.join(KINDS)}")
    if kind == "bezier":
        if closed:
            if n % 3 or n < 3:
                raise ValueError(f"a closed Bezier curve needs 3 n control points (got {n})")
            P = np.concatenate([P, P[:1]])
        elif (n - 1) % 3 or n < 4:
            raise ValueError(f"an open Bezier curve needs 3 n + 1 control points (got {n})")
        j = np.arange(0, len(P) - 1, 3)
        return np.stack([P[j], P[j + 1], P[j + 2], P[j + 3]], 1)
    if kind == "polyline":
        if closed:
            P = np.concatenate([P, P[:1]])
        return np.stack([P[:-1], P[:-1], P[1:], P[1:]], 1)
    if closed:
        idx = np.arange(n)
        return np.stack([P[(idx + k) % n] for k in (-1, 0, 1, 2)] if kind == "catmull_rom" else
                        [P[(idx + k) % n] for k in (0, 1, 2, 3)], 1)
    if n < 4:
        raise ValueError(f"an open {kind} curve needs at least 4 control points (got {n})")
    j = np.arange(len(P) - 3)
    return np.stack([P[j], P[j + 1], P[j + 2], P[j + 3]], 1)


def evaluate(points, closed: bool, kind: str, u: np.ndarray) -> np.ndarray:
    """Positions ``[len(u), 3]`` at curve parameters ``u`` in ``[0, n_segments]``."""
    S = segment_points(points, closed, kind)
    u = np.asarray(u, np.float64)
    j = np.clip(np.floor(u).astype(np.int64), 0, len(S) - 1)
    t = u - j
    P0, P1, P2, P3 = (S[j, k] for k in range(4))
    if kind == "polyline":
        return P1 + (P2 - P1) * t[:, None]
    return {"catmull_rom": _catmull_rom, "bspline": _bspline, "bezier": _bezier}[kind](P0, P1, P2, P3, t)


def n_segments(points, closed: bool, kind: str) -> int:
    return len(segment_points(points, closed, kind))


# -- B-spline interpolation ----------------------------------------------------------
def interpolate_bspline(Q: np.ndarray, closed: bool) -> np.ndarray:
    """Uniform cubic B-spline control points whose curve passes through ``Q[j]`` at its knots.

    Closed: ``(C_j-1 + 4 C_j + C_j+1) / 6 = Q_j`` cyclically; returns ``C`` with its first
    three points appended (``len(Q)`` segments, the loop closed with no seam). Open: the same
    rows plus natural ends (``C_0 - 2 C_1 + C_2 = 0`` at both ends), so the curve starts at
    ``Q_0`` and ends at ``Q_-1`` (``len(Q) - 1`` segments).

    ``Q`` may be ``[N, ..., 3]``: many curves of ``N`` samples each, solved together (one
    factorization), ``C`` then ``[M, ..., 3]``.
    """

    Q = np.asarray(Q, np.float64)
    N, tail = len(Q), Q.shape[1:]
    Q = Q.reshape(N, -1)
    if closed:
        if N < 3:
            raise ValueError(f"a closed curve needs at least 3 distinct samples (got {N})")
        rows = np.repeat(np.arange(N), 3)
        cols = (rows + np.tile([-1, 0, 1], N)) % N
        A = sp.csr_matrix((np.tile([1 / 6, 4 / 6, 1 / 6], N), (rows, cols)), shape=(N, N))
        C = np.asarray(spsolve(A.tocsc(), Q)).reshape((N,) + tail)
        C = np.roll(C, 1, axis=0)  # segment j (C_j..C_j+3) then starts at Q_j
        return np.concatenate([C, C[:3]])
    if N < 2:
        raise ValueError(f"an open curve needs at least 2 distinct samples (got {N})")
    M = N + 2
    r, c, v = [], [], []
    for j in range(N):
        r += [j + 1] * 3
        c += [j, j + 1, j + 2]
        v += [1 / 6, 4 / 6, 1 / 6]
    r += [0, 0, 0, M - 1, M - 1, M - 1]
    c += [0, 1, 2, M - 3, M - 2, M - 1]
    v += [1, -2, 1, 1, -2, 1]
    A = sp.csr_matrix((v, (r, c)), shape=(M, M))
    b = np.zeros((M, Q.shape[1]))
    b[1:-1] = Q
    if M <= 64:  # short curves (flyaways), many at once: a dense solve is cheaper than SuperLU's set-up
        return np.linalg.solve(A.toarray(), b).reshape((M,) + tail)
    return np.asarray(spsolve(A.tocsc(), b)).reshape((M,) + tail)


def bspline_samples(C: np.ndarray, per_segment: int) -> np.ndarray:
    """Points of the uniform B-spline with control points ``C`` (as Mitsuba reads them), ``per_segment``
    per segment, the curve's end included."""
    n = len(C) - 3
    u = np.concatenate([np.arange(n * per_segment) / per_segment, [n]])
    return evaluate(C, False, "bspline", u)


def to_bspline(points, closed: bool, kind: str, tol: float, max_per_segment: int = 64):
    """``(C, deviation, m)``: B-spline control points ``C`` (Mitsuba's layout) within ``tol``
    of the curve, the measured deviation, and the samples per source segment used.

    A ``bspline`` curve is converted exactly (a closed one gets its first three points
    appended). Raises if ``max_per_segment`` samples per segment do not reach ``tol``.
    """
    P = np.asarray(points, np.float64)
    if kind == "bspline":
        C = np.concatenate([P, P[:3]]) if closed else P
        if len(C) < 4:
            raise ValueError(f"a B-spline needs at least 4 control points (got {len(P)})")
        return C, 0.0, 1
    n = n_segments(P, closed, kind)
    m = 1 if kind == "catmull_rom" else 2
    while True:
        u = np.arange(n * m + (0 if closed else 1)) / m
        C = interpolate_bspline(evaluate(P, closed, kind, u), closed)
        k = 8  # check points per B-spline segment, at matched parameters
        v = np.arange(n * m * k) / k                       # B-spline parameter
        deviation = float(np.max(np.linalg.norm(evaluate(C, False, "bspline", v)
                                                - evaluate(P, closed, kind, v / m), axis=1)))
        if deviation <= tol:
            return C, deviation, m
        if 2 * m > max_per_segment:
            raise ValueError(f"a {kind} curve of {len(P)} points stays {deviation:.3g} from its B-spline at "
                             f"{m} samples per segment (tolerance {tol:.3g}); it has corners or cusps")
        m *= 2
