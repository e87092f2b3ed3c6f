"""Stage ``bake``: trace the bundle and write the ground-truth table.

Reads ``artifacts/<name>/fiber/fiber_table.npz`` (refused if it was made from other
``wavelengths/fiber/tabulate`` settings) and writes under ``artifacts/<name>/bake/``:

* ``bundle_table.npz``  the :class:`models.bundle_table.BundleTable`;
* ``arrangement.png``   the fibers and the bounding shape;
* ``slices/phi_i_XX_theta_i_YY.png``  the table per incident direction (the theta_i nodes nearest
  every 15 deg, ``plots.slice_nodes``), in sRGB;
* ``energy.png``        scattered, passthrough, absorbed and lost against theta_i;
* ``summary.json``      timing, path and vertex counts, energy balance;
* ``checkpoint.npz``    while baking: the running sums. Interrupting the bake and
  running it again continues from the last checkpoint and gives the same table as an
  uninterrupted run (batches have fixed seeds and are summed in order).

The Mitsuba variant (``bake.variant``) is chosen here, at the entry point.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import mitsuba as mi
from tqdm import tqdm

from .. import cluster
from ..baking import Bake
from ..build import describe


def run(cfg, out_root="artifacts", stop_after=None, workers=None, scheduler=None) -> Path:
    """Bake; ``stop_after`` batches simulates an interruption (the checkpoint stays).

    ``workers`` (a LocalCluster of that many processes) or ``scheduler`` (an existing
    Dask cluster's address) shard the batches (``pipeline.cluster``); the table is the
    same, bit for bit.
    """
    if cfg.bundle is None:
        raise ValueError("this config has no 'bundle:' section; add one to bake")
    mi.set_variant(cfg.bake.variant)
    bake = Bake(cfg, out_root)
    print(f"bake: {describe(bake.ply)}", flush=True)  # what was built, to set against what was asked
    with cluster.client(workers, scheduler) as dask_client, \
            tqdm(total=bake.total_paths, initial=bake.total_paths - bake.paths_left, unit="path", unit_scale=True,
                 desc=f"bake {cfg.bake.estimator}") as bar:
        batches = bake.serial() if dask_client is None else cluster.ordered_tallies(dask_client, [bake])
        with contextlib.closing(batches):
            while not bake.finished:
                if stop_after is not None and bake.done >= stop_after:
                    bake.save_checkpoint()
                    return bake.out
                _, i, tally = next(batches)
                bar.update(bake.add(i, tally))
                bar.set_postfix(batches=f"{bake.done}/{len(bake.work)}", vertices=f"{bake.tally.vertices:.3g}",
                                refresh=False)  # the bar prints on its own clock
    return bake.finish()


