"""Render benchmark: the table against every trained MLP size, jitted and through
onnxruntime, at equal samples, in one run (side by side: these machines are noisy).

    python -m pipeline.bench.render [CONFIG] [--artifacts DIR] [--spp N]

Needs ``bcsdf run CONFIG`` (bake and export) first. Prints, per scene and method, the
render time of a warm second render, its ratio to the table's, FLIP and PSNR against
the table's image, and the bytes the backend holds; writes the same as JSON beside
the render stage's output.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import mitsuba as mi

import mitsuba_ext
from models.io import write_text
from pipeline.bench import results

from .. import bsdfs, images, scenes
from ..artifacts import stage_dir
from ..loading import load_config
from ..graph import require


def measure(cfg, out_root="artifacts", spp=None) -> dict:
    r = cfg.render
    mi.set_variant(r.variant)
    mitsuba_ext.register()
    spp = spp or r.spp
    rows = []
    table_props = bsdfs.backend_props(cfg, out_root, "table")
    for scene in r.scenes:
        ref, t_ref, _ = images.render_timed(mi, scenes.named_scene(mi, cfg, scene, table_props, spp, Path("/tmp")))
        exposure = images.exposure_of(ref)
        rows.append({"scene": scene, "method": "table", "backend": "table", "seconds": t_ref, "time_ratio": 1.0,
                     "flip": 0.0, "psnr": float("inf"),
                     "bytes": int(Path(table_props["table"]).stat().st_size)})
        for size in cfg.train.models:
            sized = cfg.model_copy(update={"render": r.model_copy(update={"model": size})})
            for backend in ("mlp", "onnx"):
                props = bsdfs.backend_props(sized, out_root, backend)
                img, t, _ = images.render_timed(mi, scenes.named_scene(mi, sized, scene, props, spp, Path("/tmp")),
                                                backend)
                flip, psnr, _ = images.flip_and_psnr(ref, img, exposure)
                rows.append({"scene": scene, "method": size, "backend": backend, "seconds": t,
                             "time_ratio": t / t_ref, "flip": flip, "psnr": psnr,
                             "bytes": int(Path(props["model"]).stat().st_size)})
    return {"variant": r.variant, "spp": spp, "size": [r.width, r.height], "rows": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", nargs="?", default="configs/default.yaml")
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--spp", type=int, default=None)
    p.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                    help="change a config key, as `bcsdf run --set` (make run-sizes: the three model sizes)")
    args = p.parse_args(argv)
    cfg = load_config(args.config, args.overrides)
    require(cfg, ("bake", "train", "export"), args.artifacts,
            " ".join([".venv/bin/bcsdf run", str(args.config), *(f"--set '{o}'" for o in args.overrides)]))
    result = measure(cfg, args.artifacts, args.spp)
    print(f"{result['variant']}, {result['size'][0]}x{result['size'][1]}, {result['spp']} spp (warm kernels)")
    print(f"{'scene':6} {'method':8} {'backend':8} {'seconds':>8} {'x table':>8} {'FLIP':>7} {'PSNR':>6} {'bytes':>10}")
    for row in result["rows"]:
        print(f"{row['scene']:6} {row['method']:8} {row['backend']:8} {row['seconds']:8.2f} {row['time_ratio']:8.2f} "
              f"{row['flip']:7.4f} {row['psnr']:6.1f} {row['bytes']:10d}")
    out = stage_dir(cfg, "render", args.artifacts) / "bench_render.json"
    write_text(out, json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    with results.recorded("render", smoke="--quick" in sys.argv):
        raise SystemExit(main())
