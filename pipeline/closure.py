"""Far-field closure: does a render reproduce the scattering function it was given?

The test of docs/DESIGN.md. A long straight cylinder of radius ``R`` along the bundle frame's
``+y`` (world = bundle frame: ``up = [1, 0, 0]``), a directional light of irradiance
``E`` arriving from ``w_i`` (the direction *towards* the light, the bake's incidence),
no environment, and an orthographic camera looking along ``-w_o`` with a box filter.
Per unit length of the cylinder the scattered intensity is

    I(w_i, w_o) = E * 2R * cos(theta_i) * S(w_i -> w_o)                    (physics)

and the render measures it as ``sum(pixels) * pixel_area / visible_length`` with the
visible length ``film_height / cos(theta_o)`` (the axis runs up the film).

Everything here is in the bundle frame of docs/DESIGN.md: ``sin(theta) = w.y``,
``phi = atan2(w.z, w.x)``. :func:`direction` turns angles into vectors,
:func:`scene` builds the Mitsuba scene for any set of shapes (one cylinder with a
``fiber_bundle`` or ``fiber_table`` BSDF, or every fiber of a ply as its own cylinder),
:func:`rendered_intensity` renders and measures, :func:`predicted_intensity` is the
formula above. Mono variants render one wavelength (the BSDFs' ``wavelength``); a spectral
variant's luminance film records what :func:`luminance_weights` makes of a table's spectrum.

Example::

    mi.set_variant("llvm_ad_mono"); mitsuba_ext.register()
    w_i, w_o = direction(0.0, 0.5), direction(2.0, -0.45)
    bsdf = {"type": "fiber_bundle", "table": "bundle_table.npz", "wavelength": 550.0,
            "up": [1.0, 0.0, 0.0]}
    sc = scene(mi, {"ply": cylinder(0.2, bsdf)}, w_i, w_o, half_size=0.3)
    I = rendered_intensity(mi, sc, w_o, half_size=0.3)
    # compare with predicted_intensity(1.0, 0.2, theta_i, S(w_i -> w_o))
"""

from __future__ import annotations

import tempfile
import textwrap
from pathlib import Path

import drjit as dr
import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np

from mitsuba_ext.frame import spectral_weights
from mitsuba_ext.neural import DrJitMLP, OnnxMLP
from models.bundle import TwistedBundle
from models.bundle_table import BundleTable, lookup
from models.cloth.curves import interpolate_bspline, write_mitsuba_curves
from models.fiber.base import FiberTable
from models.fiber.ray import mitsuba_hair
from models.grid import TIE, Cells
from models.io import atomic_path
from models.spectrum import hat_basis
from models.neural import far_field

AXIS = np.array([0.0, 1.0, 0.0])   # the fibers' direction (bundle frame +y)
UP = [1.0, 0.0, 0.0]               # the BSDFs' ``up``: bundle frame x = world x


# -- small pure functions ----------------------------------------------------------
def direction(phi, theta) -> np.ndarray:
    """Unit vector of bundle-frame angles (radians): ``(cos t cos p, sin t, cos t sin p)``."""
    return np.array([np.cos(theta) * np.cos(phi), np.sin(theta), np.cos(theta) * np.sin(phi)])


def predicted_intensity(E, R, theta_i, S):
    """Intensity per unit length, ``E 2R cos(theta_i) S``: the far field of docs/DESIGN.md."""
    return E * 2.0 * R * np.cos(theta_i) * S


def visible_length(half_size, theta_o) -> float:
    """Length of the axis seen across a film of height ``2 half_size`` along ``w_o``."""
    return 2.0 * half_size / np.cos(theta_o)


def fiber_half_length(half_size, theta_o) -> float:
    """Half the length the closure scene's fibers need for views at longitudes ``theta_o``
    (radians, any shape): 40 film half sizes, or twice the half :func:`visible_length` of
    the most grazing view. A film along a nearly axial ``w_o`` sees ``2 half_size /
    cos(theta_o)`` of the axis, more than 80 half sizes beyond 88.57 deg: with shorter fibers
    it would see past their ends and read the intensity low by a large fraction."""
    return float(half_size * max(40.0, visible_length(1.0, np.max(np.abs(np.asarray(theta_o, float))))))


def cylinder(R, bsdf: dict, center_xz=(0.0, 0.0), half_length=1.0) -> dict:
    """A cylinder of radius ``R`` parallel to ``+y`` through ``(x, z) = center_xz``."""
    x, z = map(float, center_xz)
    return {"type": "cylinder", "p0": [x, -half_length, z], "p1": [x, half_length, z], "radius": float(R),
            "bsdf": bsdf}


def scene(mi, shapes: dict, w_i, w_o, half_size, *, irradiance=1.0, resolution=64, spp=16, seed=0,
          max_depth=64, background=None, integrator: str = "bundle_path") -> dict:
    """The closure scene: ``shapes`` lit from ``w_i``, seen along ``w_o`` (orthographic).

    The film is square, ``2 half_size`` wide, centred on the origin, with the projected
    fiber axis running up the film (so ``w_o`` must not be parallel to the axis).
    The cylinders' length must exceed the visible length (``half_length`` of
    :func:`cylinder`). ``background``: radiance of an optional emitting plane far
    behind the bundle (the passthrough test); no environment otherwise. ``integrator``:
    ``bundle_path`` (the project's, which every fiber BSDF needs) or Mitsuba's own ``path``
    (for Mitsuba's own BSDFs, e.g. ``hair`` on curves).
    """
    w_i, w_o = np.asarray(w_i, float), np.asarray(w_o, float)
    up, distance, to_world = _camera(mi, w_o, half_size)
    T = mi.ScalarTransform4f
    sc = {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": max_depth},
        "sensor": {"type": "orthographic", "to_world": to_world, "near_clip": 1e-3 * half_size,
                   "far_clip": 1e4 * half_size,
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                            "rfilter": {"type": "box"}, "pixel_format": "luminance"},
                   # independent, not stratified: Mitsuba's stratified sampler, driven by a
                   # path tracer's loop, made a dense ply's light of ten and more fiber events
                   # several times too bright (docs/DESIGN.md, "The ray fiber and Mitsuba's hair")
                   "sampler": {"type": "independent", "sample_count": int(spp), "seed": seed}},
        "sun": {"type": "directional", "direction": (-w_i).tolist(),
                "irradiance": {"type": "spectrum", "value": float(irradiance)}},
        **shapes,
    }
    if background is not None:
        # a plane facing the camera, far behind: it subtends ~1e-4 sr from the bundle,
        # so light it sends in by scattering is negligible next to what passes through
        size = 4.0 * half_size
        sc["backdrop"] = {"type": "rectangle",
                          "to_world": T().look_at(origin=(-distance * w_o).tolist(), target=[0, 0, 0],
                                                  up=up.tolist()) @ T().scale([size, size, 1.0]),
                          "emitter": {"type": "area", "radiance": {"type": "spectrum", "value": float(background)}}}
    return sc


def _camera(mi, w_o, half_size):
    """``(up, distance, to_world)`` of the closure scene's orthographic camera along ``-w_o``."""
    w_o = np.asarray(w_o, float)
    up = AXIS - np.dot(AXIS, w_o) * w_o
    if np.linalg.norm(up) < 1e-3:
        raise ValueError("closure scene: w_o is parallel to the fiber axis; the axis would not cross the film")
    up /= np.linalg.norm(up)
    distance = 100.0 * half_size
    T = mi.ScalarTransform4f
    to_world = T().look_at(origin=(distance * w_o).tolist(), target=[0, 0, 0], up=up.tolist()) @ \
        T().scale([half_size, half_size, 1.0])
    return up, distance, to_world


def _sun(mi, w_i):
    """The ``to_world`` Mitsuba's ``directional`` emitter builds for light arriving from ``w_i``."""
    emitter = mi.load_dict({"type": "directional", "direction": (-np.asarray(w_i, float)).tolist()})
    return mi.traverse(emitter)["to_world"]


def render_image(mi, scene, seed: int = 0) -> np.ndarray:
    """The rendered image of a scene dict or a loaded scene, one channel (a NaN or Inf is an
    error, not a pixel)."""
    img = np.asarray(mi.render(mi.load_dict(scene) if isinstance(scene, dict) else scene, seed=seed), np.float64)
    img = img[..., 0] if img.ndim == 3 else img
    if not np.all(np.isfinite(img)):
        raise FloatingPointError("closure render holds NaN or Inf")
    return img


def _per_length(img: np.ndarray, w_o, half_size) -> float:
    """``pixel_area / visible_length``: a pixel sum of an image seen along ``w_o`` as an
    intensity per unit length of the axis."""
    pixel_area = (2.0 * half_size / img.shape[0]) ** 2
    theta_o = np.arcsin(np.clip(np.asarray(w_o, float)[1], -1, 1))
    return pixel_area / visible_length(half_size, theta_o)


def intensity(img: np.ndarray, w_o, half_size) -> float:
    """The closure's measurement of an image seen along ``w_o``: ``sum(pixels) pixel_area /
    visible_length``."""
    return float(img.sum() * _per_length(img, w_o, half_size))


def profile(img: np.ndarray, w_o, half_size, radius, n_cells: int) -> np.ndarray:
    """The intensity of an image seen along ``w_o`` by ``n_cells`` equal cells across the
    ply's width ``2 radius`` (film columns; the axis runs up the film): each cell's share of
    :func:`intensity` times ``n_cells``, so that their mean is the intensity of the width."""
    n = img.shape[1]
    x = (np.arange(n) + 0.5) / n * 2 * half_size - half_size      # film x of each column
    cell = np.floor((x / radius + 1) * 0.5 * n_cells).astype(int)
    inside = (cell >= 0) & (cell < n_cells)
    per_cell = np.bincount(cell[inside], img.sum(axis=0)[inside], n_cells)
    return per_cell * _per_length(img, w_o, half_size) * n_cells


def rendered_intensity(mi, scene, w_o, half_size) -> float:
    """Render ``scene`` (a dict or a loaded scene) and measure ``sum(pixels) pixel_area /
    visible_length``."""
    return intensity(render_image(mi, scene), w_o, half_size)


def hair_bsdf(meta: dict, wavelength, wavelength_nm: float) -> dict:
    """Mitsuba's ``hair`` with the parameters of a ray fiber (``models.fiber.ray.mitsuba_hair``),
    as the closure renders it: ``hair_resampled`` (``mitsuba_ext.hair``: ``hair``'s own value
    and density, its residual sampled from that density, which Mitsuba 3.9.1's ``hair`` does
    not do)."""
    return mitsuba_hair(meta, wavelength, wavelength_nm) | {"type": "hair_resampled"}


HAIR_PLUGINS = ("hair", "hair_resampled")   # Mitsuba's hair, and it sampled as its density says


def explicit_fiber(fiber_table, exit_model: str, wavelength_nm: float | None) -> dict:
    """The BSDF of one explicit fiber that leaves as a bake with ``exit_model`` does:
    ``fiber_ray`` (each path from its own exit) for the h-resolved ``lobe`` exit, Mitsuba's
    own ``hair`` for the ``curve`` exit of a ray fiber of camera transport (what ``hair`` on
    curves renders, through :func:`hair_bsdf`; one wavelength), ``fiber_table`` (the displaced
    exit of ``bundle_path``, h uniform) otherwise. The ``entry`` exit has no explicit
    counterpart yet; it is compared with ``fiber_table``. ``wavelength_nm``: what a mono
    variant renders; ``None`` for a spectral variant."""
    if exit_model == "curve":
        table = FiberTable.load(fiber_table)
        if table.meta.get("model") == "ray" and table.meta.get("transport") == "camera":
            if wavelength_nm is None:
                raise ValueError("explicit_fiber: Mitsuba's hair takes one index of refraction; render the "
                                 "explicit hair fibers in a mono variant at one wavelength")
            return hair_bsdf(table.meta, table.wavelength, float(wavelength_nm))
    plugin = "fiber_ray" if exit_model == "lobe" else "fiber_table"
    bsdf = {"type": plugin, "filename": str(fiber_table), "up": UP}
    return bsdf if wavelength_nm is None else {**bsdf, "wavelength": float(wavelength_nm)}


def luminance_weights(mi, wavelength_nm) -> np.ndarray:
    """Weights ``w`` with ``sum_k w_k S_k`` = the luminance a spectral variant's
    ``luminance`` film records of the table spectrum ``S_k`` under a flat light.

    The plugins interpolate a table's wavelengths linearly and hold the end values
    beyond them (``mitsuba_ext.bsdf``); Mitsuba's film weighs each sampled wavelength by
    its own CIE 1931 ``y`` (an analytic fit, ``mi.cie1931_y``, not the tabulated
    observer) over its sampling range, normalized so that a flat spectrum of 1 reads 1.
    """

    fine = np.linspace(360.0, 830.0, 4701)      # Mitsuba's CIE range, 0.1 nm
    y_bar = np.asarray(mi.cie1931_y(mi.Float(fine)), np.float64)
    return y_bar @ hat_basis(wavelength_nm, fine) / y_bar.sum()


def spectrum_weights(mi, wavelength, wavelength_nm: float | None) -> np.ndarray:
    """Weights over a table's ``wavelength`` samples for the value asked for: a mono
    variant's at ``wavelength_nm`` (the plugins' own, ``mitsuba_ext.frame.spectral_weights``:
    linear between samples), or (``None``) the luminance a spectral render records."""

    wl = np.asarray(wavelength, np.float64)
    if wavelength_nm is None:
        return luminance_weights(mi, wl)
    return spectral_weights(wl, "mono", float(wavelength_nm))[0]


def explicit_shapes(bundle, fiber_bsdf: dict, half_length: float, unit: float = 1e-3) -> dict:
    """Every fiber of ``bundle`` (micrometres, centres in the bundle frame's x-z plane)
    as its own cylinder along ``+y``, unturned (:class:`TurnedFibers` turns them); ``unit``
    converts micrometres into scene units."""
    return {f"fiber_{k:05d}": cylinder(r * unit, fiber_bsdf, (x * unit, z * unit), half_length)
            for k, ((x, z), r) in enumerate(zip(np.asarray(bundle.centers, float), np.asarray(bundle.radii, float)))}


class TurnedFibers:
    """The explicit fibers of a loaded scene, turned about the ply's ``axis`` and moved
    along it between views: its cylinders named ``fiber_*`` and its curves (a twisted
    ply's ``bsplinecurve``), through ``mi.traverse``.

    Loading a scene per view made Dr.Jit compile a kernel variant for many of them (its
    calls are specialized on the shapes' and BSDFs' registry ids and on values they share);
    one scene whose fibers move renders every view with one kernel. ``place(turn, shift)``
    puts the fibers where a fresh scene turned by ``turn`` radians in ``phi = atan2`` of
    the bundle frame and moved by ``shift`` scene units along the axis would (Mitsuba's
    rotation turns the other way): load the scene unturned, with its curves long enough
    for every shift.
    """

    def __init__(self, mi, scene, axis):
        self.mi, self.axis = mi, np.asarray(axis, float)
        self.params = mi.traverse(scene)
        keys = list(self.params.keys())
        self.cylinders = {k: mi.Transform4f(self.params[k]) for k in keys
                          if k.startswith("fiber_") and k.endswith(".to_world")}
        self.curves = {k: np.array(self.params[k], np.float64).reshape(-1, 4) for k in keys
                       if k.endswith(".control_points")}

    def place(self, turn: float, shift: float = 0.0) -> None:
        mi = self.mi
        T = mi.ScalarTransform4f()
        M = T.translate((shift * self.axis).tolist()) @ T.rotate(self.axis.tolist(), -float(np.rad2deg(turn)))
        for key, base in self.cylinders.items():
            self.params[key] = mi.Transform4f(M) @ base
        A = np.array(M.matrix, np.float64)
        for key, base in self.curves.items():
            points = base.copy()
            points[:, :3] = base[:, :3] @ A[:3, :3].T + A[:3, 3]
            self.params[key] = mi.Float(points.ravel().astype(np.float32))
        self.params.update()


def helix_control_points(ply, half_length: float, unit: float = 1e-3, per_turn: int = 64) -> list:
    """The fibers of a :class:`~models.bundle.TwistedBundle` as uniform cubic B-splines
    (Mitsuba's ``bsplinecurve``) from ``y = -half_length`` to ``+half_length`` (scene
    units): one ``[n, 4]`` array of control points ``x y z r`` per fiber.

    The spline interpolates each centre line (``models.cloth.curves.interpolate_bspline``)
    at knots ``1 / per_turn`` of a turn apart, so it passes through the helix at every knot
    and strays from it between knots by about ``rho (f delta)^4 / 384`` (``delta`` the turn
    between knots, ``f`` = 1 for a helix, ``1 + s`` for a migrating one: 0.00006 um at
    ``rho`` = 260 um and 64 per turn without migration; ``tests/test_twisted.py`` evaluates
    the spline). The interpolation runs six knots past each end, where its natural end
    conditions have died out (by ``(2 - sqrt 3)^6``), and those knots are cut off.
    """

    L, extra = half_length / unit, 6
    n = int(np.ceil(2 * L / ply.turn_length * per_turn))    # knot intervals over [-L, L]
    y = -L + 2 * L / n * np.arange(-extra, n + extra + 1)
    c = ply.centers_at(y)                                   # [knots, fibers, 2]
    C = interpolate_bspline(np.stack([c[..., 0], np.broadcast_to(y[:, None], c.shape[:2]), c[..., 1]], -1),
                            closed=False)[extra:extra + n + 3]  # the segments from y = -L to +L
    return [np.concatenate([C[:, k], np.full((len(C), 1), r)], -1) * unit
            for k, r in enumerate(np.asarray(ply.bundle.radii, float))]


def straight_control_points(bundle, half_length: float, unit: float = 1e-3, segments: int = 16) -> list:
    """The fibers of a parallel :class:`~models.bundle.Bundle` as straight uniform cubic
    B-splines (``bsplinecurve``) along ``+y`` from ``-half_length`` to ``+half_length``
    (scene units), control points ``x y z r`` per fiber: evenly spaced collinear control
    points make a straight line traversed at constant speed, the curve running from the
    second control point to the last but one. ``segments``: how many spline segments (one
    long segment would cost the curve intersector precision)."""
    L = half_length
    y = -L + 2 * L / segments * np.arange(-1, segments + 2)
    return [np.stack([np.full_like(y, x * unit), y, np.full_like(y, z * unit), np.full_like(y, r * unit)], -1)
            for (x, z), r in zip(np.asarray(bundle.centers, float), np.asarray(bundle.radii, float))]


def write_curves(curves, path) -> None:
    """A scratch curve file that a render reads (not an artifact: written in place) in
    Mitsuba's format (``models.cloth.curves.write_mitsuba_curves``), at float32's precision."""

    with open(path, "w") as f:
        write_mitsuba_curves(f, curves, fmt="%.9g")


def explicit_twisted_shapes(curve_file, fiber_bsdf: dict, turn: float, shift: float = 0.0) -> dict:
    """A twisted ply's fibers (``curve_file`` from :func:`helix_control_points`) as one
    ``bsplinecurve``, turned by ``turn`` (radians) about the axis and moved by ``shift``
    (scene units) along it. Without migration a turn is a shift along the axis, so evenly
    spaced turns average over the period; with it, turns and shifts together."""

    T = mi.ScalarTransform4f()
    return {"ply": {"type": "bsplinecurve", "filename": str(curve_file), "bsdf": fiber_bsdf,
                    # Mitsuba's rotation about +y turns z towards x: -turn in phi = atan2(z, x)
                    "to_world": T.translate([0.0, float(shift), 0.0]) @ T.rotate([0.0, 1.0, 0.0],
                                                                                 -float(np.rad2deg(turn)))}}


def view_placements(ply, n_views: int, unit: float, turns: bool = True,
                    offset=(0.0, 0.0)) -> list[tuple[float, float]]:
    """``(turn, shift)`` of each view of an explicit ply, averaging over what its bake
    averages over: the incident azimuth (turns, a circle's: ``turns``) and, for a twisted ply
    (a :class:`~models.bundle.TwistedBundle`), the height within the period (shifts, scene
    units). Parallel fibers and a rigid circular twist need the turns alone (for the latter
    a turn is a shift); an ellipse, whose bake keeps its azimuth, the shifts alone (none if
    parallel); a migrating circle both, as a rank-1 lattice over (turn, height) whose every
    projection, and the shift a turn amounts to, are stratified. ``offset`` (turn, shift) in
    [0, 1): moves the lattice by that share of a stratum (a random one makes the average an
    unbiased estimate of the whole period's: :func:`replicated_bins`)."""

    twisted = isinstance(ply, TwistedBundle)
    P = ply.period * unit if twisted else 0.0
    o_turn, o_shift = offset
    if not turns:
        return [(0.0, (k + o_shift) / n_views * P) for k in range(n_views)]
    placed = [2 * np.pi * (k + o_turn) / n_views for k in range(n_views)]
    if not twisted or ply.screw:
        return [(t, 0.0) for t in placed]
    a = next(a for a in (5, 3, 7, 11, 13, 1) if np.gcd(a, n_views) == 1)  # k -> a k mod n: a permutation
    return [(t, (a * k % n_views + o_shift) / n_views * P) for k, t in enumerate(placed)]


def explicit_intensity(mi, bundle, fiber_bsdf: dict, w_i, views, spp: int = 16, resolution: int = 48,
                       unit: float = 1e-3, turns: bool = True, **options):
    """Intensity per unit length of the explicit fibers lit from ``w_i``, averaged over
    ``len(views)`` evenly spaced turns of the arrangement, turn ``k`` seen along
    ``views[k]`` (one direction, or directions spread over a table bin: the average is
    then the bin average of the rotation average, which is what a circle's bake holds).
    ``turns=False`` keeps the arrangement as it is (an ellipse's bake is not rotated).
    ``bundle``: a :class:`~models.bundle.Bundle` (parallel cylinders) or a
    :class:`~models.bundle.TwistedBundle` (every fiber a ``bsplinecurve`` along its helix,
    over many periods: :func:`helix_control_points`). ``options`` (keywords): ``curves``
    (parallel fibers as straight ``bsplinecurve``s, not cylinders: a BSDF that, as Mitsuba's
    ``hair``, counts on curves being invisible from inside) and ``integrator``
    (:func:`scene`'s).

    Returns the mean and an error estimate: half the difference of the even and the odd
    turns' means, which holds the render noise and the rule's.
    """
    return explicit_intensities(mi, bundle, fiber_bsdf, [(w_i, views)], spp, resolution, unit, turns, **options)[0]


def explicit_intensities(mi, bundle, fiber_bsdf: dict, requests, spp: int = 16, resolution: int = 48,
                         unit: float = 1e-3, turns: bool = True, curves: bool = False,
                         integrator: str = "bundle_path", cells: int = 0, offset=(0.0, 0.0),
                         seed: int = 0) -> list:
    """:func:`explicit_intensity` for many ``(w_i, views)`` at once (every ``views`` as
    long): each turn of the arrangement is loaded once, and the sun and the camera are
    moved between requests (``mi.traverse``), as a fresh scene would place them; the
    scenes' loads and kernels, not their pixels, are what explicit fibers cost here.
    ``cells``: the :func:`profile` across the ply's bounding width instead (arrays).
    ``offset``: :func:`view_placements`'; ``seed``: the first view's render seed (view ``k``
    renders with ``seed + k``)."""

    twisted = isinstance(bundle, TwistedBundle)
    section = bundle.bundle if twisted else bundle
    if fiber_bsdf.get("type") in HAIR_PLUGINS:  # Mitsuba's hair counts on curves, invisible from inside
        curves, integrator = True, "path"
    hs = 1.2 * section.bounding_radius * unit
    half_length = fiber_half_length(hs, [np.arcsin(np.clip(w_o[1], -1, 1)) for _, views in requests for w_o in views])
    n_views = len(requests[0][1])
    placements = view_placements(bundle, n_views, unit, turns, offset)
    if any(len(views) != n_views for _, views in requests):
        raise ValueError("explicit_intensities: every request needs as many views")
    values = np.zeros((len(requests), n_views) + ((cells,) if cells else ()))
    suns = [_sun(mi, w_i) for w_i, _ in requests]
    with tempfile.TemporaryDirectory(prefix="bcsdf-helices-") as tmp:
        curve_file = Path(tmp) / "helices.txt"
        if twisted:  # long enough for every shift: the view stays 40 hs from either end
            reach = max(shift for _, shift in placements)
            write_curves(helix_control_points(bundle, half_length + reach, unit), curve_file)
        elif curves:
            write_curves(straight_control_points(bundle, half_length, unit), curve_file)
        # one scene for every view, its fibers moved (TurnedFibers), the sun and camera too
        shapes = (explicit_twisted_shapes(curve_file, fiber_bsdf, 0.0) if twisted or curves
                  else explicit_shapes(bundle, fiber_bsdf, half_length, unit))
        loaded = mi.load_dict(scene(mi, shapes, requests[0][0], requests[0][1][0], hs, resolution=resolution,
                                    spp=spp, integrator=integrator))
        fibers = TurnedFibers(mi, loaded, AXIS)
        params = fibers.params
        for k, (turn, shift) in enumerate(placements):
            fibers.place(turn, shift)
            for r, (_, views) in enumerate(requests):
                params["sensor.to_world"] = _camera(mi, views[k], hs)[2]
                params["sun.to_world"] = suns[r]
                params.update()
                img = render_image(mi, loaded, seed=seed + k)
                values[r, k] = (profile(img, views[k], hs, section.bounding_radius * unit, cells) if cells
                                else intensity(img, views[k], hs))
    if cells:
        return [(v.mean(axis=0), abs(v[0::2].mean(axis=0) - v[1::2].mean(axis=0)) / 2) for v in values]
    return [(float(v.mean()), float(abs(v[0::2].mean() - v[1::2].mean()) / 2)) for v in values]


def bundle_profiles(mi, bsdf: dict, R, requests, cells: int, shape=None, spp: int = 32,
                    resolution: int = 64) -> np.ndarray:
    """The :func:`profile` of one bundle of radius ``R`` with ``bsdf`` for every ``(w_i,
    views)`` of ``requests`` (the mean over the views), seen as :func:`explicit_intensities`
    sees explicit fibers (``hs = 1.2 R``): [request, cell]. ``shape(R, bsdf, half_length)``:
    the shape along ``+y`` (default :func:`cylinder`)."""
    hs = 1.2 * R
    half_length = fiber_half_length(hs, [np.arcsin(np.clip(v[1], -1, 1)) for _, views in requests for v in views])
    make = shape or (lambda R_, b, length: cylinder(R_, b, half_length=length))
    loaded = mi.load_dict(scene(mi, {"f": make(R, bsdf, half_length)}, requests[0][0], requests[0][1][0], hs,
                                resolution=resolution, spp=spp))
    params = mi.traverse(loaded)
    out = []
    for w_i, views in requests:
        rendered, sun = [], _sun(mi, w_i)
        for k, view in enumerate(views):
            params["sensor.to_world"] = _camera(mi, view, hs)[2]
            params["sun.to_world"] = sun
            params.update()
            rendered.append(profile(render_image(mi, loaded, seed=k), view, hs, R, cells))
        out.append(np.mean(rendered, axis=0))
    return np.array(out)


def bin_views(table, phi_i, k_phi, k_theta, n=4, jitter=(0.5, 0.5)) -> list:
    """``n x n`` directions (``n = (n_phi, n_theta)``: a grid of those) stratified over output
    bin ``(k_phi, k_theta)`` of ``table`` (uniform in ``phi`` and ``sin(theta)``, i.e. in solid
    angle), in a shuffled order; ``phi`` relative to ``phi_i`` for a relative table.
    ``jitter`` in [0, 1)^2: where in its stratum each direction lies (the midpoints by
    default; one random pair for all strata, a Cranley-Patterson rotation, makes the mean an
    unbiased estimate of the bin's)."""
    n_phi, n_theta = (n, n) if np.isscalar(n) else n
    pe, te = table.phi_o_edges, table.theta_o_edges
    rel = table.meta["reductions"]["phi_o"] == "relative"
    u0, u1 = np.sin(te[k_theta]), np.sin(te[k_theta + 1])
    ja, jb = jitter
    views = {(a, b): direction(pe[k_phi] + (a + ja) / n_phi * (pe[k_phi + 1] - pe[k_phi]) + (phi_i if rel else 0.0),
                               np.arcsin(u0 + (b + jb) / n_theta * (u1 - u0)))
             for a in range(n_phi) for b in range(n_theta)}
    # Latin-square order (on a square grid the even and the odd views each cover the bin)
    return [views[k % n_phi, (k // n_phi + k % n_phi) % n_theta] for k in range(n_phi * n_theta)]


def bin_requests(table, cases, phi_i: float = 0.0, n=4, jitter=(0.5, 0.5)) -> list:
    """The ``(w_i, views)`` requests of :func:`explicit_intensities` for each bin ``(theta_i
    index, phi bin, theta bin)`` of ``cases``: light from ``(phi_i, theta_i)``, seen over the
    bin's :func:`bin_views` (``n``, ``jitter``: theirs)."""
    return [(direction(phi_i, table.theta_i[j]), bin_views(table, phi_i, k_phi, k_theta, n, jitter))
            for j, k_phi, k_theta in cases]


# -- measurements over many directions (the render stage and bench_closure) ------------
def evaluator(mi, kind: str, path, wavelength_nm: float | None):
    """``S_of(pi, ti, po, to)``: what a renderer is given, at ``wavelength_nm`` (``None``:
    the luminance a spectral render records; :func:`spectrum_weights`), evaluated the way
    its own code does, outside any render:
    a float for scalar angles, an array for arrays (broadcast; one evaluation for all).

    ``kind``: ``fiber`` (a ``fiber_table.npz``, numpy; one wavelength), ``table`` (a
    ``bundle_table.npz``, the numpy lookup), ``mlp`` (``weights.npz``, Dr.Jit) or ``onnx``
    (``model.onnx``, onnxruntime; a model of the near field: its far field, the mean over the offset).
    """
    if kind == "fiber":
        if wavelength_nm is None:
            raise ValueError("evaluator: a fiber table is evaluated at one wavelength")
        fiber = FiberTable.load(path)
        return _on_arrays(lambda pi_, ti, po, to: fiber.eval(phi_i=pi_, theta_i=ti, phi_o=po, theta_o=to,
                                                              wavelength=wavelength_nm))
    if kind == "table":
        t = BundleTable.load(path, expand=True)
        w = spectrum_weights(mi, t.wavelength, wavelength_nm)
        return _on_arrays(lambda pi_, ti, po, to: lookup(t, pi_, ti, po, to) @ w)

    if kind == "mlp":
        mlp = DrJitMLP(path)
        w = spectrum_weights(mi, mlp.spec.wavelength, wavelength_nm)
        used = np.flatnonzero(w)   # the network's other outputs are never computed

        def S_mlp(*queries):
            import drjit as dr

            S = mlp.eval(*(mi.Float(np.asarray(a, np.float32)) for a in queries))
            dr.eval(*(S[k] for k in used))   # one kernel for every output used
            return sum(w[k] * S[k].numpy().astype(np.float64) for k in used)
        return _on_arrays(far_field(S_mlp, mlp.spec))   # a near-field model: its far field
    if kind == "onnx":
        onnx = OnnxMLP(path)
        w = spectrum_weights(mi, onnx.spec.wavelength, wavelength_nm)
        return _on_arrays(far_field(lambda *q: onnx.eval(*(np.asarray(a, np.float32) for a in q)) @ w, onnx.spec))
    raise ValueError(f"evaluator: kind {kind!r}; use fiber, table, mlp or onnx")


def _on_arrays(S_flat):
    """``S_flat`` (flat float64 arrays of angles -> values) for scalars or arrays of any shape."""
    def S_of(*angles):
        a = [np.asarray(x, np.float64) for x in angles]
        shape = np.broadcast_shapes(*(x.shape for x in a))
        out = np.asarray(S_flat(*(np.broadcast_to(x, shape).ravel() for x in a)), np.float64).reshape(shape)
        return float(out) if out.ndim == 0 else out
    return S_of


def continuous(S_of, pairs, d: float = 1e-6) -> np.ndarray:
    """Which pairs have ``S`` lit and continuous around them: a table's lookup jumps at
    its bin edges (it keeps bin averages), a grid pattern at its stripes' edges, and a
    float32 direction at a jump lands on either side of it; there ``S`` is not one number.
    ``d`` (radians) is ten times a float32 direction's error and small enough that a
    steep but continuous pattern (Mie fringes) changes by far less than 0.1% over it.
    ``S_of`` is evaluated once, on arrays (every pair and its 16 neighbours)."""
    P = np.asarray(pairs, np.float64)
    corners = np.array(np.meshgrid(*[(-d, d)] * 4, indexing="ij")).reshape(4, -1).T   # [16, 4]
    values = np.atleast_1d(S_of(*P.T))
    near = S_of(*(P[:, None, :] + corners[None]).reshape(-1, 4).T).reshape(len(P), len(corners))
    spread = np.ptp(np.concatenate([near, values[:, None]], 1), axis=1)
    return (values > 1e-4 * values.max()) & (spread < 1e-3 * values)


def far_field_ratios(mi, bsdf: dict, R, S_of, pairs, evaluated: bool = False, spp: int = 4, shape=None) -> list:
    """``[theta_i, theta_o + theta_i, dphi (deg), rendered / predicted]`` per direction pair
    (radians) for one cylinder of radius ``R`` with ``bsdf``; ``S_of(pi, ti, po, to)`` is
    what the BSDF was given. ``evaluated``: Dr.Jit's evaluated mode (the onnx backend);
    ``spp``: samples per pixel (a BSDF that depends on the offset across the fiber, as
    ``fiber_ray``, needs enough of them to integrate over it); ``shape(R, bsdf, half_length)``:
    the shape dict along ``+y`` (default :func:`cylinder`; the cloth tests give a curve).
    Pairs where ``S`` is not :func:`continuous` are left out."""

    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    saved = [dr.flag(f) for f in flags]
    rows = []
    try:
        for f in flags:
            dr.set_flag(f, dr.flag(f) and not evaluated)
        hs, loaded = 1.5 * R, None
        make = shape or (lambda R_, b, half_length: cylinder(R_, b, half_length=half_length))
        pairs = np.asarray(pairs)[continuous(S_of, pairs)]
        half_length = fiber_half_length(hs, pairs[:, 3]) if len(pairs) else 0.0
        for pi_, ti, po, to in pairs:
            predicted = predicted_intensity(1.0, R, ti, S_of(pi_, ti, po, to))
            w_i, w_o = direction(pi_, ti), direction(po, to)
            if loaded is None:
                loaded = mi.load_dict(scene(mi, {"f": make(R, bsdf, half_length)}, w_i, w_o, hs, spp=spp))
                params = mi.traverse(loaded)
            else:  # one scene for every pair, its sun and camera moved: loading a BSDF cost more than a render
                params["sensor.to_world"] = _camera(mi, w_o, hs)[2]
                params["sun.to_world"] = _sun(mi, w_i)
                params.update()
            rows.append([float(np.rad2deg(ti)), float(np.rad2deg(to + ti)), float(np.rad2deg(po - pi_)),
                         rendered_intensity(mi, loaded, w_o, hs) / float(predicted)])
    finally:
        for f, v in zip(flags, saved):
            dr.set_flag(f, v)
    return rows


def explicit_bins(mi, bundle, fiber_bsdf: dict, table, cases, lam: int, phi_i: float = 0.0, spp: int = 8,
                  resolution: int = 32, unit: float = 1e-3, **options) -> list:
    """Explicit fibers against a bake, bin by bin: for each ``(theta_i index, phi bin,
    theta bin)`` of ``cases``, the explicit intensity over the bin (16 views; 16 turns
    for a circle) against ``E 2 R_b cos(theta_i) S_bin``, with 1-sigma errors of both.
    Bins the bake found dark (below 1e-3 of the brightest bin of their row) are left out.
    ``options``: :func:`explicit_intensities`' ``curves`` and ``integrator``."""
    rows = []
    a = int(np.argmin(np.abs(np.angle(np.exp(1j * (table.phi_i - phi_i))))))
    cases = [(j, k_phi, k_theta) for j, k_phi, k_theta in cases
             if table.values[a, j, k_phi, k_theta, lam] > 1e-3 * table.values[a, j, ..., lam].max()]
    if not cases:
        return rows
    section = getattr(bundle, "bundle", bundle)  # a twisted ply's cross-section
    measured = explicit_intensities(mi, bundle, fiber_bsdf, bin_requests(table, cases, phi_i), spp=spp,
                                    resolution=resolution, unit=unit, turns=section.is_circle, **options)
    for (j, k_phi, k_theta), (I, se) in zip(cases, measured):
        ti = table.theta_i[j]
        S, S_err = table.values[a, j, k_phi, k_theta, lam], table.stderr[a, j, k_phi, k_theta, lam]
        predicted = predicted_intensity(1.0, section.bounding_radius * unit, ti, S)
        rows.append({"theta_i": float(np.rad2deg(ti)), "phi_o": float(np.rad2deg(table.phi_o[k_phi])),
                     "theta_o": float(np.rad2deg(table.theta_o[k_theta])), "ratio": float(I / predicted),
                     "sigma": float(np.hypot(S_err / S, se / I))})
    return rows


def replicated_bins(mi, bundle, fiber_bsdf: dict, table, cases, replicates: int, phi_i: float = 0.0,
                    seed: int = 0, strata=(2, 8), **options) -> list[tuple[float, float]]:
    """The explicit intensity over each bin ``(theta_i index, phi bin, theta bin)`` of
    ``cases`` and its standard error, from ``replicates`` independent passes of
    :func:`explicit_intensities`: each pass moves the bin's directions (``strata``, a grid
    of :func:`bin_views`; more in theta, where a lobe beside its cone falls fastest) and the
    ply's turns (and heights) by one random share of a stratum, and renders with seeds of its
    own. Each pass is then an unbiased estimate of the bin's and the period's average (render
    noise and quadrature alike), so the passes' spread gives a standard error with
    ``replicates - 1`` degrees of freedom; the even and odd turns of one pass at the strata's
    midpoints (:func:`explicit_intensity`) give one, and the midpoints are biased where a
    bin's light falls steeply. ``options``: :func:`explicit_intensities`'."""
    if replicates < 2:
        raise ValueError("replicated_bins: a standard error needs at least two replicates")
    rng = np.random.default_rng(seed)
    passes = []
    for r in range(replicates):
        jitter, offset = rng.random(2), rng.random(2)
        requests = bin_requests(table, cases, phi_i, strata, jitter)
        measured = explicit_intensities(mi, bundle, fiber_bsdf, requests, offset=offset,
                                        seed=r * len(requests[0][1]), **options)
        passes.append([I for I, _ in measured])
    v = np.array(passes)
    return list(zip(v.mean(axis=0), v.std(axis=0, ddof=1) / np.sqrt(replicates)))


def theta_cut(mi, ply, fiber_bsdf: dict, theta_i: float, dphi: float, theta_o, turns: int = 8, spp: int = 8,
              resolution: int = 32, unit: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The explicit fibers' far field along one cut through the highlight: ``S`` (1/sr) at
    ``theta_o`` (radians, an array) for light from ``(0, theta_i)`` seen at azimuth
    ``dphi``, each point ``I / (E 2 R_b cos theta_i)`` of :func:`explicit_intensity` over
    ``turns`` turns of the ply. Returns ``S`` and its 1-sigma error."""
    section = getattr(ply, "bundle", ply)
    norm = predicted_intensity(1.0, section.bounding_radius * unit, theta_i, 1.0)
    measured = explicit_intensities(mi, ply, fiber_bsdf,
                                    [(direction(0.0, theta_i), [direction(dphi, to)] * turns)
                                     for to in np.asarray(theta_o, float)],
                                    spp=spp, resolution=resolution, unit=unit, turns=section.is_circle)
    return np.array([I / norm for I, _ in measured]), np.array([se / norm for _, se in measured])


def peak_and_width(x, y, smooth: int = 0) -> tuple[float, float]:
    """Where ``y(x)`` peaks and its full width at half its height above its floor (the
    half-height crossings interpolated between samples; the whole range where it never
    falls to half). ``smooth``: a moving average over ``2 smooth + 1`` samples first
    (Monte Carlo noise).

    The position is the centroid of ``y - half`` over the samples above half height round
    the largest, not the largest sample: a broad highlight read from a table is flat within
    its bins and noisy from one bin to the next, so its largest sample wanders by bins (a
    twisted ply's highlight, 34 deg wide in 5-deg bins of 6% noise: by up to 10 deg) while
    the centroid of its upper half moves by the noise's share of the width."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if smooth:
        y = np.convolve(np.pad(y, smooth, mode="edge"), np.ones(2 * smooth + 1) / (2 * smooth + 1), mode="valid")
    peak = int(np.argmax(y))
    half = y.min() + 0.5 * (y[peak] - y.min())
    lo, hi = peak, peak
    while lo > 0 and y[lo - 1] >= half:
        lo -= 1
    while hi < len(y) - 1 and y[hi + 1] >= half:
        hi += 1

    def crossing(inside, outside):  # where the line between two samples meets the half height
        if outside < 0 or outside >= len(y):
            return x[inside]
        w = (y[inside] - half) / (y[inside] - y[outside])
        return x[inside] + w * (x[outside] - x[inside])

    above = (y[lo:hi + 1] - half) * np.gradient(x)[lo:hi + 1]   # each sample weighed by its share of x
    centre = float(np.sum(x[lo:hi + 1] * above) / np.sum(above)) if np.sum(above) > 0 else float(x[peak])
    return centre, float(abs(crossing(hi, hi + 1) - crossing(lo, lo - 1)))


def cone_cases(table, phi_bins, beside: bool = True) -> list:
    """``(theta_i index, phi bin, theta bin)``: for each node the bin just beside its
    specular cone (and, with ``beside``, the one two bins further), at ``phi_bins``."""
    n_t = len(table.theta_o_edges) - 1
    cells = Cells(table.theta_o_edges)
    cases = []
    for j, ti in enumerate(table.theta_i):
        cone = int(cells.index(np.array(-ti), tie=TIE))  # the bin on the cone, or just above it
        for k_phi in phi_bins:
            cases.append((j, k_phi, cone))
            if beside and cone + 2 < n_t:
                cases.append((j, k_phi, cone + 2))
    return cases


def plot(far_field: dict, explicit: dict, path, title="", note: str = "") -> None:
    """Left: rendered / predicted - 1 per direction pair and backend; right: explicit
    fibers / bake - 1 per bin with 1-sigma error bars, per (fiber, ply), or ``note`` where
    there are none."""


    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.2))
    for k, (name, rows) in enumerate(far_field.items()):
        r = np.array([row[3] for row in rows])
        ax1.plot(np.arange(len(r)) + 0.15 * k, r - 1, "o", ms=3, label=name)
    ax1.axhspan(-0.01, 0.01, color="0.9", zorder=0)
    ax1.set(xlabel="direction pair (theta_i 10..80 deg; backwards, sideways, oblique; on and off the cone)",
            ylabel="rendered / predicted - 1", title="far-field closure (deterministic: 1% band)")
    ax1.legend(fontsize=8)
    for k, (label, rows) in enumerate(explicit.items()):
        x = np.arange(len(rows)) + 0.12 * k
        ax2.errorbar(x, [r["ratio"] - 1 for r in rows], yerr=[r["sigma"] for r in rows], fmt="o", ms=3,
                     capsize=2, label=label)
    ax2.axhspan(-0.02, 0.02, color="0.9", zorder=0)
    ax2.set(xlabel="(theta_i node, output bin) beside the specular cone", ylabel="explicit fibers / bake - 1",
            title="explicit fibers against the bake (1 sigma: bake and render)")
    if explicit:
        ax2.legend(fontsize=7)
    elif note:
        ax2.text(0.5, 0.5, textwrap.fill(note, 48), ha="center", va="center", transform=ax2.transAxes, fontsize=9,
                 bbox={"facecolor": "white", "edgecolor": "0.6"})
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


# -- direction sets ------------------------------------------------------------------
def direction_pairs(cone_offsets_deg=(0.0, 1.5, -3.0), kinds=("backward", "sideways", "oblique"), grazing=True):
    """Test directions ``(phi_i, theta_i, phi_o, theta_o)`` in radians.

    Light and camera at several longitudes, on the specular cone ``theta_o = -theta_i``
    and off it by ``cone_offsets_deg``, backwards (``dphi = 17 deg``), sideways
    (``dphi = 92 deg``), obliquely forward (``dphi = 152 deg``: never exactly
    forward, where a table averages the diffraction spike over one bin), plus grazing
    light (``theta_i = 80 deg``).
    """
    dphis = {"backward": 17.0, "sideways": 92.0, "oblique": 152.0}  # off the 5-degree bin edges
    thetas = [10.0, 35.0, 60.0] + ([80.0] if grazing else [])
    pairs = []
    for k, ti in enumerate(thetas):
        for kind in kinds:
            for off in cone_offsets_deg:
                if abs(-ti + off) > 89.0:  # past the pole: no such direction
                    continue
                phi_i = np.deg2rad(20.0 + 37.0 * k)
                pairs.append((phi_i, np.deg2rad(ti), phi_i + np.deg2rad(dphis[kind]), np.deg2rad(-ti + off)))
    return np.array(pairs)
