"""Test patterns for validating the baker (thesis chapter 4).

* ``isotropic``: a lossless fiber that scatters uniformly over the sphere,
  ``f = 1 / (4 pi)``; a bundle of such fibers must conserve energy exactly.
* ``grid``: bright stripes in theta_o and in dphi, the same at every wavelength, so
  any warping or blurring by the baker shows as bent or smeared grid lines.
"""

from __future__ import annotations

import numpy as np

from .base import FiberModel, FiberTable, Lobe
from .longitudinal import Longitudinal


def stripes_phi(dphi, n_stripes):
    """``n_stripes`` lit bands among ``2 n_stripes`` equal bands of dphi, integral 1."""
    band = np.floor(np.mod(np.asarray(dphi) + np.pi, 2 * np.pi) / (np.pi / n_stripes)).astype(int)
    return np.where(band % 2 == 0, 1.0 / np.pi, 0.0)  # n lit bands of width pi/n: total pi


class PatternFiber(FiberModel):
    """A separable analytic pattern ``f = albedo * M(theta_o) * N(dphi)``."""

    def __init__(self, wavelength, kind, n_stripes_theta=6, n_stripes_phi=8, albedo=1.0, n_phi=720):
        super().__init__(wavelength)
        if kind not in ("isotropic", "grid"):
            raise ValueError(f"unknown pattern {kind!r}: use 'isotropic' or 'grid'")
        self.name, self.albedo, self.n_phi = kind, float(albedo), int(n_phi)
        self.n_stripes_phi = int(n_stripes_phi)
        self.M = (Longitudinal("uniform") if kind == "isotropic"
                  else Longitudinal("stripes", n_stripes=int(n_stripes_theta)))

    def _N(self, dphi):
        if self.name == "isotropic":
            return np.full(np.shape(dphi), 1 / (2 * np.pi))
        return stripes_phi(dphi, self.n_stripes_phi)

    def eval(self, *, phi_i, theta_i, phi_o, theta_o, wavelength):
        ti, pi_, to, po, _ = np.broadcast_arrays(theta_i, phi_i, theta_o, phi_o, wavelength)
        return self.albedo * self.M(ti, to) * self._N(po - pi_)

    def tabulate(self, theta_i):
        theta_i = np.asarray(theta_i, dtype=np.float64)
        # Cell-averaged stripes so that the tabulated energy is exact at any n_phi.
        phi = -np.pi + 2 * np.pi * np.arange(self.n_phi) / self.n_phi
        fine = phi[:, None] + (np.arange(16) + 0.5 - 8) / 16 * (2 * np.pi / self.n_phi)
        N = self.albedo * self._N(fine).mean(axis=1)
        table = np.broadcast_to(N[None, None, :, None],
                                (len(theta_i), 1, self.n_phi, len(self.wavelength))).astype(np.float32)
        meta = {"model": self.name, "albedo": self.albedo}
        return FiberTable(theta_i, np.zeros(1), phi, self.wavelength.copy(), [Lobe(self.name, self.M, table)], meta)
