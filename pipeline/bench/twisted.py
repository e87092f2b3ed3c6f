"""Bake cost of a twisted ply against a parallel one of the same cross-section
(``make bench-twisted``), side by side in one run.

For the config's cross-section (its fiber, radius, packing; the Poisson distance widened
for the twist's lean in every case, so that all rows trace the same fibers): the parallel
2D bake and the 3D bake at each ``--pitch``, each traced in batches until the median
relative standard error over the bins holding 90% of its scattered energy reaches the
target (5%), or its budget runs out (then extrapolated with error ~ 1/sqrt(time), and
marked). Prints paths and vertices per second and the time to the target; the parallel
table's paths carry every theta_i, a twisted table's one each.

``--migration R_MIN S`` adds two rows at the first pitch: the cross-section that
``pipeline.build`` spaces out until fibers migrating so clear each other (sparser), twisted
rigidly (in its own one-turn scene, and in a scene as long as the migrating period) and with
the migration (a period of several turns), so that migration's own cost is read from one
cross-section.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import mitsuba as mi
import numpy as np

from models import fiber as fiber_models
from models.bake import Tally
from models.bundle import Migration, TwistedBundle
from pipeline.bench import results
from pipeline.build import build_bundle, build_ply, make_spec, tracer
from pipeline.loading import load_config

from .bake import median_rel_error


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--pitch", type=float, nargs="+", default=[-2838.0, 1500.0],
                        help="signed pitches (um); -2838: Cotton 1 scaled to a 200 um ply (its 24 deg lean)")
    parser.add_argument("--target", type=float, default=0.05)
    parser.add_argument("--budget", type=float, default=120.0, help="seconds per row")
    parser.add_argument("--batch", type=int, default=32768)
    parser.add_argument("--migration", type=float, nargs=2, metavar=("R_MIN", "S"),
                        help="add a migrating ply (Cotton 1: 0.8 1.1) and its rigid twin")
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")


    # the cross-section spaced for the steepest pitch, shared by every row
    steepest = min(abs(p) for p in args.pitch)
    cfg = load_config(args.config, [f"bundle.twist={{pitch_um: {steepest}}}"])
    mi.set_variant(cfg.bake.variant)
    wl = cfg.wavelengths.grid()
    fiber = fiber_models.build(cfg.fiber, wl).tabulate(
        cfg.tabulate.theta_i())
    bundle = build_bundle(cfg)
    print(f"config {args.config}: {len(bundle.radii)} fibers of {cfg.fiber.radius_um} um in {bundle.semi_axes} um "
          f"(packing {bundle.packing_fraction:.3f}), {len(wl)} wavelengths, {cfg.fiber.model} fiber; "
          f"target {args.target:.0%} median relative error over the bins of 90% of the energy; "
          f"budget {args.budget:.0f} s per row; {os.cpu_count()} cores")
    print(f"{'ply':>26s} {'lean':>6s} {'theta_i':>7s} {'paths/s':>9s} {'vertices/s':>11s} {'paths':>9s} "
          f"{'error':>7s} {'time to target':>15s}")
    rows = [("parallel", bundle)] + [(f"twisted, pitch {p:+.0f} um", TwistedBundle(bundle, p)) for p in args.pitch]
    if args.migration:
        r_min, s = args.migration
        migrating = build_ply(load_config(args.config, [
            f"bundle.twist={{pitch_um: {args.pitch[0]}, migration: {{r_min: {r_min}, s: {s}}}}}"]))
        print(f"migrating: {len(migrating.bundle.radii)} fibers (packing {migrating.bundle.packing_fraction:.3f}), "
              f"r_min {r_min:g}, s {s:g}: a period of {migrating.migration.turns} turns")
        # the rigid twist traced through a scene as long as the migrating period (a migration
        # of 1e-9: the same helices to 0.0002 um), to part the period's cost from migration's
        long_rigid = TwistedBundle(migrating.bundle, args.pitch[0], Migration(1 - 1e-9, s), checked=False)
        rows += [("sparser, rigid", TwistedBundle(migrating.bundle, args.pitch[0])),
                 ("sparser, rigid, long scene", long_rigid), ("sparser, migrating", migrating)]
    for name, ply in rows:
        spec, _ = make_spec(cfg, ply, fiber)
        baker = tracer(ply, fiber, spec)
        baker.trace(0, 4096, np.random.SeedSequence([7, 999]))  # compiles the kernels
        tally = Tally.zeros(spec, len(wl))
        elapsed, k, err, bins = 0.0, 0, np.inf, None
        while elapsed < args.budget:
            t0 = time.perf_counter()
            tally.add(baker.trace(0, args.batch, np.random.SeedSequence([7, k])))
            elapsed += time.perf_counter() - t0
            k += 1
            if k == 2:  # the bins of 90% of the energy, from the first batches
                _, bins = median_rel_error(tally, spec, fiber)
            if bins is not None:
                err, _ = median_rel_error(tally, spec, fiber, bins)
                if err <= args.target:
                    break
        reached = err <= args.target
        t_target = elapsed if reached else elapsed * (err / args.target) ** 2
        lean = np.degrees(ply.max_lean) if isinstance(ply, TwistedBundle) else 0.0
        if isinstance(ply, TwistedBundle):
            print(f"{name}: {len(baker.geometry.fiber_of)} cylinders over {ply.period / ply.turn_length:.0f} turn(s)")
        print(f"{name:>26s} {lean:5.1f}d {len(spec.theta_i):7d} {tally.paths.sum() / elapsed:9.0f} "
              f"{tally.vertices / elapsed:11.0f} {int(tally.paths.sum()):9d} {err:7.2%} {t_target:13.1f} s"
              f"{'' if reached else ' (extrapolated)'}")


if __name__ == "__main__":
    with results.recorded("twisted", smoke="--quick" in sys.argv):
        main()
