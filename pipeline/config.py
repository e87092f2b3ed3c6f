"""One YAML config per scene: the schema, validated.

Unknown keys, missing required keys and out-of-range values are refused with a
message that names the key (``fiber.radius_um: must be > 0 (got -1)``). Every
stage reads the same :class:`Config`; its hash goes into every artifact's metadata.
Reading a file, ``--set`` and sweeps: :mod:`pipeline.loading`.
"""

from __future__ import annotations

import hashlib
import json
import math
import typing
from typing import Annotated, Any, Literal, Optional, Union

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, PrivateAttr, field_validator, model_validator

from models.grid import cone_bin_counts, cone_edges, cone_nodes

from .machine import check_memory

# Which config sections each stage's artifact depends on (its provenance hash)
FIBER_SECTIONS = ("wavelengths", "fiber", "tabulate")
BAKE_SECTIONS = FIBER_SECTIONS + ("bundle", "bake")
TRAIN_SECTIONS = BAKE_SECTIONS + ("train",)
RENDER_SECTIONS = TRAIN_SECTIONS + ("render",)
FAMILY_SECTIONS = TRAIN_SECTIONS + ("sweep", "family")


class ConfigError(ValueError):
    """A config that cannot be used; the message says which key and why."""


class Strict(BaseModel):
    # NaN and infinities are refused everywhere (a NaN passes every `k >= 0` check)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_booleans_as_numbers(cls, v, info):
        """YAML's ``true`` is not the number 1: a boolean where a number belongs is refused
        (pydantic's lax mode would read it as 1 or 1.0)."""
        if isinstance(v, bool):
            annotation = cls.model_fields[info.field_name].annotation
            kinds = set(typing.get_args(annotation)) or {annotation}
            if bool not in kinds and kinds & {int, float}:
                raise ValueError("must be a number, not a boolean (true/false)")
        return v


class Wavelengths(Strict):
    """The wavelengths the scene renders: ``count`` samples from start to stop (nm)."""

    start_nm: float = Field(400.0, ge=200, le=2000)
    stop_nm: float = Field(700.0, ge=200, le=2000)
    count: int = Field(25, ge=1, le=1000)

    @model_validator(mode="after")
    def _ordered(self):
        if self.count > 1 and self.stop_nm <= self.start_nm:
            raise ValueError(f"stop_nm ({self.stop_nm}) must exceed start_nm ({self.start_nm})")
        return self

    def grid(self):
        from models.spectrum import wavelength_grid
        return wavelength_grid(self.start_nm, self.stop_nm, self.count)


SpectralValue = Union[float, list[tuple[float, float]]]
Micrometres = Annotated[float, Field(le=1e5)]  # a length in the cross-section
Degrees = Annotated[float, Field(ge=-360, le=360)]


class IOR(Strict):
    """Complex index ``n + ik``: Cauchy ``n = A + B / lambda_um^2``; ``k`` constant or [[nm, k], ...]."""

    cauchy_a: float = Field(1.55, gt=1.0, le=4.0)
    cauchy_b_um2: float = Field(0.0, ge=0.0, le=0.1)
    k: SpectralValue = 0.0

    @field_validator("k")
    @classmethod
    def _k_nonnegative(cls, v):
        values = [v] if isinstance(v, (int, float)) else [k for _, k in v]
        if not all(math.isfinite(k) for k in values):
            raise ValueError("k must be finite (a number >= 0, or [[nm, k], ...])")
        if any(k < 0 for k in values):
            raise ValueError("the imaginary part k must be >= 0 (n + ik with k >= 0 absorbs)")
        if not isinstance(v, (int, float)):
            if any(not 200 <= nm <= 2000 for nm, _ in v):
                raise ValueError("wavelengths of k must lie in 200..2000 nm")
            if any(b[0] <= a[0] for a, b in zip(v, v[1:])):  # an unsorted table was read as k = 0
                raise ValueError(f"the [[nm, k], ...] rows of k must be in increasing nm, got "
                                 f"{[nm for nm, _ in v]}; sort them")
        return v


class MieParams(Strict):
    roughness_deg: float = Field(3.0, gt=0.0, le=45.0, description="std. dev. of the longitudinal lobe")
    zeta_min_deg: float = Field(1.0, gt=0.0, le=10.0)
    n_phi: Optional[int] = Field(None, ge=64, le=65536, description="azimuth samples (default: resolve diffraction)")


class RayParams(Strict):
    longitudinal_roughness: float = Field(0.3, gt=0.0, le=1.0)
    azimuthal_roughness: float = Field(0.3, gt=0.0, le=1.0)
    scale_tilt_deg: float = Field(2.0, ge=-15.0, le=15.0)
    n_h: int = Field(256, ge=8, le=8192)
    n_phi: int = Field(360, ge=36, le=65536)
    lobes: int = Field(3, ge=3, le=32, description="paths kept explicit before the residual (3: Chiang's R, TT, TRT)")
    transport: Literal["light", "camera"] = Field(
        "light", description="which side the model's incident quantities belong to: light (d'Eon/Chiang, conserves "
                             "energy) or camera (what Mitsuba's path tracer renders of its hair BSDF; bake it with "
                             "bake.exit: curve to compare with explicit hair fibers on curves; models/fiber/ray.py)")


class TableParams(Strict):
    path: str
    format: Literal["xia2023", "npz"]
    albedo: float = Field(1.0, gt=0.0, le=1.0)


class PatternParams(Strict):
    n_stripes_theta: int = Field(6, ge=1, le=90)
    n_stripes_phi: int = Field(8, ge=1, le=180)
    albedo: float = Field(1.0, gt=0.0, le=1.0)
    n_phi: int = Field(720, ge=36, le=65536)


class Fiber(Strict):
    model: Literal["mie", "ray", "table", "grid", "isotropic"]
    radius_um: float = Field(20.0, gt=0.0, le=1e4)
    ior: IOR = IOR()
    mie: MieParams = MieParams()
    ray: RayParams = RayParams()
    table: Optional[TableParams] = None
    pattern: PatternParams = PatternParams()

    @model_validator(mode="after")
    def _table_given(self):
        if self.model == "table" and self.table is None:
            raise ValueError("model 'table' needs a 'table:' block with path and format")
        return self


def theta_nodes(nodes_deg, negative: bool = False, poles: bool = True) -> np.ndarray:
    """A bake's incident longitudes (radians) from its nodes ``0..90`` deg
    (:meth:`BakeCfg.theta_i_nodes_deg`): ``0..90`` deg, or ``-90..90`` with ``negative``;
    ``poles=False`` leaves out +-90 deg (a twisted ply's)."""
    half = np.deg2rad(np.asarray(nodes_deg, np.float64))
    nodes = np.concatenate([-half[::-1][half[::-1] > 0], half]) if negative else half
    return nodes if poles else nodes[np.abs(nodes) < np.pi / 2 - 1e-9]


class Tabulate(Strict):
    theta_i_step_deg: float = Field(5.0, gt=0.0, le=90.0)

    def theta_i(self) -> np.ndarray:
        """The single-fiber table's incident longitudes (radians), 0..90 deg."""
        return np.deg2rad(np.arange(0.0, 90.0 + 1e-9, self.theta_i_step_deg))

    @field_validator("theta_i_step_deg")
    @classmethod
    def _divides_90(cls, v):
        if abs(90.0 / v - round(90.0 / v)) > 1e-9:
            raise ValueError(f"must divide 90 evenly (got {v})")
        return v


class MigrationCfg(Strict):
    """Fiber migration as Zhao et al. 2016's (``models.bundle.Migration``): each fiber's
    distance from the axis moves between ``r_min`` and 1 times its nominal one, ``s``
    cycles per turn, with a phase of its own (drawn from ``bundle.seed``)."""

    r_min: float = Field(gt=0.0, le=1.0, description="innermost position, a fraction of the nominal distance")
    s: float = Field(gt=0.0, le=100.0, description="migration cycles per turn (a fraction p/q, q <= 20)")


class TwistCfg(Strict):
    """Fibers twisted about the ply's axis (a twisted ply, baked in 3D: models/bake/twisted.py).

    ``pitch_um``: the axial length of one turn, signed as Zhao et al. 2016's alpha (> 0 a
    right-handed helix, a Z twist; < 0 an S twist), in micrometres like every length of the
    cross-section. Or ``yarn``: a Zhao 2016 yarn of data/zhao2016_table2.csv whose pitch is
    scaled with the ply (pitch = alpha x the bundle radius / the yarn's e_X), so that the
    outer fibers lean as in that yarn.

    ``migration``: ``true`` takes the yarn's ``R_min`` and ``s`` (with ``yarn``), or give
    ``{r_min, s}``; absent or ``false``, the fibers keep their distance from the axis. The
    cross-section is then spaced so that migrating fibers clear each other (``pipeline.build``),
    as is an elliptical one's (``shape: ellipse``: the ellipse stays, its fibers turn through it).
    """

    pitch_um: Optional[float] = Field(None, description="signed pitch (um); > 0 right-handed. Bounded at the bake "
                                      "by the geometry: at most where float32 cylinders misplace the fibers by 1% "
                                      "of a radius (~5e6 radii), at least where one period's cylinders fit in memory")
    yarn: Optional[str] = None
    migration: Union[bool, MigrationCfg] = False

    @model_validator(mode="after")
    def _one_source(self):
        if (self.pitch_um is None) == (self.yarn is None):
            raise ValueError("bundle.twist: give either pitch_um (signed, um) or yarn (a Zhao 2016 yarn), not both")
        if self.pitch_um is not None and not (abs(self.pitch_um) >= 1.0):
            raise ValueError(f"bundle.twist.pitch_um: {self.pitch_um} um; the pitch must be a non-zero length "
                             "(at least 1 um either way); leave bundle.twist out for parallel fibers")
        if self.migration is True and self.yarn is None:
            raise ValueError("bundle.twist.migration: true takes R_min and s from a Zhao 2016 yarn "
                             "(bundle.twist.yarn); with pitch_um give them directly: migration: {r_min: 0.8, s: 1.1}")
        if not isinstance(self.migration, bool):
            from models.bundle import Migration
            Migration(self.migration.r_min, self.migration.s)  # s must repeat within a few turns
        return self

    def pitch(self, bounding_radius_um: float) -> float:
        """The signed pitch in micrometres for a ply of this bounding radius."""
        if self.pitch_um is not None:
            return float(self.pitch_um)
        from models.bundle import zhao2016_row
        row = zhao2016_row(self.yarn)
        return float(row["alpha"]) * 1e4 * bounding_radius_um / row["eX_um"]

    def migration_model(self, seed: int):
        """The :class:`models.bundle.Migration` this asks for, or ``None``."""
        from models.bundle import Migration, zhao2016_row
        if self.migration is False:
            return None
        if self.migration is True:
            row = zhao2016_row(self.yarn)
            return Migration(float(row["Rmin"]), float(row["s"]), seed)
        return Migration(self.migration.r_min, self.migration.s, seed)


class BundleCfg(Strict):
    """The fiber arrangement in the cross-section (radii from ``fiber.radius_um``)."""

    arrangement: Literal["poisson", "file", "zhao2016"] = "poisson"
    shape: Literal["circle", "ellipse"] = "circle"
    radius_um: Optional[float] = Field(None, gt=0.0, le=1e5, description="circle radius")
    semi_axes_um: Optional[tuple[Micrometres, Micrometres]] = Field(None, description="ellipse (major on x, minor on z)")
    gap_um: float = Field(0.0, ge=0.0, le=1e4)
    packing: Optional[float] = Field(None, gt=0.0, lt=0.91)
    file: Optional[str] = None
    yarn: Optional[str] = None
    seed: int = Field(1, ge=0, le=2**32 - 1)
    twist: Optional[TwistCfg] = None

    @model_validator(mode="after")
    def _consistent(self):
        if self.arrangement == "zhao2016":
            if not self.yarn:
                raise ValueError("arrangement 'zhao2016' needs 'yarn' (e.g. 'Cotton 1')")
            return self
        if self.shape == "circle" and self.radius_um is None:
            raise ValueError("a circular bundle needs 'radius_um'")
        if self.shape == "ellipse":
            if self.semi_axes_um is None:
                raise ValueError("an elliptical bundle needs 'semi_axes_um: [a, b]'")
            a, b = self.semi_axes_um
            if not (a > 0 and b > 0):
                raise ValueError(f"semi_axes_um must be positive (got {a}, {b})")
        if self.arrangement == "file" and not self.file:
            raise ValueError("arrangement 'file' needs 'file' (a CSV with x_um, z_um, r_um)")
        return self

    def semi_axes(self):
        """The bounding ellipse (um); a Zhao 2016 ply's from its row of the CSV."""
        if self.arrangement == "zhao2016":
            from models.bundle import zhao2016_row
            row = zhao2016_row(self.yarn)
            return (row["eX_um"], row["eY_um"])
        return (self.radius_um, self.radius_um) if self.shape == "circle" else tuple(self.semi_axes_um)

    def bounding_radius_um(self) -> float:
        """Radius of the circle around the bundle: the cylinder a ply renders as, the bake's beam."""
        return float(max(self.semi_axes()))


# The variants each stage can run: the baker traces every wavelength at once in a mono
# variant; renders need a colour variant (a mono one failed every render, the scalar ones
# cannot run the vectorized plugins). cuda_* need a GPU: `bcsdf` checks for one before work.
BAKE_VARIANTS = ("llvm_ad_mono", "cuda_ad_mono")
RENDER_VARIANTS = ("llvm_ad_rgb", "llvm_ad_spectral", "cuda_ad_rgb", "cuda_ad_spectral")


class BakeCfg(Strict):
    """The ground-truth path tracer (see models/bake/baker.py)."""

    estimator: Literal["fast", "thesis", "camera"] = Field(
        "fast", description="fast: paths of light carrying every theta_i; thesis: the thesis's baseline; camera: a "
                            "ray fiber of camera transport traced from the camera, as Mitsuba's path tracer renders "
                            "explicit hair fibers (the curve exit's table with far less noise in a ply)")
    paths_per_phi_i: int = Field(1_000_000, ge=1, le=10_000_000_000)
    batch_paths: int = Field(65536, ge=64, le=1 << 22)
    theta_i_step_deg: Optional[float] = Field(None, gt=0.0, le=90.0,
                                              description="incident longitudes every this many deg (10 if "
                                                          "neither this nor theta_i_deg is given)")
    theta_i_deg: Optional[list[float]] = Field(
        None, description="the incident longitudes 0..90 deg themselves, instead of theta_i_step_deg: "
                          "graded nodes, e.g. finer near grazing (from 0, increasing; a list that stops short "
                          "of 90 holds its last node's light along its cone up to the pole)")
    phi_i_step_deg: float = Field(15.0, gt=0.0, le=90.0, description="ellipse only")
    n_theta_o: int = Field(36, ge=2, le=3600)
    n_phi_o: int = Field(72, ge=4, le=7200)
    theta_o_layout: Literal["uniform", "cone"] = Field(
        "uniform", description="theta_o bins: n_theta_o equal bins, or a narrow bin on every node's specular cone "
                               "and equal bins between (models.grid.cone_edges)")
    cone_bin_deg: float = Field(2.0, gt=0.0, le=45.0, description="cone layout: the width of the bin on each cone")
    max_bounces: int = Field(1000, ge=1, le=1_000_000)
    rr_start: int = Field(8, ge=1)
    exit: Literal["auto", "uniform", "entry", "lobe", "curve"] = Field(
        "auto", description="where scattered light leaves a fiber (models/bake/baker.py); auto: lobe for ray fibers "
                            "of light transport, curve for those of camera transport, else uniform")
    orders: int = Field(
        0, ge=0, le=64, description="keep the orders of scattering apart (paths of 1 .. K-1 fiber events and the "
                                    "tail of K and more): 0 none, else K >= 2. The table can then be recoloured "
                                    "with a dye (BundleTable.recolour, fiber_bundle's albedo); 8 is plenty "
                                    "(docs/DESIGN.md, Order-resolved tables)")
    offsets: int = Field(
        0, ge=0, le=64, description="the near field: keep the light also by the cell of its exit offset across the "
                                    "ply (N equal cells of h in [-1, 1]) and the passthrough by the entry offset; 0 "
                                    "none. Circular plies (docs/DESIGN.md, Near-field tables)")
    seed: int = Field(1, ge=0, le=2**32 - 1)
    variant: Literal[BAKE_VARIANTS] = "llvm_ad_mono"
    checkpoint_every_s: float = Field(20.0, gt=0.0)

    @field_validator("theta_i_step_deg", "phi_i_step_deg")
    @classmethod
    def _divides_90(cls, v):
        if v is not None and abs(90.0 / v - round(90.0 / v)) > 1e-9:
            raise ValueError(f"must divide 90 evenly (got {v})")
        return v

    @field_validator("theta_i_deg")
    @classmethod
    def _graded_nodes(cls, v):
        if v is None:
            return v
        t = np.asarray(v, float)
        if len(t) < 2 or t[0] != 0.0 or t[-1] > 90.0 or np.any(np.diff(t) <= 0):
            raise ValueError(f"must run from 0 up to at most 90 deg, increasing, with at least two nodes (got {v}), "
                             "e.g. [0, 15, 30, 45, 60, 65, 70, 75, 80, 85, 87.5]")
        return [float(x) for x in t]

    @model_validator(mode="after")
    def _one_node_rule(self):
        if self.theta_i_deg is not None and self.theta_i_step_deg is not None:
            raise ValueError("theta_i_deg and theta_i_step_deg both set: give the nodes or their step, not both "
                             "(e.g. --set bake.theta_i_deg=null with a step)")
        return self

    @property
    def theta_i_step(self) -> float:
        """The step of the incident longitudes (deg) when they are not listed."""
        return 10.0 if self.theta_i_step_deg is None else self.theta_i_step_deg

    def theta_i_nodes_deg(self) -> np.ndarray:
        """The incident longitudes ``0..90`` deg: ``theta_i_deg``, else every :attr:`theta_i_step`."""
        if self.theta_i_deg is not None:
            return np.asarray(self.theta_i_deg, float)
        # clipped: the arange's last node can pass 90 by a rounding error
        return np.clip(np.arange(0.0, 90.0 + 1e-9, self.theta_i_step), 0.0, 90.0)

    def theta_i_said(self) -> str:
        """The incident longitudes in words, for messages and the report."""
        if self.theta_i_deg is None:
            return f"every {self.theta_i_step:g} deg"
        return "at " + ", ".join(f"{t:g}" for t in self.theta_i_deg) + " deg"

    @property
    def n_batches(self) -> int:
        """Batches per incident azimuth (the last one holds the remainder)."""
        return -(-self.paths_per_phi_i // self.batch_paths)

    def batch_size(self, k: int) -> int:
        return min(self.batch_paths, self.paths_per_phi_i - k * self.batch_paths)

    def phi_i(self, circle: bool) -> np.ndarray:
        """Incident azimuths (radians): one for a circle (rotation), else 0..90 deg (the
        ellipse's mirrors give the rest)."""
        return np.zeros(1) if circle else np.deg2rad(np.arange(0, 90 + 1e-9, self.phi_i_step_deg))

    @field_validator("n_phi_o")
    @classmethod
    def _even(cls, v):
        if v % 2:
            raise ValueError(f"must be even so that the symmetry mirrors map bins onto bins (got {v})")
        return v

    @model_validator(mode="after")
    def _theta_o_bins(self):
        if self.theta_o_layout == "uniform" and self.n_theta_o % 2:
            raise ValueError(f"n_theta_o: must be even so that the symmetry mirrors map bins onto bins (got "
                             f"{self.n_theta_o}), or use theta_o_layout: cone")
        if self.theta_o_layout == "cone":
            nodes = np.deg2rad(self.theta_i_nodes_deg())
            counts = cone_bin_counts(nodes)
            if self.n_theta_o not in counts:
                raise ValueError(f"n_theta_o: {self.n_theta_o} bins cannot follow the cones of theta_i nodes "
                                 f"{self.theta_i_said()}; "
                                 f"a cone layout has {', '.join(map(str, counts[:4]))}, ... bins (a cone bin per "
                                 "node and equal bins between)")
            narrowest = float(np.rad2deg(np.diff(cone_nodes(nodes)).min()))
            if self.cone_bin_deg >= narrowest:
                raise ValueError(f"cone_bin_deg: {self.cone_bin_deg:g} must be narrower than the narrowest step "
                                 f"between theta_i nodes ({narrowest:g} deg)")
        return self

    def theta_o_edges(self) -> np.ndarray:
        """The bake's theta_o bin edges (radians)."""
        if self.theta_o_layout == "uniform":
            return np.linspace(-np.pi / 2, np.pi / 2, self.n_theta_o + 1)
        nodes = np.deg2rad(self.theta_i_nodes_deg())
        per_gap = (self.n_theta_o + 1) // (len(cone_nodes(nodes)) - 1) - 1
        return cone_edges(nodes, np.deg2rad(self.cone_bin_deg), per_gap)


class TrainCfg(Strict):
    """Neural compression of the bundle table (see models/fit.py)."""

    models: dict[str, list[int]] = Field(default_factory=lambda: {
        "small": [32, 32], "medium": [64, 64, 64], "large": [128, 128, 128]})
    # the schedule: cosine decay from lr over the epochs (pipeline/bench/train.py measures it
    # against the earlier 1500 epochs at 3e-3, docs/BENCHMARKS.md)
    epochs: int = Field(500, ge=1, le=100_000)
    batch_size: int = Field(1024, ge=16, le=1 << 20)
    lr: float = Field(1e-2, gt=0.0, le=1.0)
    patience: int = Field(100, ge=1, le=100_000, description="epochs without a better held-out loss before stopping")
    val_fraction: float = Field(0.1, gt=0.0, lt=0.9)
    sigma_floor: float = Field(0.02, gt=0.0, le=1.0, description="log-space noise floor of the loss weights")
    bin_strata: int = Field(2, ge=1, le=8,
                            description="k: the model's mean over k x k stratified points of a bin is fitted")
    energy_gain: bool = Field(True, description="scale the model per incident longitude and wavelength so that "
                              "each incidence's albedo is the table's (models.fit.energy_gain)")
    gain_azimuth_bins: int = Field(
        0, ge=0, le=720, description="resolve the energy gain by azimuth too: this many equal bins of |phi_o - phi_i| "
                                     "over [0, pi] (dividing the table's; 0: none; models.neural.azimuth_gain), so "
                                     "the model keeps the spectra's ripple from one azimuth bin to the next")
    gain_rank: int = Field(
        0, ge=0, le=64, description="store the azimuthal gain (train.gain_azimuth_bins) as a product of this rank in "
                                    "log space: a few spectral shapes and each class's mix of them "
                                    "(models.fit.low_rank_log); 0: every value")
    seed: int = Field(0, ge=0, le=2**32 - 1)
    threads: int = Field(2, ge=1, le=256)
    line_nodes: list[Annotated[int, Field(ge=2, le=4096)]] = Field(
        default_factory=list, description="feature lines (models/lines.py): nodes of the theta_i, cone-distance and "
                                          "azimuth lines, e.g. [16, 32, 24]; [] for a plain MLP")
    line_channels: int = Field(8, ge=1, le=256, description="channels of each feature line")
    encoding: Literal["cone", "cartesian", "halfdiff"] = Field(
        "cone", description="the directions' features (models/neural.py): cone, the project's; cartesian (w_i, w_o, "
                            "as neural yarn models) and halfdiff (Rusinkiewicz, as NBRDF) are the baselines that "
                            "make bench-encoding compares")
    inputs: list[Literal["offset"]] = Field(
        default_factory=list, description="extra inputs of the model beyond the directions: [offset] learns the near "
                                          "field (bake.offsets), the light by its exit line's offset across the ply")
    orders: bool = Field(False, description="learn the orders of scattering apart (bake.orders), so that the plugin "
                                            "dyes the model (fiber_bundle's albedo) as it dyes the table")

    @field_validator("line_nodes")
    @classmethod
    def _three_lines(cls, v):
        if v and len(v) != 3:
            raise ValueError(f"line_nodes needs three node counts (theta_i, cone distance, azimuth), got {v}")
        return v

    @field_validator("models")
    @classmethod
    def _sizes(cls, v):
        if not v:
            raise ValueError("at least one model size is needed, e.g. {small: [32, 32]}")
        for name, hidden in v.items():
            if not name.replace("_", "").isalnum():
                raise ValueError(f"model name {name!r} must be alphanumeric")
            if not hidden or any(h < 1 or h > 4096 for h in hidden):
                raise ValueError(f"model {name!r}: hidden widths must be 1..4096 (got {hidden})")
        return v


def _some_backends(v: list) -> list:
    """At least one backend, each once (in the order given)."""
    if not v:
        raise ValueError("at least one backend is needed, e.g. [table]")
    return list(dict.fromkeys(v))


Backends = Annotated[list[Literal["table", "mlp", "onnx"]], AfterValidator(_some_backends)]


class RenderCfg(Strict):
    """Mitsuba renders of the bundle BSDF (see pipeline/stages/render.py)."""

    variant: Literal[RENDER_VARIANTS] = Field("llvm_ad_spectral", description="Mitsuba variant of the renders")
    scenes: list[Literal["ply", "yarn"]] = Field(default_factory=lambda: ["ply", "yarn"])
    backends: Backends = Field(default_factory=lambda: ["table", "mlp", "onnx"])
    model: Optional[str] = Field(None, description="trained size for the neural backends (default: the largest)")
    width: int = Field(256, ge=8, le=8192)
    height: int = Field(128, ge=8, le=8192)
    spp: int = Field(64, ge=1, le=1 << 16)
    max_depth: int = Field(64, ge=1, le=100_000)
    twist_turns: float = Field(2.0, ge=-1000.0, le=1000.0, description="turns of the cross-section along the ply (ellipses)")
    yarn: str = Field("Polyester 1", description="row of zhao2016_table2.csv for the yarn scene")
    mono_check: bool = Field(True, description="spectral variant against mono renders per wavelength + CIE")
    mono_check_size: list[Annotated[int, Field(ge=4, le=4096)]] = Field(default_factory=lambda: [96, 48],
                                                                    min_length=2, max_length=2)
    mono_check_spp: int = Field(64, ge=1, le=1 << 16)
    explicit: bool = Field(True, description="render the ply with every fiber as its own curve (ground truth)")
    explicit_spp: int = Field(256, ge=1, le=1 << 16)


class Swatch(Strict):
    """A procedural stockinette swatch (models/cloth/knit.py) instead of a model file."""

    courses: int = Field(4, ge=1, le=1000)
    wales: int = Field(6, ge=1, le=1000)


class Flyaways(Strict):
    """Hair-type flyaways about the plies (models/cloth/flyaways.py, Zhao et al. 2016): explicit
    fibers with the single-fiber model, their fuzz. Loop-type flyaways are not drawn (see there)."""

    yarn: Optional[str] = Field(None, description="row of zhao2016_table2.csv (default: cloth.yarn)")
    density_scale: float = Field(1.0, ge=0.0, le=100.0, description="times the yarn's hairs per length")
    seed: int = Field(0, ge=0)
    curve: Literal["linearcurve", "bsplinecurve"] = Field(
        "linearcurve", description="a hair as a polyline through its samples (a third cheaper to render) or "
                                   "the B-spline through them (models/cloth/flyaways.py)")
    share_check_scale: float = Field(0.25, gt=0.0, le=1.0,
                                     description="image scale of the renders that measure the flyaways' "
                                                 "share of the radiance (with, without, floor only)")

    @field_validator("yarn")
    @classmethod
    def _known_yarn(cls, v):
        from models.bundle import zhao2016_row
        if v is not None:
            zhao2016_row(v)  # names the yarns there are
        return v


class ClothCfg(Strict):
    """A yarn-level model rendered with the bundle BSDF (bcsdf cloth; pipeline/stages/cloth.py).

    Units: the model file's own, times ``units_mm`` millimetres; the scene is in millimetres.
    """

    model: Optional[str] = Field(None, description="a .bcc yarn-level model (relative to the config's folder)")
    swatch: Optional[Swatch] = Field(None, description="or a procedural stockinette swatch")
    units_mm: float = Field(10.0, gt=0.0, le=1e6, description="millimetres per unit of the model file")
    curves: Optional[int] = Field(None, ge=1, description="render only the first N yarn curves")
    yarn: str = Field("Cotton 1", description="row of zhao2016_table2.csv: ply count, offset and pitch")
    yarn_radius_mm: float = Field(0.9, gt=0.0, le=1000.0)
    plies: Optional[int] = Field(None, ge=1, le=16, description="ply count (default: the Zhao yarn's)")
    ply_pitch_mm: Optional[float] = Field(None, description="one turn of the plies, signed (default: Zhao's, scaled)")
    tolerance: float = Field(0.01, gt=0.0, le=0.5, description="centre-line conversion, in yarn radii")
    rotate_deg: tuple[Degrees, Degrees, Degrees] = Field((0.0, 0.0, 0.0), description="about x, then y, then z")
    variant: Literal[RENDER_VARIANTS] = "llvm_ad_spectral"
    backends: Backends = Field(default_factory=lambda: ["table", "mlp"])
    width: int = Field(640, ge=8, le=8192)
    height: int = Field(480, ge=8, le=8192)
    spp: int = Field(16, ge=1, le=1 << 16)
    max_depth: int = Field(16, ge=1, le=100_000)
    exit_split: Literal["none", "emitter", "all"] = Field(
        "all", description="bundle_path's exit_split: a ply's singly scattered light leaves where it entered "
                           "(the plies' colour against explicit fibers: docs/BENCHMARKS.md, 'Cloth')")
    camera_azimuth_deg: float = Field(90.0, ge=-360.0, le=360.0, description="about the up axis, 0 = +z")
    camera_elevation_deg: float = Field(25.0, ge=-89.0, le=89.0)
    fov_deg: float = Field(30.0, gt=1.0, lt=170.0)
    framing: float = Field(1.0, gt=0.05, le=100.0, description="camera distance, in that of the bounding sphere")
    sun_azimuth_deg: float = Field(40.0, ge=-360.0, le=360.0)
    sun_elevation_deg: float = Field(35.0, gt=0.0, le=90.0)
    turbidity: float = Field(3.0, ge=1.0, le=10.0, description="of Mitsuba's sunsky emitter")
    ground: bool = Field(True, description="a diffuse floor under the model")
    ground_reflectance: float = Field(0.35, ge=0.0, le=1.0)
    flyaways: Optional[Flyaways] = Field(None, description="hair flyaways about the plies (absent: none)")

    @model_validator(mode="after")
    def _one_source(self):
        if (self.model is None) == (self.swatch is None):
            raise ValueError("give either cloth.model (a .bcc file) or cloth.swatch ({courses: 4, wales: 6}), "
                             "not both and not neither")
        if self.ply_pitch_mm is not None and not (1e-3 <= abs(self.ply_pitch_mm) <= 1e6):
            raise ValueError(f"cloth.ply_pitch_mm must be a length of 0.001 .. 1e6 mm, either sign "
                             f"(got {self.ply_pitch_mm})")
        return self

    @field_validator("yarn")
    @classmethod
    def _known_yarn(cls, v):
        from models.bundle import zhao2016_row
        zhao2016_row(v)  # names the yarns there are
        return v

    @field_validator("model")
    @classmethod
    def _readable_model(cls, v):
        """The model file is read here, before any stage works (a few ms for the glove)."""
        if v is not None:
            from models.cloth.bcc import read_bcc
            read_bcc(v)
        return v


class FamilyCfg(Strict):
    """One model of a sweep's plies with the packing fraction as an input (``bcsdf family``;
    pipeline/stages/family.py): trained on the sweep's members (every ``bundle.seed`` of a
    packing: the model learns their mean) and measured at each packing against the seeds'
    mean table, at ``held_out`` packings without having seen them."""

    model: Optional[str] = Field(None, description="which of train.models is the network (default: the first)")
    held_out: list[float] = Field(
        default_factory=list, description="packings of the sweep's bundle.packing axis measured but not trained on; "
                                          "each between two trained ones (the model does not extrapolate)")
    held_out_seeds: list[int] = Field(
        default_factory=list, max_length=100,
        description="more bundle.seed draws baked at each held-out packing, beside the sweep's seeds: the "
                    "truth there is the seeds' mean, whose own arrangement noise falls as 1/sqrt(seeds), and "
                    "an error measured against it cannot be told apart below that noise")
    strip: bool = Field(True, description="render the yarn of the render stage at five packings (and three dyes, "
                                          "with bake.orders) from the one model file")

    def holds_out(self, packing: float) -> bool:
        """Whether the sweep's ``packing`` is one of :attr:`held_out` (a float of the axis, to rounding)."""
        return any(np.isclose(packing, q) for q in self.held_out)


class ReportCfg(Strict):
    queries: int = Field(200_000, ge=1000, le=10_000_000, description="batch size of the timings")


MAX_FIBERS = 100_000  # in one bundle (the thesis plies hold about 1,200)
MAX_MEMBERS = 1000


class Config(Strict):
    # a folder name under artifacts/: no separators, and not '.' or '..'
    name: Optional[str] = Field(None, pattern=r"^[A-Za-z0-9_.-]+$", max_length=100)
    # how the user named this config on the command line (its file and --set), for advice
    _source: str = PrivateAttr(default="CONFIG")
    wavelengths: Wavelengths = Wavelengths()
    fiber: Fiber
    tabulate: Tabulate = Tabulate()
    bundle: Optional[BundleCfg] = None
    bake: BakeCfg = BakeCfg()
    train: TrainCfg = TrainCfg()
    render: RenderCfg = RenderCfg()
    cloth: Optional[ClothCfg] = None
    report: ReportCfg = ReportCfg()
    sweep: Optional[dict[str, list[Any]]] = Field(
        None, description="axes of a family of bakes: dotted key -> values (bcsdf sweep; pipeline/stages/sweep.py)")

    family: Optional[FamilyCfg] = Field(
        None, description="one model of the sweep's packings (bcsdf family; pipeline/stages/family.py)")

    @field_validator("sweep")
    @classmethod
    def _axes(cls, v):
        if v is None:
            return v
        if not v:
            raise ValueError("an empty sweep has no members: name at least one axis, e.g. "
                             "{bundle.packing: [0.3, 0.5]}, or leave out 'sweep:'")
        members = 1
        for key, values in v.items():
            if key.split(".")[0] in ("name", "sweep", "family"):
                raise ValueError(f"{key!r} cannot be swept (members are named after their axes)")
            if not values:
                raise ValueError(f"axis {key!r} has no values")
            if len({json.dumps(x, sort_keys=True) for x in values}) < len(values):
                raise ValueError(f"axis {key!r} repeats a value ({values})")
            members *= len(values)
        if members > MAX_MEMBERS:
            raise ValueError(f"{members:,} members (the product of the axes' lengths); at most {MAX_MEMBERS}")
        return v

    @field_validator("name")
    @classmethod
    def _not_dots(cls, v):
        if v is not None and set(v) == {"."}:
            raise ValueError(f"{v!r} would write outside artifacts/: use letters, digits, '_', '-' or '.'")
        return v

    def incidences(self, expanded: bool = False) -> tuple[int, int]:
        """``(n_phi_i, n_theta_i)`` of the bake: a circle is one azimuth (rotation), other
        bundles ``0..90`` deg; theta_i ``0..90`` deg, or ``-90..90`` once expanded (a twisted
        ply: ``-90..90`` without the poles, :func:`pipeline.build.make_spec`)."""
        b = self.bake
        circle = self.bundle.shape == "circle" and self.bundle.arrangement != "zhao2016"
        n_phi_i = len(b.phi_i(circle))
        twisted = self.bundle.twist is not None
        return n_phi_i, len(theta_nodes(b.theta_i_nodes_deg(), negative=expanded or twisted, poles=not twisted))

    @model_validator(mode="after")
    def _family_of_packings(self):
        """``family:`` trains on a sweep over ``bundle.packing`` (seeds beside it, nothing else:
        one ply type), holding out packings strictly inside the trained range."""
        f = self.family
        if f is None:
            return self
        axes = self.sweep or {}
        if "bundle.packing" not in axes or self.bundle is None:
            raise ValueError("family: a model of packings is trained on a sweep over them; add e.g. "
                             "sweep: {bundle.packing: [0.1, 0.2, 0.3], bundle.seed: [1, 2, 3]}, or drop family:")
        others = sorted(set(axes) - {"bundle.packing", "bundle.seed"})
        if others:
            raise ValueError(f"family: its sweep may vary bundle.packing and bundle.seed only (one ply type); "
                             f"{', '.join(others)} would change the ply itself: sweep them in another config")
        packings = axes["bundle.packing"]
        if not all(isinstance(p, (int, float)) and not isinstance(p, bool) for p in packings):
            raise ValueError(f"family: bundle.packing's values must be numbers (got {packings})")
        missing = [p for p in f.held_out if not any(np.isclose(p, q) for q in packings)]
        if missing:
            raise ValueError(f"family.held_out {missing}: not among the sweep's bundle.packing values {packings}; "
                             "a held-out packing is baked by the sweep and measured, not trained on")
        trained = sorted(p for p in packings if not f.holds_out(p))
        if len(trained) < 2:
            raise ValueError(f"family: {len(trained)} trained packing(s) ({trained}); a model of packings needs at "
                             "least two: add values to sweep.bundle.packing or hold fewer out")
        outside = [p for p in f.held_out if not trained[0] < p < trained[-1]]
        if outside:
            raise ValueError(f"family.held_out {outside}: outside the trained packings [{trained[0]}, {trained[-1]}]; "
                             "the model does not extrapolate: hold out packings between trained ones")
        if f.held_out_seeds:
            seeds = axes.get("bundle.seed")
            if seeds is None or not f.held_out:
                raise ValueError("family.held_out_seeds: more draws at the held-out packings need held-out packings "
                                 "(family.held_out) and a sweep over bundle.seed beside bundle.packing")
            again = sorted(set(f.held_out_seeds) & set(seeds)) or sorted(
                s for s in set(f.held_out_seeds) if f.held_out_seeds.count(s) > 1)
            if again:
                raise ValueError(f"family.held_out_seeds {again}: already drawn (sweep bundle.seed {seeds}, or named "
                                 "twice); name seeds that the sweep does not, e.g. "
                                 f"[{max(seeds) + 1}, {max(seeds) + 2}, ...]")
        if f.model is not None and f.model not in self.train.models:
            raise ValueError(f"family.model: {f.model!r} is not one of train.models {sorted(self.train.models)}")
        t = self.train
        if t.inputs or t.orders or t.encoding != "cone" or t.line_nodes or t.gain_azimuth_bins:
            raise ValueError("family: the family's model takes the packing as its input and the orders of scattering "
                             "where the sweep bakes them (bake.orders); leave train.inputs, train.orders, "
                             "train.line_nodes and train.gain_azimuth_bins unset and train.encoding: cone")
        return self

    @model_validator(mode="after")
    def _render_model_is_trained(self):
        """``render.model`` names one of ``train.models`` (checked before any work, not at render)."""
        m = self.render.model
        if self.bundle is not None and m is not None and m not in self.train.models:
            raise ValueError(f"render.model: {m!r} is not one of train.models {sorted(self.train.models)}; "
                             f"set render.model to one of them (e.g. --set render.model={next(iter(self.train.models))})")
        return self

    @model_validator(mode="after")
    def _exit_fits_fiber(self):
        """The h-resolved exit knows the paths of a ray fiber only; every exit but the uniform
        one needs the fast estimator."""
        b = self.bake
        if b.exit == "lobe" and self.fiber.model != "ray":
            raise ValueError(f"bake.exit: lobe needs fiber.model: ray (got {self.fiber.model!r}); use auto, "
                             "uniform or entry")
        if b.exit == "lobe" and self.fiber.ray.transport == "camera":
            raise ValueError("bake.exit: lobe resolves the paths of light transport; fiber.ray.transport: camera "
                             "is tabulated h-averaged: use auto (curve), curve, uniform or entry")
        if b.orders == 1:
            raise ValueError("bake.orders: 0 (none) or K >= 2 (orders 1 .. K-1 and the tail); 1 would be the "
                             "whole table")
        if b.orders and b.estimator != "fast":
            raise ValueError("bake.orders needs bake.estimator: fast")
        if b.offsets == 1 or (b.offsets and (b.orders or b.estimator != "fast")):
            raise ValueError("bake.offsets: 0 (none) or N >= 2 cells, with bake.estimator: fast and without "
                             "bake.orders")
        if self.train.orders and not b.orders:
            raise ValueError("train.orders learns the orders of scattering: bake them with bake.orders: K (e.g. 8), "
                             "or drop train.orders")
        if self.train.orders and (self.train.inputs or self.train.encoding != "cone"):
            raise ValueError("train.orders: with the cone encoding and without train.inputs (a dyed near field is not "
                             "supported; a family's packing and orders train together: family: and bcsdf family)")
        if "offset" in self.train.inputs and not b.offsets:
            raise ValueError("train.inputs [offset] learns the near field: bake it with bake.offsets: N (e.g. 8), "
                             "or drop the offset input")
        t = self.train
        if t.gain_azimuth_bins and (not t.energy_gain or t.inputs or t.orders or t.encoding != "cone" or
                                    (self.bundle is not None and self.bundle.shape != "circle")):
            raise ValueError("train.gain_azimuth_bins resolves the energy gain of a circular ply's model by azimuth: "
                             "with train.energy_gain, the cone encoding, and without train.inputs or train.orders; "
                             "set it to 0")
        if t.gain_rank and not (t.gain_azimuth_bins and t.gain_rank < self.wavelengths.count):
            raise ValueError(f"train.gain_rank {t.gain_rank} factors the azimuthal gain: it needs "
                             f"train.gain_azimuth_bins and a rank below the {self.wavelengths.count} wavelengths "
                             "(e.g. 4); or set it to 0")
        if b.offsets and self.bundle is not None and self.bundle.shape != "circle":
            raise ValueError("bake.offsets: the near field is baked for circular plies (an ellipse's offset goes "
                             "with its orientation: not tallied yet)")
        if b.exit in ("entry", "lobe", "curve") and b.estimator == "thesis":
            raise ValueError(f"bake.exit: {b.exit} needs bake.estimator: fast (the thesis baseline leaves uniformly)")
        if b.estimator == "camera" and (self.fiber.model != "ray" or self.fiber.ray.transport != "camera"
                                        or b.exit not in ("auto", "curve")):
            raise ValueError("bake.estimator: camera traces what Mitsuba renders of explicit hair fibers: it needs "
                             "fiber.model: ray with fiber.ray.transport: camera and bake.exit: auto (or curve); "
                             "use bake.estimator: fast otherwise")
        if self.bundle is not None and self.bundle.twist is not None and b.estimator == "thesis":
            raise ValueError("bundle.twist: a twisted ply is baked with bake.estimator: fast (or camera, for a ray "
                             "fiber of camera transport), not thesis")
        return self

    @model_validator(mode="after")
    def _fits(self):
        """Refuse a bake whose tallies cannot fit in memory, or whose batches are too many."""
        if self.bundle is None:
            return self
        b = self.bake
        n_phi_i, n_theta_i = self.incidences(expanded=True)
        cells = n_phi_i * n_theta_i * b.n_phi_o * b.n_theta_o * self.wavelengths.count
        # float64 sum and sum of squares, float32 values and errors, and an expanded copy: 40 B a cell
        check_memory(cells * 40, f"the bake's table of {n_phi_i} x {n_theta_i} x {b.n_phi_o} x {b.n_theta_o} bins x "
                                 f"{self.wavelengths.count} wavelengths",
                     "use fewer bins (bake.n_theta_o, bake.n_phi_o), fewer theta_i nodes (bake.theta_i_step_deg) "
                     "or fewer wavelengths")
        if self.bundle.arrangement == "poisson":
            # the fibers it would place: the bundle's area over a fiber's, times the packing
            # (a Poisson disk of minimum distance 2 r fills about 0.55); said here, not after
            # minutes of placement
            a, c = self.bundle.semi_axes()
            r = self.fiber.radius_um + 0.5 * self.bundle.gap_um
            fibers = (self.bundle.packing or 0.55) * a * c / r**2
            if fibers > MAX_FIBERS:
                raise ValueError(f"the bundle would hold about {fibers:,.0f} fibers (its semi-axes {a:g} x {c:g} um "
                                 f"over fibers of {self.fiber.radius_um:g} um), at most {MAX_FIBERS:,}: a smaller "
                                 "bundle.radius_um or larger fibers")
        batches = b.n_batches * n_phi_i
        if batches > 1_000_000:
            raise ValueError(f"bake.paths_per_phi_i / bake.batch_paths makes {batches:,} batches (at most "
                             "1,000,000): raise bake.batch_paths or lower bake.paths_per_phi_i")
        return self

    def command(self, stage: str) -> str:
        """``bcsdf STAGE ...`` naming this config as the user did (file and ``--set``)."""
        return f"bcsdf {stage} {self._source}"

    def hash(self, *sections: str) -> str:
        """Hash of the named sections (all of them by default), for artifact provenance."""
        data = self.model_dump(mode="json")
        if sections:
            data = {k: data[k] for k in sections}
        text = json.dumps(data, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


