"""Bakes on a Dask cluster: every batch a task, tallies reduced in batch order.

A bake is a list of batches with fixed seeds whose tallies add, so it shards without
changing a bit: the workers trace batches in any order, the client adds their tallies
in batch order (the serial bake's order), so the table is the serial bake's, bit for
bit. ``--workers N`` starts an embedded ``distributed.LocalCluster`` of N single-threaded
worker processes; ``--scheduler ADDRESS`` (or ``BCSDF_SCHEDULER``) joins an existing
cluster, e.g. one that ``dask-jobqueue`` started on SLURM (README). A lost worker's
batches are recomputed by Dask; an interrupted client keeps the bake's checkpoint, and
the next run (serial or sharded) resumes from the batches that finished in order.

Workers must run the same code as the client (a table would not be reproducible
otherwise): each task carries the client's code digest and a worker with another one
refuses it. Dr.Jit's kernels split their work by thread, which moves the last bits of
some sums, so a table is reproducible bit for bit at a given Dr.Jit thread count: each
task also carries the client's, and the worker runs the batch with it (on a cluster of
single-core workers, run the client with ``drjit.set_thread_count(1)`` too, as
``bench_cluster`` does).
"""

from __future__ import annotations

import contextlib
import json
import os

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin

from . import graph
from .config import FIBER_SECTIONS, Config

_BAKERS: dict = {}  # per worker process: the Bakers of the last few (config, fiber table)
BAKERS_KEPT = 4  # a sweep's tasks interleave members a little: keep a few scenes built
CONNECT_TIMEOUT = "10s"  # how long to look for a scheduler before saying it cannot be reached
MAX_BATCHES_PER_TASK = 8


def code_digest(cfg) -> str:
    """The digest of the code a bake runs (the bake stage's code deps in dvc.yaml)."""
    return graph.digest(graph.spec("bake", cfg)["code"], graph.ROOT)[:16]


def trace_batches(cfg_json: str, fiber, items, code: str, threads: int = 0) -> list:
    """Several consecutive batches in one task (``items``: ``(a, k, size)``): one round
    trip to the scheduler for all of them. Returns their packed tallies, in order."""
    return [trace_batch(cfg_json, fiber, a, k, size, code, threads) for a, k, size in items]


def warm_up(variants) -> None:
    """Import everything a batch runs and set up each Mitsuba variant in ``variants``.

    These imports run Dr.Jit's ``@dr.syntax`` (Mitsuba's own integrators too), i.e.
    ``ast.parse``, which CPython 3.11 cannot run in two threads at once (gh-106905: "AST
    constructor recursion depth mismatch"), and a worker's other threads parse too
    (``inspect.signature`` of a builtin does, for one). :class:`WarmUp` runs this on every
    worker before it takes a task, so a batch parses no source.
    """
    import mitsuba as mi

    from . import build  # noqa: F401  (the bakers' @dr.syntax loops)

    for variant in variants:
        mi.set_variant(variant)


class WarmUp(WorkerPlugin):
    """A Dask worker plugin: :func:`warm_up` when a worker joins, restarted ones included
    (a worker sets its plugins up before it reads its first task)."""

    name = "bcsdf-warm-up"

    def __init__(self, variants):
        self.variants = tuple(sorted(set(variants)))

    def setup(self, worker):
        warm_up(self.variants)


def trace_batch(cfg_json: str, fiber, a: int, k: int, size: int, code: str, threads: int = 0):
    """One batch on a worker: ``Baker.trace`` with the serial bake's seed, on ``threads``
    Dr.Jit threads (the client's). Returns the tally, packed."""
    # imported here, not when the task is unpickled: see warm_up (which made these imports cheap)
    import mitsuba as mi

    from .build import batch_seed, build_ply, make_spec, tracer

    cfg = Config.model_validate(json.loads(cfg_json))
    if code != _worker_code(cfg):
        raise RuntimeError(f"this worker runs code {_worker_code(cfg)}, the client {code}: start the workers "
                           "from the same checkout (a table must be reproducible)")
    key = (cfg.hash(), id(fiber))
    if threads:
        import drjit as dr

        # Dr.Jit's kernels split their work by thread, which moves the last bits of some
        # sums: the client's thread count keeps the batch's tally the serial one's
        if dr.thread_count() != threads:
            dr.set_thread_count(threads)
    if key not in _BAKERS:
        mi.set_variant(cfg.bake.variant)  # this worker's entry point
        ply = build_ply(cfg)
        spec, _ = make_spec(cfg, ply, fiber)
        while len(_BAKERS) >= BAKERS_KEPT:
            _BAKERS.pop(next(iter(_BAKERS)))  # the oldest
        _BAKERS[key] = tracer(ply, fiber, spec)
    return pack(_BAKERS[key].trace(a, size, batch_seed(cfg, a, k)))


def pack(tally) -> dict:
    """A batch's tally for the wire: ``sum`` and ``sum_sq`` as their non-zero entries.

    Parallel fibers keep light on the specular cone, so a batch fills a few per cent of
    the bins; the zeros it leaves out add exactly nothing, so the unpacked tally adds to
    the same bits.
    """
    a = tally.arrays()
    nz = np.flatnonzero((a["sum"] != 0) | (a["sum_sq"] != 0))
    return {"shape": a["sum"].shape, "index": nz.astype(np.int64), "sum": a["sum"].ravel()[nz],
            "sum_sq": a["sum_sq"].ravel()[nz], **{k: v for k, v in a.items() if k not in ("sum", "sum_sq")}}


def unpack(packed: dict):
    from models.bake import Tally  # on the client's thread too: see trace_batch

    dense = {}
    for k in ("sum", "sum_sq"):
        a = np.zeros(packed["shape"])
        a.ravel()[packed["index"]] = packed[k]
        dense[k] = a
    return Tally.from_arrays({**packed, **dense})


_CODE = None


def _worker_code(cfg) -> str:
    """This process's :func:`code_digest`, computed once (the code does not change under it)."""
    global _CODE
    if _CODE is None:
        _CODE = code_digest(cfg)
    return _CODE


@contextlib.contextmanager
def client(workers: int | None = None, scheduler: str | None = None):
    """A ``distributed.Client`` for the bake, or ``None`` for the in-process bake."""
    scheduler = scheduler or os.environ.get("BCSDF_SCHEDULER") or None
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be at least 1 (got {workers})")
    if not workers and not scheduler:
        yield None
        return
    from distributed import Client, LocalCluster
    if scheduler:
        try:
            c = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as e:
            raise ValueError(f"cannot reach the Dask scheduler at {scheduler} ({e}); start one with "
                             "`dask scheduler` or leave out --scheduler") from None
        with c:
            print(f"[bake] Dask cluster {scheduler}: {len(c.scheduler_info()['workers'])} workers; "
                  f"dashboard {c.dashboard_link}")
            yield c
        return
    with LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=40) as cluster, Client(cluster) as c:
        print(f"[bake] Dask LocalCluster: {workers} workers; dashboard {c.dashboard_link}")
        yield c


def ordered_tallies(c, bakes):
    """Yield ``(j, index, tally)`` for the remaining batches of every bake in ``bakes``
    (:class:`pipeline.baking.Bake`), traced on the cluster; each bake's batches in order.

    All remaining batches are submitted at once, bake after bake (Dask runs tasks
    roughly in the order they were submitted, so a worker seldom switches scenes), several
    consecutive batches per task so that a round trip to the scheduler carries more work,
    fewer towards the end (guided self-scheduling: a task takes 1/(4 N) of the batches not
    yet submitted, for N workers, so the last tasks are single batches and the workers
    finish together); a result is held until every earlier batch of its bake is in, so the caller
    adds them in the serial order.
    """
    import drjit as dr
    from distributed import as_completed

    threads, code = dr.thread_count(), code_digest(bakes[0].cfg)  # one code for every bake
    c.register_plugin(WarmUp(b.cfg.bake.variant for b in bakes), name=WarmUp.name)
    n_workers = max(1, len(c.scheduler_info().get("workers", {})))
    left = sum(len(b.work) - b.done for b in bakes)
    futures, fibers = {}, {}
    for j, b in enumerate(bakes):
        cfg = b.cfg
        cfg_json = cfg.model_dump_json()
        fkey = cfg.hash(*FIBER_SECTIONS)
        if fkey not in fibers:  # members of a sweep that share a fiber share its upload
            fibers[fkey] = c.scatter(b.fiber, broadcast=True)
        i = b.done
        while i < len(b.work):
            n = min(MAX_BATCHES_PER_TASK, max(1, left // (4 * n_workers)), len(b.work) - i)
            g = list(range(i, i + n))
            fut = c.submit(trace_batches, cfg_json, fibers[fkey], [(*b.work[k], b.sizes[k]) for k in g], code,
                           threads, pure=False, key=f"bake-{cfg.name}-{cfg.hash()[:6]}-{g[0]}-{g[-1]}")
            futures[fut] = (j, g)
            i, left = i + n, left - n
    ready, nxt = [{} for _ in bakes], [b.done for b in bakes]
    try:
        for fut in as_completed(futures):
            j, g = futures[fut]
            for i, packed in zip(g, fut.result()):
                ready[j][i] = unpack(packed)
            fut.release()
            while nxt[j] in ready[j]:
                yield j, nxt[j], ready[j].pop(nxt[j])
                nxt[j] += 1
    finally:
        c.cancel(list(futures))
