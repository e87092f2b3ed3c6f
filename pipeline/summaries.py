"""The stages' records, ``artifacts/<name>/<stage>/summary.json``: one typed schema per
stage, written and read through it.

Every field is checked when a summary is written and when it is read: a summary that does
not hold its stage's schema (written by other code, or edited) is refused by its path, with
the command that writes it again (:class:`StaleSummary`). Readers use attributes, never
string keys; the nested records of the render and cloth stages (per scene, per backend) are
plain dictionaries of figures.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import ClassVar, Optional

from pydantic import BaseModel, ConfigDict, ValidationError

from models.io import write_text


class StaleSummary(ValueError):
    """A summary that its stage's schema refuses: rebuild it."""


class Summary(BaseModel):
    """One stage's summary; ``STAGE`` names the ``bcsdf`` command that writes it."""

    model_config = ConfigDict(extra="forbid")
    STAGE: ClassVar[str]

    def write(self, path: Path) -> None:
        write_text(path, self.model_dump_json(indent=1))

    @classmethod
    def read(cls, path: Path, config: str = "CONFIG"):
        """The summary at ``path``, checked; :class:`StaleSummary` naming the rebuild command."""
        try:
            return cls.model_validate(json.loads(Path(path).read_text()))
        except (ValidationError, json.JSONDecodeError, UnicodeDecodeError) as e:
            first = e.errors()[0] if isinstance(e, ValidationError) else {"loc": (), "msg": str(e)}
            where = ".".join(str(k) for k in first["loc"]) or "the file"
            raise StaleSummary(f"{path}: not a {cls.STAGE} summary of this code ({where}: {first['msg']}); "
                               f"rebuild it with `bcsdf {cls.STAGE} {config} --force`") from None


class FiberSummary(Summary):
    STAGE: ClassVar[str] = "fiber"
    model: str
    config_hash: str
    tabulate_seconds: float
    theta_i_deg: list[float]
    wavelength_nm: list[float]
    shape: dict[str, list[int]]           # each lobe's table shape
    energy: list[list[float]]             # albedo per (theta_i, wavelength)
    extinction_ratio: Optional[list[list[float]]]


class Reductions(BaseModel):
    """The bake's symmetry reductions and what they save: sizes and times with and without."""

    model_config = ConfigDict(extra="forbid")
    used: dict[str, Optional[str]]
    reduced_bytes: int
    full_bytes: int
    reduced_seconds: float
    full_seconds: float
    reduced_incidences: list[int]
    full_incidences: list[int]
    probe_paths: int


class BakeSummary(Summary):
    STAGE: ClassVar[str] = "bake"
    config_hash: str
    exit: str
    bake_seconds: float
    tracing_cpu_seconds: float
    paths: int
    vertices: int
    vertices_per_second: float
    n_fibers: int
    packing_fraction: float
    # the energy balance, each the mean over incidence and wavelength
    scattered: float
    passthrough: float
    absorbed: float
    lost: float
    total: float
    max_abs_energy_error: float
    single_share: list[float]             # of the scattered light, what left after one fiber event, per wavelength
    scattered_mc_error: Optional[float]   # standard errors of the means, from the batches (None: one batch)
    passthrough_mc_error: Optional[float]
    reductions: Reductions


class TrainSummary(Summary):
    STAGE: ClassVar[str] = "train"
    val_weighted_loss: float
    relative_l1: float        # the held-out core's relative L1 (models.errors.core_l1)
    log_mae: float
    noise_ratio: float        # relative_l1 over table_noise_l1
    table_noise_l1: float     # the table's noise on the same bins (models.errors.noise_l1)
    folds: list[str]
    fold_chi2_per_dof: float
    samples: int
    epochs: int
    train_seconds: float
    parameters: int
    gain_values: int = 0      # the azimuthal gain's values (train.gain_azimuth_bins), stored beside the weights
    # the energy gain (absent without one)
    worst_albedo_error_before: Optional[float] = None
    worst_albedo_error_after: Optional[float] = None
    calibration_seconds: Optional[float] = None


class RenderSummary(Summary):
    STAGE: ClassVar[str] = "render"
    config_hash: str
    variant: str
    spp: int
    size: list[int]
    model: Optional[str]
    scenes: dict[str, dict]               # per scene: its description, exposure and each backend's figures
    mono_check: Optional[dict] = None
    explicit: Optional[dict] = None


class ClothSummary(Summary):
    STAGE: ClassVar[str] = "cloth"
    variant: str
    size: list[int]
    spp: int
    exit_split: str
    geometry: dict                        # the plies: counts, sizes, build time, overlap
    model: Optional[str]
    backends: dict[str, dict]             # per backend: seconds, mean radiance, FLIP against the reference
    exposure: float
    flyaways: Optional[dict] = None


class FamilySummary(Summary):
    STAGE: ClassVar[str] = "family"
    config_hash: str
    model: str                            # the train.models size that is the network
    hidden: list[int]
    parameters: int
    parameter_bytes: int                  # weights.npz's float32 arrays
    orders: int                           # the orders of scattering the model holds (0: none)
    epochs: int
    train_seconds: float
    trained: list[float]                  # packings trained on
    held_out: list[float]
    members: int
    rows: list[dict]                      # per packing: its set and figures (pipeline.family.measure)
    renders: list[dict]                   # per held-out packing: the yarn, model against the seeds' mean table
