"""Sharded bakes against the serial one (``make bench-cluster``), side by side in one run.

On one config (default: the thesis's 600 um bundle, its bake shortened with ``--paths``),
bakes the same table serially, on a LocalCluster of 1 worker and of 2 workers, checks the
three tables are identical, and prints: wall time and speed-up of each, the scheduler's
overhead per batch (1 worker against serial, over the batches), the cost of a batch, and
a weak-scaling projection to 64 workers from those measured costs (batches spread over
the workers plus the measured overhead per batch, the cluster's start-up excluded).
Writes ``artifacts/<name>/bench_cluster.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def _bake(cfg, root, workers=None) -> float:
    from . import bake

    t0 = time.perf_counter()
    bake.run(cfg, root, workers=workers)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", nargs="?", default="configs/thesis_600_tight.yaml")
    p.add_argument("--paths", type=int, default=1_000_000, help="bake.paths_per_phi_i of the measured bakes")
    p.add_argument("--artifacts", default="artifacts")
    args = p.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    from models.bundle_table import BundleTable
    from models.io import write_text

    from . import fiber
    from .config import load_config

    cfg = load_config(args.config, [f"bake.paths_per_phi_i={args.paths}", "bake.checkpoint_every_s=1e9"])
    with tempfile.TemporaryDirectory() as tmp:
        roots = {k: Path(tmp) / k for k in ("serial", "1 worker", "2 workers")}
        fiber.run(cfg, roots["serial"])
        for k in ("1 worker", "2 workers"):
            (roots[k] / cfg.name).mkdir(parents=True)
            os.symlink(roots["serial"] / cfg.name / "fiber", roots[k] / cfg.name / "fiber")
        seconds = {"serial": _bake(cfg, roots["serial"]), "1 worker": _bake(cfg, roots["1 worker"], 1),
                   "2 workers": _bake(cfg, roots["2 workers"], 2)}
        tables = [BundleTable.load(r / cfg.name / "bake" / "bundle_table.npz") for r in roots.values()]
        identical = all(np.array_equal(t.values, tables[0].values) for t in tables[1:])
        bake_seconds = json.loads((roots["serial"] / cfg.name / "bake" / "summary.json").read_text())["bake_seconds"]
    n_phi_i = len(tables[0].phi_i)
    batches = n_phi_i * -(-cfg.bake.paths_per_phi_i // cfg.bake.batch_paths)
    per_batch = bake_seconds / batches
    overhead = max(seconds["1 worker"] - seconds["serial"], 0.0) / batches
    startup = seconds["serial"] - bake_seconds  # the stage around the tracing: fiber load, plots
    projection = {n: startup + np.ceil(batches / n) * per_batch + batches * overhead / n for n in (1, 2, 8, 64)}
    result = {"config": args.config, "paths_per_phi_i": args.paths, "batches": batches, "seconds": seconds,
              "speedup_2_workers": seconds["serial"] / seconds["2 workers"], "per_batch_seconds": per_batch,
              "overhead_per_batch_seconds": overhead, "overhead_fraction_of_batch": overhead / per_batch,
              "identical_tables": identical, "weak_scaling_projection_seconds": projection}
    for k, v in seconds.items():
        print(f"[cluster] {k:>9}: {v:7.1f} s  (x{seconds['serial'] / v:.2f})")
    print(f"[cluster] {batches} batches of {per_batch:.2f} s; scheduler overhead {overhead * 1000:.0f} ms per batch "
          f"({overhead / per_batch:.1%} of one); tables identical: {identical}")
    print("[cluster] projection: " + ", ".join(f"{n} workers {s:.0f} s" for n, s in projection.items()))
    write_text(Path(args.artifacts) / cfg.name / "bench_cluster.json", json.dumps(result, indent=1))
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
