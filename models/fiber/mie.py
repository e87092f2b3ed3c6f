"""Lorenz-Mie scattering by an infinite circular cylinder at oblique incidence.

Bohren & Huffman (1983), *Absorption and Scattering of Light by Small Particles*,
section 8.4. Notation follows the book:

=========  ==============================================================
``m``      complex refractive index of the cylinder relative to the medium
           (``n + ik``, ``k >= 0`` absorbs)
``x``      size parameter ``2 pi a / lambda``
``zeta``   angle between the incident direction and the cylinder axis
           (90 deg = normal incidence)
``xi``     ``x sin(zeta)``
``eta``    ``x sqrt(m^2 - cos^2(zeta))``
``Theta``  azimuthal scattering angle on the cone, 0 = forward
=========  ==============================================================

Case I: incident E in the plane of the axis and the incident direction;
case II: E perpendicular to it. Efficiencies are cross-sections per unit length
over the diameter ``2a`` (so a long cylinder has ``Q_ext / sin(zeta) -> 2``).

Numerics (what makes this stable from ``x = 0.1`` to ``x = 2000``):

* All coefficients are written with ``D_n(eta) = J_n'(eta) / J_n(eta)``; ``J_n(eta)``
  itself, which overflows for absorbing cylinders, cancels out of every ratio.
* ``D_n`` comes from the downward recurrence
  ``D_{n-1} = (n-1)/eta - 1/(D_n + n/eta)``, started far enough above
  ``max(n_max, |eta|)`` that the start value's error is damped below double
  precision (``_recurrence_start``). A fixed "+15" is not enough at ``x ~ 800``.
* ``n_max`` follows ``xi = x sin(zeta)`` (the cylinder's projected size), not ``x``.
* ``J_n(xi)``, ``Y_n(xi)`` come from scipy for real ``xi``; ``Y_n`` overflowing to
  ``-inf`` would mean the series is far past convergence, so it is checked.
* ``xi^2 / eta^2 - 1`` is evaluated as ``x^2 (1 - m^2) / eta^2`` so that an index
  matched cylinder (``m -> 1``) loses no digits.
"""

from __future__ import annotations

import numpy as np
from scipy import special
from tqdm import tqdm

from ..queries import check_theta
from .base import FiberModel, FiberTable, Lobe
from .longitudinal import Longitudinal
from .reciprocal import half_angle, scale_at, symmetric_scale

__all__ = [
    "coefficients",
    "efficiencies",
    "amplitudes",
    "azimuthal_intensity",
    "n_terms",
]


# --------------------------------------------------------------------------
# Series length and the logarithmic derivative
# --------------------------------------------------------------------------

def n_terms(xi: float) -> int:
    """Number of terms: Wiscombe's ``xi + 4 xi^(1/3) + 2`` widened until the last
    coefficients are below 1e-13 up to ``xi = 2000`` (``xi = x sin(zeta)``)."""
    return int(np.ceil(xi + 6.0 * xi ** (1.0 / 3.0) + 8))


def _recurrence_start(n_max: int, eta: complex) -> int:
    # The start value's error shrinks like (J_n / J_N)^2 while recurring down; in the
    # transition zone n ~ |eta| that ratio changes slowly (width ~ |eta|^(1/3)), so
    # the margin must grow with |eta|^(1/3), not stay a constant.
    z = abs(eta)
    return int(max(n_max, z) + 16 * z ** (1.0 / 3.0) + 32)


def _log_derivative(eta: complex, n_max: int) -> np.ndarray:
    """``D_n(eta) = J_n'(eta) / J_n(eta)`` for ``n = 0 .. n_max`` (downward recurrence)."""
    n_start = _recurrence_start(n_max, eta)
    D = np.empty(n_max + 1, dtype=np.complex128)
    d = complex(n_start / eta)  # J_n ~ (eta/2)^n / n!  =>  D_n ~ n / eta for n >> |eta|
    for n in range(n_start, 0, -1):
        d = (n - 1) / eta - 1.0 / (d + n / eta)
        if n - 1 <= n_max:
            D[n - 1] = d
    return D


# --------------------------------------------------------------------------
# Expansion coefficients
# --------------------------------------------------------------------------

def coefficients(m: complex, x: float, zeta_deg: float):
    """Expansion coefficients ``(aI, bI, aII, bII)`` for ``n = 0 .. n_max``.

    Returns four complex arrays; ``aI[0] = 0`` and ``bII[0] = 0`` by symmetry.
    Negative orders follow ``bI[-n] = bI[n]``, ``aI[-n] = -aI[n]``,
    ``aII[-n] = aII[n]``, ``bII[-n] = -bII[n]``.
    """
    m = complex(m)
    _check_inputs(m, x, zeta_deg)
    zeta = np.deg2rad(zeta_deg)
    sin_z, cos_z = np.sin(zeta), np.cos(zeta)
    xi = x * sin_z
    m2 = m * m
    eta = x * np.sqrt(m2 - cos_z**2)
    n_max = n_terms(xi)
    n = np.arange(n_max + 2)

    # Bessel functions of the real argument xi (one order beyond n_max for J', Y')
    J = special.jv(n, xi)
    Y = special.yv(n, xi)
    if not np.all(np.isfinite(Y[: n_max + 2])):
        raise FloatingPointError(f"Y_n({xi:g}) overflowed below n = {n_max + 1}")
    n = n[:-1]
    dJ = n / xi * J[:-1] - J[1:]  # J_n' = (n / xi) J_n - J_{n+1}
    dY = n / xi * Y[:-1] - Y[1:]
    J, Y = J[:-1], Y[:-1]
    H, dH = J + 1j * Y, dJ + 1j * dY

    D = _log_derivative(eta, n_max)

    # B&H eq. (8.30)-(8.33), every term divided by J_n(eta)
    chi = n * cos_z * eta * (x * x * (1.0 - m2) / (eta * eta))  # n cos(zeta) eta (xi^2/eta^2 - 1)
    A = 1j * xi * (xi * D * J - eta * dJ)
    B = xi * (m2 * xi * D * J - eta * dJ)
    C = chi * J
    Dn = chi * H
    V = xi * (m2 * xi * D * H - eta * dH)
    W = 1j * xi * (eta * dH - xi * D * H)
    denom = W * V + 1j * Dn * Dn

    aI = (C * V - B * Dn) / denom
    bI = (W * B + 1j * Dn * C) / denom
    aII = -(A * V - 1j * C * Dn) / denom
    bII = -1j * (C * W + A * Dn) / denom
    return aI, bI, aII, bII


def _check_inputs(m: complex, x: float, zeta_deg: float) -> None:
    if not np.isfinite(m) or m.real <= 0:
        raise ValueError(f"refractive index m = {m} must have a positive real part")
    if m.imag < 0:
        raise ValueError(
            f"refractive index m = {m} has a negative imaginary part; "
            "this code uses n + ik with k >= 0 for absorption")
    if not (np.isfinite(x) and x > 0):
        raise ValueError(f"size parameter x = {x} must be positive")
    if not (0 < zeta_deg <= 90):
        raise ValueError(f"incidence angle zeta = {zeta_deg} deg must lie in (0, 90]")


# --------------------------------------------------------------------------
# Observables
# --------------------------------------------------------------------------

def efficiencies(m: complex, x: float, zeta_deg: float) -> dict:
    """Extinction and scattering efficiencies per polarization (B&H eq. 8.36-8.37)."""
    return _efficiencies(coefficients(m, x, zeta_deg), x)


def _efficiencies(coeffs, x: float) -> dict:
    aI, bI, aII, bII = coeffs
    f = 2.0 / x
    return {
        "QextI": f * float(np.real(bI[0] + 2.0 * np.sum(bI[1:]))),
        "QscaI": f * float(abs(bI[0]) ** 2 + 2.0 * np.sum(np.abs(bI[1:]) ** 2 + np.abs(aI[1:]) ** 2)),
        "QextII": f * float(np.real(aII[0] + 2.0 * np.sum(aII[1:]))),
        "QscaII": f * float(abs(aII[0]) ** 2 + 2.0 * np.sum(np.abs(aII[1:]) ** 2 + np.abs(bII[1:]) ** 2)),
    }


def amplitudes(coeffs, Theta: np.ndarray):
    """Amplitude functions ``T1..T4`` at azimuths ``Theta`` (radians, 0 = forward)."""
    aI, bI, aII, bII = coeffs
    n = np.arange(1, len(bI))
    cos_nT = np.cos(np.multiply.outer(Theta, n))
    sin_nT = np.sin(np.multiply.outer(Theta, n))
    T1 = bI[0] + 2.0 * cos_nT @ bI[1:]
    T2 = aII[0] + 2.0 * cos_nT @ aII[1:]
    T3 = -2j * (sin_nT @ aI[1:])
    T4 = -2j * (sin_nT @ bII[1:])
    return T1, T2, T3, T4


def _intensity_from_amplitudes(T, x: float, zeta_deg: float) -> np.ndarray:
    power = sum(np.abs(t) ** 2 for t in T)
    return power / (2.0 * np.pi * x * np.sin(np.deg2rad(zeta_deg)))


def azimuthal_intensity(m: complex, x: float, zeta_deg: float, Theta_deg) -> np.ndarray:
    """Unpolarized ``N(Theta) = sum |T_j|^2 / (2 pi x sin(zeta))``.

    Normalized so that its integral over ``Theta`` in ``[0, 2 pi)`` equals
    ``(QscaI + QscaII) / (2 sin(zeta))``: scattered power per unit of power incident
    on the cylinder's projected width, for unpolarized light.
    """
    Theta = np.deg2rad(np.asarray(Theta_deg, dtype=np.float64))
    T = amplitudes(coefficients(m, x, zeta_deg), Theta.ravel())
    return _intensity_from_amplitudes(T, x, zeta_deg).reshape(Theta.shape)


def azimuthal_intensity_grid(m: complex, x: float, zeta_deg: float, n_phi: int):
    """``N(Theta)`` on the uniform grid ``Theta_k = 2 pi k / n_phi`` by FFT.

    The series ``T1 = sum_{n=-N}^{N} bI_n e^{-i n Theta}`` is a discrete Fourier
    transform on a uniform grid, so all four amplitudes cost four FFTs. Requires
    ``n_phi > 2 N + 1`` (checked). Also returns the efficiencies, which come free.
    """
    coeffs = coefficients(m, x, zeta_deg)
    aI, bI, aII, bII = coeffs
    N = len(bI) - 1
    if n_phi <= 2 * N + 1:
        raise ValueError(f"n_phi = {n_phi} cannot resolve {N} Mie orders; need > {2 * N + 1}")

    def series(c, odd):
        # Place c_n at index n and c_{-n} = +-c_n at index n_phi - n
        s = np.zeros(n_phi, dtype=np.complex128)
        s[: N + 1] = c
        s[n_phi - N:] = (-c[1:] if odd else c[1:])[::-1]
        return np.fft.fft(s)

    T = (series(bI, False), series(aII, False), series(aI, True), series(bII, True))
    return _intensity_from_amplitudes(T, x, zeta_deg), _efficiencies(coeffs, x)


# --------------------------------------------------------------------------
# The smooth dielectric cylinder as a fiber scattering function
# --------------------------------------------------------------------------

class MieFiber(FiberModel):
    """Wave-optics fiber: exact Mie azimuthal pattern, d'Eon longitudinal spread.

    A smooth infinite cylinder scatters only onto the cone ``theta_o = -theta_i``
    with the azimuthal pattern ``N(Theta)``; a rough fiber spreads the cone with the
    d'Eon lobe of standard deviation ``roughness_deg``, in the reciprocal form of
    :mod:`models.fiber.reciprocal` (the pattern at the half angle, a symmetric scale
    that keeps every node's albedo), so that ``f(i -> o) cos(theta_i) = f(o -> i)
    cos(theta_o)`` holds as for the exact cylinder. Normalized per geometric
    hit: the pattern is divided by the extinction ratio ``Q_ext / sin(zeta)``
    (about 2 for large fibers: the diffraction peak carries as much power as the
    geometric shadow), so that ``integral f d omega = Q_sca / Q_ext``, and that
    ratio is reported by :meth:`extinction`.

    ``zeta = 90 deg - |theta_i|``; incidence closer to the axis than ``zeta_min_deg``
    is evaluated at ``zeta_min_deg`` (the cone degenerates at the axis).
    """

    name = "mie"

    def __init__(self, wavelength, radius_um, n, k, roughness_deg, zeta_min_deg=1.0, n_phi=None):
        super().__init__(wavelength)
        self.radius_um = float(radius_um)
        self.m = np.asarray(n, dtype=np.float64) + 1j * np.asarray(k, dtype=np.float64)
        self.beta = np.deg2rad(roughness_deg)
        self.zeta_min_deg = float(zeta_min_deg)
        x_max = self.size_parameter(self.wavelength.min())
        # >= 8 samples across the forward diffraction lobe (full width 2 pi / xi)
        self.n_phi = int(n_phi or max(720, 64 * np.ceil(8 * x_max / 64)))
        if self.n_phi <= 2 * n_terms(x_max) + 1:
            raise ValueError(f"n_phi = {self.n_phi} is too coarse for x = {x_max:.0f}; "
                             f"use at least {2 * n_terms(x_max) + 2}")

    def size_parameter(self, wavelength_nm):
        return 2 * np.pi * self.radius_um / (np.asarray(wavelength_nm) * 1e-3)

    def zeta_deg(self, theta_i):
        return np.maximum(90.0 - np.rad2deg(np.abs(theta_i)), self.zeta_min_deg)

    def _lobe(self):
        return Longitudinal("deon", v=self.beta**2)

    def tabulate(self, theta_i):
        theta_i = np.asarray(theta_i, dtype=np.float64)
        n_ti, n_wl = len(theta_i), len(self.wavelength)
        N = np.empty((n_ti, 1, self.n_phi, n_wl), dtype=np.float32)
        ext = np.empty((n_ti, n_wl))
        sca = np.empty((n_ti, n_wl))
        with tqdm(total=n_ti * n_wl, desc="mie", unit="pattern", leave=False) as bar:
            for i, zeta in enumerate(self.zeta_deg(theta_i)):
                sin_z = np.sin(np.deg2rad(zeta))
                for j, lam in enumerate(self.wavelength):
                    # FFT grid Theta_k = 2 pi k / n_phi is exactly dphi_k = -pi + 2 pi k / n_phi
                    pattern, Q = azimuthal_intensity_grid(self.m[j], self.size_parameter(lam), zeta, self.n_phi)
                    ext[i, j] = 0.5 * (Q["QextI"] + Q["QextII"]) / sin_z
                    sca[i, j] = 0.5 * (Q["QscaI"] + Q["QscaII"]) / sin_z
                    N[i, 0, :, j] = pattern / ext[i, j]
                    bar.update()
        phi = -np.pi + 2 * np.pi * np.arange(self.n_phi) / self.n_phi
        # the reciprocal form (N at the half angle), scaled to keep each node's albedo
        dphi = 2 * np.pi / self.n_phi
        scale = symmetric_scale(theta_i, self._lobe(), N[:, 0].astype(np.float64).sum(1) * dphi)
        self._scale = scale
        meta = {"model": self.name, "extinction_ratio": ext.tolist(), "albedo": (sca / ext).tolist(),
                "radius_um": self.radius_um, "roughness_deg": float(np.rad2deg(self.beta)),
                "zeta_min_deg": self.zeta_min_deg}
        return FiberTable(theta_i, np.zeros(1), phi, self.wavelength.copy(), [Lobe("mie", self._lobe(), N, scale)],
                          meta)

    def scale(self) -> np.ndarray:
        """The reciprocal form's ``c[node, lambda]`` (its own nodes, ``reciprocal.scale_nodes``):
        of the last :meth:`tabulate`, or of a 5-degree tabulation."""
        if not hasattr(self, "_scale"):
            self.tabulate(np.deg2rad(np.arange(0, 91, 5.0)))
        return self._scale

    def eval(self, *, phi_i, theta_i, phi_o, theta_o, wavelength):
        """Direct evaluation (no table): the series summed at each requested angle.

        The reciprocal form of :mod:`models.fiber.reciprocal`: the pattern at the half
        angle ``theta_d``, with the scale ``c`` of :meth:`scale` (per wavelength, held
        at the nearest tabulated wavelength).
        """
        ti, pi_, to, po, wl = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                   for a in (theta_i, phi_i, theta_o, phi_o, wavelength)))
        check_theta(ti, "theta_i")
        check_theta(to, "theta_o")
        out = np.zeros(ti.shape)
        Theta = po - pi_ - np.pi
        abs_d, weight = half_angle(ti, to, np)
        c = self.scale()
        j = np.argmin(np.abs(self.wavelength[None, :] - wl.reshape(-1, 1)), axis=1).reshape(wl.shape)
        pick = lambda cc: np.take_along_axis(cc, j[..., None], -1)[..., 0]  # noqa: E731
        cc = pick(scale_at(c, np.abs(ti))) * pick(scale_at(c, np.abs(to)))
        keys = np.stack([self.zeta_deg(abs_d), wl], -1).reshape(-1, 2)
        uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
        flat = out.reshape(-1)
        for u, (zeta, lam) in enumerate(uniq):
            sel = inverse.reshape(-1) == u
            j = int(np.argmin(np.abs(self.wavelength - lam)))
            m, x = self.m[j], self.size_parameter(lam)
            coeffs = coefficients(m, x, zeta)
            Q = _efficiencies(coeffs, x)
            ext = 0.5 * (Q["QextI"] + Q["QextII"]) / np.sin(np.deg2rad(zeta))
            T = amplitudes(coeffs, Theta.reshape(-1)[sel])
            flat[sel] = _intensity_from_amplitudes(T, x, zeta) / ext
        return out * self._lobe()(ti, to) * weight * cc

    def extinction(self, theta_i):
        out = np.empty((len(theta_i), len(self.wavelength)))
        for i, zeta in enumerate(self.zeta_deg(np.asarray(theta_i))):
            for j, lam in enumerate(self.wavelength):
                Q = efficiencies(self.m[j], self.size_parameter(lam), zeta)
                out[i, j] = 0.5 * (Q["QextI"] + Q["QextII"]) / np.sin(np.deg2rad(zeta))
        return out
