"""Order-resolved bakes and dyes (docs/DESIGN.md, "Order-resolved tables").

A bake with ``orders`` keeps each escaping path's weight also by its number of fiber events;
the orders add up to the table, and ``BundleTable.recolour(a)`` (``sum_k a^k S_k``) must be
what a direct bake of the dyed fiber (``FiberTable.dyed(a)``: every event keeps ``a`` of the
scattering) measures, within the two bakes' standard errors: a grey, a published red dye
(the ColorChecker's red patch, Ohta's measurement, as colour-science ships it) and a dark
fiber. The direct bakes trace other paths (another seed, and Russian roulette plays on other
weights), so nothing is shared but the geometry and the fiber."""

import dataclasses

import colour
import numpy as np
import pytest

from models.bake import BakeSpec, bake_unreduced
from models.bake.tally import Tally
from models.bake.twisted import TwistedBaker
from models.bundle import TwistedBundle, poisson
from models.bundle_table import BundleTable, dyed, tail_factor
from models.fit import fit, model_bin_averages, prepare
from models.neural import (make_export_module, order_channels, order_sum, rounding_bound, save_onnx, save_weights,
                           table_cells)
from models.fiber.ray import RayFiber
from pipeline import closure
from tests.synthetic import make_config

WL = np.array([450.0, 550.0, 650.0])
THETA_I = np.deg2rad([0.0, 30.0, 70.0])
PATHS = 150_000
RED = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]["red"]
DYES = {"grey 0.95": np.full(3, 0.95), "ColorChecker red": np.asarray(RED[WL]), "dark 0.3": np.full(3, 0.3)}


@pytest.fixture(scope="module", autouse=True)
def _variant(mi_llvm):
    return mi_llvm


@pytest.fixture(scope="module")
def fiber():
    return RayFiber(WL, eta=1.55, sigma_a=0.0, longitudinal_roughness=0.2, azimuthal_roughness=0.3,
                    n_h=64, n_phi=180).tabulate(np.deg2rad(np.arange(0, 91, 5.0)))


@pytest.fixture(scope="module")
def ply():
    return poisson((120, 120), 10, seed=2)


def spec(orders=0, **kw):
    return BakeSpec(THETA_I, np.zeros(1), 12, 32, relative_phi=True, orders=orders, **kw)


@pytest.fixture(scope="module")
def resolved(ply, fiber):
    return bake_unreduced(ply, fiber, spec(8), PATHS, seed=3)


def test_the_orders_add_up_to_the_table_and_the_first_is_the_singly_scattered_light(resolved):
    """Each path is tallied once in ``sum`` and once in its order (float64 sums of the same
    float32 weights): the float32 tables agree to a few roundings of float32 (``K + 1``
    additions and the division, relative to the bin). The first order is ``single``."""
    T = resolved
    o = T.orders.astype(np.float64)
    eps = np.finfo(np.float32).eps
    assert np.all(np.abs(o.sum(0) - T.values) <= (len(o) + 2) * eps * o.sum(0) + 1e-30)
    first = np.einsum("abpql,pq->abl", o[0], T.solid_angle)
    np.testing.assert_allclose(first, T.single, rtol=1e-5)
    assert np.all(T.orders[1:].sum(axis=(0, 3, 4)) > 0) and np.all((T.tail_ratio > 0) & (T.tail_ratio < 1))


def test_the_orders_are_each_paths_own_count(ply, fiber):
    """The same paths (same seed) resolved to 3 and to 12 orders: orders 1 and 2 identical,
    the tail of 3 the sum of orders 3 .. 12's (to float32 rounding); the tail ratio follows
    the tail's mean order, which the finer bake resolves further."""
    a, b = (bake_unreduced(ply, fiber, spec(K), 40_000, seed=5) for K in (3, 12))
    np.testing.assert_array_equal(a.orders[:2], b.orders[:2])
    np.testing.assert_allclose(a.orders[2], b.orders[2:].astype(np.float64).sum(0), rtol=1e-5, atol=1e-12)
    np.testing.assert_array_equal(a.values, b.values)


@pytest.mark.parametrize("dye", DYES)
def test_a_recoloured_table_is_the_bake_of_the_dyed_fiber(ply, fiber, resolved, dye):
    albedo = DYES[dye]
    R = resolved.recolour(albedo)
    D = bake_unreduced(ply, fiber.dyed(albedo), spec(), PATHS, seed=17)
    assert not np.allclose(R.values, resolved.values)   # the dye changed it
    # every bin with light: z of the difference in the two bakes' standard errors
    se = np.sqrt(R.stderr.astype(np.float64) ** 2 + D.stderr.astype(np.float64) ** 2)
    big = (D.values > 0.02 * D.values.max(axis=(2, 3), keepdims=True)) & (se > 0)
    z = ((R.values - D.values) / np.where(se > 0, se, 1))[big]
    n = z.size
    print(dye, "bins", n, "mean z", z.mean(), "mean z^2", np.mean(z**2))
    assert abs(z.mean()) < 5 / np.sqrt(n) and np.mean(z**2) < 1 + 5 * np.sqrt(2 / n)
    # the balance stays what the bake's was (a Monte Carlo estimate of 1), the albedo agrees
    # within the bins' combined errors
    np.testing.assert_allclose(R.energy_balance()["total"], resolved.energy_balance()["total"], rtol=1e-9)
    se = np.sqrt(np.einsum("abpql,pq->abl", R.stderr.astype(np.float64) ** 2 + D.stderr.astype(np.float64) ** 2,
                           R.solid_angle**2))
    assert np.all(np.abs(R.scattered - D.scattered) < 5 * se), (R.scattered, D.scattered, se)
    np.testing.assert_allclose(R.single, D.single, rtol=0.05)


def test_recolour_limits(resolved):
    """A clear fiber gives the table back (the tail's factor is 1 at ``a = 1``); a black one
    scatters nothing; the tail's factor is the geometric series'."""
    same = resolved.recolour(1.0)
    np.testing.assert_allclose(same.values, resolved.values, rtol=1e-5, atol=1e-30)
    np.testing.assert_allclose(same.absorbed, resolved.absorbed, atol=1e-6)
    black = resolved.recolour(0.0)
    assert np.all(black.values == 0)
    np.testing.assert_allclose(black.absorbed + black.energy_balance()["passthrough"],
                               resolved.energy_balance()["total"], rtol=1e-12)
    rho, a = 0.7, 0.6
    series = sum((a * rho) ** j for j in range(200)) / sum(rho**j for j in range(200))
    assert tail_factor(a, rho) == pytest.approx(series, rel=1e-12)


def test_an_order_resolved_table_survives_saving_expanding_and_checkpoints(resolved, tmp_path, ply, fiber):
    path = tmp_path / "t.npz"
    resolved.meta["reductions"] = {"theta_i": None, "phi_i": "rotation", "phi_o": "relative"}
    resolved.save(path)
    back = BundleTable.load(path)
    # half precision: 2^-11 of each value, each order with its own scale
    assert np.all(np.abs(back.orders - resolved.orders) <= 2.0**-11 * resolved.orders + 1e-6 * resolved.orders.max())
    np.testing.assert_allclose(back.recolour(DYES["dark 0.3"]).scattered, resolved.recolour(DYES["dark 0.3"]).scattered,
                               rtol=2e-3)
    # the theta mirror expands every order as it expands the table
    half = bake_unreduced(ply, fiber, BakeSpec(np.deg2rad([0.0, 40.0]), np.zeros(1), 12, 32, orders=4), 5000)
    half.meta["reductions"] = {"theta_i": "mirror", "phi_i": "rotation", "phi_o": "relative"}
    full = half.expanded()
    assert full.orders.shape[2] == 3 and full.tail_ratio.shape[1] == 3
    np.testing.assert_array_equal(full.orders.sum(0) > 0, full.values > 0)
    np.testing.assert_allclose(full.recolour(0.5).values, half.recolour(0.5).expanded().values, rtol=1e-6)
    # a checkpoint's arrays carry the orders
    t = Tally.zeros(spec(4), 3)
    t.orders += 1.0
    assert Tally.from_arrays(t.arrays()).orders.sum() == t.orders.sum()
    assert Tally.from_arrays(Tally.zeros(spec(), 3).arrays()).orders is None


def test_a_twisted_bake_resolves_its_orders(fiber):
    ply = TwistedBundle(poisson((60, 60), 10, seed=1), pitch=600.0)
    s = BakeSpec(THETA_I, np.zeros(1), 12, 32, relative_phi=True, orders=4)
    tally = TwistedBaker(ply, fiber, s).trace(0, 20_000, np.random.SeedSequence(1))
    assert tally.orders[:, 0].sum() > 0
    np.testing.assert_allclose(tally.orders.sum(0), tally.sum, rtol=1e-9, atol=1e-12)


def test_bad_dyes_and_tables_without_orders_are_refused(resolved, fiber, ply):
    plain = bake_unreduced(ply, fiber, spec(), 2000)
    with pytest.raises(ValueError, match="bake.orders"):
        plain.recolour(0.5)
    for bad, said in ((1.5, r"\[0, 1\]"), (-0.1, r"\[0, 1\]"), ([0.5, 0.5], "one per wavelength"),
                      (np.nan, "not finite"), ("red", "number")):
        with pytest.raises(ValueError, match=said):
            resolved.recolour(bad)
        with pytest.raises(ValueError, match=said):
            fiber.dyed(bad)
    with pytest.raises(ValueError, match="torn order-resolved"):
        dataclasses.replace(resolved, tail_ratio=None).validate()
    with pytest.raises(ValueError, match="tail_ratio must"):
        dataclasses.replace(resolved, tail_ratio=np.ones_like(resolved.tail_ratio)).validate()
    with pytest.raises(ValueError, match="orders"):
        BakeSpec(THETA_I, np.zeros(1), orders=1)
    with pytest.raises(ValueError, match="fast"):
        BakeSpec(THETA_I, np.zeros(1), orders=4, estimator="thesis")


# ----------------------------------------------------------------------------------
# The plugin: fiber_bundle's albedo
# ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def resolved_file(ply, fiber, tmp_path_factory):
    """An order-resolved table over every incidence (the closure's directions reach 88 deg)."""
    s = BakeSpec(np.deg2rad(np.arange(0, 91, 15.0)), np.zeros(1), 18, 36, relative_phi=True, orders=8)
    path = tmp_path_factory.mktemp("dye") / "resolved.npz"
    bake_unreduced(ply, fiber, s, 100_000, seed=4).save(path)
    return path


def test_a_dyed_bundle_renders_its_recoloured_table(spectral, resolved_file, tmp_path):
    """The far-field closure (docs/DESIGN.md) of ``fiber_bundle`` with ``albedo`` a Mitsuba
    spectrum (the ColorChecker red, irregular) in the spectral variant, against the lookup
    of the table recoloured with that spectrum at the table's wavelengths, in the luminance
    the spectral film records: within 1% at every direction pair. The recolouring itself
    is held to direct bakes of the dyed fiber above."""
    mi = spectral
    nm = np.arange(380.0, 781.0, 20.0)
    red = {"type": "spectrum", "value": [(float(w), float(RED[w])) for w in nm]}
    recoloured = BundleTable.load(resolved_file).recolour(np.interp(WL, nm, RED[nm]))
    recoloured.save(tmp_path / "recoloured.npz")
    bsdf = {"type": "fiber_bundle", "table": str(resolved_file), "albedo": red, "up": closure.UP}
    S = closure.evaluator(mi, "table", tmp_path / "recoloured.npz", None)
    pairs = closure.direction_pairs(cone_offsets_deg=(0.8, -1.7))
    rows = closure.far_field_ratios(mi, bsdf, 0.2, S, pairs, spp=64)
    r = np.array([row[3] for row in rows])
    print(np.round(r, 4))
    assert len(r) >= 12 and np.allclose(r, 1.0, atol=0.01), r
    # and the dye is seen: the undyed table's luminance is another
    plain = closure.evaluator(mi, "table", resolved_file, None)
    assert np.median(S(*np.asarray(pairs).T) / plain(*np.asarray(pairs).T)) < 0.6


def test_the_plugins_albedo_in_rgb_and_what_it_refuses(mi_plugins, resolved_file, tmp_path):
    """RGB variants upsample an sRGB albedo as Mitsuba's spectral variants do (Jakob and
    Hanika): the loaded table is the recolouring with that spectrum; the spectral variant
    evaluates the same ``srgb`` texture to the same spectrum. Bad albedos are refused."""
    mi = mi_plugins
    from mitsuba_ext.params import spectrum_at, srgb_upsampled

    colour_ = {"type": "srgb", "color": [0.7, 0.2, 0.1]}
    b = mi.load_dict({"type": "fiber_bundle", "table": str(resolved_file), "albedo": colour_})
    a = srgb_upsampled([0.7, 0.2, 0.1], WL)
    assert a[2] > 0.5 > a[0]   # red
    want = BundleTable.load(resolved_file, expand=True).recolour(a)
    np.testing.assert_allclose(b.backend.table.values, want.values, rtol=1e-6)
    mi.set_variant("llvm_ad_spectral")
    try:
        np.testing.assert_allclose(spectrum_at("t", "albedo", mi.load_dict(colour_), WL), a, rtol=1e-5)
    finally:
        mi.set_variant("llvm_ad_rgb")
    plain = tmp_path / "plain.npz"
    t = BundleTable.load(resolved_file)
    t.orders = t.orders_stderr = t.tail_ratio = None
    t.save(plain)
    def bitmap():   # a fresh one each time: loading takes its tensor
        return {"type": "bitmap", "data": mi.TensorXf(np.full((2, 2, 3), 0.5))}
    for table, albedo, said in ((plain, 0.5, "bake.orders"), (resolved_file, 1.5, r"\[0, 1\]"),
                                (plain, bitmap(), "bake.orders")):
        with pytest.raises((ValueError, RuntimeError), match=said):
            mi.load_dict({"type": "fiber_bundle", "table": str(table), "albedo": albedo})


def test_a_space_dyed_bundle_renders_each_dye_where_the_texture_puts_it(mono, resolved_file, tmp_path):
    """``albedo`` a bitmap on the cylinder's UV: the orders are looked up and weighted per
    hit, ``sum_{k<K} a^k S_k + a^K T (1 - rho) / (1 - a rho)`` with each order read as the
    table backend reads a table (its own limited slopes) and ``rho`` linear between the
    theta_i nodes. The far-field closure against that model, evaluated here in numpy from
    the tables of each order (within 1%): a uniform bitmap, and one of 512 stripes around
    the cylinder (its ``u``) dyed 0.2 and 0.9 in turn, which renders the mean of the two
    dyes (the half of the circumference in view holds 256 stripes)."""
    mi = mono
    full = BundleTable.load(resolved_file, expand=True)
    K, lam = len(full.orders), list(full.wavelength).index(550.0)
    S_k = []
    for k in range(1, K + 1):
        full.order(k).save(tmp_path / f"order{k}.npz")
        S_k.append(closure.evaluator(mi, "table", tmp_path / f"order{k}.npz", 550.0))

    def dyed(a):
        def S_of(pi_, ti, po, to):
            rho = np.interp(np.abs(ti), full.theta_i, full.tail_ratio[0, :, lam])
            tail = a**K * (1 - rho) / (1 - a * rho) * S_k[-1](pi_, ti, po, to)
            return sum(a ** (k + 1) * S_k[k](pi_, ti, po, to) for k in range(K - 1)) + tail
        return S_of

    def bitmap(columns):
        data = np.repeat(np.asarray(columns, np.float32)[None, :, None], 3, axis=2)  # (v, u, rgb)
        return {"type": "bitmap", "data": mi.TensorXf(data), "filter_type": "nearest", "raw": True}

    pairs = closure.direction_pairs(cone_offsets_deg=(0.8, -1.7))[::2]
    striped = lambda *d: 0.5 * (dyed(0.2)(*d) + dyed(0.9)(*d))  # noqa: E731
    for columns, S_of in (([0.6, 0.6], dyed(0.6)), ([0.2, 0.9] * 256, striped)):
        bsdf = {"type": "fiber_bundle", "table": str(resolved_file), "albedo": bitmap(columns), "wavelength": 550.0,
                "up": closure.UP}
        r = np.array([row[3] for row in closure.far_field_ratios(mi, bsdf, 0.2, S_of, pairs, spp=64)])
        print(len(columns), "columns:", np.round(r, 4))
        assert len(r) >= 6 and np.allclose(r, 1.0, atol=0.01), r


# ----------------------------------------------------------------------------------
# A neural model of the orders (train.orders): dyed as the table is recoloured
# ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def order_model(resolved_file, tmp_path_factory):
    """A tiny model of the order-resolved table's 8 orders (8 x 3 outputs), exported, and one
    of the same table without orders (which holds one dye)."""
    tmp = tmp_path_factory.mktemp("order_model")
    table = BundleTable.load(resolved_file, expand=True)
    c = make_config(tmp).train.model_copy(update={"orders": True, "epochs": 80, "patience": 80})
    models = {}
    for name, update in (("orders", {}), ("plain", {"orders": False, "epochs": 4})):
        ci = c.model_copy(update=update)
        problem = prepare(table, resolved_file, ci, "")
        spec = dataclasses.replace(problem.base, hidden=[16, 16])
        model, *_ = fit(spec, problem, ci, name)
        (tmp / name).mkdir()
        save_weights(tmp / name / "weights.npz", spec, model)
        save_onnx(tmp / name / "model.onnx", spec, model)
        models[name] = (spec, model, tmp / name)
    return table, models


def test_a_model_of_the_orders_dyes_as_its_table_recolours(order_model):
    """Each order carries its own energy gain, so the model dyed by any albedo keeps the
    recoloured table's albedo at every incidence: within 1% (each order's gain holds its
    order's albedo to its 8 x 8-point quadrature, measured here at 4 x 4 points; without the
    gains the tiny model is 10-30% off). And the dye costs no accuracy: the model's relative
    L1 against the recoloured table is within 1.25x its L1 against the undyed table."""
    table, models = order_model
    spec, model, _ = models["orders"]
    assert spec.orders == 8 and spec.n_outputs == 8 * 3
    bins = model_bin_averages(spec, model, table_cells(table), orders=True).reshape(table.values.shape[:4] + (-1,))
    orders = order_channels(spec, bins)
    rho = table.tail_ratio[:, :, None, None, :]
    l1 = {}
    for name, a in {"undyed": np.ones(3), **DYES}.items():
        want = table.recolour(a)
        S = dyed(orders, a, rho)
        albedo = np.einsum("abpql,pq->abl", S, table.solid_angle)
        seen = want.scattered > 1e-4
        worst = np.max(np.abs(albedo[seen] / want.scattered[seen] - 1))
        l1[name] = np.abs(S - want.values).sum() / want.values.sum()
        print(f"{name}: worst albedo error {worst:.2e}, relative L1 {l1[name]:.3f}")
        assert worst < 0.01, (name, worst)
        assert l1[name] <= 1.25 * l1["undyed"], (name, l1)
    np.testing.assert_allclose(order_sum(spec, bins), bins.reshape(bins.shape[:-1] + (8, 3)).sum(-2))


def test_every_backend_returns_the_orders_and_their_sum(order_model, mi_llvm):
    """PyTorch, onnxruntime and Dr.Jit agree on the orders' sum within the derived float32
    bound, and each returns orders that add up to it (float32 summation of 8 terms)."""
    import torch

    from mitsuba_ext.neural import DrJitMLP, OnnxMLP

    _, models = order_model
    spec, model, where = models["orders"]
    rng = np.random.default_rng(1)
    q = np.stack([np.zeros(500), rng.uniform(-1.4, 1.4, 500), rng.uniform(-np.pi, np.pi, 500),
                  rng.uniform(-1.5, 1.5, 500)], -1).astype(np.float32)
    with torch.no_grad():
        ref, ref_orders = (a.numpy().astype(np.float64) for a in
                           make_export_module(spec, model, orders=True).eval()(torch.from_numpy(q)))
    jit_mlp, onnx_mlp = DrJitMLP(where / "weights.npz"), OnnxMLP(where / "model.onnx")
    tol = 2 * rounding_bound(spec, jit_mlp.layers, q)[1]
    for name, ev in (("onnx", onnx_mlp.eval), ("jit", jit_mlp.eval)):
        S, parts = ev(*q.T).astype(np.float64), ev(*q.T, orders=True).astype(np.float64)
        assert parts.shape == (500, 24) and np.all(np.abs(S - ref) <= tol), name
        summed = order_sum(spec, parts)
        assert np.all(np.abs(summed - S) <= 8 * 2.0**-24 * parts.reshape(500, 8, 3).sum(1) * 2), name
        assert np.all(np.abs(parts - ref_orders) <= 1e-3 * ref_orders.max()), name


def test_the_plugin_dyes_a_model_of_the_orders(spectral, order_model):
    """The far-field closure (docs/DESIGN.md) of ``fiber_bundle`` with a model of the orders
    (mlp and onnx) and ``albedo`` the ColorChecker red in the spectral variant, against the
    model's orders dyed at the model's wavelengths (``sum a^k S_k`` with the tail's ratio
    interpolated over theta_i), in the luminance the spectral film records: within 1%."""
    from mitsuba_ext.neural import OnnxMLP

    mi = spectral
    _, models = order_model
    spec, _, where = models["orders"]
    nm = np.arange(380.0, 781.0, 20.0)
    red = {"type": "spectrum", "value": [(float(w), float(RED[w])) for w in nm]}
    a = np.interp(WL, nm, RED[nm])
    onnx = OnnxMLP(where / "model.onnx")
    w = closure.spectrum_weights(mi, spec.wavelength, None)
    rho_of = np.asarray(spec.tail_ratio)[0]

    def S_of(pi_, ti, po, to):
        q = [np.atleast_1d(np.asarray(v, np.float64)) for v in (pi_, ti, po, to)]
        rho = np.stack([np.interp(q[1], spec.tail_ratio_theta_i, rho_of[:, l]) for l in range(3)], -1)
        shape = np.broadcast_shapes(*(np.shape(v) for v in (pi_, ti, po, to)))
        return (dyed(order_channels(spec, onnx.eval(*q, orders=True)), a, rho) @ w).reshape(shape)

    pairs = closure.direction_pairs(cone_offsets_deg=(0.8, -1.7))[::2]
    for backend, file in (("mlp", "weights.npz"), ("onnx", "model.onnx")):
        bsdf = {"type": "fiber_bundle", "backend": backend, "model": str(where / file), "albedo": red,
                "up": closure.UP}
        r = np.array([row[3] for row in closure.far_field_ratios(mi, bsdf, 0.2, S_of, pairs, spp=64,
                                                                 evaluated=backend == "onnx")])
        print(backend, np.round(r, 4))
        assert len(r) >= 6 and np.allclose(r, 1.0, atol=0.01), (backend, r)
    # and the dye is seen: the undyed model's luminance is another
    plain = onnx.eval(*np.asarray(pairs, np.float64).T) @ w
    assert np.median(S_of(*np.asarray(pairs).T) / plain) < 0.6


def test_a_model_without_orders_is_refused_a_dye(mi_plugins, order_model):
    """A model trained without ``train.orders`` holds the one dye it was trained on: an albedo
    (uniform or a texture) is refused by name, for either backend. A model of the orders in
    an RGB variant takes an sRGB albedo upsampled as Mitsuba's spectral variants do."""
    from mitsuba_ext.params import srgb_upsampled

    mi = mi_plugins
    _, models = order_model
    b = mi.load_dict({"type": "fiber_bundle", "backend": "mlp", "model": str(models["orders"][2] / "weights.npz"),
                      "albedo": {"type": "srgb", "color": [0.7, 0.2, 0.1]}})
    np.testing.assert_allclose(b.backend.albedo, srgb_upsampled([0.7, 0.2, 0.1], WL), rtol=1e-6)
    where = models["plain"][2]
    for backend, file in (("mlp", "weights.npz"), ("onnx", "model.onnx")):
        for albedo in (0.5, {"type": "bitmap", "data": mi.TensorXf(np.full((2, 2, 3), 0.5))}):
            with pytest.raises((ValueError, RuntimeError), match="holds the one dye"):
                mi.load_dict({"type": "fiber_bundle", "backend": backend, "model": str(where / file),
                              "albedo": albedo})


def test_a_model_of_the_orders_needs_an_order_resolved_bake(tmp_path, resolved):
    """``train.orders`` without ``bake.orders`` (or with an extra input) is refused by the
    config; a table without orders by the training; metadata of one order by the model."""
    with pytest.raises(ValueError, match="bake.orders"):
        make_config(tmp_path, orders=True)
    with pytest.raises(ValueError, match="not supported"):
        make_config(tmp_path, bake={"orders": 8, "offsets": 0}, orders=True, encoding="cartesian")
    plain = dataclasses.replace(resolved, orders=None, orders_stderr=None, tail_ratio=None)
    c = make_config(tmp_path, bake={"orders": 8}, orders=True).train
    with pytest.raises(ValueError, match="bake.orders"):
        prepare(plain.expanded(), tmp_path / "t.npz", c, "")
    resolved.save(tmp_path / "t.npz")   # its hash is recorded
    spec = prepare(resolved.expanded(), tmp_path / "t.npz", c.model_copy(update={"orders": False}), "").base
    with pytest.raises(ValueError, match="orders K >= 2"):
        dataclasses.replace(spec, orders=1, tail_ratio=[])


def test_a_space_dyed_model_of_the_orders_renders_its_dye(mono, order_model):
    """``albedo`` a bitmap on the cylinder's UV with the mlp backend: the model's orders read
    once per hit and weighted by the texture's albedo, against the model's orders dyed in
    numpy at 550 nm (within 1%)."""
    from mitsuba_ext.neural import DrJitMLP

    mi = mono
    _, models = order_model
    spec, _, where = models["orders"]
    mlp = DrJitMLP(where / "weights.npz")
    lam = list(spec.wavelength).index(550.0)
    rho_of = np.asarray(spec.tail_ratio)[0, :, lam]

    def S_of(pi_, ti, po, to):
        shape = np.broadcast_shapes(*(np.shape(v) for v in (pi_, ti, po, to)))
        q = [np.broadcast_to(np.asarray(v, np.float64), shape).ravel() for v in (pi_, ti, po, to)]
        parts = [S_k[:, lam] for S_k in order_channels(spec, mlp.eval(*q, orders=True))]
        return dyed(parts, 0.6, np.interp(q[1], spec.tail_ratio_theta_i, rho_of)).reshape(shape)

    bitmap = {"type": "bitmap", "data": mi.TensorXf(np.full((1, 2, 3), 0.6, np.float32)), "filter_type": "nearest",
              "raw": True}
    bsdf = {"type": "fiber_bundle", "backend": "mlp", "model": str(where / "weights.npz"), "albedo": bitmap,
            "wavelength": 550.0, "up": closure.UP}
    pairs = closure.direction_pairs(cone_offsets_deg=(0.8, -1.7))[::2]
    r = np.array([row[3] for row in closure.far_field_ratios(mi, bsdf, 0.2, S_of, pairs, spp=64)])
    print(np.round(r, 4))
    assert len(r) >= 6 and np.allclose(r, 1.0, atol=0.01), r
