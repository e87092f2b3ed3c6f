"""The geometry and colour the curve BSDFs share, as small pure functions: the bundle
frame along a curve, angles in it, which side is the light's, spectra to a variant's
colours, and file parameters resolved like Mitsuba's own.

No Mitsuba variant is needed to import this module (the plugin classes in
``mitsuba_ext.bsdf`` need one).
"""

from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from models.bake import tally
from models.spectrum import hat_basis, spectrum_to_srgb


# -- small pure functions: the geometry of the bundle frame -----------------------
def arc_length(si):
    """Distance along the shape from its start, ``v |dp/dv|``.

    On ``cylinder`` and ``bsplinecurve``, ``v = si.uv.y`` runs from 0 to 1 along the
    shape (on a curve file, along all its curves in turn), so ``v |dp/dv|`` is the arc
    length exactly on a cylinder and on curves of constant parametric speed (evenly
    spaced control points); elsewhere it is the local estimate. Zero where the shape
    gives no derivative.
    """
    s = si.uv.y * dr.norm(si.dp_dv)
    return dr.select(dr.isfinite(s), s, 0.0)


def bundle_frame(si, up, twist, twist_rate):
    """World axes ``(x, t, z)`` of the bundle frame at ``si``.

    ``t`` is the curve tangent (the shading frame's second axis on ``cylinder`` and
    ``bsplinecurve``); ``x`` is ``up`` projected perpendicular to ``t`` and turned about
    ``t`` by ``twist + twist_rate * s`` (radians, and radians per scene unit of the
    :func:`arc_length` ``s``), so an elliptical bundle's major axis winds along the
    curve at the same pitch whatever the curve's length. Degenerate tangents or an
    ``up`` parallel to the tangent fall back to a frame built from the normal.
    """
    t = si.sh_frame.t
    bad_t = ~dr.isfinite(dr.sum(t)) | (dr.squared_norm(t) < 0.25)
    n_ok = dr.isfinite(dr.sum(si.n)) & (dr.squared_norm(si.n) > 0.25)
    t_alt, _ = mi.coordinate_system(dr.select(n_ok, dr.normalize(si.n), mi.Vector3f(0, 0, 1)))
    t = dr.normalize(dr.select(bad_t, t_alt, t))
    x0 = up - dr.dot(up, t) * t
    x_alt, _ = mi.coordinate_system(t)
    x0 = dr.select(dr.squared_norm(x0) < 1e-6, x_alt, dr.normalize(x0))
    s, c = dr.sincos(twist + twist_rate * arc_length(si))
    x = c * x0 + s * dr.cross(t, x0)
    z = dr.cross(x, t)
    return x, t, z


SINGLE_FIBERS = ("fiber_table", "fiber_ray")   # the plugins of one fiber (not a bundle)


def fiber_on_linear_curve(shape) -> bool:
    """Whether ``shape`` is a ``linearcurve`` carrying a single-fiber BSDF (:class:`LinearCurves`)."""
    return (shape.shape_type() == int(mi.ShapeType.LinearCurve)
            and getattr(shape.bsdf(), "plugin", None) in SINGLE_FIBERS)


class LinearCurves:
    """The ``linearcurve`` shapes of a scene that carry a fiber BSDF, with what their hits
    lack: Mitsuba 3.9's ``linearcurve`` sets no derivative round the curve (``dp_du = 0``),
    so its shading frame is built from the normal alone and its ``t`` is not the tangent
    (a straight curve along ``y`` gave ``t = -y`` for some hits). :meth:`fix` rebuilds the
    frame of a hit from its segment's two control points (``t`` from the first to the second,
    so one fiber's frame keeps its sense along it), and ``dp_du = 2 pi r s``, round the
    curve as on ``bsplinecurve``, so that the radius is read as there.

    Built once per scene (``bundle_path`` does, at its first render of the scene), so curves
    moved afterwards through ``mi.traverse`` keep the frames of where they were; :meth:`fix`
    is traced into the kernel. An empty list fixes nothing and costs nothing.
    """

    def __init__(self, shapes):
        self.curves = []
        for shape in filter(fiber_on_linear_curve, shapes):
            params = mi.traverse(shape)
            segments, points = mi.UInt32(params["segment_indices"]), mi.Float(params["control_points"])
            dr.make_opaque(segments, points)  # evaluated once: the kernel reads them, the same each render
            self.curves.append((mi.ShapePtr(shape), segments, points))

    def __bool__(self):
        return bool(self.curves)

    def fix(self, si, d):
        """``si`` (a hit of a ray along ``d``) with the tangent frame on these curves."""
        for shape, segments, points in self.curves:
            mine = si.is_valid() & (si.shape == shape)
            k = dr.gather(mi.UInt32, segments, si.prim_index, mine)
            p0, p1 = (dr.gather(mi.Vector4f, points, k + j, mine) for j in (0, 1))
            axis = mi.Vector3f(p1.x - p0.x, p1.y - p0.y, p1.z - p0.z)
            length2 = dr.squared_norm(axis)
            u = dr.clip(dr.dot(si.p - mi.Point3f(p0.x, p0.y, p0.z), axis) / dr.maximum(length2, 1e-30), 0.0, 1.0)
            r = dr.lerp(p0.w, p1.w, u)
            n = si.sh_frame.n
            s = dr.cross(axis, n)
            ok = mine & (length2 > 0) & (dr.squared_norm(s) > 1e-12 * length2)
            s = dr.normalize(s)
            frame = mi.Frame3f(s, dr.cross(n, s), n)
            si.sh_frame = dr.select(ok, frame, si.sh_frame)
            si.wi = dr.select(ok, frame.to_local(-d), si.wi)
            si.dp_du = dr.select(ok, (2 * dr.pi) * r * s, si.dp_du)
        return si


def angles(w, frame):
    """``(phi, theta)`` of a world direction in the bundle frame (docs/DESIGN.md conventions).

    A non-finite direction (a degenerate shading frame) gives (0, 0), never NaN: the
    angles become table indices, and a NaN index reads out of bounds.
    """
    x, t, z = frame
    theta = dr.safe_asin(dr.clip(dr.dot(w, t), -1.0, 1.0))
    phi = dr.atan2(dr.dot(w, z), dr.dot(w, x))
    ok = dr.isfinite(theta) & dr.isfinite(phi)
    return dr.select(ok, phi, 0.0), dr.select(ok, theta, 0.0)


def line_offset(si, frame, phi):
    """The signed offset ``h`` in [-1, 1] of the line through the bundle hit ``si`` along
    bundle-frame azimuth ``phi``, from the bundle's axis over its radius: ``x sin(phi) -
    z cos(phi)`` of the hit's outward radial direction ``(x, z)`` in the frame, as the bake
    measures an escaping ray (``models.bake.tally.line_offset``)."""
    x, t, z = frame
    n_perp = si.n - dr.dot(si.n, t) * t
    n_perp = dr.normalize(dr.select(dr.squared_norm(n_perp) > 1e-12, n_perp, x))
    return dr.clip(tally.line_offset(dr.dot(n_perp, x), dr.dot(n_perp, z), phi, 1.0, dr), -1.0, 1.0)


def direction(phi, theta, frame):
    """World direction of bundle-frame angles."""
    x, t, z = frame
    sp, cp = dr.sincos(phi)
    st, ct = dr.sincos(theta)
    return ct * (cp * x + sp * z) + st * t


def spectral_weights(wavelength_nm, variant_kind: str, mono_nm=None) -> np.ndarray:
    """Weights ``[channels, n_lambda]`` from the table's spectrum to a non-spectral variant.

    rgb: linear sRGB of the spectrum seen under D65 (``models.spectrum``); mono: the
    value at ``mono_nm`` (linear interpolation), or the CIE luminance Y if none is given.
    """
    wl = np.asarray(wavelength_nm, float)
    eye = np.eye(len(wl))
    if variant_kind == "rgb":
        return spectrum_to_srgb(eye, wl).T
    if mono_nm is not None:
        if not wl[0] <= mono_nm <= wl[-1]:
            raise ValueError(f"fiber_bundle: wavelength {mono_nm} nm is outside the table's "
                             f"{wl[0]:.0f}..{wl[-1]:.0f} nm")
        return hat_basis(wl, [mono_nm])
    import colour

    rgb = spectrum_to_srgb(eye, wl)  # Y is the second row of XYZ
    Y = colour.sRGB_to_XYZ(rgb, apply_cctf_decoding=False)[:, 1]
    return Y[None, :]


def split_uniform(u, bits: int = 12):
    """Two uniforms from one: its top ``bits`` bits and the remaining fraction."""
    scaled = u * float(1 << bits)
    hi = dr.floor(scaled)
    return hi * (1.0 / (1 << bits)), scaled - hi


def light_and_camera(ctx, si, wo):
    """Which of Mitsuba's two directions is the table's ``w_i`` (the light side).

    In Mitsuba's ``eval(ctx, si, wo)`` of a path tracer (``TransportMode.Radiance``)
    ``wo`` points towards the light and ``si.wi`` towards the camera; a light tracer
    (``Importance``) swaps them. Returns local ``(w_light, w_camera, radiance)``.
    """
    if ctx.mode == mi.TransportMode.Radiance:
        return wo, si.wi, True
    return si.wi, wo, False


def adjoint_factor(theta_light, theta_camera):
    """``cos(theta_light) / cos(theta_camera)``: the radiance-mode value from the table's.

    The far field of a cylinder seen along ``w_o`` is ``I = E 2R cos(theta_i) S(w_i -> w_o)``,
    while a render collects ``2R cos(theta_o) E eval``; so in radiance mode
    ``eval = S(w_i -> w_o) cos(theta_i) / cos(theta_o)`` with ``w_i`` the light side.
    For a reciprocal ``S`` this equals ``S(w_o -> w_i)``. The camera's cosine is kept
    from zero (a view along the axis sees no projected width anyway).
    """
    return dr.cos(theta_light) / dr.maximum(dr.cos(theta_camera), 1e-4)


def resolve_path(plugin: str, name: str, value) -> str | None:
    """A file parameter resolved as Mitsuba resolves its own ``filename``s: against the
    file resolver, which holds the scene file's folder while an XML scene loads."""
    if value is None:
        return None
    found = str(mi.file_resolver().resolve(str(value)))
    if not Path(found).exists():
        raise ValueError(f"{plugin}: '{name}' file {value} not found (looked in the current folder and in the "
                         "scene file's folder); give a path relative to the scene file or an absolute one")
    return found
