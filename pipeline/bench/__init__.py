"""Benchmarks: one thin ``main`` per command (``python -m pipeline.bench.<name>``), each
printing its figures side by side from one run; they reuse the stages' measurement code.
Figures and commands: docs/BENCHMARKS.md."""
