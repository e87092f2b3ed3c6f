"""Error against run time on 1M queries (``make bench-neural``): the export stage's
measurement (:mod:`pipeline.error_vs_time`) at benchmark size, for a config whose models
are trained and exported."""

from __future__ import annotations

import argparse
import os

from ..config import load_config
from ..error_vs_time import measure


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--artifacts", default="artifacts")
    parser.add_argument("--queries", type=int, default=1_000_000)
    args = parser.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")
    measure(load_config(args.config), args.artifacts, args.queries)


if __name__ == "__main__":
    main()
