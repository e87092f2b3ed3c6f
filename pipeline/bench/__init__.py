"""Benchmarks: one thin ``main`` per command (``python -m pipeline.bench.<name>``), each
printing its figures side by side from one run; they run the library code the stages run
(``models``, ``pipeline``), never a stage's insides.
Figures and commands: docs/BENCHMARKS.md."""

import matplotlib

matplotlib.use("Agg")  # the benches are entry points: every picture is a file
