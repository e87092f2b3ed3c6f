"""The documents' figures, from the benches' records (``benchmarks/<name>.json``)::

    .venv/bin/python -m pipeline.figures           # rewrite every results block
    .venv/bin/python -m pipeline.figures --check   # fail on a stale block or a typed figure

A document holds measured figures only in blocks that this command writes::

    <!-- results: NAME -->
    (the record's tables, with the command, machine and date that measured them)
    <!-- /results -->

``NAME`` is a bench (``python -m pipeline.bench.NAME`` writes its record). Outside the
blocks, code and comments, a document quotes no measured figure: a percentage, a ratio
(``12x``), a time, a size in bytes, a FLIP or PSNR value. ``--check`` lists every one it
finds with its line; a tolerance (``within 3% + 3 standard errors``) is a criterion, not a
measurement, and passes (``CRITERIA``).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from models.io import write_text

from .bench import results

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", ROOT / "docs" / "BENCHMARKS.md", ROOT / "docs" / "DESIGN.md"]

BLOCK = re.compile(r"(<!-- results: (?P<name>[\w.-]+) -->\n)(?P<body>.*?)(<!-- /results -->)", re.S)
FIGURE = re.compile(r"(?<![\w.])\d+(?:[.,]\d+)*(?:\s?(?:%|KB|MB|GB|KiB|MiB|GiB|dB|ms|min|minutes|seconds|hours)\b"
                    r"|\s?%|x\b|\s?s\b)|\b(?:FLIP|PSNR)\s+(?:of\s+)?\d")
CRITERIA = re.compile("|".join([
    r"\d+(?:\.\d+)?% \+ \d+ (?:standard errors|se|sigma)\b",  # an agreement criterion
    r"holding \d+% of",                                       # the bins that hold most of the energy
    r"lie within \d+%",                                       # the highlight bench's band
]))
SKIP = re.compile(r"```.*?```|`[^`\n]*`|<!--.*?-->|\]\([^)]*\)", re.S)  # code, comments, link targets


def block_text(name: str) -> str:
    """The body of the block ``name``: its record's tables under who measured them, where."""
    record = results.load(name)
    if record is None:
        bench, _, option = name.partition("-")  # train-calibration: pipeline.bench.train --calibration
        how = f"python -m pipeline.bench.{bench}" + (f" --{option} ..." if option else "")
        return f"*Not measured yet: `{how}` records it.*\n"
    return (f"*Measured by `{record['command']}` on {record['date']}, {record['machine']}.*\n\n"
            f"{record['markdown']}\n")


def regenerate(text: str) -> str:
    return BLOCK.sub(lambda m: m.group(1) + block_text(m.group("name")) + m.group(4), text)


def typed_figures(text: str) -> list[tuple[int, str]]:
    """``(line, text)`` of every measured figure outside the blocks, code and comments."""
    masked = BLOCK.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    masked = SKIP.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), masked)
    masked = CRITERIA.sub(lambda m: " " * len(m.group(0)), masked)
    found = []
    for m in FIGURE.finditer(masked):
        line = masked.count("\n", 0, m.start()) + 1
        found.append((line, text.splitlines()[line - 1].strip()))
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.figures", description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 where a document is stale "
                        "or quotes a figure outside its blocks")
    args = parser.parse_args(argv)
    problems = []
    for path in DOCUMENTS:
        text = path.read_text()
        fresh = regenerate(text)
        if fresh != text:
            if args.check:
                problems.append(f"{path.relative_to(ROOT)}: a results block differs from its record; run "
                                "`python -m pipeline.figures`")
            else:
                write_text(path, fresh)
                print(f"wrote {path.relative_to(ROOT)}")
        for line, quote in typed_figures(fresh):
            problems.append(f"{path.relative_to(ROOT)}:{line}: a figure typed by hand: {quote}")
    for p in problems:
        print(p, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
