"""Near-field tables: the light a ply sends from each offset across its width
(docs/DESIGN.md, "Near-field tables").

A bake with ``offsets`` keeps each escaping path's weight also by the cell of its exit
offset ``h_o`` (the signed distance of its line from the ply axis, over the bounding
radius) and the passthrough by the entry offset. The cells average to the far-field table;
the passthrough per cell is what plain geometry says (lines against circles, here in
numpy); and ``fiber_bundle`` on a near-field table renders, column by column across the
ply, what explicit fibers render (the closure of the near field), where the far-field
table renders a flat profile that the explicit fibers' lit and shadowed sides refute."""

import contextlib

import numpy as np
import pytest

import mitsuba_ext
from models.bake import BakeSpec, bake_unreduced
from models.bake.tally import offset_cell
from models.bundle import TwistedBundle, poisson
from models.bundle_table import BundleTable
from models.fiber.ray import RayFiber
from pipeline import closure
from pipeline.bench import near as near_bench

WL = np.array([450.0, 550.0, 650.0])
NODES = np.deg2rad(np.arange(0, 91, 5.0))
CELLS = 8


@pytest.fixture(scope="module", autouse=True)
def _variant(mi_llvm):
    return mi_llvm


@pytest.fixture(scope="module")
def fiber():
    return RayFiber(WL, [1.56] * 3, [0.3, 0.1, 0.0], 0.3, 0.3, 0.0, n_h=64).tabulate(NODES)


@pytest.fixture(scope="module")
def ply():
    return poisson((80.0, 80.0), 20.0, packing=0.4, seed=2)


def test_the_cells_average_to_the_table_and_pass_what_geometry_passes(ply, fiber, tmp_path):
    """The mean of ``S_h`` over the cells is ``S`` (the same float64 sums, to float32
    rounding); the passthrough per entry cell is the share of lines at that offset that miss
    every fiber, over every orientation (numpy, within binomial errors); the theta mirror and
    the half-precision file keep the cells."""
    spec = BakeSpec(np.deg2rad([0.0, 40.0]), np.zeros(1), 12, 32, offsets=CELLS)
    T = bake_unreduced(ply, fiber, spec, 200_000, seed=5)
    eps = np.finfo(np.float32).eps
    assert np.all(np.abs(T.near.astype(np.float64).mean(0) - T.values) <= 4 * eps * T.values + 1e-30)
    # geometry: a line at offset h R_b (x sin phi - z cos phi = h R_b) misses a fiber at c unless
    # |c_x sin phi - c_z cos phi - h R_b| < r
    rng = np.random.default_rng(0)
    n = 400_000
    phi, h = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1, 1, n)
    R = ply.bounding_radius
    d = ply.centers[:, 0][None] * np.sin(phi)[:, None] - ply.centers[:, 1][None] * np.cos(phi)[:, None]
    missed = np.all(np.abs(d - h[:, None] * R) >= ply.radii[None], axis=1)
    cell = np.minimum(((h + 1) * CELLS / 2).astype(int), CELLS - 1)
    geometric = np.bincount(cell, missed, CELLS) / np.bincount(cell, minlength=CELLS)
    assert np.all(T.near_passthrough[0, 0] == T.near_passthrough[0, 1])   # a parallel ply: any theta_i
    p = T.near_passthrough[0, 0]
    se = np.sqrt(p * (1 - p) / (200_000 / CELLS) + geometric * (1 - geometric) / (n / CELLS)) + 1e-9
    print("passthrough by cell", np.round(p, 3), "geometry", np.round(geometric, 3))
    assert np.all(np.abs(p - geometric) < 4 * se), (p, geometric)
    assert p[0] > 0.1 and p[CELLS // 2] < p[0]           # the rims pass more than the core
    # kept through the file and the theta mirror (h is unchanged by a mirror along the axis)
    T.meta["reductions"] = {"theta_i": "mirror", "phi_i": "rotation", "phi_o": "relative"}
    T.save(tmp_path / "near.npz")
    full = BundleTable.load(tmp_path / "near.npz", expand=True)
    assert full.near.shape == (CELLS, 1, 3) + T.values.shape[2:]
    np.testing.assert_array_equal(full.near[:, :, 0], full.near[:, :, 2][:, :, :, ::-1])
    assert np.all(np.abs(full.near.mean(0) - full.values) <= 2.0**-9 * full.values + 1e-6 * full.values.max())


def test_offset_cells_in_numpy_and_drjit_agree():
    import drjit as dr
    import mitsuba as mi

    rng = np.random.default_rng(1)
    x, z, phi = rng.uniform(-1, 1, 1000), rng.uniform(-1, 1, 1000), rng.uniform(0, 2 * np.pi, 1000)
    ref = np.clip(np.floor(((x * np.sin(phi) - z * np.cos(phi)) / 1.5 + 1) * CELLS / 2), 0, CELLS - 1)
    np.testing.assert_array_equal(offset_cell(CELLS, x, z, phi, 1.5), ref)
    mi.set_variant("llvm_ad_rgb")
    dj = offset_cell(CELLS, mi.Float(x), mi.Float(z), mi.Float(phi), 1.5, dr).numpy()
    assert np.mean(dj == ref) > 0.995   # float32 at the cells' edges


PLIES = {"parallel": ([10, 30, 60, 80], 2_000_000), "twisted, pitch 1500 um": ([-30, 20, 60], 2_400_000)}


class Case:
    """One ply of :data:`PLIES`: its near-field bake (saved), the incidences and views of the
    closure, and the explicit fibers' intensities in the cells (rendered once per module)."""

    def __init__(self, mi, fiber, tmp_path, name):
        theta_i_deg, paths = PLIES[name]
        self.ply = near_bench.plies()[name]
        self.table = near_bench.bake(self.ply, fiber, theta_i_deg, CELLS, paths)
        self.path = tmp_path / "near.npz"
        self.table.save(self.path)
        fiber.save(tmp_path / "fiber.npz")
        mi.set_variant("llvm_ad_mono")
        mitsuba_ext.register()
        n_t = 18
        self.cases = [(j, k_phi, int(np.floor((np.pi / 2 - self.table.theta_i[j]) / np.pi * n_t)))
                      for j in (1, 2) for k_phi in (1, 9, 15)]
        self.requests = [(closure.direction(0.0, self.table.theta_i[j]),
                          closure.bin_views(self.table, 0.0, k_phi, k_theta)) for j, k_phi, k_theta in self.cases]
        explicit = {"type": "fiber_table", "filename": str(tmp_path / "fiber.npz"), "wavelength": 550.0,
                    "up": closure.UP}
        self.measured = closure.explicit_intensities(mi, self.ply, explicit, self.requests, spp=8, resolution=64,
                                                     cells=CELLS)
        self.R = (self.ply.bundle if isinstance(self.ply, TwistedBundle) else self.ply).bounding_radius * 1e-3


@pytest.fixture(scope="module")
def plies_seen(mi_llvm, fiber, tmp_path_factory):
    """``plies_seen(name)``: the :class:`Case` of ply ``name``, made once per module."""
    made = {}

    def get(name):
        if name not in made:
            made[name] = Case(mi_llvm, fiber, tmp_path_factory.mktemp("near"), name)
        return made[name]
    return get


@pytest.mark.parametrize("name", [pytest.param(n, marks=[pytest.mark.slow] if "twisted" in n else [])
                                  for n in PLIES])
def test_a_near_field_bundle_renders_the_profile_of_explicit_fibers(mono, plies_seen, tmp_path, name):
    """Six ray-optics fibers, every one its own cylinder (or, twisted, a ``bsplinecurve``
    along its helix; ``fiber_table``, the uniform exit), against ``fiber_bundle`` on the
    near-field bake of the same arrangement, on a cylinder and on a ``bsplinecurve``: the
    intensity in 8 cells across the width, each averaged over 16 turns of the arrangement (a
    twisted ply's: shifts along it, so the profile is averaged along the ply) and a 4 x 4
    stratification of the table bin, side, back- and forward-lit at two incidences: within
    5% + 3 standard errors (explicit renders and the bake's cell) in every cell. The same
    table read as a far field (``near_field: false``) is outside in many cells. Seen against
    a lit background, the bundle lets through what ``near_passthrough`` says per cell."""
    mi = mono
    case = plies_seen(name)
    table, requests, measured, cases, R = case.table, case.requests, case.measured, case.cases, case.R
    lam = 1

    def curve(R_, bsdf, half_length):   # the same ply as a straight bsplinecurve (the cloth's plies)
        path = tmp_path / "ply.txt"
        closure.write_curves([np.column_stack([np.zeros(33), np.linspace(-half_length, half_length, 33),
                                               np.zeros(33), np.full(33, R_)])], path)
        return {"type": "bsplinecurve", "filename": str(path), "bsdf": bsdf}

    outside = {}
    for near, kind, shape in ((True, "cylinder", None), (True, "bsplinecurve", curve), (False, "cylinder", None)):
        bsdf = {"type": "fiber_bundle", "table": str(case.path), "wavelength": 550.0, "up": closure.UP,
                "near_field": near}
        rendered = closure.bundle_profiles(mi, bsdf, R, requests, CELLS, shape=shape)
        outside[near, kind] = 0
        for profile, (I, se), (j, k_phi, k_theta) in zip(rendered, measured, cases):
            ratio = profile / I
            S, S_se = table.near[:, 0, j, k_phi, k_theta, lam], table.near_stderr[:, 0, j, k_phi, k_theta, lam]
            sigma = np.hypot(se / I, S_se / S)
            print("near" if near else "far", kind, (j, k_phi, k_theta), "bundle / explicit", np.round(ratio, 2),
                  "sigma", np.round(sigma, 2))
            outside[near, kind] += int(np.sum(np.abs(ratio - 1) > 0.05 + 3 * sigma))
    assert outside[True, "cylinder"] == 0 and outside[True, "bsplinecurve"] == 0, outside
    assert outside[False, "cylinder"] >= 12, outside
    # the null lobe per offset: a lit background seen through the ply
    hs = 1.2 * R
    bsdf = {"type": "fiber_bundle", "table": str(case.path), "wavelength": 550.0, "up": closure.UP}
    w_o = closure.direction(0.4, 0.3)
    sc = closure.scene(mi, {"f": closure.cylinder(R, bsdf, half_length=40 * hs)}, -w_o, w_o, hs, irradiance=0.0,
                       background=1.0, spp=16, resolution=64)
    seen = closure.profile(closure.render_image(mi, sc), w_o, hs, R, CELLS)
    clear = closure.profile(np.ones((64, 64)), w_o, hs, R, CELLS)
    P = np.array([np.interp(-0.3, table.theta_i, table.near_passthrough[0, :, c]) for c in range(CELLS)])
    np.testing.assert_allclose(seen / clear, P, atol=0.03)


def test_near_field_bakes_are_refused_where_they_are_not_defined():
    from pipeline.config import ConfigError
    from pipeline.loading import load_config

    with pytest.raises(ConfigError, match="circular plies"):
        load_config("configs/thesis_ellipse.yaml", ["bake.offsets=8"])
    assert load_config("configs/twisted_cotton1.yaml", ["bake.offsets=8"]).bake.offsets == 8
    assert load_config("configs/default.yaml", ["bake.offsets=8"]).bake.offsets == 8
    with pytest.raises(ValueError, match="offsets"):
        BakeSpec(np.zeros(1), np.zeros(1), offsets=1)
    for kw in ({"estimator": "thesis"}, {"relative_phi": False}, {"orders": 4}):
        with pytest.raises(ValueError, match="offsets need"):
            BakeSpec(np.zeros(1), np.zeros(1), offsets=8, **kw)


@pytest.mark.slow
def test_a_neural_near_field_renders_the_profile_of_explicit_fibers(mono, plies_seen, tmp_path):
    """A model with the offset as an input (``train.inputs: [offset]``), trained on the
    parallel ply's near-field bake and rendered by ``fiber_bundle``'s ``mlp`` and ``onnx``
    backends, against the explicit fibers of the table's closure test, cell by cell: within
    5% + 3 standard errors plus the model's own distance from its table in that cell (its bin
    and cell average, measured here: the triangle inequality of render, model, table and
    fibers). The model learns the cells: its median distance from them is under 10%, and the
    same model read as a far field (its mean over the offset) misses many cells."""
    from models.fit import model_bin_averages
    from models.neural import table_cells

    mi = mono
    case = plies_seen("parallel")
    table, lam = case.table, 1
    fitted = near_bench.train(table, case.path, tmp_path)
    spec, model = fitted["spec"], fitted["model"]
    n_po, n_to = len(table.phi_o), len(table.theta_o)
    edges = np.linspace(-1, 1, CELLS + 1)
    own = {}
    for j, k_phi, k_theta in case.cases:
        cell = table_cells(table)[[(j * n_po + k_phi) * n_to + k_theta] * CELLS]
        S_model = model_bin_averages(spec, model, cell, k=4, extra_cell=np.stack([edges[:-1], edges[1:]], -1)[:, None])
        own[j, k_phi, k_theta] = np.abs(S_model[:, lam] / table.near[:, 0, j, k_phi, k_theta, lam] - 1)
    assert np.median(np.concatenate(list(own.values()))) < 0.10, own
    mi.set_variant("llvm_ad_mono")
    mitsuba_ext.register()
    outside = {}
    for backend, near in (("mlp", True), ("onnx", True), ("mlp", False)):
        model_file = tmp_path / ("weights.npz" if backend == "mlp" else "model.onnx")
        bsdf = {"type": "fiber_bundle", "backend": backend, "model": str(model_file), "wavelength": 550.0,
                "up": closure.UP, "near_field": near}
        with mitsuba_ext.evaluated_mode() if backend == "onnx" else contextlib.nullcontext():
            rendered = closure.bundle_profiles(mi, bsdf, case.R, case.requests, CELLS)
        outside[backend, near] = 0
        for profile, (I, se), key in zip(rendered, case.measured, case.cases):
            j, k_phi, k_theta = key
            ratio = profile / I
            S, S_se = table.near[:, 0, j, k_phi, k_theta, lam], table.near_stderr[:, 0, j, k_phi, k_theta, lam]
            sigma = np.hypot(se / I, S_se / S)
            print(backend, "near" if near else "far", key, "bundle / explicit", np.round(ratio, 2),
                  "sigma", np.round(sigma, 2), "model / table", np.round(own[key], 2))
            outside[backend, near] += int(np.sum(np.abs(ratio - 1) > 0.05 + 3 * sigma + own[key]))
    assert outside["mlp", True] == 0 and outside["onnx", True] == 0, outside
    assert outside["mlp", False] >= 12, outside
