"""Tabulated data: Xia et al. 2023 raw files (synthetic) and the generic npz format."""

import numpy as np
import pytest

from models.fiber.base import FiberTable
from models.fiber.table import XIA_SHAPE, load_npz, load_xia2023

T_O = -np.pi / 2 + np.pi * np.arange(XIA_SHAPE[0]) / XIA_SHAPE[0]
P_O = 2 * np.pi * np.arange(XIA_SHAPE[1]) / XIA_SHAPE[1]


def write_xia(root, k, L, pol, raw):
    d = root / f"theta-{k}-phi-0"
    d.mkdir(exist_ok=True)
    raw.astype("<f4").tofile(d / f"fiber_1_lambda{L}_T{pol}_depth0.binary")


def forward_peak(k, scale=1.0):
    """A blob at their forward direction: t = t_inc, p = 0."""
    t_inc = -np.pi / 2 + np.pi * k / 180
    dp = np.angle(np.exp(1j * P_O))
    return scale * np.exp(-((T_O[:, None] - t_inc) ** 2 + dp[None, :] ** 2) / (2 * 0.05**2)) + 1e-3


def test_xia_frame_and_normalization(tmp_path):
    # k = 60: t_inc = -30 deg, so our theta_i = +30 deg; k = 120 mirrors to theta_i = 30... use 150: -60 deg
    for k in (60, 150):
        for L in (0, 25):
            write_xia(tmp_path, k, L, "M", forward_peak(k, 2.0))
            write_xia(tmp_path, k, L, "E", forward_peak(k, 1.0))
    table = load_xia2023(tmp_path, albedo=0.8)
    assert np.allclose(np.rad2deg(table.theta_i), [30.0, 60.0])
    assert np.allclose(table.wavelength, [400.0, 700.0])
    # normalized with DESIGN's cell rule; the table integrates its linear interpolant
    assert np.allclose(table.energy(), 0.8, rtol=1e-4)
    for ti_deg, mirrored in ((30.0, False), (60.0, True)):
        ti = np.deg2rad(ti_deg) * (-1 if mirrored else 1)
        # the original incidence of k=150 is theta_i = -60 deg: look it up there
        theta_o = np.linspace(-1.5, 1.5, 301)
        dphi = np.linspace(-np.pi, np.pi, 721)
        T, P = np.meshgrid(theta_o, dphi, indexing="ij")
        f = table.eval(phi_i=0.0, theta_i=ti, phi_o=P, theta_o=T, wavelength=550.0)
        i, j = np.unravel_index(np.argmax(f), f.shape)
        assert theta_o[i] == pytest.approx(-ti, abs=0.02)        # forward: theta_o = -theta_i
        assert abs(abs(dphi[j]) - np.pi) < 0.02                   # forward: dphi = pi


def test_xia_truncated_file_refused(tmp_path):
    write_xia(tmp_path, 60, 0, "M", forward_peak(60))
    d = tmp_path / "theta-60-phi-0"
    (d / "fiber_1_lambda0_TE_depth0.binary").write_bytes(b"\0" * 1000)
    with pytest.raises(ValueError, match="truncated"):
        load_xia2023(tmp_path)


def test_xia_missing_polarization_refused(tmp_path):
    write_xia(tmp_path, 60, 0, "M", forward_peak(60))
    with pytest.raises(ValueError, match="TE"):
        load_xia2023(tmp_path)


def test_xia_empty_directory_refused(tmp_path):
    with pytest.raises(ValueError, match="no files"):
        load_xia2023(tmp_path)


def test_npz_named_axes_any_order(tmp_path):
    axes = {"theta_i": np.deg2rad([0.0, 45.0, 90.0]), "theta_o": np.linspace(-np.pi / 2, np.pi / 2, 31),
            "phi": -np.pi + 2 * np.pi * np.arange(36) / 36, "wavelength": np.array([500.0, 600.0])}
    f = np.full((3, 31, 36, 2), 1 / (4 * np.pi))
    order = ["wavelength", "phi", "theta_o", "theta_i"]
    np.savez(tmp_path / "f.npz", values=np.transpose(f, [3, 2, 1, 0]), axes=np.array(order), **axes)
    table = load_npz(tmp_path / "f.npz")
    assert table.eval(phi_i=0.0, theta_i=0.3, phi_o=1.0, theta_o=-0.2, wavelength=550.0) == pytest.approx(1 / (4 * np.pi))
    assert np.allclose(table.energy(), 1.0, atol=2e-3)  # trapezoid in theta_o on 31 nodes
    np.savez(tmp_path / "bad.npz", values=f[:, :, :, :1], axes=np.array(["theta_i", "theta_o", "phi", "wavelength"]), **axes)
    with pytest.raises(ValueError, match="shape"):
        load_npz(tmp_path / "bad.npz")


def test_fiber_table_roundtrip_and_corruption(tmp_path):
    from models.fiber.patterns import PatternFiber

    table = PatternFiber([500.0, 600.0], "grid").tabulate(np.deg2rad([0.0, 45.0, 90.0]))
    table.save(tmp_path / "t.npz")
    again = FiberTable.load(tmp_path / "t.npz")
    args = dict(phi_i=0.1, theta_i=0.4, phi_o=1.0, theta_o=np.linspace(-1.5, 1.5, 50), wavelength=550.0)
    assert np.array_equal(table.eval(**args), again.eval(**args))
    (tmp_path / "t.npz").write_bytes((tmp_path / "t.npz").read_bytes()[:500])
    with pytest.raises(ValueError, match="re-run"):
        FiberTable.load(tmp_path / "t.npz")
    with pytest.raises(ValueError, match="radians"):
        table.eval(phi_i=0.0, theta_i=45.0, phi_o=0.0, theta_o=0.0, wavelength=500.0)  # degrees by mistake
