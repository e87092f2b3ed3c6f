"""Explicit fibers: every fiber of a ply as its own curve (the ground truth of a cloth render),
and patches of a model (a few stitches) small enough to render them.

A ply's fibers are the bake's arrangement (``centres[n, 2]``, ``radii[n]`` in the ply's
cross-section, bounding radius ``R_b``) scaled to the ply's radius and carried along the
ply's centre line in its rotation-minimizing frame: parallel to the ply, as the bake
assumes (the twisted-ply bake is another issue's). Each fiber is a uniform cubic B-spline
through its samples, as the plies are.
"""

from __future__ import annotations

import numpy as np

from .bcc import Curve, CurveCollection
from .curves import bspline_samples, interpolate_bspline
from .plies import transport_frames


def explicit_fibers(plies: list[np.ndarray], r_ply: float, centres, radii, R_b: float,
                    per_segment: int = 2) -> tuple[list[np.ndarray], np.ndarray]:
    """``(curves, radius per curve)``: the fibers of every ply (B-spline control points in
    Mitsuba's layout; open plies only: patches are cut open)."""
    centres = np.asarray(centres, float) * (r_ply / R_b)
    radii = np.asarray(radii, float) * (r_ply / R_b)
    curves, r_out = [], []
    for C in plies:
        p = bspline_samples(C, per_segment)
        f = transport_frames(p, closed=False)
        for (x, z), r in zip(centres, radii):
            curves.append(interpolate_bspline(p + x * f.n + z * f.b, closed=False))
            r_out.append(r)
    return curves, np.array(r_out)


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
