"""The Mitsuba plugins: ``fiber_bundle`` (table, jitted MLP, ONNX) and ``bundle_path``.

References: Mitsuba's own chi-square test for sample/pdf, Mitsuba's ``path`` integrator
on ordinary BSDFs, a white-furnace closed form from the table's energy balance, and
the numpy lookup of the table for ``eval``.
"""

import numpy as np
import pytest

from models.bundle_table import BundleTable, lookup
from tests.synthetic import make_config, synthetic_table


@pytest.fixture(scope="module")
def mi_plug(mi_llvm):
    import mitsuba_ext

    mitsuba_ext.register()
    return mi_llvm


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plugin")
    cfg = make_config(tmp)
    circle, ellipse = tmp / "circle.npz", tmp / "ellipse.npz"
    synthetic_table(cfg, circle, relative=True, passthrough=0.3)
    synthetic_table(cfg, ellipse, relative=False, passthrough=0.2)
    return {"circle": circle, "ellipse": ellipse}


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


def wi_of(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return [np.cos(t) * np.cos(p), np.sin(t), np.cos(t) * np.sin(p)]


@pytest.mark.parametrize("which,backend", [("circle", "table"), ("ellipse", "table"), ("circle", "mlp")])
@pytest.mark.parametrize("theta,phi", [(0, 90), (40, 20), (-75, 160)])  # wi.z > 0: from outside
def test_sampling_passes_mitsuba_chi2(mi_plug, tables, trained, which, backend, theta, phi):
    mi = mi_plug
    from mitsuba.chi2 import ChiSquareTest

    if backend == "mlp":
        _, tmp = trained
        props = {"type": "fiber_bundle", "backend": "mlp", "model": str(tmp / "n/export/tiny/weights.npz")}
    else:
        props = {"type": "fiber_bundle", "table": str(tables[which])}
    bsdf = mi.load_dict({**props, "passthrough": False, "up": [1.0, 0.0, 0.0]})
    sample, pdf = chi2_adapter(mi, bsdf, wi_of(theta, phi))
    # cells: table 36 x 18 or model grid 72 x 36, relative to phi_i for a circle
    phi0 = (np.radians(phi) if which == "circle" else 0.0) - np.pi
    test = ChiSquareTest(domain=BundleDomain(phi0), sample_func=sample, pdf_func=pdf,
                         sample_dim=3, sample_count=500_000, res=144, ires=6, seed=3)
    assert test.run(), test.messages


def test_passthrough_is_a_null_lobe_with_the_baked_probability(mi_plug, tables):
    import drjit as dr

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


@pytest.mark.parametrize("which", ["circle", "ellipse"])
def test_eval_is_the_table_lookup_in_the_bundle_frame(mi_plug, tables, which):
    """eval in rgb = the numpy multilinear lookup, seen through the D65 sRGB weights."""
    import drjit as dr

    from mitsuba_ext.bsdf import spectral_weights

    mi = mi_plug
    table = BundleTable.load(tables[which], expand=True)
    bsdf = mi.load_dict({"type": "fiber_bundle", "table": str(tables[which]), "up": [1.0, 0.0, 0.0]})
    rng = np.random.default_rng(1)
    n = 2000
    ti, to = rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n)
    pi_, po = rng.uniform(0, np.pi, n), rng.uniform(-np.pi, np.pi, n)  # wi from outside: z > 0
    si = local_si(mi, np.array(wi_of(np.degrees(ti), np.degrees(pi_))), n)
    value = np.array(bsdf.eval(mi.BSDFContext(), si, vec(mi, wi_of(np.degrees(to), np.degrees(po))))).T
    expected = lookup(table, pi_, ti, po, to) @ spectral_weights(table.wavelength, "rgb").T
    assert np.allclose(value, expected, rtol=2e-4, atol=1e-6 * expected.max())


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


def furnace_expected(table_path, theta_i=0.0):
    """Pixel value of a bundle seen at theta_i in a white environment: sum_k W_ck E_k + P."""
    from mitsuba_ext.bsdf import spectral_weights

    t = BundleTable.load(table_path, expand=True)
    k = int(np.argmin(np.abs(t.theta_i - theta_i)))
    E = t.scattered[:, k].mean(0)  # over phi_i nodes (a circle has one)
    return spectral_weights(t.wavelength, "rgb") @ E + t.passthrough.mean()


def test_white_furnace_matches_the_tables_energy_balance(mi_plug, tables):
    """A bundle in a uniform white sky: each pixel sees scattered + passthrough energy."""
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


def test_passthrough_shadow_transmittance_is_unbiased(mi_plug, tables):
    """NEE through bundles (bundle_path) and BSDF sampling alone (path) agree on average."""
    mi = mi_plug
    bundle = {"type": "fiber_bundle", "table": str(tables["circle"])}
    scene = scene_dict({"type": "bundle_path", "max_depth": 6, "displaced_exit": False}, bundle, spp=256, res=(24, 16))
    a = np.array(mi.render(mi.load_dict(scene)))
    scene["integrator"] = {"type": "path", "max_depth": 6}
    b = np.array(mi.render(mi.load_dict(scene)))
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    assert abs(a.mean() / b.mean() - 1) < 0.03, (a.mean(), b.mean())
