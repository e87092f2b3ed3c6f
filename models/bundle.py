"""Bundle geometry: fiber centres and radii in the 2D cross-section (micrometres).

The cross-section is the x-z plane of the bundle frame (+y along all fibers); an
elliptical bundle has its major axis on x. Arrangements:

* ``poisson``: Poisson-disk centres (``scipy.stats.qmc.PoissonDisk``) with minimum
  distance ``2 r + gap`` in a square around the bound, isotropically scaled (a circle
  is never stretched into an ellipse), keeping only fibers entirely inside the bound;
  thinned at random to a target packing fraction if one is given.
* ``file``: an explicit CSV with columns ``x_um, z_um, r_um``.
* ``zhao2016``: the procedural ply cross-section of Zhao et al. 2016: fiber density
  ``p(R) = (1 - 2 eps) ((e - e^R) / (e - 1))^beta + eps`` over the normalized radius
  ``R`` of the ``eX x eY`` ellipse, ``m`` fibers placed by rejection, overlapping
  candidates discarded.

Every bundle is checked on construction: no two fibers overlap and every fiber lies
inside the bound, or a :class:`ValueError` says which fibers and by how much.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .io import atomic_path

# Zhao et al. 2016, Table 2 (data/zhao2016_table2.csv, its source in data/ATTRIBUTION.md; kept in the
# repository so that a fresh clone needs nothing beside it)
ZHAO_CSV = Path(__file__).resolve().parents[1] / "data" / "zhao2016_table2.csv"
CM_TO_UM = 1e4


@dataclass
class Bundle:
    """Fibers ``centers[n, 2]`` (x, z) and ``radii[n]`` inside an ellipse ``semi_axes``."""

    centers: np.ndarray
    radii: np.ndarray
    semi_axes: tuple[float, float]
    name: str = "bundle"

    def __post_init__(self):
        self.centers = np.asarray(self.centers, dtype=np.float64).reshape(-1, 2)
        self.radii = np.broadcast_to(np.asarray(self.radii, dtype=np.float64), (len(self.centers),)).copy()
        self.semi_axes = (float(self.semi_axes[0]), float(self.semi_axes[1]))
        self.validate()

    @property
    def is_circle(self) -> bool:
        return self.semi_axes[0] == self.semi_axes[1]

    @property
    def bounding_radius(self) -> float:
        """Radius of the bounding circle; rays enter across its width ``2 R_b``."""
        return max(self.semi_axes)

    @property
    def packing_fraction(self) -> float:
        a, b = self.semi_axes
        return float(np.sum(np.pi * self.radii**2) / (np.pi * a * b))

    # -- checks ------------------------------------------------------------
    def validate(self, tol: float = 1e-9) -> None:
        a, b = self.semi_axes
        n = len(self.centers)
        if not (a > 0 and b > 0):
            raise ValueError(f"bundle {self.name}: semi-axes must be positive (got {a}, {b})")
        if n == 0:
            raise ValueError(f"bundle {self.name}: no fibers; enlarge the bundle or reduce the gap")
        if np.any(self.radii <= 0):
            raise ValueError(f"bundle {self.name}: fiber radii must be positive")
        if np.any(self.radii > min(a, b)):
            raise ValueError(f"bundle {self.name}: a fiber (r = {self.radii.max()} um) is larger than the "
                             f"bundle (semi-axes {a}, {b} um)")
        from scipy.spatial import cKDTree

        pairs = cKDTree(self.centers).query_pairs(2 * self.radii.max() + tol, output_type="ndarray")
        if len(pairs):
            d = np.linalg.norm(self.centers[pairs[:, 0]] - self.centers[pairs[:, 1]], axis=1)
            overlap = self.radii[pairs[:, 0]] + self.radii[pairs[:, 1]] - d
            bad = overlap > tol * max(a, b)
            if np.any(bad):
                i, j = pairs[np.argmax(overlap)]
                raise ValueError(f"bundle {self.name}: {bad.sum()} pair(s) of fibers overlap, worst fibers "
                                 f"{i} and {j} by {overlap.max():.4g} um; fibers may touch but not intersect")
        margin = distance_inside_ellipse(self.centers, a, b) - self.radii
        if np.any(margin < -tol * max(a, b)):
            i = int(np.argmin(margin))
            raise ValueError(f"bundle {self.name}: {np.sum(margin < 0)} fiber(s) leave the bound, worst fiber "
                             f"{i} at {self.centers[i]} by {-margin[i]:.4g} um")

    # -- pictures ----------------------------------------------------------
    def plot(self, path) -> None:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import EllipseCollection
        from matplotlib.patches import Circle, Ellipse

        a, b = self.semi_axes
        fig, ax = plt.subplots(figsize=(6, 6 * max(b / a, 0.35)), dpi=120)
        d = 2 * self.radii
        ax.add_collection(EllipseCollection(d, d, 0, units="xy", offsets=self.centers,
                                            offset_transform=ax.transData, facecolors="#d9b36c",
                                            edgecolors="#6b4f1d", linewidths=0.4))
        ax.add_patch(Ellipse((0, 0), 2 * a, 2 * b, fill=False, color="k", lw=1))
        if not self.is_circle:
            ax.add_patch(Circle((0, 0), self.bounding_radius, fill=False, color="0.6", ls="--", lw=0.8))
        R = self.bounding_radius * 1.05
        ax.set(xlim=(-R, R), ylim=(-min(R, b * 1.3 + 1), min(R, b * 1.3 + 1)), aspect="equal",
               xlabel="x [um]", ylabel="z [um]")
        ax.set_title(f"{self.name}: {len(self.radii)} fibers, packing {self.packing_fraction:.3f}")
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)


def distance_inside_ellipse(points: np.ndarray, a: float, b: float, n: int = 8192) -> np.ndarray:
    """Signed distance from points to the ellipse boundary (positive inside).

    The boundary is sampled densely (``n`` points, chord sag ~ (2 pi a / n)^2 / (8 rho));
    exact for a circle.
    """
    points = np.asarray(points, dtype=np.float64)
    if a == b:
        return a - np.linalg.norm(points, axis=1)
    from scipy.spatial import cKDTree

    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    boundary = np.stack([a * np.cos(t), b * np.sin(t)], -1)
    dist, _ = cKDTree(boundary).query(points)
    inside = (points[:, 0] / a) ** 2 + (points[:, 1] / b) ** 2 <= 1
    return np.where(inside, dist, -dist)


# --------------------------------------------------------------------------
# Arrangements
# --------------------------------------------------------------------------

def poisson(semi_axes, r, gap=0.0, packing=None, seed=0, name="poisson") -> Bundle:
    """Poisson-disk fibers of radius ``r`` inside an ellipse (or circle)."""
    from scipy.stats import qmc

    a, b = float(semi_axes[0]), float(semi_axes[1])
    if r >= min(a, b):
        raise ValueError(f"bundle {name}: fiber radius {r} um does not fit in semi-axes ({a}, {b}) um")
    side = 2 * max(a, b)
    engine = qmc.PoissonDisk(2, radius=(2 * r + gap) / side, rng=np.random.default_rng(seed))
    centers = engine.fill_space() * side - side / 2
    # Keep whole fibers only: centres inside the ellipse with semi-axes (a - r, b - r),
    # which lies inside the boundary's inner parallel curve; then the exact check.
    keep = (centers[:, 0] / (a - r)) ** 2 + (centers[:, 1] / (b - r)) ** 2 <= 1
    centers = centers[keep]
    centers = centers[distance_inside_ellipse(centers, a, b) >= r]
    if len(centers) == 0:
        raise ValueError(f"bundle {name}: the sampling region is empty (no fiber of radius {r} um with gap "
                         f"{gap} um fits in semi-axes ({a}, {b}) um)")
    if packing is not None:
        n_target = int(round(packing * a * b / r**2))
        achieved = len(centers) * r**2 / (a * b)
        if n_target > len(centers):
            raise ValueError(f"bundle {name}: packing {packing} is not reachable with Poisson-disk sampling "
                             f"(at most {achieved:.3f} with gap {gap} um); lower it or the gap")
        rng = np.random.default_rng(seed + 1)
        centers = centers[np.sort(rng.choice(len(centers), n_target, replace=False))]
    return Bundle(centers, r, (a, b), name)


def from_file(path, semi_axes, name="file") -> Bundle:
    """Fibers from a CSV with columns ``x_um, z_um, r_um`` (header required)."""
    path = Path(path)
    try:
        with path.open() as fh:
            rows = list(csv.DictReader(fh))
        data = np.array([[float(row["x_um"]), float(row["z_um"]), float(row["r_um"])] for row in rows])
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise ValueError(f"{path}: expected a CSV with columns x_um, z_um, r_um ({e})") from e
    if data.size == 0:
        raise ValueError(f"{path}: no fibers listed")
    bad = np.flatnonzero(~np.all(np.isfinite(data), axis=1) | (data[:, 2] <= 0))
    if bad.size:
        raise ValueError(f"{path}: row {bad[0] + 2} (x_um, z_um, r_um = {', '.join(map(str, data[bad[0]]))}) needs "
                         f"finite numbers and a radius > 0" + (f"; {bad.size - 1} more rows too" if bad.size > 1 else ""))
    return Bundle(data[:, :2], data[:, 2], semi_axes, name)


def zhao2016_row(yarn: str, csv_path=ZHAO_CSV) -> dict:
    """One yarn of Zhao et al. 2016 Table 2 (lengths converted to micrometres)."""
    with open(csv_path) as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    for row in rows:
        if row["yarn"].strip().lower() == yarn.strip().lower():
            out = {k: (v if k in ("yarn", "config") else float(v)) for k, v in row.items()}
            for k in ("eX", "eY", "R_ply"):
                out[k + "_um"] = out[k] * CM_TO_UM
            return out
    names = ", ".join(r["yarn"] for r in rows)
    raise ValueError(f"yarn {yarn!r} is not in {csv_path}; choose one of: {names}")


def zhao2016(yarn: str, r: float, seed=0, max_tries=200_000, name=None) -> Bundle:
    """The ply cross-section of a Zhao 2016 yarn with fibers of radius ``r`` (um)."""
    row = zhao2016_row(yarn)
    a, b = row["eX_um"], row["eY_um"]
    m, beta, eps = int(row["m_fibers_per_ply"]), row["beta"], row["eps"]
    if r >= min(a, b):
        raise ValueError(f"fiber radius {r} um does not fit in the ply ({a:.0f} x {b:.0f} um)")
    rng = np.random.default_rng(seed)
    e = np.e

    def density(R):
        return (1 - 2 * eps) * ((e - np.exp(R)) / (e - 1)) ** beta + eps

    centers = []
    tries = 0
    from scipy.spatial import cKDTree

    while len(centers) < m and tries < max_tries:
        batch = 4096
        tries += batch
        # uniform in the unit disk, accepted with probability p(R) (p <= 1 - eps <= 1)
        u = rng.uniform(-1, 1, (batch, 2))
        u = u[np.hypot(u[:, 0], u[:, 1]) <= 1]
        u = u[rng.uniform(size=len(u)) < density(np.hypot(u[:, 0], u[:, 1]))]
        for x, z in u * [a - r, b - r]:  # centres within the shrunk ellipse: whole fibers inside
            if centers:
                d, _ = cKDTree(centers).query([x, z]) if len(centers) > 64 else (
                    np.min(np.hypot(*(np.asarray(centers) - [x, z]).T)), None)
                if d < 2 * r:
                    continue
            centers.append((x, z))
            if len(centers) == m:
                break
    if len(centers) < m:
        raise ValueError(f"yarn {yarn}: only {len(centers)} of {m} fibers of radius {r} um fit without "
                         "overlap; use a smaller fiber radius")
    return Bundle(np.array(centers), r, (a, b), name or f"zhao2016 {yarn}")


# ------------------------------------------------------------------------------
# Twisted plies: the cross-section turned along the axis
# ------------------------------------------------------------------------------

@dataclass
class TwistedBundle:
    """A ply whose fibers are helices about its axis: the cross-section ``bundle`` (at
    ``y = 0``) turned rigidly along ``+y``, one turn per ``pitch`` micrometres.

    ``pitch`` is signed as Zhao et al. 2016's ``alpha``: positive, every fiber is a
    right-handed helix (a Z twist); negative, left-handed (an S twist). Fiber ``k`` at
    height ``y`` sits at its ``y = 0`` position turned by ``-2 pi y / pitch`` about the
    axis (the project's ``phi`` runs from ``+x`` to ``+z``, a left-handed sense about
    ``+y``). A fiber at distance ``rho`` from the axis leans ``atan(2 pi rho / |pitch|)``
    from it. The arrangement repeats every ``|pitch|`` along the axis.

    Circular plies only (an ellipse would turn with its fibers, which a yarn's plies do
    not). Checked on construction: no two fibers come closer than their radii anywhere
    along their length (:meth:`closest_approach`).
    """

    bundle: Bundle
    pitch: float

    def __post_init__(self):
        if not np.isfinite(self.pitch) or self.pitch == 0:
            raise ValueError(f"twisted ply: the pitch must be a finite, non-zero length (got {self.pitch} um); "
                             "leave bundle.twist out for parallel fibers")
        if not self.bundle.is_circle:
            raise ValueError("twisted ply: only circular cross-sections can be twisted (an elliptical ply "
                             f"{self.bundle.semi_axes} would turn with its fibers); use shape: circle")
        self.validate()

    @property
    def omega(self) -> float:
        """Turn per unit length about ``+y`` in the ``phi`` sense (radians per um)."""
        return -2 * np.pi / self.pitch

    @property
    def period(self) -> float:
        return abs(self.pitch)

    @property
    def max_lean(self) -> float:
        """The largest angle (radians) between a fiber and the ply's axis."""
        rho = np.hypot(*self.bundle.centers.T)
        return float(np.arctan(np.max(rho) * abs(self.omega)))

    def centers_at(self, y) -> np.ndarray:
        """Fiber centres ``[..., n, 2]`` (x, z) at heights ``y`` (broadcast)."""
        a = self.omega * np.asarray(y, float)[..., None]
        x, z = self.bundle.centers.T
        return np.stack([x * np.cos(a) - z * np.sin(a), x * np.sin(a) + z * np.cos(a)], -1)

    def closest_approach(self) -> tuple[float, int, int]:
        """``(gap, i, j)``: the smallest surface-to-surface distance between two fibers
        anywhere along their length (negative: they intersect), and the pair.

        The twist is a screw symmetry, so the distance between fibers ``i`` and ``j`` at
        heights ``y`` and ``y + dy`` depends on ``dy`` alone; it is minimized over ``dy``
        (dense samples, then refined) for every pair within reach.
        """
        b = self.bundle
        c, r = b.centers, b.radii
        reach = 1.5 * (2 * r.max()) / np.cos(self.max_lean)  # beyond it, no pair comes near touching
        from scipy.spatial import cKDTree

        pairs = cKDTree(c).query_pairs(reach, output_type="ndarray")
        if len(pairs) == 0:
            return np.inf, -1, -1
        i, j = pairs.T
        span = 2 * reach * np.tan(self.max_lean) + 1e-9
        dy = np.linspace(-span, span, 801)

        def dist(dy_):
            cj = self.centers_at(dy_)[..., j, :]                    # [k, pairs, 2]
            return np.sqrt(np.sum((c[i] - cj) ** 2, -1) + dy_[:, None] ** 2)

        d = dist(dy)
        k = np.argmin(d, 0)
        step = dy[1] - dy[0]
        fine = dy[k][None, :] + np.linspace(-step, step, 201)[:, None]  # refine around each minimum
        cj = np.stack([self.centers_at(fine[:, p])[:, q] for p, q in enumerate(j)], 1)
        d_fine = np.sqrt(np.sum((c[i][None] - cj) ** 2, -1) + fine**2)
        gap = d_fine.min(0) - r[i] - r[j]
        worst = int(np.argmin(gap))
        return float(gap[worst]), int(i[worst]), int(j[worst])

    def validate(self, tol: float = 1e-6) -> None:
        gap, i, j = self.closest_approach()
        if gap < -tol * self.bundle.bounding_radius:
            raise ValueError(
                f"twisted ply: fibers {i} and {j} intersect by {-gap:.4g} um where they lean past each other "
                f"(the pitch {self.pitch:g} um leans the outer fibers {np.degrees(self.max_lean):.1f} deg); space "
                "the cross-section out (bundle.gap_um) or lengthen the pitch")
