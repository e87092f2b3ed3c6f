"""Radiometric closure: every path that makes pixels reproduces the far field it was given.

DESIGN's test (``pipeline.closure``): a long cylinder under a directional light from
``w_i``, an orthographic camera along ``w_o``, box filter; the intensity per unit length
``sum(pixels) * pixel_area / visible_length`` must equal ``E 2R cos(theta_i) S(w_i -> w_o)``
with ``S`` what the renderer was given: the fiber model (one explicit fiber with
``fiber_table``), the bundle's table or its MLP (``fiber_bundle``, each backend against
its own evaluation), and, for explicit fibers in a ply, the bake of that ply. The
directions: on and off the specular cone, backwards, sideways, obliquely forward and
grazing (``closure.direction_pairs``), never exactly forward.
"""

import numpy as np
import pytest

from models.bundle_table import BundleTable, lookup
from pipeline import closure
from tests.synthetic import make_config, synthetic_table

WL = np.array([450.0, 550.0, 650.0])
NODES = np.deg2rad(np.arange(0, 91, 5.0))
LAM = 550.0


def pairs_deg(n_min=20, offsets=(0.0, 1.5, -3.0)):
    pairs = closure.direction_pairs(cone_offsets_deg=offsets)
    assert len(pairs) >= n_min
    return pairs


def ratios(mi, bsdf, R, S_of, pairs, twist_deg=0.0, evaluated=False):
    """rendered / predicted for every direction pair (radians; ``closure.far_field_ratios``);
    a constant twist turns the bundle frame, ``phi_bundle = phi + twist``."""
    tw = np.deg2rad(twist_deg)
    rows = closure.far_field_ratios(mi, bsdf, R, lambda pi_, ti, po, to: S_of(pi_ + tw, ti, po + tw, to), pairs,
                                    evaluated)
    assert len(rows) == len(pairs), "a pair was left out as not continuous"
    return np.array([row[3] for row in rows])


# ----------------------------------------------------------------------------------
# One explicit fiber: fiber_table against the fiber model
# ----------------------------------------------------------------------------------

def fiber_models():
    from models.fiber.mie import MieFiber
    from models.fiber.patterns import PatternFiber
    from models.fiber.ray import RayFiber

    return {
        "mie": lambda: MieFiber(WL, 3.0, [1.56, 1.555, 1.55], [1e-3, 0.0, 0.0], 3.0).tabulate(NODES),
        "ray": lambda: RayFiber(WL, [1.56] * 3, [0.3, 0.1, 0.0], 0.3, 0.3, 2.0, n_h=64).tabulate(NODES),
        "grid": lambda: PatternFiber(WL, "grid", n_stripes_theta=6, n_stripes_phi=8, albedo=0.9).tabulate(NODES),
        "isotropic": lambda: PatternFiber(WL, "isotropic").tabulate(NODES),
        "table": dense_table,
    }


def dense_table():
    """A measured-style fiber (``fiber.model: table``): the ray model on a dense grid, via npz."""
    import tempfile
    from pathlib import Path

    from models.fiber.ray import RayFiber
    from models.fiber.table import load_npz

    ray = RayFiber(WL, [1.5] * 3, [0.2, 0.1, 0.05], 0.4, 0.4, 0.0, n_h=32).tabulate(NODES)
    theta_o = np.deg2rad(np.arange(-90, 91, 2.0))
    phi = -np.pi + 2 * np.pi * np.arange(120) / 120
    TI, TO, P = np.meshgrid(NODES, theta_o, phi, indexing="ij")
    values = ray.eval_spectrum(TI, TO, P)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fiber.npz"
        np.savez(path, axes=np.array(["theta_i", "theta_o", "phi", "wavelength"]), values=values,
                 theta_i=NODES, theta_o=theta_o, phi=phi, wavelength=WL)
        return load_npz(path)


@pytest.mark.parametrize("model", ["mie", "ray", "grid", "isotropic", "table"])
def test_one_explicit_fiber_renders_its_model(mono, tmp_path, model):
    """``fiber_table`` on a cylinder: rendered / predicted within 1% (deterministic render)."""
    mi = mono
    table = fiber_models()[model]()
    table.save(tmp_path / "fiber.npz")
    bsdf = {"type": "fiber_table", "filename": str(tmp_path / "fiber.npz"), "wavelength": LAM, "up": closure.UP}
    # the grid's dark stripes (f = 0: nothing to compare) take more pairs to find 20 lit ones
    pairs = pairs_deg(offsets=(0.0, 1.5, -3.0, 4.5, 7.0, -6.0, -12.0) if model == "grid" else (0.0, 1.5, -3.0))
    # predicted from the model's numpy evaluation; grazing light at 80 deg included
    S = closure.evaluator(mi, "fiber", tmp_path / "fiber.npz", LAM)
    keep = closure.continuous(S, pairs) if model == "grid" else np.ones(len(pairs), bool)
    r = ratios(mi, bsdf, 0.02, S, pairs[keep])
    print(model, np.round(r, 4))
    assert keep.sum() >= 20
    assert np.allclose(r, 1.0, atol=0.01), r


def test_the_closure_scene_sees_no_fiber_end_at_nearly_axial_views(mono, tmp_path):
    """Views within 1.5 deg of the axis (the film then spans more than 80 film half sizes of
    it): the fiber must still fill the film, or the intensity reads 0.66 of the far field."""
    mi = mono
    fiber_models()["isotropic"]().save(tmp_path / "fiber.npz")
    bsdf = {"type": "fiber_table", "filename": str(tmp_path / "fiber.npz"), "wavelength": LAM, "up": closure.UP}
    S = closure.evaluator(mi, "fiber", tmp_path / "fiber.npz", LAM)
    pairs = np.deg2rad([[20.0, 30.0, 112.0, -88.8], [20.0, 45.0, 60.0, 88.8], [20.0, 88.0, 172.0, -88.8]])
    r = ratios(mi, bsdf, 0.02, S, pairs)
    print(np.round(r, 4))
    assert np.allclose(r, 1.0, atol=0.01), r


@pytest.mark.parametrize("shape", ["cylinder", "linearcurve"])
def test_one_explicit_h_resolved_fiber_renders_its_model(mono, tmp_path, shape):
    """``fiber_ray`` on a cylinder: each pixel evaluates the paths at its own offset h, and
    the far field over the fiber's width is the offset-averaged ray model (within 1%; the
    pixels across the fiber, 64 samples each, are the quadrature over h). Tilted and
    absorbing, at grazing light too: the light side's longitude sets Bravais' index and the
    attenuation, as in the table, or the far field is 0.44 .. 1.26 of it off the cone.
    The same on a ``linearcurve`` (the flyaways' shape), whose hits ``bundle_path`` gives
    their tangent frame (with Mitsuba's own frame there, which is not the tangent's: 0.78 .. 1.08)."""
    mi = mono
    table = fiber_models()["ray"]()
    table.save(tmp_path / "fiber.npz")
    bsdf = {"type": "fiber_ray", "filename": str(tmp_path / "fiber.npz"), "wavelength": LAM, "up": closure.UP}
    S = closure.evaluator(mi, "fiber", tmp_path / "fiber.npz", LAM)

    def polyline(R, b, half_length):  # a straight fiber along +y in 8 segments, the cylinder's axis
        points = tmp_path / "fiber.txt"
        points.write_text("".join(f"0 {y:.6f} 0 {R}\n" for y in np.linspace(-half_length, half_length, 9)))
        return {"type": "linearcurve", "filename": str(points), "bsdf": b}
    rows = closure.far_field_ratios(mi, bsdf, 0.02, S, pairs_deg(), spp=64,
                                    shape=polyline if shape == "linearcurve" else None)
    r = np.array([row[3] for row in rows])
    print("fiber_ray", np.round(r, 4))
    assert len(r) >= 20 and np.allclose(r, 1.0, atol=0.01), r


# ----------------------------------------------------------------------------------
# fiber_bundle: table, jitted MLP and ONNX, each against its own evaluation
# ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("closure")
    cfg = make_config(tmp)
    synthetic_table(cfg, tmp / "circle.npz", relative=True, passthrough=0.3)
    synthetic_table(cfg, tmp / "ellipse.npz", relative=False, passthrough=0.2)
    return {"circle": tmp / "circle.npz", "ellipse": tmp / "ellipse.npz"}


@pytest.mark.parametrize("which,twist", [("circle", 0.0), ("ellipse", 0.0), ("ellipse", 35.0)])
def test_bundle_table_backend_renders_its_table(mono, tables, which, twist):
    mi = mono
    bsdf = {"type": "fiber_bundle", "table": str(tables[which]), "wavelength": LAM, "up": closure.UP,
            "twist": twist}
    S = closure.evaluator(mi, "table", tables[which], LAM)
    tw = np.deg2rad(twist)
    # a table knows no position inside a bin: "on the cone" is read anywhere in its bin, and
    # pairs on a bin's edge (where the bin-average preserving lookup jumps) are left out
    pairs = pairs_deg(offsets=(0.0, 0.8, 1.5, -1.7, -3.0))
    pairs = pairs[closure.continuous(lambda pi_, ti, po, to: S(pi_ + tw, ti, po + tw, to), pairs)]
    assert len(pairs) >= 20
    r = ratios(mi, bsdf, 0.2, S, pairs, twist_deg=twist)
    print(which, twist, np.round(r, 4))
    assert np.allclose(r, 1.0, atol=0.01), r


def test_a_spectral_render_records_the_lookups_luminance(spectral, tables, tmp_path):
    """The luminance of a spectral render (Mitsuba samples wavelengths over 360-830 nm and
    weighs them by its own CIE y) against ``closure.luminance_weights`` applied to the
    lookup's spectrum: the measure ``make bench-highlight`` compares the highlight in. A
    weighting by the tabulated observer under D65 (what a mono render takes for
    luminance) reads this red-rising table 3-4% low, and fails."""
    mi = spectral
    from mitsuba_ext.frame import spectral_weights

    # the synthetic table, dyed: it scatters 5% in blue, 40% in green of what it does in red
    t = BundleTable.load(tables["circle"])
    dye = np.array([0.05, 0.4, 1.0])
    t.absorbed = t.absorbed + t.scattered * (1 - dye)   # what the dye takes is absorbed
    t.values, t.stderr = t.values * dye, t.stderr * dye
    t.save(tmp_path / "dyed.npz")
    bsdf = {"type": "fiber_bundle", "table": str(tmp_path / "dyed.npz"), "up": closure.UP}
    S = closure.evaluator(mi, "table", tmp_path / "dyed.npz", None)
    pairs = pairs_deg(offsets=(0.8, -1.7))
    rows = closure.far_field_ratios(mi, bsdf, 0.2, S, pairs, spp=64)
    r = np.array([row[3] for row in rows])
    print(np.round(r, 4))
    assert len(r) >= 12 and np.allclose(r, 1.0, atol=0.01), r
    # the power: the luminance of the tabulated observer under D65 (a mono render's), or the
    # mean over the table's wavelengths, differs from the spectral film's here
    t = BundleTable.load(tmp_path / "dyed.npz", expand=True)
    spectrum = lookup(t, *np.asarray(pairs).T)
    y_film = spectrum @ closure.luminance_weights(mi, t.wavelength)
    for wrong in (spectral_weights(t.wavelength, "mono")[0], np.full(len(t.wavelength), 1 / len(t.wavelength))):
        assert np.median(np.abs(spectrum @ wrong / y_film - 1)) > 0.03


@pytest.mark.parametrize("models", ["trained", "trained_lines", "trained_azimuth"])
@pytest.mark.parametrize("backend", ["mlp", "onnx"])
def test_bundle_neural_backends_render_their_model(request, mono, backend, models):
    """The plugin renders what its model evaluates (plain MLP; with feature lines, and with
    the gain resolved by azimuth: gathers traced into the render's kernel)."""
    mi = mono
    cfg, root = request.getfixturevalue(models)
    size = sorted(cfg.train.models)[0]
    path = root / cfg.name / "export" / size / ("weights.npz" if backend == "mlp" else "model.onnx")
    bsdf = {"type": "fiber_bundle", "backend": backend, "model": str(path), "wavelength": LAM, "up": closure.UP}
    r = ratios(mi, bsdf, 0.2, closure.evaluator(mi, backend, path, LAM), pairs_deg(), evaluated=backend == "onnx")
    print(backend, np.round(r, 4))
    assert np.allclose(r, 1.0, atol=0.01), r


@pytest.mark.parametrize("which", ["circle", "ellipse"])
def test_passthrough_shows_the_background_times_p_pass(mono, tables, which):
    """Looking through the ply at a lit plane far behind it: the band shows ``P_pass`` of it
    (the plane subtends 1e-4 sr, so what the bundle scatters into view is negligible)."""
    mi = mono
    t = BundleTable.load(tables[which], expand=True)
    R, hs = 0.2, 0.3
    bsdf = {"type": "fiber_bundle", "table": str(tables[which]), "wavelength": LAM, "up": closure.UP}
    for phi, theta in [(0.3, 0.2), (1.4, -0.6), (2.5, 0.9)]:
        w_o = closure.direction(phi, theta)
        sc = closure.scene(mi, {"f": closure.cylinder(R, bsdf, half_length=40 * hs)}, -w_o, w_o, hs,
                           irradiance=0.0, background=1.0, spp=16)
        img = closure.render_image(mi, sc)
        n = img.shape[1]
        x = (np.arange(n) + 0.5) / n * 2 * hs - hs      # film x of each column (the axis runs up)
        band, clear = np.abs(x) < 0.9 * R, np.abs(x) > 1.1 * R
        assert img[:, clear].mean() == pytest.approx(1.0, rel=1e-3)
        expected = float(np.interp(phi % (2 * np.pi), t.phi_i, t.passthrough, period=2 * np.pi))
        assert img[:, band].mean() == pytest.approx(expected, abs=0.005), (phi, theta)


# ----------------------------------------------------------------------------------
# The table's lookup along the specular cone
# ----------------------------------------------------------------------------------

@pytest.mark.parametrize("cone", [False, True])
def test_table_lookup_keeps_its_bin_averages_and_moves_the_ridge_with_the_cone(tmp_path, cone):
    """Averaged over each of its own bins (6 x 6 points uniform in phi and sin theta), the
    lookup gives the bin values (relative L1 <= 3% on the bins holding 90% of the
    energy, albedo <= 0.5%); between theta_i nodes it keeps the nodes' blended albedo
    (<= 0.5%, grazing included: light shifted past a pole comes back over it) and one
    ridge on the cone, not two half ridges at the nodes' cones, within the narrowest bin
    (the cone layout's: the bin on the cone)."""
    from models.fiber.base import sphere_quadrature

    cfg = make_config(tmp_path)
    table = synthetic_table(cfg, tmp_path / "t.npz", relative=True, cone=3.0 if cone else None)
    t = BundleTable.load(tmp_path / "t.npz", expand=True)
    pe, te = t.phi_o_edges, t.theta_o_edges
    sub = (np.arange(6) + 0.5) / 6
    fp = (pe[:-1, None] + sub * np.diff(pe)[:, None]).ravel()
    s0, s1 = np.sin(te[:-1]), np.sin(te[1:])
    ft = np.arcsin((s0[:, None] + sub * (s1 - s0)[:, None]).ravel())
    P, T = np.meshgrid(fp, ft, indexing="ij")
    for j, ti in enumerate(t.theta_i):
        S = lookup(t, 0.0, ti, P, T).reshape(len(pe) - 1, 6, len(te) - 1, 6, -1).mean((1, 3))
        V = t.values[0, j].astype(float)
        E = (V * t.solid_angle[..., None]).sum(-1).ravel()
        order = np.argsort(E)[::-1]
        top = order[: np.searchsorted(np.cumsum(E[order]), 0.9 * E.sum()) + 1]
        l1 = np.abs(S - V).sum(-1).ravel()[top].sum() / V.sum(-1).ravel()[top].sum()
        albedo = (S * t.solid_angle[..., None]).sum((0, 1)) / (V * t.solid_angle[..., None]).sum((0, 1))
        assert l1 <= 0.03 and np.all(np.abs(albedo - 1) <= 0.005), (np.degrees(ti), l1, albedo)
    # between nodes
    TQ, PQ, W = sphere_quadrature(720, 144)
    for ti in np.deg2rad([7.5, 37.5, 71.0, 82.5, 88.0]):
        S = lookup(t, 0.0, ti, PQ, TQ)
        expected = np.array([np.interp(ti, t.theta_i, t.scattered[0, :, k]) for k in range(3)])
        assert np.einsum("tpl,tp->l", S, W) == pytest.approx(expected, rel=0.005)
        theta = np.linspace(-np.pi / 2, np.pi / 2, 3601)
        ridge = lookup(t, 0.0, ti, 0.0, theta)[:, 1]
        assert abs(theta[np.argmax(ridge)] + ti) < np.diff(te).min()  # the peak within a bin of -theta_i
    del table


def misses_on_the_cone(mi, bundle, fiber_path, tables: dict, cases) -> dict:
    """``{table name: [(lookup / explicit - 1, its 1 sigma), ...]}`` per ``(theta_i, dphi)``
    case (deg): the fibers of ``bundle``, each its own cylinder with ``fiber_table``, rendered
    with theta_o exactly on the specular cone (16 turns, each at its own azimuth across 10
    deg), against each table's lookup averaged over the same azimuths; sigma from the
    explicit views and the table's own error in the cone bins of the nodes its lookup blends."""
    import mitsuba_ext

    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    lam = list(WL).index(LAM)
    bsdf = {"type": "fiber_table", "filename": str(fiber_path), "wavelength": LAM, "up": closure.UP}
    spread = np.deg2rad(10.0) * ((np.arange(16) + 0.5) / 16 - 0.5)
    measured = closure.explicit_intensities(
        mi, bundle, bsdf, [(closure.direction(0.0, np.deg2rad(ti)),
                            [closure.direction(np.deg2rad(dp) + o, -np.deg2rad(ti)) for o in spread])
                           for ti, dp in cases], spp=8, resolution=32)
    misses = {}
    for name, t in tables.items():
        misses[name] = []
        for (ti, dp), (I, se) in zip(cases, measured):
            S = lookup(t, 0.0, np.deg2rad(ti), np.deg2rad(dp) + spread, -np.deg2rad(ti))[:, lam].mean()
            k_p = int(np.searchsorted(t.phi_o_edges, np.deg2rad(dp)) - 1)
            near = np.argsort(np.abs(t.theta_i - np.deg2rad(ti)))[:2]
            blended = near[:1] if np.isclose(t.theta_i[near[0]], np.deg2rad(ti)) else near
            rel = []
            for j in blended:  # the bin on (or, on an edge, below) the node's cone
                k_t = max(0, int(np.searchsorted(t.theta_o_edges, -t.theta_i[j] - 1e-9) - 1))  # a pole: its cap
                rel.append(t.stderr[0, j, k_p, k_t, lam] / t.values[0, j, k_p, k_t, lam])
            I_table = closure.predicted_intensity(1.0, bundle.bounding_radius * 1e-3, np.deg2rad(ti), S)
            misses[name].append((I_table / I - 1, np.hypot(max(rel), se / I)))
    print({k: np.round(v, 3).tolist() for k, v in misses.items()})
    return misses


def test_cone_layout_reads_the_highlight_where_equal_bins_miss_it(mono, tmp_path):
    """The highlight's resolution in small (``make bench-highlight`` measures the default
    ply): six ray-optics fibers (beta_m 0.1: longitudinal lobes of about 5 deg for R and
    2 deg for TT; a lobe narrower than the cone bin would be read low by its bin average,
    -7 to -11% at beta_m 0.05), every one its own cylinder
    with ``fiber_table``, rendered with theta_o exactly on the specular cone (16 turns of the
    arrangement, each at its own azimuth across a phi_o bin), against the table's lookup at
    the same directions. The cone layout (a 2-deg bin on each node's cone) agrees within
    5% + 3 standard errors at every node; 36 equal bins baked from the same paths (nearly
    the same bytes) put the cone on a bin edge and miss it by more (the test's power)."""
    import mitsuba as mi

    from models.bundle import poisson
    from models.fiber.ray import RayFiber
    from models.grid import cone_edges
    from tests.test_bake import bake

    fiber = RayFiber(WL, [1.56] * 3, [0.3, 0.1, 0.0], 0.1, 0.3, 0.0, n_h=64).tabulate(NODES)
    fiber.save(tmp_path / "fiber.npz")
    bundle = poisson((80.0, 80.0), 20.0, packing=0.4, seed=2)
    mi.set_variant("llvm_ad_rgb")  # the baker's own variant
    kw = dict(paths=1_000_000, theta_i=(20, 30, 60), n_phi_o=36)
    tables = {"cone": bake(bundle, fiber, n_theta_o=35, theta_o_edges=cone_edges(np.deg2rad(10), np.deg2rad(2)), **kw),
              "equal": bake(bundle, fiber, n_theta_o=36, **kw)}
    cases = [(ti, dp) for ti in (20.0, 30.0, 60.0) for dp in (95.0, 155.0)]   # middles of 10-deg phi_o bins
    misses = misses_on_the_cone(mi, bundle, tmp_path / "fiber.npz", tables, cases)
    cone, equal = np.array(misses["cone"]), np.array(misses["equal"])
    assert np.all(np.abs(cone[:, 0]) <= 0.05 + 3 * cone[:, 1]), cone
    assert np.sum(np.abs(equal[:, 0]) > 0.05 + 3 * equal[:, 1]) >= 3, equal


def test_graded_nodes_read_the_grazing_highlight_between_nodes(mono, tmp_path):
    """Between theta_i nodes near grazing (``make bench-highlight`` measures the default
    ply): a Mie fiber's azimuthal pattern moves faster with theta_i there than the blend of
    two nodes 10 deg apart follows. Fibers of 3 um, each its own cylinder with
    ``fiber_table``, rendered with theta_o exactly on the cone at theta_i 65, 72.5, 75, 77.5
    (16 turns, each at its own azimuth across 10 deg), against the lookup of tables baked
    with as many nodes, every 10 deg or graded (5 deg from 60 to 80): the graded table agrees
    within 5% + 3 standard errors at every direction, the 10-deg one misses most of them
    (the test's power; it also fails a Dr.Jit or numpy lookup that blends the wrong nodes)."""
    import mitsuba as mi

    from models.bundle import poisson
    from models.fiber.mie import MieFiber
    from models.grid import cone_edges
    from tests.test_bake import bake

    fiber = MieFiber(WL, 3.0, [1.56, 1.555, 1.55], [1e-3, 0.0, 0.0], 3.0).tabulate(NODES)
    fiber.save(tmp_path / "fiber.npz")
    bundle = poisson((24.0, 24.0), 3.0, packing=0.3, seed=2)
    mi.set_variant("llvm_ad_rgb")  # the baker's own variant
    nodes = {"every 10": (0, 10, 20, 30, 40, 50, 60, 70, 80, 90), "graded": (0, 15, 30, 45, 60, 65, 70, 75, 80, 90)}
    tables = {name: bake(bundle, fiber, paths=1_000_000, theta_i=t, n_phi_o=36, n_theta_o=35,
                         theta_o_edges=cone_edges(np.deg2rad(t), np.deg2rad(2))) for name, t in nodes.items()}
    cases = [(ti, dp) for ti in (65.0, 72.5, 75.0, 77.5) for dp in (35.0, 95.0, 155.0)]  # 10-deg phi_o bin middles
    misses = misses_on_the_cone(mi, bundle, tmp_path / "fiber.npz", tables, cases)
    graded, coarse = np.array(misses["graded"]), np.array(misses["every 10"])
    assert np.all(np.abs(graded[:, 0]) <= 0.05 + 3 * graded[:, 1]), graded
    assert np.sum(np.abs(coarse[:, 0]) > 0.05 + 3 * coarse[:, 1]) >= 6, coarse


def test_the_last_node_held_along_its_cone_reads_the_pole_gap(mono, tmp_path):
    """Between the last node and the pole the cone shrinks onto the fiber axis. A node at
    90 deg has no cone, only a polar cap holding the whole lobe; blended into the gap it
    reads the ridge far too bright (``make bench-highlight``: +30..+180% at 88.75 deg on the
    default ply). A table whose nodes stop at 87.5 holds that node's light along its cone
    instead. The 3-um Mie ply of the test above, theta_o exactly on the cone at theta_i 88.75
    (between the nodes 87.5 and 90) and 86.25 (between 85 and 87.5), three azimuths each:
    the held table within 5% + 3 standard errors everywhere, the one with a pole node
    outside at most of 88.75's."""
    import mitsuba as mi

    from models.bundle import poisson
    from models.fiber.mie import MieFiber
    from models.grid import cone_edges
    from tests.test_bake import bake

    fiber = MieFiber(WL, 3.0, [1.56, 1.555, 1.55], [1e-3, 0.0, 0.0], 3.0).tabulate(NODES)
    fiber.save(tmp_path / "fiber.npz")
    bundle = poisson((24.0, 24.0), 3.0, packing=0.3, seed=2)
    mi.set_variant("llvm_ad_rgb")  # the baker's own variant
    held_nodes = (0, 15, 30, 45, 60, 70, 75, 80, 85, 87.5)
    nodes = {"held": held_nodes, "pole node": held_nodes + (90,)}
    edges = cone_edges(np.deg2rad(held_nodes), np.deg2rad(2))  # the poles' cones are in either layout
    tables = {name: bake(bundle, fiber, paths=1_000_000, theta_i=t, n_phi_o=36, n_theta_o=len(edges) - 1,
                         theta_o_edges=edges) for name, t in nodes.items()}
    cases = [(ti, dp) for ti in (86.25, 88.75) for dp in (35.0, 95.0, 155.0)]
    misses = misses_on_the_cone(mi, bundle, tmp_path / "fiber.npz", tables, cases)
    held, pole = np.array(misses["held"]), np.array(misses["pole node"])
    assert np.all(np.abs(held[:, 0]) <= 0.05 + 3 * held[:, 1]), held
    assert np.sum(np.abs(pole[3:, 0]) > 0.05 + 3 * pole[3:, 1]) >= 2, pole


def test_bin_views_moved_by_a_random_share_of_their_strata_average_to_the_bin():
    """A light falling steeply across a bin (e-fold 2.3 deg in theta, as beside a lobe's cone):
    the strata's midpoints miss the bin's average (solid angle: uniform in phi and sin theta)
    by more than a per cent; views moved by one random share of their strata (a
    Cranley-Patterson rotation, what ``closure.replicated_bins`` draws) average to it, each
    draw's views inside the bin and one per stratum. The turns move by the same rule."""
    from types import SimpleNamespace

    table = SimpleNamespace(phi_o_edges=np.deg2rad([-90.0, -80.0]), theta_o_edges=np.deg2rad([-10.0, 0.0]),
                            meta={"reductions": {"phi_o": "relative"}})

    def light(views):
        w = np.array(views)
        theta, phi = np.arcsin(w[:, 1]), np.arctan2(w[:, 2], w[:, 0])
        return np.exp(-np.rad2deg(theta) / 2.3) * (1.0 + 0.3 * np.cos(8 * phi))

    # the bin's average: midpoints of a fine grid in (phi, sin theta)
    u = np.sin(np.deg2rad(-10.0)) + (np.arange(4000) + 0.5) / 4000 * (0.0 - np.sin(np.deg2rad(-10.0)))
    ph = np.deg2rad(-90.0) + (np.arange(40) + 0.5) / 40 * np.deg2rad(10.0)
    T, P = np.meshgrid(np.arcsin(u), ph, indexing="ij")
    exact = light(np.stack([np.cos(T) * np.cos(P), np.sin(T), np.cos(T) * np.sin(P)], -1).reshape(-1, 3)).mean()

    assert abs(light(closure.bin_views(table, 0.0, 0, 0)).mean() / exact - 1) > 0.01   # 4 x 4 midpoints
    rng = np.random.default_rng(5)
    draws = []
    for _ in range(2000):
        views = np.array(closure.bin_views(table, 0.0, 0, 0, (2, 8), rng.random(2)))
        theta, phi = np.rad2deg(np.arcsin(views[:, 1])), np.rad2deg(np.arctan2(views[:, 2], views[:, 0]))
        assert np.all((theta >= -10.0) & (theta <= 0.0) & (phi >= -90.0) & (phi <= -80.0))
        u0 = np.sin(np.deg2rad(-10.0))
        strata = {(int((p + 90.0) // 5.0), int((np.sin(np.deg2rad(t)) - u0) // (-u0 / 8))) for p, t in zip(phi, theta)}
        assert len(strata) == 16
        draws.append(light(views).mean())
    draws = np.array(draws)
    assert abs(draws.mean() - exact) < 4 * draws.std() / np.sqrt(len(draws)), (draws.mean(), exact)

    turns = [t for t, _ in closure.view_placements(None, 16, 1e-3, offset=(0.25, 0.0))]
    assert np.allclose(turns, 2 * np.pi * (np.arange(16) + 0.25) / 16)


# ----------------------------------------------------------------------------------
# Explicit fibers against the bake (light version; the full sweep: pipeline.bench.closure)
# ----------------------------------------------------------------------------------

@pytest.mark.parametrize("plugin,exit_model,dye", [("fiber_table", "uniform", 0.6), ("fiber_ray", "lobe", None)])
def test_explicit_ply_renders_its_bake(mono, tmp_path, plugin, exit_model, dye):
    """Six ray-optics fibers in a circle, every one its own cylinder with ``fiber_table``
    (light leaves from the uniform displaced exit) or ``fiber_ray`` (each path from its own
    exit), against the bundle table baked from the same arrangement with the same exit
    model, bin by bin. The ``fiber_table`` fibers are dyed (every event keeps ``dye`` of the
    fiber's scattering, ``FiberTable.dyed``) and their table is the undyed fiber's
    order-resolved bake recoloured (``BundleTable.recolour``): the dye's closure. 16 turns of the
    arrangement, each seen from its own direction of a 4 x 4 stratification of the bin,
    estimate the rotation-averaged bin average that the bake holds. Within 3 standard
    errors (bake and render) + 2%, at 20 (theta_i node, bin) pairs: on the cone (the bins
    on either side of it), off it, backwards, sideways, obliquely forward, grazing."""
    import mitsuba as mi

    import mitsuba_ext
    from models.bundle import poisson
    from models.fiber.ray import RayFiber
    from tests.test_bake import bake

    fiber = RayFiber(WL, [1.56] * 3, [0.3, 0.1, 0.0], 0.3, 0.3, 0.0, n_h=64).tabulate(NODES)
    (fiber if dye is None else fiber.dyed(dye)).save(tmp_path / "fiber.npz")
    bundle = poisson((80.0, 80.0), 20.0, packing=0.4, seed=2)
    mi.set_variant("llvm_ad_rgb")  # the baker's own variant
    table = bake(bundle, fiber, paths=2_000_000, theta_i=(10, 30, 60, 80), n_theta_o=18, n_phi_o=36,
                 exit_model=exit_model, orders=0 if dye is None else 8)
    table = table if dye is None else table.recolour(dye)
    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    lam = list(WL).index(LAM)
    bsdf = {"type": plugin, "filename": str(tmp_path / "fiber.npz"), "wavelength": LAM, "up": closure.UP}
    n_t = len(table.theta_o_edges) - 1
    cases = []
    for j, ti in enumerate(table.theta_i):
        cone = int(np.floor((np.pi / 2 - ti) / np.pi * n_t))           # the bin just above -theta_i
        for k_phi in (1, 9, 15):                                         # dphi 15, 95, 155 deg
            for k_theta in {cone, cone - 1, min(cone + 2, n_t - 1)} - {-1}:
                cases.append((j, k_phi, k_theta))
    cases = cases[:24]
    assert len(cases) >= 20
    res = []
    measured = closure.explicit_intensities(mi, bundle, bsdf, [(closure.direction(0.0, table.theta_i[j]),
                                                               closure.bin_views(table, 0.0, k_phi, k_theta))
                                                              for j, k_phi, k_theta in cases], spp=8, resolution=32)
    for (j, k_phi, k_theta), (I, se) in zip(cases, measured):
        ti = table.theta_i[j]
        S, S_err = table.values[0, j, k_phi, k_theta, lam], table.stderr[0, j, k_phi, k_theta, lam]
        predicted = closure.predicted_intensity(1.0, bundle.bounding_radius * 1e-3, ti, S)
        res.append((I / predicted - 1, np.hypot(S_err / S, se / I)))
    res = np.array(res)
    print("explicit / bake - 1:", np.round(res[:, 0], 3).tolist(), "sigma:", np.round(res[:, 1], 3).tolist())
    assert np.all(np.abs(res[:, 0]) <= 0.02 + 3 * res[:, 1]), res
