"""From a config to the model objects a stage works with: the bundle, the bake's spec and
its seeds, and the version of the code that made an artifact.

One place for each rule, so that the bake stage, the cluster's workers, the sweep, the
render stage and the benchmarks build the same objects from the same config.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np

from models import bundle as bundles
from models.bake import Baker, BakeSpec, CameraBaker
from models.bake import twisted
from models.bake.twisted import TwistedBaker
from models.bake.twisted_camera import TwistedCameraBaker
from models.fiber.base import FiberTable

from .config import theta_nodes
from .machine import check_memory


# A ply spaced out to clear its turning fibers keeps at least this share of the packing asked
# for; below it, spacing makes another ply rather than clearing this one.
KEPT_PACKING = 0.5


def build_bundle(cfg, gap: float | None = None) -> bundles.Bundle:
    """The cross-section (of a twisted ply: at height 0, spaced so that its leaning fibers
    clear). ``gap``: a Poisson arrangement's gap (um) instead of :func:`_poisson_gap`'s."""
    b, r = cfg.bundle, cfg.fiber.radius_um
    if b.arrangement == "zhao2016":
        return bundles.zhao2016(b.yarn, r, seed=b.seed, name=f"{cfg.name} ({b.yarn})")
    if b.arrangement == "file":
        bundle = bundles.from_file(b.file, b.semi_axes(), name=cfg.name)
        check_radii(bundle, r, b.file)
        return bundle
    gap = _poisson_gap(cfg) if gap is None else gap
    return bundles.poisson(b.semi_axes(), r, gap=gap, packing=b.packing, seed=b.seed, name=cfg.name)


# How far a listed fiber's radius may differ from the fiber table's: the table's absorption
# follows the chord (proportional to the radius), so 1% of radius moves it by 1% of itself,
# below the bake's own Monte Carlo noise; a fiber further off would scatter as another fiber.
RADIUS_TOLERANCE = 0.01


def check_radii(bundle: bundles.Bundle, r: float, source) -> None:
    """Refuse listed fibers whose radii differ from the one the fiber table was made for."""
    off = np.abs(bundle.radii / r - 1.0) > RADIUS_TOLERANCE
    if np.any(off):
        raise ValueError(f"bundle.file {source}: {off.sum()} of {len(off)} fibers have radii other than fiber.radius_um "
                         f"= {r:g} um (from {bundle.radii.min():g} to {bundle.radii.max():g} um); the bake scatters "
                         "every fiber with the one fiber table made at that radius: list fibers of one radius and "
                         "set fiber.radius_um to it")


def _poisson_gap(cfg) -> float:
    """The Poisson arrangement's gap: ``bundle.gap_um``, widened for a twist so that fibers
    leaning by ``lean`` clear each other (centres ``2 r / cos(lean)`` apart in the
    cross-section, for the leanest, outermost fibers)."""
    b, r = cfg.bundle, cfg.fiber.radius_um
    if b.twist is None:
        return b.gap_um
    rho = b.bounding_radius_um() - r
    lean = np.arctan(2 * np.pi * rho / abs(b.twist.pitch(b.bounding_radius_um())))
    return max(b.gap_um, 2 * r * (1 / np.cos(lean) - 1) * 1.001)


def build_ply(cfg) -> bundles.Bundle | bundles.TwistedBundle:
    """What the bake traces: the cross-section, or the twisted ply of ``bundle.twist``.

    Migrating fibers (``bundle.twist.migration``) and the fibers of an elliptical ply pass
    each other closer than the cross-section shows; a Poisson cross-section is spaced out
    until they clear (its gap grown by each try's overlap), a listed one is refused with the
    amount. Spacing thins the ply: where it would keep under :data:`KEPT_PACKING` of the
    packing asked for (``bundle.packing``, or the Poisson arrangement's at ``bundle.gap_um``),
    the ply built would be another one, and it is refused (fibers of radius ``r`` migrating
    to ``r_min`` of their distance from the axis clear each other only in radial runs that
    shrink by ``r_min`` per fiber, so the packing that clears falls steeply with ``r_min``)."""
    twist = cfg.bundle.twist
    try:
        bundle = build_bundle(cfg)
    except ValueError as e:
        if twist is None or cfg.bundle.arrangement != "poisson" or _poisson_gap(cfg) <= cfg.bundle.gap_um:
            raise
        r = cfg.fiber.radius_um
        raise ValueError(f"bundle.twist: fibers leaning with the twist clear each other only {2 * r:g} um / cos(lean) "
                         f"apart, so the Poisson cross-section's gaps are widened from bundle.gap_um = {cfg.bundle.gap_um:g} to "
                         f"{_poisson_gap(cfg):.3g} um, and then {str(e).partition(': ')[2]}; lengthen the pitch (less lean) or "
                         "enlarge the bundle") from None
    if twist is None:
        return bundle
    pitch, migration = twist.pitch(bundle.bounding_radius), twist.migration_model(cfg.bundle.seed)
    if (migration is None and bundle.is_circle) or cfg.bundle.arrangement != "poisson":
        return bundles.TwistedBundle(bundle, pitch, migration)
    asked, gap = bundle, _poisson_gap(cfg)
    why = (f"migration (r_min {migration.r_min:g}, s {migration.s:g})" if migration is not None
           else "the ellipse's fibers passing each other")
    for _ in range(40):
        ply = bundles.TwistedBundle(bundle, pitch, migration, checked=False)
        overlap = -ply.closest_approach()[0]
        if overlap <= 0:  # checked: its closest approach is a gap
            kept = ply.bundle.packing_fraction / asked.packing_fraction
            if kept < KEPT_PACKING:
                raise ValueError(
                    f"bundle.twist: for {why} to clear, the Poisson cross-section had to be spaced out from "
                    f"{len(asked.radii)} fibers (packing {asked.packing_fraction:.3f}) to {len(ply.bundle.radii)} "
                    f"({ply.bundle.packing_fraction:.3f}), under {KEPT_PACKING:.0%} of the packing asked for: "
                    + ("migrate less (r_min nearer 1), or " if migration is not None else "")
                    + f"ask for the sparser ply itself (bundle.packing: {ply.bundle.packing_fraction:.2f})")
            return ply
        gap += overlap + 0.01 * cfg.fiber.radius_um
        try:
            bundle = build_bundle(cfg, gap)
        except ValueError as e:  # the packing asked for does not fit at the wider gap
            raise ValueError(f"bundle.twist: for {why} to clear, the Poisson cross-section needs gaps of "
                             f"{gap:.3g} um, at which it cannot hold the packing asked for ({e}); "
                             + ("migrate less (r_min nearer 1) or " if migration is not None else "")
                             + "lower bundle.packing") from None
    raise ValueError(f"bundle.twist: no Poisson cross-section with gaps from {_poisson_gap(cfg):.3g} to {gap:.3g} "
                     f"um clears {why}; migrate less (r_min nearer 1) or lengthen the pitch")


def describe(ply) -> str:
    """What was built, in one line: the fibers, their packing, the twist."""
    b = cross_section(ply)
    text = f"{len(b.radii)} fibers, packing {b.packing_fraction:.3f}"
    if isinstance(ply, bundles.TwistedBundle):
        text += f", pitch {ply.pitch:g} um (outer fibers lean {np.degrees(ply.max_lean):.1f} deg)"
        if ply.migration is not None:
            text += f", migrating to r_min {ply.migration.r_min:g}"
    return text


def tracer(ply, fiber: FiberTable, spec: BakeSpec):
    """The bake's tracer for this ply: the 2D one for parallel fibers, the 3D one for a twist
    (each from the camera with ``bake.estimator: camera``)."""
    if isinstance(ply, bundles.TwistedBundle):
        check_scene_fits(ply)
        return (TwistedCameraBaker if spec.estimator == "camera" else TwistedBaker)(ply, fiber, spec)
    return (CameraBaker if spec.estimator == "camera" else Baker)(ply, fiber, spec)


def check_scene_fits(ply) -> None:
    """Refuse, before building it, a twisted ply whose Mitsuba scene would not fit in memory
    (a short pitch leans the fibers towards the ply's cross-section, and the period's
    margins then hold ever more cylinders)."""
    twisted.check_geometry(ply)
    cylinders = twisted.segments_per_fiber(ply) * len(ply.bundle.radii)
    check_memory(cylinders * twisted.BYTES_PER_CYLINDER,
                 f"bundle.twist: a pitch of {ply.pitch:g} um leans the outer fibers {np.degrees(ply.max_lean):.1f} deg; "
                 f"one period would take {cylinders:,} cylinders", "lengthen the pitch")


def cross_section(ply) -> bundles.Bundle:
    """The cross-section of a ply (a twisted one's at height 0)."""
    return ply.bundle if isinstance(ply, bundles.TwistedBundle) else ply


def exit_model(name: str, fiber: FiberTable, estimator: str = "fast") -> str:
    """The exit model a bake uses: ``auto`` is the one that agrees with exact geometry where
    the fiber knows its paths (``lobe`` for ray fibers with the fast estimator, parallel or
    twisted), else ``uniform`` (measured on the ray model's smooth limit: docs/BENCHMARKS.md,
    "Exit models"); a ray fiber of camera transport (what Mitsuba renders of its ``hair``)
    leaves as from Mitsuba's curves (``curve``), whichever side it is traced from."""
    if name == "auto":
        if fiber.meta.get("model") != "ray" or estimator == "thesis":
            return "uniform"
        return "curve" if fiber.meta.get("transport") == "camera" else "lobe"
    return name  # an impossible choice is refused by the config (and by BakeSpec and the ray sampler)


def make_spec(cfg, bundle, fiber: FiberTable) -> tuple[BakeSpec, dict]:
    """Incident directions and bins, after the symmetry reductions the scene allows.

    A twisted ply (``bundle`` a :class:`~models.bundle.TwistedBundle`) keeps the rotation
    reduction of a circle (a turn of the ply is a shift along its axis, and rays enter over a
    whole period), but not the theta mirror (the mirror of a twisted ply is twisted the other
    way); a twisted ellipse keeps its half turns (``half_turns``: models/bundle_table.py);
    its theta_i nodes stop short of +-90 deg, where light runs along the axis and crosses no
    width (the lookup holds the last node's value beyond it), as those of a ray fiber of camera
    transport do, whose adjoint grows without bound towards the pole.
    """
    c = cfg.bake
    twisted = isinstance(bundle, bundles.TwistedBundle)
    bundle = cross_section(bundle)
    mirror_theta = bool(fiber.meta.get("mirror_symmetric", True)) and not twisted
    # a twisted ply's light along the axis crosses no width; a camera transport's table (the
    # adjoint, f cos(theta_o) / cos(theta_i)) has no finite value there: neither keeps the poles
    camera = fiber.meta.get("transport") == "camera"
    theta_i = theta_nodes(c.theta_i_nodes_deg(), negative=not mirror_theta, poles=not (twisted or camera))
    # an ellipse: its x and z mirrors; twisted, the half turns about y (exact: a shift by half
    # a turn) and about x and z (each a mirror of the cross-section with theta flipped)
    phi_i = c.phi_i(bundle.is_circle)
    phi_reduction = "rotation" if bundle.is_circle else "half_turns" if twisted else "mirror_xz"
    spec = BakeSpec(theta_i, phi_i, c.n_theta_o, c.n_phi_o, relative_phi=bundle.is_circle,
                    estimator=c.estimator, max_bounces=c.max_bounces, rr_start=c.rr_start,
                    exit=exit_model(c.exit, fiber, c.estimator), theta_o_edges=c.theta_o_edges(), orders=c.orders,
                    offsets=c.offsets)
    reductions = {"theta_i": "mirror" if mirror_theta else None, "phi_i": phi_reduction,
                  "phi_o": "relative" if bundle.is_circle else "absolute"}
    return spec, reductions


def batch_seed(cfg, a: int, k: int) -> np.random.SeedSequence:
    """The seed of batch ``k`` of incident azimuth ``a``: fixed, wherever it is traced."""
    return np.random.SeedSequence([cfg.bake.seed, a, k])


def code_version() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, timeout=5).stdout.strip() or "unknown"
    except Exception:
        return "unknown"
