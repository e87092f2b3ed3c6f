"""Spectral helpers against colour-science's own spectral integration."""

import colour
import numpy as np
import pytest

from models.spectrum import cauchy, spectrum_to_srgb


@pytest.mark.parametrize("n", [3, 7, 25, 61])
def test_flat_spectrum_is_white(n):
    rgb = spectrum_to_srgb(np.ones(n), np.linspace(400, 700, n))
    assert np.allclose(rgb, 1.0, atol=1e-3)


def test_matches_colour_science_for_a_smooth_spectrum():
    wl = np.linspace(400, 700, 25)
    refl = 0.2 + 0.6 * np.exp(-((wl - 620) / 40) ** 2)  # a red dye
    ours = spectrum_to_srgb(refl, wl)
    sd = colour.SpectralDistribution(dict(zip(wl, refl))).interpolate(colour.SpectralShape(400, 700, 1),
                                                                       interpolator=colour.LinearInterpolator)
    sd = sd.extrapolate(colour.SpectralShape(360, 830, 1))
    xyz = colour.sd_to_XYZ(sd, colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"],
                           colour.SDS_ILLUMINANTS["D65"], method="Integration") / 100
    ref = colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False)
    assert np.allclose(ours, ref, atol=2e-3)
    assert ours[0] > ours[1] > 0 and ours[0] > ours[2]  # red


def test_cauchy():
    assert cauchy(1.5, 0.01, 500.0) == pytest.approx(1.5 + 0.01 / 0.25)
