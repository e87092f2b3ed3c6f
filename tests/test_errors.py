"""The figures of merit of models/errors.py on cases worked by hand."""

import numpy as np

from models import errors


def test_core_l1_keeps_the_fewest_bins_that_hold_the_fraction_and_pools_rows_by_energy():
    # row 0: energies 5, 3, 1, 1 (omega 1): 90% of 10 needs 5 + 3 + 1; the last bin is floor
    # row 1: one bin holds everything
    true = np.array([[1.0, 5.0, 3.0, 1.0], [0.0, 0.0, 2.0, 0.0]])
    pred = true + np.array([[-1.0, 1.0, 0.0, 5.0], [7.0, 0.0, 0.5, 0.0]])
    # kept: row 0 bins 1, 2 and one of the two energy-1 bins (a tie: either), row 1 bin 2
    got = errors.core_l1(pred, true, np.ones(4))
    assert got in (np.float64((1 + 0 + 1 + 0.5) / (5 + 3 + 1 + 2)), np.float64((1 + 0 + 5 + 0.5) / 11))
    # the solid angle weighs the bins: doubling one bin's omega doubles its energy and error
    omega = np.array([1.0, 1.0, 2.0, 1.0])
    assert np.isclose(errors.core_l1(pred, true, omega, fraction=0.5), (1 * 1 + 0 * 2 + 0.5 * 2) / (5 + 6 + 4))
    assert errors.core_l1(true, true, np.ones(4)) == 0.0


def test_a_model_equal_to_the_truth_scores_the_tables_noise():
    """The definition behind "error over noise": a table is its expectation plus Gaussian
    noise of standard error E; the truth measured against the table by ``core_l1`` is, in
    expectation, ``noise_l1`` of the same bins (mean |N(0, E)| = sqrt(2 / pi) E). Checked
    on 200 rows of 400 bins (sampling error of the mean of ~50k |z| ~ 0.3%); ``where``
    restricts both figures to the same bins; a biased model scores more."""
    rng = np.random.default_rng(7)
    truth = np.exp(-((np.linspace(-3, 3, 400)[None] - rng.uniform(-1, 1, (200, 1))) ** 2)) + 1e-3
    E = 0.05 * truth
    table = truth + E * rng.standard_normal(truth.shape)
    omega = rng.uniform(0.5, 1.5, 400)
    held = rng.random(truth.shape) < 0.3
    for where in (None, held):
        error, noise = errors.core_l1(truth, table, omega, where=where), errors.noise_l1(table, E, omega, where=where)
        assert abs(error / noise - 1) < 0.03, (error, noise)
    assert errors.core_l1(1.1 * truth, table, omega) / errors.noise_l1(table, E, omega) > 1.5
    assert errors.error_over_noise(0.1, 0.0) == 0.0
    # by hand: one row, the core is bins 0 and 1 (energy 5 + 4 of 10), noise sqrt(2/pi)(1 + 2)/9
    assert np.isclose(errors.noise_l1([[5.0, 4.0, 1.0]], [[1.0, 2.0, 7.0]], np.ones(3), fraction=0.8),
                      np.sqrt(2 / np.pi) * 3 / 9)
