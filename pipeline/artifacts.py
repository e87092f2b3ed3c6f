"""Where a config's artifacts live, and their checked loaders: one place.

Every stage reads its inputs through these loaders, which refuse an artifact that is
missing or was made from other settings than the config's, naming the file and what to
run.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from models.io import atomic_path

from .config import BAKE_SECTIONS, FIBER_SECTIONS


def config_dir(cfg, out_root="artifacts") -> Path:
    """``<out_root>/<config name>/``: everything one config makes."""
    return Path(out_root) / cfg.name


def stage_dir(cfg, stage: str, out_root="artifacts") -> Path:
    """``<out_root>/<config name>/<stage>/``: one stage's outputs (or a bench's, by its name)."""
    return config_dir(cfg, out_root) / stage


def checkpoint_path(cfg, model: str, out_root="artifacts") -> Path:
    """The trained model ``model`` (a size of ``train.models``)."""
    return stage_dir(cfg, "train", out_root) / model / "model.pt"


def fiber_table_path(cfg, out_root="artifacts") -> Path:
    return stage_dir(cfg, "fiber", out_root) / "fiber_table.npz"


def bundle_table_path(cfg, out_root="artifacts") -> Path:
    return stage_dir(cfg, "bake", out_root) / "bundle_table.npz"


def load_fiber_table(cfg, out_root="artifacts"):
    """The config's :class:`models.fiber.base.FiberTable`, checked."""
    # imported here: the stages that read only bundle tables run no fiber code (their deps)
    from models.fiber.base import FiberTable

    path = fiber_table_path(cfg, out_root)
    if not path.exists():
        raise ValueError(f"{path} does not exist; run `{cfg.command('fiber')}` (or `bcsdf run`) first")
    table = FiberTable.load(path)
    if table.meta.get("config_hash") != cfg.hash(*FIBER_SECTIONS):
        raise ValueError(f"{path} was made from different fiber settings than this config; "
                         "re-run `bcsdf fiber` with this config")
    return table


def load_bundle_table(cfg, out_root="artifacts") -> tuple:
    """The config's expanded :class:`models.bundle_table.BundleTable` and its path, checked."""
    # imported here: the stages that read no bundle table run none of its code (their deps)
    from models.bundle_table import BundleTable

    path = bundle_table_path(cfg, out_root)
    if not path.exists():
        raise ValueError(f"{path} does not exist; run `bcsdf bake` (or `bcsdf run`) with this config first")
    table = BundleTable.load(path, expand=True)
    if table.meta.get("config_hash") != cfg.hash(*BAKE_SECTIONS):
        raise ValueError(f"{path} was baked from different settings than this config; re-run `bcsdf bake`")
    return table, path


# -- a stage that failed: its reason and partial results, kept apart --------------------
class StageFailed(Exception):
    """A stage that ran to its end and found something wrong: ``partial`` maps file names
    to the text of its diagnosis (the stability stage's table), which is kept under
    :func:`failure_dir` while the stage's own outputs stay as they were."""

    def __init__(self, message: str, partial: dict | None = None):
        super().__init__(message)
        self.partial = partial or {}


def failure_dir(cfg, stage: str, out_root="artifacts") -> Path:
    """``<out_root>/<config name>/failed/<stage>/``: outside the stage's outputs (which a
    failed stage leaves as they were), so no up-to-date check or DVC hash sees it."""
    return config_dir(cfg, out_root) / "failed" / stage


def record_failure(cfg, stage: str, out_root, error: BaseException) -> Path | None:
    """Write why ``stage`` failed (``reason.txt``) and its partial results, outside the
    stage's journal so that they outlive its rollback; best effort (a full disk may be why
    it failed)."""
    folder = failure_dir(cfg, stage, out_root)
    files = {"reason.txt": str(error).strip() + "\n", **getattr(error, "partial", {})}
    try:
        for name, text in files.items():
            with atomic_path(folder / name, journaled=False) as tmp:
                Path(tmp).write_text(text)
    except OSError:
        return None
    return folder


def clear_failure(cfg, stage: str, out_root="artifacts") -> None:
    """A stage that succeeded has no failure on record."""
    shutil.rmtree(failure_dir(cfg, stage, out_root), ignore_errors=True)


def read_failure(cfg, stage: str, out_root="artifacts") -> str | None:
    """The recorded reason ``stage`` last failed, or None."""
    path = failure_dir(cfg, stage, out_root) / "reason.txt"
    try:
        return path.read_text().strip()
    except OSError:
        return None


def model_size(cfg) -> str:
    """The trained size the renders use: ``render.model``, or the widest of ``train.models``."""
    sizes = list(cfg.train.models)
    size = cfg.render.model or max(sizes, key=lambda s: sum(cfg.train.models[s]))
    if size not in cfg.train.models:
        raise ValueError(f"render.model: {size!r} is not one of the trained sizes {sizes}")
    return size
