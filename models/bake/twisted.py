"""Paths through a twisted ply, traced in 3D (the parallel bake's 2D shortcut no longer holds).

The fibers of a :class:`~models.bundle.TwistedBundle` are helices, so a path's geometry
depends on its longitude: each path carries one incident ``theta_i`` (and, as in the
parallel bake, every wavelength). The ply repeats every ``|pitch|`` along its axis (with
migration, every few turns: ``TwistedBundle.period``), so one period is built, as Mitsuba
``cylinder`` segments along each helix, and a ray that leaves the period through its top or
bottom re-enters through the other side (the axis coordinate is wrapped). Cylinders rather
than curves: Mitsuba 3.9's curve intersection reads past its segment array where fibers
touch (``pipeline.scenes.explicit_scene``), and a chord of ``SEGMENTS`` per turn strays from
the helix by ``rho (1 - cos(pi / SEGMENTS))`` (0.08 um at ``rho`` = 260 um).

At a hit the fiber is evaluated in its own frame: the tangent ``T`` is the segment's axis,
``theta`` is measured from the plane normal to ``T`` and ``phi`` in that plane; the outgoing
direction is importance-sampled from the fiber table at the local ``theta_in`` and leaves
from the fiber's surface by the bake's exit model, in the plane normal to ``T`` as the
parallel bake does: ``uniform`` (offset ``h r`` along ``T x w_o``, ``h`` uniform), ``entry``
(where the light entered) or ``lobe`` (the ray fiber resolved in the ray's own offset ``h``:
a path sampled at that ``h``, leaving where that path leaves). An escaping path is tallied
in the ply's frame (``theta_o = asin(w_o . y)``, ``phi_o`` from ``+x``) into the parallel
table's bins, per ``theta_i`` node; the passthrough now depends on ``theta_i`` too.

Rays enter across the bounding width ``2 R_b`` at a height uniform over one period and, for
a circle (statistically rotation invariant: a turn is a shift along the axis), from an
azimuth stratified over the circle, binned at ``phi_o - phi_i``; for an ellipse (whose
fibers turn through it) from the spec's azimuth node, binned at ``phi_o``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi  # its types resolve to the variant chosen at the entry point, at call time
import numpy as np
from scipy.spatial import cKDTree

from ..bundle import TwistedBundle
from ..fiber import lobes
from ..fiber.base import FiberTable
from ..fiber.sampling import FiberSampler
from ..fiber.sampling_drjit import DrJitFiber
from ..jit import to_drjit
from . import weights
from .rounds import LoopState, in_rounds
from .scene import across_width, incident_azimuths, shuffled_strata
from .tally import BakeSpec, Tally, offset_cell, output_bin, split_bins

ESCAPED, CAPPED, STOPPED = 1, 2, 3
SEGMENTS = 128          # cylinders per turn of a helix
MAX_WRAPS = 10_000      # crossings of the period's ends one path may make (steep rays make many)
# Mitsuba builds a cylinder's frame from p0 and p1 in float32, orthonormal to rounding
# (u = 2^-24 per entry), and places a point a distance s along it through three-term products:
# within about 4 u s of where it belongs. A segment longer than PLACEMENT_TOLERANCE x the
# smallest fiber radius / (4 u) misplaces its own fibers' surfaces by more than that share of
# a radius (the tolerance: the order of the chord error above). Past it the ply is straight to
# float32 precision, and the parallel bake is the exact one.
PLACEMENT_TOLERANCE = 0.01
BYTES_PER_CYLINDER = 19_000  # Mitsuba's cylinder shape and its dict, measured at 20000 of them


def segments_per_fiber(ply: TwistedBundle, segments: int = SEGMENTS) -> int:
    """How many cylinders one fiber of the period is built of (before building them)."""
    r_max = float(ply.bundle.radii.max())
    margin = r_max / np.cos(ply.max_lean) + r_max  # see TwistedScene
    return int(np.ceil(segments * (ply.period + 2 * margin) / ply.turn_length))


def check_geometry(ply: TwistedBundle, segments: int = SEGMENTS) -> None:
    """Refuse a pitch too long for the float32 cylinders (see PLACEMENT_TOLERANCE)."""
    r_min = float(ply.bundle.radii.min())
    longest = PLACEMENT_TOLERANCE * r_min / (4 * 2.0**-24) * segments  # pitch whose segments reach the bound
    if ply.turn_length > longest:
        raise ValueError(f"bundle.twist: a pitch of {ply.pitch:g} um is longer than {longest:.3g} um, where "
                         f"Mitsuba's float32 cylinders ({segments} per turn) misplace the fibers by over "
                         f"{PLACEMENT_TOLERANCE:.0%} of their {r_min:g} um radius; such a ply is straight to that "
                         "precision: leave bundle.twist out (the parallel bake)")


class TwistedScene:
    """One period of the twisted ply as Mitsuba cylinders (segments of the helices,
    ``segments`` per turn; a migrating ply's period is several turns)."""

    def __init__(self, ply: TwistedBundle, segments: int = SEGMENTS):
        b = ply.bundle
        check_geometry(ply, segments)
        self.ply, self.period = ply, ply.period
        r_max = float(b.radii.max())
        # a margin so that every fiber's surface inside the period is whole: a tube leaning
        # by `lean` reaches r / cos(lean) along the axis past its centre line's end
        margin = r_max / np.cos(ply.max_lean) + r_max
        n_seg = segments_per_fiber(ply, segments)
        y = np.linspace(-margin, self.period + margin, n_seg + 1)
        c = ply.centers_at(y)                                     # [n_seg + 1, fibers, 2]
        shapes, fiber_of, axis = {}, [], []
        for k, r in enumerate(b.radii):
            for m in range(n_seg):
                p0 = [float(c[m, k, 0]), float(y[m]), float(c[m, k, 1])]
                p1 = [float(c[m + 1, k, 0]), float(y[m + 1]), float(c[m + 1, k, 1])]
                shapes[f"s{len(fiber_of):06d}"] = {"type": "cylinder", "p0": p0, "p1": p1, "radius": float(r)}
                fiber_of.append(k)
                d = np.subtract(p1, p0)
                axis.append(d / np.linalg.norm(d))
        # a cylinder's frame, built from p0 and p1 in float32, is orthogonal only to rounding:
        # Mitsuba calls that shearing and warns once per segment
        level = mi.logger().log_level()
        mi.logger().set_log_level(mi.LogLevel.Error)
        try:
            self.scene = mi.load_dict({"type": "scene", **shapes})
        finally:
            mi.logger().set_log_level(level)
        # Mitsuba numbers shapes in the order it stores them: map each back by its bounding box's
        # centre, the segment's midpoint
        mid = np.array([np.add(v["p0"], v["p1"]) * 0.5 for v in shapes.values()])
        centres = []
        for shape in self.scene.shapes():
            bb = shape.bbox()
            centres.append([(bb.min.x + bb.max.x) / 2, (bb.min.y + bb.max.y) / 2, (bb.min.z + bb.max.z) / 2])
        _, order = cKDTree(mid).query(np.array(centres, np.float64).reshape(-1, 3))
        self.fiber_of = np.asarray(fiber_of, np.uint32)[order]
        self.axis = np.asarray(axis, np.float64)[order]
        self.radii = b.radii


@dataclass
class TwistedPaths(LoopState):
    """Per-path state of the 3D loop (Dr.Jit arrays, one lane a path)."""

    o: Any           # ray origin (Point3f), its y within [0, period)
    d: Any           # ray direction (Vector3f)
    B: list          # spectral weight, per wavelength
    R: list          # weight absorbed (expected value), per wavelength
    depth: Any       # fiber events so far
    wraps: Any       # crossings of the period's ends
    status: Any
    bin: Any
    active: Any
    pid: Any
    phi_i: Any       # incident azimuth (for relative binning)
    steps: Any       # segments traced in this round


@dataclass
class _Upload:
    scene: Any
    fiber_of: Any
    axis: list       # three Floats: each segment's unit axis
    radii: Any
    seed: Any


def segment_limits(o, d, Rb: float, P: float):
    """How far the ray ``o + t d`` may go within one period of the ply: ``(t_out, t_end)``,
    to where it leaves the bounding cylinder of radius ``Rb`` and to the period's end
    (``y`` in [0, P]); ``inf`` where it never does."""
    a = d.x * d.x + d.z * d.z
    bq = o.x * d.x + o.z * d.z
    c = o.x * o.x + o.z * o.z - Rb * Rb
    t_out = dr.select(a > 1e-12, (-bq + dr.safe_sqrt(bq * bq - a * c)) / dr.maximum(a, 1e-12), dr.inf)
    t_end = dr.select(d.y > 0, (P - o.y) / d.y, dr.select(d.y < 0, -o.y / d.y, dr.inf))
    return dr.maximum(t_out, 0.0), t_end


def through_end(o, d, t_end: float, P: float):
    """Where the ray ``o + t d`` leaves the period through an end, ``t_end`` along it, moved to
    the other end: the same point a period away."""
    out = o + d * t_end
    out.y = dr.select(d.y > 0, 0.0, P)
    return out


def directions(phi, theta) -> np.ndarray:
    """Unit directions ``[n, 3]`` of azimuths ``phi`` and longitudes ``theta`` in the ply frame."""
    return np.stack([np.cos(theta) * np.cos(phi), np.sin(theta), np.cos(theta) * np.sin(phi)], -1)


def entry_points(phi, t, y, Rb: float) -> np.ndarray:
    """Where lines arriving from azimuths ``phi`` (towards them) enter the bounding cylinder of
    radius ``Rb`` at offsets ``t`` across it, at heights ``y``: ``[n, 3]``."""
    dh = np.stack([np.cos(phi + np.pi), np.sin(phi + np.pi)], -1)   # horizontal travel
    side = np.stack([-dh[:, 1], dh[:, 0]], -1)
    o_h = -np.sqrt(np.maximum(Rb**2 - t**2, 0.0))[:, None] * dh + t[:, None] * side
    return np.stack([o_h[:, 0], y, o_h[:, 1]], -1)


def hit_frame(pi, ray, up: _Upload, active):
    """The fiber's frame where ``ray`` meets it (``pi`` its preliminary intersection): its
    tangent ``T`` (the segment's axis), ``e1, e2`` spanning the plane normal to it (the fiber
    frame's x and z: for ``T = +y``, ``x`` and ``z``), the outward normal ``n`` in that plane,
    the centre line's point ``centre`` at the hit's height, the radius ``r`` and the fiber ``k``."""
    Float, UInt = mi.Float, mi.UInt32
    si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
    T = mi.Vector3f(*(dr.gather(Float, ax, pi.shape_index, active) for ax in up.axis))
    k = dr.gather(UInt, up.fiber_of, pi.shape_index, active)
    r = dr.gather(Float, up.radii, k, active)
    n = dr.normalize(si.n - T * dr.dot(si.n, T))
    e1 = dr.normalize(dr.select(dr.abs(T.z) > 0.999, dr.cross(mi.Vector3f(1.0, 0.0, 0.0), T),
                                dr.cross(T, mi.Vector3f(0.0, 0.0, 1.0))))
    return T, e1, dr.cross(e1, T), n, si.p - r * n, r, k


def local_angles(w, T, e1, e2):
    """``(theta, phi)`` of the direction ``w`` in the fiber frame ``(e1, T, e2)`` of :func:`hit_frame`."""
    return dr.safe_asin(dr.dot(w, T)), dr.atan2(dr.dot(w, e2), dr.dot(w, e1))


class TwistedBaker:
    """Traces batches of paths through a twisted ply; ``trace(phi_index, n_paths, seed)``
    returns a :class:`Tally` as :class:`~models.bake.baker.Baker`'s does (each path one
    ``theta_i`` node, in turn: ``paths_theta`` and ``passthrough_theta`` count them)."""

    ROUND = 16         # segments per round of the loop before compaction
    TAIL_LANES = 4096  # with this few paths left, the last round runs to the end

    def __init__(self, ply: TwistedBundle, fiber: FiberTable, spec: BakeSpec):
        if spec.estimator != "fast":
            raise ValueError(f"a twisted ply is traced with the fast estimator (got {spec.estimator!r})")
        lobes.check_exit(fiber.meta, spec.exit)
        self.ply, self.fiber, self.spec = ply, fiber, spec
        self.geometry = TwistedScene(ply)
        self.twin = DrJitFiber(fiber, FiberSampler(fiber), mi.Float)
        # the h-resolved ray fiber for the lobe exit (refuses any other fiber, with the reason)
        self.lobes = lobes.LobeSampler(fiber.meta, fiber.wavelength, mi.Float) if spec.exit == "lobe" else None
        # the h-resolved adjoint for the curve exit of a ray fiber of camera transport
        camera = fiber.meta.get("model") == "ray" and fiber.meta.get("transport") == "camera"
        self.curve_lobes = (lobes.LobeSampler(fiber.meta, fiber.wavelength, mi.Float)
                            if spec.exit == "curve" and camera else None)
        self.n_lambda = len(fiber.wavelength)

    # -- entry -----------------------------------------------------------------------
    def trace(self, phi_index: int, n_paths: int, seed) -> Tally:
        self.spec.theta_cells.upload(mi.Float)  # read in the bounce loop: uploaded before it
        spec, L = self.spec, self.n_lambda
        rng = np.random.default_rng(seed)
        Rb, P = self.ply.bundle.bounding_radius, self.geometry.period
        n_ti = len(spec.theta_i)
        # stratified offsets across 2 R_b, heights over a period, theta_i nodes in turn
        t = across_width(n_paths, Rb, rng)
        y0 = P * shuffled_strata(n_paths, rng)
        j = (rng.integers(n_ti) + np.arange(n_paths)) % n_ti
        phi_i = incident_azimuths(spec, phi_index, n_paths, rng)
        # light from w_i travels along d = -w_i; it enters the bounding cylinder at offset t
        d = -directions(phi_i, spec.theta_i[j])
        origin = entry_points(phi_i, t, y0, Rb)
        count = np.bincount(j, minlength=n_ti)
        weight = n_paths / np.maximum(count, 1)   # each node normalized by its own paths

        out = self._loop(origin, d, phi_i, int(rng.integers(2**62)))
        status, bins = out["status"], out["bin"]
        tally = Tally.zeros(spec, L)
        tally.vertices = out["vertices"]
        passed = (out["depth"] == 0) & (status == ESCAPED)
        tally.paths[phi_index] = n_paths
        tally.passthrough[phi_index] = np.sum(passed)
        tally.paths_theta[phi_index] = count
        tally.passthrough_theta[phi_index] = np.bincount(j[passed], minlength=n_ti)
        n_bins = spec.n_phi_o * spec.n_theta_o
        W = np.stack([b.numpy() for b in out["B"]], -1).astype(np.float64) * weight[j][:, None]  # [path, lambda]
        esc = (status == ESCAPED) & ~passed
        cells, bins = split_bins(spec, bins)   # the exit offset's cell rides above the bin
        if spec.offsets:  # the near field: exits by their offset's cell, paths by their entry's
            N = spec.offsets
            dh = np.stack([np.cos(phi_i + np.pi), np.sin(phi_i + np.pi)], -1)   # horizontal travel
            entry = offset_cell(N, origin[:, 0], origin[:, 2], np.arctan2(dh[:, 1], dh[:, 0]), Rb)
            tally.paths_h[phi_index] = np.bincount(j * N + entry, minlength=n_ti * N).reshape(n_ti, N)
            tally.passthrough_h[phi_index] = np.bincount(j[passed] * N + entry[passed],
                                                         minlength=n_ti * N).reshape(n_ti, N)
            tally.add_offsets(phi_index, cells[esc], bins[esc], j[esc], W[esc])
        flat = j[esc] * n_bins + bins[esc]
        for l in range(L):
            tally.sum[phi_index, ..., l] += np.bincount(flat, W[esc, l], n_ti * n_bins).reshape(
                n_ti, spec.n_phi_o, spec.n_theta_o)
            tally.sum_sq[phi_index, ..., l] += np.bincount(flat, W[esc, l] ** 2, n_ti * n_bins).reshape(
                n_ti, spec.n_phi_o, spec.n_theta_o)
        if tally.orders is not None:
            tally.add_orders(phi_index, out["depth"][esc].astype(np.int64), bins[esc].astype(np.int64), j[esc],
                             W[esc])
        once = esc & (out["depth"] == 1)  # one fiber event: singly scattered
        for l in range(L):
            tally.single[phi_index, :, l] += np.bincount(j[once], W[once, l], n_ti)
        capped = status == CAPPED
        R = np.stack([r.numpy() for r in out["R"]], -1).astype(np.float64) * weight[j][:, None]
        for l in range(L):
            tally.lost[phi_index, :, l] += np.bincount(j[capped], W[capped, l], n_ti)
            tally.absorbed[phi_index, :, l] += np.bincount(j, R[:, l], n_ti)
        return tally

    # -- the loop --------------------------------------------------------------------
    def _loop(self, origin, d, phi_i, seed) -> dict:
        Float, UInt = mi.Float, mi.UInt32
        n, L, g = len(d), self.n_lambda, self.geometry
        up = _Upload(scene=g.scene, fiber_of=UInt(g.fiber_of), axis=[Float(g.axis[:, k].astype(np.float32))
                                                                      for k in range(3)],
                     radii=Float(g.radii.astype(np.float32)), seed=dr.opaque(mi.UInt64, seed % 2**63))
        paths = TwistedPaths(
            o=mi.Point3f(*(to_drjit(Float, origin[:, k]) for k in range(3))),
            d=mi.Vector3f(*(to_drjit(Float, d[:, k]) for k in range(3))),
            B=[dr.full(Float, 1.0, n) for _ in range(L)], R=[dr.zeros(Float, n) for _ in range(L)],
            depth=dr.zeros(UInt, n), wraps=dr.zeros(UInt, n), status=dr.zeros(UInt, n), bin=dr.zeros(UInt, n),
            active=dr.full(mi.Bool, True, n), pid=dr.arange(UInt, n), phi_i=to_drjit(Float, phi_i),
            steps=dr.zeros(UInt, n))
        out = in_rounds(paths, lambda p, limit: self._run(p, up, limit), self.ROUND, 0xFFFFFFFF, self.TAIL_LANES)
        out["vertices"] = int(out["depth"].astype(np.int64).sum())
        return out

    @dr.syntax
    def _run(self, paths: TwistedPaths, up: _Upload, limit) -> TwistedPaths:
        while dr.hint(paths.active & (paths.steps < limit), label="bake_twisted"):
            paths = self._step(paths, up)
        return paths

    def _step(self, p: TwistedPaths, up: _Upload) -> TwistedPaths:
        """One segment of every active path: to the next fiber, the period's end, or out."""
        p.steps = p.steps + 1
        spec, Rb, P = self.spec, self.ply.bundle.bounding_radius, self.geometry.period

        # Phase 1: how far the ray may go: out of the bounding cylinder, or to the period's end
        t_out, t_end = segment_limits(p.o, p.d, Rb, P)
        t_max = dr.minimum(t_out, t_end)
        ray = mi.Ray3f(mi.Ray3f(p.o, p.d), t_max)
        pi = up.scene.ray_intersect_preliminary(ray, coherent=False, active=p.active)
        hit = p.active & pi.is_valid()

        # Phase 2: no fiber before the end of the period: wrap around it; before the bound: escape
        wrap = p.active & ~hit & (t_end < t_out)
        escaped = p.active & ~hit & ~wrap
        p.status = dr.select(escaped, ESCAPED, p.status)
        phi = dr.atan2(p.d.z, p.d.x)
        theta = dr.safe_asin(p.d.y)
        p.bin = dr.select(escaped, output_bin(spec, phi, theta, p.phi_i, dr, (p.o.x, p.o.z), Rb), p.bin)
        p.wraps = dr.select(wrap, p.wraps + 1, p.wraps)
        p.status = dr.select(wrap & (p.wraps > MAX_WRAPS), CAPPED, p.status)
        p.o = dr.select(wrap, through_end(p.o, p.d, t_end, P), p.o)

        # Phase 3: a fiber event, in the fiber's frame (T its axis)
        capped = hit & (p.depth >= spec.max_bounces)
        p.status = dr.select(capped, CAPPED, p.status)
        go = hit & ~capped
        p.depth = dr.select(go, p.depth + 1, p.depth)
        T, e1, e2, n, centre, r, _ = hit_frame(pi, ray, up, go)
        wi = -p.d
        theta_in, phi_wi = local_angles(wi, T, e1, e2)

        # the ray's offset h across the fiber, in the plane normal to T (the 2D bake's, per fiber)
        s_d, c_d = dr.sincos(phi_wi + np.pi)                      # the ray's travel in that plane
        h_in = lobes.entry_offset(0.0, 0.0, r, r * dr.dot(n, e1), r * dr.dot(n, e2), c_d, s_d, dr)

        rng = mi.PCG32()
        rng.seed(up.seed + mi.UInt64(p.depth), mi.UInt64(p.pid))
        u = [rng.next_float32() for _ in range(5)]
        x6, x7 = rng.next_float32(), rng.next_float32()
        if self.lobes is not None:  # a path (lobe) at the ray's own offset, and where it leaves
            path, theta_out, dphi, pdf = self.lobes.sample(theta_in, h_in, u[:4])
            f, alb = self.lobes.eval_spectrum(theta_in, h_in, path, theta_out, dphi)
        else:
            theta_out, dphi, pdf, f, alb = self.twin.event(theta_in, u)
        phi_wo = phi_wi + dphi
        s_o, c_o = dr.sincos(phi_wo)
        if spec.exit == "curve":  # the curve's value; its difference from f is booked as absorbed
            nx, nz, h_out, w = lobes.curve_exit(h_in, c_d, s_d, c_o, s_o, x7, dr)
            f, alb = weights.curve_event(self.curve_lobes, theta_in, theta_out, dphi, h_out, w, f, alb)

        # Phase 4: the weight (B carries f cos / pdf, R the expected absorption) and roulette
        p.B, p.R, kept, roulette = weights.scatter(p.B, p.R, f, alb, theta_out, pdf, go, p.depth, spec.rr_start, x6)
        p.status = dr.select(go & ~kept, STOPPED, p.status)
        alive = go & kept
        h_u = dr.select(roulette, x7, x6)

        # Phase 5: leave the fiber's surface (the exit model, in the plane normal to T): anywhere
        # on the outgoing side, where the light entered, where its path leaves, or (curve) at an
        # end of its chord
        ex, ez = lobes.leave_uniform(0.0, 0.0, r, 2 * h_u - 1, c_o, s_o, dr)
        if spec.exit == "curve":  # the end of the light's chord chosen above
            ex, ez = r * (1 + 1e-4) * nx, r * (1 + 1e-4) * nz
        elif spec.exit != "uniform":
            nx, nz = lobes.entry_normal(h_in, c_d, s_d, dr)
            if self.lobes is not None:
                nx, nz = self.lobes.exit_normal(nx, nz, path, h_in, theta_in, dr)
            lx, lz = lobes.leave(0.0, 0.0, r, nx, nz, c_o, s_o, dr)
            if self.lobes is not None:  # the residual has no single exit: it keeps the uniform one
                placed = path != self.lobes.p_max
                lx, lz = dr.select(placed, lx, ex), dr.select(placed, lz, ez)
            ex, ez = lx, lz
        exit_point = centre + e1 * ex + e2 * ez
        wo = e1 * (dr.cos(theta_out) * c_o) + e2 * (dr.cos(theta_out) * s_o) + T * dr.sin(theta_out)
        # an exit point beyond the period's ends is the same point a period away
        exit_point.y = exit_point.y - P * dr.floor(exit_point.y * (1.0 / P))
        p.o = dr.select(alive, exit_point, p.o)
        p.d = dr.select(alive, dr.normalize(wo), p.d)
        p.active = p.active & (p.status == 0)
        return p
