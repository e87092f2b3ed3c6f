"""``hair_resampled``: Mitsuba's ``hair`` BSDF, its value and density unchanged, its sampling
made to draw from that density (the class docstring says why and how)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from models.fiber.lobes import longitudinal_variance

if mi.variant() is None:
    raise ImportError("mitsuba_ext.hair: choose a Mitsuba variant first (mi.set_variant), then "
                      "mitsuba_ext.register()")
VARIANT = mi.variant()  # the variant this class derives from

HAIR_DEFAULT_BETA_M = 0.3   # hair's own default longitudinal roughness


class ResampledHair(mi.BSDF):
    r"""Mitsuba's hair, sampled as its density says (``hair_resampled``)
    -------------------------------------------------------------------

    Mitsuba's own ``hair`` BSDF (Chiang et al. 2016) with its value and density unchanged
    (``eval``, ``pdf`` and ``eval_pdf`` are ``hair``'s) and its sampling made to draw from
    that density. Use it where ``hair`` fibers scatter light more than once (plies, tresses):
    the explicit references of the project's closure tests render it.

    Mitsuba 3.9.1's ``hair.sample`` picks a path ``p`` (R, TT, TRT, or the residual) and draws
    the outgoing longitude around the incident direction tilted for that path. For the residual
    (``p = P_MAX``) no tilted direction is set: its ``sin(theta_ip)`` and ``cos(theta_ip)`` stay
    zero, so every residual sample leaves exactly in the normal plane (``theta_o = 0``), while
    ``hair.pdf`` (and the weight ``eval / pdf``, which is 1 for a lossless fiber) describes the
    residual as d'Eon's longitudinal lobe around the untilted cone, of variance ``4 v_0``. The
    samples do not follow their density, and Mitsuba's own chi-square test of ``hair`` rejects
    them at each direction it tries (``tests/test_hair_closure.py``). A path tracer's
    next-event estimate is unaffected, but every indirect bounce off a ``hair`` fiber carries
    the residual's share of the light (a few per cent, more towards grazing) to the normal
    plane instead of its lobe.

    This plugin redraws the residual's samples from the lobe its density describes
    (``mi.warp.square_to_rough_fiber`` around the untilted incident direction, ``kappa = 1 /
    (4 v_0)``), with ``hair``'s value and density there. A residual sample is recognised by
    ``wo.y == 0`` exactly, which no other path produces with non-zero probability; with a
    ``hair`` that samples its residual correctly the plugin is ``hair`` unchanged.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Default
         - Unit
         - Description
       * - int_ior
         - float
         - hair's
         - 
         - Passed to ``hair``, as every other parameter of ``hair`` (``ext_ior``,
           ``sigma_a`` or ``eumelanin`` / ``pheomelanin``, ``scale``, ...).
       * - longitudinal_roughness
         - float
         - 0.3
         - 
         - Passed to ``hair``; also the residual's lobe width here.
       * - azimuthal_roughness
         - float
         - 0.3
         - 
         - Passed to ``hair``.
       * - scale_tilt
         - float
         - 2
         - degrees
         - Passed to ``hair`` (the residual is not tilted).
       * - sigma_a
         - spectrum or texture
         - 
         - per fiber radius
         - Passed to ``hair``.

    On ``bsplinecurve`` shapes, as ``hair``; ``mi.traverse`` exposes ``hair``'s parameters.

    .. code-block:: python

        bsdf = {"type": "hair_resampled", "int_ior": 1.55, "longitudinal_roughness": 0.2,
                "sigma_a": {"type": "uniform", "value": 0.0}}

    .. code-block:: xml

        <!-- declared once, then <ref id="fiber"/> inside each bsplinecurve of hair -->
        <bsdf type="hair_resampled" id="fiber">
            <float name="int_ior" value="1.55"/>
            <float name="longitudinal_roughness" value="0.2"/>
            <float name="azimuthal_roughness" value="0.3"/>
            <float name="scale_tilt" value="2"/>
            <float name="sigma_a" value="0"/>
        </bsdf>
    """

    def __init__(self, props):
        super().__init__(props)
        self.hair = mi.load_dict({"type": "hair", **{name: props[name] for name in props.keys()}})
        beta_m = float(props.get("longitudinal_roughness", HAIR_DEFAULT_BETA_M))
        self.kappa = float(1 / longitudinal_variance(beta_m)[-1])   # the residual's concentration
        self.m_flags = self.hair.flags()
        self.m_components = [self.hair.flags(i) for i in range(self.hair.component_count())]

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs, value = self.hair.sample(ctx, si, sample1, sample2, active)
        # hair draws the residual's azimuth change as 2 pi u, with u uniform and independent of
        # sample2: read it back, and draw the residual's longitude from sample2 afresh
        residual = active & (bs.pdf > 0) & (bs.wo.y == 0)
        dphi = dr.atan2(bs.wo.z, bs.wo.x) - dr.atan2(si.wi.z, si.wi.x)
        u = dphi * (0.5 / dr.pi)
        u = u - dr.floor(u)
        wo = mi.warp.square_to_rough_fiber(mi.Point3f(u, sample2.x, sample2.y), si.wi, mi.Vector3f(0, 1, 0),
                                           self.kappa)
        f, pdf = self.hair.eval_pdf(ctx, si, wo, residual)
        bs.wo = dr.select(residual, wo, bs.wo)
        bs.pdf = dr.select(residual, pdf, bs.pdf)
        value = dr.select(residual, dr.select(pdf > 0, f / pdf, 0.0), value)
        return bs, value

    def eval(self, ctx, si, wo, active=True):
        return self.hair.eval(ctx, si, wo, active)

    def pdf(self, ctx, si, wo, active=True):
        return self.hair.pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.hair.eval_pdf(ctx, si, wo, active)

    def traverse(self, callback):
        self.hair.traverse(callback)

    def to_string(self):
        return f"ResampledHair[\n  hair = {self.hair}\n]"


PLUGINS = {"hair_resampled": ResampledHair}
