"""The energy gain resolved by azimuth (``train.gain_azimuth_bins``, ``models.neural.azimuth_gain``):
on a synthetic table whose spectra ripple from one bin of ``|phi_o - phi_i|`` to the next
(``tests.synthetic.with_ripple``), as a fiber's Mie resonances make a baked table's."""

import dataclasses

import numpy as np
import pytest

from models import errors
from models.fit import azimuth_ratio, fit, model_bin_averages, prepare
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
    the gain by azimuth with orders or extra inputs (config), and metadata of the wrong shape."""
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
