"""Ray-optics fiber: d'Eon et al. 2011 / Chiang et al. 2016, as Mitsuba's ``hair``.

Per offset ``h`` across the fiber the light splits into paths with ``p`` internal
segments: R (p = 0), TT (1), TRT (2) and the residual (p >= 3). Each carries

    M_p(theta_i + tilt_p, theta_o)   longitudinal lobe (d'Eon), variance v_p
    A_p(theta_i, h, lambda)          Fresnel and absorption along the path
    D_p(dphi - Phi_p(h))             trimmed logistic around the ideal exit azimuth

and ``f = sum_{p<P} M_p A_p D_p + M_P A_P / (2 pi)`` with ``P = lobes`` (3 as Chiang and
Mitsuba; more explicit paths for smooth fibers, where the residual's uniform azimuth
is the model's largest error against exact geometry, docs/BENCHMARKS.md). Averaging over ``h`` uniform in
[-1, 1] (per geometric hit) gives the far-field fiber function that the baker needs:
``N_p(theta_i, dphi, lambda) = 1/2 integral A_p D_p dh``.

Conventions match Mitsuba 3's ``hair`` plugin so that it is a direct reference:
refraction and attenuation use the incident longitude ``theta_i``; the cuticle tilt
shifts the lobes by ``-2 alpha, alpha, 4 alpha`` for R, TT, TRT; roughness maps to
``v_p`` and the logistic scale ``s`` by Chiang's fits; absorption ``sigma_a`` is per
fiber radius. The relative index is ``eta = n(lambda)`` (exterior index 1).

The model is not reciprocal (docs/DESIGN.md): ``M_p`` is symmetric in its two longitudes
but lacks the ``cos`` that reciprocity asks for, and ``A_p``, ``Phi_p`` and ``h`` belong to
the side called incident. ``transport`` says which side that is. ``light`` (the default):
the side the light comes from, as d'Eon and Chiang write it; a lossless fiber then scatters
exactly the light it intercepts. ``camera``: what Mitsuba's path tracer makes of its
``hair`` BSDF, which it evaluates with the camera side as incident (``si.wi``): the adjoint
``f(w_o -> w_i) cos(theta_o) / cos(theta_i)``. A ply baked with it is what explicit
``hair`` fibers on curves render; it does not conserve energy under light off the
specular cone (``python -m pipeline.bench.hair`` measures both).
"""

from __future__ import annotations

import numpy as np
from scipy import special
from tqdm import tqdm

from ..queries import check_theta
from . import lobes
from .base import FiberModel, FiberTable, Lobe
from .lobes import P_MAX, logistic_scale, longitudinal_variance, tilt_shifts  # noqa: F401 (this model's API)
from .longitudinal import Longitudinal

# --------------------------------------------------------------------------
# Small pure pieces of the physics (the per-h formulas live in models.fiber.lobes)
# --------------------------------------------------------------------------

def fresnel_dielectric(cos_i, eta):
    """Unpolarized Fresnel reflectance from outside (index 1) into index ``eta``."""
    return lobes.fresnel(np.asarray(cos_i, np.float64), eta, np)


def Ap(cos_theta_i, eta, h, sigma_a, p_max: int = P_MAX):
    """Attenuations ``A_0 .. A_{p_max}`` (array with a leading axis of ``p_max + 1``)."""
    A = lobes.attenuation(np.asarray(cos_theta_i, np.float64), eta, h, sigma_a, p_max, np)
    return np.stack(np.broadcast_arrays(*A))


Phi = lobes.Phi

TRANSPORTS = ("light", "camera")   # which side the model's incident quantities belong to


def Np(dphi, p, s, gamma_i, gamma_t):
    """Trimmed logistic (scale ``s``) on [-pi, pi] around ``Phi_p``."""
    return lobes.logistic(lobes.wrap(dphi - Phi(p, gamma_i, gamma_t), np), s, np)


def Np_cell(phi, width, p, s, gamma_i, gamma_t):
    """Mean of :func:`Np` over the cell ``[phi - width/2, phi + width/2]``, exactly.

    From the trimmed logistic's CDF, so a lobe narrower than the cell (small azimuthal
    roughness) keeps its energy: the cells of a period sum to exactly one.
    """
    lo, hi = special.expit(-np.pi / s), special.expit(np.pi / s)

    def cdf(x):  # of the trimmed logistic on [-pi, pi]
        return (special.expit(np.clip(x, -np.pi, np.pi) / s) - lo) / (hi - lo)

    x0 = np.mod(phi - 0.5 * width - Phi(p, gamma_i, gamma_t) + np.pi, 2 * np.pi) - np.pi
    x1 = x0 + width
    inside = cdf(x1) - cdf(x0)
    wrapped = np.where(x1 > np.pi, cdf(x1 - 2 * np.pi) - cdf(-np.pi), 0.0)
    return (inside + wrapped) / width


def h_quadrature(n_h: int):
    """Gauss-Legendre nodes and weights for the mean over h in [-1, 1]."""
    h, w = np.polynomial.legendre.leggauss(n_h)
    return h, w / 2


def mitsuba_hair(meta: dict, wavelength, wavelength_nm: float) -> dict:
    """Mitsuba's ``hair`` BSDF with the parameters of a ray fiber (its table's ``meta`` and
    ``wavelength``) at one wavelength: the mapping of docs/DESIGN.md, "The ray fiber and
    Mitsuba's hair". Both sides name the same quantities: ``eta`` (the exterior index is 1),
    ``sigma_a`` per fiber radius, Chiang's roughnesses and the tilt in degrees."""
    wl = np.asarray(wavelength, np.float64)
    return {"type": "hair", "int_ior": float(np.interp(wavelength_nm, wl, meta["eta"])), "ext_ior": 1.0,
            "sigma_a": {"type": "uniform", "value": float(np.interp(wavelength_nm, wl, meta["sigma_a"]))},
            "longitudinal_roughness": float(meta["longitudinal_roughness"]),
            "azimuthal_roughness": float(meta["azimuthal_roughness"]),
            "scale_tilt": float(meta["scale_tilt_deg"])}


# --------------------------------------------------------------------------
# The fiber model
# --------------------------------------------------------------------------

class RayFiber(FiberModel):
    """d'Eon/Chiang fiber averaged over the offset, with spectral ``eta`` and ``sigma_a``.

    Parameters: ``eta[lambda]`` (relative index), ``sigma_a[lambda]`` (absorption per
    fiber radius), ``longitudinal_roughness``, ``azimuthal_roughness`` (in (0, 1]),
    ``scale_tilt_deg``, ``n_h`` (quadrature nodes over the offset) and ``lobes`` (the
    paths R, TT, TRT, ... kept explicit before the residual; 3 = Chiang's model).
    """

    name = "ray"

    def __init__(self, wavelength, eta, sigma_a, longitudinal_roughness=0.3,
                 azimuthal_roughness=0.3, scale_tilt_deg=2.0, n_h=256, n_phi=360, lobes=P_MAX,
                 transport="light"):
        super().__init__(wavelength)
        self.eta = np.broadcast_to(np.asarray(eta, dtype=np.float64), self.wavelength.shape)
        self.sigma_a = np.broadcast_to(np.asarray(sigma_a, dtype=np.float64), self.wavelength.shape)
        if not 3 <= int(lobes) <= 32:
            raise ValueError(f"lobes must be in 3 .. 32 (got {lobes})")
        self.p_max = int(lobes)
        self.v = longitudinal_variance(longitudinal_roughness, self.p_max)
        self.s = logistic_scale(azimuthal_roughness)
        self.shifts = tilt_shifts(scale_tilt_deg, self.p_max)
        self.n_h, self.n_phi = int(n_h), int(n_phi)
        if transport not in TRANSPORTS:
            raise ValueError(f"transport {transport!r}: use one of {', '.join(TRANSPORTS)}")
        self.transport = transport
        self.params = dict(longitudinal_roughness=longitudinal_roughness,
                           azimuthal_roughness=azimuthal_roughness, scale_tilt_deg=scale_tilt_deg,
                           n_h=n_h, n_phi=n_phi, lobes=self.p_max, transport=transport)

    def lobes(self):
        return [Longitudinal("deon", v=float(self.v[p]), shift=float(self.shifts[p])) for p in range(self.p_max + 1)]

    def azimuthal(self, theta_i, dphi, eta, sigma_a, cell=None):
        """``N_p`` for p = 0..p_max at broadcastable ``theta_i, dphi, eta, sigma_a``.

        With ``cell`` (a width in radians) each value is the mean over its azimuth cell
        (:func:`Np_cell`), as tables want. Returns an array with a leading axis of p_max + 1;
        the h average is the last step.
        """
        h, wh = h_quadrature(self.n_h)
        cos_ti = np.cos(theta_i)[..., None]
        eta_ = np.asarray(eta)[..., None]
        eta_p = np.sqrt(np.maximum(0.0, eta_**2 - (1 - cos_ti**2))) / cos_ti
        gamma_i = np.arcsin(h)
        gamma_t = np.arcsin(np.clip(h / eta_p, -1, 1))
        A = Ap(cos_ti, eta_, h, np.asarray(sigma_a)[..., None], self.p_max)
        dphi_ = np.asarray(dphi)[..., None]
        if cell is None:
            N = [A[p] * Np(dphi_, p, self.s, gamma_i, gamma_t) for p in range(self.p_max)]
        else:
            N = [A[p] * Np_cell(dphi_, cell, p, self.s, gamma_i, gamma_t) for p in range(self.p_max)]
        N.append(np.broadcast_to(A[self.p_max] / (2 * np.pi), N[0].shape))
        return np.stack([n @ wh for n in N])

    def tabulate(self, theta_i):
        if self.transport == "camera":
            return self._tabulate_camera(np.asarray(theta_i, dtype=np.float64))

        theta_i = np.asarray(theta_i, dtype=np.float64)
        phi = -np.pi + 2 * np.pi * np.arange(self.n_phi) / self.n_phi
        N = np.empty((self.p_max + 1, len(theta_i), 1, self.n_phi, len(self.wavelength)), dtype=np.float32)
        for i, ti in enumerate(tqdm(theta_i, desc="ray", unit="theta_i", leave=False)):
            # Exactly at grazing cos(theta_i) = 0 the Bravais index diverges; take the limit.
            ti = min(ti, np.deg2rad(89.99))
            N[:, i, 0] = self.azimuthal(ti, phi[:, None], self.eta[None, :], self.sigma_a[None, :],
                                        cell=2 * np.pi / self.n_phi)
        names = ["R", "TT", "TRT"] + [f"p{p}" for p in range(3, self.p_max)] + ["residual"]
        lobes = [Lobe(names[p], m, N[p]) for p, m in enumerate(self.lobes())]
        meta = {"model": self.name, **self.params, "eta": self.eta.tolist(), "sigma_a": self.sigma_a.tolist(),
                # cuticle tilt breaks the mirror symmetry along the axis
                "mirror_symmetric": self.params["scale_tilt_deg"] == 0}
        return FiberTable(theta_i, np.zeros(1), phi, self.wavelength.copy(), lobes, meta)

    def _tabulate_camera(self, theta_i):
        """The adjoint ``f(w_o -> w_i) cos(theta_o) / cos(theta_i)`` as one dense lobe on a
        1-degree ``theta_o`` grid (it is not a sum of separable lobes): ``N_p`` at the
        camera's longitude ``theta_o`` and azimuth ``-dphi``, ``M_p`` with the tilt on
        ``theta_o``. The adjoint grows as ``1 / cos(theta_i)`` towards grazing light; light
        arrives at a fiber with the weight ``cos(theta_i)``, and a node at 90 deg holds 4 times
        the value at the node before it, which makes the product's integral over that last
        cell, linear in ``theta_i`` as tables interpolate, the adjoint's to first order."""

        theta_o = np.deg2rad(np.linspace(-90.0, 90.0, 181))
        to_safe = np.clip(theta_o, -np.deg2rad(89.99), np.deg2rad(89.99))
        ti_safe = np.minimum(theta_i, np.deg2rad(89.99))
        phi = -np.pi + 2 * np.pi * np.arange(self.n_phi) / self.n_phi
        M = np.stack([m(to_safe[None, :], ti_safe[:, None]) for m in self.lobes()])     # [p, theta_i, theta_o]
        cos_i = np.cos(ti_safe)
        grazing = (theta_i >= np.deg2rad(89.99)) & (np.arange(len(theta_i)) > 0)
        cos_i[grazing] = np.cos(theta_i[np.flatnonzero(grazing) - 1]) / 4
        cosines = np.cos(to_safe)[None, :] / cos_i[:, None]
        values = np.empty((len(theta_i), len(theta_o), self.n_phi, len(self.wavelength)), np.float32)
        for k in tqdm(range(len(self.wavelength)), desc="ray (camera)", unit="lambda", leave=False):
            N = self.azimuthal(to_safe[:, None], -phi[None, :], self.eta[k], self.sigma_a[k],
                               cell=2 * np.pi / self.n_phi)                            # [p, theta_o, phi]
            values[..., k] = np.einsum("pio,pof->iof", M, N) * cosines[..., None]
        meta = {"model": self.name, **self.params, "eta": self.eta.tolist(), "sigma_a": self.sigma_a.tolist(),
                "mirror_symmetric": self.params["scale_tilt_deg"] == 0}
        return FiberTable(theta_i, theta_o, phi, self.wavelength.copy(),
                          [Lobe("adjoint", Longitudinal("none"), values)], meta)

    def eval(self, *, phi_i, theta_i, phi_o, theta_o, wavelength):
        """Direct evaluation, h-averaged by quadrature (no table), in this fiber's transport."""
        if self.transport == "camera":
            to = np.asarray(theta_o, np.float64)
            light = RayFiber(self.wavelength, self.eta, self.sigma_a, **{**self.params, "transport": "light"})
            return (light.eval(phi_i=phi_o, theta_i=theta_o, phi_o=phi_i, theta_o=theta_i, wavelength=wavelength)
                    * np.cos(np.minimum(np.abs(to), np.deg2rad(89.99)))
                    / np.cos(np.minimum(np.abs(np.asarray(theta_i, np.float64)), np.deg2rad(89.99))))
        ti, pi_, to, po, wl = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                   for a in (theta_i, phi_i, theta_o, phi_o, wavelength)))
        check_theta(ti, "theta_i")
        check_theta(to, "theta_o")
        eta = np.interp(wl, self.wavelength, self.eta)
        sigma_a = np.interp(wl, self.wavelength, self.sigma_a)
        ti_safe = np.minimum(np.abs(ti), np.deg2rad(89.99))
        N = self.azimuthal(ti_safe, po - pi_, eta, sigma_a)
        return sum(M(ti, to) * N[p] for p, M in enumerate(self.lobes()))

    def extinction(self, theta_i):
        return None
