"""Wavefront path tracer through a bundle of parallel fibers (the ground truth).

Fibers are parallel and infinite, so a path's geometry lives in the cross-section:
rays are cast horizontally (in the x-z plane) against Mitsuba ``cylinder`` shapes, and
the longitude and the wavelength change only the path's weight. At every hit an
outgoing direction is chosen, the weight is multiplied by
``f(theta_in, theta_out, dphi) cos(theta_out) / pdf(theta_out, dphi)``, and the path
leaves the fiber from its surface at a lateral offset ``h r`` (``h`` uniform in
[-1, 1]) along the side vector ``y x d_out``. It ends when its ray escapes (tallied in
the bin of its direction), when Russian roulette stops it, or at the bounce cap (its
weight is reported as *lost*).

Estimators
==========

``thesis``  the thesis's scheme and the baseline: one wavelength and one theta_i per
            path (assigned round-robin), outgoing direction uniform in
            (theta_o, phi_o), fixed bounce cap, no roulette.
``fast``    one geometric path carries every wavelength and every theta_i. The first
            bounce samples from the mixture of the fiber's proposals over all incident
            theta_i (so the same direction is valid for each, with weight
            ``A[theta_i, lambda] = f cos / pdf_mix``); later bounces importance-sample
            the fiber at the path's own longitude. The weight factorizes as
            ``A[theta_i, lambda] * B[lambda]``, so a path stores only ``B`` and the
            first bounce, and ``A`` is evaluated once, when the path ends.
            Bounces 2.. run as one symbolic Dr.Jit loop, a single kernel (ray cast,
            sampling, pdf, spectral value, weight, roulette, exit point), in rounds
            with compaction of the unfinished paths; the first bounce and the final
            weights ``A B`` use the same Dr.Jit fiber code; the sums over paths are
            numpy (float64, in a fixed order).
``camera``  the ``curve`` exit's table traced from the camera, as Mitsuba's path tracer
            renders explicit ``hair`` fibers (``models.bake.camera``: another tracer).

Tallies (per incident azimuth phi_i, normalized by the paths entering the bounding
width ``2 R_b``): the summed weights and squared weights per output bin, the
passthrough count, the absorbed weight (expected loss ``1 - albedo`` at every
bounce) and the lost weight; with ``BakeSpec.orders`` the escaping weight also by its
number of fiber events (``Tally.add_orders``: the dye's order-resolved table).

A circle (``relative_phi``) has one table for all incident azimuths: each path enters
from its own azimuth (stratified over the circle) and is binned at ``phi_o - phi_i``,
so the table is the rotation average of the arrangement. A finite arrangement is not
rotation invariant (four fibers: passthrough 0.25 to 0.37 with the azimuth), so a
single azimuth would describe one orientation of the ply, not the ply.

Exit models
===========

Where scattered light starts its next ray (``BakeSpec.exit``):

``uniform``  anywhere on the outgoing side, ``h`` uniform (the thesis's);
``entry``    where the light entered; a direction back into the fiber crosses it;
``lobe``     where the sampled path (R, TT, TRT, ...) leaves, ``h``-resolved (ray fibers);
``curve``    as Mitsuba's curves: a curve is invisible from inside, so a light ray lights
             both ends of its chord through the fiber, and each end that faces the
             outgoing direction sends light there, as the BSDF says at the offset of the
             outgoing side's ray through it. The end is chosen in proportion to
             ``a_k = max(0, n_k . d_out)`` and the value is ``w`` times the BSDF there,
             ``w = sum_k a_k / sqrt(1 - h^2)`` (mean 1 over the offset ``h``): for a ray
             fiber of camera transport the adjoint at that offset
             (``LobeSampler.adjoint``: what Mitsuba's ``hair`` renders), for any other
             fiber its far field. A fiber alone scatters its far field; a shadowed one
             what the curve shows. Where that differs from the sampled fiber's own value
             (and albedo) the difference is booked as absorption, so the balance stays
             closed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi  # its types resolve to the variant chosen at the entry point, at call time
import numpy as np
from scipy import sparse

from ..bundle import Bundle
from ..fiber import lobes
from ..fiber.base import FiberTable
from ..fiber.sampling import FiberSampler
from ..fiber.sampling_drjit import DrJitFiber
from ..jit import to_drjit
from . import weights
from .rounds import LoopState, in_rounds
from .scene import BundleScene, across_width, incident_azimuths
from .tally import BakeSpec, Tally, offset_cell, output_bin, split_bins

# how a path of the fast estimator ended
ESCAPED, CAPPED, STOPPED = 1, 2, 3


# ------------------------------------------------------------------------------
# The state of the bounce loop
# ------------------------------------------------------------------------------

@dataclass
class Paths(LoopState):
    """The per-path state of the fast estimator's bounce loop (Dr.Jit arrays, one lane a
    path). A lane that has ended (``active`` false) keeps its state, so the state after the
    loop is the per-path result."""

    ox: Any            # where the path's next ray starts, in the cross-section (x, z)
    oz: Any
    phi: Any           # its azimuth of travel
    theta: Any         # its longitude (of w_o at the last fiber)
    B: list            # spectral weight after the first bounce, per wavelength
    R: list            # weight absorbed after the first bounce (expected value), per wavelength
    depth: Any         # bounces so far
    status: Any        # 0 while running, then ESCAPED, CAPPED or STOPPED
    bin: Any           # output bin of an escaped path
    active: Any
    pid: Any           # the path's index in the batch (its output row and its random stream)
    phi_i: Any         # its incident azimuth (a circle's paths enter from their own)
    steps: Any         # bounces in this round


@dataclass
class LoopScene:
    """What every bounce reads: the Mitsuba scene, the fibers uploaded, the batch's seed."""

    scene: Any
    centers_x: Any
    centers_z: Any
    radii: Any
    shape_to_fiber: Any
    seed: Any

    @classmethod
    def upload(cls, geometry: BundleScene, bundle: Bundle, seed: int) -> "LoopScene":
        """The scene and the fibers of ``bundle`` as float32 Dr.Jit arrays, ``seed`` opaque."""
        Float = mi.Float
        return cls(scene=geometry.scene, centers_x=Float(bundle.centers[:, 0].astype(np.float32)),
                   centers_z=Float(bundle.centers[:, 1].astype(np.float32)),
                   radii=Float(bundle.radii.astype(np.float32)),
                   shape_to_fiber=mi.UInt32(geometry.shape_to_fiber.astype(np.uint32)),
                   seed=dr.opaque(mi.UInt64, seed % 2**63))


# ------------------------------------------------------------------------------
# The tracer
# ------------------------------------------------------------------------------

class Baker:
    """Traces batches of paths; see the module docstring for the estimators."""

    ROUND = 16         # fast: bounces per round of the bounce loop before compaction
    TAIL_LANES = 4096  # fast: with this few paths left, the last round runs to the end
    CHUNK = 16384      # fast: paths per launch of the weights for every theta_i (their memory)

    def __init__(self, bundle: Bundle, fiber: FiberTable, spec: BakeSpec):
        lobes.check_exit(fiber.meta, spec.exit)
        self.bundle, self.fiber, self.spec = bundle, fiber, spec
        self.geometry = BundleScene(bundle)
        self.sampler = FiberSampler(fiber)
        self.n_lambda = len(fiber.wavelength)

    def _bin(self, phi_travel, theta, phi_i, xp=np, start=None):
        return output_bin(self.spec, phi_travel, theta, phi_i, xp, start, self.bundle.bounding_radius)

    def trace(self, phi_index: int, n_paths: int, seed) -> Tally:
        self.spec.theta_cells.upload(mi.Float)  # read in the bounce loop: uploaded before it
        rng = np.random.default_rng(seed)
        tally = Tally.zeros(self.spec, self.n_lambda)
        Rb = self.bundle.bounding_radius
        t = across_width(n_paths, Rb, rng)
        phi_i = incident_azimuths(self.spec, phi_index, n_paths, rng)   # a circle's binned relative to it
        origin, phi_t = self.geometry.entry(phi_i, t)
        hit, fiber = self.geometry.cast(origin, phi_t)
        tally.count(phi_index, n_paths, int(np.sum(~hit)))
        if self.spec.offsets:  # the near field: paths and passthrough by their entry offset
            N = self.spec.offsets
            cell = offset_cell(N, origin[:, 0], origin[:, 1], phi_t, Rb)
            tally.paths_h[phi_index] += np.bincount(cell, minlength=N)   # every theta_i alike
            tally.passthrough_h[phi_index] += np.bincount(cell[~hit], minlength=N)
        tally.vertices += n_paths
        if self.spec.estimator == "fast":
            self._trace_fast(tally, phi_index, origin[hit], phi_t[hit], fiber[hit], phi_i[hit], rng)
        else:
            # one (theta_i, lambda) per launched path, round robin from a random start;
            # weights scaled so that each combination is normalized by its own paths
            n_combo = len(self.spec.theta_i) * self.n_lambda
            combo = (rng.integers(n_combo) + np.arange(n_paths)) % n_combo
            scale = n_paths / np.maximum(np.bincount(combo, minlength=n_combo), 1)
            self._trace_thesis(tally, phi_index, phi_t[hit], fiber[hit], phi_i[hit], combo[hit], scale[combo[hit]],
                               rng)
        return tally

    # -- fast ----------------------------------------------------------------
    def _trace_fast(self, tally, phi_index, origin, phi_t, fiber, phi_i, rng):
        spec, theta_nodes = self.spec, self.spec.theta_i
        n_ti = len(theta_nodes)
        n = len(phi_t)

        # Phase 1: the first bounce, from the mixture over every incident theta_i
        twin = self._drjit_fiber()
        j = rng.integers(n_ti, size=n)
        u = rng.uniform(size=(5, n))
        lobe_state = ()
        h1 = None if spec.exit == "uniform" else self._offsets(origin, phi_t, fiber)
        if spec.exit == "lobe":
            # the path (lobe) and direction at the ray's own offset h; the mixture over the
            # theta_i nodes as below, each node's pdf its own lobe probabilities and azimuths
            lob = self._lobes()
            h_d = to_drjit(mi.Float, h1)
            p1_d, theta1_d, dphi1_d, _ = lob.sample(to_drjit(mi.Float, theta_nodes[j]), h_d,
                                                    [to_drjit(mi.Float, a) for a in u[:4]])
            lobe_state = (h_d, p1_d)

            def pdf_at(t):
                return lob.pdf(dr.full(mi.Float, t, n), h_d, p1_d, theta1_d, dphi1_d)
            loss = self._first_loss(h1)
        else:
            theta1_d, dphi1_d = twin.sample(to_drjit(mi.Float, theta_nodes[j]), [to_drjit(mi.Float, a) for a in u])

            def pdf_at(t):
                return twin.pdf(dr.full(mi.Float, t, n), theta1_d, dphi1_d)
            # every hit path loses 1 - albedo(theta_i) at its first fiber (expected value)
            loss = n * (1 - self.fiber.albedo(theta_nodes))
        pdf_mix_d = pdf_at(float(theta_nodes[0]))
        for t in theta_nodes[1:]:
            pdf_mix_d = pdf_mix_d + pdf_at(float(t))
        dr.eval(theta1_d, dphi1_d, pdf_mix_d, *lobe_state)  # pdf_mix_d: n_ti times the mixture pdf
        tally.absorbed[phi_index] += loss
        theta1, dphi1 = theta1_d.numpy().astype(np.float64), dphi1_d.numpy().astype(np.float64)
        phi_t_in = phi_t
        phi_t = phi_t + np.pi + dphi1
        curve_state = ()
        if spec.exit == "uniform":
            origin = self.geometry.exit_point(fiber, phi_t, rng.uniform(-1, 1, n))
        elif spec.exit == "curve":
            origin, curve_state = self._leave_curve(h1, phi_t_in, fiber, phi_t, u[4])
        else:
            p1 = lobe_state[1].numpy() if lobe_state else None
            origin = self._leave(h1, phi_t_in, fiber, phi_t, theta1, p1, u[4])

        # Phase 2: bounce in Dr.Jit until every path has escaped, been stopped, or hit the cap
        final = self._bounce_loop(origin, phi_t, theta1, phi_i, int(rng.integers(2**62)))
        tally.vertices += final["vertices"]
        status, bin_of = final["status"], final["bin"]
        escaped, capped = status == ESCAPED, status == CAPPED

        # Phase 3: finalize. W[path, theta_i, lambda] = A B is computed in Dr.Jit (one kernel
        # per chunk), for the paths in the order: escaped, capped, the rest; the sums over
        # paths are numpy (float64, in a fixed order: same seed, same table)
        # a sample whose mixture pdf rounds to zero carries no weight (never seen in tests)
        factor = dr.select(pdf_mix_d > 0, dr.cos(theta1_d) * n_ti / dr.maximum(pdf_mix_d, 1e-30), 0.0)
        B = [dr.select(to_drjit(mi.UInt32, status, np.uint32) == STOPPED, 0.0, b) for b in final["B"]]  # roulette victims
        esc = np.flatnonzero(escaped)
        order = np.concatenate([esc, np.flatnonzero(capped), np.flatnonzero(~(escaped | capped))])
        n_esc, n_cap = len(esc), int(capped.sum())
        esc_cells, esc_bins = split_bins(spec, bin_of[esc])  # the exit offset's cell rides above the bin
        esc_depth = final["depth"][esc].astype(np.int64)  # fiber events of each escaped path
        esc_once = esc_depth == 1  # no fiber after the first: singly scattered
        perm = to_drjit(mi.UInt32, order, np.uint32)
        per_path = [dr.gather(mi.Float, x, perm) for x in [theta1_d, dphi1_d, factor] + B + final["R"]]
        lobe_path = tuple(dr.gather(type(x), x, perm) for x in lobe_state)
        curve_path = tuple(dr.gather(mi.Float, to_drjit(mi.Float, x), perm) for x in curve_state)
        dr.eval(per_path, lobe_path, curve_path)  # once per path, so that the (path, theta_i) lanes below read in order
        L = self.n_lambda
        sums = np.zeros((spec.n_phi_o * spec.n_theta_o, n_ti * self.n_lambda))
        sums_sq = np.zeros_like(sums)
        chunk = self.CHUNK
        for lo in range(0, n, chunk):
            hi = min(n, lo + chunk)
            W, A_R = self._path_weights(twin, *per_path[:3], per_path[3:3 + L], per_path[3 + L:], lo, hi - lo,
                                        lobe_path, curve_path)
            tally.absorbed[phi_index] += A_R.sum(axis=0, dtype=np.float64)
            W = W.reshape(hi - lo, -1)
            k = max(0, min(hi, n_esc) - lo)  # escaped rows of this chunk
            if k:  # one-hot (bin x path) products: the fastest deterministic segmented sum here
                one_hot = sparse.csr_matrix((np.ones(k), (esc_bins[lo:lo + k], np.arange(k))),
                                            shape=(len(sums), k))
                sums += one_hot @ W[:k]
                sums_sq += one_hot @ np.square(W[:k], dtype=np.float64)
                tally.single[phi_index] += W[:k][esc_once[lo:lo + k]].sum(axis=0, dtype=np.float64).reshape(
                    n_ti, self.n_lambda)
                if tally.near is not None or tally.orders is not None:
                    # every path carries every theta_i: a row per (path, theta_i)
                    rows = (np.repeat(esc_bins[lo:lo + k], n_ti), np.tile(np.arange(n_ti), k),
                            W[:k].reshape(k * n_ti, self.n_lambda).astype(np.float64))
                    if tally.near is not None:
                        tally.add_offsets(phi_index, np.repeat(esc_cells[lo:lo + k], n_ti), *rows)
                    if tally.orders is not None:
                        tally.add_orders(phi_index, np.repeat(esc_depth[lo:lo + k], n_ti), *rows)
            c0, c1 = max(lo, n_esc) - lo, max(lo, min(hi, n_esc + n_cap)) - lo  # capped rows
            if c1 > c0:
                tally.lost[phi_index] += W[c0:c1].sum(axis=0, dtype=np.float64).reshape(n_ti, self.n_lambda)
        shape = (spec.n_phi_o, spec.n_theta_o, n_ti, self.n_lambda)
        tally.sum[phi_index] += sums.reshape(shape).transpose(2, 0, 1, 3)
        tally.sum_sq[phi_index] += sums_sq.reshape(shape).transpose(2, 0, 1, 3)

    def _path_weights(self, twin, theta1, dphi1, factor, B, R, lo, m, lobe_path=(), curve_path=()):
        """``W = A B`` and ``A R`` of paths ``lo .. lo + m`` for every theta_i: two float32
        arrays [m, n_ti, n_lambda].

        ``A[theta_i, lambda] = f(theta_i, theta_1, dphi_1) cos(theta_1) / pdf_mix`` (``factor``
        holds the last two); one lane per (path, theta_i), spectra written as packets. With
        the h-resolved exit, ``lobe_path = (h, p)`` of each path's first event and ``f`` is
        that path's lobe at that offset. With the ``curve`` exit, ``curve_path = (h_out, w)``
        of each path's first exit, its value is :meth:`_curve_value` and the difference
        from the sampled fiber's is booked as absorbed.
        """
        n_ti, L, P = len(self.spec.theta_i), self.n_lambda, twin.packet
        lane = dr.arange(mi.UInt32, m * n_ti)
        path = dr.opaque(mi.UInt32, lo) + lane // n_ti  # opaque: a literal would make a kernel per chunk
        theta_i = dr.gather(mi.Float, mi.Float(self.spec.theta_i.astype(np.float32)), lane % n_ti)
        if lobe_path:
            h, p = lobe_path
            f, _ = self._lobes().eval_spectrum(theta_i, dr.gather(mi.Float, h, path), dr.gather(type(p), p, path),
                                               dr.gather(mi.Float, theta1, path), dr.gather(mi.Float, dphi1, path))
        else:
            f = twin.eval_spectrum(theta_i, dr.gather(mi.Float, theta1, path), dr.gather(mi.Float, dphi1, path))
        fac = dr.gather(mi.Float, factor, path)
        booked = [0.0] * L
        if curve_path:
            h_out, w = (dr.gather(mi.Float, x, path) for x in curve_path)
            f_curve = self._curve_value(theta_i, dr.gather(mi.Float, theta1, path), dr.gather(mi.Float, dphi1, path),
                                        h_out, w, f)
            booked = [(a - b) * fac for a, b in zip(f, f_curve)]
            f = f_curve
        A = [v * fac for v in f]
        pad = [dr.zeros(mi.Float, m * n_ti)] * (P - L)
        out = []
        for carried, extra in ((B, [0.0] * L), (R, booked)):
            values = [a * dr.gather(mi.Float, c, path) + e for a, c, e in zip(A, carried, extra)]
            target = dr.zeros(mi.Float, m * n_ti * P)
            dr.scatter(target, twin.ArrayXf(values + pad) if P > 1 else values[0], lane)
            out.append(target)
        dr.eval(out)
        return tuple(t.numpy().reshape(m, n_ti, P)[..., :L] for t in out)

    def _bounce_loop(self, origin, phi_t, theta, phi_i, seed) -> dict:
        """Bounces 2.. of the fast estimator: one symbolic Dr.Jit loop, one megakernel.

        Each path ends ESCAPED (with its output bin), CAPPED (bounce cap) or STOPPED
        (Russian roulette). A lane that has ended is never updated again, so the loop's
        final state is the per-path result: status, bin and vertex count (numpy), the
        spectral weight ``B`` and the weight lost to absorption after the first bounce
        ``R`` (lists of Dr.Jit arrays). Random numbers come from a PCG32 stream per path and
        bounce, so results do not depend on batching or checkpoints. One kernel for all
        bounces outruns a kernel per bounce with compaction; reading the final state instead
        of scattering each path's result from inside the loop (dozens of masked scatters per
        vertex) and packet gathers of whole spectra gain more (``make bench-bake`` measures
        the vertex rate).
        """
        Float, UInt = mi.Float, mi.UInt32
        n, L = len(theta), self.n_lambda
        scene = LoopScene.upload(self.geometry, self.bundle, seed)
        paths = Paths(
            ox=to_drjit(Float, origin[:, 0]), oz=to_drjit(Float, origin[:, 1]),
            phi=to_drjit(Float, np.mod(phi_t, 2 * np.pi)), theta=to_drjit(Float, theta),
            B=[dr.full(Float, 1.0, n) for _ in range(L)], R=[dr.zeros(Float, n) for _ in range(L)],
            depth=dr.full(UInt, 1, n), status=dr.zeros(UInt, n), bin=dr.zeros(UInt, n),
            active=dr.full(mi.Bool, True, n), pid=dr.arange(UInt, n),
            phi_i=to_drjit(Float, phi_i) if np.ndim(phi_i) else Float(np.asarray(phi_i, np.float32)),
            steps=dr.zeros(UInt, n))

        out = in_rounds(paths, lambda p, limit: self._bounce_round(p, scene, limit), self.ROUND,
                        self.spec.max_bounces + 2, self.TAIL_LANES)
        out["vertices"] = int(out["depth"].astype(np.int64).sum())
        return out

    @dr.syntax
    def _bounce_round(self, paths: "Paths", scene: "LoopScene", limit) -> "Paths":
        """Bounce every active path until it ends or has made ``limit`` bounces this round."""

        while dr.hint(paths.active & (paths.steps < limit), label="bake_bounces"):
            paths = self._bounce(paths, scene)
        return paths

    def _bounce(self, paths: "Paths", scene: "LoopScene") -> "Paths":
        """One bounce of every active path: ray cast, tally or scatter, roulette, exit point."""
        spec = self.spec
        exit_model = spec.exit
        Float, UInt = mi.Float, mi.UInt32
        p = paths
        p.steps = p.steps + 1

        # Phase 1: the ray from the path's exit point; an escaping ray is tallied in its bin
        sp, cp = dr.sincos(p.phi)
        ray = mi.Ray3f(mi.Point3f(p.ox, 0.0, p.oz), mi.Vector3f(cp, 0.0, sp))
        hit_info = scene.scene.ray_intersect_preliminary(ray, coherent=False, active=p.active)
        hit = p.active & hit_info.is_valid()
        escaped = p.active & ~hit
        p.status = dr.select(escaped, ESCAPED, p.status)
        p.bin = dr.select(escaped, self._bin(p.phi, p.theta, p.phi_i, dr, (p.ox, p.oz)), p.bin)
        capped = hit & (p.depth >= spec.max_bounces)
        p.status = dr.select(capped, CAPPED, p.status)
        go = hit & ~capped
        p.depth = dr.select(go, p.depth + 1, p.depth)

        # Phase 2: sample the fiber at the path's longitude (and offset, for the lobe exit)
        rng = mi.PCG32()
        rng.seed(scene.seed + mi.UInt64(p.depth), mi.UInt64(p.pid))
        u = [rng.next_float32() for _ in range(5)]
        x6, x7 = rng.next_float32(), rng.next_float32()
        theta_in = -p.theta
        if exit_model != "uniform":  # the event's geometry: the fiber hit and the ray's offset
            k = dr.gather(UInt, scene.shape_to_fiber, hit_info.shape_index, go)
            cx, cz = dr.gather(Float, scene.centers_x, k, go), dr.gather(Float, scene.centers_z, k, go)
            r = dr.gather(Float, scene.radii, k, go)
            h_in = lobes.entry_offset(cx, cz, r, p.ox, p.oz, cp, sp, dr)
        if exit_model == "lobe":
            lob = self._lobes()
            path, theta_out, dphi, pdf = lob.sample(theta_in, h_in, u[:4])
            f, alb = lob.eval_spectrum(theta_in, h_in, path, theta_out, dphi)
        else:
            theta_out, dphi, pdf, f, alb = self._drjit_fiber().event(theta_in, u)

        phi_n = p.phi + np.pi + dphi
        phi_n = phi_n - 2 * np.pi * dr.floor(phi_n * (1 / (2 * np.pi)))
        s_o, c_o = dr.sincos(phi_n)
        if exit_model == "curve":  # the curve's value; its difference from f is booked as absorbed
            nx, nz, h_out, w = lobes.curve_exit(h_in, cp, sp, c_o, s_o, x7, dr)
            f, alb = self._curve_event(theta_in, theta_out, dphi, h_out, w, f, alb)

        # Phase 3: the weight (B carries f cos / pdf, R the expected absorption) and roulette
        p.B, p.R, kept, roulette = weights.scatter(p.B, p.R, f, alb, theta_out, pdf, go, p.depth, spec.rr_start, x6)
        p.status = dr.select(go & ~kept, STOPPED, p.status)
        alive = go & kept
        h_u = dr.select(roulette, x7, x6)

        # Phase 4: where the scattered light leaves the fiber (the exit model)
        if exit_model == "uniform":  # anywhere on the outgoing side, h uniform
            k = dr.gather(UInt, scene.shape_to_fiber, hit_info.shape_index, alive)
            cx, cz = dr.gather(Float, scene.centers_x, k, alive), dr.gather(Float, scene.centers_z, k, alive)
            new_x, new_z = lobes.leave_uniform(cx, cz, dr.gather(Float, scene.radii, k, alive), 2 * h_u - 1,
                                               c_o, s_o, dr)
        elif exit_model == "curve":  # the end of the light's chord chosen above
            new_x, new_z = cx + r * (1 + 1e-4) * nx, cz + r * (1 + 1e-4) * nz
        else:  # where the light entered, or where its path leaves
            nx, nz = lobes.entry_normal(h_in, cp, sp, dr)
            if exit_model == "lobe":
                nx, nz = lob.exit_normal(nx, nz, path, h_in, theta_in, dr)
            new_x, new_z = lobes.leave(cx, cz, r, nx, nz, c_o, s_o, dr)
            if exit_model == "lobe":  # the residual has no single exit: the uniform one
                res_x, res_z = lobes.leave_uniform(cx, cz, r, 2 * h_u - 1, c_o, s_o, dr)
                residual = path == lob.p_max
                new_x, new_z = dr.select(residual, res_x, new_x), dr.select(residual, res_z, new_z)
        p.ox = dr.select(alive, new_x, p.ox)
        p.oz = dr.select(alive, new_z, p.oz)
        p.phi = dr.select(alive, phi_n, p.phi)
        p.theta = dr.select(alive, theta_out, p.theta)
        p.active = alive
        return p

    def _lobes(self):
        """The h-resolved ray fiber (exit ``lobe``), built from the fiber table's parameters."""
        if getattr(self, "_lobe_sampler", None) is None:
            self._lobe_sampler = lobes.LobeSampler(self.fiber.meta, self.fiber.wavelength, mi.Float)
        return self._lobe_sampler

    def _offsets(self, origin, phi_t, fiber):
        """``h`` of the rays ``origin`` along ``phi_t`` at the fibers they hit (numpy)."""
        c, r = self.bundle.centers[fiber], self.bundle.radii[fiber]
        return lobes.entry_offset(c[:, 0], c[:, 1], r, origin[:, 0], origin[:, 1], np.cos(phi_t), np.sin(phi_t), np)

    def _first_loss(self, h):
        """Expected absorption ``sum over paths of 1 - sum_p A_p(h)`` at the first event, [n_ti, lambda]."""
        lob = self._lobes()
        eta, sigma_a = np.asarray(lob.eta), np.asarray(lob.sigma_a)
        loss = np.zeros((len(self.spec.theta_i), len(eta)))
        for i, t in enumerate(self.spec.theta_i):
            cos_t = max(np.cos(t), lobes.COS_GRAZING)
            A = lobes.attenuation(cos_t, eta[None, :], h[:, None], sigma_a[None, :], lob.p_max, np)
            loss[i] = np.sum(1 - sum(A[1:], A[0]), axis=0)
        return loss

    def _leave(self, h, phi_in, fiber, phi_out, theta_out, p, h_u):
        """Start points of the rays leaving the first fibers, entered at offsets ``h``
        (exits ``entry`` and ``lobe``).

        ``entry``: where the light entered; ``lobe``: where the sampled path ``p`` leaves,
        with Bravais' index at the outgoing longitude (the same exit for every theta_i node
        the path carries; exactly the incident one for smooth fibers), the residual
        uniformly over the outgoing side as the ``uniform`` exit.
        """
        c, r = self.bundle.centers[fiber], self.bundle.radii[fiber]
        nx, nz = lobes.entry_normal(h, np.cos(phi_in), np.sin(phi_in), np)
        dx, dz = np.cos(phi_out), np.sin(phi_out)
        if self.spec.exit == "lobe":
            lob = self._lobes()
            nx, nz = lob.exit_normal(nx, nz, p, h, theta_out, np)
        out = np.stack(lobes.leave(c[:, 0], c[:, 1], r, nx, nz, dx, dz, np), -1)
        if self.spec.exit == "lobe":
            residual = p == self._lobes().p_max
            out[residual] = self.geometry.exit_point(fiber[residual], phi_out[residual], 2 * h_u[residual] - 1)
        return out

    def _leave_curve(self, h, phi_in, fiber, phi_out, u):
        """Start points of the rays leaving the first fibers as from Mitsuba's curves (the
        ``curve`` exit; numpy, as :meth:`_bounce` in Dr.Jit) and ``(h_out, w)`` per path."""
        c, r = self.bundle.centers[fiber], self.bundle.radii[fiber]
        nx, nz, h_out, w = lobes.curve_exit(h, np.cos(phi_in), np.sin(phi_in), np.cos(phi_out), np.sin(phi_out),
                                            u, np)
        return np.stack([c[:, 0] + r * (1 + 1e-4) * nx, c[:, 1] + r * (1 + 1e-4) * nz], -1), (h_out, w)

    def _curve_value(self, theta_in, theta_out, dphi, h_out, w, f):
        """The ``curve`` exit's value at every wavelength: ``w`` times the adjoint at the
        outgoing ray's offset for a ray fiber of camera transport, ``w f`` otherwise."""
        return weights.curve_value(self._curve_lobes(), theta_in, theta_out, dphi, h_out, w, f)

    def _curve_event(self, theta_in, theta_out, dphi, h_out, w, f, alb):
        """``(f, albedo)`` of an event with the ``curve`` exit: its value, and the sampled
        fiber's albedo scaled alike (so that ``R`` books the difference as absorbed)."""
        return weights.curve_event(self._curve_lobes(), theta_in, theta_out, dphi, h_out, w, f, alb)

    def _curve_lobes(self):
        if self.fiber.meta.get("model") == "ray" and self.fiber.meta.get("transport") == "camera":
            return self._lobes()
        return None

    def _drjit_fiber(self):
        if getattr(self, "_dj_fiber", None) is None:
            self._dj_fiber = DrJitFiber(self.fiber, self.sampler, mi.Float)
        return self._dj_fiber

    # -- thesis ----------------------------------------------------------------
    def _trace_thesis(self, tally, phi_index, phi_t, fiber, phi_i, combo, w, rng):
        spec = self.spec
        n_ti, n_l = len(spec.theta_i), self.n_lambda
        n = len(phi_t)
        j, lam = np.divmod(combo, n_l)
        theta_in = spec.theta_i[j]  # longitude of w_i at the first fiber
        alive = np.arange(n)
        depth = 0
        esc_idx, esc_bin, esc_w = [], [], []
        while True:
            # scatter at the current fiber: uniform in (theta_out, dphi), pdf 1 / (2 pi^2)
            depth += 1
            m = len(alive)
            theta_out = rng.uniform(-np.pi / 2, np.pi / 2, m)
            dphi = rng.uniform(-np.pi, np.pi, m)
            f = self.fiber.eval_spectrum(theta_in, theta_out, dphi, lambda_index=lam[alive])
            alb = self.fiber.albedo(theta_in)[np.arange(m), lam[alive]]
            np.add.at(tally.absorbed[phi_index], (j[alive], lam[alive]), w * (1 - alb))
            w = w * f * np.cos(theta_out) * 2 * np.pi**2
            phi_t = phi_t + np.pi + dphi
            origin = self.geometry.exit_point(fiber, phi_t, rng.uniform(-1, 1, m))
            hit, fiber = self.geometry.cast(origin, phi_t)
            tally.vertices += m
            esc_idx.append(alive[~hit])
            esc_bin.append(self._bin(phi_t[~hit], theta_out[~hit], phi_i[~hit]))
            esc_w.append(w[~hit])
            alive, w, phi_t, fiber, theta_out = alive[hit], w[hit], phi_t[hit], fiber[hit], theta_out[hit]
            phi_i = phi_i[hit]
            theta_in = -theta_out
            if len(alive) == 0:
                break
            if depth >= spec.max_bounces:
                np.add.at(tally.lost[phi_index], (j[alive], lam[alive]), w)
                break
        np.add.at(tally.single[phi_index], (j[esc_idx[0]], lam[esc_idx[0]]), esc_w[0])  # left the first fiber
        idx, bins, ws = (np.concatenate(a) for a in (esc_idx, esc_bin, esc_w))
        n_bins = spec.n_phi_o * spec.n_theta_o
        flat = (j[idx] * n_bins + bins) * n_l + lam[idx]
        size = n_ti * n_bins * n_l
        shape = (n_ti, spec.n_phi_o, spec.n_theta_o, n_l)
        tally.sum[phi_index] += np.bincount(flat, ws, size).reshape(shape)
        tally.sum_sq[phi_index] += np.bincount(flat, ws**2, size).reshape(shape)
