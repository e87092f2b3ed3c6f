"""The energy gain resolved by azimuth (``train.gain_azimuth_bins``, ``models.neural.azimuth_gain``):
on a synthetic table whose spectra ripple from one bin of ``|phi_o - phi_i|`` to the next
(``tests.synthetic.with_ripple``), as a fiber's Mie resonances make a baked table's."""

import dataclasses

import numpy as np
import pytest

from models import errors
from models.fit import azimuth_ratio, fit, low_rank_log, model_bin_averages, prepare
from models.neural import NeuralSpec, table_cells
from tests.synthetic import make_config, synthetic_table, with_ripple

BINS = 18   # the synthetic table's bins of |phi_o - phi_i|


@pytest.fixture(scope="module")
def ripple(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ripple")
    cfg = make_config(tmp)
    table = with_ripple(synthetic_table(cfg, tmp / "t.npz"), BINS)
    table.save(tmp / "ripple.npz")
    return cfg, table.expanded(), tmp / "ripple.npz"


def trained(cfg, table, path, bins: int):
    c = cfg.train.model_copy(update={"gain_azimuth_bins": bins})
    problem = prepare(table, path, c, "")
    spec = dataclasses.replace(problem.base, hidden=[16, 16])
    model, _, _, _, calibration = fit(spec, problem, c, f"{bins} bins")
    return problem, spec, model, calibration


def test_the_gain_by_azimuth_keeps_the_ripple_a_small_network_smooths(ripple):
    """A [16, 16] network smooths the ripple; with the gain in the table's 18 azimuth bins the
    model's bin averages come within a third of its error, against the table over every bin's
    core (models.errors.core_l1); each incidence's albedo is still the table's (the gain
    after the classes' ratios). Without it (the converse, same network and schedule), the
    error stays large: the comparison can fail."""
    cfg, table, path = ripple
    omega = table.solid_angle.ravel()
    error = {}
    for bins in (0, BINS):
        _, spec, model, calibration = trained(cfg, table, path, bins)
        S = model_bin_averages(spec, model, table_cells(table)).reshape(table.values.shape)
        error[bins] = errors.core_l1(errors.by_rows(S), errors.by_rows(table.values), omega)
        assert calibration["worst_albedo_error_after"] < 0.01
        assert bool(spec.azimuth_gain) == bool(bins)
    assert error[0] > 0.1 and error[BINS] < error[0] / 3, error


def test_the_classes_ratios_read_no_held_out_bin(ripple):
    """A class's ratio is the table's energy over the model's on its *training* samples: a
    held-out sample made a thousand times brighter changes no ratio, a training sample in the
    same class does."""
    cfg, table, path = ripple
    problem, spec, model, _ = trained(cfg, table, path, BINS)
    from models.fit import BinFit, _midpoint_means

    p = BinFit(spec, problem)
    S_model = _midpoint_means(model, p, 4)
    theta = np.abs(problem.data.cell[:, 1])
    nodes = np.unique(np.round(theta, 12))
    at = np.zeros(len(problem.data.albedo), int)
    at[problem.data.group] = np.searchsorted(nodes, np.round(theta, 12))
    before = azimuth_ratio(p, S_model, at, len(nodes), BINS)
    for idx, changes in ((problem.val_idx[0], False), (problem.train_idx[0], True)):
        p.data.S[idx] *= 1000.0
        after = azimuth_ratio(p, S_model, at, len(nodes), BINS)
        p.data.S[idx] /= 1000.0
        assert (not np.allclose(after, before)) == changes


def test_bins_that_split_the_tables_are_refused(ripple, tmp_path):
    """Bins that do not divide the table's 18 are refused naming the table's count; so is
    the gain by azimuth with orders or extra inputs (config), a rank without bins or not below
    the wavelengths' count (config), and metadata of the wrong shape, non-finite, or whose
    product overflows."""
    cfg, table, path = ripple
    with pytest.raises(ValueError, match="must divide the table's 18 bins"):
        prepare(table, path, cfg.train.model_copy(update={"gain_azimuth_bins": 7}), "")
    with pytest.raises(ValueError, match="gain_azimuth_bins"):
        make_config(tmp_path, bake={"orders": 4}, orders=True, gain_azimuth_bins=6)
    spec = dataclasses.replace(prepare(table, path, cfg.train, "").base, hidden=[4])
    good = dict(spec.to_dict(), gain=np.ones((7, 3)).tolist(), gain_theta_i=np.linspace(0, 1.5, 7).tolist())
    NeuralSpec.from_dict(dict(good, azimuth_gain=np.ones((BINS, 7, 3)).tolist()))
    for bad in (np.ones((BINS, 6, 3)), -np.ones((BINS, 7, 3)), np.ones((BINS, 7))):
        with pytest.raises(ValueError, match="azimuth_gain"):
            NeuralSpec.from_dict(dict(good, azimuth_gain=bad.tolist()))
    # a product: coefficients [bin][node][rank] and a basis [rank][output], finite, of matching rank
    NeuralSpec.from_dict(dict(good, azimuth_gain=np.zeros((BINS, 7, 2)).tolist(),
                              azimuth_gain_basis=np.ones((2, 3)).tolist()))
    for coefficients, basis in ((np.zeros((BINS, 7, 2)), np.ones((3, 3))), (np.zeros((BINS, 7, 2)), np.ones((2, 4))),
                                (np.full((BINS, 7, 2), np.nan), np.ones((2, 3))),
                                (np.full((BINS, 7, 2), 400.0), np.ones((2, 3)))):   # exp overflows
        with pytest.raises(ValueError, match="azimuth_gain"):
            NeuralSpec.from_dict(dict(good, azimuth_gain=coefficients.tolist(), azimuth_gain_basis=basis.tolist()))
    for rank in (2, 3):   # without bins; not below the 3 wavelengths
        with pytest.raises(ValueError, match="gain_rank"):
            make_config(tmp_path, gain_azimuth_bins=6 if rank == 3 else 0, gain_rank=rank)


def test_a_log_space_product_of_low_rank_is_recovered_to_float32_rounding():
    """Ratios that are exactly ``exp(C @ V)`` of rank 3 come back from
    :func:`models.fit.low_rank_log` at rank 3 within the float32 rounding of the stored factors
    (each product term rounded twice: ``3 eps32 sum_k |c_k v_k|`` in the exponent), whatever the
    classes' weights, a class of no weight included (its coefficients are its projection)."""
    rng = np.random.default_rng(1)
    C, V = rng.normal(0, 0.3, (12, 5, 3)), rng.normal(0, 0.5, (3, 25))
    ratio = np.exp(C @ V)
    weight = rng.uniform(0, 2, (12, 5))
    weight[0, 0] = 0.0
    coefficients, basis = low_rank_log(ratio, weight, 3)
    assert coefficients.dtype == basis.dtype == np.float32 and basis.shape == (3, 25)
    back = np.exp(coefficients.astype(float) @ basis.astype(float))
    bound = 3 * np.finfo(np.float32).eps * (np.abs(coefficients[..., :, None]) * np.abs(basis)).sum(-2)
    assert np.all(np.abs(np.log(back / ratio)) <= bound + 1e-12)


def test_the_product_follows_the_classes_that_hold_the_light():
    """Rank 1 of classes with two spectral shapes: one heavy class of its own shape and many
    light ones of another. Weighted by energy, the basis is the heavy class's shape (its
    residual within 1% of its values: the light classes, 1/250 of the weight, pull a little);
    with equal weights the many light classes win and it is not. Fails if the weights are
    ignored."""
    rng = np.random.default_rng(2)
    a, b = rng.normal(0, 1, 25), rng.normal(0, 1, 25)
    log_ratio = np.outer(rng.uniform(0.5, 1, 40), a)
    log_ratio[7] = 0.8 * b
    weight = np.full(40, 1e-3)
    weight[7] = 10.0
    for w, heavy_fits in ((weight, True), (np.ones(40), False)):
        coefficients, basis = low_rank_log(np.exp(log_ratio), w, 1)
        residual = np.abs(coefficients[7] @ basis - log_ratio[7]).max()
        assert (residual < 0.01 * np.abs(log_ratio[7]).max()) == heavy_fits, residual


@pytest.fixture(scope="module")
def ripple_of_one_shape(tmp_path_factory):
    """A ripple whose log is one spectral shape in every azimuth bin, scaled per bin:
    ``exp(0.3 sin(7 b) u_l)``, ``u = (1, -0.6, 0.8)``: exactly rank 1 in log space."""
    tmp = tmp_path_factory.mktemp("shape")
    cfg = make_config(tmp)
    table = synthetic_table(cfg, tmp / "t.npz")
    d = np.abs(np.angle(np.exp(1j * (table.phi_o[None, :] - table.phi_i[:, None]))))
    b = np.minimum((d / np.pi * BINS).astype(int), BINS - 1)
    r = np.exp(0.3 * np.sin(7.0 * b)[..., None] * np.array([1.0, -0.6, 0.8]))[:, None, :, None, :]
    table = table._replace(values=(table.values * r).astype(np.float32), stderr=(table.stderr * r).astype(np.float32))
    table.save(tmp / "shape.npz")
    return cfg, table.expanded(), tmp / "shape.npz"


def test_the_gain_as_a_product_keeps_a_ripple_of_its_rank_in_fewer_numbers(ripple_of_one_shape):
    """A ripple of one spectral shape, on top of which the network's own error adds a grey
    factor per class: the classes' log ratios are of rank 2. Stored at rank 2, the gain's error
    is the full gain's (same network) within 3% (the rest is noise off rank 2), against 2.5x as
    much without the azimuthal factor; rank 1 cannot hold both and loses a fifth (the converse:
    the comparison can fail); each incidence's albedo is still the table's within 1%; the model
    stores (bins x nodes + wavelengths) x rank numbers."""
    from models.fit import BinFit, energy_gain

    cfg, table, path = ripple_of_one_shape
    omega = table.solid_angle.ravel()
    c = cfg.train.model_copy(update={"gain_azimuth_bins": BINS, "gain_rank": 2})
    problem = prepare(table, path, c, "")
    spec = dataclasses.replace(problem.base, hidden=[16, 16])
    model, _, _, _, calibration = fit(spec, problem, c, "rank 2")
    assert calibration["worst_albedo_error_after"] < 0.01
    nodes = len(spec.gain_theta_i)
    assert spec.azimuth_gain_values == (BINS * nodes + 3) * 2 and spec.azimuth_gains().shape == (BINS, nodes, 3)

    def error(s):
        S = model_bin_averages(s, model, table_cells(table)).reshape(table.values.shape)
        return errors.core_l1(errors.by_rows(S), errors.by_rows(table.values), omega)

    others = {}
    for rank in (0, 1):   # the same network, its gain stored in full and at rank 1
        others[rank] = dataclasses.replace(spec, azimuth_gain=[], azimuth_gain_basis=[])
        energy_gain(model, others[rank], BinFit(others[rank], problem), azimuth_bins=BINS, rank=rank)
    smooth = dataclasses.replace(others[0], azimuth_gain=[])
    e2, full, e1, e0 = error(spec), error(others[0]), error(others[1]), error(smooth)
    assert e2 < 1.03 * full and e0 > 2 * full and e1 > 1.1 * full, (e2, full, e1, e0)
