"""What ``dvc metrics`` and ``dvc plots`` read: ``artifacts/<name>/metrics/``.

Each stage keeps its full record beside its artifacts (``summary.json``); here it also
writes its headline scalars (``<stage>.json``, flat, for ``dvc metrics show/diff``) and
the data of its curves (CSV, for ``dvc plots show/diff``). The folder sits beside the
stages' output folders, not in them: DVC refuses metrics inside another output.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from models.io import write_text

from .artifacts import stage_dir


def folder(cfg, root) -> Path:
    return stage_dir(cfg, "metrics", root)


def _clean(v):
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    v = float(v)
    return v if math.isfinite(v) else None  # JSON has no NaN; DVC shows null as '-'


def write_metrics(cfg, root, stage: str, values: dict) -> Path:
    """``values``: name -> number, or nested dicts of them (DVC shows ``a.b.c``)."""
    path = folder(cfg, root) / f"{stage}.json"
    write_text(path, json.dumps(_clean(values), indent=1))
    return path


def write_curve(path: Path, rows: list[dict]) -> Path:
    """One CSV of ``rows`` (same keys each), for a ``plots:`` entry."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buf.getvalue())
    return path


def rows_table(rows: list[dict], columns: list[str] | None = None) -> str:
    """A Markdown table of ``rows`` (one dict each), numbers to 4 significant digits."""
    columns = columns or list(dict.fromkeys(k for r in rows for k in r if not isinstance(r[k], (dict, list))))

    def cell(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)
