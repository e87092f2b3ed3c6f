"""Benchmark: time to tabulate the single-fiber models (``make bench``).

Runs each case ``--repeat`` times in one process, side by side, and prints the
minimum and median wall time. The Mie case is the default spectral table of
``configs/default.yaml``: 20 um fiber, 25 wavelengths, theta_i every 5 deg.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np

from models import fiber as fiber_models
from pipeline.bench import results
from pipeline.loading import load_config


def _time(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return times, result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}")
    print(f"{'case':46s} {'min [s]':>9s} {'median [s]':>11s}  table")
    for name, path in (("mie, default config", "configs/default.yaml"),
                       ("ray, configs/fiber_ray.yaml", "configs/fiber_ray.yaml")):
        cfg = load_config(path)
        wl = cfg.wavelengths.grid()
        theta_i = cfg.tabulate.theta_i()
        model = fiber_models.build(cfg.fiber, wl)
        times, table = _time(lambda: model.tabulate(theta_i), args.repeat)
        shape = "x".join(str(s) for s in table.lobes[0].azimuthal.shape)
        print(f"{name:46s} {min(times):9.2f} {statistics.median(times):11.2f}  "
              f"{len(table.lobes)} lobe(s) of {shape}")
    # Lookup throughput of the tabulated Mie model (numpy, 1M queries)
    cfg = load_config("configs/default.yaml")
    table = fiber_models.build(cfg.fiber, cfg.wavelengths.grid()).tabulate(np.deg2rad(np.arange(0, 91, 5.0)))
    rng = np.random.default_rng(0)
    q = 1_000_000
    args_q = dict(phi_i=0.0, theta_i=rng.uniform(-1.5, 1.5, q), phi_o=rng.uniform(-np.pi, np.pi, q),
                  theta_o=rng.uniform(-1.5, 1.5, q), wavelength=rng.uniform(400, 700, q))
    times, _ = _time(lambda: table.eval(**args_q), args.repeat)
    print(f"{'mie table lookup, numpy, 1M queries':46s} {min(times):9.2f} {statistics.median(times):11.2f}  "
          f"{min(times) / q * 1e9:.0f} ns/query")


if __name__ == "__main__":
    with results.recorded("fiber", smoke="--quick" in sys.argv):
        main()
