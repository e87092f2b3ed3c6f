"""Sharded bakes against the serial one (``make bench-cluster``), side by side in one run.

On one config (default: the thesis's 600 um bundle, its bake set with ``--paths``), bakes
the same table serially, on a LocalCluster of 1 worker and of 2 workers, each on one core
(one Dr.Jit thread and one BLAS thread, as Dask's workers run numpy: without that the
serial bake's kernels already use every core), checks that the
three tables are identical, and prints wall times and speed-ups, both of the whole stage
and of its tracing phase. A worker's first task pays a one-time warm-up (importing
Mitsuba, building the baker, compiling its kernels), measured apart with a one-batch
bake on one worker against the same batch serially; the scheduler's overhead per batch
is what the 1-worker bake takes beyond the serial one and that warm-up, per batch. The
weak-scaling projection to 64 workers uses these measured costs: the stage's serial part,
the warm-up, the batches spread over the workers, the overhead. Writes
``artifacts/<name>/bench_cluster.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import drjit as dr
import numpy as np

from models.bundle_table import BundleTable
from models.io import write_text
from pipeline.bench import results

from .. import graph
from ..artifacts import config_dir, stage_dir
from ..loading import load_config
from ..summaries import BakeSummary


def _bake(cfg, root, workers=None) -> tuple[float, float, float]:
    """(stage seconds, tracing seconds, CPU seconds of this process while tracing) of one
    bake: with workers, this process is the client and the scheduler (LocalCluster runs it here)."""

    t0 = time.perf_counter()
    graph.run_stage("bake", cfg, root, workers=workers)
    stage = time.perf_counter() - t0
    summary = BakeSummary.read(stage_dir(cfg, "bake", root) / "summary.json")
    return stage, summary.bake_seconds, summary.tracing_cpu_seconds


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", nargs="?", default="configs/thesis_600_tight.yaml")
    p.add_argument("--paths", type=int, default=1_000_000, help="bake.paths_per_phi_i of the measured bakes")
    p.add_argument("--artifacts", default="artifacts")
    args = p.parse_args(argv)
    if argv is None and os.environ.get("OMP_NUM_THREADS") != "1":
        # Dask's workers run numpy's BLAS on one thread (OMP/OPENBLAS/MKL_NUM_THREADS=1);
        # the serial bake must too, and BLAS reads these only when numpy loads: start again
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        os.execve(sys.executable, [sys.executable, "-m", "pipeline.bench.cluster", *sys.argv[1:]], env)
    os.environ.setdefault("TQDM_DISABLE", "1")


    # one Dr.Jit thread everywhere: a worker is one core, and the serial bake is the
    # one-core reference (a bake is bit for bit reproducible at a given thread count)
    dr.set_thread_count(1)
    cfg = load_config(args.config, [f"bake.paths_per_phi_i={args.paths}", "bake.checkpoint_every_s=1e9"])
    one = cfg.model_copy(update={"bake": cfg.bake.model_copy(update={"paths_per_phi_i": cfg.bake.batch_paths})})
    runs = {"serial": None, "1 worker": 1, "2 workers": 2}
    with tempfile.TemporaryDirectory() as tmp:
        roots = {k: Path(tmp) / k for k in (*runs, "one batch serial", "one batch 1 worker")}
        graph.run_stage("fiber", cfg, roots["serial"])
        for k in list(roots)[1:]:
            config_dir(cfg, roots[k]).mkdir(parents=True)
            os.symlink(stage_dir(cfg, "fiber", roots["serial"]), stage_dir(cfg, "fiber", roots[k]))
        timed = {k: _bake(cfg, roots[k], w) for k, w in runs.items()}
        warm = {k: _bake(one, roots[k], w)[1] for k, w in (("one batch serial", None), ("one batch 1 worker", 1))}
        tables = [BundleTable.load(stage_dir(cfg, "bake", roots[k]) / "bundle_table.npz") for k in runs]
        identical = all(np.array_equal(t.values, tables[0].values) for t in tables[1:])
    seconds = {k: v[0] for k, v in timed.items()}
    tracing = {k: v[1] for k, v in timed.items()}
    client_cpu = {k: v[2] for k, v in timed.items() if runs[k]}
    batches = len(tables[0].phi_i) * -(-cfg.bake.paths_per_phi_i // cfg.bake.batch_paths)
    per_batch = tracing["serial"] / batches
    warmup = max(warm["one batch 1 worker"] - warm["one batch serial"], 0.0)
    overhead = max(tracing["1 worker"] - tracing["serial"] - warmup, 0.0) / batches
    serial_part = seconds["serial"] - tracing["serial"]  # fiber table, bundle, pictures, reduction probes
    projection = {n: serial_part + warmup + np.ceil(batches / n) * per_batch + batches * overhead / n
                  for n in (1, 2, 8, 64)}
    result = {"config": args.config, "paths_per_phi_i": args.paths, "batches": batches, "stage_seconds": seconds,
              "tracing_seconds": tracing, "speedup_2_workers_stage": seconds["serial"] / seconds["2 workers"],
              "speedup_2_workers_tracing": tracing["serial"] / tracing["2 workers"],
              "per_batch_seconds": per_batch, "worker_warmup_seconds": warmup,
              "overhead_per_batch_seconds": overhead, "overhead_fraction_of_batch": overhead / per_batch,
              "client_cpu_seconds": client_cpu,
              "identical_tables": identical, "weak_scaling_projection_seconds": projection}
    for k in runs:
        print(f"[cluster] {k:>9}: stage {seconds[k]:6.1f} s (x{seconds['serial'] / seconds[k]:.2f}), "
              f"tracing {tracing[k]:6.1f} s (x{tracing['serial'] / tracing[k]:.2f})")
    print(f"[cluster] {batches} batches of {per_batch:.2f} s; worker warm-up {warmup:.1f} s; scheduler overhead "
          f"{overhead * 1000:.0f} ms per batch ({overhead / per_batch:.1%} of one); tables identical: {identical}")
    print("[cluster] CPU of the client and scheduler (this process) while tracing: "
          + ", ".join(f"{k} {v:.1f} s" for k, v in client_cpu.items()))
    print("[cluster] projection (stage): " + ", ".join(f"{n} workers {s:.0f} s" for n, s in projection.items()))
    write_text(config_dir(cfg, args.artifacts) / "bench_cluster.json", json.dumps(result, indent=1))
    return 0 if identical else 1


if __name__ == "__main__":
    with results.recorded("cluster", smoke="--quick" in sys.argv):
        raise SystemExit(main())
