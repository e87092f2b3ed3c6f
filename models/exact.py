"""Exact ray optics of a ply of smooth dielectric cylinders: the reference for exit models.

Nothing is modelled here but the geometry, Snell's law and Fresnel's equations:
parallel circular fibers of relative index ``eta`` (lossless), unpolarized Fresnel
reflectance at every interface (the 3D angle between the ray and the surface normal),
total internal reflection, and the ray's direction carried as a 3D vector. It shares
nothing with the baker but the fiber centres: no fiber table, no lobes, no offsets
``h``, no Mitsuba (its own ray-circle intersections, float64).

Why it is exact at any ``theta_i``: the normals of parallel cylinders are perpendicular
to their common axis, so reflection keeps the axial component ``d.y`` of a direction
and refraction scales it by the index ratio; outside the fibers every ray travels with
``d.y = -sin(theta_i)``, so all light leaves on the cone ``theta_o = -theta_i`` and only
the azimuth needs tallying. Each interface splits the ray stochastically (reflect with
probability ``F``, refract otherwise), which is unbiased for the energy.

Rays enter as the baker's do (the same meaning, independent code): azimuths
``phi_i`` stratified over the circle, offsets stratified across the bounding width
``2 R_b``, and each escaping ray is binned at ``dphi = phi_o - phi_i``, so the result is
the arrangement's rotation average, per ray entering ``2 R_b``:

    energy[k]   fraction leaving into azimuth bin ``k`` of ``dphi`` in [-pi, pi)
    passthrough fraction touching no fiber
    lost        fraction still bouncing at ``max_events`` (reported, never silently dropped)

Example::

    from models import bundle, exact
    b = bundle.poisson((200.0, 200.0), 20.0, seed=1)
    out = exact.trace(b.centers, b.radii, eta=1.5639, theta_i=0.0, n_rays=400_000)
    out["energy"].sum() + out["passthrough"] + out["lost"]   # 1 (lossless)
"""

from __future__ import annotations

import numpy as np


def fresnel_unpolarized(cos_i, eta_r):
    """Reflectance for light in a medium of index ``n1`` meeting ``n2``, ``eta_r = n1 / n2``.

    ``cos_i`` is the 3D angle of incidence. Returns ``(F, cos_t)``; ``F = 1`` under total
    internal reflection.
    """
    sin2_t = eta_r**2 * (1 - cos_i**2)
    tir = sin2_t >= 1
    cos_t = np.sqrt(np.maximum(0.0, 1 - sin2_t))
    rs = (eta_r * cos_i - cos_t) / (eta_r * cos_i + cos_t)
    rp = (cos_i - eta_r * cos_t) / (cos_i + eta_r * cos_t)
    return np.where(tir, 1.0, 0.5 * (rs**2 + rp**2)), cos_t


def _first_hit(pos, u, centers, radii, skip):
    """Nearest circle hit from outside, for 2D rays ``pos + t u`` (``u`` unit).

    ``skip[n]`` is the circle a ray has just left (a convex circle cannot be met again
    by a ray leaving it), -1 for none. Returns ``(t, index)``, ``t = inf`` where missed.
    """
    oc = centers[None, :, :] - pos[:, None, :]                 # [n, m, 2]
    b = np.einsum("nmk,nk->nm", oc, u)
    disc = b * b - (np.einsum("nmk,nmk->nm", oc, oc) - radii[None, :] ** 2)
    t = b - np.sqrt(np.maximum(disc, 0.0))
    ok = (disc > 0) & (t > 0)
    ok[np.arange(len(pos)), np.maximum(skip, 0)] &= skip < 0
    t = np.where(ok, t, np.inf)
    k = np.argmin(t, axis=1)
    return t[np.arange(len(pos)), k], k


def trace(centers, radii, eta: float, theta_i: float, n_rays: int, seed: int = 1,
          bounding_radius: float | None = None, n_phi_bins: int = 72, max_events: int = 100_000,
          chunk: int = 4096, progress: bool = False) -> dict:
    """Trace ``n_rays`` rays through smooth lossless dielectric circles (module docstring).

    ``centers[m, 2]`` (x, z) and ``radii[m]`` in any one unit, the bundle centred at the
    origin; ``theta_i`` in radians; ``bounding_radius`` the beam's half width ``R_b``
    (default: the smallest circle about the origin holding every fiber). Returns ``energy[n_phi_bins]`` over ``dphi`` edges
    ``linspace(-pi, pi, n_phi_bins + 1)``, its binomial standard error ``energy_se``,
    ``passthrough``, ``lost``, ``events`` (interfaces met, in total) and ``n_rays``.
    """
    centers = np.asarray(centers, np.float64).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radii, np.float64), (len(centers),))
    if not (abs(theta_i) < np.pi / 2):
        raise ValueError(f"theta_i must lie in (-pi/2, pi/2) radians (got {theta_i})")
    if eta <= 0:
        raise ValueError(f"eta must be positive (got {eta})")
    rng = np.random.default_rng(seed)
    R_b = float(np.max(np.hypot(centers[:, 0], centers[:, 1]) + radii))
    if bounding_radius is not None:
        if bounding_radius < R_b * (1 - 1e-9):
            raise ValueError(f"bounding_radius {bounding_radius} does not hold every fiber (needs {R_b})")
        R_b = float(bounding_radius)
    counts = np.zeros(n_phi_bins)
    passthrough = lost = events = 0
    # stratified offsets across the width and azimuths over the circle, shuffled apart
    offset = (-1 + 2 * (np.arange(n_rays) + rng.uniform(size=n_rays)) / n_rays) * R_b
    phi_i = 2 * np.pi * rng.permutation((np.arange(n_rays) + rng.uniform(size=n_rays)) / n_rays)
    sin_ti, cos_ti = np.sin(theta_i), np.cos(theta_i)
    chunks = range(0, n_rays, chunk)
    if progress:
        from tqdm import tqdm
        chunks = tqdm(chunks, desc="exact", unit="chunk", leave=False)
    for lo in chunks:
        hi = min(n_rays, lo + chunk)
        n = hi - lo
        # Phase 1: rays arriving from w_i (azimuth phi_i, longitude theta_i) travel along -w_i
        travel = phi_i[lo:hi] + np.pi
        u = np.stack([np.cos(travel), np.sin(travel)], -1)
        pos = -2 * R_b * u + offset[lo:hi, None] * np.stack([-u[:, 1], u[:, 0]], -1)
        d = np.stack([cos_ti * u[:, 0], np.full(n, -sin_ti), cos_ti * u[:, 1]], -1)  # 3D (x, y, z)
        inside = np.full(n, -1)      # the fiber a ray is in, -1 outside
        last = np.full(n, -1)        # the fiber a ray outside has just left
        alive = np.arange(n)
        n_events = np.zeros(n, np.int64)
        while len(alive):
            p, dd, ins = pos[alive], d[alive], inside[alive]
            u2 = dd[:, [0, 2]] / np.linalg.norm(dd[:, [0, 2]], axis=1, keepdims=True)
            out = ins < 0
            # Phase 2: the next interface: the nearest circle from outside, the far
            # side of its own circle from inside (a chord, 2 (c - p).u long)
            t = np.empty(len(alive))
            k = np.where(out, -1, ins)
            if out.any():
                t[out], k[out] = _first_hit(p[out], u2[out], centers, radii, last[alive][out])
            c_in = centers[ins[~out]]
            t[~out] = 2 * np.einsum("nk,nk->n", c_in - p[~out], u2[~out])
            # Phase 3: rays leaving the ply; tally their azimuth relative to phi_i
            esc = ~np.isfinite(t)
            if esc.any():
                idx = alive[esc]
                never = n_events[idx] == 0
                passthrough += int(never.sum())
                dphi = np.arctan2(dd[esc, 2], dd[esc, 0]) - phi_i[lo + idx]
                dphi = np.mod(dphi + np.pi, 2 * np.pi) - np.pi
                b = np.clip(((dphi + np.pi) / (2 * np.pi) * n_phi_bins).astype(np.int64), 0, n_phi_bins - 1)
                counts += np.bincount(b[~never], minlength=n_phi_bins)
            # Phase 4: the interface: reflect with probability F, else refract (3D Snell)
            m = ~esc
            idx, k, hit_from_out = alive[m], k[m], out[m]
            dd = dd[m]
            normal = p[m] + t[m, None] * u2[m] - centers[k]
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            pos[idx] = centers[k] + radii[k, None] * normal     # on the circle, no drift
            n3 = np.stack([normal[:, 0], np.zeros(len(k)), normal[:, 1]], -1)
            facing = np.where(hit_from_out[:, None], n3, -n3)  # towards the side the ray comes from
            cos_i = np.clip(-np.einsum("nk,nk->n", dd, facing), 0.0, 1.0)
            eta_r = np.where(hit_from_out, 1.0 / eta, eta)
            F, cos_t = fresnel_unpolarized(cos_i, eta_r)
            reflect = rng.uniform(size=len(k)) < F
            d_refl = dd + 2 * cos_i[:, None] * facing
            d_refr = eta_r[:, None] * dd + (eta_r * cos_i - cos_t)[:, None] * facing
            dn = np.where(reflect[:, None], d_refl, d_refr)
            d[idx] = dn / np.linalg.norm(dn, axis=1, keepdims=True)
            now_inside = np.where(reflect, ~hit_from_out, hit_from_out)
            inside[idx] = np.where(now_inside, k, -1)
            last[idx] = np.where(now_inside, -1, k)
            n_events[idx] += 1
            capped = n_events[idx] >= max_events
            lost += int(capped.sum())
            alive = idx[~capped]
        events += int(n_events.sum())
    energy = counts / n_rays
    return {"energy": energy, "energy_se": np.sqrt(energy * (1 - energy) / n_rays),
            "passthrough": passthrough / n_rays, "lost": lost / n_rays, "events": events, "n_rays": n_rays,
            "phi_edges": np.linspace(-np.pi, np.pi, n_phi_bins + 1)}


def shadow_passthrough(centers, radii, bounding_radius: float, n_phi: int = 3600) -> float:
    """Geometric passthrough of the rotation average: the uncovered share of ``2 R_b``.

    Per azimuth, the fibers' shadows on the line across the beam are intervals
    ``[s - r, s + r]``; their union's length is what a ray cannot cross. Exact per
    azimuth (midpoint rule over ``n_phi`` azimuths), independent of any tracing.
    """
    centers = np.asarray(centers, np.float64).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radii, np.float64), (len(centers),))
    R_b = float(bounding_radius)
    free = 0.0
    for phi in (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi:
        s = -centers[:, 0] * np.sin(phi) + centers[:, 1] * np.cos(phi)
        lo, hi = s - radii, s + radii
        order = np.argsort(lo)
        lo, hi = lo[order], np.maximum.accumulate(hi[order])
        # the union's length: what each interval adds beyond the running maximum before it
        prev = np.concatenate([[-np.inf], hi[:-1]])
        covered = np.sum(np.maximum(0.0, hi - np.maximum(lo, prev)))
        free += 2 * R_b - covered
    return free / (n_phi * 2 * R_b)
