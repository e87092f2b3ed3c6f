"""Single-fiber scattering models (see :mod:`models.fiber.base` for the interface).

``build(fiber_cfg, wavelength)`` turns the ``fiber:`` block of a config into a model:

=============  =================================================================
``mie``        exact wave optics of a smooth dielectric cylinder (:mod:`.mie`)
``ray``        d'Eon / Chiang ray optics, as Mitsuba's ``hair`` (:mod:`.ray`)
``table``      Xia et al. 2023 raw files or a generic npz (:mod:`.table`)
``grid``       test pattern of stripes in theta_o and phi (:mod:`.patterns`)
``isotropic``  lossless uniform scatterer (:mod:`.patterns`)
=============  =================================================================
"""

from __future__ import annotations

import numpy as np

from models.spectrum import cauchy, spectral_values

from .base import FiberModel, FiberTable, Lobe  # noqa: F401
from .patterns import PatternFiber


def build(fiber, wavelength) -> FiberModel:
    """The model named by a validated ``fiber`` config block, at these wavelengths (nm)."""

    wl = np.asarray(wavelength, dtype=np.float64)
    n = cauchy(fiber.ior.cauchy_a, fiber.ior.cauchy_b_um2, wl)
    k = spectral_values(fiber.ior.k, wl)
    if fiber.model == "mie":
        from .mie import MieFiber
        p = fiber.mie
        return MieFiber(wl, fiber.radius_um, n, k, p.roughness_deg, p.zeta_min_deg, p.n_phi)
    if fiber.model == "ray":
        from .ray import RayFiber
        p = fiber.ray
        # absorption coefficient 4 pi k / lambda, per fiber radius as the model expects
        sigma_a = 4 * np.pi * k / (wl * 1e-3) * fiber.radius_um
        return RayFiber(wl, n, sigma_a, p.longitudinal_roughness, p.azimuthal_roughness,
                        p.scale_tilt_deg, p.n_h, p.n_phi, p.lobes, p.transport)
    if fiber.model == "table":
        from .table import TableFiber, load_npz, load_xia2023
        t = fiber.table
        table = load_xia2023(t.path, t.albedo) if t.format == "xia2023" else load_npz(t.path)
        have = np.asarray(table.wavelength, float)
        if len(have) != len(wl) or not np.allclose(have, wl, atol=0.5):
            raise ValueError(f"fiber.table.path {t.path} holds {len(have)} wavelengths {have[0]:.0f}..{have[-1]:.0f} nm, "
                             f"the config asks for {len(wl)} from {wl[0]:.0f} to {wl[-1]:.0f} nm: set `wavelengths:` "
                             "to the table's (start_nm, stop_nm, count) or use a table made for these")
        return TableFiber(table)
    p = fiber.pattern
    return PatternFiber(wl, fiber.model, p.n_stripes_theta, p.n_stripes_phi, p.albedo, p.n_phi)
