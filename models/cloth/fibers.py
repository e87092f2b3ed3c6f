"""Explicit fibers: every fiber of a ply as its own curve (the ground truth of a cloth render),
and patches of a model (a few stitches) small enough to render them.

A ply's fibers are the bake's arrangement (``centres[n, 2]``, ``radii[n]`` in the ply's
cross-section, bounding radius ``R_b``) scaled to the ply's radius and carried along the
ply's centre line in its rotation-minimizing frame: parallel to the ply, or, for a twisted
ply (``pitch_um``, signed as :class:`~models.bundle.TwistedBundle`'s), turned along it as
the twisted bake's helices are, the pitch scaled with the cross-section so that the fibers
lean as in the bake. Each fiber is a uniform cubic B-spline through its samples, as the
plies are.

The bundle frame ``(x, y = axis, z)`` maps onto the ply's frame ``(n, t, -b)`` (``b = t x
n``): a rotation, so that a right-handed helix of the bake stays right-handed along the ply.
"""

from __future__ import annotations

import numpy as np

from .bcc import Curve, CurveCollection
from .curves import bspline_samples, interpolate_bspline
from .plies import transport_frames

SAMPLES_PER_TURN = 32   # of a twisted ply's helices: the B-spline strays ~1e-4 of rho from each


def explicit_fibers(plies: list[np.ndarray], r_ply: float, centres, radii, R_b: float,
                    per_segment: int = 2, pitch_um: float | None = None) -> tuple[list[np.ndarray], np.ndarray]:
    """``(curves, radius per curve)``: the fibers of every ply (B-spline control points in
    Mitsuba's layout; open plies only: patches are cut open). ``pitch_um``: the twisted
    ply's signed pitch in the cross-section's units (``None``: parallel fibers)."""
    scale = r_ply / R_b
    centres = np.asarray(centres, float) * scale
    radii = np.asarray(radii, float) * scale
    omega = _turn_rate(pitch_um, scale)
    curves, r_out = [], []
    for C in plies:
        p = bspline_samples(C, _samples_per_segment(C, omega, per_segment))
        f = transport_frames(p, closed=False)
        a = np.zeros(len(p)) if omega is None else omega * f.s
        c, s = np.cos(a)[:, None], np.sin(a)[:, None]
        for (x, z), r in zip(centres, radii):
            # the cross-section at arc length s turned by omega s (phi from x towards z)
            curves.append(interpolate_bspline(p + (c * x - s * z) * f.n - (s * x + c * z) * f.b, closed=False))
            r_out.append(r)
    return curves, np.array(r_out)


def _turn_rate(pitch_um, scale):
    """The helices' turn per scene unit of ply length (``None``: parallel fibers)."""
    return None if pitch_um is None else -2 * np.pi / (float(pitch_um) * scale)


def _samples_per_segment(C, omega, per_segment: int, samples_per_turn: int = SAMPLES_PER_TURN) -> int:
    """Samples per ply segment: ``samples_per_turn`` for every turn of the helices."""
    if omega is None:
        return per_segment
    step = np.linalg.norm(np.diff(bspline_samples(C, 1), axis=0), axis=1).max()
    return max(per_segment, int(np.ceil(step * abs(omega) * samples_per_turn / (2 * np.pi))))


def explicit_point_count(plies: list[np.ndarray], r_ply: float, n_fibers: int, R_b: float,
                         per_segment: int = 2, pitch_um: float | None = None,
                         samples_per_turn: int = SAMPLES_PER_TURN) -> int:
    """Control points :func:`explicit_fibers` would make for ``n_fibers`` fibers in every
    ply, without making them (a whole garment's fibers do not fit in memory);
    ``samples_per_turn`` of the helices (:data:`SAMPLES_PER_TURN`: what it makes)."""
    omega = _turn_rate(pitch_um, r_ply / R_b)
    # interpolate_bspline of the samples (the end included) adds the two natural ends; a
    # closed loop's fibers, closed, would hold as many (its three repeated points)
    per_fiber = sum((len(C) - 3) * _samples_per_segment(C, omega, per_segment, samples_per_turn) + 3 for C in plies)
    return int(n_fibers * per_fiber)


def patch(collection: CurveCollection, centre, radius: float, min_points: int = 6) -> CurveCollection:
    """The parts of every curve whose control points lie within ``radius`` of ``centre``, each
    run of consecutive points an open curve (a closed loop's run may wrap past its start)."""
    centre = np.asarray(centre, float)
    out = []
    for c in collection.curves:
        inside = np.linalg.norm(c.points - centre, axis=1) <= radius
        if not inside.any():
            continue
        n = len(inside)
        if inside.all():
            out.append(Curve(c.points.copy(), c.closed))
            continue
        # start scanning just after an outside point, so a run that wraps stays whole
        start = int(np.argmin(inside)) if c.closed else 0
        order = (np.arange(n) + start) % n if c.closed else np.arange(n)
        run = []
        for i in list(order) + [None]:
            if i is not None and inside[i]:
                run.append(i)
                continue
            if len(run) >= min_points:
                out.append(Curve(c.points[run].copy(), False))
            run = []
    if not out:
        raise ValueError(f"no curve has {min_points} control points within {radius} of {centre.tolist()}")
    return CurveCollection(out, collection.kind, collection.up)
