"""Longitudinal lobes integrate to one with the cosine and peak on the specular cone."""

import numpy as np
import pytest
from scipy import integrate

from models.fiber.longitudinal import Longitudinal


@pytest.mark.parametrize("lobe", [
    Longitudinal("deon", v=0.3), Longitudinal("deon", v=1e-3), Longitudinal("deon", v=1e-5),
    Longitudinal("deon", v=0.05, shift=0.1), Longitudinal("uniform"), Longitudinal("stripes", n_stripes=5),
])
@pytest.mark.parametrize("theta_i", [0.0, 0.7, -1.2, 1.55])
def test_normalized(lobe, theta_i):
    g = lambda t: lobe(theta_i, t) * np.cos(t)  # noqa: E731
    points = np.linspace(-np.pi / 2, np.pi / 2, 21) if lobe.kind == "stripes" else [-(theta_i + lobe.shift)]
    points = [p for p in np.atleast_1d(points) if -np.pi / 2 < p < np.pi / 2]
    value, _ = integrate.quad(g, -np.pi / 2, np.pi / 2, points=points or None, limit=400, epsabs=1e-12)
    assert value == pytest.approx(1.0, abs=2e-6)


def test_deon_peaks_on_cone_and_is_finite_for_tiny_variance():
    t = np.linspace(-np.pi / 2, np.pi / 2, 20001)
    M = Longitudinal("deon", v=1e-4)(0.5, t)
    assert np.all(np.isfinite(M))
    assert t[np.argmax(M)] == pytest.approx(-0.5, abs=1e-3)
