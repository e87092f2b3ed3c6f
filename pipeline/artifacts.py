"""Where a config's artifacts live, and their checked loaders: one place.

Every stage reads its inputs through these loaders, which refuse an artifact that is
missing or was made from other settings than the config's, naming the file and what to
run.
"""

from __future__ import annotations

from pathlib import Path

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
        raise ValueError(f"{path} does not exist; run `bcsdf fiber {cfg.name}` (or `bcsdf run`) first")
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
