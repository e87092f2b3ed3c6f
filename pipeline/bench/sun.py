"""A ply under the sun alone, seen from the render stage's camera and from afar
(``make bench-sun``): where its bundle and its explicit fibers part, and why.

The config's ply (default ``configs/twisted_cotton1.yaml``) baked with ``--paths`` paths and
its orders of scattering (``bake.orders: 3``), rendered in the render stage's ply scene with
the sky taken away (``scenes.sun_alone``), in a mono variant at 550 nm: every fiber explicit
(16 turns of the arrangement, the fiber plugin of the bake's exit) against ``fiber_bundle``
with the table. Four cameras (``scenes.ply_scene``'s ``view``): the render stage's own (60
deg wide, 14 ply radii from its axis: its view sweeps +-30 deg along the ply, and its rays
fan out by +-4 deg across the ply's width) and one ten times further away (6 deg wide: the
far field the table describes) turned to ``theta_o`` -20, 0 and +20 deg. Each twice: all
the light, and the singly scattered light alone (the explicit fibers at ``max_depth`` 2, the
bundle with the table's first order). Per row: bundle / explicit, the explicit mean's
standard error (the spread of its 16 views) and the table's own noise in the ratio
(``pipeline.noise.table_noise``: tables redrawn within the bake's standard errors); for the
distant cameras also what the stage's camera sees at the same view angle along the ply over
what they see, for the explicit fibers and for the bundle: a far-field model reads the same
there (up to the +-4 deg its rays fan across the width), the explicit fibers need not.
Records ``benchmarks/sun.json``::

    .venv/bin/python -m pipeline.bench.sun              # about 20 minutes on 2 cores
    .venv/bin/python -m pipeline.bench.sun --quick      # 2M paths, two views: a smoke run
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import mitsuba as mi
import numpy as np
from tqdm import tqdm

import mitsuba_ext
from models.bundle_table import BundleTable

from .. import closure, scenes
from ..bsdfs import backend_props
from ..build import build_ply
from ..images import render_timed
from ..loading import load_config
from ..noise import table_noise
from . import baked, results

LAM = 550.0
STAGE = "the render stage's camera"
VIEWS = {STAGE: (60.0, 0.0), "far, theta_o -20 deg": (6.0, -20.0), "far, theta_o 0": (6.0, 0.0),
         "far, theta_o +20 deg": (6.0, 20.0)}
LIGHT = {"all light": None, "singly scattered": 2}   # the explicit fibers' max_depth


def variant(config: str, paths: int):
    """The config baked with ``paths`` and three orders, under a name of its own (reused
    where its artifacts match)."""
    return baked(load_config(config, [f"name={Path(config).stem}_sun_{paths}", f"bake.paths_per_phi_i={paths}",
                                      "bake.orders=3"]))


def explicit(cfg, ply, fiber_table, plugin: str, view, max_depth) -> tuple[np.ndarray, float]:
    """Every fiber explicit: the mean image of 16 views, and the standard error of its mean
    radiance over the ply's rows (relative)."""
    placements = closure.view_placements(ply, 16, scenes.UM, True)
    rows = scenes.ply_rows(cfg, cfg.render.height)
    images = []
    with tempfile.TemporaryDirectory(prefix="bcsdf-sun-") as tmp:
        scene = scenes.explicit_scene(mi, cfg, ply, fiber_table, max(1, cfg.render.explicit_spp // 16), plugin=plugin,
                                      curve_file=Path(tmp) / "helices.txt", lights=scenes.sun_alone(mi), view=view,
                                      reach=max(abs(s) for _, s in placements))
        for shape in scene.values():
            if isinstance(shape, dict) and "bsdf" in shape:
                shape["bsdf"]["wavelength"] = LAM
        if max_depth:
            scene["integrator"]["max_depth"] = max_depth
        loaded = mi.load_dict(scene)
        fibers = closure.TurnedFibers(mi, loaded, [1.0, 0.0, 0.0])
        for k, (turn, shift) in enumerate(placements):
            fibers.place(turn, shift)
            images.append(render_timed(mi, loaded, warm=False, seed=2 * k)[0].sum(-1))
    means = np.array([img[rows].mean() for img in images])
    return np.mean(images, 0), float(means.std(ddof=1) / np.sqrt(len(means)) / means.mean())


def near_over_far(near, far, rows, theta_o: float) -> float:
    """The stage camera's image ``near`` over the distant camera's ``far`` at the same view
    angle along the ply: ``near``'s columns within 2.5 deg of ``theta_o`` (its perspective
    sweeps +-30 deg along the ply) against the middle half of ``far``'s (+-1.5 deg)."""
    n = near.shape[1]
    x = (np.arange(n) + 0.5) / n * 2 - 1                                    # film x, -1 .. 1
    along = -np.degrees(np.arctan(x * np.tan(np.radians(VIEWS[STAGE][0] / 2))))  # the view's theta_o
    return float(near[rows][:, np.abs(along - theta_o) < 2.5].mean() / far[rows][:, n // 4:3 * n // 4].mean())


def measure(cfg, views: dict) -> list:
    ply = build_ply(cfg)
    fiber_table = Path("artifacts") / cfg.name / "fiber" / "fiber_table.npz"
    props = backend_props(cfg, "artifacts", "table") | {"wavelength": LAM}
    table = BundleTable.load(props["table"])
    plugin = closure.explicit_fiber(fiber_table, table.meta.get("exit", "uniform"), LAM)["type"]
    rows_of = scenes.ply_rows(cfg, cfg.render.height)
    out = []
    with tempfile.TemporaryDirectory(prefix="bcsdf-sun-") as tmp:
        first = Path(tmp) / "order_1.npz"
        table.order(1).save(first)
        for (light, depth), (name, view) in tqdm([(lv, v) for lv in LIGHT.items() for v in views.items()],
                                                 desc="sun alone", unit="view"):
            bundle_props = {**props, "table": str(first)} if depth else props
            scene = dict(twist_turns=0.0, lights=scenes.sun_alone(mi), view=view)
            img = render_timed(mi, scenes.ply_scene(mi, cfg, bundle_props, cfg.render.spp, 0, **scene),
                               warm=False, seed=1)[0]
            noise = table_noise(mi, cfg, bundle_props, img, rows_of, **scene)
            ex, ex_se = explicit(cfg, ply, fiber_table, plugin, view, depth)
            bundle = img.sum(-1)
            ratio = float(bundle[rows_of].mean() / ex[rows_of].mean())
            row = {"light": light, "view": name, "fov_deg": view[0], "theta_o_deg": view[1],
                   "bundle_vs_explicit": ratio, "explicit_stderr": ratio * ex_se,
                   "table_noise": ratio * noise["mean_relative"]}
            if name == STAGE:
                near = (bundle, ex)
            elif STAGE in views:  # the same view angles from the stage's camera, over from afar
                row["explicit_near_over_far"] = near_over_far(near[1], ex, rows_of, view[1])
                row["bundle_near_over_far"] = near_over_far(near[0], bundle, rows_of, view[1])
            out.append(row)
    return out


def markdown(cfg, rows: list) -> str:
    lines = [f"`{cfg.name}` ({len(build_ply(cfg).bundle.radii)} fibers, {cfg.bake.paths_per_phi_i:.3g} paths), "
             f"the render stage's sun alone, {LAM:.0f} nm:", "",
             "| light | camera | bundle / explicit | explicit se | the table's noise | explicit: the stage's camera "
             "/ far | bundle: the stage's camera / far |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['light']} | {r['view']} | {r['bundle_vs_explicit']:.3f} | {r['explicit_stderr']:.3f} "
                     f"| {r['table_noise']:.3f} | " + " | ".join(f"{r[k]:.3f}" if k in r else ""
                                                               for k in ("explicit_near_over_far", "bundle_near_over_far"))
                     + " |")
    lines += ["", "The last two columns: the stage's camera's image at the far camera's view angle along the ply "
              "(its columns within 2.5 deg of it) over the far camera's, for the same fibers or the same table."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.sun", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/twisted_cotton1.yaml")
    ap.add_argument("--paths", type=int, default=16_000_000, help="bake paths (a twisted ply's: each one theta_i)")
    ap.add_argument("--quick", action="store_true", help="2M paths, the stage's camera and one far one")
    a = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    cfg = variant(a.config, 2_000_000 if a.quick else a.paths)
    views = dict(list(VIEWS.items())[:3:2]) if a.quick else VIEWS
    with mitsuba_ext.variant("llvm_ad_mono"):
        rows = measure(cfg, views)
    table = markdown(cfg, rows)
    print(table)
    if not a.quick:  # a smoke run is not a measurement
        results.save("sun", table, {"config": a.config, "paths": a.paths, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
