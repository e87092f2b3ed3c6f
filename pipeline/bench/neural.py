"""Error against run time on 1M queries (``make bench-neural``): the export stage's
measurement (:mod:`pipeline.error_vs_time`) at benchmark size, for a config whose models
are trained and exported.

    python -m pipeline.bench.neural [--config C] [--artifacts A] [--queries N]
    python -m pipeline.bench.neural --forms [--config C] [--artifacts A] [--queries N]

``--forms`` compares the two formulations of :class:`mitsuba_ext.neural.DrJitMLP`
(literal weights, cooperative vectors) for every model size, side by side, each on a cold
kernel cache (a child process with a fresh ``HOME``, where Dr.Jit keeps its cache): the
first call (tracing, compilation, run) and a warm second one, in a plain kernel over the
queries and inside a symbolic loop of 8 evaluations (as in a render).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_ext.neural import DrJitMLP
from models.jit import to_drjit
from pipeline.bench import results

from ..artifacts import stage_dir
from ..loading import load_config
from ..error_vs_time import measure
from ..graph import require


def one_form(weights: str, form: str, context: str, queries: int) -> tuple[float, float]:
    """Seconds of a first and a second evaluation of the model at ``weights`` in ``form``:
    ``context`` "plain" (one kernel over the queries) or "loop" (a symbolic loop of 8)."""

    mi.set_variant("llvm_ad_rgb")

    mlp = DrJitMLP(weights, form=form)
    rng = np.random.default_rng(0)
    q = [to_drjit(mi.Float, rng.uniform(-1.5, 1.5, queries).astype(np.float32)) for _ in range(4)]

    seconds = []
    for _ in range(2):
        t0 = time.perf_counter()
        out = mlp.eval(*q) if context == "plain" else _loop(mlp, mi.Float(q[0]), mi.UInt32(0))
        dr.eval(out)
        dr.sync_thread()
        seconds.append(time.perf_counter() - t0)
    return seconds[0], seconds[1]


@dr.syntax
def _loop(mlp, x, i):
    """8 evaluations in a symbolic loop from ``i = 0``, each input depending on the last output."""
    acc = dr.zeros(type(x), dr.width(x))
    while i < 8:
        acc += mlp.eval(x, 0.3 * x, -x, 0.5 + 0.1 * x)[0]
        x = dr.fma(x, 0.7, 0.1 * dr.sin(acc))
        i += 1
    return acc


def forms(cfg, artifacts: str, queries: int) -> list[dict]:
    """Every model size x form x context, each in a child process on a cold kernel cache."""
    rows = []
    print(f"{'model':8s} {'form':12s} {'context':8s} {'first call s':>12s} {'second s':>9s}   ({queries} queries)")
    for size in cfg.train.models:
        weights = stage_dir(cfg, "export", artifacts) / size / "weights.npz"
        for context in ("plain", "loop"):
            for form in ("literal", "cooperative"):
                with tempfile.TemporaryDirectory(prefix="bcsdf-cold-cache-") as home:
                    code = (f"from pipeline.bench.neural import one_form; "
                            f"print(*one_form({str(weights)!r}, {form!r}, {context!r}, {queries}))")
                    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                       env={**os.environ, "HOME": home}, check=True)
                first, second = map(float, r.stdout.split()[-2:])
                rows.append({"model": size, "form": form, "context": context, "first": first, "second": second})
                print(f"{size:8s} {form:12s} {context:8s} {first:12.2f} {second:9.3f}", flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    parser.add_argument("--queries", type=int, default=1_000_000)
    parser.add_argument("--forms", action="store_true", help="literal weights against cooperative vectors")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                    help="change a config key, as `bcsdf run --set` (make run-sizes: the three model sizes)")
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    cfg = load_config(args.config, args.overrides)
    require(cfg, ("bake", "train", "export"), args.artifacts,
            " ".join([".venv/bin/bcsdf run", str(args.config), *(f"--set '{o}'" for o in args.overrides)]))
    if args.forms:
        forms(cfg, args.artifacts, args.queries)
    else:
        measure(cfg, args.artifacts, args.queries)


if __name__ == "__main__":
    with results.recorded("neural", smoke="--quick" in sys.argv):
        main()
