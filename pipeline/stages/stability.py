"""``bcsdf stability CONFIG``: numerical stability on stiff and extreme cases.

Every case runs one piece of the pipeline where it is hardest (tiny and huge size
parameters, grazing and axial directions, index-matched and opaque fibers, dense and
sparse bundles, extreme dynamic ranges, degenerate geometry) and checks invariants:
finite and non-negative values, energy within bounds, symmetry, and agreement with an
independent reference or a higher-precision run to a stated tolerance. The result is
a table (case, quantity, invariant, value, limit, pass) written to
``artifacts/<name>/stability/`` as JSON and Markdown, and shown in the report. The
cases do not depend on the config (it names the output folder): they run once per code
and machine, and other configs reuse the rows (:func:`shared_result`). Each case is also a
test (``tests/test_stability.py``).

=========  ==================================================================
group      cases
=========  ==================================================================
mie        x 0.1..2000, zeta 1..90 deg, m 1.001..2, k 0 / 1e-6 / 1; mpmath
ray        theta +-90 deg, h +-1, sigma_a 0 and 1e4, roughness 0.01
baker      one fiber, touching fibers, packing 0.8 lossless, very sparse,
           ellipse of aspect 20, directions along the axis, float32 storage
neural     1e5:1 targets, inputs at and beyond the domain in every backend,
           float32 against float64 evaluation
plugin     grazing views, edge hits, a degenerate curve tangent
=========  ==================================================================
"""

from __future__ import annotations

import hashlib
import json
import platform
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
import torch
import yaml
from tqdm import tqdm

import mitsuba_ext
from mitsuba_ext.neural import DrJitMLP, OnnxMLP
from models.bake import Baker, BakeSpec, tally_to_table
from models.bundle import Bundle, poisson
from models.bundle_table import BundleTable
from models.fiber.mie import coefficients, efficiencies
from models.fiber.patterns import PatternFiber
from models.fiber.ray import Ap, RayFiber
from models.io import scratch, write_text
from models.neural import NeuralSpec, make_export_module, make_torch_model, rounding_bound
from models.rounding import U32, U64, gamma
from pipeline import graph
from pipeline.config import BAKE_SECTIONS
from pipeline.loading import load_config

from ..artifacts import StageFailed, stage_dir
from ..build import code_version
from ..metrics import write_metrics
from ..summaries import TrainSummary


@dataclass
class Check:
    case: str
    quantity: str
    invariant: str
    value: float
    limit: float
    passed: bool
    derivation: str = ""  # where the limit comes from

    def line(self) -> str:
        mark = "ok  " if self.passed else "FAIL"
        why = f"\n       limit: {self.derivation}" if self.derivation and not self.passed else ""
        return (f"{mark} {self.case:34} {self.quantity:38} {self.invariant:30} {self.value:11.3e} "
                f"(limit {self.limit:.1e}){why}")


def at_most(case, quantity, invariant, value, limit, derivation="") -> Check:
    value = float(value)
    return Check(case, quantity, invariant, value, float(limit), bool(np.isfinite(value) and value <= limit),
                 derivation)


def within_bound(case, quantity, measured, bound, derivation) -> Check:
    """Every entry of ``measured`` at most its derived ``bound``: the value is the largest
    ratio (limit 1), and the derivation names the worst entry's error and bound."""
    measured, bound = np.asarray(measured, np.float64).ravel(), np.asarray(bound, np.float64).ravel()
    if measured.size == 0:
        return at_most(case, quantity, "derived bound", np.nan, 1.0, "nothing to compare")
    ratio = np.where(measured > 0, measured / np.maximum(bound, 1e-300), 0.0)
    k = int(np.nanargmax(np.where(np.isfinite(ratio), ratio, np.inf)))
    note = (f"{derivation}. Worst of {measured.size} entries: {measured[k]:.3e} against its bound {bound[k]:.3e}; "
            f"bounds {np.min(bound):.1e}..{np.max(bound):.1e}")
    return at_most(case, f"max {quantity} / bound", "derived bound", ratio[k], 1.0, note)


EXACT = "exact: the invariant holds in any precision, so any violation is a defect"


def all_finite_nonneg(case, quantity, arrays) -> list[Check]:
    a = np.concatenate([np.asarray(x, np.float64).ravel() for x in arrays])
    return [at_most(case, quantity, "finite (count of NaN/Inf)", np.sum(~np.isfinite(a)), 0, EXACT),
            at_most(case, quantity, "non-negative (most negative)", max(0.0, -np.nanmin(a)) if a.size else 0.0, 0,
                    "exact: every value is clamped or a product of non-negative factors")]


def n_orders(x: float) -> int:
    """Orders a Mie series of size parameter x sums (Wiscombe 1980): x + 4.05 x^(1/3) + 2."""
    return int(np.ceil(x + 4.05 * x ** (1 / 3) + 2))


# float32 roundings in one bounce of a bake path's weight B f cos(theta) / pdf: f and the pdf
# are each a bilinear lookup (4 products and sums, the interpolation weights: 5), cos within
# 2 ulp (4 u), one product and one quotient (2)
BOUNCE_ROUNDINGS = 16


CASES = {}


def case(fn):
    CASES[fn.__name__] = fn
    return fn


# -- Mie -------------------------------------------------------------------------
@case
def mie_extremes() -> list[Check]:
    """Efficiencies over the corners of the domain: finite, Q_abs >= 0, = 0 when lossless."""

    worst = {"nonfinite": 0, "neg_sca": 0.0, "neg_abs": 0.0, "lossless_abs": 0.0, "ext_limit": 0.0}
    for x in (0.1, 1.0, 10.0, 100.0, 2000.0):
        for zeta in (1.0, 30.0, 90.0):
            for n in (1.001, 1.55, 2.0):
                for k in (0.0, 1e-6, 1.0):
                    e = efficiencies(complex(n, k), x, zeta)
                    v = np.array(list(e.values()))
                    worst["nonfinite"] += int(np.sum(~np.isfinite(v)))
                    for pol in ("I", "II"):
                        ext, sca = e[f"Qext{pol}"], e[f"Qsca{pol}"]
                        scale = max(abs(ext), 1e-300)
                        worst["neg_sca"] = max(worst["neg_sca"], -sca / scale)
                        worst["neg_abs"] = max(worst["neg_abs"], (sca - ext) / scale)
                        if k == 0:
                            worst["lossless_abs"] = max(worst["lossless_abs"], abs(ext - sca) / scale)
                    if x == 2000.0 and k == 1.0 and zeta >= 30:  # x sin(zeta) >= 1000: Q_ext / sin -> 2
                        q = 0.5 * (e["QextI"] + e["QextII"]) / np.sin(np.radians(zeta))
                        edge = 2.0 * (x * np.sin(np.radians(zeta))) ** (-2 / 3)
                        worst["ext_limit"] = max(worst["ext_limit"], abs(q - 2.0) / edge)
    c = "mie: 135 cases"
    # Q_sca and Q_ext are sums of 2 N float64 terms over the orders (N at x = 2000); for a
    # lossless fiber every term of Q_ext equals one of Q_sca (Re a = |a|^2), all >= 0
    sums = float(gamma(2 * n_orders(2000.0) + 2, U64))
    how = f"gamma_2N+2 in float64 with N = {n_orders(2000.0)} orders at x = 2000 (Wiscombe), terms >= 0"
    return [at_most(c, "Q_ext, Q_sca (both polarizations)", "finite (count of NaN/Inf)", worst["nonfinite"], 0,
                    EXACT),
            at_most(c, "-Q_sca / Q_ext", "scattering >= 0", worst["neg_sca"], 0,
                    "exact: Q_sca is a sum of squares |a|^2 + |b|^2"),
            at_most(c, "(Q_sca - Q_ext) / Q_ext", "absorption >= 0", worst["neg_abs"], 2 * sums,
                    f"summation rounding of both series: 2 {how}"),
            at_most(c, "|Q_ext - Q_sca| / Q_ext, k = 0", "lossless: no absorption", worst["lossless_abs"], 2 * sums,
                    f"summation rounding of both series: 2 {how}"),
            at_most("mie: x = 2000, k = 1, zeta 30, 90", "|Q_ext / sin(zeta) - 2| / edge term",
                    "extinction paradox", worst["ext_limit"], 1.0,
                    "the edge term of the large-x expansion, Q_ext / sin = 2 + c (x sin zeta)^(-2/3) with c < 2 "
                    "(van de Hulst 1957, sec. 17.2 and 15.3): the limit is 2 (x sin zeta)^(-2/3) per case")]


@case
def mie_against_mpmath() -> list[Check]:
    """Coefficients against 40-digit mpmath (no recurrences) where that is cheap."""
    try:
        from models.fiber import mie_reference as ref
    except ImportError:  # pragma: no cover - mpmath is in the test extra
        return [Check("mie vs mpmath", "coefficients", "needs mpmath (test extra)", np.nan, 0, False)]

    worst = 0.0
    for m, x, zeta in ((1.001 + 0j, 0.1, 1.0), (2.0 + 1j, 5.0, 1.0), (1.55 + 1e-6j, 20.0, 45.0), (2.0 + 0j, 3.0, 90.0)):
        ours = coefficients(m, x, zeta)
        orders = list(range(0, min(len(ours[0]), 12), 3))
        theirs = ref.coefficients(m, x, zeta, orders)
        scale = max(np.max(np.abs(a)) for a in ours)
        for a, b in zip(ours, theirs):
            worst = max(worst, max(abs(a[n] - complex(v)) for n, v in zip(orders, b)) / scale)
    return [at_most("mie vs mpmath: 4 stiff cases", "max |a - a_ref| / max |a|", "agrees with 40 digits",
                    worst, U32, "what the tables need: the coefficients as accurate as float32 storage (2^-24)")]


# -- ray model ---------------------------------------------------------------------
@case
def ray_extremes() -> list[Check]:
    wl = np.array([450.0, 650.0])
    checks = []
    nodes = np.deg2rad([0.0, 45.0, 89.0, 90.0])
    for sigma_a in (0.0, 1e4):
        for beta in (0.01, 0.3):
            fiber = RayFiber(wl, [1.55, 1.55], [sigma_a] * 2, beta, beta, 0.0, n_h=64, n_phi=720)
            t = fiber.tabulate(nodes)
            E = t.energy()
            c = f"ray: sigma_a {sigma_a:g}, roughness {beta:g}"
            th = np.deg2rad([-90.0, -89.0, 0.0, 89.0, 90.0])
            values = fiber.eval(phi_i=0.0, theta_i=th[:, None], phi_o=np.pi / 3, theta_o=th[None, :], wavelength=550.0)
            checks += all_finite_nonneg(c, "f at theta_i, theta_o = +-90 deg", [values, E])
            # the tabulation integrates each lobe numerically on n_phi azimuths and n_h offsets:
            # these two limits are quadrature tolerances, not rounding bounds
            quad = "a quadrature tolerance of the tabulation (n_h 64, n_phi 720), not derived from rounding"
            checks.append(at_most(c, "albedo - 1", "energy <= 1", np.max(E) - 1, 2e-3, quad))
            if sigma_a == 0:
                checks.append(at_most(c, "|albedo - 1|, theta_i < 90", "lossless conserves", np.max(np.abs(E[:3] - 1)),
                                      1e-6, quad))
            if sigma_a == 1e4:  # nothing crosses the fiber: every lobe but R (p = 0) is dark
                inner = sum(float(np.abs(lobe.azimuthal).max()) for lobe in t.lobes[1:])
                checks.append(at_most(c, "max N of the TT, TRT, residual lobes", "opaque: surface only", inner,
                                      1e-12, "the inner lobes carry exp(-2 sigma_a cos gamma_t) <= exp(-2e4 cos "
                                             "gamma_t): zero in float64 but where the path inside is shorter than "
                                             "1e-12 of a diameter's worth of absorption"))
    A = Ap(np.cos(np.deg2rad([0.0, 89.0]))[:, None], 1.55, np.array([-1.0, 1.0]), 0.0)
    checks += all_finite_nonneg("ray: h = +-1 (grazing offsets)", "A_p attenuation", [A])
    return checks


# -- baker -------------------------------------------------------------------------
def _bake(bundle, fiber_table, theta_i_deg, paths, max_bounces=100_000, n_phi=24, n_theta=18):
    with mitsuba_ext.variant("llvm_ad_mono"):
        spec = BakeSpec(np.deg2rad(theta_i_deg), [0.0], n_theta, n_phi, max_bounces=max_bounces)
        tally = Baker(bundle, fiber_table, spec).trace(0, paths, 1)
        table = tally_to_table(tally, spec, fiber_table, {"theta_i": None, "phi_i": None, "phi_o": "relative"})
        table.meta["vertices_per_path"] = tally.vertices / paths
    return table


def _isotropic(albedo=1.0):
    t = PatternFiber(np.array([550.0]), "isotropic").tabulate(np.deg2rad(np.arange(0, 91, 10.0)))
    if albedo != 1.0:
        for lobe in t.lobes:
            lobe.azimuthal = lobe.azimuthal * albedo
    return t


@case
def baker_geometry() -> list[Check]:
    fiber = _isotropic()
    r = 20.0
    checks = []
    # one fiber in a bounding circle twice its radius: passthrough = 1 - r / R_b exactly
    one = _bake(Bundle([[0.0, 0.0]], r, (2 * r, 2 * r)), fiber, [0.0, 60.0], 100_000)
    checks += all_finite_nonneg("baker: one fiber", "S, passthrough", [one.values, one.passthrough])
    checks.append(at_most("baker: one fiber", "|P_pass - (1 - r/R_b)|", "geometry", abs(one.passthrough[0] - 0.5),
                          4 * np.sqrt(0.25 / 100_000), BINOMIAL))
    checks.append(balance("baker: one fiber", one))
    # two fibers touching (distance 2r to 1e-7)
    two = _bake(Bundle([[-r, 0.0], [r * (1 + 1e-7), 0.0]], r, (2.2 * r, 2.2 * r)), fiber, [0.0, 89.9, 90.0], 50_000)
    checks += all_finite_nonneg("baker: two touching fibers", "S at theta_i 0, 89.9, 90", [two.values])
    checks.append(balance("baker: two touching fibers", two))
    # very sparse: 3 fibers in a circle of 40 r -> passthrough close to 1, geometric estimate
    sparse = Bundle([[-300.0, 100.0], [0.0, -200.0], [350.0, 300.0]], r, (800.0, 800.0))
    t = _bake(sparse, fiber, [0.0], 200_000)
    # rays cross the bounding width 2 R_b uniformly from every azimuth (a circle's table is
    # the rotation average): the mean shadow of 3 disjoint fibers over the azimuths
    shadow = float(np.mean([_shadow_fraction(sparse, a) for a in np.linspace(0, 2 * np.pi, 720, endpoint=False)]))
    checks.append(at_most("baker: very sparse (3 fibers, R_b 40 r)", "|P_pass - geometric|", "passthrough",
                          abs(t.passthrough[0] - (1 - shadow)), 4 * np.sqrt(shadow * (1 - shadow) / 200_000) + 1e-6,
                          BINOMIAL + ", plus the 720-azimuth average of the shadow (1e-6)"))
    # ellipse of aspect 20
    thin = poisson((400.0, 20.0), 5.0, seed=2)
    t = _bake(thin, fiber, [0.0, 45.0], 50_000)
    checks += all_finite_nonneg("baker: ellipse aspect 20", "S", [t.values])
    checks.append(balance("baker: ellipse aspect 20", t))
    return checks


BINOMIAL = "4 standard errors of a binomial fraction of the paths (a false alarm once in 16,000 runs)"


def balance(case_name, table) -> Check:
    """|scattered + passthrough + absorbed + lost - 1|: what float32 path weights can lose.

    A path's weight is rounded BOUNCE_ROUNDINGS times per bounce, so after V bounces it is
    off by at most gamma(16 V); the tally is the mean over paths (float64 sums): to first
    order 16 u times the mean vertices per path."""
    V = float(table.meta["vertices_per_path"])
    limit = float(gamma(BOUNCE_ROUNDINGS * V))
    return at_most(case_name, "|total - 1|", "energy balance", np.max(np.abs(table.energy_balance()["total"] - 1)),
                   limit, f"float32 path weights: gamma_16V with {BOUNCE_ROUNDINGS} roundings per bounce "
                          f"(two table lookups, cos, product, quotient) and V = {V:.2f} vertices per path")


def _shadow_fraction(bundle, phi_i):
    """Fraction of the bounding width covered by the fibers' shadows (disjoint intervals here)."""
    d = np.array([np.cos(phi_i), np.sin(phi_i)])
    side = np.array([-d[1], d[0]])
    offsets = bundle.centers @ side
    intervals = sorted(zip(offsets - bundle.radii, offsets + bundle.radii))
    covered, end = 0.0, -np.inf
    for lo, hi in intervals:
        covered += max(0.0, hi - max(lo, end))
        end = max(end, hi)
    return covered / (2 * bundle.bounding_radius)


@case
def baker_dense_lossless() -> list[Check]:
    """Packing 0.8 on a hexagonal lattice, lossless isotropic fibers: long random walks
    (a mean of ~30 bounces for paths entering at the edge, a tail of thousands)."""
    r, R = 10.0, 400.0
    bundle = _hexagonal(r, R, 0.8)
    t0 = time.perf_counter()
    t = _bake(bundle, _isotropic(1.0), [0.0, 80.0], 10_000, max_bounces=1_000_000)
    seconds = time.perf_counter() - t0
    c = f"baker: packing {bundle.packing_fraction:.2f} lossless ({len(bundle.centers)} fibers)"
    bal = t.energy_balance()
    checks = all_finite_nonneg(c, "S", [t.values])
    checks.append(balance(c, t))
    # the isotropic albedo is 1 in float32 (1 - 6e-8), lost at every bounce of every path
    V = float(t.meta["vertices_per_path"])
    checks.append(at_most(c, "absorbed", "lossless: float32 rounding only", np.max(bal["absorbed"]),
                          float(gamma(BOUNCE_ROUNDINGS * V)),
                          f"the albedo 1 in float32 and the weights' rounding: gamma_16V, V = {V:.2f} vertices per path"))
    checks.append(at_most(c, "lost at the bounce cap", "reported, small", np.max(bal["lost"]), 0.01,
                          "a walk of 10^6 bounces at packing 0.8: none of 10^4 paths expected; 1% is 100 paths"))
    # a random walk that enters at the edge: the mean is tens of bounces, the tail
    # thousands; none may reach the cap of 10^6 (lost = 0 above)
    checks.append(at_most(c, "-(mean vertices per path)", "long walks (> 20 bounces)",
                          -t.meta["vertices_per_path"], -20,
                          "physics: a diffusive walk from the edge of a bundle 40 fibers across takes tens of bounces"))
    checks.append(at_most(c, "seconds for 10k paths", "completes", seconds, 600, "a hang, not a timing"))
    return checks


def _hexagonal(r, R, packing):
    """Fibers of radius ``r`` on a hexagonal lattice inside a circle ``R`` at the given packing."""

    def lattice(d):
        n = int(R / d) + 2
        pts = np.array([(i * d + (j % 2) * d / 2, j * d * np.sqrt(3) / 2) for i in range(-n, n + 1)
                        for j in range(-n, n + 1)])
        return pts[np.hypot(*pts.T) <= R - r]

    lo, hi = 2 * r * (1 + 1e-6), 4 * r
    for _ in range(40):  # denser lattice, higher packing: bisect the spacing
        d = 0.5 * (lo + hi)
        frac = len(lattice(d)) * r * r / (R * R)
        lo, hi = (d, hi) if frac > packing else (lo, d)
    return Bundle(lattice(hi), r, (R, R))


@case
def baker_float32_storage() -> list[Check]:
    """The table is stored in float32: its energy sums match the float64 tally's."""

    t = _bake(poisson((100.0, 100.0), 10.0, seed=4), _isotropic(0.9), [0.0, 45.0], 50_000)
    s64 = np.einsum("abpql,pq->abl", t.values.astype(np.float64), t.solid_angle)
    s32 = np.einsum("abpql,pq->abl", t.values.astype(np.float32), t.solid_angle.astype(np.float32),
                    dtype=np.float32)
    # n products summed in float32, each factor rounded to float32 once: gamma_(n+2) sum |S dw|
    n = t.solid_angle.size
    bound = gamma(n + 2) * np.einsum("abpql,pq->abl", np.abs(t.values.astype(np.float64)), t.solid_angle)
    return [within_bound("baker: float32 against float64", "|sum S dw (f32) - (f64)|", np.abs(s32 - s64), bound,
                         f"Higham gamma_(n+2) sum |S dw| over the n = {n} bins, per incidence and wavelength")]


# -- neural ------------------------------------------------------------------------
@case
def neural_extremes() -> list[Check]:
    checks = []
    with tempfile.TemporaryDirectory() as tmp, scratch(tmp):
        tmp = Path(tmp)
        cfg_path = tmp / "stiff.yaml"
        cfg_path.write_text(yaml.safe_dump({
            "name": "stiff", "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
            "fiber": {"model": "isotropic"}, "bundle": {"shape": "circle", "radius_um": 100},
            "train": {"models": {"tiny": [16, 16]}, "epochs": 40, "batch_size": 512, "patience": 40}}))
        cfg = load_config(cfg_path)
        # a ridge along the specular cone over a floor 1e5 below it
        theta_i = np.deg2rad(np.arange(0, 91, 15.0))
        pe, te = np.linspace(-np.pi, np.pi, 37), np.linspace(-np.pi / 2, np.pi / 2, 19)
        PO, TO = np.meshgrid(0.5 * (pe[1:] + pe[:-1]), 0.5 * (te[1:] + te[:-1]), indexing="ij")
        S = np.stack([1e-5 + np.exp(-((np.sin(TO) + np.sin(t)) / 0.1) ** 2) * (0.6 + 0.4 * np.cos(PO))
                      for t in theta_i])[None, ..., None] * np.ones(3)
        z = np.zeros((1, len(theta_i), 3))
        BundleTable(S.astype(np.float32), 0.01 * S.astype(np.float32), np.zeros(1), np.zeros(1), z, z, np.zeros(1),
                    theta_i, pe, te, np.array([450.0, 550.0, 650.0]),
                    {"reductions": {"theta_i": "mirror", "phi_i": "rotation", "phi_o": "relative"},
                     "config_hash": cfg.hash(*BAKE_SECTIONS)}).save(tmp / "stiff" / "bake" / "bundle_table.npz")
        graph.run_stage("train", cfg, tmp)
        graph.run_stage("export", cfg, tmp)
        summary = TrainSummary.read(tmp / "stiff" / "train" / "tiny" / "summary.json")
        c = "neural: 1e5:1 targets"
        checks.append(at_most(c, "held-out relative L1", "trains without NaN", summary.relative_l1, 1.0,
                          "a model that learned anything: off by less than the table itself"))
        checks += _backends_at_edges(tmp / "stiff" / "export" / "tiny", tmp / "stiff" / "train" / "tiny" / "model.pt")
    return checks


def _edge_queries():
    edges = [[0, np.pi / 2, np.pi, -np.pi / 2], [0, -np.pi / 2, 0, np.pi / 2], [np.pi, 0, -np.pi, 0],
             [2 * np.pi, 0.3, 2 * np.pi + 1e-6, -0.3], [-np.pi, 1.0, np.pi, -1.0],
             [1e4, 3.0, -1e4, -3.0], [7.0, -2.0, -7.0, 2.0], [0, 1.5707964, 0, -1.5707964]]
    rng = np.random.default_rng(0)
    random = np.stack([rng.uniform(-np.pi, np.pi, 2000), rng.uniform(-np.pi / 2, np.pi / 2, 2000),
                       rng.uniform(-np.pi, np.pi, 2000), rng.uniform(-np.pi / 2, np.pi / 2, 2000)], -1)
    return np.concatenate([edges, random]).astype(np.float32)


def _backends_at_edges(export_dir: Path, checkpoint: Path) -> list[Check]:
    ckpt = torch.load(checkpoint, weights_only=True)
    spec = NeuralSpec.from_dict(ckpt["spec"])
    q = _edge_queries()
    if spec.inputs:  # extra inputs (an offset in [-1, 1]): across, at and beyond their ends
        extra = np.random.default_rng(1).uniform(-1.5, 1.5, (len(q), len(spec.inputs)))
        extra[:3] = [[-1.0], [1.0], [0.0]] * np.ones((1, len(spec.inputs)))
        q = np.concatenate([q, extra.astype(np.float32)], -1)
    mlp = make_torch_model(spec)
    mlp.load_state_dict(ckpt["state"])
    module = make_export_module(spec, mlp).eval()
    with torch.no_grad():
        f32 = module(torch.from_numpy(q)).numpy().astype(np.float64)
        f64 = module.double()(torch.from_numpy(q).double()).numpy()
    # the graph itself, as another renderer runs it (OnnxMLP.eval refuses a theta beyond pi/2;
    # the graph, like the traced Dr.Jit code, clamps it)
    onnx = OnnxMLP(export_dir / "model.onnx").session.run(None, {"angles": q})[0].astype(np.float64)
    with mitsuba_ext.variant("llvm_ad_rgb"):
        dj = DrJitMLP(export_dir / "weights.npz")
        jit = np.stack([np.asarray(v) for v in dj.eval(*(mi.Float(c) for c in q.T))], -1).astype(np.float64)
    c = "neural: inputs at and beyond the edges"
    checks = []
    for name, v in (("pytorch", f32), ("onnxruntime", onnx), ("Dr.Jit", jit)):
        checks += all_finite_nonneg(c, f"S ({name})", [v])
    # each evaluation against the exact value of the same model (the exported weights, the
    # checkpoint's float32 values): the bounds of models.rounding
    _, b32 = rounding_bound(spec, dj.layers, q, lines=dj.lines)
    _, b64 = rounding_bound(spec, dj.layers, q, u=U64, lines=dj.lines)
    how = ("Higham gamma_(n+1) (|W||x| + |b|) of every layer carried to the output by the network's Jacobian, "
           "elementary functions within 2 ulp, per query and wavelength (models/rounding.py)")
    checks.append(within_bound("neural: float32 against float64", "|f32 - f64| (PyTorch)", np.abs(f32 - f64),
                               b32 + b64, f"{how}; bound of f32 + bound of f64"))
    checks.append(within_bound("neural: onnxruntime against PyTorch", "|onnxruntime - PyTorch| (float32)",
                               np.abs(onnx - f32), 2 * b32, f"{how}; twice the float32 bound"))
    # Dr.Jit documents its sin and cos for |x| < 8192 (beyond: finite, checked above)
    inside = np.all(np.abs(np.c_[q[:, :4], q[:, 2] - q[:, 0]]) < 8192, axis=1)
    checks.append(within_bound("neural: Dr.Jit against PyTorch", "|Dr.Jit - PyTorch| (float32)",
                               np.abs(jit - f32)[inside], 2 * b32[inside],
                               f"{how}; twice the float32 bound; angles within Dr.Jit's |x| < 8192"))
    return checks


# -- plugin ------------------------------------------------------------------------
@case
def plugin_extremes() -> list[Check]:
    with mitsuba_ext.variant("llvm_ad_rgb"):
        checks = []
        with tempfile.TemporaryDirectory() as tmp, scratch(tmp):
            tmp = Path(tmp)
            # a small ellipse-like table (absolute phi, mirror_xz) with a passthrough
            phi_i, theta_i = np.deg2rad([0.0, 45.0, 90.0]), np.deg2rad(np.arange(0, 91, 15.0))
            pe, te = np.linspace(-np.pi, np.pi, 37), np.linspace(-np.pi / 2, np.pi / 2, 19)
            PI, TI, PO, TO = np.meshgrid(phi_i, theta_i, 0.5 * (pe[1:] + pe[:-1]), 0.5 * (te[1:] + te[:-1]),
                                         indexing="ij")
            S = (0.05 + np.exp(-((np.sin(TO) + np.sin(TI)) / 0.2) ** 2) * (1 + 0.5 * np.cos(2 * PI)))[..., None]
            z = np.zeros((3, len(theta_i), 1))
            BundleTable(S.astype(np.float32), 0.01 * S.astype(np.float32), np.full(3, 0.2), np.zeros(3), z, z, phi_i,
                        theta_i, pe, te, np.array([550.0]),
                        {"reductions": {"theta_i": "mirror", "phi_i": "mirror_xz", "phi_o": "absolute"}}
                        ).save(tmp / "t.npz")
            bundle = {"type": "fiber_bundle", "table": str(tmp / "t.npz"), "radius": 0.3, "twist_rate": 180.0}
            pts = [[np.cos(a) * 0.8, -1.5 + a / 2, np.sin(a) * 0.8, 0.3] for a in np.linspace(0, 6, 10)]
            degenerate = pts[:4] + [pts[4]] * 4 + pts[5:]
            (tmp / "c.txt").write_text("\n".join(" ".join(f"{v:.6f}" for v in p) for p in degenerate))
            cylinder = {"type": "cylinder", "p0": [0, -1, 0], "p1": [0, 1, 0], "radius": 0.3, "bsdf": bundle}
            views = {
                "plugin: grazing view along the axis": (cylinder, [0.35, 3.0, 0.0], [0, -1, 0], [0, 0, 1], 40),
                "plugin: silhouette edge hits": (cylinder, [0.299, 0, 4], [0.299, 0, 0], [0, 1, 0], 2),
                "plugin: curve with zero-length tangent": ({"type": "bsplinecurve", "filename": str(tmp / "c.txt"),
                                                            "bsdf": bundle}, [0, 0.4, 5], [0, 0, 0], [0, 1, 0], 40),
            }
            for name, (shape, eye, target, up, fov) in views.items():
                scene = mi.load_dict({
                    "type": "scene", "integrator": {"type": "bundle_path", "max_depth": 16},
                    "sensor": {"type": "perspective", "fov": fov,
                               "to_world": mi.ScalarTransform4f().look_at(eye, target, up),
                               "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                               "sampler": {"type": "independent", "sample_count": 16}},
                    "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
                    "sun": {"type": "directional", "direction": [-0.3, -1, -0.6], "irradiance": {"type": "rgb", "value": 3}},
                    "shape": shape})
                img = np.array(mi.render(scene))
                checks += all_finite_nonneg(name, "pixel values", [img])
                checks.append(at_most(name, "-(max |pixel - sky|)", "the bundle is visible", -np.abs(img - 0.3).max(),
                                      -0.01, "a visible difference: a bundle lit by a sun of 3 differs from the sky 0.3 "
                                             "by far more than 0.01"))
        return checks


# -- the stage ---------------------------------------------------------------------
def run_cases(names=None) -> list[Check]:
    checks = []
    for name in tqdm(list(names or CASES), desc="stability", unit="case"):
        t0 = time.perf_counter()
        result = CASES[name]()
        print(f"[stability] {name}: {sum(c.passed for c in result)}/{len(result)} passed "
              f"({time.perf_counter() - t0:.1f} s)")
        for c in result:
            if not c.passed:
                print("  " + c.line())
        checks += result
    return checks


def markdown(checks) -> str:
    """The table of stability.md: each limit beside the measured value, and where it comes from."""
    md = ["| case | quantity | invariant | value | limit | result | where the limit comes from |",
          "|---|---|---|---|---|---|---|"]
    cell = lambda text: text.replace("|", "\\|")  # noqa: E731 - a pipe inside a cell is escaped
    md += [f"| {cell(c.case)} | {cell(c.quantity)} | {cell(c.invariant)} | {c.value:.3e} | {c.limit:.1e} | "
           f"{'pass' if c.passed else '**FAIL**'} | {cell(c.derivation)} |" for c in checks]
    return "\n".join(md) + "\n"


def shared_result(cfg, out_root="artifacts") -> Path:
    """Where the checks of this code on this machine are kept for every config: the cases do
    not read the config, so a second config's stage reuses the first's rows. The key is the
    digest of the stage's code (its deps in dvc.yaml) and of the machine's arithmetic (CPU,
    torch's kernel set, the libraries' versions) and of the set of cases: another kernel set
    runs them again."""
    code = graph.digest(graph.spec("stability", cfg)["code"], graph.ROOT)
    arithmetic = json.dumps([platform.machine(), platform.processor(), torch.backends.cpu.get_cpu_capability(),
                             torch.__version__, mi.__version__, np.__version__])
    cases = json.dumps(sorted(CASES))  # the cases this process runs (a test may pick others)
    key = hashlib.sha256((code + arithmetic + cases).encode()).hexdigest()[:16]
    return Path(out_root) / ".shared" / "stability" / f"{key}.json"


def run(cfg, out_root="artifacts") -> Path:
    """Run every case (or reuse the rows of this code on this machine, :func:`shared_result`);
    write the table. A failed check raises :class:`StageFailed` with the table as its partial
    result (kept under ``failed/stability/``), after printing the failing rows."""
    out = stage_dir(cfg, "stability", out_root)
    shared = shared_result(cfg, out_root)
    try:
        checks = [Check(**row) for row in json.loads(shared.read_text())]
        print(f"[stability] these checks already ran with this code on this machine ({shared}): reused")
    except (OSError, ValueError, TypeError):  # none yet (or unreadable): run them
        checks = run_cases()
    rows = json.dumps([asdict(c) for c in checks], indent=1)
    failed = [c for c in checks if not c.passed]
    print(f"[stability] {len(checks) - len(failed)}/{len(checks)} checks passed")
    if failed:
        raise StageFailed(f"{len(failed)} of {len(checks)} stability checks failed:\n"
                          + "\n".join(c.line() for c in failed),
                          partial={"stability.json": rows, "stability.md": markdown(checks)})
    write_text(shared, rows)  # only rows that passed are kept for other configs
    write_text(out / "stability.json", rows)
    write_text(out / "provenance.json", json.dumps({"config_hash": cfg.hash(), "code": code_version()}))
    write_text(out / "stability.md", markdown(checks))
    write_metrics(cfg, out_root, "stability", {"checks": len(checks), "passed": len(checks)})
    print(f"[stability] wrote {out}")
    return out
