"""From tallies to tables: a bake's running sums as a :class:`~models.bundle_table.BundleTable`.

``tally_to_table`` divides the sums by paths and bin solid angles (the table holds
``S`` in 1/sr) and keeps their standard errors; ``bake_unreduced`` is a whole small bake
in one call, without checkpoints or symmetry reductions, for tests and benchmarks.
"""

from __future__ import annotations

import numpy as np

from ..bundle_table import BundleTable
from ..fiber.base import FiberTable
from .baker import Baker
from .camera import CameraBaker
from .tally import BakeSpec, Tally


def bake_unreduced(bundle, fiber: FiberTable, spec: BakeSpec, paths: int, seed: int = 1) -> BundleTable:
    """``paths`` per incident azimuth of ``spec`` in one go (no checkpoints, no symmetry
    reductions): the small bakes of tests and benchmarks."""
    baker = (CameraBaker if spec.estimator == "camera" else Baker)(bundle, fiber, spec)
    tally = None
    for a in range(len(spec.phi_i)):
        t = baker.trace(a, paths, np.random.SeedSequence([seed, a]))
        tally = t if tally is None else (tally.add(t) or tally)
    return tally_to_table(tally, spec, fiber, {"theta_i": None, "phi_i": None,
                                               "phi_o": "relative" if spec.relative_phi else "absolute"})


def tally_to_table(tally: Tally, spec: BakeSpec, fiber: FiberTable, reductions: dict) -> BundleTable:
    """The table of a bake's sums: bin means over paths per solid angle (1/sr), their
    standard errors, and the energy balance's parts as fractions of the paths.
    ``reductions`` records the symmetries the bake used (``BundleTable.meta``)."""
    # paths per bin: every path of an azimuth, or the camera estimator's own per bin
    n = tally.paths[:, None, None, None, None] if tally.bin_paths is None else \
        np.maximum(tally.bin_paths[..., None], 1)
    omega = spec.bin_solid_angle()[None, None, :, :, None]
    mean = tally.sum / n
    var = np.maximum(tally.sum_sq / n - mean**2, 0.0) / n
    p = tally.passthrough / tally.paths
    # per theta_i where it depends on it (twisted plies: each path one theta_i); a parallel
    # bake's is the same for every theta_i, and its table keeps the one per phi_i
    p_theta = tally.passthrough_theta / np.maximum(tally.paths_theta, 1)
    per_theta = not np.array_equal(p_theta, np.broadcast_to(p[:, None], p_theta.shape))
    orders = {}
    if tally.orders is not None:
        o_mean = tally.orders / n[None]
        o_var = np.maximum(tally.orders_sq / n[None] - o_mean**2, 0.0) / n[None]
        # the tail's mean excess order m = sum (k - K) E_k / sum E_k, and the ratio rho of the
        # geometric series with that mean, m = rho / (1 - rho) (models.bundle_table.tail_factor)
        tail_energy = tally.orders[-1].sum(axis=(2, 3))
        m = np.divide(tally.tail_excess, tail_energy, out=np.zeros_like(tail_energy), where=tail_energy > 0)
        orders = {"orders": (o_mean / omega[None]).astype(np.float32),
                  "orders_stderr": (np.sqrt(o_var) / omega[None]).astype(np.float32),
                  "tail_ratio": m / (1 + m)}
    if tally.near is not None:
        # S_h: each cell's light over the paths, per solid angle and per share of the width
        # (2 / N of it), so that the mean over the cells is S
        N = len(tally.near)
        h_mean = tally.near / n[None]
        h_var = np.maximum(tally.near_sq / n[None] - h_mean**2, 0.0) / n[None]
        orders |= {"near": (h_mean / omega[None] * N).astype(np.float32),
                   "near_stderr": (np.sqrt(h_var) / omega[None] * N).astype(np.float32),
                   "near_passthrough": tally.passthrough_h / np.maximum(tally.paths_h, 1)}
    return BundleTable(
        values=(mean / omega).astype(np.float32), stderr=(np.sqrt(var) / omega).astype(np.float32),
        passthrough=p, passthrough_stderr=np.sqrt(p * (1 - p) / tally.paths),
        passthrough_theta=p_theta if per_theta else None,
        absorbed=tally.absorbed / tally.paths[:, None, None], lost=tally.lost / tally.paths[:, None, None],
        single=tally.single / tally.paths[:, None, None],
        phi_i=spec.phi_i, theta_i=spec.theta_i, phi_o_edges=spec.phi_o_edges,
        theta_o_edges=spec.theta_o_edges, wavelength=fiber.wavelength.copy(),
        meta={"reductions": reductions, "units": {"angles": "rad", "wavelength": "nm", "values": "1/sr"},
              **({"transport": "camera"} if fiber.meta.get("transport") == "camera" else {})},
        **orders)
