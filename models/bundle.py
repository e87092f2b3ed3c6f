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
from dataclasses import InitVar, dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import EllipseCollection
from matplotlib.patches import Circle, Ellipse
from scipy.spatial import cKDTree
from scipy.stats import qmc

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
                         f"{gap:.3g} um fits in semi-axes ({a:g}, {b:g}) um)")
    if packing is not None:
        n_target = int(round(packing * a * b / r**2))
        achieved = len(centers) * r**2 / (a * b)
        if n_target > len(centers):
            raise ValueError(f"bundle {name}: packing {packing} is not reachable with Poisson-disk sampling "
                             f"(at most {achieved:.3f} with gap {gap:.3g} um); lower it or the gap")
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

@dataclass(frozen=True)
class Migration:
    """Fiber migration (Zhao et al. 2016): fiber ``k`` at nominal distance ``rho_k`` from the
    axis moves between ``r_min rho_k`` and ``rho_k`` as it turns,

        ``rho_k(theta) = rho_k (r_min + (1 - r_min) (cos(s theta + theta_k0) + 1) / 2)``,

    ``theta = 2 pi y / pitch`` the helix's angle, ``s`` migration cycles per turn, ``theta_k0``
    each fiber's phase (uniform, drawn from ``seed``). The paper's ``R_max`` is 1: the
    nominal arrangement is the outermost position of every fiber.

    A ply with migration repeats after ``turns`` turns, the fewest (at most
    :attr:`MAX_TURNS`) in which every fiber completes whole migration cycles: ``s`` must be
    a fraction ``p / q`` with ``q <= MAX_TURNS`` (Cotton 1's 1.1 repeats after 10 turns).
    """

    r_min: float
    s: float
    seed: int = 0

    MAX_TURNS = 20

    def __post_init__(self):
        if not (0.0 < self.r_min <= 1.0):
            raise ValueError(f"migration: r_min {self.r_min:g} must lie in (0, 1] (the innermost position as a "
                             "fraction of the fiber's nominal distance from the axis; 1 = no migration)")
        if not (np.isfinite(self.s) and self.s > 0.0):
            raise ValueError(f"migration: s {self.s:g} must be a positive number of migration cycles per turn")
        self.turns  # refuse a period that never repeats, here rather than at the bake

    @property
    def turns(self) -> int:
        """Turns of the helix after which every fiber is back where it started."""
        for q in range(1, self.MAX_TURNS + 1):
            if abs(self.s * q - round(self.s * q)) < 1e-6 * q:
                return q
        raise ValueError(f"migration: s = {self.s:g} cycles per turn makes the ply repeat only after more than "
                         f"{self.MAX_TURNS} turns (s must be a fraction p/q with q <= {self.MAX_TURNS}, e.g. "
                         f"{round(self.s * 10) / 10:g}); the bake traces one whole period")

    def factor(self, theta, phases) -> np.ndarray:
        """``rho(theta) / rho`` at helix angles ``theta`` for fibers of ``phases`` (broadcast)."""
        return self.r_min + (1.0 - self.r_min) * 0.5 * (np.cos(self.s * theta + phases) + 1.0)

    def phases(self, n: int) -> np.ndarray:
        return np.random.default_rng(self.seed).uniform(0.0, 2 * np.pi, n)


@dataclass
class TwistedBundle:
    """A ply whose fibers are helices about its axis: the cross-section ``bundle`` (at
    ``y = 0``) turned along ``+y``, one turn per ``pitch`` micrometres, each fiber's distance
    from the axis migrating if ``migration`` is given (:class:`Migration`).

    ``pitch`` is signed as Zhao et al. 2016's ``alpha``: positive, every fiber is a
    right-handed helix (a Z twist); negative, left-handed (an S twist). Fiber ``k`` at
    height ``y`` sits at its ``y = 0`` position turned by ``-2 pi y / pitch`` about the
    axis (the project's ``phi`` runs from ``+x`` to ``+z``, a left-handed sense about
    ``+y``), scaled towards the axis by its migration. The arrangement repeats every
    :attr:`period`: ``|pitch|`` without migration, a whole number of turns with it.

    An elliptical cross-section (semi-axes ``a`` on x, ``b`` on z) stays where it is while
    its fibers turn through it, as in Zhao et al.: a fiber's position in the unit disk,
    ``(x / a, z / b)``, turns (and migrates), then is scaled back to the ellipse, so its
    helix is elliptical. Only a circle's fibers turn rigidly (a screw symmetry); an
    ellipse's pass each other closer than at ``y = 0`` (by up to ``b / a``), and a fiber
    near the rim crosses the ellipse by up to ``r (1 - b / a)`` where it passes the minor
    axis (it stays inside the bounding circle, across which the bake's rays enter).

    Checked on construction: no two fibers come closer than their radii anywhere along
    their length (:meth:`closest_approach`).
    """

    bundle: Bundle
    pitch: float
    migration: Migration | None = None
    checked: InitVar[bool] = True   # False: the caller checks (pipeline.build spaces a ply out)

    def __post_init__(self, checked: bool = True):
        if not np.isfinite(self.pitch) or self.pitch == 0:
            raise ValueError(f"twisted ply: the pitch must be a finite, non-zero length (got {self.pitch} um); "
                             "leave bundle.twist out for parallel fibers")
        if self.migration is not None and self.migration.r_min == 1.0:
            self.migration = None  # no migration: the rigid twist
        self._axes = np.asarray(self.bundle.semi_axes, float)
        u, v = (self.bundle.centers / self._axes).T          # in the unit disk
        self._rho, self._phi = np.hypot(u, v), np.arctan2(v, u)
        self._phases = None if self.migration is None else self.migration.phases(len(u))
        if checked:
            self.validate()

    @property
    def screw(self) -> bool:
        """Whether a turn of the ply is a shift along its axis (a circle, no migration)."""
        return self.migration is None and self.bundle.is_circle

    @property
    def omega(self) -> float:
        """Turn per unit length about ``+y`` in the ``phi`` sense (radians per um)."""
        return -2 * np.pi / self.pitch

    @property
    def turn_length(self) -> float:
        """The axial length of one turn of every helix, ``|pitch|``."""
        return abs(self.pitch)

    @property
    def period(self) -> float:
        """The axial length after which the whole arrangement repeats."""
        return self.turn_length * (1 if self.migration is None else self.migration.turns)

    def radius_at(self, y, k=None) -> np.ndarray:
        """Every fiber's radius in the unit disk at heights ``y`` (``[..., n]``), or that of
        fibers ``k`` (an index array broadcast against ``y``: ``[...]``)."""
        y = np.asarray(y, float)
        rho = self._rho if k is None else self._rho[k]
        if self.migration is None:
            return np.broadcast_to(rho, (y.shape + rho.shape) if k is None else np.broadcast_shapes(y.shape, rho.shape))
        theta = 2 * np.pi * y / self.pitch
        if k is None:
            return rho * self.migration.factor(theta[..., None], self._phases)
        return rho * self.migration.factor(theta, self._phases[k])

    def centers_at(self, y, k=None) -> np.ndarray:
        """Fiber centres (x, z) at heights ``y``: ``[..., n, 2]`` for every fiber, or
        ``[..., 2]`` for fibers ``k`` (an index array broadcast against ``y``)."""
        y = np.asarray(y, float)
        a = (self._phi if k is None else self._phi[k]) + self.omega * (y[..., None] if k is None else y)
        rho = self.radius_at(y, k)
        return np.stack([self._axes[0] * rho * np.cos(a), self._axes[1] * rho * np.sin(a)], -1)

    @property
    def max_lean(self) -> float:
        """The largest angle (radians) between a fiber and the ply's axis."""
        if self.screw:
            return float(np.arctan(np.max(self._rho) * self._axes[0] * abs(self.omega)))
        # the centre lines' slope |dc/dy|, sampled densely over the period
        y = np.linspace(0.0, self.period, 256 * round(self.period / self.turn_length) + 1)
        slope = np.linalg.norm(np.gradient(self.centers_at(y), y, axis=0), axis=-1)
        return float(np.arctan(slope.max()))

    def closest_approach(self) -> tuple[float, int, int]:
        """``(gap, i, j)``: the smallest surface-to-surface distance between two fibers
        anywhere along their length (negative: they intersect), and the pair.

        For every pair within reach, the distance between fiber ``i`` at height ``y`` and
        fiber ``j`` at ``y + dy`` is minimized over both, on a grid and then on grids 10x
        finer about each pair's minimum. For a screw symmetry (a circle without migration)
        the distance depends on ``dy`` alone, and ``y = 0`` suffices; otherwise ``y`` runs
        over the whole period.
        """
        b = self.bundle
        c, r = b.centers, b.radii
        lean = self.max_lean  # sampled over the period where a turn is no shift: computed once
        reach = 1.5 * (2 * r.max()) / np.cos(lean)  # beyond it, no pair comes near touching
        if self.migration is not None:  # fibers move towards the axis by up to (1 - r_min) rho
            reach += (1.0 - self.migration.r_min) * 2 * b.bounding_radius
        reach *= self._axes.max() / self._axes.min()  # an ellipse brings fibers closer by up to b / a

        pairs = cKDTree(c).query_pairs(reach, output_type="ndarray")
        if len(pairs) == 0:
            return np.inf, -1, -1
        i, j = pairs.T

        span = 2 * reach * np.tan(lean) + 1e-9
        if self.screw:
            grid = (np.zeros(1), np.linspace(-span, span, 801))
        else:
            n_y = 32 * round(self.period / self.turn_length)
            grid = (np.arange(n_y) * self.period / n_y, np.linspace(-span, span, 121))
            # drop the pairs that cannot be the closest: centre lines leaning by at most L that
            # lie D apart at equal heights are nowhere nearer than D cos L, and D moves by at
            # most 2 tan L per unit height between the samples; the equal-height samples are
            # themselves distances, so a pair whose bound exceeds the least of them is out
            t = np.tan(lean)
            D = np.min(np.linalg.norm(self.centers_at(grid[0][:, None], i) - self.centers_at(grid[0][:, None], j),
                                      axis=-1), 0)
            lower = np.maximum(D - t * (grid[0][1] - grid[0][0]), 0.0) * np.cos(lean) - r[i] - r[j]
            keep = lower <= np.min(D - r[i] - r[j])
            i, j = i[keep], j[keep]

        def dist(y, dy, i=i, j=j):  # [..., pairs] each
            d = self.centers_at(y, i) - self.centers_at(y + dy, j)
            return np.sqrt(np.sum(d**2, -1) + dy**2)

        steps = [g[1] - g[0] if len(g) > 1 else 0.0 for g in grid]
        Y, DY = (g.reshape(-1, 1) for g in np.meshgrid(*grid, indexing="ij"))
        best = np.empty((2, len(i)))
        for s0 in range(0, len(i), 64):  # a block of pairs at a time: the grid is large
            sl = slice(s0, s0 + 64)
            k = np.argmin(dist(Y, DY, i[sl], j[sl]), 0)
            best[:, sl] = Y[k, 0], DY[k, 0]
        U, V = (g.reshape(-1, 1) for g in np.meshgrid(np.linspace(-1.0, 1.0, 21), np.linspace(-1.0, 1.0, 21),
                                                         indexing="ij"))
        for _ in range(4):  # zoom in about each pair's minimum, 10x per round
            gy, gdy = best[0] + steps[0] * U, best[1] + steps[1] * V      # [21 x 21, pairs]
            d = dist(gy, gdy)
            k = np.argmin(d, 0)
            at = (k, np.arange(len(i)))
            best = np.stack([gy[at], gdy[at]])
            steps = [s / 10 for s in steps]
        gap = dist(best[0], best[1]) - r[i] - r[j]
        worst = int(np.argmin(gap))
        return float(gap[worst]), int(i[worst]), int(j[worst])

    def validate(self, tol: float = 1e-6) -> None:
        gap, i, j = self.closest_approach()
        if gap < -tol * self.bundle.bounding_radius:
            how = "lean" + (" and migrate" if self.migration is not None else "") + " past each other"
            if not self.bundle.is_circle:
                a, b = self.bundle.semi_axes
                how += f" through the ellipse ({a:g} x {b:g} um: its fibers pass closer than at y = 0)"
            raise ValueError(
                f"twisted ply: fibers {i} and {j} intersect by {-gap:.4g} um where they {how} (the pitch "
                f"{self.pitch:g} um leans the outer fibers {np.degrees(self.max_lean):.1f} deg); space the "
                "cross-section out (bundle.gap_um) or lengthen the pitch"
                + ("" if self.migration is None else f", or migrate less (r_min {self.migration.r_min:g} nearer 1)"))
