"""What the benches measured, kept: ``benchmarks/<name>.json``.

A record holds the command that measured it, the machine and the date, the figures as
data and its tables in Markdown. ``python -m pipeline.figures`` copies the tables into the
documents (README.md, docs/BENCHMARKS.md) between ``<!-- results: NAME -->`` markers; its
``--check`` (run by the tests) fails where a document's block differs from its record, or
where a document quotes a measured figure outside the blocks.

A bench records itself in one of two ways:

* ``save(name, markdown, data)``: its own tables (the hair and exit benches);
* ``with recorded(name):`` around its work: what it prints, as one text block, and only
  when it ran in full (a ``--quick`` smoke run is not a measurement).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import platform
import sys
from datetime import date
from pathlib import Path

from models.io import write_text

from ..metrics import rows_table  # noqa: F401  (the benches' tables: results.rows_table)

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks"


def machine() -> str:
    """The CPU, its cores and torch's kernel set: what the figures were measured on."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    kernels = os.environ.get("ATEN_CPU_CAPABILITY")
    if kernels is None:
        with contextlib.suppress(Exception):
            import torch  # optional here: a record names torch's kernels where torch is loaded

            kernels = torch.backends.cpu.get_cpu_capability()
    return f"{cpu}, {os.cpu_count()} cores" + (f", torch {kernels} kernels" if kernels else "")


def command() -> str:
    """This process's command line, as a user would type it."""
    script = Path(sys.argv[0]).resolve()
    if script.is_relative_to(RESULTS.parent):  # python -m pipeline.bench.NAME
        return " ".join(["python -m", ".".join(script.relative_to(RESULTS.parent).with_suffix("").parts),
                         *sys.argv[1:]])
    return " ".join([script.name, *sys.argv[1:]])


def provenance() -> dict:
    """What a record's header says of a measurement: this command, today, this machine."""
    return {"command": command(), "date": date.today().isoformat(), "machine": machine()}


def save(name: str, markdown: str, data=None, cmd: str | None = None, folder: Path | None = None) -> Path:
    """Write ``<folder>/<name>.json``: the command, machine, date, ``markdown`` and ``data``."""
    record = {"name": name, **provenance(), "markdown": markdown.strip(), "data": data}
    if cmd:
        record["command"] = cmd
    path = (folder or RESULTS) / f"{name}.json"
    write_text(path, json.dumps(record, indent=1) + "\n")
    print(f"recorded {path}")
    return path


def load(name: str, folder: Path | None = None) -> dict | None:
    """The record ``name``, or ``None`` where it was never measured."""
    path = (folder or RESULTS) / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, s):
        for stream in self.streams:
            stream.write(s)
        return len(s)

    def flush(self):
        for stream in self.streams:
            stream.flush()


@contextlib.contextmanager
def recorded(name: str, smoke: bool = False, folder: Path | None = None):
    """Record what the body prints as ``name`` (a fenced text block), if it finishes and is
    not a ``smoke`` run (``--quick``: not a measurement)."""
    printed = io.StringIO()
    real = sys.stdout
    sys.stdout = _Tee(real, printed)
    done = None
    try:
        yield
    except SystemExit as e:   # a bench's `raise SystemExit(main())`: it finished, record it
        if e.code not in (None, 0):
            raise
        done = e
    finally:
        sys.stdout = real
    if smoke:
        print(f"not recorded: a smoke run (run without --quick to update benchmarks/{name}.json)")
    else:
        save(name, f"```text\n{printed.getvalue().strip()}\n```", folder=folder)
    if done is not None:
        raise done
