"""The ``curve`` exit's table of a twisted ply traced from the camera, in 3D
(``BakeSpec.estimator = "camera"`` for a :class:`~models.bundle.TwistedBundle`).

The parallel ply's camera estimator (``models.bake.camera``, whose docstring gives the
reasons and the estimate) in the twisted ply's 3D geometry (``models.bake.twisted``: one
period of helices as cylinder segments, a ray wrapped round the period's ends). As there,
a camera ray meets a fiber at the offset ``hair`` reads, the light is added there where the
line towards it leaves the ply unblocked (through the fiber's own interior: a curve is
invisible from inside), and the path goes on in a direction sampled from the same lobes,
from the point it met or, pointing into its fiber, from the far end of its chord, in 3D: each
line is followed past the walls of its own fiber within a chord's reach (the helix is built
of short straight segments that overlap at its bends).

Each path carries one incident ``theta_i`` (the light's longitude changes the geometry of its
line), so its paths are spread evenly over (``theta_i``, output bin); the passthrough per
``theta_i`` is counted with lines from the light traced through the same loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi  # its types resolve to the variant chosen at the entry point, at call time
import numpy as np

from ..bundle import TwistedBundle
from ..fiber import lobes
from ..fiber.base import FiberTable
from ..jit import to_drjit
from . import weights
from .camera import camera_directions, check_camera
from .rounds import LoopState, in_rounds
from .tally import BakeSpec, Tally
from .scene import across_width, incident_azimuths
from .twisted import (CAPPED, ESCAPED, MAX_WRAPS, STOPPED, TwistedScene, _Upload, directions, entry_points,
                      hit_frame, local_angles, segment_limits, through_end)

# segments of a shadow line: enough to cross every period end it can meet before leaving the
# bounding cylinder is checked at construction (longitude of the steepest theta_i node)
SHADOW_SEGMENTS = 4
# walls of its own fiber a line may meet on its way out (TwistedCameraBaker._leave)
OWN_WALLS = 4


@dataclass
class TwistedCameraPaths(LoopState):
    """Per-path state of the twisted camera loop (Dr.Jit arrays, one lane a path)."""

    o: Any           # ray origin (Point3f), its y within [0, period)
    d: Any           # ray direction (Vector3f)
    wl: Any          # towards the light (Vector3f)
    B: list          # throughput, per wavelength
    C: list          # light gathered, per wavelength
    C1: list         # of it, at the first fiber
    depth: Any
    wraps: Any
    status: Any
    active: Any
    probe: Any       # a line from the light, traced for the passthrough only
    pid: Any
    steps: Any

    RESULTS = ("C", "C1", "depth", "status")


class TwistedCameraBaker:
    """Traces the ``curve`` exit's table of a twisted ply from the camera; see the module docstring."""

    ROUND = 16
    TAIL_LANES = 4096

    def __init__(self, ply: TwistedBundle, fiber: FiberTable, spec: BakeSpec):
        check_camera(fiber, spec)
        self.ply, self.fiber, self.spec = ply, fiber, spec
        self.geometry = TwistedScene(ply)
        Rb, P = ply.bundle.bounding_radius, self.geometry.period
        steepest = float(np.max(np.abs(spec.theta_i)))
        if 2 * Rb * np.tan(steepest) > (SHADOW_SEGMENTS - 2) * P:
            raise ValueError(f"the camera estimator's shadow lines cross at most {SHADOW_SEGMENTS - 2} periods of "
                             f"the ply: theta_i {np.rad2deg(steepest):.1f} deg is too steep for its period of {P:g} um")
        self.lob = lobes.LobeSampler(fiber.meta, fiber.wavelength, mi.Float)
        self.n_lambda = len(fiber.wavelength)

    def trace(self, phi_index: int, n_paths: int, seed) -> Tally:
        spec, L = self.spec, self.n_lambda
        rng = np.random.default_rng(seed)
        Rb, P = self.ply.bundle.bounding_radius, self.geometry.period
        n_ti, n_bins = len(spec.theta_i), spec.n_phi_o * spec.n_theta_o
        m = max(1, n_paths // (n_ti * n_bins))  # camera paths per (theta_i, bin)
        n = m * n_ti * n_bins

        # Phase 1: the camera rays, m per (theta_i, bin); the light's lines (probes) as many
        # as the light side would launch, each of a theta_i in turn
        k = np.arange(n)
        j, flat = np.divmod(k % (n_ti * n_bins), n_bins)
        stratum = k // (n_ti * n_bins)
        a, c = np.divmod(flat, spec.n_theta_o)
        phi_l = incident_azimuths(spec, phi_index, n, rng)
        phi_o, theta_o = camera_directions(spec, a, c, phi_l, rng)
        t = (-1 + 2 * (stratum + rng.uniform(size=n)) / m) * Rb
        y0 = P * rng.uniform(size=n)
        w_o = directions(phi_o, theta_o)
        w_l = directions(phi_l, spec.theta_i[j])
        jp = (rng.integers(n_ti) + np.arange(n_paths)) % n_ti
        phi_p = incident_azimuths(spec, phi_index, n_paths, rng)
        w_p = directions(phi_p, spec.theta_i[jp])
        t_p = across_width(n_paths, Rb, rng)
        origin = np.concatenate([entry_points(phi_o, t, y0, Rb),
                                 entry_points(phi_p, t_p, P * rng.uniform(size=n_paths), Rb)])
        out = self._loop(origin, -np.concatenate([w_o, w_p]), np.concatenate([w_l, w_p]),
                         np.arange(n + n_paths) >= n, int(rng.integers(2**62)))

        # Phase 2: the passthrough per theta_i, from the probes
        tally = Tally.zeros(spec, L)
        tally.vertices = int(out["depth"][:n].astype(np.int64).sum())
        passed = (out["depth"][n:] == 0) & (out["status"][n:] == ESCAPED)
        count = np.bincount(jp, minlength=n_ti)
        tally.paths[phi_index] = n_paths
        tally.passthrough[phi_index] = np.sum(passed)
        tally.paths_theta[phi_index] = count
        tally.passthrough_theta[phi_index] = np.bincount(jp[passed], minlength=n_ti)

        # Phase 3: S per camera path, cos(theta_o) / cos(theta_i) times what it gathered; sums
        # per (theta_i, bin)
        omega = spec.bin_solid_angle().ravel()[flat]
        scale = np.cos(theta_o) / np.maximum(np.cos(spec.theta_i[j]), lobes.COS_GRAZING) * omega
        row = j * n_bins + flat
        shape = (n_ti, spec.n_phi_o, spec.n_theta_o)
        p_theta = tally.passthrough_theta[phi_index] / np.maximum(count, 1)
        for l in range(L):
            S = out["C"][l].numpy()[:n].astype(np.float64) * scale
            S1 = out["C1"][l].numpy()[:n].astype(np.float64) * scale
            tally.sum[phi_index, ..., l] += np.bincount(row, S, n_ti * n_bins).reshape(shape)
            tally.sum_sq[phi_index, ..., l] += np.bincount(row, S * S, n_ti * n_bins).reshape(shape)
            single = np.bincount(j, S1, n_ti) / m
            scattered = tally.sum[phi_index, ..., l].reshape(n_ti, -1).sum(-1) / m
            # per path of each theta_i, as the light side keeps them (models.bake.camera)
            tally.single[phi_index, :, l] += count * single
            tally.absorbed[phi_index, :, l] += count * np.maximum(1 - p_theta - scattered, 0.0)
        tally.bin_paths[phi_index] += m
        return tally

    def _loop(self, origin, d, wl, probe, seed) -> dict:
        Float, UInt = mi.Float, mi.UInt32
        n, L, g = len(d), self.n_lambda, self.geometry
        up = _Upload(scene=g.scene, fiber_of=UInt(g.fiber_of), axis=[Float(g.axis[:, k].astype(np.float32))
                                                                      for k in range(3)],
                     radii=Float(g.radii.astype(np.float32)), seed=dr.opaque(mi.UInt64, seed % 2**63))
        vec = lambda a, T: T(*(to_drjit(Float, a[:, k]) for k in range(3)))  # noqa: E731
        paths = TwistedCameraPaths(
            o=vec(origin, mi.Point3f), d=vec(d, mi.Vector3f), wl=vec(wl, mi.Vector3f),
            B=[dr.full(Float, 1.0, n) for _ in range(L)], C=[dr.zeros(Float, n) for _ in range(L)],
            C1=[dr.zeros(Float, n) for _ in range(L)], depth=dr.zeros(UInt, n), wraps=dr.zeros(UInt, n),
            status=dr.zeros(UInt, n), active=dr.full(mi.Bool, True, n), probe=mi.Bool(probe),
            pid=dr.arange(UInt, n), steps=dr.zeros(UInt, n))
        return in_rounds(paths, lambda p, limit: self._run(p, up, limit), self.ROUND, 0xFFFFFFFF, self.TAIL_LANES)

    @dr.syntax
    def _run(self, paths: TwistedCameraPaths, up: _Upload, limit) -> TwistedCameraPaths:
        while dr.hint(paths.active & (paths.steps < limit), label="bake_twisted_camera"):
            paths = self._step(paths, up)
        return paths

    def _leave(self, x, n, w, r, k, theta_local, up: _Upload, active):
        """Where a line along ``w`` from the surface point ``x`` of fiber ``k`` (outward normal
        ``n``) starts, a hair outside its fiber: past every wall of that fiber it meets within
        the reach of a chord (``2 r / cos^2(theta)``, ``theta`` its longitude in the fiber's
        frame, and a radius more). A helix is built of short segments whose ends overlap at
        its bends, so a line can meet its own fiber's walls more than once on its way out."""
        cos = dr.maximum(dr.cos(theta_local), lobes.COS_GRAZING)
        reach = 2 * r / (cos * cos) + 2 * r
        o = x + dr.select(dr.dot(n, w) < 0, -n, n) * (1e-4 * r)
        gone, going = dr.zeros(mi.Float, dr.width(x)), mi.Bool(active)
        for _ in range(OWN_WALLS):
            pi = up.scene.ray_intersect_preliminary(mi.Ray3f(mi.Ray3f(o, w), dr.maximum(reach - gone, 0.0)),
                                                    coherent=False, active=going)
            own = going & pi.is_valid() & (dr.gather(mi.UInt32, up.fiber_of, pi.shape_index, going) == k)
            step = pi.t + 1e-4 * r
            o = dr.select(own, o + w * step, o)
            gone = dr.select(own, gone + step, gone)
            going = own
        return o

    def _visible(self, o, w, up: _Upload, active):
        """Whether the line from ``o`` along ``w`` leaves the ply unblocked: its segments within
        the period, wrapped round its ends (:data:`SHADOW_SEGMENTS` of them at most)."""
        Rb, P = self.ply.bundle.bounding_radius, self.geometry.period
        o = mi.Point3f(o)
        o.y = o.y - P * dr.floor(o.y * (1.0 / P))   # a point in the period's margins: a period away
        open_, going = dr.full(mi.Bool, False, dr.width(active)), mi.Bool(active)
        for _ in range(SHADOW_SEGMENTS):
            t_out, t_end = segment_limits(o, w, Rb, P)
            ray = mi.Ray3f(mi.Ray3f(o, w), dr.minimum(t_out, t_end))
            blocked = going & up.scene.ray_test(ray, going)
            wrap = going & ~blocked & (t_end < t_out)
            open_ = open_ | (going & ~blocked & ~wrap)
            o = dr.select(wrap, through_end(o, w, t_end, P), o)
            going = wrap
        return open_

    def _step(self, p: TwistedCameraPaths, up: _Upload) -> TwistedCameraPaths:
        """One segment of every active path: to the next fiber, the period's end, or out."""
        p.steps = p.steps + 1
        spec, Rb, P = self.spec, self.ply.bundle.bounding_radius, self.geometry.period

        # Phase 1: the ray within the period: a fiber, the period's end (wrap), or out of the ply
        t_out, t_end = segment_limits(p.o, p.d, Rb, P)
        ray = mi.Ray3f(mi.Ray3f(p.o, p.d), dr.minimum(t_out, t_end))
        pi = up.scene.ray_intersect_preliminary(ray, coherent=False, active=p.active)
        hit = p.active & pi.is_valid()
        wrap = p.active & ~hit & (t_end < t_out)
        p.status = dr.select(p.active & ~hit & ~wrap, ESCAPED, p.status)
        p.wraps = dr.select(wrap, p.wraps + 1, p.wraps)
        p.status = dr.select(wrap & (p.wraps > MAX_WRAPS), CAPPED, p.status)
        p.o = dr.select(wrap, through_end(p.o, p.d, t_end, P), p.o)
        # a probe (a line from the light) ends at its first fiber
        capped = hit & (p.probe | (p.depth >= spec.max_bounces))
        p.status = dr.select(capped, CAPPED, p.status)
        go = hit & ~capped
        p.depth = dr.select(go, p.depth + 1, p.depth)

        # Phase 2: the fiber's frame; the camera's side and offset there
        T, e1, e2, n, centre, r, k = hit_frame(pi, ray, up, go)
        x = p.o + p.d * pi.t                                      # the point the camera sees
        x = centre + n * r + T * dr.dot(x - centre, T)
        theta_cam, phi_cam = local_angles(-p.d, T, e1, e2)
        s_d, c_d = dr.sincos(phi_cam + np.pi)                     # the ray's travel in that plane
        h = lobes.entry_offset(0.0, 0.0, r, r * dr.dot(n, e1), r * dr.dot(n, e2), c_d, s_d, dr)

        # Phase 3: the light at that point, through its own fiber
        theta_l, phi_l = local_angles(p.wl, T, e1, e2)
        lit = self._visible(self._leave(x, n, p.wl, r, k, theta_l, up, go), p.wl, up, go)
        f_l = self.lob.eval_all(theta_cam, h, [theta_l], lobes.wrap(phi_l - phi_cam, dr))[0]
        p.C = [dr.select(lit, c + b * f, c) for c, b, f in zip(p.C, p.B, f_l)]
        first = go & (p.depth == 1)
        p.C1 = [dr.select(first, c, c1) for c, c1 in zip(p.C, p.C1)]

        # Phase 4: the path goes on, sampled from the same lobes at the same offset
        rng = mi.PCG32()
        rng.seed(up.seed + mi.UInt64(p.depth), mi.UInt64(p.pid))
        u = [rng.next_float32() for _ in range(5)]
        path, theta_out, dphi, pdf = self.lob.sample(theta_cam, h, u[:4])
        f, _ = self.lob.eval_spectrum(theta_cam, h, path, theta_out, dphi)
        p.B, _, kept, _ = weights.scatter(p.B, None, f, None, theta_out, pdf, go, p.depth, spec.rr_start, u[4])
        p.status = dr.select(go & ~kept, STOPPED, p.status)
        alive = go & kept
        s_o, c_o = dr.sincos(phi_cam + dphi)
        wo = dr.normalize(e1 * (dr.cos(theta_out) * c_o) + e2 * (dr.cos(theta_out) * s_o) + T * dr.sin(theta_out))
        start = self._leave(x, n, wo, r, k, theta_out, up, alive)
        start.y = start.y - P * dr.floor(start.y * (1.0 / P))   # beyond the period's ends: a period away
        p.o = dr.select(alive, start, p.o)
        p.d = dr.select(alive, wo, p.d)
        p.active = p.active & (p.status == 0)
        return p

