"""The ``fiber_bundle`` BSDF: a baked or neural bundle scattering function on a curve.

Call :func:`mitsuba_ext.register` after ``mi.set_variant`` to make it available;
the class is built for the active variant (Mitsuba's Python plugins derive from the
variant's ``mi.BSDF``).
"""

from __future__ import annotations

import numpy as np

from mitsuba_ext.backends import load_backend
from models.spectrum import spectrum_to_srgb


# -- small pure functions: the geometry of the bundle frame -----------------------
def bundle_frame(si, up, twist, twist_rate):
    """World axes ``(x, t, z)`` of the bundle frame at ``si``.

    ``t`` is the curve tangent (the shading frame's second axis on ``cylinder`` and
    ``bsplinecurve``); ``x`` is ``up`` projected perpendicular to ``t`` and turned about
    ``t`` by ``twist + twist_rate * v`` (``v = si.uv.y`` runs along the shape), so an
    elliptical bundle's major axis winds along the curve. Degenerate tangents or an
    ``up`` parallel to the tangent fall back to a frame built from the normal.
    """
    import drjit as dr
    import mitsuba as mi

    t = si.sh_frame.t
    bad_t = ~dr.isfinite(dr.sum(t)) | (dr.squared_norm(t) < 0.25)
    n_ok = dr.isfinite(dr.sum(si.n)) & (dr.squared_norm(si.n) > 0.25)
    t_alt, _ = mi.coordinate_system(dr.select(n_ok, dr.normalize(si.n), mi.Vector3f(0, 0, 1)))
    t = dr.normalize(dr.select(bad_t, t_alt, t))
    x0 = up - dr.dot(up, t) * t
    x_alt, _ = mi.coordinate_system(t)
    x0 = dr.select(dr.squared_norm(x0) < 1e-6, x_alt, dr.normalize(x0))
    s, c = dr.sincos(twist + twist_rate * si.uv.y)
    x = c * x0 + s * dr.cross(t, x0)
    z = dr.cross(x, t)
    return x, t, z


def angles(w, frame):
    """``(phi, theta)`` of a world direction in the bundle frame (DESIGN.md conventions)."""
    import drjit as dr

    x, t, z = frame
    theta = dr.safe_asin(dr.clip(dr.dot(w, t), -1.0, 1.0))
    phi = dr.atan2(dr.dot(w, z), dr.dot(w, x))
    return phi, theta


def direction(phi, theta, frame):
    """World direction of bundle-frame angles."""
    import drjit as dr

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
        return np.array([[np.interp(mono_nm, wl, eye[k]) for k in range(len(wl))]])
    import colour

    rgb = spectrum_to_srgb(eye, wl)  # Y is the second row of XYZ
    Y = colour.sRGB_to_XYZ(rgb, apply_cctf_decoding=False)[:, 1]
    return Y[None, :]


def bsdf_class():
    """The ``fiber_bundle`` plugin class for the active Mitsuba variant."""
    import drjit as dr
    import mitsuba as mi

    class FiberBundleBSDF(mi.BSDF):
        r"""Fiber bundle BSDF (``fiber_bundle``)
        -------------------------------------

        The far-field scattering function of a bundle of parallel fibers (a yarn ply),
        baked by ``bcsdf bake`` or compressed by ``bcsdf train``/``export``, on a
        ``cylinder`` or ``bsplinecurve`` whose radius is the bundle's bounding radius.

        .. list-table::
           :header-rows: 1

           * - Parameter
             - Description
           * - backend
             - ``table`` (default), ``mlp`` (jitted Dr.Jit MLP) or ``onnx`` (onnxruntime).
           * - table
             - ``bundle_table.npz`` (backend ``table``).
           * - model
             - ``weights.npz`` (``mlp``) or ``model.onnx`` (``onnx``) from ``bcsdf export``.
           * - lookup
             - ``linear`` (default: multilinear in all four angles) or ``nearest``.
           * - passthrough
             - Let rays cross the bundle with the baked probability (default ``true``).
           * - twist, twist_rate
             - Orientation of an elliptical cross-section about the tangent, in degrees,
               and its change per unit of ``v`` along the shape (default 0, 0).
           * - up
             - Reference vector for the cross-section's major axis (default ``[0, 0, 1]``).
           * - wavelength
             - Mono variants: the wavelength (nm) to render; default CIE luminance.
           * - radius
             - Bundle radius in scene units, for the displaced exit point of
               ``bundle_path`` on ``bsplinecurve`` shapes (cylinders measure it).
           * - sampling_uniform
             - Fraction of direction samples drawn uniformly on the sphere (default 0.1).

        ``eval`` returns ``S(w_i, w_o)`` with the cosine included, as Mitsuba's ``hair``:
        it integrates over ``w_o`` to the fraction of the light reaching the bundle's
        projected width that is scattered. The remaining passthrough is a null lobe
        (``sample`` returns ``w_o = -w_i`` with probability ``P_pass(phi_i)``); a hit from
        the inside of the shape always passes, so the far wall of a cylinder is not a
        second interaction. Spectral variants interpolate the table's wavelengths
        linearly (held constant outside), rgb variants see the spectrum under D65.

        .. code-block:: python

            import mitsuba as mi
            mi.set_variant("llvm_ad_spectral")
            import mitsuba_ext
            mitsuba_ext.register()
            bsdf = mi.load_dict({"type": "fiber_bundle", "backend": "mlp",
                                 "model": "artifacts/default/export/medium/weights.npz"})
        """

        def __init__(self, props):
            super().__init__(props)

            def get(name, default):
                return props.get(name, default)

            # -- backend and its sampling distribution
            self.backend = load_backend(get("backend", "table"), mi.Float, table=get("table", None),
                                        model=get("model", None), lookup=get("lookup", "linear"))
            self.grid = self.backend.sampling_grid(float(get("sampling_uniform", 0.1)))
            self.use_passthrough = bool(get("passthrough", True))
            self.twist = float(np.radians(get("twist", 0.0)))
            self.twist_rate = float(np.radians(get("twist_rate", 0.0)))
            up = np.asarray(get("up", [0.0, 0.0, 1.0]), float).ravel()
            if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) == 0:
                raise ValueError(f"fiber_bundle: 'up' must be a non-zero 3-vector, got {up}")
            self.up = [float(v) for v in up / np.linalg.norm(up)]
            self.radius = float(get("radius", 0.0))

            # -- spectra: how the table's wavelengths become this variant's Spectrum
            wl = self.backend.wavelength
            if mi.is_spectral:
                step = np.diff(wl)
                if len(wl) > 1 and not np.allclose(step, step[0], rtol=1e-4):
                    raise ValueError("fiber_bundle: spectral variants need evenly spaced table wavelengths")
                self.weights = None
            else:
                kind = "rgb" if mi.is_rgb else "mono"
                mono_nm = float(props["wavelength"]) if "wavelength" in props else None
                self.weights = spectral_weights(wl, kind, mono_nm).tolist()

            scatter = (mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.GlossyTransmission |
                       mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide | mi.BSDFFlags.NonSymmetric)
            passing = mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [scatter, passing]
            self.m_flags = scatter | passing

        # -- pieces ----------------------------------------------------------
        def _frame(self, si):
            return bundle_frame(si, mi.Vector3f(*self.up), self.twist, self.twist_rate)

        def _spectrum(self, S, si):
            """Table spectrum (list over lambda) -> this variant's unpolarized Spectrum."""
            if self.weights is not None:
                chans = []
                for row in self.weights:
                    acc = mi.Float(0.0)
                    for w, s in zip(row, S):
                        if w != 0.0:
                            acc = dr.fma(s, w, acc)
                    chans.append(acc)
                return mi.UnpolarizedSpectrum(*chans) if len(chans) > 1 else mi.UnpolarizedSpectrum(chans[0])
            wl = self.backend.wavelength
            lam0, step, n = float(wl[0]), float(wl[1] - wl[0]) if len(wl) > 1 else 1.0, len(wl)
            # hat functions of linear interpolation, held constant beyond the ends
            t = dr.clip((si.wavelengths - lam0) / step, 0.0, float(n - 1))
            out = dr.zeros(mi.UnpolarizedSpectrum, dr.width(t))
            for k, s in enumerate(S):
                out += s * dr.maximum(0.0, 1.0 - dr.abs(t - k))
            return out

        def _passthrough(self, si, phi_i, inside):
            if not self.use_passthrough:
                return dr.select(inside, 1.0, 0.0)
            return dr.select(inside, 1.0, dr.clip(self.backend.passthrough(phi_i), 0.0, 1.0))

        def _setup(self, si):
            """Bundle frame, incident angles and whether the ray arrived from inside."""
            frame = self._frame(si)
            wi = si.to_world(si.wi)
            phi_i, theta_i = angles(wi, frame)
            inside = mi.Frame3f.cos_theta(si.wi) < 0.0
            return frame, phi_i, theta_i, inside

        def _value(self, si, frame, phi_i, theta_i, wo_world):
            phi_o, theta_o = angles(wo_world, frame)
            S = self.backend.eval(phi_i, theta_i, phi_o, theta_o)
            value = self._spectrum(S, si)
            return dr.select(dr.isfinite(value), dr.maximum(value, 0.0), 0.0), phi_o, theta_o

        # -- the BSDF interface ---------------------------------------------
        def eval(self, ctx, si, wo, active=True):
            frame, phi_i, theta_i, inside = self._setup(si)
            value, _, _ = self._value(si, frame, phi_i, theta_i, si.to_world(wo))
            enabled = ctx.is_enabled(mi.BSDFFlags.Glossy, 0)
            return dr.select(active & ~inside & enabled, value, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            frame, phi_i, theta_i, inside = self._setup(si)
            phi_o, theta_o = angles(si.to_world(wo), frame)
            P = self._passthrough(si, phi_i, inside)
            pdf = (1.0 - P) * self.grid.pdf(phi_i, theta_i, phi_o, theta_o)
            return dr.select(active & ~inside & ctx.is_enabled(mi.BSDFFlags.Glossy, 0), pdf, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            frame, phi_i, theta_i, inside = self._setup(si)
            P = self._passthrough(si, phi_i, inside)
            if not ctx.is_enabled(mi.BSDFFlags.Null, 1):
                P = dr.zeros(mi.Float, dr.width(P))
            elif not ctx.is_enabled(mi.BSDFFlags.Glossy, 0):
                P = dr.select(P > 0, 1.0, 0.0)
            passes = sample1 < P

            # scattering: the remainder of sample1 picks uniform or tabulated sampling
            u_mix = (sample1 - P) / dr.maximum(1.0 - P, 1e-12)
            phi_o, theta_o, pdf_dir = self.grid.sample(phi_i, theta_i, u_mix, sample2)
            wo_world = direction(phi_o, theta_o, frame)
            value, _, _ = self._value(si, frame, phi_i, theta_i, wo_world)

            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = dr.select(passes, -si.wi, si.to_local(wo_world))
            bs.pdf = dr.select(passes, P, (1.0 - P) * pdf_dir)
            bs.eta = 1.0
            bs.sampled_type = dr.select(passes, mi.UInt32(+(mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission)),
                                        mi.UInt32(+mi.BSDFFlags.GlossyTransmission))
            bs.sampled_component = dr.select(passes, mi.UInt32(1), mi.UInt32(0))
            weight = dr.select(passes, 1.0, value / dr.maximum(bs.pdf, 1e-20))
            ok = active & (bs.pdf > 0)
            return bs, dr.select(ok & dr.isfinite(weight), weight, 0.0)

        def eval_attribute_1(self, name, si, active=True):
            if name == "passthrough":
                _, phi_i, _, inside = self._setup(si)
                return self._passthrough(si, phi_i, inside)
            if name == "radius":
                return dr.zeros(mi.Float, dr.width(si.t)) + self.radius
            return dr.zeros(mi.Float, dr.width(si.t))

        def has_attribute(self, name, active=True):
            return name in ("passthrough", "radius")

        def to_string(self):
            return (f"FiberBundleBSDF[backend={self.backend.name}, wavelengths={len(self.backend.wavelength)}, "
                    f"passthrough={self.use_passthrough}]")

    return FiberBundleBSDF
