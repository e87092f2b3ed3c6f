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
