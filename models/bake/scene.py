"""The bundle as Mitsuba geometry: parallel fibers as ``cylinder`` shapes along y, cast
against with horizontal rays (the cross-section is the whole geometry of a path); where
light enters the bounding width and where it leaves a fiber.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi  # its types resolve to the variant chosen at the entry point, at call time
import numpy as np
from scipy.spatial import cKDTree

from ..bundle import Bundle
from ..fiber import lobes
from ..jit import to_drjit


def across_width(n: int, radius: float, rng) -> np.ndarray:
    """Offsets of ``n`` rays across the width ``2 radius``, one in each of ``n`` equal strata, in order."""
    return (-1 + 2 * (np.arange(n) + rng.uniform(size=n)) / n) * radius


def shuffled_strata(n: int, rng) -> np.ndarray:
    """``n`` numbers in [0, 1), one in each of ``n`` equal strata, shuffled (against the offsets)."""
    return rng.permutation((np.arange(n) + rng.uniform(size=n)) / n)


def incident_azimuths(spec, phi_index: int, n: int, rng) -> np.ndarray:
    """The azimuth each of ``n`` paths arrives from: the spec's node ``phi_index``, or for a
    circle (whose table is the rotation average: a finite arrangement is not exactly rotation
    invariant) its own per path, stratified over the circle and shuffled."""
    phi = np.full(n, spec.phi_i[phi_index])
    if spec.relative_phi:
        phi = phi + 2 * np.pi * shuffled_strata(n, rng)
    return phi


class BundleScene:
    """The bundle as a Mitsuba scene of cylinders along y; casts 2D rays."""

    def __init__(self, bundle: Bundle):
        self.bundle = bundle
        half = 1e3 * bundle.bounding_radius  # long enough: rays stay at y = 0
        shapes = {f"fiber_{k}": {"type": "cylinder", "p0": [float(x), -half, float(z)],
                                 "p1": [float(x), half, float(z)], "radius": float(r)}
                  for k, ((x, z), r) in enumerate(zip(bundle.centers, bundle.radii))}
        self.scene = mi.load_dict({"type": "scene", **shapes})
        # Mitsuba numbers shapes in the order it stores them; map back by position
        order = []
        for shape in self.scene.shapes():
            bbox = shape.bbox()
            order.append(((bbox.min.x + bbox.max.x) / 2, (bbox.min.z + bbox.max.z) / 2))
        order = np.array(order, dtype=np.float64).reshape(-1, 2)
        _, self.shape_to_fiber = cKDTree(bundle.centers).query(order)

    def cast(self, origin: np.ndarray, phi: np.ndarray):
        """First hit of rays from ``origin[n, 2]`` (x, z) along azimuth ``phi``.

        Returns ``(hit, fiber)``: a mask and the fiber index (-1 where missed).
        """
        n = len(phi)
        if n == 0:
            return np.zeros(0, bool), np.zeros(0, np.int64)
        Float, zero = mi.Float, dr.zeros(mi.Float, n)
        o = mi.Point3f(to_drjit(Float, origin[:, 0]), zero, to_drjit(Float, origin[:, 1]))
        d = mi.Vector3f(to_drjit(Float, np.cos(phi)), zero, to_drjit(Float, np.sin(phi)))
        pi = self.scene.ray_intersect_preliminary(mi.Ray3f(o, d), coherent=False)
        t = pi.t.numpy()
        index = pi.shape_index.numpy().astype(np.int64)
        dr.sync_thread()
        hit = np.isfinite(t) & (index < len(self.shape_to_fiber))
        fiber = np.where(hit, self.shape_to_fiber[np.where(hit, index, 0)], -1)
        return hit, fiber

    def exit_point(self, fiber: np.ndarray, phi_out: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Where light leaving ``fiber`` along ``phi_out`` with offset ``h`` starts (on the surface)."""
        c = self.bundle.centers[fiber]
        r = self.bundle.radii[fiber]
        return np.stack(lobes.leave_uniform(c[:, 0], c[:, 1], r, h, np.cos(phi_out), np.sin(phi_out), np), -1)

    def entry(self, phi_i, t: np.ndarray):
        """Rays of light arriving from azimuths ``phi_i`` (w_i; one, or one per ray), offsets
        ``t`` across 2 R_b."""
        Rb = self.bundle.bounding_radius
        phi_travel = np.broadcast_to(np.asarray(phi_i, np.float64) + np.pi, t.shape)
        d = np.stack([np.cos(phi_travel), np.sin(phi_travel)], -1)
        side = np.stack([-d[:, 1], d[:, 0]], -1)
        origin = -2 * Rb * d + t[:, None] * side
        return origin, phi_travel.copy()
