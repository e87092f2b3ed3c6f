"""From a yarn-level model (centre lines) to the ply curves a renderer draws.

:func:`build_plies` takes a :class:`~models.cloth.bcc.CurveCollection` in the model's
units, scales it to scene units, and winds ``K`` plies about every yarn
(:mod:`models.cloth.plies`); each ply becomes a closed (or open) uniform cubic B-spline
with the ply's radius at every control point: the control points of one Mitsuba
``bsplinecurve`` (:func:`write_curves`, Mitsuba's text format ``x y z r`` per line, a
blank line between curves). What it measured travels with the result (:class:`PlyGeometry`):
how far the B-splines stay from the file's centre lines, and how close yarns come.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io import atomic_path
from .bcc import CurveCollection
from .curves import evaluate, interpolate_bspline, n_segments, to_bspline, write_mitsuba_curves
from .plies import bend_radius, nearest_other, transport_frames, wind_plies


@dataclass
class YarnSpec:
    """A yarn's plies in scene units: ``K`` plies of radius ``r_ply`` at ``R`` from the yarn's
    centre line, one turn per ``pitch`` (signed: the twist direction)."""

    K: int
    r_ply: float
    R: float
    pitch: float

    @property
    def radius(self) -> float:
        """The yarn's radius: the circle around its plies."""
        return self.R + self.r_ply if self.K > 1 else self.r_ply

    @classmethod
    def from_zhao(cls, row: dict, yarn_radius: float, K: int | None = None) -> "YarnSpec":
        """Zhao et al. 2016's plies (``K_plies``, ``R_ply``, ``alpha_ply``, the ply's
        ``e_X``, ``e_Y``), scaled so that the yarn's radius is ``yarn_radius``. The ply is
        drawn as its bounding circle (the bundle BSDF's cylinder)."""
        K = int(row["K_plies"]) if K is None else int(K)
        r_ply = max(float(row["eX"]), float(row["eY"]))
        R = float(row["R_ply"]) if K > 1 else 0.0
        scale = yarn_radius / (R + r_ply)
        return cls(K, r_ply * scale, R * scale, float(row["alpha_ply"]) * scale)

    def overlap(self) -> float:
        """How far neighbouring plies of one yarn interpenetrate (0: they do not)."""
        if self.K < 2:
            return 0.0
        return max(0.0, 2 * self.r_ply - 2 * self.R * np.sin(np.pi / self.K))


@dataclass
class PlyGeometry:
    """Ply curves (Mitsuba B-spline control points ``[n, 3]``, with ``radius``) and measurements."""

    curves: list[np.ndarray]
    radius: float
    centre_deviation: float          # B-spline of a centre line vs the file's curve, largest (scene units)
    closest_yarns: float             # smallest centre-to-centre distance of two yarn passes (scene units)
    overlapping: float               # share of the yarn length nearer another pass than a yarn diameter
    folded: float = 0.0              # share of the yarn length bent tighter than the yarn's radius
    pitch_used: list[float] = field(default_factory=list)

    @property
    def control_points(self) -> int:
        return sum(len(c) for c in self.curves)

    def overlap_warning(self, yarn: YarnSpec) -> str | None:
        """A sentence about interpenetrating yarns, with the amounts (None if they do not)."""
        said = []
        if self.overlapping > 0:
            said.append(f"yarns interpenetrate: the nearest two passes are {self.closest_yarns:.3g} apart centre to "
                        f"centre (a yarn diameter is {2 * yarn.radius:.3g}), and {100 * self.overlapping:.1f}% of the "
                        "yarn length comes nearer another pass than a yarn diameter")
        if self.folded > 0:
            said.append(f"{100 * self.folded:.2f}% of the yarn length bends tighter than the yarn's radius "
                        f"({yarn.radius:.3g}), where the yarn folds through itself")
        if not said:
            return None
        return "; ".join(said) + "; a smaller cloth.yarn_radius_mm " + ("separates them" if self.overlapping > 0
                                                                          else "clears it")


def centre_lines(collection: CurveCollection, scale: float, tol: float):
    """Each curve as ``(B-spline control points, closed)`` in scene units within ``tol``, and
    the largest deviation."""
    out, worst = [], 0.0
    for k, c in enumerate(collection.curves):
        P = scale * c.points
        if len(P) < (3 if c.closed else 4):
            raise ValueError(f"curve {k} has {len(P)} control points; a yarn needs at least 4 "
                             "(3 on a closed loop)")
        step = np.linalg.norm(np.diff(np.concatenate([P, P[:1]]) if c.closed else P, axis=0), axis=1)
        tiny = step <= 1e-9 * max(1.0, float(np.abs(P).max()))
        if np.any(tiny):
            raise ValueError(f"curve {k} has coincident control points (point {int(np.argmax(tiny))}); "
                             "remove zero-length segments from the model")
        C, deviation, _ = to_bspline(P, c.closed, collection.kind, tol)
        out.append((C, c.closed))
        worst = max(worst, deviation)
    return out, worst


def build_plies(collection: CurveCollection, scale: float, yarn: YarnSpec, tol_fraction: float = 0.01,
                samples_per_turn: int = 16, samples_per_segment: int = 2, progress=None) -> PlyGeometry:
    """The plies of every yarn of ``collection`` (model units times ``scale`` = scene units).

    ``tol_fraction``: how far (in yarn radii) a centre line's B-spline may leave the file's
    curve. The plies are wound about the file's own curve (evaluated exactly, 8 samples per
    segment), so the B-spline conversion's deviation does not add up along them, and
    sampled ``samples_per_turn`` times a turn of their winding, at least
    ``samples_per_segment`` times a segment of the file's curve (:func:`~models.cloth.plies.wind_plies`).
    """
    if not scale > 0:
        raise ValueError(f"the model's scale must be positive (got {scale})")
    centres, deviation = centre_lines(collection, scale, tol_fraction * yarn.radius)
    # the file's own curves, evaluated exactly, 8 samples a segment
    passes, closed, segments = [], [c.closed for c in collection.curves], []
    for c in collection.curves:
        P = scale * c.points
        segments.append(n_segments(P, c.closed, collection.kind))
        passes.append(evaluate(P, c.closed, collection.kind, np.arange(8 * segments[-1] + (0 if c.closed else 1)) / 8))
    bends = Bends.of(passes)
    bends.check(yarn.radius)
    plies, pitches = [], []
    for k, samples in enumerate(passes):
        if yarn.K == 1:  # a single ply is the yarn: its centre line as converted
            plies.append(centres[k][0])
        else:
            frames = transport_frames(samples, closed[k], stride=4)
            wound, pitch = wind_plies(frames, yarn.K, yarn.R, yarn.pitch, samples_per_turn,
                                      min_samples=samples_per_segment * segments[k])
            pitches.append(pitch)
            plies += [interpolate_bspline(q, closed[k]) for q in wound]
        if progress is not None:
            progress(k + 1)
    near = nearest_other([q[::4] for q in passes], closed, along_min=4 * yarn.radius)
    check_distinct([q[::4] for q in passes], near, yarn.radius)
    return PlyGeometry(plies, yarn.r_ply, deviation, float(near.min()), float(np.mean(near < 2 * yarn.radius)),
                       folded=bends.folded(yarn.radius), pitch_used=pitches)


def check_distinct(passes: list[np.ndarray], near: np.ndarray, radius: float) -> None:
    """Refuse coincident yarns (a curve listed twice, or one that runs back over itself):
    no yarn radius separates them. ``near``: each sample's nearest other pass
    (:func:`~models.cloth.plies.nearest_other`); coincident means within float64 rounding of
    the model's size, far below any yarn radius (1e-6 of it)."""
    i = int(np.argmin(near))
    if not near[i] < 1e-6 * radius:
        return
    owner = np.concatenate([np.full(len(p), k) for k, p in enumerate(passes)])
    pts = np.concatenate(passes)
    d = np.linalg.norm(pts - pts[i], axis=1)
    others = np.flatnonzero((d < 1e-6 * radius) & (np.abs(np.arange(len(pts)) - i) > 1))
    j = int(others[np.argmax(owner[others] != owner[i])]) if len(others) else i
    share = float(np.mean(near < 1e-6 * radius))
    what = (f"curves {owner[i]} and {owner[j]} coincide" if owner[j] != owner[i]
            else f"curve {owner[i]} runs back over itself")
    raise ValueError(f"cloth.model: {what} ({100 * share:.1f}% of the yarn length lies on another pass); no yarn "
                     "radius separates them: remove the duplicated or degenerate curves from the model")


@dataclass
class Bends:
    """How tightly the centre lines bend: the radius of the circle through every three
    consecutive samples (:func:`~models.cloth.plies.bend_radius`) and the length each stands for."""

    radius: np.ndarray
    step: np.ndarray

    @classmethod
    def of(cls, passes: list[np.ndarray]) -> "Bends":
        return cls(np.concatenate([bend_radius(p) for p in passes]),
                   np.concatenate([0.5 * np.linalg.norm(p[2:] - p[:-2], axis=1) for p in passes]))

    def folded(self, radius: float) -> float:
        """The share of the length that bends tighter than ``radius``: there a tube of that
        radius folds through itself."""
        return float(np.sum(self.step * (self.radius < radius)) / np.sum(self.step))

    def check(self, radius: float) -> None:
        """Refuse a yarn radius at which most of the centre lines fold the yarn through itself
        (their median bend is tighter than the radius): what would render is a blob, not a
        yarn. A few tight bends (a simulated knit's kinks) are measured and warned of instead
        (:attr:`PlyGeometry.folded`)."""
        median = float(np.median(self.radius))
        if radius > median:
            raise ValueError(f"cloth.yarn_radius_mm: a yarn radius of {radius:.3g} mm is larger than the centre lines' median bend "
                             f"radius ({median:.3g} mm), so the yarn would fold through itself along "
                             f"{100 * self.folded(radius):.0f}% of its length; give a yarn radius under "
                             f"{median:.3g} mm, or check cloth.units_mm (the model's size in millimetres)")


def write_curves(path, geometry: PlyGeometry) -> None:
    """Mitsuba's curve text format: ``x y z r`` per control point, a blank line between curves."""
    r = geometry.radius
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        write_mitsuba_curves(f, (np.column_stack([C, np.full(len(C), r)]) for C in geometry.curves))
