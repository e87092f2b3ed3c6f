"""``bcsdf``: one subcommand per pipeline stage, each driven by one config file.

    bcsdf fiber CONFIG     tabulate and draw the single-fiber model
    bcsdf bake CONFIG      trace the bundle, write the ground-truth table
    bcsdf train CONFIG     fit the MLP sizes of the config to the baked table
    bcsdf export CONFIG    write each trained model as ONNX and as plain weights
    bcsdf report CONFIG    one HTML page with the pictures and figures of every stage
    bcsdf run CONFIG       every stage in order

Errors in the config or the data print what is wrong and exit with status 2;
artifacts from earlier runs are left as they were.
"""

from __future__ import annotations

import argparse
import sys

STAGES = ("fiber", "bake", "train", "export", "report")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="bcsdf", description=__doc__.split("\n\n")[0])
    parser.add_argument("--artifacts", default="artifacts", help="output root (default: artifacts/)")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, help_ in (("fiber", "tabulate and draw the single-fiber model"),
                        ("bake", "trace the bundle and write the ground-truth table"),
                        ("train", "fit the neural models to the baked table"),
                        ("export", "write the models as ONNX and plain weights"),
                        ("report", "write the HTML report"),
                        ("run", "run every stage in order")):
        p = sub.add_parser(name, help=help_)
        p.add_argument("config", help="YAML config, e.g. configs/default.yaml")
    args = parser.parse_args(argv)

    from .config import ConfigError, load_config

    try:
        cfg = load_config(args.config)
        stages = [s for s in STAGES if s in ("fiber", "report") or cfg.bundle is not None] \
            if args.command == "run" else (args.command,)
        for stage in stages:
            _stage(stage).run(cfg, args.artifacts)
    except (ConfigError, ValueError, FileNotFoundError, FloatingPointError) as e:
        print(f"bcsdf {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bcsdf {args.command}: interrupted; earlier artifacts are intact", file=sys.stderr)
        return 130
    return 0


def _stage(name):
    import importlib
    return importlib.import_module(f"pipeline.{name}")


if __name__ == "__main__":
    sys.exit(main())
