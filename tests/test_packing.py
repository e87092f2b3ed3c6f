"""A model of a family of bakes with the packing fraction as an input (models.fit.prepare_family)
and ``fiber_bundle``'s ``packing``: on a synthetic family whose light grows linearly with the
packing and whose passthrough falls with it, so that what the model should answer is known."""

import dataclasses

import numpy as np
import pytest

from models.fit import fit, prepare_family
from models.neural import fold_table, make_export_module, rounding_bound, save_onnx, save_weights
from tests.synthetic import make_config, synthetic_table

PACKINGS = [0.1, 0.2, 0.3, 0.4]


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """Two seeds per packing (the second 2% brighter: an arrangement's spread), a tiny model
    trained on all of them, written as weights.npz and model.onnx."""
    tmp = tmp_path_factory.mktemp("packing")
    cfg = make_config(tmp)
    base = synthetic_table(cfg, tmp / "t.npz", passthrough=0.3).expanded()
    members = [(p, base._replace(values=(base.values * (0.5 + p) * k).astype(np.float32),
                                 stderr=(base.stderr * (0.5 + p)).astype(np.float32),
                                 passthrough=np.full_like(base.passthrough, 0.5 - p)))
               for p in PACKINGS for k in (1.0, 1.02)]
    c = cfg.train.model_copy(update={"inputs": ["packing"], "epochs": 80, "patience": 80})
    problem = prepare_family(members, c, "")
    spec = dataclasses.replace(problem.base, hidden=[16, 16])
    model, *_ = fit(spec, problem, c, "family")
    save_weights(tmp / "weights.npz", spec, model)
    save_onnx(tmp / "model.onnx", spec, model)
    return members, problem, spec, model, tmp


def test_a_family_is_folded_member_by_member_with_its_packing(family):
    """The range, the passthrough per packing (the seeds' mean; after the fit also at the
    gain's nodes between them, on the family's line) and every member's samples with its
    packing as a constant input; each member's energy weights give its own albedo."""
    members, problem, spec, _, _ = family
    assert spec.inputs == ["packing"] and spec.input_range == {"packing": [0.1, 0.4]}
    assert problem.base.packings == PACKINGS and set(PACKINGS) < set(spec.packings)
    np.testing.assert_allclose(np.asarray(problem.base.passthrough_packing)[:, 0], [0.5 - p for p in PACKINGS])
    np.testing.assert_allclose(np.asarray(spec.passthrough_packing)[:, 0], [0.5 - p for p in spec.packings])
    one = fold_table(members[0][1], spec, {"packing": 0.1})
    data = problem.data
    assert len(data.S) == len(members) * len(one.S) and np.all(data.extra_cell[: len(one.S)] == 0.1)
    sums = np.zeros_like(data.albedo)
    np.add.at(sums, data.group, data.S * data.omega[:, None])
    np.testing.assert_allclose(sums, data.albedo, rtol=1e-6)
    assert len(data.albedo) == len(members) * len(one.albedo)


def test_the_model_follows_the_packing_and_every_backend_agrees(family, mi_llvm):
    """The family's light grows as (0.5 + p): the model's ratio between the ends is the
    family's within 15% (a tiny model, 80 epochs), and at a packing between the trained ones
    it lies between its neighbours; PyTorch, onnxruntime and Dr.Jit agree within the derived
    float32 bound with the packing as the fifth input."""
    import torch

    from mitsuba_ext.neural import DrJitMLP, OnnxMLP

    _, _, spec, model, tmp = family
    rng = np.random.default_rng(0)
    n = 2000
    angles = np.stack([np.zeros(n), rng.uniform(0.2, 1.2, n), rng.uniform(-np.pi, np.pi, n), np.zeros(n)], -1)
    angles[:, 3] = -angles[:, 1]            # on the specular cone, where the light is
    module = make_export_module(spec, model).eval()

    def S(p):
        q = np.c_[angles, np.full(n, p)].astype(np.float32)
        with torch.no_grad():
            return q, module(torch.from_numpy(q)).numpy().astype(np.float64)
    lo, hi, mid = S(0.1)[1].sum(), S(0.4)[1].sum(), S(0.25)[1].sum()
    assert abs((hi / lo) / (0.9 / 0.6) - 1) < 0.15 and lo < mid < hi
    q, ref = S(0.25)
    tol = 2 * rounding_bound(spec, DrJitMLP(tmp / "weights.npz").layers, q)[1]
    onnx = OnnxMLP(tmp / "model.onnx").eval(*q.T).astype(np.float64)
    jit = DrJitMLP(tmp / "weights.npz").eval(*q.T).astype(np.float64)
    assert np.all(np.abs(onnx - ref) <= tol) and np.all(np.abs(jit - ref) <= tol)


def test_fiber_bundle_takes_the_packing_within_the_trained_range(family, mi_plugins):
    """``packing`` sets the model's input and the passthrough (linear between the trained
    packings); outside the range, missing, with a table or with a one-ply model it is refused
    by name; an edit through ``mi.traverse`` changes what the BSDF returns."""
    import drjit as dr

    mi = mi_plugins
    _, _, spec, _, tmp = family
    bsdf = mi.load_dict({"type": "fiber_bundle", "backend": "mlp", "model": str(tmp / "weights.npz"),
                         "packing": 0.25})
    P = bsdf.backend.passthrough(mi.Float(0.0), mi.Float(0.5))
    np.testing.assert_allclose(np.asarray(P), 0.25, atol=1e-6)

    def value():
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        si.wi = mi.Vector3f(0.6, 0.0, 0.8)
        si.dp_du, si.n = mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1)
        return float(np.asarray(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(-0.6, 0.0, 0.8))).mean())
    before = value()
    params = mi.traverse(bsdf)
    params["packing"] = 0.4
    params.update()
    assert value() > before
    for props, message in (({"packing": 0.6}, "outside 0.1 .. 0.4"), ({}, "give 'packing'"),
                           ({"packing": 0.45}, "does not extrapolate")):
        with pytest.raises(Exception, match=message):
            mi.load_dict({"type": "fiber_bundle", "backend": "onnx", "model": str(tmp / "model.onnx"), **props})
    synthetic_table(make_config(tmp, name="one"), tmp / "one.npz")
    with pytest.raises(Exception, match="holds the one packing"):
        mi.load_dict({"type": "fiber_bundle", "table": str(tmp / "one.npz"), "packing": 0.2})


def test_the_energy_gain_holds_each_trained_packings_albedo(family):
    """One gain per trained packing: at every packing and incident longitude, the seeds'
    albedo summed equals the model's (its bin averages at the gain's 8 x 8 midpoints, the
    gain applied) to float32 rounding; a gain pooled over packings would leave the family's
    slope in it."""
    from models.fit import model_bin_averages

    _, problem, spec, model, _ = family
    data = problem.data
    assert np.asarray(spec.gain).shape == (len(spec.packings), len(spec.gain_theta_i), 3)
    assert set(PACKINGS) <= set(spec.packings)
    S = model_bin_averages(spec, model, data.cell, k=8, extra_cell=data.extra_cell)
    albedo = np.zeros_like(data.albedo)
    np.add.at(albedo, data.group, S * data.omega[:, None])
    key = np.zeros(len(albedo), int)
    theta = np.zeros(len(albedo))
    key[data.group] = np.searchsorted(PACKINGS, data.extra_cell[:, 0, 0])
    theta[data.group] = np.abs(data.cell[:, 1])
    for k in range(len(PACKINGS)):
        for t in np.unique(np.round(theta, 9)):
            rows = (key == k) & np.isclose(theta, t)
            # the gain was computed from the network's float32 outputs and is applied here by the
            # exported float32 graph (its own expm1 form): a few float32 roundings per value, so
            # ~1e-6 relative; 2e-5 leaves ten times that, far below a pooled gain's miss (~1e-2)
            np.testing.assert_allclose(albedo[rows].sum(0), data.albedo[rows].sum(0), rtol=2e-5)


def trained_only(spec):
    """``spec`` with its per-packing data at the trained packings alone (the gain linear
    between them, the network's own interpolation inside)."""
    keep = [k for k, q in enumerate(spec.packings) if q in PACKINGS]
    pick = lambda a: [a[k] for k in keep] if a else a  # noqa: E731
    return dataclasses.replace(spec, packings=pick(spec.packings), gain=pick(spec.gain),
                               passthrough_packing=pick(spec.passthrough_packing), tail_ratio=pick(spec.tail_ratio))


def model_albedo(problem, spec, model, seeds, q):
    """The model's albedo per group of the first member (its directions), read at packing ``q``
    (its bin averages at 8 x 8 midpoints); ``seeds`` members per packing."""
    from models.fit import model_bin_averages

    data = problem.data
    G = len(data.albedo) // (seeds * len(PACKINGS))   # the groups of one member
    first = data.group < G
    S = model_bin_averages(spec, model, data.cell[first], k=8, extra_cell=np.full((first.sum(), 1, 2), q))
    out = np.zeros((G, S.shape[1]))
    np.add.at(out, data.group[first], S * data.omega[first, None])
    return out


def test_between_trained_packings_the_albedo_is_linear(family):
    """The synthetic family's light grows linearly with the packing, so its albedo between two
    trained packings is the straight line between theirs. The gain's nodes between them
    (``models.fit.packing_gains``) put the model's albedo on that line at each node, to float32
    rounding (the monotone cubic through the trained packings reproduces a line). Without them
    (the converse: the gain of the trained packings alone, linear between them) the network's
    own interpolation misses the line by more."""
    _, problem, spec, model, _ = family
    data = problem.data
    inside = [q for q in spec.packings if q not in PACKINGS]
    assert len(inside) == 3 * (len(PACKINGS) - 1)
    G = len(data.albedo) // (2 * len(PACKINGS))

    def line(q):   # the seeds' albedo, linear between the trained packings around q
        k = int(np.searchsorted(PACKINGS, q)) - 1
        w = (q - PACKINGS[k]) / (PACKINGS[k + 1] - PACKINGS[k])
        mean = [(data.albedo[2 * j * G:(2 * j + 1) * G] + data.albedo[(2 * j + 1) * G:(2 * j + 2) * G]) / 2
                for j in (k, k + 1)]
        return (1 - w) * mean[0] + w * mean[1]

    misses = []
    for q in inside:
        np.testing.assert_allclose(model_albedo(problem, spec, model, 2, q), line(q), rtol=2e-5)
        misses.append(np.max(np.abs(model_albedo(problem, trained_only(spec), model, 2, q) / line(q) - 1)))
    assert max(misses) > 1e-3, misses


def test_between_trained_packings_a_bending_family_is_followed_closer_than_by_its_chords(tmp_path):
    """A family that bends as a ply's does: its light grows as ``1 - exp(-p / 0.1)`` (ever more
    slowly as the ply fills), its passthrough falls as ``0.05 + 0.6 exp(-p / 0.1)``. Between the
    trained packings the straight line (the chord) cuts under the albedo's curve, by 3.7% at
    worst at the gain's nodes, and over the passthrough's, by 9.3%. The model's albedo there,
    and its passthrough, lie within 0.4 of the chord's miss of the closed form (a monotone
    cubic through the four packings: 1.1% and 2.1%), and its albedo is that cubic's
    (:func:`models.fit.along_packing`) to float32 rounding."""
    from models.fit import along_packing
    from models.neural import between

    cfg = make_config(tmp_path)
    base = synthetic_table(cfg, tmp_path / "t.npz", passthrough=0.3).expanded()
    law = lambda p: 1 - np.exp(-p / 0.1)  # noqa: E731
    passthrough = lambda p: 0.05 + 0.6 * np.exp(-p / 0.1)  # noqa: E731
    members = [(p, base._replace(values=(base.values * law(p)).astype(np.float32),
                                 stderr=(base.stderr * law(p)).astype(np.float32),
                                 passthrough=np.full_like(base.passthrough, passthrough(p))))
               for p in PACKINGS]
    c = cfg.train.model_copy(update={"inputs": ["packing"], "epochs": 80, "patience": 80})
    problem = prepare_family(members, c, "")
    spec = dataclasses.replace(problem.base, hidden=[16, 16])
    model, *_ = fit(spec, problem, c, "bending family")
    data = problem.data
    G = len(data.albedo) // len(PACKINGS)
    at_trained = np.stack([data.albedo[j * G:(j + 1) * G] for j in range(len(PACKINGS))])
    one = data.albedo[:G] / law(PACKINGS[0])   # the family's albedo per unit of its law
    inside = [q for q in spec.packings if q not in PACKINGS]
    albedo_miss, chord_miss, pass_miss, pass_chord = [], [], [], []
    for q in inside:
        A = model_albedo(problem, spec, model, 1, q)
        np.testing.assert_allclose(A, along_packing(PACKINGS, at_trained, q), rtol=2e-5)
        albedo_miss.append(np.max(np.abs(A / (one * law(q)) - 1)))
        chord_miss.append(np.max(np.abs(np.interp(q, PACKINGS, law(np.array(PACKINGS))) / law(q) - 1)))
        T = between(np.clip, np.float64(q), spec.packings, np.asarray(spec.passthrough_packing), False)
        pass_miss.append(np.max(np.abs(T / passthrough(q) - 1)))
        pass_chord.append(abs(np.interp(q, PACKINGS, passthrough(np.array(PACKINGS))) / passthrough(q) - 1))
    assert max(chord_miss) > 0.03 and max(pass_chord) > 0.09
    assert max(albedo_miss) < 0.4 * max(chord_miss), (albedo_miss, chord_miss)
    assert max(pass_miss) < 0.4 * max(pass_chord), (pass_miss, pass_chord)


# ----------------------------------------------------------------------------------
# A family of orders: packing and dye from one model
# ----------------------------------------------------------------------------------

DYE = np.array([0.9, 0.5, 0.3])   # a per-event albedo at the synthetic table's three wavelengths


def with_orders(table, p):
    """A member with its orders of scattering (K = 3) falling by decades, as a ply's do, and
    growing with the packing, as a denser ply's do: shares ``1 - 0.011 (1 + p)``, ``0.01 (1 +
    p)`` and ``0.001 (1 + p)`` of ``S``, the tail's ratio ``0.3 + p``."""
    shares = np.array([1 - 0.011 * (1 + p), 0.01 * (1 + p), 0.001 * (1 + p)])[:, None, None, None, None, None]
    return table._replace(orders=(table.values[None] * shares).astype(np.float32),
                          orders_stderr=(table.stderr[None] * shares).astype(np.float32),
                          tail_ratio=np.full(table.values.shape[:2] + table.values.shape[-1:], 0.3 + p))


def fit_orders(members, tmp):
    c = make_config(tmp, name="orders").train.model_copy(update={"inputs": ["packing"], "orders": True, "epochs": 40,
                                                                  "patience": 40})
    problem = prepare_family(members, c, "")
    spec = dataclasses.replace(problem.base, hidden=[16, 16])
    model, *_ = fit(spec, problem, c, "family of orders")
    return problem, spec, model


@pytest.fixture(scope="module")
def order_family(family):
    """The family above with its orders (:func:`with_orders`), a tiny model of them."""
    members, _, _, _, tmp = family
    members = [(p, with_orders(t, p)) for p, t in members]
    problem, spec, model = fit_orders(members, tmp)
    save_weights(tmp / "orders.npz", spec, model)
    return members, problem, spec, model, tmp


def test_each_order_is_fitted_in_a_log_space_of_its_own(order_family, monkeypatch):
    """Each order is fitted relative to its own scale (``models.fit.order_scales``: the mean of
    its positive values), folded into the exported gain, so the gain beside the scale is the
    fit's own correction: within a factor 2 of 1 for every packing, longitude and output.
    With one scale for all (its converse, tried here) the network leaves the small orders near
    zero and their gains would grow tenfold and more (fireflies wherever the model is read off
    the bins it was fitted on): they are held at ``GAIN_LIMIT``."""
    from models import fit as fitting

    members, problem, spec, _, tmp = order_family
    scale = fitting.order_scales(problem.base, problem.data)
    assert scale[0] / scale[-1] > 100   # order 1 against the tail
    assert np.all((np.asarray(spec.gain) / scale > 0.5) & (np.asarray(spec.gain) / scale < 2))
    monkeypatch.setattr(fitting, "order_scales", lambda spec, data: np.ones(spec.n_outputs))
    _, one_scale, _ = fit_orders(members, tmp)
    assert np.isclose(np.asarray(one_scale.gain).max(), fitting.GAIN_LIMIT)


def test_a_family_of_orders_is_dyed_at_every_trained_packing(order_family):
    """Each order's albedo is held per trained packing by its gain, so the dyed model's albedo,
    ``dyed(order albedos, a, rho)`` with the tail's ratio the model keeps at that packing, is
    the seeds' recoloured tables' to float32 rounding, at every packing and incident longitude;
    the tail's ratio is kept per packing node (the seeds' mean at the trained ones, on the
    family's line between them)."""
    from models.bundle_table import dyed
    from models.fit import model_bin_averages

    members, problem, spec, model, _ = order_family
    data = problem.data
    assert spec.orders == 3 and np.asarray(spec.tail_ratio).shape == (len(spec.packings), 1, 13, 3)
    np.testing.assert_allclose(np.asarray(spec.tail_ratio)[:, 0, 0, 0], [0.3 + p for p in spec.packings])
    S = model_bin_averages(spec, model, data.cell, k=8, extra_cell=data.extra_cell, orders=True)
    albedo = np.zeros_like(data.albedo)           # [groups, K x lambda]: each order's
    np.add.at(albedo, data.group, S * data.omega[:, None])
    key, theta = np.zeros(len(albedo), int), np.zeros(len(albedo))
    key[data.group] = np.searchsorted(PACKINGS, data.extra_cell[:, 0, 0])
    theta[data.group] = np.abs(data.cell[:, 1])
    split = lambda a: [a[..., k * 3:(k + 1) * 3] for k in range(3)]  # noqa: E731
    for k, p in enumerate(PACKINGS):
        rho = np.asarray(spec.tail_ratio[spec.packings.index(p)])[0, 0]
        want = np.mean([t.recolour(DYE).scattered for q, t in members if q == p], 0)[0]   # [theta_i, lambda]
        for j, t in enumerate(members[0][1].theta_i):
            rows = (key == k) & np.isclose(theta, abs(t))
            model_dyed = dyed(split(albedo[rows].sum(0)), DYE, rho)
            table_dyed = dyed(split(data.albedo[rows].sum(0)), DYE, rho)
            np.testing.assert_allclose(model_dyed, table_dyed, rtol=2e-5)
            np.testing.assert_allclose(table_dyed / rows.sum(), want[j], rtol=1e-5)


def test_a_family_backend_reads_each_lane_at_its_own_packing(order_family, mi_llvm):
    """``at_packing`` with one packing per lane (a texture's, per hit): each lane's value, its
    passthrough and its tail's ratio are those of the backend set to that packing alone, on
    the family's lines between the trained packings (the synthetic family's passthrough is
    ``0.5 - p``, its tail's ratio ``0.3 + p``)."""
    import drjit as dr

    from mitsuba_ext.backends import MLPBackend

    *_, tmp = order_family
    lanes = np.array([0.1, 0.17, 0.25, 0.4])
    backend = MLPBackend(tmp / "orders.npz", mi_llvm.Float, packing=0.2)
    view = backend.at_packing(mi_llvm.Float(lanes))
    angles = [mi_llvm.Float(np.full(4, v)) for v in (0.0, 0.5, 2.0, -0.5)]
    S = np.array([np.asarray(s) for s in view.eval(*angles)])
    _, rho = view.eval_orders(*angles)
    np.testing.assert_allclose(np.asarray(view.passthrough(angles[0], angles[1])), 0.5 - lanes, atol=1e-6)
    np.testing.assert_allclose(np.array([np.asarray(r) for r in rho]), np.tile(0.3 + lanes, (3, 1)), atol=1e-6)
    for i, p in enumerate(lanes):
        backend.set_packing(p)   # the two packing nodes around p alone
        one = np.array([np.asarray(s)[0] for s in backend.eval(*(a[i] for a in angles))])
        np.testing.assert_allclose(S[:, i], one, rtol=1e-5)
        np.testing.assert_allclose(np.asarray(backend.passthrough(angles[0][i], angles[1][i])), 0.5 - p, atol=1e-6)
        _, rho_one = backend.eval_orders(*(a[i] for a in angles))
        np.testing.assert_allclose([np.asarray(r)[0] for r in rho_one], np.full(3, 0.3 + p), atol=1e-6)
    assert np.ptp(S[0]) > 0 and dr.width(view.constants[0]) == 4


def test_a_uniform_packing_is_read_between_its_two_packing_nodes(order_family, mi_llvm):
    """A uniform packing keeps only the two packing nodes around it (``bracketed``): the
    gain and the passthrough there are the full family's, at the nodes and between them; the
    backend set to a packing traces that pair. A pair read outside its own interval (clamped
    at its ends) is not the family: the comparison can fail."""
    from mitsuba_ext.backends import MLPBackend
    from models.neural import between, bracketed, energy_gain

    *_, spec, _, tmp = order_family
    theta = np.linspace(-1.5, 1.5, 7)
    for p in (0.1, 0.15, 0.2, 0.27, 0.3, 0.4):
        pair = bracketed(spec, p)
        assert len(pair.packings) == 2 and pair.packings[0] <= p <= pair.packings[1]
        assert pair.input_range == spec.input_range
        np.testing.assert_allclose(energy_gain(np, pair, theta, np.full(7, p)),
                                   energy_gain(np, spec, theta, np.full(7, p)), rtol=1e-12)
        np.testing.assert_allclose(between(np.clip, np.float64(p), pair.packings, np.asarray(pair.passthrough_packing),
                                           False),
                                   between(np.clip, np.float64(p), spec.packings, np.asarray(spec.passthrough_packing),
                                           False))
    backend = MLPBackend(tmp / "orders.npz", mi_llvm.Float, packing=0.27)
    assert np.allclose(backend.here.spec.packings, [0.25, 0.275]) and backend.mlp.spec.packings == spec.packings
    far = bracketed(spec, 0.35)
    at = np.full(7, 0.15)
    assert not np.allclose(energy_gain(np, far, theta, at), energy_gain(np, spec, theta, at))


def test_a_packing_texture_sets_the_packing_per_hit(order_family, mi_plugins):
    """``packing`` a bitmap on the UV (two columns, 0.15 and 0.35): a hit on either half
    is what the BSDF with that packing everywhere returns, scattering and passthrough; a
    texture reaching outside the trained range is refused at load, naming its span; the
    dye applies on top."""
    import drjit as dr

    mi = mi_plugins
    *_, tmp = order_family
    model = str(tmp / "orders.npz")

    def bitmap(columns):   # raw: the values as they are (no sRGB decoding)
        return {"type": "bitmap", "raw": True, "filter_type": "nearest",
                "data": mi.TensorXf(np.tile(np.asarray(columns, np.float32)[None, :, None], (2, 1, 1)))}

    def at(bsdf, u):
        si = dr.zeros(mi.SurfaceInteraction3f, len(u))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        si.wi = mi.Vector3f(0.6, 0.0, 0.8)
        si.dp_du, si.n = mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1)
        si.uv = mi.Point2f(mi.Float(u), mi.Float(0.5))
        value = np.asarray(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(-0.6, 0.0, 0.8))).reshape(3, -1).T
        return value, np.asarray(bsdf.eval_attribute_1("passthrough", si))

    u = np.array([0.1, 0.3, 0.7, 0.9])
    for extra in ({}, {"albedo": {"type": "srgb", "color": [0.8, 0.3, 0.2]}}):
        textured = mi.load_dict({"type": "fiber_bundle", "backend": "mlp", "model": model,
                                 "packing": bitmap([0.15, 0.35]), **extra})
        value, P = at(textured, u)
        for lanes, p in ((slice(0, 2), 0.15), (slice(2, 4), 0.35)):
            uniform = mi.load_dict({"type": "fiber_bundle", "backend": "mlp", "model": model, "packing": p, **extra})
            want, want_P = at(uniform, u[lanes])
            np.testing.assert_allclose(value[lanes], want, rtol=1e-5)
            np.testing.assert_allclose(P[lanes], want_P, atol=1e-6)
        assert value[3].sum() > value[0].sum() and P[3] < P[0]
    with pytest.raises(Exception, match=r"'packing' texture: its values span 0.2 .. 0.6"):
        mi.load_dict({"type": "fiber_bundle", "backend": "mlp", "model": model, "packing": bitmap([0.2, 0.6])})


def test_a_family_model_of_the_older_format_is_refused_by_name(family):
    """``bcsdf.neural/5`` kept a family's gain on packing nodes of its own (``gain_packings``)
    and its passthrough on the trained packings; read as ``/6`` the passthrough would sit on the
    wrong nodes. Such a file is refused with the command that rebuilds it; a ``/5`` model
    without those nodes (every one-ply model) still reads."""
    from models.neural import NeuralSpec

    _, _, spec, _, _ = family
    old = {**spec.to_dict(), "format": "bcsdf.neural/5", "gain_packings": list(spec.packings)}
    with pytest.raises(ValueError, match="re-run `bcsdf family`"):
        NeuralSpec.from_dict(old)
    assert NeuralSpec.from_dict({**old, "gain_packings": []}).packings == spec.packings
