"""The bounce loops in rounds, shared by the parallel and the twisted tracers.

A SIMD packet of lanes iterates until its longest path ends, so a loop runs in rounds:
after ``round_steps`` iterations the unfinished lanes are compacted and continue, and the
last round (few lanes left) runs to the end. A lane that has ended keeps its state (an
inactive lane is not updated), so each round's final state is the per-path result, scattered
to per-path outputs by the path's id.
"""

from __future__ import annotations

from dataclasses import fields

import drjit as dr
import mitsuba as mi  # its types resolve to the variant chosen at the entry point, at call time
import numpy as np


class LoopState:
    """Mixin of a loop's per-path state (a dataclass of Dr.Jit arrays, one lane a path) with
    the fields ``active``, ``pid`` (the path's output row), ``steps`` (iterations this round)
    and those named in ``RESULTS``, the per-path results (Dr.Jit arrays or lists of them)."""

    RESULTS = ("B", "R", "depth", "status", "bin")

    def gather(self, index):
        """The lanes ``index`` (compaction between rounds), with a new round's step count."""
        take = lambda v: [dr.gather(type(x), x, index) for x in v] if isinstance(v, list) \
            else dr.gather(type(v), v, index)  # noqa: E731
        out = type(self)(**{f.name: take(getattr(self, f.name)) for f in fields(self)})
        out.steps = dr.zeros(type(self.steps), dr.width(index))
        return out


def in_rounds(paths: LoopState, run_round, round_steps: int, last_steps: int, tail_lanes: int) -> dict:
    """Run ``run_round(paths, limit)`` (a symbolic loop of at most ``limit`` iterations per
    lane; ``limit`` is an opaque kernel input, so one kernel serves every round) until every
    path has ended; ``last_steps`` bounds the round that runs with ``tail_lanes`` or fewer.

    Returns the state's ``RESULTS`` in the order of the path ids: a list field as a list of
    Dr.Jit arrays (``B``, ``R``), any other as numpy (``status``, ``depth``; ``bin`` int64).
    """
    n = dr.width(paths.pid)
    out = {}
    for name in paths.RESULTS:
        v = getattr(paths, name)
        out[name] = [dr.zeros(type(x), n) for x in v] if isinstance(v, list) else dr.zeros(type(v), n)
    while True:
        last = dr.width(paths.pid) <= tail_lanes
        paths = run_round(paths, dr.opaque(mi.UInt32, last_steps if last else round_steps))
        for name in paths.RESULTS:
            targets, values = out[name], getattr(paths, name)
            for o, v in zip(targets, values) if isinstance(values, list) else [(targets, values)]:
                dr.scatter(o, v, paths.pid)
        if last:
            dr.eval(out)
            break
        dr.eval(out, paths)  # one kernel for all
        keep = dr.compress(paths.active)
        if dr.width(keep) == 0:
            break
        paths = paths.gather(keep)
    return {k: v if isinstance(v, list) else v.numpy().astype(np.int64) if k == "bin" else v.numpy()
            for k, v in out.items()}
