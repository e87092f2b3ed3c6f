"""Benchmarks: one thin ``main`` per command (``python -m pipeline.bench.<name>``), each
printing its figures side by side from one run; they run the library code the stages run
(``models``, ``pipeline``), never a stage's insides.
Figures and commands: docs/BENCHMARKS.md."""

import matplotlib

from pipeline import graph
from pipeline.bsdfs import backend_props

matplotlib.use("Agg")  # the benches are entry points: every picture is a file


def baked(cfg, root="artifacts"):
    """``cfg`` with its table baked: its fiber and bake stages run where the table is missing
    or was baked from other settings (a bench's variant of a config, under a name of its own,
    reused where its artifacts match)."""
    try:
        backend_props(cfg, root, "table")
    except ValueError:
        for stage in ("fiber", "bake"):
            graph.run_stage(stage, cfg, root)
    return cfg
