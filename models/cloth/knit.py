"""A stockinette swatch from a closed form: centre lines for tests and examples, no download.

Each course (row) of plain knit is one yarn, the published closed-form loop curve

    x(t) = W / (2 pi) (t + a sin 2t),   y(t) = H / 2 cos t + j D,   z(t) = Z / 2 cos 2t,

``t`` over ``2 pi`` per loop: ``x`` advances one wale per loop, the ``sin 2t`` term bends
the loop's legs outwards, ``cos t`` takes the yarn down and up through the row below
(rows ``D`` apart overlap by ``H - D``), ``cos 2t`` takes it through the fabric's
thickness so that neighbouring rows interlock. Sizes are in yarn radii ``r``; the defaults
(a loose knit) keep every two yarns at least a yarn diameter apart, centre to centre, and
bend no yarn tighter than its radius once interpolated (``tests/test_cloth.py`` checks both).
"""

from __future__ import annotations

import numpy as np

from .bcc import Curve, CurveCollection


def stockinette(courses: int = 4, wales: int = 6, r: float = 1.0, W: float = 12.0, H: float = 10.0,
                D: float = 8.0, Z: float = 3.5, a: float = 0.3, per_loop: int = 32) -> CurveCollection:
    """``courses`` open yarns of ``wales`` loops each, as uniform Catmull-Rom control points
    (``r``: the yarn radius in the model's units; the other sizes in units of ``r``)."""
    if courses < 1 or wales < 1:
        raise ValueError(f"a swatch needs at least one course and one wale (got {courses} x {wales})")
    if per_loop < 8:
        raise ValueError(f"at least 8 control points per loop are needed (got {per_loop})")
    # one control point beyond each end: an open Catmull-Rom's end points are its tangents
    step = 2 * np.pi / per_loop
    t = np.linspace(-step, 2 * np.pi * wales + step, wales * per_loop + 3)
    curves = []
    for j in range(courses):
        x = W / (2 * np.pi) * (t + a * np.sin(2 * t))
        y = H / 2 * np.cos(t) + j * D
        z = Z / 2 * np.cos(2 * t)
        curves.append(Curve(r * np.stack([x, y, z], -1), closed=False))
    return CurveCollection(curves, "catmull_rom", up=1)
