"""BSDFs on curves: ``fiber_bundle`` (a baked or neural bundle), ``fiber_table`` (one
fiber's tabulated model) and ``fiber_ray`` (one ray-optics fiber, path by path), for
explicit-fiber ground-truth renders.

Mitsuba's Python plugins derive from the active variant's ``mi.BSDF``, so this module
is imported once a variant is chosen, as Mitsuba's own Python plugins are:
:func:`mitsuba_ext.register` imports it (and reloads it after a variant switch) and
registers :data:`PLUGINS`. The geometry they share is in ``mitsuba_ext.frame``.
"""

from __future__ import annotations

from functools import partial

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_ext.backends import load_backend
from mitsuba_ext.crossing import refuse_other_integrators
from mitsuba_ext.frame import (adjoint_factor, angles, bundle_frame, direction, light_and_camera, line_offset,
                               resolve_path, spectral_weights, split_uniform)
from mitsuba_ext.params import (boolean, jit_variant_only, number, spectrum_at, spectrum_property, texture_values,
                                vector3)
from models.bundle_table import dyed
from models.fiber import lobes
from models.fiber.base import FiberTable
from models.fiber.lobes import LobeSampler
from models.fiber.sampling import FiberSampler
from models.fiber.sampling_drjit import DrJitFiber

if mi.variant() is None:
    raise ImportError("mitsuba_ext.bsdf: choose a Mitsuba variant first (mi.set_variant), then "
                      "mitsuba_ext.register()")
VARIANT = mi.variant()  # the variant these classes derive from


class CurveBSDF(mi.BSDF):
    """What both plugins share: the curve frame, spectra, inside hits, attributes."""

    def __init__(self, props):
        jit_variant_only(self.plugin)
        super().__init__(props)

    def _init_curve(self, props, wavelength):
        def get(name, default):
            return props.get(name, default)

        # what mi.traverse exposes (as the user wrote them: degrees, any length of up) ...
        self.params = {"twist": mi.Float(number(self.plugin, "twist", get("twist", 0.0))),
                       "twist_rate": mi.Float(number(self.plugin, "twist_rate", get("twist_rate", 0.0))),
                       "up": mi.ScalarVector3f(vector3(self.plugin, "up", get("up", [0.0, 0.0, 1.0]))),
                       "radius": mi.Float(number(self.plugin, "radius", get("radius", 0.0), lo=0.0))}
        self._read_params()

        # how the table's wavelengths become this variant's Spectrum
        self.wavelength = wl = np.asarray(wavelength, float)
        if mi.is_spectral:
            if len(wl) < 2:
                raise ValueError(f"{self.plugin}: the table holds one wavelength ({wl[0]:.0f} nm); a spectral "
                                 "variant needs a spectrum: re-bake with more wavelengths or render in a mono variant")
            step = np.diff(wl)
            if not np.allclose(step, step[0], rtol=1e-4):
                raise ValueError(f"{self.plugin}: spectral variants need evenly spaced table wavelengths")
            self.weights = None
        else:
            kind = "rgb" if mi.is_rgb else "mono"
            mono_nm = number(self.plugin, "wavelength", props["wavelength"], 1.0) if "wavelength" in props else None
            self.weights = spectral_weights(wl, kind, mono_nm).tolist()

    def _read_params(self):
        """... and the Python floats the kernels are traced with (literals, not kernel inputs)."""
        def scalar(name, lo=-np.inf):
            return number(self.plugin, name, float(dr.ravel(self.params[name])[0]), lo=lo)
        self.twist = float(np.radians(scalar("twist")))
        self.twist_rate = float(np.radians(scalar("twist_rate")))
        up = np.array([float(v) for v in self.params["up"]])
        if not np.all(np.isfinite(up)) or np.linalg.norm(up) == 0:
            raise ValueError(f"{self.plugin}: 'up' must be a non-zero 3-vector, got {up.tolist()}")
        self.up = [float(v) for v in up / np.linalg.norm(up)]
        self.radius = scalar("radius", lo=0.0)

    def traverse(self, callback):
        """``mi.traverse`` exposes ``twist``, ``twist_rate`` (degrees, per scene unit of
        length), ``up`` and ``radius``; the kernels are traced anew after a change. The
        radius is read-only: the ply's radius is the shape's, so an edit is refused."""
        for name, value in self.params.items():
            callback.put(name, value, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        loaded = self.radius
        self._read_params()
        if any(k.split(".")[-1] == "radius" for k in keys) and self.radius != loaded:
            self.params["radius"] = mi.Float(loaded)
            self.radius = loaded
            raise ValueError(f"{self.plugin}: 'radius' cannot change after loading: the ply's radius is its "
                             "shape's (a cylinder's 'radius', a curve's control points); edit the shape instead")

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
        wl = self.wavelength
        lam0, step, n = float(wl[0]), float(wl[1] - wl[0]), len(wl)
        # hat functions of linear interpolation, held constant beyond the ends
        t = dr.clip((si.wavelengths - lam0) / step, 0.0, float(n - 1))
        out = dr.zeros(mi.UnpolarizedSpectrum, dr.width(t))
        for k, s in enumerate(S):
            out += s * dr.maximum(0.0, 1.0 - dr.abs(t - k))
        return dr.select(dr.isfinite(out), dr.maximum(out, 0.0), 0.0)

    def _setup(self, si):
        """Curve frame, incident angles and whether the ray arrived from inside."""
        frame = bundle_frame(si, mi.Vector3f(*self.up), self.twist, self.twist_rate)
        wi = si.to_world(si.wi)
        phi_i, theta_i = angles(wi, frame)
        # a hit from inside passes; so does one whose frame is degenerate (no direction)
        inside = (mi.Frame3f.cos_theta(si.wi) < 0.0) | ~dr.isfinite(dr.sum(wi))
        return frame, phi_i, theta_i, inside

    def _passthrough(self, si, phi_i, theta_i, inside):
        return dr.select(inside, 1.0, 0.0)

    def _load_fiber(self, props, what: str):
        """The single-fiber table named by ``filename`` (``what``: the words for the error)."""
        if "filename" not in props:
            raise ValueError(f"{self.plugin}: needs 'filename' ({what})")
        return FiberTable.load(resolve_path(self.plugin, "filename", props["filename"]))

    def _fiber_components(self, n_scatter: int = 1):
        """A single fiber's components: ``n_scatter`` glossy ones (one per path where the
        model has paths), then passing, for hits from inside the shape only."""
        scatter = (mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.GlossyTransmission |
                   mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide)
        passing = mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        self.m_components = [scatter] * n_scatter + [passing]
        self.m_flags = scatter | passing

    def eval_attribute_1(self, name, si, active=True):
        if name == "passthrough":
            _, phi_i, theta_i, inside = self._setup(si)
            return self._passthrough(si, phi_i, theta_i, inside)
        if name == "radius":
            return dr.zeros(mi.Float, dr.width(si.t)) + self.radius
        return dr.zeros(mi.Float, dr.width(si.t))

    def has_attribute(self, name, active=True):
        return name in ("passthrough", "radius")

class FiberBundleBSDF(CurveBSDF):
    r"""Fiber bundle BSDF (``fiber_bundle``)
    -------------------------------------

    The far-field scattering function of a bundle of parallel fibers (a yarn ply),
    baked by ``bcsdf bake`` or compressed by ``bcsdf train``/``export``, on a
    ``cylinder`` or ``bsplinecurve`` whose radius is the bundle's bounding radius.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Default
         - Unit
         - Description
       * - backend
         - string
         - ``table``
         - 
         - ``table``, ``mlp`` (the jitted Dr.Jit MLP) or ``onnx`` (onnxruntime).
       * - table
         - filename
         - 
         - 
         - ``bundle_table.npz`` from ``bcsdf bake`` (backend ``table``).
       * - model
         - filename
         - 
         - 
         - ``weights.npz`` (``mlp``) or ``model.onnx`` (``onnx``) from ``bcsdf export``.
       * - lookup
         - string
         - ``linear``
         - 
         - ``linear``: each bin its value plus limited slopes, so that it averages to
           its value; theta_i nodes read along their own specular cone and blended.
           ``nearest``: the nearest node's bin value.
       * - albedo
         - spectrum
         - none
         - fraction
         - A dye: every fiber event keeps this fraction of the baked fiber's scattering
           (``BundleTable.recolour``): a table baked with ``bake.orders``, or a model
           trained on one with ``train.orders: true``. A number or a uniform Mitsuba
           spectrum (``spectrum``, ``srgb``, ...) recolours the table once, at load (a
           model at every evaluation): spectral variants evaluate it at the table's
           wavelengths, RGB variants upsample its colour as Mitsuba's spectral variants
           do (Jakob and Hanika 2019). A texture on the shape's UV (space-dyed yarn,
           e.g. a ``bitmap``) is applied per hit to the orders (K lookups; one
           evaluation of a model); in RGB variants then per channel.
       * - packing
         - float or texture
         - none
         - fraction
         - The ply's packing fraction, for a model trained on a family of bakes
           (``train.inputs: [packing]``, ``python -m pipeline.bench.packing``): within
           the range it was trained on (refused outside: it does not extrapolate). A
           number is editable at render time through ``mi.traverse`` (the ``mlp``
           backend traces the two trained packings around it: an edit between them
           compiles nothing, one past a trained packing compiles once); a texture on the
           shape's UV (a ``bitmap`` with ``raw: true``, say) sets it per hit, its values
           checked at load on a 256 x 256 grid of the UV square. Refused by the table
           backend and by models of one ply.
       * - near_field
         - boolean
         - ``true``
         - 
         - Where the table (``bake.offsets``) or the model (``train.inputs: [offset]``)
           holds the near field: evaluate the light leaving on the camera ray's own line
           across the ply (its offset ``h`` from the axis) and let a ray through with the
           passthrough of its own offset; else (or ``false``) the far field, the same at
           every offset (a model's: its mean over the offset).
       * - passthrough
         - boolean
         - ``true``
         - 
         - Let rays cross the bundle with the baked probability.
       * - twist
         - float
         - 0
         - degrees
         - Orientation of an elliptical cross-section about the tangent.
       * - twist_rate
         - float
         - 0
         - degrees per scene unit
         - Its change along the shape (the length is ``v |dp/dv|``, exact on
           cylinders and on curves with evenly spaced control points).
       * - up
         - vector
         - ``[0, 0, 1]``
         - 
         - Reference vector for the cross-section's major axis.
       * - wavelength
         - float
         - CIE luminance
         - nm
         - Mono variants: the wavelength to render.
       * - radius
         - float
         - the shape's
         - scene units
         - Optional, >= 0. ``bundle_path`` reads the radius from the shape
           (``|dp/du| = 2 pi r`` per hit on ``cylinder`` and ``bsplinecurve``) and warns
           once if this one disagrees; read-only in ``mi.traverse`` (edit the shape's).
       * - sampling_uniform
         - float
         - 0.1
         - fraction
         - Share of direction samples drawn uniformly on the sphere, in [0, 1].

    File parameters (``table``, ``model``) resolve like Mitsuba's own ``filename``:
    relative to the XML scene's folder, else to the current one. Every parameter
    is checked at load (a value outside its domain is refused, naming it).

    **Supported**: ``cylinder`` and ``bsplinecurve`` shapes whose radius is the
    bundle's bounding radius (``bundle_path`` warns once about any other shape:
    the frame follows a tangent only these two have); every JIT variant, ``llvm_*``
    and ``cuda_*`` (the ``onnx`` backend in evaluated mode only; ``scalar_*`` is refused
    at load: the lookups are vectorized Dr.Jit code); ``path`` and ``bundle_path``
    integrator ``bundle_path`` only: it crosses bundles with their passthrough in shadow
    rays and leaves them from the displaced exit point, which Mitsuba's ``path`` (or any
    other) would leave out, rendering the ply darker. A bundle rendered by another
    integrator raises in ``mi.render`` (``bcsdf render-scene`` says so on loading the
    scene; ``mitsuba_ext.check_integrator(scene)`` asks the same of a loaded scene).
    **Which direction is incident.** The table's ``S(w_i -> w_o)`` has ``w_i`` on the
    light's side (the bake's incidence). In ``eval(ctx, si, wo)`` of a path tracer
    (``TransportMode.Radiance``) the light side is ``wo`` and the camera side
    ``si.wi``, so ``eval = S(w_i = wo -> w_o = si.wi) cos(theta_wo) / cos(theta_si.wi)``:
    then a cylinder of radius ``R`` under a directional light ``E`` from ``w_i`` and
    seen from ``w_o`` sends ``I = E 2R cos(theta_i) S(w_i -> w_o)`` per unit length,
    the far field the table describes (``pipeline.closure`` tests it in every
    backend). For a reciprocal ``S`` this is ``S(si.wi -> wo)``; a baked table is
    reciprocal only within its noise and an MLP within its error, so the order is
    kept exactly. In ``TransportMode.Importance`` (light tracing) ``si.wi`` is the
    light side and ``eval = S(si.wi -> wo)``. ``sample`` proposes ``wo`` from the
    table (or the model's own tabulation) conditioned on ``si.wi``, mixed with a
    uniform share; ``pdf`` is that proposal's density (Mitsuba's chi-square test),
    and the weight ``eval / pdf`` is exact whatever the proposal.

    **Attributes** for ``bundle_path``: ``passthrough`` and ``radius`` at a hit, and, where
    the bake recorded it (the table's ``single``, or the exported model's metadata),
    ``single_share``: per wavelength, the share of the scattered light that left the
    ply after one fiber event (``bundle_path``'s ``exit_split`` sends that share from
    where it entered).

    ``mi.traverse`` exposes ``twist``, ``twist_rate``, ``up``, ``radius`` and
    ``sampling_uniform`` (non-differentiable; edit them and ``params.update()``, as with
    Mitsuba's own plugins: the next render uses them).

    The passthrough is a null lobe
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
                             "model": "artifacts/default/export/small/weights.npz"})

    In a scene (``bcsdf render-scene``; ``scenes/ply.xml`` is a whole one):

    .. code-block:: xml

        <shape type="cylinder">
            <point name="p0" value="-3, 0, 0"/>
            <point name="p1" value="3, 0, 0"/>
            <float name="radius" value="0.2"/>
            <bsdf type="fiber_bundle">
                <string name="backend" value="table"/>
                <string name="table" value="artifacts/default/bake/bundle_table.npz"/>
            </bsdf>
        </shape>
    """

    plugin = "fiber_bundle"

    def __init__(self, props):
        super().__init__(props)
        # a dye: uniform, the table recoloured once at load; varying over the shape (a texture
        # on its UV), the orders looked up and weighted by the texture's albedo per hit
        albedo = spectrum_property(props, "albedo") if "albedo" in props else None
        varying = isinstance(albedo, mi.Texture) and albedo.is_spatially_varying()
        self.dye = albedo if varying else None
        # a family's packing: a number (editable through mi.traverse) or a texture on the UV,
        # read per hit, its values checked against the trained range at load
        packing = props["packing"] if "packing" in props else None
        self.packing = packing if isinstance(packing, mi.Texture) else None
        if self.packing is not None:
            values = texture_values(self.packing)
            packing = float(np.mean(values))   # the sampling grid's
        elif packing is not None:
            packing = number(self.plugin, "packing", packing, 0.0, 1.0)
        self.backend = load_backend(props.get("backend", "table"), mi.Float,
                                    table=resolve_path(self.plugin, "table", props.get("table", None)),
                                    model=resolve_path(self.plugin, "model", props.get("model", None)),
                                    lookup=props.get("lookup", "linear"),
                                    dye=None if albedo is None else
                                    self.dye if varying else partial(spectrum_at, self.plugin, "albedo", albedo),
                                    near_field=boolean(self.plugin, "near_field", props.get("near_field", True)),
                                    packing=packing)
        if self.packing is not None:
            try:
                for extreme in (values.min(), values.max()):
                    self.backend.check_packing(extreme)
            except ValueError as e:
                raise ValueError(f"{e} ('packing' texture: its values span {values.min():g} .. {values.max():g})") \
                    from None
        uniform = number(self.plugin, "sampling_uniform", props.get("sampling_uniform", 0.1), 0.0, 1.0)
        self.grid = self.backend.sampling_grid(uniform)
        self.camera_grid = None if self.backend.near is None else self.backend.camera_grid(uniform)
        self.use_passthrough = boolean(self.plugin, "passthrough", props.get("passthrough", True))
        self._init_curve(props, self.backend.wavelength)
        self.params["sampling_uniform"] = mi.Float(uniform)
        if self.backend.constants and self.packing is None:   # a family's: its packing edited at render time
            self.params["packing"] = mi.Float(packing)
        scatter = (mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.GlossyTransmission |
                   mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide | mi.BSDFFlags.NonSymmetric)
        passing = mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        self.m_components = [scatter, passing]
        self.m_flags = scatter | passing

    def parameters_changed(self, keys):
        super().parameters_changed(keys)
        if "packing" in keys and "packing" in self.params:
            self.backend.set_packing(number(self.plugin, "packing", float(dr.ravel(self.params["packing"])[0]),
                                            0.0, 1.0))
        if "sampling_uniform" in keys or "packing" in keys:
            uniform = float(dr.ravel(self.params["sampling_uniform"])[0])
            uniform = number(self.plugin, "sampling_uniform", uniform, 0.0, 1.0)
            self.grid = self.backend.sampling_grid(uniform)
            self.camera_grid = None if self.backend.near is None else self.backend.camera_grid(uniform)

    def _passthrough(self, si, phi_i, theta_i, inside):
        if not self.use_passthrough:
            return dr.select(inside, 1.0, 0.0)
        if self.backend.near is not None:   # the arriving ray's own offset, as it travels
            frame = bundle_frame(si, mi.Vector3f(*self.up), self.twist, self.twist_rate)
            P = self.backend.passthrough_near(theta_i, -line_offset(si, frame, phi_i))
        else:
            P = self._backend_at(si).passthrough(phi_i, theta_i)
        return dr.select(inside, 1.0, dr.clip(P, 0.0, 1.0))

    def _value(self, ctx, si, frame, wo):
        """The BSDF value for local ``wo``: the table's ``S(w_i -> w_o)`` with ``w_i``
        the light side, times the adjoint factor in radiance mode."""
        w_light, w_camera, radiance = light_and_camera(ctx, si, wo)
        phi_l, theta_l = angles(si.to_world(w_light), frame)
        phi_c, theta_c = angles(si.to_world(w_camera), frame)
        backend = self._backend_at(si)
        if backend.near is not None:   # the near field: the camera ray's own offset
            h = line_offset(si, frame, phi_c)
            value = self._spectrum(backend.eval_near(phi_l, theta_l, phi_c, theta_c, h), si)
        elif self.dye is None:
            value = self._spectrum(backend.eval(phi_l, theta_l, phi_c, theta_c), si)
        else:
            value = self._dyed(backend, si, phi_l, theta_l, phi_c, theta_c)
        return value * adjoint_factor(theta_l, theta_c) if radiance else value

    def _backend_at(self, si):
        """The backend at this hit: a family's model read at the packing texture's value here."""
        return self.backend if self.packing is None else self.backend.at_packing(self.packing.eval_1(si))

    def _dyed(self, backend, si, phi_l, theta_l, phi_c, theta_c):
        """``sum_{k<K} a^k S_k + a^K T (1 - rho) / (1 - a rho)`` with the texture's albedo ``a``
        at this hit and this path's wavelengths (``BundleTable.recolour``, per hit): each
        order is mapped to the render's spectrum first (in RGB variants the dye then acts
        per channel, an approximation of the spectral product)."""
        orders, rho = backend.eval_orders(phi_l, theta_l, phi_c, theta_c)
        a = dr.clip(mi.UnpolarizedSpectrum(self.dye.eval(si)), 0.0, 1.0)
        r = dr.minimum(self._spectrum(rho, si), 1.0 - 1e-6)   # < 1 as baked; kept so in float32: 1 - a rho > 0
        return dyed([self._spectrum(S_k, si) for S_k in orders], a, r)

    # -- the BSDF interface ---------------------------------------------
    def eval(self, ctx, si, wo, active=True):
        refuse_other_integrators()
        frame, _, _, inside = self._setup(si)
        value = self._value(ctx, si, frame, wo)
        return dr.select(active & ~inside & ctx.is_enabled(mi.BSDFFlags.Glossy, 0), value, 0.0)

    def _proposal(self, ctx, si, frame, phi_i):
        """``(grid, extra)``: the far field's proposal, conditioned on ``si.wi`` (by
        reciprocity it stands for the table read the other way), or, for a near-field table
        in radiance mode, the table transposed per offset cell of the camera ray's line
        (:meth:`TableBackend.camera_grid`)."""
        if self.camera_grid is None or ctx.mode != mi.TransportMode.Radiance:
            return self.grid, None
        return self.camera_grid, self.backend.offset_cell(line_offset(si, frame, phi_i))

    def pdf(self, ctx, si, wo, active=True):
        frame, phi_i, theta_i, inside = self._setup(si)
        phi_o, theta_o = angles(si.to_world(wo), frame)
        P = self._passthrough(si, phi_i, theta_i, inside)
        grid, cell = self._proposal(ctx, si, frame, phi_i)
        pdf = (1.0 - P) * grid.pdf(phi_i, theta_i, phi_o, theta_o, cell)
        return dr.select(active & ~inside & ctx.is_enabled(mi.BSDFFlags.Glossy, 0), pdf, 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        refuse_other_integrators()
        frame, phi_i, theta_i, inside = self._setup(si)
        P = self._passthrough(si, phi_i, theta_i, inside)
        if not ctx.is_enabled(mi.BSDFFlags.Null, 1):
            P = dr.zeros(mi.Float, dr.width(P))
        elif not ctx.is_enabled(mi.BSDFFlags.Glossy, 0):
            P = dr.select(P > 0, 1.0, 0.0)
        passes = sample1 < P

        # scattering: the remainder of sample1 picks uniform or tabulated sampling
        u_mix = (sample1 - P) / dr.maximum(1.0 - P, 1e-12)
        grid, cell = self._proposal(ctx, si, frame, phi_i)
        phi_o, theta_o, pdf_dir = grid.sample(phi_i, theta_i, u_mix, sample2, cell)
        wo_local = si.to_local(direction(phi_o, theta_o, frame))
        value = self._value(ctx, si, frame, wo_local)

        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = dr.select(passes, -si.wi, wo_local)
        bs.pdf = dr.select(passes, P, (1.0 - P) * pdf_dir)
        bs.eta = 1.0
        bs.sampled_type = dr.select(passes, mi.UInt32(+(mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission)),
                                    mi.UInt32(+mi.BSDFFlags.GlossyTransmission))
        bs.sampled_component = dr.select(passes, mi.UInt32(1), mi.UInt32(0))
        weight = dr.select(passes, 1.0, value / dr.maximum(bs.pdf, 1e-20))
        ok = active & (bs.pdf > 0)
        return bs, dr.select(ok & dr.isfinite(weight), weight, 0.0)

    def has_attribute(self, name, active=True):
        return name in ("passthrough", "radius") or (name == "single_share" and self.backend.single_share is not None)

    def eval_attribute(self, name, si, active=True):
        """``single_share``: per wavelength of this render, the share of the bundle's scattered
        light that left after one fiber event (``bundle_path`` sends it from where it entered)."""
        if name == "single_share" and self.backend.single_share is not None:
            q = [dr.zeros(mi.Float, dr.width(si.t)) + float(v) for v in self.backend.single_share]
            return dr.clip(self._spectrum(q, si), 0.0, 1.0)
        return dr.zeros(mi.UnpolarizedSpectrum, dr.width(si.t))

    def to_string(self):
        return (f"FiberBundleBSDF[backend={self.backend.name}, wavelengths={len(self.wavelength)}, "
                f"passthrough={self.use_passthrough}]")

class FiberTableBSDF(CurveBSDF):
    r"""Single fiber BSDF (``fiber_table``)
    ------------------------------------

    One fiber's tabulated scattering model (a ``fiber_table.npz`` from ``bcsdf fiber``)
    on a ``cylinder`` or ``bsplinecurve`` of the fiber's radius: the ground truth that a
    bundle BSDF is compared with, with every fiber of a ply as its own shape. ``eval``
    is the far-field (offset-averaged) fiber function ``f(w_i -> w_o)``, cosine
    included, with ``w_i`` the light side, read as ``fiber_bundle`` reads its table
    (``f(wo -> si.wi) cos(theta_wo) / cos(theta_si.wi)`` in radiance mode); sampling
    follows the fiber's own importance sampler (the baker's) from ``si.wi``.
    With ``bundle_path`` the light leaves the fiber from the displaced exit point,
    as in the baker.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Default
         - Unit
         - Description
       * - filename
         - filename
         - 
         - 
         - ``fiber_table.npz`` written by ``bcsdf fiber``.
       * - radius
         - float
         - the shape's
         - scene units
         - Optional, >= 0: the fiber radius; ``bundle_path`` reads it from the
           shape and warns once if this one disagrees.
       * - up
         - vector
         - ``[0, 0, 1]``
         - 
         - As ``fiber_bundle`` (a fiber is rotation invariant: it only sets the
           frame's azimuth origin).
       * - twist
         - float
         - 0
         - degrees
         - As ``fiber_bundle``.
       * - twist_rate
         - float
         - 0
         - degrees per scene unit
         - As ``fiber_bundle``.
       * - wavelength
         - float
         - CIE luminance
         - nm
         - Mono variants: the wavelength to render.

    Defined on ``cylinder`` and ``bsplinecurve`` shapes, like ``fiber_bundle``, and under
    ``bundle_path`` on ``linearcurve`` (cheaper to intersect: the cloth's flyaways), whose
    hits it gives their tangent frame (``mitsuba_ext.frame.LinearCurves``).
    ``mi.traverse`` exposes ``twist``, ``twist_rate``, ``up`` and ``radius``.

    .. code-block:: python

        fiber = {"type": "fiber_table", "filename": "artifacts/default/fiber/fiber_table.npz"}
        scene["fiber_0"] = {"type": "cylinder", "p0": [-1, 0, 0], "p1": [1, 0, 0], "radius": 0.02,
                            "bsdf": fiber}

    .. code-block:: xml

        <shape type="cylinder">
            <point name="p0" value="-1, 0, 0"/>
            <point name="p1" value="1, 0, 0"/>
            <float name="radius" value="0.02"/>
            <bsdf type="fiber_table">
                <string name="filename" value="artifacts/default/fiber/fiber_table.npz"/>
            </bsdf>
        </shape>
    """

    plugin = "fiber_table"

    def __init__(self, props):
        super().__init__(props)
        table = self._load_fiber(props, "a fiber_table.npz written by `bcsdf fiber`")
        self.fiber = DrJitFiber(table, FiberSampler(table), mi.Float)
        self._init_curve(props, table.wavelength)
        self._fiber_components()

    def _angles(self, si, wo_world):
        """Longitudes of ``si.wi`` and ``wo`` and their azimuth difference (wrapped)."""
        frame, phi_i, theta_i, inside = self._setup(si)
        phi_o, theta_o = angles(wo_world, frame)
        dphi = phi_o - phi_i
        return theta_i, theta_o, dphi - 2 * np.pi * dr.floor((dphi + np.pi) / (2 * np.pi)), inside

    def _value(self, ctx, theta_si, theta_wo, dphi, si):
        """``f(w_i -> w_o)`` with ``w_i`` the light side (``wo`` in radiance mode),
        times the adjoint factor; ``dphi`` is ``phi(wo) - phi(si.wi)``."""
        if ctx.mode == mi.TransportMode.Radiance:
            f = self.fiber.eval_spectrum(theta_wo, theta_si, -dphi)
            return self._spectrum(f, si) * adjoint_factor(theta_wo, theta_si)
        return self._spectrum(self.fiber.eval_spectrum(theta_si, theta_wo, dphi), si)

    def eval(self, ctx, si, wo, active=True):
        theta_i, theta_o, dphi, inside = self._angles(si, si.to_world(wo))
        value = self._value(ctx, theta_i, theta_o, dphi, si)
        return dr.select(active & ~inside, value, 0.0)

    def _pdf(self, theta_i, theta_o, dphi):
        """Per steradian: the fiber sampler's density is per d(theta_o) d(phi)."""
        return self.fiber.pdf(theta_i, theta_o, dphi) / dr.maximum(dr.cos(theta_o), 1e-6)

    def pdf(self, ctx, si, wo, active=True):
        theta_i, theta_o, dphi, inside = self._angles(si, si.to_world(wo))
        return dr.select(active & ~inside, self._pdf(theta_i, theta_o, dphi), 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        frame, phi_i, theta_i, inside = self._setup(si)
        u0, u1 = split_uniform(sample1)
        u3, u4 = split_uniform(sample2.y)
        theta_o, dphi = self.fiber.sample(theta_i, [u0, u1, sample2.x, u3, u4])
        wo_world = direction(phi_i + dphi, theta_o, frame)
        pdf = self._pdf(theta_i, theta_o, dphi)
        value = self._value(ctx, theta_i, theta_o, dphi, si)
        # a ray that meets the fiber's wall from inside crosses it (the light of this
        # fiber left through its displaced exit point already)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = dr.select(inside, -si.wi, si.to_local(wo_world))
        bs.pdf = dr.select(inside, 1.0, pdf)
        bs.eta = 1.0
        bs.sampled_type = dr.select(inside, mi.UInt32(+(mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission)),
                                    mi.UInt32(+mi.BSDFFlags.GlossyTransmission))
        bs.sampled_component = dr.select(inside, mi.UInt32(1), mi.UInt32(0))
        weight = dr.select(inside, 1.0, value / dr.maximum(pdf, 1e-20))
        ok = active & (inside | (pdf > 0))
        return bs, dr.select(ok & dr.isfinite(weight), weight, 0.0)

    def to_string(self):
        return f"FiberTableBSDF[wavelengths={len(self.wavelength)}]"

class FiberRayBSDF(CurveBSDF):
    r"""Ray-optics fiber, resolved in the entry offset (``fiber_ray``)
    -----------------------------------------------------------------

    One smooth-walled ray-optics fiber (d'Eon / Chiang, ``fiber.model: ray``) on a
    ``cylinder`` or ``bsplinecurve`` of the fiber's radius (or, under ``bundle_path``, a
    ``linearcurve``, as ``fiber_table``), evaluated at the hit's own
    offset ``h`` across the fiber instead of averaged over it (``fiber_table``). Each
    path ``p`` (R, TT, TRT, ..., the residual) is a BSDF component: ``bundle_path``
    starts the light of path ``p`` from where that path leaves the fiber (the
    attribute ``exit_<p>``, the outward normal there), for the sampled direction and
    for every path of the emitter sample, as the baker's ``lobe`` exit does. This is
    the explicit-fiber reference for bakes with ``bake.exit: lobe``. Under other
    integrators it is Mitsuba's ``hair`` on tubes: every path leaves at the hit.

    The paths are those of the ray that reached the hit (``si.wi``'s offset ``h``): a
    smooth fiber's ray paths are reversible, so the camera ray's path ``p`` is the
    light's path ``p`` run backwards. Its value is the light-side model, as
    ``fiber_table`` reads it (longitudes, Bravais' index and attenuation of the light
    side, times ``cos(theta_light) / cos(theta_camera)`` in radiance mode), so that
    averaged over the fiber's width it is exactly ``fiber_table``'s.

    ``sample`` draws the path by its attenuation at the wavelengths the render carries
    (as pbrt-v4's hair BSDF does; not the table's spectral mean, which for a dyed fiber
    weighs the long red paths up at every bounce), then the light side's longitude, then
    the azimuth about the lobe of *that* longitude's Bravais index (the one ``eval``
    reads). The model is not reciprocal: seen along grazing directions its radiance-mode
    albedo exceeds one, so a path that runs along the fibers of a ply gains weight; its
    variance is the model's, not the sampler's.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Default
         - Unit
         - Description
       * - filename
         - filename
         - 
         - 
         - ``fiber_table.npz`` of a ray fiber of light transport (``bcsdf fiber``
           with ``fiber.model: ray``): its parameters (index and absorption per
           wavelength, roughness, tilt, paths).
       * - radius
         - float
         - the shape's
         - scene units
         - As ``fiber_table``.
       * - up
         - vector
         - ``[0, 0, 1]``
         - 
         - As ``fiber_table``.
       * - twist
         - float
         - 0
         - degrees
         - As ``fiber_table``.
       * - twist_rate
         - float
         - 0
         - degrees per scene unit
         - As ``fiber_table``.
       * - wavelength
         - float
         - CIE luminance
         - nm
         - Mono variants: the wavelength to render.

    ``mi.traverse`` exposes ``twist``, ``twist_rate``, ``up`` and ``radius``.

    .. code-block:: python

        fiber = {"type": "fiber_ray", "filename": "artifacts/ray_ply/fiber/fiber_table.npz"}
        scene["fiber_0"] = {"type": "cylinder", "p0": [-1, 0, 0], "p1": [1, 0, 0], "radius": 0.02,
                            "bsdf": fiber}

    .. code-block:: xml

        <shape type="cylinder">
            <point name="p0" value="-1, 0, 0"/>
            <point name="p1" value="1, 0, 0"/>
            <float name="radius" value="0.02"/>
            <bsdf type="fiber_ray">
                <string name="filename" value="artifacts/ray_ply/fiber/fiber_table.npz"/>
            </bsdf>
        </shape>
    """

    plugin = "fiber_ray"

    def __init__(self, props):
        super().__init__(props)
        table = self._load_fiber(props, "a fiber_table.npz of a ray fiber, from `bcsdf fiber`")
        if table.meta.get("model") != "ray":
            raise ValueError(f"fiber_ray: {props['filename']} holds a {table.meta.get('model')!r} fiber; "
                             "fiber_ray needs a ray fiber (use fiber_table for other models)")
        if table.meta.get("transport", "light") != "light":
            raise ValueError(f"fiber_ray: {props['filename']} holds a ray fiber of {table.meta['transport']} "
                             "transport, the adjoint that Mitsuba's hair renders; fiber_ray resolves the model in "
                             "light transport. Render Mitsuba's hair on curves (models.fiber.ray.mitsuba_hair) or "
                             "this table with fiber_table (docs/DESIGN.md)")
        self.lobes = LobeSampler(table.meta, table.wavelength, mi.Float)
        self.n_paths = self.lobes.p_max + 1
        self._init_curve(props, table.wavelength)
        self._fiber_components(self.n_paths)

    def _local(self, si, wo_world):
        """Frame, ``theta`` of ``si.wi`` and ``wo``, ``dphi`` (wrapped), the offset ``h``
        of ``si``'s ray and whether it arrived from inside."""
        frame, phi_i, theta_i, inside = self._setup(si)
        phi_o, theta_o = angles(wo_world, frame)
        dphi = lobes.wrap(phi_o - phi_i, dr)
        return frame, theta_i, theta_o, dphi, self._offset(si, frame), inside

    @staticmethod
    def _offset(si, frame):
        """``h`` of the ray that reached ``si``, in the bundle frame's cross-section."""
        x, _, z = frame
        n = dr.normalize(mi.Vector2f(dr.dot(si.n, x), dr.dot(si.n, z)))
        d = -si.to_world(si.wi)
        u = dr.normalize(mi.Vector2f(dr.dot(d, x), dr.dot(d, z)))
        # the entry normal is -sqrt(1 - h^2) u + h u_perp, u_perp = (-u_z, u_x)
        h = dr.clip(-n.x * u.y + n.y * u.x, -1.0, 1.0)
        return dr.select(dr.isfinite(h), h, 0.0), n, u

    def _components(self, ctx):
        """The paths ``ctx`` asks for (all, one, or none: the passing component)."""
        c = ctx.component
        if c == 0xFFFFFFFF:
            return range(self.n_paths)
        return [c] if c < self.n_paths else []

    def _path_value(self, ctx, h, p, theta_si, theta_wo, dphi):
        """Path ``p``'s value at every wavelength: the light side is the incident one
        (``wo`` in radiance mode), the offset and azimuth those of ``si``'s ray."""
        if ctx.mode == mi.TransportMode.Radiance:
            f, _ = self.lobes.eval_spectrum(theta_wo, h, p, theta_si, dphi)
            scale = adjoint_factor(theta_wo, theta_si)
            return [v * scale for v in f]
        f, _ = self.lobes.eval_spectrum(theta_si, h, p, theta_wo, dphi)
        return f

    def _choice(self, si, theta_i, h):
        """The paths' probabilities at ``si``'s ray: their attenuations at the wavelengths
        this render carries (the variant's spectrum, as :meth:`_spectrum` maps the table's),
        not the table's spectral mean (see ``LobeSampler.lobe_probabilities``)."""
        A = self.lobes.attenuations(self.lobes.cos_in(theta_i), h)
        P, _ = self.lobes.lobe_probabilities(A, lambda a: dr.sum(self._spectrum(a, si)))
        return P

    def eval(self, ctx, si, wo, active=True):
        _, theta_i, theta_o, dphi, (h, _, _), inside = self._local(si, si.to_world(wo))
        total = [dr.zeros(mi.Float, dr.width(h)) for _ in range(self.lobes.L)]
        for p in self._components(ctx):
            f = self._path_value(ctx, h, dr.zeros(mi.UInt32, dr.width(h)) + p, theta_i, theta_o, dphi)
            total = [a + b for a, b in zip(total, f)]
        return dr.select(active & ~inside, self._spectrum(total, si), 0.0)

    def pdf(self, ctx, si, wo, active=True):
        _, theta_i, theta_o, dphi, (h, _, _), inside = self._local(si, si.to_world(wo))
        pdf = dr.zeros(mi.Float, dr.width(h))
        P = self._choice(si, theta_i, h)
        light_out = ctx.mode == mi.TransportMode.Radiance  # wo is the light's side
        for p in self._components(ctx):
            pdf += self.lobes.pdf(theta_i, h, dr.zeros(mi.UInt32, dr.width(h)) + p, theta_o, dphi, P, light_out)
        return dr.select(active & ~inside, pdf / dr.maximum(dr.cos(theta_o), 1e-6), 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        frame, phi_i, theta_i, inside = self._setup(si)
        h, _, _ = self._offset(si, frame)
        u0, u1 = split_uniform(sample1)
        p, theta_o, dphi, pdf = self.lobes.sample(theta_i, h, [u0, u1, sample2.x, sample2.y],
                                                  self._choice(si, theta_i, h),
                                                  light_out=ctx.mode == mi.TransportMode.Radiance)
        wo_world = direction(phi_i + dphi, theta_o, frame)
        f = self._path_value(ctx, h, p, theta_i, theta_o, dphi)
        pdf = pdf / dr.maximum(dr.cos(theta_o), 1e-6)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = dr.select(inside, -si.wi, si.to_local(wo_world))
        bs.pdf = dr.select(inside, 1.0, pdf)
        bs.eta = 1.0
        bs.sampled_type = dr.select(inside, mi.UInt32(+(mi.BSDFFlags.Null | mi.BSDFFlags.DeltaTransmission)),
                                    mi.UInt32(+mi.BSDFFlags.GlossyTransmission))
        bs.sampled_component = dr.select(inside, mi.UInt32(self.n_paths), p)
        weight = dr.select(inside, 1.0, self._spectrum(f, si) / dr.maximum(pdf, 1e-20))
        ok = active & (inside | (pdf > 0))
        return bs, dr.select(ok & dr.isfinite(weight), weight, 0.0)

    def eval_attribute_3(self, name, si, active=True):
        """``exit_<p>``: the world outward normal where path ``p`` leaves (zero for the
        residual, which has no single exit, and for other names)."""
        zero = dr.zeros(mi.Color3f, dr.width(si.t))
        if not name.startswith("exit_") or not name[5:].isdigit() or int(name[5:]) >= self.lobes.p_max:
            return zero
        p = int(name[5:])
        frame, _, theta_i, _ = self._setup(si)
        h, n, _ = self._offset(si, frame)
        nx, nz = self.lobes.exit_normal(n.x, n.y, dr.zeros(mi.UInt32, dr.width(h)) + p, h, theta_i, dr)
        x, _, z = frame
        w = nx * x + nz * z
        return mi.Color3f(w.x, w.y, w.z)

    def eval_attribute_1(self, name, si, active=True):
        if name == "paths":
            return dr.zeros(mi.Float, dr.width(si.t)) + self.n_paths
        return super().eval_attribute_1(name, si, active)

    def has_attribute(self, name, active=True):
        return name in ("passthrough", "radius", "paths") or name.startswith("exit_")

    def to_string(self):
        return f"FiberRayBSDF[paths={self.n_paths}, wavelengths={len(self.wavelength)}]"


PLUGINS = {"fiber_bundle": FiberBundleBSDF, "fiber_table": FiberTableBSDF, "fiber_ray": FiberRayBSDF}
