"""Importance sampling of fiber tables: the pdf is the density of the samples, and the
Dr.Jit twin draws the same samples and evaluates the same pdf and values as numpy."""

import numpy as np
import pytest

from models.fiber.base import FiberTable, Lobe
from models.fiber.longitudinal import Longitudinal
from models.fiber.mie import MieFiber
from models.fiber.patterns import PatternFiber
from models.fiber.ray import RayFiber
from models.fiber.sampling import FiberSampler

WL = np.array([450.0, 650.0])
NODES = np.deg2rad(np.arange(0, 91, 15.0))


def dense_table():
    to = np.linspace(-np.pi / 2, np.pi / 2, 61)
    ph = -np.pi + 2 * np.pi * np.arange(72) / 72
    N = (1 + np.cos(ph))[None, None, :, None] * np.exp(-(to[None, :, None, None] + NODES[:, None, None, None]) ** 2
                                                       / 0.1) * np.ones((1, 1, 1, 2))
    return FiberTable(NODES, to, ph, WL, [Lobe("d", Longitudinal("none"), N.astype(np.float32))], {})


TABLES = {
    "ray": lambda: RayFiber(WL, [1.56, 1.54], [0.5, 0.1], 0.3, 0.3, 2.0, n_h=64).tabulate(NODES),
    "mie": lambda: MieFiber(WL, 2.0, [1.56, 1.54], [1e-3, 0.0], 3.0).tabulate(NODES),
    "grid": lambda: PatternFiber(WL, "grid").tabulate(NODES),
    "dense": dense_table,
}


@pytest.fixture(scope="module", params=list(TABLES))
def table(request):
    return TABLES[request.param]()


@pytest.mark.parametrize("theta_i", [0.3, -0.7, 1.2])
def test_samples_follow_the_pdf(table, theta_i):
    sampler = FiberSampler(table)
    rng = np.random.default_rng(0)
    n = 200_000
    theta_o, dphi = sampler.sample(np.full(n, theta_i), rng.uniform(size=(5, n)))
    # chi-square of a 12 x 12 histogram against the pdf integrated over each cell
    H, _, _ = np.histogram2d(theta_o, dphi, bins=[12, 12], range=[[-np.pi / 2, np.pi / 2], [-np.pi, np.pi]])
    k = 40
    xs = -np.pi / 2 + (np.arange(12 * k) + 0.5) * np.pi / (12 * k)
    ys = -np.pi + (np.arange(12 * k) + 0.5) * 2 * np.pi / (12 * k)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    P = sampler.pdf(theta_i, X, Y) * (np.pi / (12 * k)) * (2 * np.pi / (12 * k))
    assert P.sum() == pytest.approx(1.0, abs=5e-3)  # the pdf integrates to one
    expected = P.reshape(12, k, 12, k).sum(axis=(1, 3)) * n
    m = expected > 50
    chi2 = np.sum((H[m] - expected[m]) ** 2 / expected[m]) / m.sum()
    assert chi2 < 1.6
    # f cos / pdf estimates the albedo of the interpolated table
    f = table.eval_spectrum(np.full(n, theta_i), theta_o, dphi)
    est = (f * (np.cos(theta_o) / sampler.pdf(theta_i, theta_o, dphi))[:, None]).mean(axis=0)
    assert np.allclose(est, table.albedo(np.array(theta_i)), rtol=0.01)


def test_drjit_twin_matches_numpy(table, mi_llvm):
    import drjit as dr

    from models.fiber.longitudinal import i0e
    from models.fiber.sampling_drjit import DrJitFiber

    mi = mi_llvm
    from scipy import special
    x = np.linspace(0, 60, 601)
    assert np.allclose(i0e(mi.Float(x), dr).numpy(), special.i0e(x), rtol=5e-7)

    sampler = FiberSampler(table)
    twin = DrJitFiber(table, sampler, mi.Float)
    rng = np.random.default_rng(1)
    n = 100_000
    th = rng.uniform(-1.5, 1.5, n)
    u = rng.uniform(size=(5, n)).astype(np.float32).astype(np.float64)
    to_d, dp_d = twin.sample(mi.Float(th), [mi.Float(a) for a in u])
    dr.eval(to_d, dp_d)
    to_d, dp_d = to_d.numpy().astype(float), dp_d.numpy().astype(float)
    to_n, dp_n = sampler.sample(th, u)
    same = (np.abs(to_d - to_n) < 1e-3) & (np.abs(np.angle(np.exp(1j * (dp_d - dp_n)))) < 1e-3)
    assert same.mean() > 0.9995  # float32 against float64 only moves samples at cell edges
    pdf_d = twin.pdf(mi.Float(th), mi.Float(to_d), mi.Float(dp_d)).numpy()
    pdf_n = sampler.pdf(th, to_d, dp_d)
    # samples stay EDGE inside their cell, so float32 and float64 agree on the cell everywhere
    assert np.all(np.abs(pdf_d - pdf_n) <= 1e-3 * np.maximum(pdf_n, 1e-3 * pdf_n.max()))
    f_d = np.stack([a.numpy() for a in twin.eval_spectrum(mi.Float(th), mi.Float(to_d), mi.Float(dp_d))], -1)
    f_n = table.eval_spectrum(th, to_d, dp_d)
    assert np.mean(np.abs(f_d - f_n) <= 1e-3 * np.abs(f_n).max()) > 0.999
    a_d = np.stack([a.numpy() for a in twin.albedo(mi.Float(th))], -1)
    assert np.allclose(a_d, table.albedo(th), rtol=1e-5)
