"""Independent high-precision Mie cylinder coefficients with mpmath.

No recurrences and no logarithmic derivatives: every Bessel function, including
J_n(eta) of the complex argument, is evaluated directly by mpmath at 40 digits, and
B&H's eq. (8.30)-(8.33) are used as printed. Slow, so the tests and ``bcsdf
stability`` use it at a handful of cases only. Needs ``mpmath`` (test extra).
"""


def coefficients(m, x, zeta_deg, orders, dps=40):
    """(aI, bI, aII, bII) as lists of complex, at the given orders n."""
    import mpmath as mp

    with mp.workdps(dps):
        m = mp.mpc(m)
        x = mp.mpf(x)
        zeta = mp.radians(mp.mpf(zeta_deg))
        xi = x * mp.sin(zeta)
        eta = x * mp.sqrt(m**2 - mp.cos(zeta) ** 2)
        out = []
        for n in orders:
            Jx, dJx = mp.besselj(n, xi), mp.besselj(n, xi, derivative=1)
            Yx, dYx = mp.bessely(n, xi), mp.bessely(n, xi, derivative=1)
            Hx, dHx = Jx + 1j * Yx, dJx + 1j * dYx
            Je, dJe = mp.besselj(n, eta), mp.besselj(n, eta, derivative=1)
            A = 1j * xi * (xi * dJe * Jx - eta * Je * dJx)
            B = xi * (m**2 * xi * dJe * Jx - eta * Je * dJx)
            C = n * mp.cos(zeta) * eta * Je * Jx * (xi**2 / eta**2 - 1)
            D = n * mp.cos(zeta) * eta * Je * Hx * (xi**2 / eta**2 - 1)
            V = xi * (m**2 * xi * dJe * Hx - eta * Je * dHx)
            W = 1j * xi * (eta * Je * dHx - xi * dJe * Hx)
            den = W * V + 1j * D * D
            out.append(((C * V - B * D) / den, (W * B + 1j * D * C) / den,
                        -(A * V - 1j * C * D) / den, -1j * (C * W + A * D) / den))
        return tuple([complex(o[k]) for o in out] for k in range(4))
