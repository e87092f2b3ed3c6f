"""``bcsdf``: one subcommand per pipeline stage, each driven by one config file.

    bcsdf fiber CONFIG     tabulate and draw the single-fiber model
    bcsdf bake CONFIG      trace the bundle, write the ground-truth table
    bcsdf train CONFIG     fit the MLP sizes of the config to the baked table
    bcsdf export CONFIG    write each trained model as ONNX and as plain weights
    bcsdf render CONFIG    render the bundle BSDF in Mitsuba: table, ONNX and jitted MLP
    bcsdf cloth CONFIG     render the config's yarn-level model (a .bcc file or a swatch)
    bcsdf stability CONFIG check finiteness, energy and references on stiff and extreme cases
    bcsdf sweep CONFIG     bake every member of the config's sweep, write the family page
    bcsdf family CONFIG    one model of the sweep's packings (the packing an input of it)
    bcsdf report CONFIG    one HTML page with the pictures and figures of every stage
    bcsdf render-scene SCENE.xml -o OUT.exr
                           render any Mitsuba XML scene with the plugins registered
    bcsdf run CONFIG       every stage in order, skipping those that are up to date
                           (code, config sections and input artifacts unchanged, outputs
                           intact: the same notion as DVC's, from dvc.yaml; --force reruns)

Errors in the config or the data print what is wrong and exit with status 2;
artifacts from earlier runs are left as they were.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

import matplotlib

from models.io import OBSTACLES, WRITE_ERRORS, confined, exclusive, journal, writable_folder

from . import estimate, graph
from .artifacts import StageFailed, clear_failure, config_dir, failure_dir, record_failure
from .config import ConfigError
from .loading import check_variants, load_config

EPILOG = """\
The config's keys are documented in configs/default.yaml and pipeline/config.py.
--set changes keys for one run without editing the file; the artifacts still go to
artifacts/<name>/ and carry the changed settings' hash, so later stages see the
change (a quick trial: --set name=trial keeps it apart from the real artifacts).
Errors print what is wrong and exit with status 2; earlier artifacts stay intact."""

STAGES = ("fiber", "bake", "train", "export", "render", "cloth", "stability", "sweep", "family", "report")


def main(argv=None) -> int:
    matplotlib.use("Agg")  # every picture is a file: no window, no display needed
    parser = argparse.ArgumentParser(prog="bcsdf", description=__doc__.split("\n\n")[0])
    parser.add_argument("--artifacts", default="artifacts", help="output root (default: artifacts/)")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, help_ in (("fiber", "tabulate and draw the single-fiber model"),
                        ("bake", "trace the bundle and write the ground-truth table"),
                        ("train", "fit the neural models to the baked table"),
                        ("export", "write the models as ONNX and plain weights"),
                        ("render", "render the bundle BSDF in Mitsuba (table, ONNX, jitted MLP)"),
                        ("cloth", "render the config's yarn-level model (cloth: a .bcc file or a swatch)"),
                        ("stability", "numerical stability on stiff and extreme cases"),
                        ("sweep", "bake every member of the config's sweep: section, write the family page"),
                        ("family", "train one model of the sweep's packings (family: section), measure it"),
                        ("report", "write the HTML report"),
                        ("run", "run every stage in order")):
        p = sub.add_parser(name, help=help_, description=f"bcsdf {name}: {help_}.", epilog=EPILOG,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.add_argument("config", help="YAML config, e.g. configs/default.yaml")
        p.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                       help="override a config key for this run (repeatable), e.g. "
                            "--set bake.paths_per_phi_i=20000 --set 'train.models={s: [16]}'")
        p.add_argument("--artifacts", default=argparse.SUPPRESS, help="output root (default: artifacts/)")
        p.add_argument("--force", action="store_true",
                       help=("rerun stages that are up to date; " if name == "run" else "")
                       + "take over the artifacts folder of another config file of the same name")
        if name in ("bake", "sweep", "run"):
            p.add_argument("--workers", type=int, default=None, metavar="N",
                           help="bake on a local Dask cluster of N single-threaded worker processes")
            p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                           help="bake on an existing Dask cluster (tcp://host:8786; or set BCSDF_SCHEDULER)")
    p = sub.add_parser("render-scene", help="render a Mitsuba XML scene with this project's plugins",
                       description="bcsdf render-scene: render any Mitsuba XML scene with fiber_bundle, fiber_table, "
                                   "fiber_ray and bundle_path registered (Mitsuba's own command cannot load them).")
    p.add_argument("scene", help="Mitsuba XML scene, e.g. scenes/ply.xml")
    p.add_argument("-o", "--output", required=True, help="the image: OUT.exr (and OUT.png beside it)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default: the scene's sampler)")
    p.add_argument("--variant", default="llvm_ad_spectral", help="Mitsuba variant (default llvm_ad_spectral)")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="set the scene's $NAME parameter (repeatable), as Mitsuba's -D")
    args = parser.parse_args(argv)
    if args.command == "render-scene":
        return _render_scene(args)
    if not sys.stderr.isatty():
        # a log file, not a terminal: one progress line per 30 s instead of per 0.1 s (a
        # default run wrote 7,000 lines); tqdm reads its defaults from TQDM_* variables
        os.environ.setdefault("TQDM_MININTERVAL", "30")
        os.environ.setdefault("TQDM_MAXINTERVAL", "60")

    try:
        with contextlib.ExitStack() as hold:
            _check_environment()
            cfg = load_config(args.config, args.overrides)
            check_variants(cfg)  # a cuda_* variant on a machine without a GPU: before any work

            hold.enter_context(confined(args.artifacts))  # no write leaves the artifacts root
            folder = writable_folder(config_dir(cfg, args.artifacts))  # before any long work, not after it
            hold.enter_context(exclusive(folder, f"bcsdf {args.command} {args.config}"))  # one writer per config
            _run(args, cfg)
    except (ConfigError, ValueError, FileNotFoundError, FloatingPointError, StageFailed) as e:
        print(f"bcsdf {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bcsdf {args.command}: interrupted; earlier artifacts are intact", file=sys.stderr)
        return 130
    except RuntimeError as e:
        if _interrupted(e):
            print(f"bcsdf {args.command}: interrupted; earlier artifacts are intact", file=sys.stderr)
            return 130
        reason = _write_error_in(e)
        if reason is None:
            raise
        # torch and Mitsuba raise a full disk as a RuntimeError whose text holds the OS's words
        print(f"bcsdf {args.command}: error: a write failed ({reason}): free some space, fix the folder's "
              "permissions or point --artifacts at another disk, then run again; earlier artifacts are intact, "
              "and a bake resumes from its last checkpoint", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno in OBSTACLES:
            print(f"bcsdf {args.command}: error: cannot write {e.filename} ({e.strerror}): something in the "
                  "artifacts folder is in the way (a folder where a file belongs, a file where a folder belongs, "
                  "a link loop); move it aside and run again; earlier artifacts are intact", file=sys.stderr)
            return 2
        if e.errno not in WRITE_ERRORS:
            raise
        print(f"bcsdf {args.command}: error: cannot write {e.filename} ({e.strerror}): free some space, fix the "
              "folder's permissions or point --artifacts at another disk, then run again; earlier artifacts are "
              "intact, and a bake resumes from its last checkpoint", file=sys.stderr)
        return 2
    return 0


def _write_error_in(e: Exception) -> str | None:
    """The OS's words for a write error (a full disk, a quota, a read-only disk, a file-size
    limit) if ``e``'s message holds them: how torch and Mitsuba report ENOSPC."""

    text = str(e)
    return next((os.strerror(code) for code in WRITE_ERRORS if os.strerror(code) in text), None)


def _address(value: str) -> str:
    """A Dask scheduler address: ``protocol://host[:port]``."""
    protocol, _, where = value.partition("://")
    if not protocol.isalpha() or not where:
        raise ValueError(value)
    return value


ENVIRONMENT = {  # variables bcsdf reads, and what each must hold
    "TQDM_MININTERVAL": ("a number of seconds", float), "TQDM_MAXINTERVAL": ("a number of seconds", float),
    "BCSDF_SCHEDULER": ("a Dask scheduler address, e.g. tcp://host:8786", _address),
}


def _check_environment() -> None:
    """Environment variables with garbage in them are named, not a traceback later."""

    for name, (what, parse) in ENVIRONMENT.items():
        value = os.environ.get(name)
        if value is None or (name == "BCSDF_SCHEDULER" and not value):
            continue
        try:
            parse(value)
        except ValueError:
            raise ConfigError(f"the environment variable {name}={value!r} must be {what}; fix or unset it") from None


def _render_scene(args) -> int:
    from .render_scene import render_scene  # loaded for this command alone: the stages' deps stay their own

    if args.spp is not None and args.spp < 1:
        print(f"bcsdf render-scene: error: --spp must be at least 1 (got {args.spp})", file=sys.stderr)
        return 2
    try:
        render_scene(args.scene, args.output, args.spp, args.variant, args.defines)
    except (ValueError, FileNotFoundError, FloatingPointError) as e:
        print(f"bcsdf render-scene: error: {e}", file=sys.stderr)
        return 2
    return 0


def _run(args, cfg) -> None:
    """The stages ``args.command`` asks for (``run``: each that is not up to date).

    A stage that fails leaves its last good outputs, its reason and partial results under
    ``failed/<stage>/``; ``bcsdf run`` then still writes the report (which says so), records
    for DVC the stages that did finish, and raises the failure."""

    stages = [s for s in STAGES if _applies(s, cfg)] if args.command == "run" else (args.command,)
    graph.check_claim(cfg, args.config, stages, args.artifacts, args.force)  # one config file per folder
    timings = {}
    if args.command == "run":
        todo = [s for s in stages if args.force or not graph.up_to_date(s, cfg, args.artifacts)[0]]
        if todo:
            print(estimate.plan(cfg, todo, args.artifacts), flush=True)
    finished, interrupted = [], False
    try:
        for stage in stages:
            if args.command == "run":  # asked again: an earlier stage may have rewritten this one's inputs
                fresh, why = graph.up_to_date(stage, cfg, args.artifacts)
                if fresh and not args.force:
                    print(f"[run] {stage}: up to date, skipped")
                    finished.append(stage)
                    continue
                print(f"[run] {stage}: {'forced' if fresh else why}", flush=True)
            timings[stage] = _run_stage(stage, args, cfg)
            graph.record_claim(cfg, args.config, args.artifacts)
            finished.append(stage)
    except KeyboardInterrupt:
        interrupted = True
        raise
    except Exception:
        stage = stages[len(finished)]
        print(f"[run] {stage} failed; its reason and partial results: "
              f"{failure_dir(cfg, stage, args.artifacts)}", file=sys.stderr, flush=True)
        if args.command == "run" and stage != "report" and "report" in stages:
            try:  # the report says what failed, with what finished
                graph.run_stage("report", cfg, args.artifacts)
            except Exception as e:  # the failure that stopped the run is the one to tell
                print(f"[run] the report could not be written either ({type(e).__name__}: {e})", file=sys.stderr)
        raise
    finally:
        if not interrupted:
            if args.command == "run" and timings:
                print(estimate.against_measured(cfg, timings), flush=True)
            _record_lock(args, cfg, finished)


def _run_stage(stage, args, cfg) -> float:
    """One stage, all or nothing; stamped when it succeeds, its failure kept apart when not."""

    t0 = time.perf_counter()
    shard = {k: getattr(args, k, None) for k in ("workers", "scheduler")} if stage in ("bake", "sweep") else {}
    try:
        # all or nothing (the sweep keeps each member as it finishes, as a bake keeps its checkpoint)
        with contextlib.nullcontext() if stage == "sweep" else journal(config_dir(cfg, args.artifacts)):
            graph.run_stage(stage, cfg, args.artifacts, **{k: v for k, v in shard.items() if v})
    except StageFailed as e:  # a stage that ran to its end and found something wrong: its diagnosis is kept
        record_failure(cfg, stage, args.artifacts, e)
        raise
    seconds = time.perf_counter() - t0
    graph.stamp(stage, cfg, args.artifacts, seconds=seconds, work=estimate.work(stage, cfg),
                probe=estimate.measured_probe())
    clear_failure(cfg, stage, args.artifacts)
    return seconds


def _record_lock(args, cfg, finished) -> None:
    """Record the finished stages of a shipped config in DVC's lock (one notion of up to
    date for both tools: what the lock would hold after ``dvc repro``)."""

    shipped = Path(args.config).resolve() == graph.ROOT / "configs" / f"{cfg.name}.yaml"
    if args.command == "run" and finished and shipped and not args.overrides \
            and Path(args.artifacts).resolve() == graph.ROOT / "artifacts":
        try:
            print(f"[run] {graph.record_dvc_lock(finished, cfg)}")
        except Exception as e:  # the lock is a convenience: never the error a user sees
            print(f"[run] dvc.lock not updated ({type(e).__name__}: {e})", file=sys.stderr)


def _applies(stage: str, cfg) -> bool:
    """Whether ``bcsdf run`` runs ``stage`` for this config (a fiber alone: no bake ...)."""
    if stage == "sweep":
        return bool(cfg.sweep)
    if stage == "family":
        return cfg.family is not None
    if stage == "cloth":
        return cfg.cloth is not None and cfg.bundle is not None
    return stage in ("fiber", "stability", "report") or cfg.bundle is not None


def _interrupted(exc) -> bool:
    """Whether Ctrl-C is behind ``exc``: Dr.Jit re-raises a KeyboardInterrupt that lands
    inside a traced loop (``dr.while_loop``) as a RuntimeError raised from it."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc = exc.__cause__ or exc.__context__
    return False



if __name__ == "__main__":
    sys.exit(main())
