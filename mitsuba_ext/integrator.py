"""The ``bundle_path`` integrator: Mitsuba's ``path`` plus what fiber bundles need.

Mitsuba's Python plugins derive from the active variant's classes, so this module is
imported once a variant is chosen: :func:`mitsuba_ext.register` imports it (and reloads
it after a variant switch). Its ``@dr.syntax`` methods are recompiled from their source
and see this module's globals. The geometry it uses is in ``mitsuba_ext.crossing``.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mitsuba_ext.crossing import (bundle_axis, check_bundles, displaced_exit, far_side, mis_weight, offset_ray,
                                  tracing)
from mitsuba_ext.frame import LinearCurves
from mitsuba_ext.params import boolean, choice, integer, jit_variant_only, number

if mi.variant() is None:
    raise ImportError("mitsuba_ext.integrator: choose a Mitsuba variant first (mi.set_variant), then "
                      "mitsuba_ext.register()")
VARIANT = mi.variant()  # the variant this class derives from


def exit_probability(q, throughput):
    """The chance that a bundle vertex's light leaves from where it entered, given the
    share ``q`` of singly scattered light per wavelength: ``q`` averaged over the path's
    wavelengths weighted by the throughput each carries, so that the wavelengths that
    carry the path keep weights ``q / P`` and ``(1 - q) / (1 - P)`` near 1 (in a dyed
    yarn the red runs long and the blue dies out: an unweighted mean would give the red
    0.4 or 1.6 at every vertex). Never 0 or 1: each exit keeps its chance."""
    total = dr.sum(throughput)
    mean = dr.select(total > 0, dr.sum(throughput * q) / dr.maximum(total, 1e-30), dr.mean(q))
    return dr.clip(mean, 0.02, 0.98)


class BundlePathIntegrator(mi.SamplingIntegrator):
    r"""Bundle path tracer (``bundle_path``)
    -------------------------------------

    Mitsuba's ``path`` integrator (next-event estimation, multiple importance
    sampling, Russian roulette) with the two special cases of ``fiber_bundle``
    surfaces (any BSDF with a ``passthrough`` attribute):

    * **passthrough**: the BSDF's null lobe continues the ray in the same direction;
      the far wall of the bundle is crossed as a null interface. Passthrough events
      do not count as bounces and leave the MIS state of the last real vertex alone.
      Shadow rays cross bundles with transmittance ``P_pass`` (``path`` would treat
      them as opaque and find those paths by BSDF sampling only), with Russian
      roulette once the product falls below ``shadow_rr``.
    * **displaced exit**: scattered light, and the shadow ray of next-event
      estimation, leave from :func:`displaced_exit`, with ``h`` uniform in [-1, 1].
      The radius comes from the shape (``|dp/du| = 2 pi r`` per hit on
      ``cylinder`` and ``bsplinecurve``), else the BSDF's ``radius``, else a probe
      ray across the shape.
    * **light that scattered once leaves where it entered** (``exit_split``, off by
      default here; the cloth stage's scenes use ``"all"``): where the BSDF has a
      ``single_share`` (``fiber_bundle`` from a bake that records it: the share ``q``
      of the scattered light, per wavelength, that left the ply after one fiber
      event), each bundle vertex leaves from its hit point with probability ``P``,
      the mean of ``q`` over the path's wavelengths weighted by their throughput
      (:func:`exit_probability`), else from the displaced exit, each wavelength
      weighted by ``q / P`` or ``(1 - q) / (1 - P)`` (unbiased for either part): for
      the emitter sample's shadow ray only (``"emitter"``) or for the path's next ray
      too (``"all"``: the exit model of both sampling strategies, so that MIS weighs
      two estimates of one integral). In a dyed yarn most blue light that leaves a
      ply leaves after one fiber, near where it entered: the split moves a knitted
      patch's colour towards explicit fibers, about half as far with ``"emitter"`` as
      with ``"all"``, for a little more variance (the figures: docs/BENCHMARKS.md,
      "Cloth").

    On scenes without bundles it is ``path``, sample for sample.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Default
         - Unit
         - Description
       * - max_depth
         - integer
         - -1
         - bounces
         - Longest path (passthrough events excluded); -1: no limit. A bundle hit is
           one bounce for a whole ply; explicit fibers count one per fiber, and light
           in a dyed ply meets dozens: compare explicit fibers at 64 or more.
       * - rr_depth
         - integer
         - 5
         - bounces
         - Depth at which Russian roulette starts.
       * - displaced_exit
         - boolean
         - ``true``
         - 
         - Leave bundles from the displaced exit point.
       * - exit_split
         - string
         - ``none``
         - 
         - Send the ``single_share`` of a bundle's light from where it entered:
           ``none``, ``emitter`` (the shadow rays of next-event estimation) or ``all``
           (the path's next rays too). Without a share, or with ``displaced_exit`` off,
           it does nothing.
       * - max_passes
         - integer
         - 64
         - crossings
         - Most bundle crossings of one path or shadow ray.
       * - shadow_rr
         - float
         - 0.1
         - transmittance
         - Below it each further crossing of a shadow ray is survived with
           probability ``T / shadow_rr`` (Russian roulette, unbiased); 0 traces every
           crossing.
       * - overlaps
         - boolean
         - ``false``
         - 
         - Light that leaves a bundle inside another (interpenetrating yarns) enters
           that other one at the near wall of its chord, for paths and shadow rays
           alike (up to two probe rays per ray that leaves a bundle); ``false``: such
           light crosses the other bundle unseen (a curve reports no hit from inside).

    Not supported: ``hide_emitters`` (refused at load). Bundles belong on
    ``cylinder`` and ``bsplinecurve`` shapes; the first render of a scene warns
    once about a bundle BSDF on any other shape, or a BSDF ``radius`` that
    disagrees with its shape's (:func:`check_bundles`).

    .. code-block:: python

        mi.set_variant("llvm_ad_rgb"); mitsuba_ext.register()
        scene = mi.load_dict({..., "integrator": {"type": "bundle_path", "max_depth": 32}})

    .. code-block:: xml

        <integrator type="bundle_path">
            <integer name="max_depth" value="32"/>
            <string name="exit_split" value="emitter"/>
        </integrator>
    """

    def __init__(self, props):
        jit_variant_only("bundle_path")
        super().__init__(props)
        max_depth = integer("bundle_path", "max_depth", props.get("max_depth", -1), lo=-1)  # -1: no limit
        self.max_depth = 0xFFFFFFFF if max_depth == -1 else max_depth
        self.rr_depth = integer("bundle_path", "rr_depth", props.get("rr_depth", 5), lo=1)
        self.displace = boolean("bundle_path", "displaced_exit", props.get("displaced_exit", True))
        self.split = choice("bundle_path", "exit_split", props.get("exit_split", "none"), ("none", "emitter", "all"))
        self.max_passes = integer("bundle_path", "max_passes", props.get("max_passes", 64), lo=1)
        self.shadow_rr = number("bundle_path", "shadow_rr", props.get("shadow_rr", 0.1), 0.0, 1.0)
        self.overlaps = boolean("bundle_path", "overlaps", props.get("overlaps", False))
        if boolean("bundle_path", "hide_emitters", props.get("hide_emitters", False)):
            raise ValueError("bundle_path: hide_emitters is not supported (directly visible emitters are "
                             "always shown); leave it out")
        self._checked = {}
        self._paths = 0

    def _check(self, scene):
        """Warn once per scene about bundles on shapes they are not defined on; count the
        paths of the scene's h-resolved fibers (``fiber_ray``: the paths an emitter sample chooses among)."""
        if id(scene) not in self._checked:
            for line in check_bundles(scene):
                mi.Log(mi.LogLevel.Warn, "bundle_path: " + line)
            self._checked[id(scene)] = (max([int(getattr(s.bsdf(), "n_paths", 0)) for s in scene.shapes()] + [0]),
                                        LinearCurves(scene.shapes()))
        self._paths, self._linear = self._checked[id(scene)]

    # -- h-resolved fibers: each path leaves from its own exit point --------------
    def _path_exit(self, si, bsdf, radius, p, w, active):
        """Start and outward normal of light leaving along ``w`` on path ``p`` (a Python
        int) of an h-resolved fiber, and whether the path has a single exit (not the
        residual). A direction into the fiber crosses it to the chord's far end."""
        n = mi.Vector3f(bsdf.eval_attribute_3(f"exit_{p}", si, active))
        ok = active & (dr.squared_norm(n) > 0.25)
        t, n_perp, _ = bundle_axis(si)
        w_perp = dr.normalize(w - dr.dot(w, t) * t)
        nd = dr.dot(n, w_perp)
        n = dr.select(nd < 0, n - 2 * nd * w_perp, n)
        return si.p - radius * n_perp + radius * n, n, ok

    def _sampled_exit(self, si, bsdf, radius, path, w, active):
        """:meth:`_path_exit` of the sampled path (``bs.sampled_component`` per lane)."""
        p_out, n_out, ok = si.p, si.n, mi.Bool(False)
        for p in range(self._paths - 1):  # the last index is at most a residual
            mine = active & (path == p)
            q, n, good = self._path_exit(si, bsdf, radius, p, w, mine)
            p_out, n_out, ok = dr.select(mine, q, p_out), dr.select(mine, n, n_out), ok | (mine & good)
        return p_out, n_out, ok

    def _emitter_paths(self, scene, sampler, si, bsdf, ds, radius, h, active):
        """The emitter sample's contribution through an h-resolved fiber: each path leaves
        from its own exit, with its own MIS weight. One path is chosen, in proportion to
        its term ``f_p mis_p`` (summed over the spectrum), and its shadow ray traced; its
        term divided by the probability of the choice is an unbiased estimate of the sum
        over paths, at one shadow ray instead of one per path."""
        wo = si.to_local(ds.d)

        # the paths' terms and the choice (u against their running sum)
        terms, sums = [], []
        for p in range(self._paths):
            ctx = mi.BSDFContext()
            ctx.component = p
            f = bsdf.eval(ctx, si, wo, active)
            mis = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf.pdf(ctx, si, wo, active)))
            terms.append(f * mis)
            sums.append(dr.sum(mi.unpolarized_spectrum(terms[-1])))
        total = mi.Float(0.0)
        for w in sums:
            total += w
        u = sampler.next_1d(active) * total
        term, weight = dr.zeros(mi.Spectrum), mi.Float(0.0)
        p_res, r_res = displaced_exit(si, radius, h, ds.d)  # where the residual leaves
        p_exit, radial, picked, acc = p_res, r_res, mi.Bool(False), mi.Float(0.0)
        for p, (t, w) in enumerate(zip(terms, sums)):
            acc += w
            pick = active & ~picked & (w > 0) & (u < acc)
            q, n, ok = self._path_exit(si, bsdf, radius, p, ds.d, pick)
            p_exit, radial = dr.select(pick & ok, q, p_exit), dr.select(pick & ok, n, radial)
            term, weight = dr.select(pick, t, term), dr.select(pick, w, weight)
            picked |= pick

        # its shadow ray
        dist = dr.select(ds.delta & (ds.dist == dr.inf), dr.inf, dr.norm(ds.p - p_exit))
        d_exit = dr.select(dr.isinf(dist), ds.d, dr.normalize(ds.p - p_exit))
        shadow = offset_ray(p_exit, radial, d_exit, si.wavelengths, dist * (1.0 - mi.math.ShadowEpsilon))
        T = self._transmittance(scene, sampler, self._backed(scene, shadow, radius, picked), picked)
        return dr.select(picked, term * T * (total / weight), 0.0)

    # -- helpers ----------------------------------------------------------
    # what the BSDFs read (UV for the twist, the shading frame for the tangent); the
    # normal derivatives of RayFlags.All read past the last bsplinecurve segment
    RAY_FLAGS = mi.RayFlags.UV | mi.RayFlags.dPdUV | mi.RayFlags.ShadingFrame

    def _radius(self, scene, si, bsdf, active):
        """Bundle radius at a hit, from the shape where Mitsuba's parametrization holds it.

        On ``cylinder`` and ``bsplinecurve`` the first surface derivative runs around
        the circumference, ``|dp/du| = 2 pi r`` (exact, per hit, also for a curve whose
        radius varies). Elsewhere: the BSDF's ``radius``, else a probe ray across the
        shape (a probe spawned a float epsilon inside a thin cylinder can hit its entry
        wall again, which is why it is the last resort).
        """
        shape_type = si.shape.shape_type()
        curve = ((shape_type == int(mi.ShapeType.Cylinder)) | (shape_type == int(mi.ShapeType.BSplineCurve))
                 | (shape_type == int(mi.ShapeType.LinearCurve)))  # its dp_du set by LinearCurves.fix
        r_shape = dr.norm(si.dp_du) * (0.5 / dr.pi)
        r = dr.select(curve & dr.isfinite(r_shape), r_shape, bsdf.eval_attribute_1("radius", si, active))
        need = active & (r <= 0)
        _, n_perp, _ = bundle_axis(si)
        probe = offset_ray(si.p, -n_perp, -n_perp, si.wavelengths)
        si_far = scene.ray_intersect(probe, need)
        measured = dr.select(need & si_far.is_valid() & (si_far.shape == si.shape), 0.5 * si_far.t, 0.0)
        return dr.select(need, measured, r)

    def _backed(self, scene, ray, r, active):
        """``ray`` (leaving a bundle of radius ``r``), or, where its origin lies inside
        another bundle, the same ray moved back to a hair before that bundle's near wall.

        Yarns interpenetrate; light that leaves one ply inside another must meet the other
        (its fibers are there), but a ray that starts inside a curve never hits it. Up to
        two probes along ``ray.d`` from ``2 r`` behind the origin find a bundle entered
        before the origin whose chord reaches past it (the first probe often meets the
        bundle being left, whose chord ends at the origin). Bundles larger than ``2 r``
        across, entered further back, are not found."""
        if not self.overlaps:
            return ray
        d = ray.d
        o, left = ray.o - 2.0 * r * d, 2.0 * r
        pending = mi.Bool(active) & (r > 0)
        found, p_in, n_in = mi.Bool(False), ray.o, mi.Vector3f(0.0)
        for _ in range(2):
            probe = offset_ray(o, d, d, ray.wavelengths, left)
            si = scene.ray_intersect(probe, ray_flags=self.RAY_FLAGS, coherent=False, active=pending)
            hit = pending & si.is_valid()
            bsdf = si.bsdf()
            front = hit & (mi.Frame3f.cos_theta(si.wi) > 0) & bsdf.has_attribute("passthrough", hit)
            r_b = self._radius(scene, si, bsdf, front)
            p_far, _, ok = far_side(si, r_b, d)
            inside = front & ok & (dr.dot(p_far - ray.o, d) > 0.01 * r_b)
            found |= inside
            p_in, n_in = dr.select(inside, si.p, p_in), dr.select(inside, si.n, n_in)
            # not this one (the bundle being left, or anything else): on past it
            o_next = dr.select(front & ok, p_far, si.p)
            left = left - dr.dot(o_next - o, d)
            o = o_next
            pending = hit & ~inside & (left > 0.01 * r)
        # from a hair before the near wall (outside it: the next cast meets the wall from outside)
        moved = offset_ray(p_in - 1e-3 * r * d, n_in, d, ray.wavelengths)
        moved.maxt = ray.maxt + dr.norm(ray.o - moved.o)
        return dr.select(found, moved, ray)

    @dr.syntax
    def _transmittance(self, scene, sampler, ray, active):
        """Fraction of light crossing ``ray``: product of ``P_pass`` of the bundles on it.

        Once the product falls below ``shadow_rr``, each further crossing is survived with
        probability ``T / shadow_rr`` at ``T = shadow_rr`` (Russian roulette: unbiased). A
        shadow ray through a knitted garment crosses dozens of plies, and without it the
        loop runs to ``max_passes`` for light that has long been negligible."""
        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        T = dr.select(active, mi.Float(1.0), 0.0)
        steps = mi.UInt32(0)

        while dr.hint(active, label="bundle_shadow"):
            si = scene.ray_intersect(ray, ray_flags=self.RAY_FLAGS, coherent=False, active=active)
            hit = active & si.is_valid()
            bsdf = si.bsdf()
            bundle = hit & bsdf.has_attribute("passthrough", hit)
            P = bsdf.eval_attribute_1("passthrough", si, bundle)
            T = dr.select(hit, dr.select(bundle, T * P, 0.0), T)
            if dr.hint(self.shadow_rr > 0, mode="scalar"):
                roulette = bundle & (T < self.shadow_rr)
                survive = sampler.next_1d(roulette) * self.shadow_rr < T
                T = dr.select(roulette, dr.select(survive, self.shadow_rr, 0.0), T)
            steps += 1
            active = bundle & (T > 0) & (steps < self.max_passes)
            nxt = si.spawn_ray(ray.d)
            nxt.maxt = ray.maxt - si.t
            # from outside: continue beyond the bundle's far wall
            front = active & (mi.Frame3f.cos_theta(si.wi) > 0)
            r = self._radius(scene, si, bsdf, front)
            p_far, radial, ok = far_side(si, r, ray.d)
            crossed = offset_ray(p_far, radial, ray.d, si.wavelengths, ray.maxt - si.t - dr.norm(p_far - si.p))
            # its far side may lie inside an overlapping bundle: that one is crossed too
            crossed = self._backed(scene, crossed, r, front & ok)
            nxt = dr.select(front & ok, crossed, nxt)
            ray = dr.select(active, nxt, ray)
        return T

    # -- the integrator ---------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        with tracing("bundle_path"):  # the bundles it meets know who traces them
            return self._sample(scene, sampler, ray, medium, active)

    @dr.syntax
    def _sample(self, scene, sampler, ray, medium=None, active=True):
        self._check(scene)  # Python, once per render call: the body below is traced
        ctx = mi.BSDFContext()

        # ---------------------- loop state ----------------------
        ray = mi.Ray3f(ray)
        throughput = mi.Spectrum(1.0)
        result = mi.Spectrum(0.0)
        eta = mi.Float(1.0)
        depth = mi.UInt32(0)
        passes = mi.UInt32(0)
        valid_ray = mi.Bool(scene.environment() is not None)
        prev_si = dr.zeros(mi.Interaction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        active = mi.Bool(active)

        while dr.hint(active, label="bundle_path"):
            si = scene.ray_intersect(ray, ray_flags=self.RAY_FLAGS, coherent=(depth == 0), active=active)
            if dr.hint(bool(self._linear), mode="scalar"):  # fibers on linearcurve: their tangent frame
                si = self._linear.fix(si, ray.d)

            # ------------------ direct emission ------------------
            ds = mi.DirectionSample3f(scene, si, prev_si)
            em_pdf = scene.pdf_emitter_direction(prev_si, ds, active & ~prev_bsdf_delta)
            em_pdf = dr.select(prev_bsdf_delta, 0.0, em_pdf)
            mis_bsdf = mis_weight(prev_bsdf_pdf, em_pdf)
            emitted = ds.emitter.eval(si, active & (prev_bsdf_pdf > 0))
            result = dr.select(active, dr.fma(throughput, emitted * mis_bsdf, result), result)

            active_next = active & (depth + 1 < self.max_depth) & si.is_valid()
            bsdf = si.bsdf(ray)

            # ------------- bundle hit: exit offset and radius -------------
            bundle = active_next & bsdf.has_attribute("passthrough", active_next)
            radius = self._radius(scene, si, bsdf, bundle)
            h = mi.Float(0.0)
            if dr.hint(self.displace, mode="scalar"):
                h = 2.0 * sampler.next_1d(bundle) - 1.0

            # --- light that scattered once: from the hit, the rest from the displaced exit ---
            from_hit = mi.Bool(False)
            w_exit = mi.UnpolarizedSpectrum(1.0)
            if dr.hint(self.displace & (self.split != "none"), mode="scalar"):
                split = (bundle & (radius > 0) & bsdf.has_attribute("single_share", bundle)
                         & ~bsdf.has_attribute("paths", bundle))
                q = dr.clip(bsdf.eval_attribute("single_share", si, split), 0.0, 1.0)
                P = exit_probability(q, mi.unpolarized_spectrum(throughput))
                from_hit = split & (sampler.next_1d(split) < P)
                w_exit = dr.select(split, dr.select(from_hit, q / P, (1.0 - q) / (1.0 - P)), 1.0)
            # the path's next ray follows the choice only for "all": its weights multiply along the path
            from_hit_next = from_hit if self.split == "all" else mi.Bool(False)
            w_next = w_exit if self.split == "all" else mi.UnpolarizedSpectrum(1.0)

            # ------------------ emitter sampling ------------------
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(active_em), False, active_em)
            active_em &= ds.pdf != 0.0
            # h-resolved fibers trace their own shadow ray, from the chosen path's exit
            lobed = mi.Bool(False)
            if dr.hint((self._paths > 0) & self.displace, mode="scalar"):
                lobed = active_em & bsdf.has_attribute("paths", active_em) & (radius > 0)
            shadowed = active_em & ~lobed
            shadow = si.spawn_ray_to(ds.p)
            if dr.hint(self.displace, mode="scalar"):
                p_exit, radial = displaced_exit(si, radius, h, ds.d)
                dist = dr.select(ds.delta & (ds.dist == dr.inf), dr.inf, dr.norm(ds.p - p_exit))
                d_exit = dr.select(dr.isinf(dist), ds.d, dr.normalize(ds.p - p_exit))
                moved = offset_ray(p_exit, radial, d_exit, si.wavelengths, dist * (1.0 - mi.math.ShadowEpsilon))
                displaced = bundle & (radius > 0) & ~from_hit
                shadow = dr.select(displaced, self._backed(scene, moved, radius, displaced & shadowed), shadow)
            T = self._transmittance(scene, sampler, shadow, shadowed)
            wo = si.to_local(ds.d)

            # ------------- BSDF evaluation and sampling -------------
            sample_1 = sampler.next_1d(active_next)
            sample_2 = sampler.next_2d(active_next)
            bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(ctx, si, wo, sample_1, sample_2, active_next)
            mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
            nee = bsdf_val * T * mis_em * w_exit
            if dr.hint((self._paths > 0) & self.displace, mode="scalar"):  # h-resolved fibers in the scene
                nee = dr.select(lobed, self._emitter_paths(scene, sampler, si, bsdf, ds, radius, h, lobed), nee)
            result = dr.select(active_em, dr.fma(throughput, nee * em_weight, result), result)

            # ------------------ the next ray ------------------
            passed = active_next & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            wo_world = si.to_world(bs.wo)
            next_ray = si.spawn_ray(wo_world)
            # passing from outside: the whole crossing is one null event
            p_far, radial, ok = far_side(si, radius, wo_world)
            crossed = offset_ray(p_far, radial, wo_world, si.wavelengths)
            next_ray = dr.select(passed & ok & (mi.Frame3f.cos_theta(si.wi) > 0), crossed, next_ray)
            if dr.hint(self.displace, mode="scalar"):
                p_exit, radial = displaced_exit(si, radius, h, wo_world)
                moved = offset_ray(p_exit, radial, wo_world, si.wavelengths)
                next_ray = dr.select(bundle & ~passed & (radius > 0) & ~from_hit_next, moved, next_ray)
            if dr.hint((self._paths > 0) & self.displace, mode="scalar"):
                lobed_next = bundle & ~passed & (radius > 0) & bsdf.has_attribute("paths", bundle)
                p_path, n_path, single = self._sampled_exit(si, bsdf, radius, bs.sampled_component, wo_world,
                                                            lobed_next)
                next_ray = dr.select(single, offset_ray(p_path, n_path, wo_world, si.wavelengths), next_ray)
            # leaving (or crossing) a bundle inside another one: into that one
            next_ray = self._backed(scene, next_ray, radius, active_next & bundle)
            ray = dr.select(active_next, next_ray, ray)

            throughput = dr.select(active_next, throughput * bsdf_weight * dr.select(passed, 1.0, w_next), throughput)
            eta = dr.select(active_next, eta * bs.eta, eta)
            # Mitsuba's rule (a hit on a non-null BSDF), plus a bundle seen from outside: it
            # scatters even when this sample passes through (its emitter sample counts)
            front_of_bundle = bsdf.has_attribute("passthrough", active) & (mi.Frame3f.cos_theta(si.wi) > 0)
            valid_ray |= active & si.is_valid() & (~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null)
                                                   | front_of_bundle)

            # passthrough keeps the last real vertex for MIS
            real = active_next & ~passed
            prev_si = dr.select(real, mi.Interaction3f(si), prev_si)
            prev_bsdf_pdf = dr.select(real, bs.pdf, prev_bsdf_pdf)
            prev_bsdf_delta = dr.select(real, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                                        prev_bsdf_delta)
            depth = dr.select(real, depth + 1, depth)
            passes = dr.select(passed, passes + 1, passes)

            # ------------------ stopping criterion ------------------
            throughput_max = dr.max(mi.unpolarized_spectrum(throughput))
            rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
            rr_active = (depth >= self.rr_depth) & ~passed
            rr_continue = sampler.next_1d(active_next) < rr_prob
            throughput = dr.select(active_next & rr_active, throughput * dr.rcp(rr_prob), throughput)
            active = (active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)
                      & (passes <= self.max_passes))

        result = dr.select(dr.isfinite(dr.sum(mi.unpolarized_spectrum(result))), result, 0.0)
        return dr.select(valid_ray, result, 0.0), valid_ray, []

    def aov_names(self):
        return []

    def to_string(self):
        return (f"BundlePathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"displaced_exit={self.displace}, exit_split={self.split}]")


PLUGINS = {"bundle_path": BundlePathIntegrator}
