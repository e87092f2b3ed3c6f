"""The Mitsuba plugins: ``fiber_bundle`` (table, jitted MLP, ONNX) and ``bundle_path``.

References: Mitsuba's own chi-square test for sample/pdf, Mitsuba's ``path`` integrator
on ordinary BSDFs, a white-furnace closed form from the table's energy balance, and
the numpy lookup of the table for ``eval``.
"""

import numpy as np
import pytest

from models.bundle_table import BundleTable, lookup
from tests.synthetic import make_config, synthetic_table


@pytest.fixture
def mi_plug(mi_plugins):
    return mi_plugins


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plugin")
    cfg = make_config(tmp)
    circle, ellipse, cone = tmp / "circle.npz", tmp / "ellipse.npz", tmp / "cone.npz"
    synthetic_table(cfg, circle, relative=True, passthrough=0.3)
    synthetic_table(cfg, ellipse, relative=False, passthrough=0.2)
    # the cone layout's theta_o bins: 5 deg on each cone, 10 between (edges on the 2.5-deg
    # cells of the chi-square test, which integrates the pdf over its cells)
    synthetic_table(cfg, cone, relative=True, passthrough=0.3, cone=5.0)
    # the circle with a near field: 8 offset cells, each the table times its own azimuthal
    # wave (their mean the table), and a passthrough per cell
    near = tmp / "near.npz"
    t = BundleTable.load(circle)
    N, phase = 8, 2 * np.pi * np.arange(8) / 8
    wave = 1 + 0.8 * np.sin(t.phi_o[None, :] + phase[:, None])[:, None, None, :, None, None]
    t.near, t.near_stderr = (t.values[None] * wave).astype(np.float32), (t.stderr[None] * wave).astype(np.float32)
    t.near_passthrough = np.broadcast_to(0.3 + 0.2 * np.cos(phase), t.absorbed.shape[:2] + (N,)).copy()
    t.save(near)
    return {"circle": circle, "ellipse": ellipse, "cone": cone, "near": near}


def vec(mi, w):
    w = np.asarray(w, np.float32)
    return mi.Vector3f(*map(float, w)) if w.ndim == 1 else mi.Vector3f(*(mi.Float(c) for c in w))


def local_si(mi, wi, n):
    """Interactions with the bundle frame = shading frame (tangent +y, normal +z)."""
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.n = mi.Vector3f(0, 0, 1)
    si.wi = vec(mi, wi)
    return si


class BundleDomain:
    """mitsuba.chi2 domain: (phi_o, theta_o) of the bundle frame (x, t, z) = (+x, +y, +z).

    The bins of (phi, theta), not (phi, cos) as in ``SphericalDomain``: the sampling
    density is piecewise constant on (phi_o, theta_o) cells, so with bin edges on the
    cell edges (each cell split in 2 x 2 bins, phi from ``phi0``) the trapezoid
    integration of the pdf is accurate and the split still sees how samples fall
    inside a cell. The pdf functor multiplies by the Jacobian cos(theta).
    """

    def __init__(self, phi0):
        import mitsuba as mi

        self.phi0 = phi0
        self._bounds = mi.ScalarBoundingBox2f([phi0, -np.pi / 2], [phi0 + 2 * np.pi, np.pi / 2])

    def bounds(self):
        return self._bounds

    def aspect(self):
        return 2

    def map_forward(self, p):
        import drjit as dr
        import mitsuba as mi

        sp, cp = dr.sincos(p.x)
        st, ct = dr.sincos(p.y)
        return mi.Vector3f(ct * cp, st, ct * sp)

    def map_backward(self, w):
        import drjit as dr
        import mitsuba as mi

        phi = dr.atan2(w.z, w.x) - self.phi0
        phi = phi - dr.floor(phi / (2 * np.pi)) * 2 * np.pi + self.phi0
        return mi.Vector2f(phi, dr.safe_asin(dr.clip(w.y, -1, 1)))


def chi2_adapter(mi, bsdf, wi):
    def sample(s, *args):
        import drjit as dr

        si = local_si(mi, wi, dr.width(s))
        bs, w = bsdf.sample(mi.BSDFContext(), si, s[0], mi.Vector2f(s[1], s[2]))
        # a valid sample may carry zero weight where the MLP outputs exactly 0
        return bs.wo, dr.select(bs.pdf > 0, 1.0, 0.0)

    def pdf(wo, *args):
        import drjit as dr

        jacobian = dr.safe_sqrt(1 - dr.square(wo.y))
        return bsdf.pdf(mi.BSDFContext(), local_si(mi, wi, dr.width(wo)), wo) * jacobian
    return sample, pdf


def error_chain(exc) -> list:
    """The messages of an exception and of everything it was raised from (Mitsuba wraps a
    plugin's error in its own)."""
    chain = []
    while exc is not None:
        chain.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return chain


def wi_of(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return [np.cos(t) * np.cos(p), np.sin(t), np.cos(t) * np.sin(p)]


@pytest.mark.parametrize("which,backend", [("circle", "table"), ("ellipse", "table"), ("cone", "table"),
                                           ("near", "table"), ("circle", "mlp")])
@pytest.mark.parametrize("theta,phi", [(0, 90), (40, 20), (-75, 160)])  # wi.z > 0: from outside
def test_sampling_passes_mitsuba_chi2(mi_plug, tables, trained, which, backend, theta, phi, tmp_path, monkeypatch):
    mi = mi_plug
    from mitsuba.chi2 import ChiSquareTest

    monkeypatch.chdir(tmp_path)  # a failing test writes chi2_data.py into the working directory

    if backend == "mlp":
        _, tmp = trained
        props = {"type": "fiber_bundle", "backend": "mlp", "model": str(tmp / "n/export/tiny/weights.npz")}
    else:
        props = {"type": "fiber_bundle", "table": str(tables[which])}
    bsdf = mi.load_dict({**props, "passthrough": False, "up": [1.0, 0.0, 0.0]})
    sample, pdf = chi2_adapter(mi, bsdf, wi_of(theta, phi))
    # cells: table 36 x 18 or model grid 72 x 36, relative to phi_i for a circle
    phi0 = (np.radians(phi) if which != "ellipse" else 0.0) - np.pi
    test = ChiSquareTest(domain=BundleDomain(phi0), sample_func=sample, pdf_func=pdf,
                         sample_dim=3, sample_count=500_000, res=144, ires=6, seed=3)
    assert test.run(), test.messages


def test_passthrough_is_a_null_lobe_with_the_baked_probability(mi_plug, tables):
    mi = mi_plug
    bsdf = mi.load_dict({"type": "fiber_bundle", "table": str(tables["circle"])})
    n = 200_000
    si = local_si(mi, wi_of(20, 60), n)
    rng = np.random.default_rng(0)
    bs, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n)), mi.Vector2f(rng.random((2, n))))
    passed = np.asarray(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null))
    assert abs(passed.mean() - 0.3) < 4 * np.sqrt(0.3 * 0.7 / n)
    wo = np.array(bs.wo)[:, passed]
    assert np.allclose(wo, -np.array(wi_of(20, 60))[:, None], atol=1e-6)
    assert np.allclose(np.array(w)[:, passed], 1.0)
    # a ray arriving from inside the shape (wi below the surface) always passes
    inside = local_si(mi, [0.3, 0.1, -0.9], 8)
    assert np.allclose(np.asarray(bsdf.eval_attribute_1("passthrough", inside)), 1.0)
    assert np.all(np.asarray(bsdf.eval(mi.BSDFContext(), inside, mi.Vector3f(0, 0, 1))) == 0)


def test_passthrough_follows_theta_i_where_the_table_has_it(mi_plug, tables, tmp_path):
    """A twisted ply's table holds P_pass per (phi_i, theta_i): the plugin reads it at the
    light's theta_i, linearly between nodes, held beyond the last, and the table's energy
    balance counts it per theta_i."""
    mi = mi_plug
    t = BundleTable.load(tables["circle"])  # theta_i 0..90 by 15, mirror-reduced
    t.passthrough_theta = (0.1 + 0.5 * np.sin(t.theta_i) ** 2)[None, :]
    t.passthrough = t.passthrough_theta.mean(1)
    t.save(tmp_path / "twisted.npz")
    back = BundleTable.load(tmp_path / "twisted.npz", expand=True)   # mirrored: P(-theta) = P(theta)
    assert np.allclose(back.passthrough_theta[0], 0.1 + 0.5 * np.sin(back.theta_i) ** 2)
    assert np.allclose(back.energy_balance()["passthrough"][..., 0], back.passthrough_theta)
    bsdf = mi.load_dict({"type": "fiber_bundle", "table": str(tmp_path / "twisted.npz")})
    for theta in (0.0, 30.0, -45.0, 52.5, 89.0):
        si = local_si(mi, wi_of(theta, 60), 4)
        nodes = np.rad2deg(back.theta_i)
        want = np.interp(theta, nodes, back.passthrough_theta[0])
        assert np.allclose(np.asarray(bsdf.eval_attribute_1("passthrough", si)), want, atol=1e-5), theta


@pytest.mark.parametrize("which", ["circle", "ellipse"])
def test_eval_is_the_table_lookup_in_the_bundle_frame(mi_plug, tables, which):
    """eval in rgb = the numpy lookup with ``w_i`` the light side, seen through the D65 sRGB weights.

    Radiance mode (a path tracer): ``wo`` is the light side, so ``eval = S(wo -> si.wi)
    cos(theta_wo) / cos(theta_si.wi)`` (DESIGN's far-field closure); importance mode (a
    light tracer): ``si.wi`` is the light side and ``eval = S(si.wi -> wo)``.
    """
    from mitsuba_ext.frame import spectral_weights

    mi = mi_plug
    table = BundleTable.load(tables[which], expand=True)
    bsdf = mi.load_dict({"type": "fiber_bundle", "table": str(tables[which]), "up": [1.0, 0.0, 0.0]})
    rng = np.random.default_rng(1)
    n = 2000
    ti, to = rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n)
    pi_, po = rng.uniform(0, np.pi, n), rng.uniform(-np.pi, np.pi, n)  # wi from outside: z > 0
    si = local_si(mi, np.array(wi_of(np.degrees(ti), np.degrees(pi_))), n)
    wo = vec(mi, wi_of(np.degrees(to), np.degrees(po)))
    rgb = spectral_weights(table.wavelength, "rgb").T
    # the lookup jumps at bin edges; float32 directions land on either side there
    d = 1e-5
    jumps = np.ptp([lookup(table, po + a, to + b, pi_ + a, ti - b) for a in (-d, d) for b in (-d, d)], 0)
    smooth = np.all(jumps <= 1e-3 * lookup(table, po, to, pi_, ti) + 1e-9, -1)
    assert smooth.mean() > 0.9
    value = np.array(bsdf.eval(mi.BSDFContext(), si, wo)).T
    expected = (lookup(table, po, to, pi_, ti) @ rgb) * (np.cos(to) / np.cos(ti))[:, None]
    assert np.allclose(value[smooth], expected[smooth], rtol=2e-3, atol=1e-6 * expected.max())
    value = np.array(bsdf.eval(mi.BSDFContext(mi.TransportMode.Importance), si, wo)).T
    expected = lookup(table, pi_, ti, po, to) @ rgb
    assert np.allclose(value[smooth], expected[smooth], rtol=2e-3, atol=1e-6 * expected.max())


def scene_dict(integrator, shape_bsdf, *, spp=64, res=(48, 32), orthographic=False, seed=0):
    import mitsuba as mi

    to_world = mi.ScalarTransform4f().look_at([0, 0.4, 4], [0, 0, 0], [0, 1, 0])
    sensor = ({"type": "orthographic", "to_world": to_world @ mi.ScalarTransform4f().scale([0.5, 0.5, 1])}
              if orthographic else {"type": "perspective", "fov": 35, "to_world": to_world})
    sensor["film"] = {"type": "hdrfilm", "width": res[0], "height": res[1], "rfilter": {"type": "box"}}
    sensor["sampler"] = {"type": "independent", "sample_count": spp, "seed": seed}
    return {"type": "scene", "integrator": integrator, "sensor": sensor,
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.3, 0.3]}},
            "light": {"type": "rectangle", "to_world": mi.ScalarTransform4f().look_at([2, 3, 2], [0, 0, 0], [0, 1, 0]),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 8.0}}},
            "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, -1, 0]).rotate([1, 0, 0], -90)
                      .scale(3), "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}}},
            "body": {"type": "sphere", "center": [0.3, -0.3, 0], "radius": 0.5, "bsdf": shape_bsdf}}


def test_bundle_path_is_path_on_ordinary_bsdfs(mi_plug):
    mi = mi_plug
    metal = {"type": "roughconductor", "alpha": 0.2}
    a = np.array(mi.render(mi.load_dict(scene_dict({"type": "bundle_path", "max_depth": 8}, metal))))
    b = np.array(mi.render(mi.load_dict(scene_dict({"type": "path", "max_depth": 8}, metal))))
    c = np.array(mi.render(mi.load_dict(scene_dict({"type": "path", "max_depth": 8}, metal, seed=1))))
    # same sampler, same seed: the same estimates (float rounding of a different kernel)
    assert np.abs(a - b).max() < 1e-3 * max(1.0, b.max()), np.abs(a - b).max()
    assert np.abs(c - b).mean() > 100 * np.abs(a - b).mean()  # a different seed is far away


def furnace_expected(table_path, theta_c=0.0):
    """Pixel value of a bundle seen at ``theta_c`` in a white sky, by quadrature.

    The light from every ``w_l`` scattered towards the camera, per projected width:
    ``L = P + integral S(w_l -> w_c) cos(theta_l) / cos(theta_c) d omega_l``
    (DESIGN's far field ``I = E 2R cos(theta_l) S`` over the width ``2R cos(theta_c)``).
    """
    from mitsuba_ext.frame import spectral_weights
    from models.fiber.base import sphere_quadrature

    t = BundleTable.load(table_path, expand=True)
    T, P, W = sphere_quadrature(256, 256)  # weights of integral g cos(theta) d theta d phi
    S = lookup(t, P, T, 0.0, theta_c, mode="nearest")  # [..., lambda]
    E = np.einsum("tpl,tp->l", S, W * np.cos(T)) / np.cos(theta_c)
    return spectral_weights(t.wavelength, "rgb") @ E + t.passthrough.mean()


def test_white_furnace_matches_the_tables_energy_balance(mi_plug, tables):
    """A bundle in a uniform white sky: each pixel sees passthrough plus the sky scattered
    towards the camera (for a reciprocal table that is its albedo; this one is not)."""
    mi = mi_plug
    bundle = {"type": "fiber_bundle", "table": str(tables["circle"]), "lookup": "nearest"}
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "bundle_path"},
        "sensor": {"type": "orthographic", "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0])
                   @ mi.ScalarTransform4f().scale([0.3, 0.3, 1]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 512}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "cyl": {"type": "cylinder", "p0": [0, -2, 0], "p1": [0, 2, 0], "radius": 0.5, "bsdf": bundle}})
    img = np.array(mi.render(scene))
    inside = img[:, 8:24]  # the cylinder covers |x| < 0.5 of the 0.6 wide view: these columns see it
    expected = furnace_expected(tables["circle"], 0.0)
    assert np.all(np.isfinite(img))
    # orthographic view along -z: theta_i = 0 everywhere; 512 spp x 512 pixels
    assert np.allclose(inside.reshape(-1, 3).mean(0), expected, rtol=0.02), (inside.mean((0, 1)), expected)
    assert abs(expected.mean() - 1.0) > 0.05  # the check is not trivially "everything is white"


def row_of_plies(mi, table_path, spp, **integrator) -> np.ndarray:
    """Mean RGB of five touching plies in a row with the table at ``table_path``, lit from
    the side by a directional light (from below their axis, so that the camera is on the
    synthetic ridge's cone), under ``bundle_path`` with ``integrator``'s parameters: where
    the exit matters (the displaced exit sends light across a ply and past its
    neighbours' shadow)."""
    to_world = (mi.ScalarTransform4f().look_at([0, 1.5, 4], [0, 0, 0], [0, 1, 0])
                @ mi.ScalarTransform4f().scale([0.7, 0.7, 1]))
    scene = {"type": "scene", "integrator": {"type": "bundle_path", "max_depth": 8} | integrator,
             "sensor": {"type": "orthographic", "to_world": to_world,
                        "film": {"type": "hdrfilm", "width": 32, "height": 24, "rfilter": {"type": "box"}},
                        "sampler": {"type": "independent", "sample_count": spp}},
             "light": {"type": "directional", "direction": [0.9, 0.33, 0.1], "irradiance": {"type": "rgb",
                                                                                             "value": 3.0}}}
    for k, x in enumerate((-1.0, -0.5, 0.0, 0.5, 1.0)):
        scene[f"ply_{k}"] = {"type": "cylinder", "p0": [x, -2, 0], "p1": [x, 2, 0], "radius": 0.25,
                             "bsdf": {"type": "fiber_bundle", "table": str(table_path)}}
    img = np.array(mi.render(mi.load_dict(scene)), np.float64)
    assert np.all(np.isfinite(img))
    return img.reshape(-1, 3).mean(0)


def test_light_that_scattered_once_leaves_where_it_entered(mi_plug, tables, tmp_path):
    """``bundle_path``'s exit split against its two limits, which need no split: a row of
    touching plies lit from the side, where the exit matters (the displaced exit sends light
    across a ply and past its neighbours' shadow: 30% brighter here than leaving from the hit).
    A table whose light all scattered once (``single = scattered``) renders as
    ``displaced_exit`` off; none (``single = 0``) as the displaced exit; half as their mean
    (each wavelength's weight ``q / P`` or ``(1 - q) / (1 - P)``); ``exit_split`` ``"none"``
    (the default) ignores the share; ``"emitter"`` splits the shadow rays alone, which is all
    of it where the light arrives directly."""
    mi = mi_plug
    table = BundleTable.load(tables["circle"])
    paths = {}
    for q in (0.0, 0.5, 1.0):
        table.single = q * table.scattered
        paths[q] = tmp_path / f"share_{q}.npz"
        table.save(paths[q])

    def mean(q, **integrator):
        return float(row_of_plies(mi, paths[q], 256, **integrator).mean())

    entry, displaced = mean(0.0, displaced_exit=False), mean(0.0, exit_split="all")
    gap = displaced - entry
    assert gap > 0.2 * entry, (entry, displaced)  # the exits differ here
    assert abs(mean(1.0, exit_split="all") - entry) < 0.1 * gap
    assert abs(mean(0.5, exit_split="all") - 0.5 * (entry + displaced)) < 0.1 * gap
    assert abs(mean(1.0) - displaced) < 0.1 * gap  # off by default
    # direct light alone (one bounce, a directional light): "emitter" is all there is to split
    direct = {"max_depth": 2}
    entry, displaced = mean(0.0, displaced_exit=False, **direct), mean(0.0, exit_split="emitter", **direct)
    gap = displaced - entry
    assert gap > 0.1 * entry, (entry, displaced)
    assert abs(mean(1.0, exit_split="emitter", **direct) - entry) < 0.1 * gap


def test_each_wavelength_leaves_by_its_own_share(mi_plug, tables, tmp_path):
    """The exit split with a share that differs between wavelengths (all of the 450 nm
    light scattered once, half of 550, none of 650): one path chooses one exit for all its
    wavelengths with one probability ``P``, so each is weighted by its own ``q / P`` or
    ``(1 - q) / (1 - P)``. Under direct light alone (one bundle vertex) each channel must
    be the mixture of the two exits' renders in its own share, ``q_c entry + (1 - q_c)
    displaced``, whatever ``P`` was; ``q_c`` is the BSDF's ``single_share`` in that channel."""
    mi = mi_plug
    table = BundleTable.load(tables["circle"])
    paths = {}
    for name, q in (("none", [0.0, 0.0, 0.0]), ("all", [1.0, 1.0, 1.0]), ("graded", [1.0, 0.5, 0.0])):
        table.single = table.scattered * np.asarray(q)
        paths[name] = tmp_path / f"share_{name}.npz"
        table.save(paths[name])

    def image(name, **integrator):
        return row_of_plies(mi, paths[name], 512, **{"max_depth": 2, **integrator})

    bsdf = mi.load_dict({"type": "fiber_bundle", "table": str(paths["graded"])})
    si = local_si(mi, [0.0, 0.6, 0.8], 1)
    q = np.array(bsdf.eval_attribute("single_share", si, True), np.float64).ravel()
    assert q[2] > q[1] > q[0] and q[2] > 0.6 and q[0] < 0.4, q  # blue mostly single, red mostly not
    entry, displaced = image("none", displaced_exit=False), image("none", exit_split="emitter")
    gap = displaced - entry
    assert np.all(gap > 0.1 * entry), (entry, displaced)
    for split in ("emitter", "all"):
        graded = image("graded", exit_split=split)
        expected = q * entry + (1 - q) * displaced
        assert np.all(np.abs(graded - expected) < 0.1 * gap), (split, graded, expected, q)
    # and both limits, channel by channel
    assert np.all(np.abs(image("all", exit_split="emitter") - entry) < 0.1 * gap)


def test_passthrough_shadow_transmittance_is_unbiased(mi_plug, tables):
    """NEE through bundles (bundle_path) and BSDF sampling alone (path) agree on average."""
    from mitsuba_ext.crossing import tracing

    mi = mi_plug
    bundle = {"type": "fiber_bundle", "table": str(tables["circle"])}
    scene = scene_dict({"type": "bundle_path", "max_depth": 6, "displaced_exit": False}, bundle, spp=256, res=(24, 16))
    a = np.array(mi.render(mi.load_dict(scene)))
    scene["integrator"] = {"type": "path", "max_depth": 6}
    with pytest.raises(RuntimeError) as refused:
        mi.render(mi.load_dict(scene))  # a bundle under path is refused ...
    chain, e = [], refused.value
    while e is not None:  # mi.render wraps it: "error while performing a custom differentiable operation"
        chain.append(str(e))
        e = e.__cause__ or e.__context__
    assert any("integrator other than bundle_path" in text for text in chain), chain
    with tracing("any"):  # ... unless a reference knows what it leaves out (no displaced exit here)
        b = np.array(mi.render(mi.load_dict(scene)))
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    assert abs(a.mean() / b.mean() - 1) < 0.03, (a.mean(), b.mean())


def test_shadow_roulette_is_unbiased_through_many_bundles(mi_plug, tables):
    """A shadow ray across K bundles carries T = P_pass^K (each crossing at the same angles);
    with Russian roulette (``shadow_rr``) its mean over many rays is the same product."""
    import drjit as dr

    mi = mi_plug
    bundle = {"type": "fiber_bundle", "table": str(tables["circle"])}

    def transmittance(K, shadow_rr, n=200_000):
        scene = mi.load_dict({"type": "scene", **{
            f"c{k}": {"type": "cylinder", "p0": [0, -1, 0.5 * k], "p1": [0, 1, 0.5 * k], "radius": 0.2, "bsdf": bundle}
            for k in range(K)}})
        integrator = mi.load_dict({"type": "bundle_path", "shadow_rr": shadow_rr})
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(0, n)
        ray = mi.Ray3f(mi.Point3f(0.05, 0.1, -1.0), mi.Vector3f(0, 0, 1))
        ray.maxt = 100.0
        T = integrator._transmittance(scene, sampler, ray, dr.full(mi.Bool, True, n))
        return np.array(T)

    P = transmittance(1, 0.0)
    assert np.allclose(P, P[0]) and 0.2 < P[0] < 0.95, P[0]
    K = 4
    exact = transmittance(K, 0.0)
    assert np.allclose(exact, P[0] ** K, rtol=1e-4), (exact[0], P[0] ** K)
    T = transmittance(K, 0.3)
    survived = T > 0
    assert 0.002 < survived.mean() < 0.5, (P[0], survived.mean())  # the roulette ran
    se = T.std() / np.sqrt(len(T))
    assert abs(T.mean() - P[0] ** K) < 4 * se, (T.mean(), P[0] ** K, se)


def test_light_leaving_one_bundle_inside_another_meets_it(mi_plug, tables, tmp_path):
    """Interpenetrating plies (yarns in a knitted model overlap): a ray that starts inside a
    curve never hits it, so without ``bundle_path``'s ``overlaps`` a bundle is transparent
    to all light that leaves its neighbour inside it. Two overlapping curves A, B (centres
    0.34 apart, radius 0.2): a shadow ray across A whose far side lies inside B carries
    ``P_A P_B`` (each bundle met once, as if apart); one that starts inside B (where light
    leaving A would start it), ``P_B``.
    ``P`` of one crossing is measured alone (the same angles: the bundles are parallel)."""
    import drjit as dr

    mi = mi_plug
    bundle = {"type": "fiber_bundle", "table": str(tables["circle"]), "up": [0, 0, 1]}
    shapes = {f"c{k}": {"type": "bsplinecurve", "bsdf": bundle,
                        "filename": curve_file(tmp_path / f"c{k}.txt", [[x, y, 0, 0.2] for y in np.linspace(-2, 2, 6)])}
              for k, x in enumerate((-0.17, 0.17))}

    def transmittance(shape_names, origin, d, overlaps):
        scene = mi.load_dict({"type": "scene", **{k: shapes[k] for k in shape_names}})
        integrator = mi.load_dict({"type": "bundle_path", "shadow_rr": 0.0, "overlaps": overlaps})
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(0, 1)
        ray = mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*d))
        ray.maxt = 100.0
        # as the integrator sends a shadow ray from where light leaves a bundle of radius 0.2
        ray = integrator._backed(scene, ray, mi.Float(0.2), mi.Bool(True))
        return float(dr.ravel(integrator._transmittance(scene, sampler, ray, mi.Bool(True)))[0])

    P = transmittance(["c0"], [-1.0, 0.1, 0.0], [1, 0, 0], True)       # A alone, across its axis
    assert 0.05 < P < 0.95, P
    assert transmittance(["c1"], [-1.0, 0.1, 0.0], [1, 0, 0], True) == pytest.approx(P, rel=1e-4)
    both = ["c0", "c1"]
    assert transmittance(both, [-1.0, 0.1, 0.0], [1, 0, 0], True) == pytest.approx(P * P, rel=1e-3)
    assert transmittance(both, [0.25, 0.1, 0.0], [1, 0, 0], True) == pytest.approx(P, rel=1e-3)  # from inside B
    # without the rule: B unseen in both
    assert transmittance(both, [-1.0, 0.1, 0.0], [1, 0, 0], False) == pytest.approx(P, rel=1e-3)
    assert transmittance(both, [0.25, 0.1, 0.0], [1, 0, 0], False) == pytest.approx(1.0)


@pytest.fixture
def variant_guard(mi_plug):
    """Tests that switch variants put the session's variant (and plugins) back."""
    import drjit as dr

    import mitsuba_ext

    mi = mi_plug
    before = mi.variant()
    flags = dr.flag(dr.JitFlag.SymbolicLoops), dr.flag(dr.JitFlag.SymbolicCalls)
    yield mi
    dr.set_flag(dr.JitFlag.SymbolicLoops, flags[0])
    dr.set_flag(dr.JitFlag.SymbolicCalls, flags[1])
    mi.set_variant(before)
    mitsuba_ext.register()


def lit_cylinder(mi, bsdf, spp=128, res=(32, 24), max_depth=8):
    """A bundle on a cylinder under a grey sky and a white sun (no colour of their own)."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "bundle_path", "max_depth": max_depth},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.5, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res[0], "height": res[1], "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.2, 0.2, 0.2]}},  # D65 white
        "sun": {"type": "directional", "direction": [-0.4, -0.5, -1], "irradiance": {"type": "rgb", "value": [4.0, 4.0, 4.0]}},
        "cyl": {"type": "cylinder", "p0": [0, -2, 0], "p1": [0, 2, 0], "radius": 0.6, "bsdf": bsdf}})


def test_spectral_render_equals_mono_renders_combined_with_cie(variant_guard, tables):
    """Mitsuba's spectral variant against the thesis's way: one mono render per table
    wavelength, combined with CIE 1931 and D65 into sRGB."""
    import mitsuba_ext
    from mitsuba_ext.frame import spectral_weights

    mi = variant_guard
    table = BundleTable.load(tables["circle"])
    bsdf = {"type": "fiber_bundle", "table": str(tables["circle"])}
    mi.set_variant("llvm_ad_spectral")
    mitsuba_ext.register()
    spectral = np.array(mi.render(lit_cylinder(mi, bsdf, spp=512)))[..., :3]
    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    monos = np.stack([np.array(mi.render(lit_cylinder(mi, {**bsdf, "wavelength": float(wl)}, spp=512)))[..., 0]
                      for wl in table.wavelength])
    combined = np.einsum("ck,khw->hwc", spectral_weights(table.wavelength, "rgb"), monos)
    assert np.all(np.isfinite(spectral)) and np.all(np.isfinite(combined))
    cyl = combined[:, 10:22]  # the columns that see the cylinder
    ratio = spectral[:, 10:22].reshape(-1, 3).mean(0) / cyl.reshape(-1, 3).mean(0)
    assert np.allclose(ratio, 1.0, atol=0.02), ratio
    # the fibers do colour the image: red over blue, as the table's spectrum rises with lambda
    assert spectral[:, 10:22, 0].mean() > 1.1 * spectral[:, 10:22, 2].mean()


def test_onnx_and_jitted_mlp_renders_agree(variant_guard, trained):
    """The two neural backends render the same image to within the float32 rounding that
    each one's evaluation of the model allows, rendered alongside as an image of its own.

    With single scattering (max_depth 2: camera, bundle, light) and uniform direction
    sampling, the two renders trace the same paths (passthrough and sampling do not depend
    on the backend) and each pixel is ``sum_s a_s sum_k w_k S_k(q_s)``, linear in the model's
    values ``S_k`` at the queries ``q_s``. So the difference is at most ``sum_s a_s sum_k
    |w_k| 2 B_k(q_s)``, ``B`` the forward error bound of one float32 evaluation
    (:func:`models.neural.rounding_bound`): the same scene rendered with a backend that
    returns ``B`` and the spectral weights' absolute values. The arithmetic after the model
    (the spectrum's fma over the table's wavelengths, the adjoint factor, the division by the
    pdf, the emitter, MIS, the film's sum over ``spp`` samples and its normalization) rounds
    each render's value by at most ``gamma_n`` of ``sum_s a_s sum_k |w_k| S_k``, ``n`` those
    operations counted.
    """
    import drjit as dr

    from mitsuba_ext.neural import load_weights
    from models.neural import rounding_bound
    from models.rounding import gamma

    mi = variant_guard
    _, tmp = trained
    export = tmp / "n" / "export" / "wide"
    spec, layers, lines = load_weights(export / "weights.npz")
    dr.set_flag(dr.JitFlag.SymbolicLoops, False)  # onnxruntime needs evaluated mode
    dr.set_flag(dr.JitFlag.SymbolicCalls, False)
    # Uniform direction sampling: each backend tabulates its own sampling grid, and where a
    # random number falls within float rounding of a cell boundary of the CDF the other
    # backend picks the next cell, another direction, another path.
    spp = 32

    def render(backend, model, bound=False, absolute=False, zero=False):
        scene = lit_cylinder(mi, {"type": "fiber_bundle", "backend": backend, "sampling_uniform": 1.0,
                                  "model": str(export / model)}, spp=spp, max_depth=2)
        bsdf = scene.shapes()[0].bsdf()
        if absolute:  # the spectral weights' absolute values: sum_k |w_k| x_k bounds |sum_k w_k x_k|
            bsdf.weights = np.abs(np.asarray(bsdf.weights)).tolist()
        if bound:  # the model's values replaced by their float32 error bound at the same queries
            def eval_bound(*angles):
                dr.eval(*angles)
                q = np.stack(np.broadcast_arrays(*(np.asarray(a, np.float64) for a in angles)), -1)
                S_, B = rounding_bound(spec, layers, q, lines=lines)
                return [mi.Float(B[:, k].astype(np.float32)) for k in range(B.shape[1])]
            bsdf.backend.eval = eval_bound
        if zero:  # what reaches the camera without the model: the sky seen directly
            bsdf.backend.eval = lambda *angles: [dr.zeros(mi.Float, dr.width(angles[0]))] * len(spec.wavelength)
        return np.array(mi.render(scene), np.float64)

    jit, onnx = render("mlp", "weights.npz"), render("onnx", "model.onnx")
    # the bound's render less the light that never met the model (identical in every render)
    bound = np.maximum(render("onnx", "model.onnx", bound=True, absolute=True) - render("onnx", "model.onnx", zero=True),
                       0.0)
    magnitude = render("mlp", "weights.npz", absolute=True)
    assert np.all(np.isfinite(onnx)) and onnx.mean() > 0 and bound.max() > 0
    operations = len(spec.wavelength) + 8 + spp  # spectrum fma, 8 products and quotients, the film's sum
    tol = 2 * bound * (1 + gamma(operations)) + 2 * gamma(operations) * magnitude
    excess = np.abs(onnx - jit) - tol
    print(f"|onnx - jit| max {np.abs(onnx - jit).max():.3g}, its bound there {tol.flat[np.argmax(np.abs(onnx - jit))]:.3g}, "
          f"largest share of the bound used {np.max(np.abs(onnx - jit) / np.maximum(tol, 1e-30)):.3g}")
    assert np.all(excess <= 0), (np.abs(onnx - jit).max(), tol.max(), np.sum(excess > 0))


def test_onnx_backend_refuses_symbolic_mode(mi_plug, trained):
    mi = mi_plug
    _, tmp = trained
    with pytest.raises(Exception) as info:
        mi.render(lit_cylinder(mi, {"type": "fiber_bundle", "backend": "onnx",
                                    "model": str(tmp / "n/export/wide/model.onnx")}, spp=4, res=(8, 6)))
    chain = error_chain(info.value)
    assert any("evaluated mode" in m for m in chain), chain


def test_twist_rate_is_per_scene_unit_of_length(mi_plug, tables):
    """twist_rate (deg per scene unit) winds the major axis by the distance along the
    shape: 0.5 units from the start of a cylinder 2 long and of one 4 long is the same
    frame, and that of a constant twist of 0.5 x the rate."""
    mi = mi_plug
    path = str(tables["ellipse"])
    rng = np.random.default_rng(2)
    n = 64
    wi = np.array(wi_of(rng.uniform(-60, 60, n), rng.uniform(10, 170, n))).T
    wo = vec(mi, wi_of(rng.uniform(-80, 80, n), rng.uniform(-180, 180, n)))

    def eval_at(length, bsdf, at=0.5):
        """Hits on a cylinder along +y (bundle frame = shading frame) at ``at`` from p0."""
        scene = mi.load_dict({"type": "scene", "c": {"type": "cylinder", "p0": [0, 0, 0], "p1": [0, length, 0],
                                                     "radius": 0.3, "bsdf": bsdf}})
        origin = mi.Point3f(np.zeros(n), np.full(n, at), np.full(n, 5.0))
        si = scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(0, 0, -1)), mi.RayFlags.All, True)
        si.wi = si.to_local(vec(mi, wi.T))
        return np.array(si.bsdf().eval(mi.BSDFContext(), si, si.to_local(wo)))

    rate = {"type": "fiber_bundle", "table": path, "twist_rate": 120.0}
    short, long_ = eval_at(2.0, rate), eval_at(4.0, rate)
    fixed = eval_at(4.0, {"type": "fiber_bundle", "table": path, "twist": 60.0})
    untwisted = eval_at(4.0, {"type": "fiber_bundle", "table": path})
    assert np.allclose(short, long_, rtol=1e-4, atol=1e-7)
    assert np.allclose(long_, fixed, rtol=1e-3, atol=1e-6)
    assert not np.allclose(long_, untwisted, rtol=0.05)  # the ellipse's table does depend on the twist


def test_traverse_exposes_what_a_user_edits(mi_plug, tables):
    """``mi.traverse`` lists fiber_bundle's orientation, radius and sampling share; an edit
    followed by ``update()`` renders as the plugin loaded with that value does, and a value
    outside its domain is refused by the update."""
    mi = mi_plug
    path = str(tables["ellipse"])
    rng = np.random.default_rng(3)
    n = 64
    wi = np.array(wi_of(rng.uniform(-60, 60, n), rng.uniform(10, 170, n))).T
    wo = vec(mi, wi_of(rng.uniform(-80, 80, n), rng.uniform(-180, 180, n)))

    def scene_of(**kw):
        return mi.load_dict({"type": "scene", "c": {"type": "cylinder", "p0": [0, 0, 0], "p1": [0, 2, 0],
                                                    "radius": 0.3, "bsdf": {"type": "fiber_bundle", "table": path,
                                                                            **kw}}})

    def query(scene):
        origin = mi.Point3f(np.zeros(n), np.full(n, 0.5), np.full(n, 5.0))
        si = scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(0, 0, -1)), mi.RayFlags.All, True)
        si.wi = si.to_local(vec(mi, wi.T))
        ctx = mi.BSDFContext()
        return (np.array(si.bsdf().eval(ctx, si, si.to_local(wo))),
                np.array(si.bsdf().pdf(ctx, si, si.to_local(wo))))

    scene = scene_of()
    params = mi.traverse(scene)
    keys = {k.split(".")[-1] for k in params.keys() if k.startswith("c.bsdf.")}
    assert {"twist", "twist_rate", "up", "radius", "sampling_uniform"} <= keys
    untwisted = query(scene)
    params["c.bsdf.twist"] = 60.0
    params["c.bsdf.sampling_uniform"] = 0.5
    params.update()
    edited = query(scene)
    loaded = query(scene_of(twist=60.0, sampling_uniform=0.5))
    assert np.allclose(edited[0], loaded[0], rtol=1e-5, atol=1e-8)
    assert np.allclose(edited[1], loaded[1], rtol=1e-5, atol=1e-8)
    assert not np.allclose(edited[0], untwisted[0], rtol=0.05)
    params["c.bsdf.radius"] = -1.0
    with pytest.raises(ValueError, match="radius"):
        params.update()
    params = mi.traverse(scene)
    params["c.bsdf.radius"] = 0.5  # the shape's radius rules: an edit would be silently ignored, so it is refused
    with pytest.raises(ValueError, match="edit the shape"):
        params.update()


@pytest.mark.parametrize("bad,message", [({"twist_rate": float("nan")}, "'twist_rate' must be finite"),
                                         ({"twist": float("inf")}, "'twist' must be finite"),
                                         ({"sampling_uniform": 1.5}, "'sampling_uniform' must be [0, 1]"),
                                         ({"sampling_uniform": -0.1}, "'sampling_uniform' must be [0, 1]"),
                                         ({"radius": -1.0}, "'radius' must be >= 0"),
                                         ({"lookup": "cubic"}, "lookup"),
                                         ({"table": "no/such/table.npz"}, "not found")])
def test_parameters_outside_their_domain_are_refused_at_load(mi_plug, tables, bad, message):
    with pytest.raises(Exception) as e:
        mi_plug.load_dict({"type": "fiber_bundle", "table": str(tables["circle"]), **bad})
    chain = error_chain(e.value)
    assert any(message in m for m in chain), chain


def test_files_resolve_against_the_scene_file(mi_plug, tables, tmp_path, monkeypatch):
    """As Mitsuba's own ``filename``s: a path relative to the XML scene, from any folder."""
    import shutil

    scene_dir = tmp_path / "scene"
    (scene_dir / "data").mkdir(parents=True)
    shutil.copy(tables["circle"], scene_dir / "data" / "ply.npz")
    (scene_dir / "ply.xml").write_text(
        '<scene version="3.0.0"><shape type="cylinder"><float name="radius" value="0.3"/>'
        '<bsdf type="fiber_bundle"><string name="table" value="data/ply.npz"/></bsdf></shape></scene>')
    monkeypatch.chdir(tmp_path)  # not the scene's folder
    scene = mi_plug.load_file(str(scene_dir / "ply.xml"))
    assert scene.shapes()[0].bsdf().backend.name == "table"


def test_bundles_on_other_shapes_and_disagreeing_radii_are_named(mi_plug, tables):
    from mitsuba_ext.crossing import check_bundles

    table = str(tables["circle"])
    scene = mi_plug.load_dict({
        "type": "scene",
        "ball": {"type": "sphere", "radius": 0.3, "bsdf": {"type": "fiber_bundle", "table": table}},
        "ply": {"type": "cylinder", "radius": 0.3, "bsdf": {"type": "fiber_bundle", "table": table, "radius": 0.2}},
        "ok": {"type": "cylinder", "p0": [2, 0, 0], "p1": [2, 1, 0], "radius": 0.3,
               "bsdf": {"type": "fiber_bundle", "table": table, "radius": 0.3}}})
    problems = check_bundles(scene)
    assert len(problems) == 2
    assert "'ball'" in problems[0] and "cylinder' and 'bsplinecurve' shapes only" in problems[0]
    assert "'ply'" in problems[1] and "0.2 disagrees" in problems[1] and "(0.3)" in problems[1]


def test_single_fibers_may_be_linear_curves_under_bundle_path_only(mi_plug, tables, tmp_path):
    """``fiber_table`` and ``fiber_ray`` take a ``linearcurve`` (bundle_path gives its hits the
    tangent frame), ``fiber_bundle`` does not (its twist runs along the curve's ``v``); under
    another integrator a fiber on a ``linearcurve`` is refused at the entry points."""
    from mitsuba_ext.crossing import check_bundles, check_integrator
    from models.fiber.ray import RayFiber

    RayFiber(np.array([450.0, 650.0]), [1.55, 1.54], [0.0, 0.0], 0.25, 0.4, 2.0, n_h=16).tabulate(
        np.deg2rad(np.arange(0, 91, 15.0))).save(tmp_path / "f.npz")
    line = curve_file(tmp_path / "l.txt", [[0, y, 0, 0.3] for y in np.linspace(-1, 1, 5)])

    def scene(integrator, **shapes):
        return mi_plug.load_dict({"type": "scene", "integrator": {"type": integrator},
                                  **{k: {"type": "linearcurve", "filename": line, "bsdf": b} for k, b in shapes.items()}})
    hair = {"type": "fiber_ray", "filename": str(tmp_path / "f.npz")}
    flat = {"type": "fiber_bundle", "table": str(tables["circle"])}
    problems = check_bundles(scene("bundle_path", hair=hair, flat=flat))
    assert len(problems) == 1 and "'flat'" in problems[0] and "(and 'linearcurve')" not in problems[0]
    assert check_integrator(scene("bundle_path", hair=hair)) is None
    assert "'linearcurve' need the bundle_path integrator" in check_integrator(scene("path", hair=hair))


def curve_file(path, points):
    path.write_text("\n".join(" ".join(f"{v:.6f}" for v in p) for p in points) + "\n")
    return str(path)


@pytest.mark.parametrize("case", ["curve", "degenerate_tangent", "grazing", "edge"])
def test_extremes_render_finite_images(mi_plug, tables, tmp_path, case):
    mi = mi_plug
    bundle = {"type": "fiber_bundle", "table": str(tables["ellipse"]), "radius": 0.3, "twist_rate": 180.0}
    if case in ("curve", "degenerate_tangent"):
        pts = [[np.cos(a) * 0.8, -1.5 + a / 2, np.sin(a) * 0.8, 0.3] for a in np.linspace(0, 6, 10)]
        if case == "degenerate_tangent":  # repeated control points: zero-length tangent on a segment
            pts = pts[:4] + [pts[4]] * 4 + pts[5:]
        shape = {"type": "bsplinecurve", "filename": curve_file(tmp_path / "c.txt", pts), "bsdf": bundle}
        eye = [0, 0.4, 5]
    else:
        shape = {"type": "cylinder", "p0": [0, -1, 0], "p1": [0, 1, 0], "radius": 0.3, "bsdf": bundle}
        # grazing: nearly along the axis onto the outer wall; edge: the silhouette fills the view
        eye = [0.6, 3.0, 0.0] if case == "grazing" else [0.29, 0, 4]
    target = {"grazing": [0, -1, 0], "edge": [0.29, 0, 0]}.get(case, [0, 0, 0])
    look = mi.ScalarTransform4f().look_at(eye, target, [0, 0, 1] if case == "grazing" else [0, 1, 0])
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "bundle_path", "max_depth": 12},
        "sensor": {"type": "perspective", "fov": 4 if case == "edge" else 40, "to_world": look,
                   "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 32}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.3, 0.3]}},
        "sun": {"type": "directional", "direction": [-0.3, -1, -0.6], "irradiance": {"type": "rgb", "value": 3.0}},
        "shape": shape})
    img = np.array(mi.render(scene))
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    assert np.abs(img - 0.3).max() > 0.01  # the bundle is visible, not just sky


def test_bad_parameters_are_refused_with_clear_errors(mi_plug, tables, trained, tmp_path):
    mi = mi_plug
    _, tmp = trained
    with pytest.raises(Exception, match="backend 'table' needs the parameter 'table'"):
        mi.load_dict({"type": "fiber_bundle"})
    with pytest.raises(Exception, match="use one of table, mlp, onnx"):
        mi.load_dict({"type": "fiber_bundle", "backend": "lut", "table": str(tables["circle"])})
    with pytest.raises(Exception, match="not a readable bundle table"):
        bad = tmp_path / "bad.npz"
        bad.write_bytes(b"not a table")
        mi.load_dict({"type": "fiber_bundle", "table": str(bad)})
    with pytest.raises(Exception, match="reads weights.npz"):
        mi.load_dict({"type": "fiber_bundle", "backend": "mlp", "model": str(tmp / "n/export/wide/model.onnx")})
    with pytest.raises(Exception, match="'up' must be a non-zero 3-vector"):
        mi.load_dict({"type": "fiber_bundle", "table": str(tables["circle"]), "up": [0.0, 0.0, 0.0]})


def test_wavelengths_outside_the_table(variant_guard, tables):
    """Mono: a wavelength outside the table is refused; spectral: held at the ends, finite."""
    import mitsuba_ext

    mi = variant_guard
    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    with pytest.raises(Exception, match="outside the table's 450..650 nm"):
        mi.load_dict({"type": "fiber_bundle", "table": str(tables["circle"]), "wavelength": 380.0})
    mi.set_variant("llvm_ad_spectral")
    mitsuba_ext.register()
    bsdf = mi.load_dict({"type": "fiber_bundle", "table": str(tables["circle"]), "up": [1.0, 0.0, 0.0]})
    si = local_si(mi, wi_of(10, 90), 1)
    si.wavelengths = mi.Spectrum(360.0, 450.0, 650.0, 830.0)
    v = np.array(bsdf.eval(mi.BSDFContext(), si, vec(mi, wi_of(-10, -90)))).ravel()
    assert np.all(np.isfinite(v)) and v[0] == pytest.approx(v[1]) and v[3] == pytest.approx(v[2])


def test_fiber_table_bsdf_matches_mitsuba_hair_with_light_and_camera_swapped(mi_plug, tmp_path):
    """One fiber on a curve, far-field intensity per unit length, against Mitsuba's own
    ``hair`` BSDF with the light and the camera exchanged.

    ``hair``'s ``eval(si.wi, wo)`` integrates to one over ``wo`` for a fixed ``si.wi``:
    it reads the camera side as incident, so seen from ``w_i`` and lit from ``w_o`` it
    sends ``I = E 2R cos(theta_i) f(w_i -> w_o)``, which is DESIGN's far field of ours
    lit from ``w_i`` and seen from ``w_o``. The ray model is not exactly reciprocal
    (docs/BENCHMARKS.md), so the unswapped comparison differs by a few per cent.
    """
    from models.fiber.ray import RayFiber
    from pipeline import closure

    mi = mi_plug
    wl = np.array([450.0, 550.0, 650.0])
    table = RayFiber(wl, [1.55] * 3, [0.0] * 3, 0.3, 0.3, 2.0, n_h=64).tabulate(np.deg2rad(np.arange(0, 91, 5.0)))
    table.save(tmp_path / "fiber.npz")
    R, hs = 0.05, 0.1
    curve = curve_file(tmp_path / "f.txt", [[0, y, 0, R] for y in np.linspace(-2, 2, 6)])
    hair = {"type": "hair", "int_ior": 1.55, "ext_ior": 1.0, "sigma_a": {"type": "rgb", "value": [0, 0, 0]},
            "longitudinal_roughness": 0.3, "azimuthal_roughness": 0.3, "scale_tilt": 2.0}
    ours = {"type": "fiber_table", "filename": str(tmp_path / "fiber.npz"), "up": closure.UP}

    def intensity(bsdf, w_light, w_camera):
        shapes = {"fiber": {"type": "bsplinecurve", "filename": curve, "bsdf": bsdf}}
        sc = closure.scene(mi, shapes, w_light, w_camera, hs, resolution=48, spp=16, max_depth=2)
        sc["integrator"] = {"type": "path", "max_depth": 2}
        return closure.rendered_intensity(mi, sc, w_camera, hs)

    # (phi_i, theta_i, phi_o, theta_o) in degrees: R, TT and sideways, on and off the cone
    pairs = [(10, 30, 25, -30), (10, 30, 25, -15), (40, -20, 210, 20), (40, -20, 215, 35), (0, 50, 90, -40)]
    ratios, unswapped = [], []
    for pi_, ti, po, to in pairs:
        w_i, w_o = closure.direction(*np.deg2rad([pi_, ti])), closure.direction(*np.deg2rad([po, to]))
        reference = intensity(hair, w_o, w_i)
        ratios.append(intensity(ours, w_i, w_o) / reference)
        unswapped.append(intensity(hair, w_i, w_o) / reference)
    print("ours / hair swapped:", np.round(ratios, 4), " hair unswapped / swapped:", np.round(unswapped, 4))
    assert np.allclose(ratios, 1.0, atol=0.01)
    assert np.max(np.abs(np.array(unswapped) - 1)) > 0.02  # the swap matters for this model


@pytest.mark.parametrize("theta,phi", [(30, 90), (0, 45), (-60, 120)])
def test_fiber_table_sampling_passes_mitsuba_chi2(mi_plug, tmp_path, theta, phi, monkeypatch):
    """The single-fiber plugin samples its table's own importance sampler; its pdf is
    the sampler's density per d(theta) d(phi) turned into one per steradian."""
    from mitsuba.chi2 import ChiSquareTest

    monkeypatch.chdir(tmp_path)  # a failing test writes chi2_data.py into the working directory

    from models.fiber.ray import RayFiber

    mi = mi_plug
    wl = np.array([450.0, 650.0])
    RayFiber(wl, [1.55, 1.54], [0.2, 0.1], 0.25, 0.4, 2.0, n_h=32).tabulate(
        np.deg2rad(np.arange(0, 91, 5.0))).save(tmp_path / "f.npz")
    bsdf = mi.load_dict({"type": "fiber_table", "filename": str(tmp_path / "f.npz"), "up": [1.0, 0.0, 0.0]})
    sample, pdf = chi2_adapter(mi, bsdf, wi_of(theta, phi))
    test = ChiSquareTest(domain=BundleDomain(np.radians(phi) - np.pi), sample_func=sample, pdf_func=pdf,
                         sample_dim=3, sample_count=300_000, res=72, ires=6, seed=2)
    assert test.run(), test.messages


def test_scene_xml_loads_the_plugins(mi_plug, tables):
    """`<bsdf type="fiber_bundle">` and `<integrator type="bundle_path">` in a scene file."""
    mi = mi_plug
    scene = mi.load_string(f"""<scene version="3.0.0">
        <integrator type="bundle_path"><integer name="max_depth" value="8"/></integrator>
        <sensor type="perspective">
            <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
            <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
        </sensor>
        <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
        <shape type="cylinder">
            <point name="p0" x="0" y="-2" z="0"/><point name="p1" x="0" y="2" z="0"/>
            <float name="radius" value="0.5"/>
            <bsdf type="fiber_bundle"><string name="table" value="{tables['circle']}"/></bsdf>
        </shape>
    </scene>""")
    img = np.array(mi.render(scene))
    assert np.all(np.isfinite(img)) and np.abs(img[:, 8] - 0.5).max() > 1e-3


# ----------------------------------------------------------------------------------
# fiber_ray: the h-resolved ray fiber samples what it evaluates
# ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dyed_ray_fiber(tmp_path_factory):
    """A ray fiber dyed red: blue absorbed along a chord, red nearly clear (as the glove's)."""
    from models.fiber.ray import RayFiber

    path = tmp_path_factory.mktemp("dyed") / "fiber.npz"
    RayFiber(np.array([450.0, 550.0, 650.0]), [1.55] * 3, [2.0, 0.5, 0.005], 0.25, 0.4, 2.0,
             n_h=32).tabulate(np.deg2rad(np.arange(0, 91, 5.0))).save(path)
    return path


def cylinder_hits(mi, bsdf: dict, theta_deg: float, n: int, seed: int):
    """``n`` hits on a unit cylinder along +y by parallel rays tilted ``theta_deg`` towards
    its axis, at offsets uniform across it: each hit's own ``h``. The scene is returned
    too: the hits point into its shapes, which must outlive them."""
    rng = np.random.default_rng(seed)
    t = np.radians(theta_deg)
    d = np.array([0.0, np.sin(t), -np.cos(t)])
    o = np.stack([rng.uniform(-0.999, 0.999, n), np.zeros(n), np.zeros(n)], 1) - 10 * d[None]
    from pipeline import closure

    scene = mi.load_dict({"type": "scene", "c": closure.cylinder(1.0, bsdf, half_length=40.0)})
    ray = mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*np.tile(d, (n, 1)).T.astype(np.float32)))
    si = scene.ray_intersect(ray)
    assert np.all(np.array(si.is_valid()))
    return scene, si, rng


@pytest.mark.parametrize("theta", [0, 30, 60])
def test_fiber_ray_weights_follow_what_it_evaluates(mono, dyed_ray_fiber, theta):
    """A render at 650 nm through the red-dyed fiber: ``sample``'s weights ``f / pdf``
    average to the integral of ``eval`` over the sphere (an independent quadrature: uniform
    directions), and their second moment is within 15% of the mean's square: the path is
    chosen by the attenuation at the wavelength the render carries (not the table's
    spectral mean: long paths, dark in blue, were drawn too rarely and weighed up to
    ~30x) and the azimuth is drawn about the light side's lobe (which ``eval`` reads),
    not the camera side's. Either mistake multiplies the weights' spread, and a path's
    dozens of bounces in a ply multiply it again: the explicit ply's fireflies."""
    import drjit as dr

    mi = mono
    bsdf = {"type": "fiber_ray", "filename": str(dyed_ray_fiber), "wavelength": 650.0, "up": [0, 0, 1]}
    n = 400_000
    scene, si, rng = cylinder_hits(mi, bsdf, theta, n, seed=theta)
    fiber = si.bsdf()
    ctx = mi.BSDFContext()
    _, w = fiber.sample(ctx, si, mi.Float(rng.uniform(size=n).astype(np.float32)),
                        mi.Vector2f(*rng.uniform(size=(2, n)).astype(np.float32)))
    w = np.array(w, np.float64).ravel()
    # the integral of eval over the sphere: the same hits, directions uniform on the sphere
    wo = mi.warp.square_to_uniform_sphere(mi.Vector2f(*rng.uniform(size=(2, n)).astype(np.float32)))
    f = np.array(fiber.eval(ctx, si, si.to_local(wo)), np.float64).ravel() * (4 * np.pi)
    se = np.hypot(w.std(), f.std()) / np.sqrt(n)
    print(f"theta {theta}: E[w] {w.mean():.4f}, integral of eval {f.mean():.4f} +- {se:.4f}, "
          f"E[w^2] / E[w]^2 {np.mean(w ** 2) / w.mean() ** 2:.3f}, max {w.max():.1f}")
    assert np.all(np.isfinite(w)) and dr.width(si.t) == n and scene is not None
    assert abs(w.mean() - f.mean()) < 4 * se + 0.005 * f.mean()
    assert np.mean(w ** 2) < 1.15 * w.mean() ** 2


@pytest.mark.parametrize("theta,phi", [(30, 90), (10, 40), (-60, 150)])
def test_fiber_ray_sampling_passes_mitsuba_chi2(mono, dyed_ray_fiber, theta, phi, tmp_path, monkeypatch):
    """``fiber_ray``'s ``sample`` draws from its ``pdf`` (radiance mode: the azimuthal lobe
    about the sampled light side's Bravais index, the path by the rendered wavelength),
    at offsets ``h`` that the incident azimuth sets (the normal is fixed)."""
    from mitsuba.chi2 import ChiSquareTest

    monkeypatch.chdir(tmp_path)  # a failing test writes chi2_data.py into the working directory
    mi = mono
    bsdf = mi.load_dict({"type": "fiber_ray", "filename": str(dyed_ray_fiber), "wavelength": 650.0,
                         "up": [1.0, 0.0, 0.0]})
    sample, pdf = chi2_adapter(mi, bsdf, wi_of(theta, phi))
    test = ChiSquareTest(domain=BundleDomain(np.radians(phi) - np.pi), sample_func=sample, pdf_func=pdf,
                         sample_dim=3, sample_count=300_000, res=72, ires=6, seed=2)
    assert test.run(), test.messages
