"""Plies wound about a yarn's centre line, in a frame that never flips.

A yarn's centre line ``c(s)`` (arc length ``s``) carries a rotation-minimizing frame
``(t, n, b)`` (parallel transport, by the double-reflection method of Wang et al. 2008:
no flips where the curve is straight or turns back). On a closed loop the transported
normal comes back turned by the loop's holonomy angle; that angle is spread evenly along
the loop, so the frame is continuous where the loop closes. Ply ``k`` of ``K`` is

    p_k(s) = c(s) + R (cos a_k(s) n(s) + sin a_k(s) b(s)),   a_k = 2 pi (k / K + sign s / pitch),

a helix of radius ``R`` about the centre line; ``sign`` is the twist direction (Zhao et
al.'s ``alpha_ply < 0``: clockwise). On a closed loop the pitch is rounded to a whole
number of turns per loop, so every ply closes on itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass
class Frames:
    """Samples of a centre line: positions, tangents, normals, binormals ``[n, 3]`` and arc
    lengths ``s[n]`` (a closed loop's last sample is not its first again; ``length`` is the
    whole loop's)."""

    p: np.ndarray
    t: np.ndarray
    n: np.ndarray
    b: np.ndarray
    s: np.ndarray
    length: float
    closed: bool

    def at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(p, t, n, b)`` at arc lengths ``s`` (any shape, within ``[0, length]``), linearly
        between the samples (round a closed loop's seam too), one search for all twelve
        coordinates. Not unit length between samples: callers that need a frame
        re-orthonormalize."""
        knots = np.append(self.s, self.length) if self.closed else self.s
        table = np.concatenate([self.p, self.t, self.n, self.b], axis=1)
        table = np.concatenate([table, table[:1]]) if self.closed else table
        s = np.asarray(s, np.float64)
        j = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, len(knots) - 2)
        w = ((s - knots[j]) / (knots[j + 1] - knots[j]))[..., None]
        f = (1 - w) * table[j] + w * table[j + 1]
        return f[..., 0:3], f[..., 3:6], f[..., 6:9], f[..., 9:12]


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _transport(p: np.ndarray, t: np.ndarray, n0: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Normals carried along ``p`` by double reflection (Wang, Juettler, Zheng, Liu 2008), and
    on a closed loop the normal carried back to the start. Plain floats: one step is a few
    dozen operations, where numpy's per-call cost would dominate."""
    P, T = p.tolist(), t.tolist()
    N = [tuple(n0)]
    steps = len(P) if closed else len(P) - 1
    for i in range(steps):
        j = (i + 1) % len(P)
        (px, py, pz), (qx, qy, qz) = P[i], P[j]
        v1 = (qx - px, qy - py, qz - pz)
        c1 = v1[0] ** 2 + v1[1] ** 2 + v1[2] ** 2
        n, ti, tj = N[i], T[i], T[j]
        a = 2 / c1 * (v1[0] * n[0] + v1[1] * n[1] + v1[2] * n[2])
        rL = (n[0] - a * v1[0], n[1] - a * v1[1], n[2] - a * v1[2])
        a = 2 / c1 * (v1[0] * ti[0] + v1[1] * ti[1] + v1[2] * ti[2])
        v2 = (tj[0] - ti[0] + a * v1[0], tj[1] - ti[1] + a * v1[1], tj[2] - ti[2] + a * v1[2])
        c2 = v2[0] ** 2 + v2[1] ** 2 + v2[2] ** 2
        a = 2 / c2 * (v2[0] * rL[0] + v2[1] * rL[1] + v2[2] * rL[2]) if c2 > 1e-30 else 0.0
        N.append((rL[0] - a * v2[0], rL[1] - a * v2[1], rL[2] - a * v2[2]))
    N = np.array(N)
    return N[: len(P)], N[-1]


def transport_frames(p: np.ndarray, closed: bool, stride: int = 1) -> Frames:
    """Rotation-minimizing frames at the samples ``p[n, 3]`` (tangents by central
    differences), transported along every ``stride``-th sample and interpolated between."""
    p = np.asarray(p, np.float64)
    seg = np.linalg.norm(np.diff(np.concatenate([p, p[:1]]) if closed else p, axis=0), axis=1)
    tiny = 1e-12 * max(1.0, float(np.abs(p).max()))
    if np.any(seg <= tiny):
        raise ValueError(f"the centre line has coincident samples (at sample {int(np.argmax(seg <= tiny))}); "
                         "remove zero-length segments")
    if closed:
        t = _unit(np.roll(p, -1, 0) - np.roll(p, 1, 0))
        s = np.concatenate([[0.0], np.cumsum(seg[:-1])])
        length = float(seg.sum())
    else:
        t = _unit(np.gradient(p, axis=0))
        s = np.concatenate([[0.0], np.cumsum(seg)])
        length = float(s[-1])
    # the first normal: any vector perpendicular to the first tangent
    a = np.eye(3)[int(np.argmin(np.abs(t[0])))]
    n0 = _unit(a - np.dot(a, t[0]) * t[0])
    keep = np.arange(0, len(p), max(1, int(stride)))
    if not closed and keep[-1] != len(p) - 1:
        keep = np.append(keep, len(p) - 1)
    n_coarse, n_end = _transport(p[keep], t[keep], n0, closed)
    if closed:
        # the holonomy: the angle about t[0] from the normal carried round the loop to n[0];
        # turned back evenly along the loop, so the frame is continuous where the loop closes
        n_end = _unit(n_end - np.dot(n_end, t[0]) * t[0])
        angle = np.arctan2(np.dot(np.cross(n_end, n0), t[0]), np.dot(n_end, n0))
        b_coarse = np.cross(t[keep], n_coarse)
        phi = (angle * s[keep] / length)[:, None]
        n_coarse = np.cos(phi) * n_coarse + np.sin(phi) * b_coarse
        knots, values = np.append(s[keep], length), np.concatenate([n_coarse, n_coarse[:1]])
    else:
        knots, values = s[keep], n_coarse
    n = np.stack([np.interp(s, knots, values[:, d]) for d in range(3)], -1)
    n = _unit(n - np.sum(n * t, -1, keepdims=True) * t)
    return Frames(p, t, n, np.cross(t, n), s, length, closed)


def wind_plies(frames: Frames, K: int, R: float, pitch: float, samples_per_turn: int = 16,
               min_samples: int = 0) -> tuple[list[np.ndarray], float]:
    """Centre lines of ``K`` plies about ``frames``'s curve: ``([K][m, 3], pitch used)``.

    ``pitch`` is signed (the twist direction). The plies are sampled ``samples_per_turn``
    times per turn of their helix (an interpolating B-spline through 16 samples a turn
    strays about 1e-4 of ``R`` from a helix: ``tests/test_cloth.py``), and at least
    ``min_samples`` times along the curve (the caller's measure of the centre line's own
    detail: :func:`~models.cloth.yarn.build_plies` asks for two per segment of the file's
    curve). Sampling the plies as densely as the centre line's samples instead holds many more
    control points for the same curves (the cloth bench's ``speed`` part counts them).
    """
    if K < 1:
        raise ValueError(f"a yarn needs at least one ply (got K = {K})")
    if pitch == 0:
        raise ValueError("the ply pitch must not be zero")
    L = frames.length
    turns = L / abs(pitch)
    if frames.closed:
        turns = max(1, round(turns))   # a whole number of turns: every ply closes on itself
        pitch = np.sign(pitch) * L / turns
    m = int(max(np.ceil(turns * samples_per_turn), min_samples, 3))
    s = np.arange(m) * (L / m) if frames.closed else np.linspace(0, L, m + 1)
    # the frame between the centre line's samples, linearly (they are denser than the ply's)
    c, t, n, _ = frames.at(s)
    n = _unit(n - np.sum(n * t, -1, keepdims=True) * t)
    b = np.cross(_unit(t), n)
    plies = []
    for k in range(K):
        a = 2 * np.pi * (k / K + s / pitch)
        plies.append(c + R * (np.cos(a)[:, None] * n + np.sin(a)[:, None] * b))
    return plies, float(pitch)


def nearest_other(curves: list[np.ndarray], closed: list[bool], along_min: float, within: float | None = None,
                  k: int = 32) -> np.ndarray:
    """For every sample of ``curves`` (concatenated), the distance to the nearest sample of
    another curve, or of its own curve more than ``along_min`` away along it: where yarns
    touch or interpenetrate. ``inf`` where there is none nearer than ``within`` (default:
    ``along_min``).

    A sample whose ``k`` nearest all lie on its own pass, the farthest of them nearer than
    ``within``, is asked again with 4x as many, until it is decided (a thick yarn's pass
    holds many samples within a diameter)."""

    within = along_min if within is None else within
    pts = np.concatenate(curves)
    owner = np.concatenate([np.full(len(c), i) for i, c in enumerate(curves)])
    s = np.concatenate([np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
                        for c in curves])
    length = np.array([float(np.linalg.norm(np.diff(np.concatenate([c, c[:1]]) if cl else c, axis=0),
                                            axis=1).sum()) for c, cl in zip(curves, closed)])
    loop = np.array(closed)[owner]
    tree, out, todo = cKDTree(pts), np.full(len(pts), np.inf), np.arange(len(pts))
    while len(todo):
        kk = min(k, len(pts))
        for c0 in range(0, len(todo), max(1, 2**22 // kk)):  # blocks: [block, kk] stays small
            at = todo[c0:c0 + max(1, 2**22 // kk)]
            d, j = tree.query(pts[at], k=kk, distance_upper_bound=within)
            found = np.isfinite(d)
            j = np.where(found, j, 0)
            gap = np.abs(s[j] - s[at, None])
            gap = np.where(loop[at, None], np.minimum(gap, length[owner[at]][:, None] - gap), gap)
            other = found & ((owner[j] != owner[at, None]) | (gap > along_min))
            out[at] = np.where(other, d, np.inf).min(axis=1)
            # undecided: every one of the kk nearest is its own pass, and the ball holds more
            out[at[np.isinf(out[at]) & found[:, -1]]] = -1.0
        if kk == len(pts):
            break
        todo, k = np.flatnonzero(out == -1.0), 4 * k
    return np.where(out < 0, np.inf, out)


def bend_radius(p: np.ndarray) -> np.ndarray:
    """The radius of the circle through each three consecutive samples ``p[n, 3]`` (``n - 2``
    values; ``inf`` where they are collinear): a tube of radius ``r`` about the curve folds
    through itself where this is under ``r``."""
    a, b = np.diff(p[:-1], axis=0), np.diff(p[1:], axis=0)
    chord = np.linalg.norm(p[2:] - p[:-2], axis=1)
    twice_area = np.linalg.norm(np.cross(a, b), axis=1)
    with np.errstate(divide="ignore"):
        return np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) * chord / (2 * twice_area)
