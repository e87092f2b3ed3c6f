"""The ray model at one entry offset ``h``: where each lobe goes and where it leaves.

A ray that meets a smooth circular fiber (radius 1) at offset ``h`` (its signed
distance from the centre, ``gamma_i = asin h``) splits into paths with ``p`` internal
segments. In the cross-section each segment is a chord that turns the point on the
circle by ``2 gamma_t - pi`` (``gamma_t = asin(h / eta')``, ``eta'`` Bravais' index), so
path ``p``

* leaves from the point whose outward normal is the entry normal turned by
  ``p (2 gamma_t - pi)`` (:func:`exit_turn`; ``p = 0``, reflection, leaves where it entered),
* in the direction turned by ``Phi_p = 2 p gamma_t - 2 gamma_i + p pi`` from the
  backward direction (:func:`Phi`, the project's ``dphi = phi_o - phi_i``),
* carrying ``A_p`` of the light (:func:`attenuation`: Fresnel at the 3D angle of incidence,
  absorption along the chords; the paths from ``p_max`` on are summed into a residual).

Each formula is written once, for numpy (``xp=np``) and Dr.Jit (``xp=drjit``): the
h-averaged ray model (:mod:`models.fiber.ray`) and the baker's h-resolved exit
(:class:`LobeSampler`) evaluate the same code. Sign conventions: a ray travelling along
``u`` meets the fiber centred at ``c`` with ``h = cross(c - o, u) / r`` (z-x plane,
``cross(a, b) = a_x b_z - a_z b_x``); its entry normal is ``-sqrt(1 - h^2) u + h u_perp``
with ``u_perp = (-u_z, u_x)``.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from ..xp import asin, select
from .longitudinal import Longitudinal

TWO_PI = 2 * np.pi
P_MAX = 3  # Chiang's explicit paths: R, TT, TRT (then the residual)
COS_GRAZING = float(np.cos(np.deg2rad(89.99)))


# --------------------------------------------------------------------------
# Roughness parameterization (Chiang et al. 2016, eq. 7-8)
# --------------------------------------------------------------------------

def longitudinal_variance(beta_m: float, p_max: int = P_MAX) -> np.ndarray:
    """``v_p`` for p = 0..p_max (the last the residual) from the longitudinal roughness."""
    v0 = (0.726 * beta_m + 0.812 * beta_m**2 + 3.7 * beta_m**20) ** 2
    return np.array([v0, 0.25 * v0] + [4 * v0] * (p_max - 1))


def logistic_scale(beta_n: float) -> float:
    """Logistic scale ``s`` from the azimuthal roughness in [0, 1]."""
    return float(np.sqrt(np.pi / 8) * (0.265 * beta_n + 1.194 * beta_n**2 + 5.372 * beta_n**22))


def tilt_shifts(alpha_deg: float, p_max: int = P_MAX) -> np.ndarray:
    """Longitudinal shifts of the R, TT, TRT lobes by the cuticle tilt (none beyond, as
    Chiang's residual)."""
    a = np.deg2rad(alpha_deg)
    return np.array([-2 * a, a, 4 * a] + [0.0] * (p_max - 2))


def bravais(eta, cos_theta, xp):
    """Bravais' index ``eta'`` of the cross-section for a ray of longitude ``theta``."""
    return xp.sqrt(xp.maximum(eta * eta - (1 - cos_theta * cos_theta), 0.0)) / cos_theta


def gammas(h, eta_p, xp):
    """``(gamma_i, gamma_t)``: the angles of incidence and refraction in the cross-section."""
    return asin(h, xp), asin(h / eta_p, xp)


def fresnel(cos_i, eta, xp):
    """Unpolarized Fresnel reflectance from outside (index 1) into ``eta``; ``cos_i`` in 3D."""
    cos_i = xp.clip(cos_i, 0.0, 1.0)
    sin_t2 = (1 - cos_i * cos_i) / (eta * eta)
    cos_t = xp.sqrt(xp.maximum(0.0, 1 - sin_t2))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return select(xp)(sin_t2 >= 1, 1.0, 0.5 * (rs * rs + rp * rp))


def attenuation(cos_theta_i, eta, h, sigma_a, p_max, xp) -> list:
    """``[A_0, ..., A_{p_max - 1}, A_residual]``: the share of the light on each path.

    Fresnel at the 3D angle ``cos(theta_i) cos(gamma_i)``; absorption ``sigma_a`` per
    radius along chords of length ``2 cos(gamma_t) / cos(theta_t)``. The residual is the
    geometric series of the paths from ``p_max`` on; at ``T F = 1`` (``h = +-1`` on a
    lossless fiber) its limit is 0, not 0 / 0.
    """
    sin_theta_i2 = 1 - cos_theta_i * cos_theta_i
    cos_theta_t = xp.sqrt(xp.maximum(0.0, 1 - sin_theta_i2 / (eta * eta)))
    eta_p = bravais(eta, cos_theta_i, xp)
    cos_gamma_t = xp.sqrt(xp.maximum(0.0, 1 - (h / eta_p) ** 2))
    T = xp.exp(-sigma_a * 2 * cos_gamma_t / cos_theta_t)
    F = fresnel(cos_theta_i * xp.sqrt(xp.maximum(0.0, 1 - h * h)), eta, xp)
    A = [F, (1 - F) ** 2 * T]
    for _ in range(2, p_max):
        A.append(A[-1] * T * F)
    denom = 1 - T * F
    where = select(xp)
    A.append(where(denom > 1e-12, A[p_max - 1] * F * T / xp.maximum(denom, 1e-12), 0.0 * denom))
    return A


def Phi(p, gamma_i, gamma_t):
    """Ideal change of azimuth ``dphi`` of the path with ``p`` internal segments."""
    return 2 * p * gamma_t - 2 * gamma_i + p * np.pi


def exit_turn(p, gamma_t):
    """Angle from the entry normal to the exit normal of path ``p`` (radians, signed)."""
    return p * (2 * gamma_t - np.pi)


def wrap(x, xp):
    """``x`` wrapped into [-pi, pi)."""
    return x - TWO_PI * xp.floor((x + np.pi) * (1 / TWO_PI))


def logistic_trim(s: float) -> float:
    """Mass of the logistic of scale ``s`` inside [-pi, pi] (float64)."""
    return float(1 / (1 + np.exp(-np.pi / s)) - 1 / (1 + np.exp(min(np.pi / s, 700.0))))


def logistic(x, s: float, xp):
    """The azimuthal lobe: a logistic of scale ``s`` trimmed to [-pi, pi], at ``x`` in [-pi, pi)."""
    e = xp.exp(-xp.abs(x) * (1 / s))
    return e / (s * (1 + e) * (1 + e)) * (1 / logistic_trim(s))


def sample_logistic(u, s: float, xp):
    """Inverse CDF of :func:`logistic` at ``u`` in [0, 1)."""
    lo = float(1 / (1 + np.exp(min(np.pi / s, 700.0))))
    y = xp.clip(lo + u * (1 - 2 * lo), 1e-7, 1 - 1e-7)
    return xp.clip(s * xp.log(y / (1 - y)), -np.pi, np.pi)


# ------------------------------------------------------------------------------
# The h-resolved scattering event, for the baker's Dr.Jit loop
# ------------------------------------------------------------------------------

def check_exit(meta: dict, exit_model: str) -> None:
    """Refuse the h-resolved ``lobe`` exit for a ray fiber of camera transport: its table is
    the adjoint, while the lobes the exit samples are the model in light transport."""
    if exit_model == "lobe" and meta.get("transport", "light") != "light":
        raise ValueError(f"the lobe exit resolves the paths of light transport; this ray fiber is of "
                         f"{meta['transport']} transport (what Mitsuba's hair renders): bake it with the curve exit")


class LobeSampler:
    """Samples a path ``p``, its outgoing direction and its exit point, at a known ``h``.

    Built from a ``ray`` fiber table's metadata (the same parameters the table was
    tabulated from), so that averaged over ``h`` it is that table's fiber. The geometry
    (lobe choice, sampled azimuth, exit point) is that of the middle wavelength; the
    weight of every wavelength is its own ``A_p N_p`` over the sampling pdf, so dispersion
    moves the exit point of no wavelength but its own direction's weight (unbiased in the
    directions; the exit points of the other wavelengths are the middle one's).

    ``Float`` is the Dr.Jit float type of the chosen variant.
    """

    def __init__(self, meta: dict, wavelength, Float):
        if meta.get("model") != "ray":
            raise ValueError(f"the h-resolved exit needs a 'ray' fiber (this table is {meta.get('model')!r}); "
                             "use bake.exit: uniform or entry for other fibers")
        self.dr, self.Float = dr, Float
        self.p_max = int(meta.get("lobes", 3))
        self.eta = [float(e) for e in meta["eta"]]
        self.sigma_a = [float(s) for s in meta["sigma_a"]]
        self.L = len(self.eta)
        self.ref = self.L // 2
        self.s = logistic_scale(meta["azimuthal_roughness"])
        v = longitudinal_variance(meta["longitudinal_roughness"], self.p_max)
        shifts = tilt_shifts(meta["scale_tilt_deg"], self.p_max)
        self.M = [Longitudinal("deon", v=float(v[p]), shift=float(shifts[p])) for p in range(self.p_max + 1)]

    # -- pieces ---------------------------------------------------------------
    def cos_in(self, theta):
        """``cos(theta)``, kept off 0: at grazing (89.99 deg and beyond) the Bravais index is
        taken at its limit, as the tabulated model does."""
        return self.dr.maximum(self.dr.cos(theta), COS_GRAZING)

    def attenuations(self, cos_theta_in, h):
        """``A[p][lambda]`` at every wavelength (p = 0 .. p_max, the last the residual)."""
        per_lambda = [attenuation(cos_theta_in, self.eta[l], h, self.sigma_a[l], self.p_max, self.dr)
                      for l in range(self.L)]
        return [[per_lambda[l][p] for l in range(self.L)] for p in range(self.p_max + 1)]

    def _pick(self, values, p):
        """``values[p]`` per lane (``values`` a list over paths of Dr.Jit floats)."""
        out = values[-1]
        for q in range(self.p_max - 1, -1, -1):
            out = self.dr.select(p == q, values[q], out)
        return out

    def _azimuthal(self, p, h, cos_theta_in, dphi, l):
        """``N_p(dphi)`` at wavelength ``l`` (the residual: uniform)."""
        dr = self.dr
        gamma_i, gamma_t = gammas(h, bravais(self.eta[l], cos_theta_in, dr), dr)
        pf = self.Float(p)
        lobe = logistic(wrap(dphi - Phi(pf, gamma_i, gamma_t), dr), self.s, dr)
        return dr.select(p == self.p_max, 1 / TWO_PI, lobe)

    def _longitudinal(self, p, theta_in, theta_out):
        return self._pick([m(theta_in, theta_out, xp=self.dr) for m in self.M], p)

    def lobe_probabilities(self, A, weigh=None):
        """``P(p)``: each path's share of the attenuation, averaged over the spectrum, or
        weighed by ``weigh`` (a function from ``A[p]``, a list over the table's wavelengths,
        to a non-negative float per lane: the wavelengths a renderer carries).

        The weight of a sampled path at wavelength ``l`` is ``A[p][l] / P(p)``: with ``P``
        from wavelengths the path does not carry (a dyed fiber's absorbed blue, for a
        renderer at 650 nm), it exceeds 1 at every long path's vertex, and the product over
        a path's dozens of bounces in a ply is a firefly."""
        dr = self.dr
        mean = [sum(a[1:], a[0]) * (1 / self.L) for a in A]
        total = sum(mean[1:], mean[0])
        P = [m / dr.maximum(total, 1e-30) for m in mean]
        if weigh is None:
            return P, total
        mine = [weigh(a) for a in A]
        own = sum(mine[1:], mine[0])
        # lanes whose own wavelengths see no light on any path keep the spectral mean
        return [dr.select(own > 0, m / dr.maximum(own, 1e-30), q) for m, q in zip(mine, P)], total

    # -- the event --------------------------------------------------------------
    def sample(self, theta_in, h, u, P=None, light_out=False):
        """One event at offset ``h`` for light of longitude ``theta_in``; ``u`` four uniforms;
        ``P`` the paths' probabilities (default: :meth:`lobe_probabilities` of the spectral mean).

        The longitude is sampled first; the azimuthal lobe is centred with the Bravais
        index of the light's longitude: ``theta_in`` (the baker, tracing light), or the
        sampled ``theta_out`` if ``light_out`` (a camera path, which samples the light's
        side). Centred at the other side's index, a broad longitudinal lobe's sample falls
        in the far tail of the azimuthal lobe it is weighed with (a weight of hundreds).

        Returns ``(p, theta_out, dphi, pdf)`` (``p`` a UInt32, ``pdf`` of the middle
        wavelength over (lobe, theta_out, dphi), with the cosine of ``theta_out``).
        """
        dr = self.dr
        UInt = dr.uint32_array_t(self.Float)
        cos_in = self.cos_in(theta_in)
        if P is None:
            P, _ = self.lobe_probabilities(self.attenuations(cos_in, h))
        p = dr.zeros(UInt, dr.width(h)) + self.p_max
        cdf = dr.zeros(self.Float, dr.width(h))
        for q in range(self.p_max):  # the first lobe whose running sum passes u[0]
            cdf = cdf + P[q]
            p = dr.select((p == self.p_max) & (u[0] < cdf), q, p)
        theta_out = self._pick([m.sample(theta_in, u[1], u[2], xp=dr) for m in self.M], p)
        cos_light = self.cos_in(theta_out) if light_out else cos_in
        gamma_i, gamma_t = gammas(h, bravais(self.eta[self.ref], cos_light, dr), dr)
        dphi = dr.select(p == self.p_max, TWO_PI * u[3] - np.pi,
                         wrap(Phi(self.Float(p), gamma_i, gamma_t) + sample_logistic(u[3], self.s, dr), dr))
        return p, theta_out, dphi, self.pdf(theta_in, h, p, theta_out, dphi, P, light_out)

    def pdf(self, theta_in, h, p, theta_out, dphi, P=None, light_out=False):
        """Density of :meth:`sample` at ``(p, theta_out, dphi)`` (cosine of theta_out included)."""
        dr = self.dr
        cos_in = self.cos_in(theta_in)
        if P is None:
            P, _ = self.lobe_probabilities(self.attenuations(cos_in, h))
        cos_light = self.cos_in(theta_out) if light_out else cos_in
        return (self._pick(P, p) * self._longitudinal(p, theta_in, theta_out) * dr.cos(theta_out)
                * self._azimuthal(p, h, cos_light, dphi, self.ref))

    def eval_spectrum(self, theta_in, h, p, theta_out, dphi):
        """``f_p = M_p A_p N_p`` of path ``p`` at every wavelength (no cosine), and the kept
        energy ``sum_p A_p`` (the albedo at this ``h``) at every wavelength."""
        cos_in = self.cos_in(theta_in)
        A = self.attenuations(cos_in, h)
        M = self._longitudinal(p, theta_in, theta_out)
        f, kept = [], []
        for l in range(self.L):
            f.append(M * self._pick([A[q][l] for q in range(self.p_max + 1)], p)
                     * self._azimuthal(p, h, cos_in, dphi, l))
            kept.append(sum((A[q][l] for q in range(1, self.p_max + 1)), A[0][l]))
        return f, kept

    def eval_all(self, theta_in, h, thetas_out, dphi):
        """``f = sum_p M_p A_p N_p`` at offset ``h`` for light of longitude ``theta_in``, summed
        over every path, at each longitude of ``thetas_out`` (a list: the attenuations and
        azimuthal lobes, which do not depend on it, are computed once): a list over
        ``thetas_out`` of lists over the wavelengths (no cosine)."""
        dr = self.dr
        UInt = dr.uint32_array_t(self.Float)
        cos_in = self.cos_in(theta_in)
        A = self.attenuations(cos_in, h)
        AN = []
        for p in range(self.p_max + 1):
            pv = dr.zeros(UInt, dr.width(h)) + p
            AN.append([A[p][l] * self._azimuthal(pv, h, cos_in, dphi, l) for l in range(self.L)])
        out = []
        for theta_out in thetas_out:
            M = [m(theta_in, theta_out, xp=dr) for m in self.M]
            out.append([sum((M[p] * AN[p][l] for p in range(1, self.p_max + 1)), M[0] * AN[0][l])
                        for l in range(self.L)])
        return out

    def adjoint(self, theta_in, h_out, theta_out, dphi):
        """What Mitsuba's path tracer makes of its ``hair`` at one offset: the adjoint
        ``f(w_o -> w_i) cos(theta_o) / cos(theta_i)`` summed over every path, the model
        evaluated with the outgoing (camera) side as incident at ``h_out``, the offset of
        the camera's ray (``dphi = phi_o - phi_i``; every wavelength; no cosine of
        ``theta_out`` beyond the adjoint's own)."""
        scale = self.dr.cos(theta_out) / self.cos_in(theta_in)
        return [v * scale for v in self.eval_all(theta_out, h_out, [theta_in], -dphi)[0]]

    def exit_normal(self, nx, nz, p, h, theta, xp):
        """The outward normal where path ``p`` leaves, from the entry normal ``(nx, nz)``,
        for light of longitude ``theta`` entering at offset ``h`` (the middle wavelength's
        refraction; numpy or Dr.Jit).

        The residual (p = p_max) has no single exit; it is given the entry normal and the
        caller places it (the baker: uniformly over the outgoing side)."""
        cos = xp.maximum(xp.cos(theta), COS_GRAZING)
        _, gamma_t = gammas(h, bravais(self.eta[self.ref], cos, xp), xp)
        pf = np.asarray(p, np.float64) if xp is np else self.Float(p)
        turn = select(xp)(p == self.p_max, 0.0, exit_turn(pf, gamma_t))
        s, c = xp.sin(turn), xp.cos(turn)
        return c * nx - s * nz, s * nx + c * nz


# ------------------------------------------------------------------------------
# Geometry of one event in the cross-section (numpy or Dr.Jit)
# ------------------------------------------------------------------------------

def entry_offset(cx, cz, r, ox, oz, ux, uz, xp):
    """``h`` of the ray ``o + t u`` (``u`` unit) at the fiber centred at ``c`` of radius ``r``."""
    return xp.clip(((cx - ox) * uz - (cz - oz) * ux) / r, -1.0, 1.0)


def entry_normal(h, ux, uz, xp):
    """Outward normal where a ray travelling along ``u`` enters at offset ``h``."""
    along = xp.sqrt(xp.maximum(0.0, 1 - h * h))
    return -along * ux - h * uz, -along * uz + h * ux


def chord_end_normal(h, ux, uz, far, xp):
    """Outward normal at the end of the chord of a ray along ``u`` at offset ``h``: where it
    enters, or (``far``) where it would leave the fiber going straight on."""
    nx, nz = entry_normal(h, ux, uz, xp)
    along = 2 * xp.sqrt(xp.maximum(0.0, 1 - h * h))     # -2 (n . u) at the entry
    where = select(xp)
    return where(far, nx + along * ux, nx), where(far, nz + along * uz, nz)


def curve_exit(h, ux, uz, dx, dz, u, xp):
    """The ``curve`` exit (``models.bake.baker``) of light along ``u`` entering at offset
    ``h`` and leaving along ``d``: one end of the light's chord, chosen with the uniform
    ``u`` in proportion to ``a_k = max(0, n_k . d)`` (the width it shows the outgoing
    direction). Returns its outward normal ``(nx, nz)``, the offset ``h_out`` of the
    outgoing side's ray through it, and the weight ``w = (a_entry + a_far) / sqrt(1 - h^2)``
    (its mean over ``h`` uniform is 1 for every ``d``)."""
    n1x, n1z = chord_end_normal(h, ux, uz, False, xp)
    n2x, n2z = chord_end_normal(h, ux, uz, True, xp)
    a1 = xp.maximum(0.0, n1x * dx + n1z * dz)
    a2 = xp.maximum(0.0, n2x * dx + n2z * dz)
    far = u * (a1 + a2) >= a1
    where = select(xp)
    nx, nz = where(far, n2x, n1x), where(far, n2z, n1z)
    # float32 rounds h to +-1 about once in 1e7 rays, where 1 / sqrt(1 - h^2) would be
    # unbounded; the floor leaves out the |h| > 1 - 5e-7 that carry 0.1% of the weight
    w = (a1 + a2) / xp.maximum(xp.sqrt(xp.maximum(0.0, 1 - h * h)), 1e-3)
    # entry_offset of the ray along -d through the end: (c - x) x (-d) / r, x = c + r n
    return nx, nz, xp.clip(nx * dz - nz * dx, -1.0, 1.0), w


def leave_uniform(cx, cz, r, h, dx, dz, xp):
    """The thesis's exit: light leaving along ``d`` starts at the lateral offset ``h r``
    along the side vector ``y x d`` on the outgoing side, a hair beyond the surface."""
    along = xp.sqrt(xp.maximum(0.0, 1 - h * h)) + 1e-4
    return cx + r * (h * dz + along * dx), cz + r * (-h * dx + along * dz)


def leave(cx, cz, r, nx, nz, dx, dz, xp):
    """Where light leaving the surface point of normal ``n`` along ``d`` starts its next ray.

    A direction pointing back into the fiber (possible where a rough lobe leaves near
    grazing, and for every inward direction of an exit at the entry point) crosses its
    fiber unchanged to the far end of the chord (normal ``n - 2 (n.d) d``); the start is
    a hair outside the surface, so that the next cast cannot meet this fiber again.
    """
    nd = nx * dx + nz * dz
    inward = nd < 0
    where = select(xp)
    nx = where(inward, nx - 2 * nd * dx, nx)
    nz = where(inward, nz - 2 * nd * dz, nz)
    return cx + r * (1 + 1e-4) * nx, cz + r * (1 + 1e-4) * nz
