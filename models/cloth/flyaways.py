"""Hair-type flyaways about the plies: the fuzz of a real yarn (Zhao et al. 2016, Sec. 4.4).

A hair flyaway is a short fiber that leaves its ply: in the ply's cylindrical frame
``(r, phi, s)`` (distance from the ply's centre line, angle about it, arc length along it)
it runs straight from ``(r0, phi0, s0)`` to ``(r0 + r_span, phi0 + phi_span, s0 + s_span)``,
with ``s0`` and ``phi0`` uniform and

    r0 ~ N(Rhair_min),  r_span ~ N(Rhair_span) > 0,  s_span ~ N(zhair_span) > 0,
    phi_span ~ N(thhair_span),   Rhair_min etc. the (mu, sigma) pairs of Zhao's Table 2,

``rho_hair`` of them per unit length of every ply. As in Zhao et al.'s public generator
(``Fiber-level-cloth-simulation``, its "improved flyaways"), each draw uses half the listed
sigma (that code's note: the fitted sigma is twice the Gaussian's), ``r0`` is clamped to
the ply's radius, and the axial span is drawn positive; which way along the ply a hair
points is a coin flip here (the ply has no preferred direction).

**Units.** The lengths of ``zhao2016_table2.csv`` are absolute, in the table's length unit
(the generator clamps ``r0`` against the ply's ellipse, ``sqrt(e_X e_Y)``, in the same
unit); they are scaled with the ply, as :meth:`~models.cloth.yarn.YarnSpec.from_zhao` scales
the yarn, and the density per unit length inversely.

**Loop-type flyaways are not drawn.** Their fitted radius (``Rloop_max``, Cotton 1: mean
0.024) lies inside the ply's own ellipse (``e_X`` 0.026) in the table's units, so as
absolute radii the loops would not leave the ply, and the public generator has them
switched off (``if (0 && nloop > 0)``): what they should be is not settled by the data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .curves import bspline_samples, interpolate_bspline
from .plies import transport_frames

HAIR_SAMPLES = 4        # points along one hair (a straight line in (r, phi, s): a gentle spiral)
SIGMA_SCALE = 0.5       # Zhao et al.'s generator: the fitted sigma is twice the Gaussian's


@dataclass
class HairSpec:
    """Hair flyaways of one ply in scene units: ``density`` per unit length and the
    ``(mu, sigma)`` of the start radius, radial span, axial span (lengths) and azimuthal
    span (radians)."""

    density: float
    r0: tuple[float, float]
    r_span: tuple[float, float]
    s_span: tuple[float, float]
    phi_span: tuple[float, float]

    @classmethod
    def from_zhao(cls, row: dict, r_ply: float, density_scale: float = 1.0) -> "HairSpec":
        """Zhao's hair flyaways for a ply of radius ``r_ply`` (scene units): the table's
        lengths scaled by ``r_ply / max(e_X, e_Y)`` (the ply's bounding circle, as the plies
        are drawn), its density by the inverse, times ``density_scale``."""
        scale = r_ply / max(float(row["eX"]), float(row["eY"]))

        def pair(name, k=scale):
            return (k * float(row[f"{name}_mu"]), k * float(row[f"{name}_sd"]))
        return cls(density_scale * float(row["rho_hair"]) / scale, pair("Rhair_min"), pair("Rhair_span"),
                   pair("zhair_span"), pair("thhair_span", 1.0))


def _normal(rng, mu_sigma, n, low=None):
    """``n`` draws of N(mu, SIGMA_SCALE sigma), redrawn where ``<= low`` (a truncated normal)."""
    mu, sigma = mu_sigma
    x = mu + SIGMA_SCALE * sigma * rng.standard_normal(n)
    if low is not None:
        for _ in range(1000):
            bad = x <= low
            if not bad.any():
                break
            x[bad] = mu + SIGMA_SCALE * sigma * rng.standard_normal(int(bad.sum()))
        x = np.maximum(x, np.nextafter(low, np.inf))  # a spread too narrow to leave `low`: at it
    return x


@dataclass
class Hairs:
    """The drawn parameters of ``n`` hairs about one ply (arrays ``[n]``): where each starts
    (``s0`` along the ply, ``phi0`` round it, ``r0`` from its axis) and its spans."""

    s0: np.ndarray
    phi0: np.ndarray
    r0: np.ndarray
    r_span: np.ndarray
    s_span: np.ndarray
    phi_span: np.ndarray


def draw_hairs(rng, spec: HairSpec, r_ply: float, length: float) -> Hairs:
    """``round(density * length)`` hairs: ``s0``, ``phi0`` uniform, the rest from ``spec``
    (``r0`` clamped to the ply's radius, positive radial and axial spans, the axial one's
    sign a coin flip)."""
    n = int(np.floor(spec.density * length + 0.5))
    r0 = np.minimum(_normal(rng, spec.r0, n, low=0.0), r_ply)
    r_span = _normal(rng, spec.r_span, n, low=0.0)
    s_span = _normal(rng, spec.s_span, n, low=0.0) * rng.choice([-1.0, 1.0], n)
    phi_span = _normal(rng, spec.phi_span, n)
    return Hairs(rng.uniform(0.0, length, n), rng.uniform(0.0, 2 * np.pi, n), r0, r_span, s_span, phi_span)


def place_hairs(frames, hairs: Hairs, r_out: float) -> np.ndarray:
    """Points ``[HAIR_SAMPLES, n, 3]`` of each hair's part outside radius ``r_out`` (the ply's
    surface and a margin; the part inside is the ply's own fibers, which the bundle stands
    for), in the ply's frame; hairs that never leave it are not placed (``n`` counts the rest)."""
    f = frames
    end = hairs.r0 + hairs.r_span
    out = end > r_out
    u_in = np.clip((r_out - hairs.r0[out]) / hairs.r_span[out], 0.0, 1.0)
    u = u_in + np.linspace(0.0, 1.0, HAIR_SAMPLES)[:, None] * (1.0 - u_in)   # [HAIR_SAMPLES, n]
    r = hairs.r0[out] + u * hairs.r_span[out]
    phi = hairs.phi0[out] + u * hairs.phi_span[out]
    s = hairs.s0[out] + u * hairs.s_span[out]
    s = np.mod(s, f.length) if f.closed else np.clip(s, 0.0, f.length)
    centre, _, normal, binormal = f.at(s)  # the ply's frame at s, between its dense samples
    return centre + r[..., None] * (np.cos(phi)[..., None] * normal + np.sin(phi)[..., None] * binormal)


def piercing(points: np.ndarray, owner: np.ndarray, ply_samples: list[np.ndarray], reach: float) -> np.ndarray:
    """Which hairs (``points [HAIR_SAMPLES, n, 3]``, of plies ``owner [n]``) come within
    ``reach`` of another ply's centre line (its samples): they would pierce it."""

    pts = np.concatenate(ply_samples)
    ids = np.concatenate([np.full(len(p), k) for k, p in enumerate(ply_samples)])
    tree = cKDTree(pts)
    hit = np.zeros(points.shape[1], bool)
    for row in points:  # the 16 nearest samples within reach: the own ply's are a few of them
        d, j = tree.query(row, k=16, distance_upper_bound=reach)
        found = np.isfinite(d)
        hit |= np.any(found & (ids[np.minimum(j, len(ids) - 1)] != owner[:, None]), axis=1)
    return hit


def tapered(C: np.ndarray, radius: float) -> np.ndarray:
    """Open B-splines' control points ``C [m, ..., 3]`` (many curves at once) with a radius
    column, ``[m + 6, ..., 4]``: three more control points beyond each end, along the end's
    direction, whose radius 0 makes the curve taper to a point over a short tip. Mitsuba
    3.9's ``bsplinecurve`` crashed (segfault) on a 1280 x 960 x 32 spp glove render of blunt
    open hairs, and rendered it with tips; a fiber's tip is tapered anyway."""
    step = (np.arange(1.0, 4.0) / 9).reshape((3,) + (1,) * (C.ndim - 1))  # a tip a third of the end's spacing
    head = C[0] - (C[1] - C[0]) * step[::-1]
    tail = C[-1] + (C[-1] - C[-2]) * step
    points = np.concatenate([head, C, tail])
    r = np.zeros(points.shape[:-1] + (1,))
    r[3:-3] = radius
    return np.concatenate([points, r], axis=-1)


def pointed(P: np.ndarray, radius: float) -> np.ndarray:
    """Polylines through ``P [m, ..., 3]`` (many at once) with a radius column, ``[m + 2, ..., 4]``:
    one more point beyond each end, a third of the end's spacing out, of radius 0 (a
    pointed tip, as :func:`tapered` gives a B-spline)."""
    points = np.concatenate([P[:1] - (P[1] - P[0])[None] / 3, P, P[-1:] + (P[-1] - P[-2])[None] / 3])
    r = np.full(points.shape[:-1] + (1,), float(radius))
    r[0] = r[-1] = 0.0
    return np.concatenate([points, r], axis=-1)


CURVES = ("linearcurve", "bsplinecurve")   # what a hair is drawn as (Mitsuba's shape type)


def hair_flyaways(plies: list[np.ndarray], r_ply: float, spec: HairSpec, seed: int = 0,
                  hair_radius: float = 0.0, curve: str = "linearcurve") -> list[np.ndarray]:
    """Hair flyaways about every ply (``plies``: B-spline control points ``[n, 3]`` of the
    ply centre lines in Mitsuba's layout, as :func:`~models.cloth.yarn.build_plies` returns
    them; a closed loop's ends repeat its first three points), each hair its control points
    with their radius, ``[m, 4]``: for ``curve = "linearcurve"`` the polyline of its
    ``HAIR_SAMPLES`` points, :func:`pointed` (6 points); for ``"bsplinecurve"`` the B-spline
    through them, :func:`tapered` at both tips (12 points). The polyline is a third cheaper to
    render (docs/BENCHMARKS.md, "Cloth"); its kinks, a few degrees on hairs a tenth of a
    pixel wide, do not show.

    Per ply, :func:`draw_hairs`, in the ply's rotation-minimizing frame (continuous round a
    closed loop, so a hair may cross its seam); each hair from where it leaves the ply
    (:func:`place_hairs`, ``hair_radius`` clear of its surface); hairs that would pierce
    another ply are left out (:func:`piercing`): touching curves are also what Mitsuba 3.9's
    curve intersection cannot take (it crashed a glove render).
    """
    if curve not in CURVES:
        raise ValueError(f"flyaways: curve {curve!r}: use one of {', '.join(CURVES)}")
    rng = np.random.default_rng(seed)
    placed, owner, samples = [], [], []
    for k, C in enumerate(plies):
        loop = len(C) > 6 and np.allclose(C[:3], C[-3:])
        p = bspline_samples(C, 2)
        f = transport_frames(p[:-1] if loop else p, closed=loop, stride=4)
        samples.append(f.p)
        pts = place_hairs(f, draw_hairs(rng, spec, r_ply, f.length), r_ply + 1.5 * hair_radius)
        placed.append(pts)
        owner.append(np.full(pts.shape[1], k))
    if not placed:
        return []
    points, owner = np.concatenate(placed, axis=1), np.concatenate(owner)
    if len(plies) > 1 and points.shape[1]:
        points = points[:, ~piercing(points, owner, samples, r_ply + 1.5 * hair_radius)]
    if not points.shape[1]:
        return []
    if curve == "linearcurve":
        return list(pointed(points, hair_radius).transpose(1, 0, 2))
    return list(tapered(interpolate_bspline(points, closed=False), hair_radius).transpose(1, 0, 2))
