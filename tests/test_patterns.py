"""Test patterns: exact energies and shapes, the same at every wavelength."""

import numpy as np
import pytest

from models.fiber.patterns import PatternFiber


def test_isotropic_is_uniform_and_lossless():
    fiber = PatternFiber([450.0, 650.0], "isotropic")
    rng = np.random.default_rng(0)
    f = fiber.eval(phi_i=rng.uniform(-3, 3, 100), theta_i=rng.uniform(-1.5, 1.5, 100), phi_o=rng.uniform(-3, 3, 100),
                   theta_o=rng.uniform(-1.5, 1.5, 100), wavelength=450.0)
    assert np.allclose(f, 1 / (4 * np.pi))
    assert fiber.energy(0.3, 450.0) == pytest.approx(1.0, rel=1e-9)
    assert np.allclose(fiber.tabulate(np.deg2rad([0.0, 90.0])).energy(), 1.0, rtol=1e-6)


def test_grid_energy_stripes_and_wavelength_independence():
    fiber = PatternFiber([450.0, 650.0], "grid", n_stripes_theta=6, n_stripes_phi=8, albedo=0.7)
    assert fiber.energy(0.4, 450.0, n_theta=512, n_phi=2048) == pytest.approx(0.7, rel=5e-3)
    table = fiber.tabulate(np.deg2rad([0.0, 45.0, 90.0]))
    assert np.allclose(table.energy(), 0.7, rtol=1e-6)
    # lit and dark stripes alternate in dphi (8 lit bands of 22.5 deg) and in theta_o
    dphi = np.deg2rad(np.arange(-180, 180, 22.5) + 11.25)
    row = fiber.eval(phi_i=0.0, theta_i=0.3, phi_o=dphi, theta_o=np.deg2rad(-82.5), wavelength=450.0)
    assert np.all(row[::2] > 0) and np.all(row[1::2] == 0)
    col = fiber.eval(phi_i=0.0, theta_i=0.3, phi_o=np.deg2rad(-168.75), theta_o=np.deg2rad(np.arange(-82.5, 90, 15)),
                     wavelength=650.0)
    assert np.all(col[::2] > 0) and np.all(col[1::2] == 0)
    same = dict(phi_i=0.0, theta_i=0.3, phi_o=dphi, theta_o=0.2)
    assert np.array_equal(fiber.eval(**same, wavelength=450.0), fiber.eval(**same, wavelength=650.0))
