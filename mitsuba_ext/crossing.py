"""How light crosses and leaves a bundle, as small pure functions for ``bundle_path``:
the displaced exit point, the far side of the bundle, offset rays, the bundle radius of a
shape, the MIS weight; and the checks of a scene's bundles and integrator.

No Mitsuba variant is needed to import this module (the plugin class in
``mitsuba_ext.integrator`` needs one).
"""

from __future__ import annotations

import contextlib
import sys
import threading

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_ext.frame import SINGLE_FIBERS, fiber_on_linear_curve


# -- who renders a bundle -----------------------------------------------------------
# ``bundle_path`` marks the thread while it traces; a ``fiber_bundle`` evaluated inside
# ``mi.render`` with no mark is being rendered by another integrator and refuses, so that a
# hand-built scene keeps the rule ``bcsdf render-scene`` checks on loading
_TRACING = threading.local()

OTHER_INTEGRATOR = ("fiber_bundle is rendered by an integrator other than bundle_path, which would render it "
                    "without passthrough in its shadow rays and without its displaced exits (darker, wrongly): "
                    "use the bundle_path integrator ({'type': 'bundle_path'}, or <integrator type=\"bundle_path\"> "
                    "in XML; it takes path's max_depth and rr_depth)")


@contextlib.contextmanager
def tracing(who: str):
    """Mark this thread as rendered by ``who``: ``"bundle_path"`` (the integrator, around its
    ``sample``), or ``"any"``: a reference that renders a bundle under another integrator
    knowing what it leaves out (a test of one part of ``bundle_path``)."""
    before = getattr(_TRACING, "who", None)
    _TRACING.who = who
    try:
        yield
    finally:
        _TRACING.who = before


def refuse_other_integrators() -> None:
    """Raise where a bundle is evaluated inside ``mi.render`` (a Python function: its frame is
    on this thread's stack) with no integrator's mark. Evaluations outside a render (a test, a
    chi-square check, an analysis through ``si.bsdf()``) pass."""
    if getattr(_TRACING, "who", None) is not None:
        return
    render = getattr(getattr(mi, "render", None), "__code__", None)
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code is render:
            raise RuntimeError(OTHER_INTEGRATOR)
        frame = frame.f_back


# -- small pure functions ----------------------------------------------------------
def mis_weight(pdf_a, pdf_b):
    """Power heuristic, as Mitsuba's ``path`` (zero where undefined)."""
    a, b = dr.square(pdf_a), dr.square(pdf_b)
    w = a / (a + b)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))


def bundle_axis(si):
    """Unit tangent and in-plane outward normal of a bundle hit (``None``-safe: finite)."""
    t = si.sh_frame.t
    ok = dr.isfinite(dr.sum(t)) & (dr.squared_norm(t) > 0.25) & dr.isfinite(dr.sum(si.n))
    t = dr.select(ok, dr.normalize(t), mi.Vector3f(0, 1, 0))
    n_perp = si.n - dr.dot(si.n, t) * t
    ok &= dr.squared_norm(n_perp) > 1e-8
    return t, dr.select(ok, dr.normalize(n_perp), mi.Vector3f(0, 0, 1)), ok


def displaced_exit(si, r, h, w):
    """Where light scattered into ``w`` leaves a bundle of radius ``r`` (thesis 3.3).

    A ray in direction ``w``, shifted sideways from the bundle's axis by ``h r`` along
    the side vector ``t x w``, leaves the bounding cylinder at
    ``c + r (h s + sqrt(1 - h^2) o)`` in the cross-section of the hit (``c`` the axis
    point, ``o`` the direction of ``w`` in that plane). Fibers are parallel and the
    table knows no axial displacement, so the exit stays in the hit's cross-section.
    Returns the exit point and its outward radial direction (for the ray offset).
    """
    t, n_perp, ok = bundle_axis(si)
    c = si.p - r * n_perp
    w_perp = w - dr.dot(w, t) * t
    ok &= dr.squared_norm(w_perp) > 1e-10
    o = dr.normalize(w_perp)
    s = dr.cross(t, o)
    radial = h * s + dr.safe_sqrt(1.0 - dr.square(h)) * o
    p = c + r * radial
    ok &= r > 0
    return dr.select(ok, p, si.p), dr.select(ok, radial, si.n)


def far_side(si, r, d):
    """Where a ray entering a bundle of radius ``r`` at ``si`` along ``d`` leaves it.

    The far end of the chord in the hit's cross-section, and the outward radial
    direction there (for the ray offset). Spawning the continuing ray there, rather
    than just inside the entry point, crosses the bundle as one null event: a ray
    spawned a float epsilon inside a long thin cylinder was seen to hit the same
    entry wall again (from outside: a second scattering event for the same light).
    """
    t, n_perp, ok = bundle_axis(si)
    d_perp = d - dr.dot(d, t) * t
    dd = dr.squared_norm(d_perp)
    ok &= (dd > 1e-10) & (r > 0)
    s = dr.maximum(-2.0 * r * dr.dot(n_perp, d_perp) / dr.maximum(dd, 1e-10), 0.0)
    p = si.p + s * d
    c = si.p - r * n_perp
    radial = (p - c) - dr.dot(p - c, t) * t
    radial = dr.normalize(dr.select(dr.squared_norm(radial) > 0, radial, n_perp))
    return dr.select(ok, p, si.p), dr.select(ok, radial, si.n), ok


def offset_ray(p, n, d, wavelengths, maxt=None):
    """A ray from ``p`` pushed off its surface along ``n`` (Mitsuba's spawn offset).

    It carries the path's ``wavelengths``: a spectral ray without them sees every
    emitter at 0 nm, i.e. black.
    """
    eps = (1.0 + dr.max(dr.abs(p))) * mi.math.RayEpsilon
    o = p + dr.mulsign(n, dr.dot(n, d)) * eps
    ray = mi.Ray3f(o, d, 0.0, wavelengths)
    if maxt is not None:
        ray.maxt = maxt
    return ray


def shape_radius(shape):
    """The bundle radius a ``cylinder``, ``bsplinecurve`` or ``linearcurve`` holds, else ``None``.

    A cylinder's ``to_world`` scales its unit cylinder by the radius across the axis;
    a curve's control points carry it as their fourth coordinate (a range if it varies).
    """
    kind = shape.shape_type()
    params = mi.traverse(shape)
    if kind == int(mi.ShapeType.Cylinder):
        m = np.asarray(params["to_world"].matrix).reshape(4, 4)
        r = float(np.linalg.norm(m[:3, 0]))
        return r, r
    if kind in (int(mi.ShapeType.BSplineCurve), int(mi.ShapeType.LinearCurve)):
        radii = np.asarray(params["control_points"]).reshape(-1, 4)[:, 3]
        return float(radii.min()), float(radii.max())
    return None


def check_bundles(scene) -> list[str]:
    """What is wrong with the bundles of a scene, in words (one line per shape).

    ``fiber_bundle``, ``fiber_table`` and ``fiber_ray`` are defined on cylinders and B-spline curves
    (the frame follows their tangent, the radius comes from their parametrization), the two
    single-fiber ones also on ``linearcurve`` (``bundle_path`` gives its hits their tangent
    frame: :class:`~mitsuba_ext.frame.LinearCurves`); a BSDF ``radius`` that disagrees with the
    shape's is named (the shape's is used).
    """
    problems = []
    tangent_shapes = (int(mi.ShapeType.Cylinder), int(mi.ShapeType.BSplineCurve))
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        plugin = getattr(bsdf, "plugin", None)
        if plugin not in ("fiber_bundle",) + SINGLE_FIBERS:
            continue
        kind = shape.shape_type()
        single = plugin in SINGLE_FIBERS
        if kind not in tangent_shapes and not fiber_on_linear_curve(shape):
            problems.append(f"shape '{shape.id()}' ({mi.ShapeType(kind).name}) has a {plugin} BSDF, which is "
                            "defined on 'cylinder' and 'bsplinecurve' shapes only"
                            + (" (and 'linearcurve')" if single else "")
                            + ": its frame and radius are meaningless on this shape")
            continue
        lo, hi = shape_radius(shape)
        r = float(getattr(bsdf, "radius", 0.0))
        if r > 0 and not (0.99 * lo <= r <= 1.01 * hi):
            problems.append(f"shape '{shape.id()}': the {plugin} BSDF's radius {r:g} disagrees with the shape's "
                            f"({lo:g}" + (f" .. {hi:g}" if hi > lo else "") + "); the shape's is used, drop the "
                            "BSDF's 'radius' or make them agree")
    return problems


def check_integrator(scene) -> str | None:
    """Why ``scene``'s integrator cannot render its bundles, or ``None``.

    ``fiber_bundle`` is a far-field model with passthrough and displaced exits that only
    ``bundle_path`` carries out; under Mitsuba's ``path`` (or any other) integrator it
    renders without an error but wrong. A Python BSDF cannot see its integrator, so the
    entry points (``bcsdf render-scene``) ask here after loading.
    """
    integrator = type(scene.integrator()).__name__
    if integrator == "BundlePathIntegrator":
        return None
    why = []
    if any(getattr(shape.bsdf(), "plugin", None) == "fiber_bundle" for shape in scene.shapes()):
        why.append("fiber_bundle BSDFs need the bundle_path integrator (passthrough, displaced exits)")
    if any(map(fiber_on_linear_curve, scene.shapes())):
        why.append("fiber BSDFs on 'linearcurve' need the bundle_path integrator (their tangent frame)")
    if why:
        return (f"the scene's {' and its '.join(why)}, but its integrator is {integrator}: "
                "use <integrator type=\"bundle_path\"> (it takes path's max_depth and rr_depth)")
    return None
