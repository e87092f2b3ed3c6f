"""The table's own noise in a rendered figure (docs/DESIGN.md, "The far-field closure test").

A figure read off a render of ``fiber_bundle`` (the mean radiance over a ply, its brightness
along the ply) differs from the same figure of explicit fibers by the model's error, the
explicit render's noise, and the table's noise: the bake's Monte Carlo error in the bins the
render reads. :func:`table_noise` measures the last by rendering tables redrawn within the
bake's standard errors (:meth:`models.bundle_table.BundleTable.redrawn`).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm

from models.bundle_table import BundleTable
from models.io import scratch

from . import scenes
from .images import render_timed

DRAWS = 8  # tables redrawn within the bake's errors: the noise's own relative error is about 1 / sqrt(2 x 8)


def table_noise(mi, cfg, table_props: dict, img, rows, draws: int = DRAWS, seed: int = 0, **scene) -> dict:
    """The table's own noise in the ply scene's figures: the bundle rendered ``img`` with the
    table, and again with ``draws`` tables redrawn within the bake's standard errors
    (:meth:`~models.bundle_table.BundleTable.redrawn`), at the same sampler seed as
    :func:`~pipeline.images.render_timed` gave ``img``. A draw differs from the table as the
    table differs from its expectation, so the draws' spread in mean radiance (relative) is
    the table's noise in it, and their brightness along the ply (``rows`` averaged per
    column) off from the table's, as a relative L1, is what the table's own profile is off
    by. The renders' sampling noise is in both too: an upper bound, close at these samples.
    ``scene``: :func:`~pipeline.scenes.ply_scene`'s keywords (default: the stage's ply, untwisted)."""
    table = BundleTable.load(table_props["table"])
    rng = np.random.default_rng(seed)
    profile = img[rows].sum(-1).mean(0)
    means, l1 = [], []
    # the draws are scratch: written outside the artifacts, thrown away whole
    with tempfile.TemporaryDirectory(prefix="bcsdf-redrawn-") as tmp, scratch(tmp):
        for k in tqdm(range(draws), desc="the table's noise", unit="draw"):
            path = Path(tmp) / f"redrawn_{k}.npz"
            table.redrawn(rng).save(path)
            drawn, _, _ = render_timed(mi, scenes.ply_scene(mi, cfg, {**table_props, "table": str(path)},
                                                            cfg.render.spp, 0, **({"twist_turns": 0.0} | scene)),
                                       warm=False, seed=1)
            p = drawn[rows].sum(-1).mean(0)
            means.append(p.mean())
            l1.append(np.abs(p - profile).mean() / profile.mean())
    return {"draws": draws, "mean_relative": float(np.std(means, ddof=1) / profile.mean()),
            "profile_l1": float(np.mean(l1))}
