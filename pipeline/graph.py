"""The stage graph, declared once in ``dvc.yaml`` and read by ``bcsdf run`` too.

Each stage of ``dvc.yaml`` is a ``foreach`` template over the configs; its ``deps`` are
the code it runs and the artifacts it reads, its ``params`` the config sections it
depends on, its ``outs`` and ``metrics`` what it writes. ``bcsdf run`` instantiates the
same template for a config's name, so the two tools share one notion of up to date:

    fingerprint = sha256(the stage's config sections, as validated (defaults and --set
                  included), the bytes of every code file and every input artifact)

A stage is up to date when its stamp (``artifacts/<name>/.stamps/<stage>.json``) holds
the current fingerprint and every output it recorded is still there, byte for byte.
Every ``bcsdf`` stage command writes its stamp when it succeeds (also when DVC ran it).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
import logging
import os
from pathlib import Path

import yaml

from models.io import write_text

from .artifacts import config_dir
from .loading import PATH_KEYS

ROOT = Path(__file__).resolve().parents[1]
DVC_YAML = ROOT / "dvc.yaml"
SKIP = ("__pycache__", ".stamps")


def dvc_yaml() -> dict:
    """``dvc.yaml``, parsed once per version of its text (a run reads a stage's spec a dozen
    times: its fingerprint before and after, its stamp, the estimate). Read-only: shared."""
    return _parse(DVC_YAML.read_text())


@functools.lru_cache(maxsize=4)
def _parse(text: str) -> dict:
    # libyaml's loader where PyYAML has it: ten times faster on this file
    return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def run_stage(stage: str, cfg, root="artifacts", **options):
    """Run ``stage``'s command for ``cfg`` (what ``bcsdf STAGE`` runs, less its stamp).

    The one way to a stage from outside it: the CLI, and the stages that run others (the
    sweep's members, the stability stage's stiff model) call it, so no stage imports
    another (tests/test_layout.py)."""
    return stage_module(stage).run(cfg, root, **options)


def stage_module(stage: str):
    """``pipeline.stages.<stage>``, imported when it runs (a stage loads no other's code)."""
    return importlib.import_module(f"pipeline.stages.{stage}")


def template(stage: str, cfg) -> str:
    """The ``dvc.yaml`` stage that runs ``stage`` for this config (reports differ by kind)."""
    if stage == "report" and cfg.bundle is None:
        return "report_fiber"
    if stage == "report" and cfg.cloth is not None:
        return "report_cloth"  # it reads the cloth stage's pictures too
    if stage == "report" and cfg.family is not None:
        return "report_family"  # it reads the family stage's too
    return stage


def spec(stage: str, cfg, root="artifacts") -> dict:
    """``{"code": [...], "inputs": [...], "params": [...], "outs": [...]}`` of one stage for
    this config, paths resolved (code against the repository, artifacts under ``root``)."""
    try:
        stages = dvc_yaml()["stages"]
        do = stages[template(stage, cfg)]["do"]
    except (OSError, KeyError, TypeError, yaml.YAMLError) as e:
        raise ValueError(f"{DVC_YAML}: no usable stage {template(stage, cfg)!r} ({e}); "
                         "restore dvc.yaml from the repository") from None

    def path(p: str) -> Path:
        p = p.replace("${item}", cfg.name)
        return Path(root) / p.removeprefix("artifacts/") if p.startswith("artifacts/") else ROOT / p

    def names(entries):
        return [next(iter(e)) if isinstance(e, dict) else e for e in entries or []]

    deps = names(do.get("deps"))
    params = [key for entry in do.get("params") or [] for keys in entry.values() for key in keys]
    return {"code": [path(d) for d in deps if not d.startswith("artifacts/")],
            "inputs": [path(d) for d in deps if d.startswith("artifacts/")],
            "params": params,
            "outs": [path(o) for o in names(do.get("outs")) + names(do.get("metrics"))]}


def _files(path: Path):
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file() and not any(s in p.parts for s in SKIP))
    return [path] if path.exists() else []


def digest(paths, relative_to: Path) -> str:
    """sha256 over the names and bytes of every file under ``paths`` (missing ones count)."""
    h = hashlib.sha256()
    for top in paths:
        files = _files(top)
        if not files:
            h.update(f"missing:{top}\n".encode())
        for f in files:
            h.update(str(f.relative_to(relative_to) if f.is_relative_to(relative_to) else f).encode())
            h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()


def fingerprint(stage: str, cfg, root="artifacts") -> str:
    s = spec(stage, cfg, root)
    settings = cfg.model_dump(mode="json")
    h = hashlib.sha256(json.dumps({k: settings.get(k) for k in s["params"]}, sort_keys=True).encode())
    h.update(digest(s["code"], ROOT).encode())
    h.update(digest(s["inputs"], Path(root)).encode())
    for path in named_files(settings, s["params"]):  # their bytes, wherever they lie
        h.update(hashlib.sha256(path.read_bytes()).digest() if path.is_file() else b"missing")
    return h.hexdigest()[:24]


def named_files(settings: dict, sections) -> list[Path]:
    """The files a config names in ``sections`` (``bundle.file``, ``fiber.table.path``,
    ``cloth.model``): part of a stage's identity by their content, not by their name, so that
    a user's own file rewritten in place makes the stage stale (DVC sees only the files
    dvc.yaml lists: those under data/)."""
    found = []
    for key in PATH_KEYS:
        node, parts = settings, key.split(".")
        if parts[0] not in sections:
            continue
        for part in parts:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, str) and node:
            found.append(Path(node))
    return found


def stamp_path(stage: str, cfg, root="artifacts") -> Path:
    """Where ``stage``'s stamp for this config lives (beside, not inside, its outputs)."""
    return config_dir(cfg, root) / ".stamps" / f"{stage}.json"


def stamp(stage: str, cfg, root="artifacts", seconds: float | None = None, work: float | None = None,
          probe: float | None = None) -> None:
    """Record that ``stage`` just ran for this config: its fingerprint, its outputs, and
    how long it took for how much ``work`` (``pipeline.estimate.work``, what the estimate
    scales from) at the machine's pace ``probe`` (``pipeline.estimate.probe``, if measured)."""
    outs = {str(p.relative_to(root)): digest([p], Path(root)) for p in spec(stage, cfg, root)["outs"]}
    record = {"fingerprint": fingerprint(stage, cfg, root), "outs": outs}
    if seconds is not None and work is not None:
        record.update(seconds=seconds, work=work)
        if probe is not None:
            record["probe"] = probe
    write_text(stamp_path(stage, cfg, root), json.dumps(record, indent=1))


def up_to_date(stage: str, cfg, root="artifacts") -> tuple[bool, str]:
    """Whether ``stage`` can be skipped, and why not."""
    path = stamp_path(stage, cfg, root)
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return False, "never ran"
    if record.get("fingerprint") != fingerprint(stage, cfg, root):
        return False, "its code, config or inputs changed"
    for out, d in record.get("outs", {}).items():
        if not _files(Path(root) / out):
            return False, f"{out} is gone"
        if digest([Path(root) / out], Path(root)) != d:
            return False, f"{out} changed since the stage wrote it"
    return True, ""


def dvc_stage(stage: str, cfg) -> str | None:
    """DVC's name for ``stage`` of this config (``report@default``), or ``None`` where
    ``dvc.yaml`` does not list the config for that stage."""
    name = template(stage, cfg)
    try:
        entry = dvc_yaml()
        items = entry["stages"][name]["foreach"]
        if isinstance(items, str):  # ${configs}: a list among the vars
            key = items.strip("${} ")
            items = next(v[key] for v in entry.get("vars", []) if isinstance(v, dict) and key in v)
    except (OSError, KeyError, TypeError, StopIteration, yaml.YAMLError):
        return None
    return f"{name}@{cfg.name}" if cfg.name in items else None


def record_dvc_lock(stages, cfg) -> str:
    """Record ``stages`` of this config in ``dvc.lock`` as DVC's own ``dvc commit`` does
    (hashes of their deps, params and outputs; the outputs go to DVC's cache), so that after
    ``bcsdf run`` ``dvc status`` agrees that they are up to date. For the shipped configs
    under the repository's ``artifacts/`` only (``bcsdf run`` calls it when the run had no
    ``--set`` and the default artifacts root). Returns what it did, in words."""
    targets = [t for t in (dvc_stage(s, cfg) for s in stages) if t]
    if not targets:
        return f"dvc.lock: {cfg.name} is not among dvc.yaml's configs; nothing recorded"
    try:
        from dvc.repo import Repo
    except ImportError:
        return ("dvc.lock not updated: DVC is not installed (`make setup` installs it; then `bcsdf run` "
                "again records the lock without re-running anything)")

    logging.getLogger("dvc").setLevel(logging.WARNING)
    with Repo(str(ROOT)) as repo:
        for target in targets:
            repo.commit(target, force=True)
    return f"dvc.lock: recorded {len(targets)} stages ({', '.join(targets)})"


def require(cfg, stages, root, command: str) -> None:
    """Refuse, naming ``command`` (what builds them), when ``stages`` have never finished for
    this config (no stamp): what a bench that reads their artifacts must have run first."""
    missing = [s for s in stages if not stamp_path(s, cfg, root).exists()]
    if missing:
        raise SystemExit(f"error: this benchmark reads the {', '.join(missing)} artifacts of "
                         f"{cfg.name!r} under {root}/, which do not exist yet; run `{command}` first")


def _owner(config_file, root) -> str:
    """A config file as the artifacts folder records it: relative to the folder that holds
    the artifacts root (a project moved or cloned elsewhere keeps its owners)."""
    return os.path.relpath(Path(config_file).resolve(), Path(root).resolve().parent)


def check_claim(cfg, config_file, stages, root="artifacts", force: bool = False) -> None:
    """Refuse to let ``config_file`` run ``stages`` where another config file of the same
    ``name:`` made artifacts from other settings (an hours-long bake among them): it would
    write over them. The owner is recorded in ``<root>/<name>/.config`` (:func:`record_claim`);
    ``force`` takes the folder over."""
    try:
        owner = (config_dir(cfg, root) / ".config").read_text().strip()
    except (OSError, UnicodeDecodeError):
        return
    mine = _owner(config_file, root)
    if not owner or owner == mine or force:
        return
    clash = []
    for stage in stages:
        try:
            made = json.loads(stamp_path(stage, cfg, root).read_text()).get("fingerprint")
        except (OSError, ValueError):
            continue
        if made != fingerprint(stage, cfg, root):
            clash.append(stage)
    if clash:
        raise ValueError(f"{config_dir(cfg, root)} holds the artifacts of {owner} (its {', '.join(clash)} from "
                         f"other settings); {config_file} has the same name: and would write over them. Give it "
                         f"another name: (or run with --set name=...), or add --force to take the folder over")


def record_claim(cfg, config_file, root="artifacts") -> None:
    """Record ``config_file`` as the owner of its artifacts folder (after a stage of it
    finished there)."""
    record = config_dir(cfg, root) / ".config"
    mine = _owner(config_file, root)
    try:
        if record.read_text().strip() == mine:
            return
    except (OSError, UnicodeDecodeError):
        pass
    write_text(record, mine + "\n")
