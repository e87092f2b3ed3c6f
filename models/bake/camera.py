"""The ``curve`` exit's table traced from the camera, as Mitsuba's path tracer renders a ply
of explicit ``hair`` fibers (``BakeSpec.estimator = "camera"``).

The light-side ``fast`` estimator with the ``curve`` exit (``models.bake.baker``) weighs the
end of a light ray's chord by ``w = sum_k a_k / sqrt(1 - h^2)``, the change from the light's
offset ``h`` to the camera's: its mean over ``h`` is 1, its second moment grows as
``log(1 / (1 - |h|))``, so a ply whose paths meet many fibers sums heavy-tailed products of
it. Traced from the camera the same table has no such factor: a camera ray meets a fiber at
the offset ``hair`` reads, and the light reaches that point along one line, through its own
fiber (a curve is invisible from inside). Per camera path, in the cross-section as the light
side's bake:

1. the camera direction ``w_o`` (longitude ``theta_o``, azimuth ``phi_l + dphi``) is drawn
   uniformly in solid angle within its output bin, and its ray enters the bounding width
   ``2 R_b`` at a stratified offset; every bin gets the same number of paths;
2. at each fiber the ray meets, at the offset ``h`` of the camera's ray, the light is added
   (next-event estimation): the throughput ``beta`` times the ray fiber in light transport
   with the camera side as incident, ``f(w_cam -> w_l; h)`` (what ``hair``'s ``eval``
   returns), for every incident longitude ``theta_i`` of the table at once, where the line
   from the point towards the light (the light's azimuth ``phi_l``) leaves the ply unblocked;
3. the path goes on in a direction sampled from the same lobes (``beta *= f cos / pdf``),
   from the point it met, or, pointing into its fiber, from the far end of that chord;
   Russian roulette as the light side's.

The estimate of the bin is ``S(w_i -> w_o) = cos(theta_o) / cos(theta_i)`` times the mean
over the width of the light a camera ray gathers (docs/DESIGN.md, "The far-field closure
test": ``I = E 2 R_b cos(theta_i) S`` is what an orthographic render sees). For one fiber it
is the adjoint averaged over the camera's offset, as the ``curve`` exit's.

The passthrough is counted with rays from the light as in the light-side bake. A camera
path sees no light-side absorption: ``absorbed`` is the balance's remainder ``1 - scattered -
passthrough`` where that is positive; where the adjoint scatters more than arrives (towards
grazing light) it is zero and the balance's total exceeds 1 by the excess. ``lost`` is zero:
the light a path would have gathered past the bounce cap is not known. ``single`` is the
light gathered at the first fiber. Parallel plies of a ray fiber of camera transport (twisted
ones: ``models.bake.twisted_camera``); orders and offsets are not kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi  # its types resolve to the variant chosen at the entry point, at call time
import numpy as np

from ..bundle import Bundle
from ..fiber import lobes
from ..fiber.base import FiberTable
from ..jit import to_drjit
from . import weights
from .baker import CAPPED, ESCAPED, STOPPED, LoopScene
from .rounds import LoopState, in_rounds
from .scene import BundleScene, across_width, incident_azimuths
from .tally import BakeSpec, Tally


@dataclass
class CameraPaths(LoopState):
    """Per-path state of the camera loop (Dr.Jit arrays, one lane a path)."""

    ox: Any            # where the camera path's next ray starts, in the cross-section (x, z)
    oz: Any
    phi: Any           # its azimuth of travel
    theta: Any         # its longitude of travel
    B: list            # throughput beta, per wavelength
    C: list            # light gathered, per (theta_i, wavelength): index j * L + l
    C1: list           # of it, what the first fiber gathered
    depth: Any         # fibers met so far
    status: Any
    active: Any
    pid: Any
    phi_l: Any         # the light's azimuth (towards it)
    steps: Any

    RESULTS = ("C", "C1", "depth", "status")


def check_camera(fiber: FiberTable, spec: BakeSpec) -> None:
    """Refuse what the camera estimator cannot trace: another estimator's spec, or a fiber
    other than a ray fiber of camera transport."""
    if spec.estimator != "camera":
        raise ValueError(f"the camera tracers trace the camera estimator (spec.estimator is {spec.estimator!r})")
    if fiber.meta.get("model") != "ray" or fiber.meta.get("transport") != "camera":
        raise ValueError("the camera estimator traces what Mitsuba's hair renders: it needs a ray fiber of camera "
                         "transport (fiber.ray.transport: camera)")


def camera_directions(spec: BakeSpec, a, c, phi_l, rng):
    """``(phi_o, theta_o)`` of camera directions drawn uniformly in solid angle within the output
    bins ``(a, c)`` (azimuth and longitude bins), for lights at azimuths ``phi_l``."""
    edges = spec.phi_o_edges
    phi_o = edges[a] + (edges[a + 1] - edges[a]) * rng.uniform(size=len(a))
    if spec.relative_phi:
        phi_o = phi_o + phi_l
    s0, s1 = np.sin(spec.theta_o_edges[c]), np.sin(spec.theta_o_edges[c + 1])
    return phi_o, np.arcsin(np.clip(s0 + (s1 - s0) * rng.uniform(size=len(c)), -1.0, 1.0))


class CameraBaker:
    """Traces the ``curve`` exit's table from the camera; see the module docstring."""

    ROUND = 16
    TAIL_LANES = 4096

    def __init__(self, bundle: Bundle, fiber: FiberTable, spec: BakeSpec):
        check_camera(fiber, spec)
        self.bundle, self.fiber, self.spec = bundle, fiber, spec
        self.geometry = BundleScene(bundle)
        self.lob = lobes.LobeSampler(fiber.meta, fiber.wavelength, mi.Float)
        self.n_lambda = len(fiber.wavelength)

    def trace(self, phi_index: int, n_paths: int, seed) -> Tally:
        spec, L = self.spec, self.n_lambda
        rng = np.random.default_rng(seed)
        tally = Tally.zeros(spec, L)
        Rb = self.bundle.bounding_radius
        n_bins = spec.n_phi_o * spec.n_theta_o
        m = max(1, n_paths // n_bins)  # camera paths per bin
        n = m * n_bins

        # Phase 1: the passthrough, with rays from the light as the light side counts it
        phi_i = incident_azimuths(spec, phi_index, n_paths, rng)
        t = across_width(n_paths, Rb, rng)
        hit, _ = self.geometry.cast(*self.geometry.entry(phi_i, t))
        tally.count(phi_index, n_paths, int(np.sum(~hit)))

        # Phase 2: the camera rays, m per bin: the direction uniform in the bin's solid angle,
        # the offsets stratified across the width within each bin
        flat = np.arange(n) % n_bins
        stratum = np.arange(n) // n_bins
        a, c = np.divmod(flat, spec.n_theta_o)
        phi_l = incident_azimuths(spec, phi_index, n, rng)
        phi_o, theta_o = camera_directions(spec, a, c, phi_l, rng)
        t = (-1 + 2 * (stratum + rng.uniform(size=n)) / m) * Rb
        origin, phi_t = self.geometry.entry(phi_o, t)
        final = self._gather(origin, phi_t, -theta_o, phi_l, int(rng.integers(2**62)))
        tally.vertices += int(final["depth"].astype(np.int64).sum())

        # Phase 3: S per path, cos(theta_o) / cos(theta_i) times the light it gathered; sums
        # per bin (numpy, float64, in a fixed order)
        n_ti = len(spec.theta_i)
        omega = spec.bin_solid_angle().ravel()[flat]
        scale = np.cos(theta_o)[:, None] / np.maximum(np.cos(spec.theta_i), lobes.COS_GRAZING)[None, :]
        sums = np.zeros((n_ti, n_bins, L))
        sums_sq = np.zeros_like(sums)
        single = np.zeros((n_ti, L))
        for j in range(n_ti):
            for l in range(L):
                S = final["C"][j * L + l].numpy().astype(np.float64) * scale[:, j] * omega
                sums[j, :, l] = np.bincount(flat, S, n_bins)
                sums_sq[j, :, l] = np.bincount(flat, S * S, n_bins)
                S1 = final["C1"][j * L + l].numpy().astype(np.float64) * scale[:, j] * omega
                single[j, l] = S1.sum() / m   # over the bins, omega S_1
        shape = (n_ti, spec.n_phi_o, spec.n_theta_o, L)
        tally.sum[phi_index] += sums.reshape(shape)
        tally.sum_sq[phi_index] += sums_sq.reshape(shape)
        tally.bin_paths[phi_index] += m
        # per path launched, as the light side keeps them: what the first fiber scattered, and
        # the balance's remainder as absorbed (none where the adjoint makes more light than arrives)
        tally.single[phi_index] += n_paths * single
        scattered = sums.sum(axis=1) / m
        passed = tally.passthrough[phi_index] / n_paths
        tally.absorbed[phi_index] += n_paths * np.maximum(1 - passed - scattered, 0.0)
        return tally

    def _gather(self, origin, phi_t, theta, phi_l, seed) -> dict:
        """Trace every camera path to its end (one symbolic loop, in rounds): the light each
        gathered, ``C`` and ``C1`` (Dr.Jit, per theta_i and wavelength), and its fibers met."""
        Float, UInt = mi.Float, mi.UInt32
        n, L, n_ti = len(phi_t), self.n_lambda, len(self.spec.theta_i)
        scene = LoopScene.upload(self.geometry, self.bundle, seed)
        paths = CameraPaths(
            ox=to_drjit(Float, origin[:, 0]), oz=to_drjit(Float, origin[:, 1]),
            phi=to_drjit(Float, np.mod(phi_t, 2 * np.pi)), theta=to_drjit(Float, theta),
            B=[dr.full(Float, 1.0, n) for _ in range(L)],
            C=[dr.zeros(Float, n) for _ in range(n_ti * L)], C1=[dr.zeros(Float, n) for _ in range(n_ti * L)],
            depth=dr.zeros(UInt, n), status=dr.zeros(UInt, n), active=dr.full(mi.Bool, True, n),
            pid=dr.arange(UInt, n), phi_l=to_drjit(Float, np.mod(phi_l, 2 * np.pi)), steps=dr.zeros(UInt, n))
        return in_rounds(paths, lambda p, limit: self._round(p, scene, limit), self.ROUND,
                         self.spec.max_bounces + 2, self.TAIL_LANES)

    @dr.syntax
    def _round(self, paths: CameraPaths, scene: LoopScene, limit) -> CameraPaths:
        while dr.hint(paths.active & (paths.steps < limit), label="bake_camera"):
            paths = self._vertex(paths, scene)
        return paths

    def _vertex(self, p: CameraPaths, scene: LoopScene) -> CameraPaths:
        """One fiber of every active camera path: the light there, and the path's next ray."""
        spec, lob, L = self.spec, self.lob, self.n_lambda
        Float, UInt = mi.Float, mi.UInt32
        p.steps = p.steps + 1

        # Phase 1: the camera's ray; one that leaves the ply sees the black background
        sp, cp = dr.sincos(p.phi)
        ray = mi.Ray3f(mi.Point3f(p.ox, 0.0, p.oz), mi.Vector3f(cp, 0.0, sp))
        hit_info = scene.scene.ray_intersect_preliminary(ray, coherent=False, active=p.active)
        hit = p.active & hit_info.is_valid()
        p.status = dr.select(p.active & ~hit, ESCAPED, p.status)
        capped = hit & (p.depth >= spec.max_bounces)
        p.status = dr.select(capped, CAPPED, p.status)
        go = hit & ~capped
        p.depth = dr.select(go, p.depth + 1, p.depth)
        k = dr.gather(UInt, scene.shape_to_fiber, hit_info.shape_index, go)
        cx, cz = dr.gather(Float, scene.centers_x, k, go), dr.gather(Float, scene.centers_z, k, go)
        r = dr.gather(Float, scene.radii, k, go)
        h = lobes.entry_offset(cx, cz, r, p.ox, p.oz, cp, sp, dr)    # the offset hair reads
        nx, nz = lobes.entry_normal(h, cp, sp, dr)                    # the point the camera sees
        theta_cam, phi_cam = -p.theta, p.phi + np.pi                  # towards the camera's side

        # Phase 2: the light at that point, through its own fiber, for every theta_i at once
        sl, cl = dr.sincos(p.phi_l)
        lx, lz = lobes.leave(cx, cz, r, nx, nz, cl, sl, dr)
        blocked = scene.scene.ray_test(mi.Ray3f(mi.Point3f(lx, 0.0, lz), mi.Vector3f(cl, 0.0, sl)), go)
        lit = go & ~blocked
        dphi_l = lobes.wrap(p.phi_l - phi_cam, dr)
        f_l = lob.eval_all(theta_cam, h, [Float(float(t)) for t in spec.theta_i], dphi_l)
        p.C = [dr.select(lit, p.C[j * L + l] + p.B[l] * f_l[j][l], p.C[j * L + l])
               for j in range(len(spec.theta_i)) for l in range(L)]
        first = go & (p.depth == 1)
        p.C1 = [dr.select(first, c, c1) for c, c1 in zip(p.C, p.C1)]

        # Phase 3: the path goes on, sampled from the same lobes at the same offset
        rng = mi.PCG32()
        rng.seed(scene.seed + mi.UInt64(p.depth), mi.UInt64(p.pid))
        u = [rng.next_float32() for _ in range(5)]
        path, theta_out, dphi, pdf = lob.sample(theta_cam, h, u[:4])
        f, _ = lob.eval_spectrum(theta_cam, h, path, theta_out, dphi)
        p.B, _, kept, _ = weights.scatter(p.B, None, f, None, theta_out, pdf, go, p.depth, spec.rr_start, u[4])
        p.status = dr.select(go & ~kept, STOPPED, p.status)
        alive = go & kept
        phi_n = phi_cam + dphi
        phi_n = phi_n - 2 * np.pi * dr.floor(phi_n * (1 / (2 * np.pi)))
        s_o, c_o = dr.sincos(phi_n)
        new_x, new_z = lobes.leave(cx, cz, r, nx, nz, c_o, s_o, dr)  # inwards: from the chord's far end
        p.ox = dr.select(alive, new_x, p.ox)
        p.oz = dr.select(alive, new_z, p.oz)
        p.phi = dr.select(alive, phi_n, p.phi)
        p.theta = dr.select(alive, theta_out, p.theta)
        p.active = alive
        return p
