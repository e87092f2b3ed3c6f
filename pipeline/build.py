"""From a config to the model objects a stage works with: the bundle, the bake's spec and
its seeds, and the version of the code that made an artifact.

One place for each rule, so that the bake stage, the cluster's workers, the sweep, the
render stage and the benchmarks build the same objects from the same config.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models import bundle as bundles
from models.baker import BakeSpec
from models.fiber.base import FiberTable


def build_bundle(cfg) -> bundles.Bundle:
    b, r = cfg.bundle, cfg.fiber.radius_um
    if b.arrangement == "zhao2016":
        return bundles.zhao2016(b.yarn, r, seed=b.seed, name=f"{cfg.name} ({b.yarn})")
    if b.arrangement == "file":
        return bundles.from_file(b.file, b.semi_axes(), name=cfg.name)
    return bundles.poisson(b.semi_axes(), r, gap=b.gap_um, packing=b.packing, seed=b.seed, name=cfg.name)


def exit_model(name: str, fiber: FiberTable, estimator: str = "fast") -> str:
    """The exit model a bake uses: ``auto`` is the one that agrees with exact geometry where
    the fiber knows its paths (``lobe`` for ray fibers with the fast estimator), else
    ``uniform`` (measured on the ray model's smooth limit: docs/BENCHMARKS.md, "Exit models")."""
    if name == "auto":
        return "lobe" if fiber.meta.get("model") == "ray" and estimator == "fast" else "uniform"
    return name  # an impossible choice is refused by the config (and by BakeSpec and the ray sampler)


def make_spec(cfg, bundle, fiber: FiberTable) -> tuple[BakeSpec, dict]:
    """Incident directions and bins, after the symmetry reductions the scene allows."""
    c = cfg.bake
    mirror_theta = bool(fiber.meta.get("mirror_symmetric", True))
    step = np.deg2rad(c.theta_i_step_deg)
    # clipped: the last node of the arange can exceed pi/2 by a rounding error
    theta_i = np.clip(np.arange(0 if mirror_theta else -np.pi / 2, np.pi / 2 + 1e-9, step), -np.pi / 2, np.pi / 2)
    if bundle.is_circle:
        phi_i, phi_reduction = np.zeros(1), "rotation"
    else:
        phi_i, phi_reduction = np.deg2rad(np.arange(0, 90 + 1e-9, c.phi_i_step_deg)), "mirror_xz"
    spec = BakeSpec(theta_i, phi_i, c.n_theta_o, c.n_phi_o, relative_phi=bundle.is_circle,
                    estimator=c.estimator, max_bounces=c.max_bounces, rr_start=c.rr_start,
                    exit=exit_model(c.exit, fiber, c.estimator))
    reductions = {"theta_i": "mirror" if mirror_theta else None, "phi_i": phi_reduction,
                  "phi_o": "relative" if bundle.is_circle else "absolute"}
    return spec, reductions


def batch_seed(cfg, a: int, k: int) -> np.random.SeedSequence:
    """The seed of batch ``k`` of incident azimuth ``a``: fixed, wherever it is traced."""
    return np.random.SeedSequence([cfg.bake.seed, a, k])


def code_version() -> str:
    import subprocess
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, timeout=5).stdout.strip() or "unknown"
    except Exception:
        return "unknown"
