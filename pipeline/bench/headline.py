"""The README's headline figures, from one config's artifacts (after ``make run``)::

    .venv/bin/python -m pipeline.bench.headline [CONFIG] [--artifacts DIR]

Reads what the stages wrote (summaries, metrics, stamps and file sizes; nothing is run
again) and records ``benchmarks/headline.json``: the bake (passthrough, albedo, time),
sizes (the stored table, the expanded float32 table, the model's float32 parameters, its
files), the model against the table (held-out error, albedo errors, render FLIP and time)
and each stage's seconds. Each size ratio says what it divides by what, so that no two
figures of one quantity disagree.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..artifacts import config_dir, model_size
from ..loading import load_config
from ..summaries import RenderSummary, TrainSummary
from . import results

STAGES = ("fiber", "bake", "train", "export", "render", "stability", "report")


def read(path: Path) -> dict:
    if not path.exists():
        raise SystemExit(f"{path} does not exist: run `bcsdf run` on this config first (make run)")
    return json.loads(path.read_text())


def figures(cfg, artifacts) -> tuple[list[dict], dict]:
    root = config_dir(cfg, artifacts)
    size = model_size(cfg)
    bake = read(root / "metrics" / "bake.json")
    train = TrainSummary.read(root / "train" / size / "summary.json")
    export = read(root / "metrics" / "export.json")
    render = RenderSummary.read(root / "render" / "summary.json")
    table_file = (root / "bake" / "bundle_table.npz").stat().st_size
    weights_file = (root / "export" / size / "weights.npz").stat().st_size
    onnx_file = (root / "export" / size / "model.onnx").stat().st_size
    expanded = next(v["bytes"] for k, v in export.items() if k.startswith("table"))
    mlp = next(v for k, v in export.items() if k.startswith(f"mlp {size}"))
    params = train.parameters
    ply = render.scenes["ply"]
    seconds = {s: read(root / ".stamps" / f"{s}.json").get("seconds") for s in STAGES
               if (root / ".stamps" / f"{s}.json").exists()}
    rows = [
        ("bake", "passthrough (mean over incidences)", f"{bake['passthrough']:.3f}"),
        ("bake", "albedo (scattered fraction)", f"{bake['albedo']:.3f}"),
        ("bake", "energy balance: the largest deviation of the total from 1", f"{bake['max_abs_energy_error']:.2e}"),
        ("sizes", "baked table, stored (bundle_table.npz, half precision, symmetries folded)", _bytes(table_file)),
        ("sizes", "baked table, expanded float32 (what a lookup reads)", _bytes(expanded)),
        ("sizes", f"model {size}: {params} float32 parameters", _bytes(4 * params)),
        ("sizes", f"model {size}: weights.npz / model.onnx", f"{_bytes(weights_file)} / {_bytes(onnx_file)}"),
        ("sizes", "expanded table / model parameters", f"{expanded / (4 * params):.0f}x"),
        ("sizes", "stored table / weights.npz", f"{table_file / weights_file:.0f}x"),
        ("model", "held-out relative L1 of the core (bin averages; models.errors)", f"{train.relative_l1:.1%}"),
        ("model", "the table's own noise on those bins", f"{train.table_noise_l1:.1%}"),
        ("model", "held-out error / the table's own noise", f"{train.noise_ratio:.2f}"),
        ("model", "worst albedo error per incidence and wavelength after the energy gain (9 x 9 points a bin, not the gain's 8 x 8)",
         f"{train.worst_albedo_error_after:.2%}" if train.worst_albedo_error_after is not None else "-"),
        ("model", "worst albedo error of the exported model, each bin averaged on its own",
         f"{mlp['albedo_error']:.2%}"),
        ("render", f"ply, FLIP of the jitted MLP against the table ({render.spp} spp)",
         f"{ply['mlp']['flip']:.3f}"),
        ("render", "ply, MLP render time / table render time (warm)", f"{ply['mlp']['time_ratio']:.2f}"),
    ] + [("time", f"bcsdf {s}", f"{t:.0f} s") for s, t in seconds.items() if t is not None]
    data = {"config": cfg.name, "model": size, "bake": bake, "train": train.model_dump(), "table_file_bytes": table_file,
            "expanded_table_bytes": expanded, "weights_bytes": weights_file, "onnx_bytes": onnx_file,
            "stage_seconds": seconds, "render_ply": ply}
    return [{"part": a, "figure": b, "value": c} for a, b, c in rows], data


def _bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.bench.headline", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", nargs="?", default="configs/default.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    args = parser.parse_args(argv)
    cfg = load_config(args.config)
    rows, data = figures(cfg, args.artifacts)
    table = results.rows_table(rows)
    print(table)
    results.save("headline", f"`{args.config}`:\n\n{table}", data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
