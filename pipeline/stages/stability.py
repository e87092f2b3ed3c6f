"""``bcsdf stability CONFIG``: numerical stability on stiff and extreme cases.

Every case runs one piece of the pipeline where it is hardest (tiny and huge size
parameters, grazing and axial directions, index-matched and opaque fibers, dense and
sparse bundles, extreme dynamic ranges, degenerate geometry) and checks invariants:
finite and non-negative values, energy within bounds, symmetry, and agreement with an
independent reference or a higher-precision run to a stated tolerance. The result is
a table (case, quantity, invariant, value, limit, pass) written to
``artifacts/<name>/stability/`` as JSON and Markdown, and shown in the report. The
cases do not depend on the config (it names the output folder); each one is also a
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

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from models.io import scratch, write_text

from ..metrics import write_metrics
from ..artifacts import stage_dir


@dataclass
class Check:
    case: str
    quantity: str
    invariant: str
    value: float
    limit: float
    passed: bool

    def line(self) -> str:
        mark = "ok  " if self.passed else "FAIL"
        return f"{mark} {self.case:34} {self.quantity:38} {self.invariant:30} {self.value:11.3e} (limit {self.limit:.1e})"


def at_most(case, quantity, invariant, value, limit) -> Check:
    value = float(value)
    return Check(case, quantity, invariant, value, float(limit), bool(np.isfinite(value) and value <= limit))


def all_finite_nonneg(case, quantity, arrays) -> list[Check]:
    a = np.concatenate([np.asarray(x, np.float64).ravel() for x in arrays])
    return [at_most(case, quantity, "finite (count of NaN/Inf)", np.sum(~np.isfinite(a)), 0),
            at_most(case, quantity, "non-negative (most negative)", max(0.0, -np.nanmin(a)) if a.size else 0.0, 0)]


CASES = {}


def case(fn):
    CASES[fn.__name__] = fn
    return fn


# -- Mie -------------------------------------------------------------------------
@case
def mie_extremes() -> list[Check]:
    """Efficiencies over the corners of the domain: finite, Q_abs >= 0, = 0 when lossless."""
    from models.fiber.mie import efficiencies

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
                        worst["ext_limit"] = max(worst["ext_limit"], abs(q - 2.0))
    c = "mie: 135 cases"
    return [at_most(c, "Q_ext, Q_sca (both polarizations)", "finite (count of NaN/Inf)", worst["nonfinite"], 0),
            at_most(c, "-Q_sca / Q_ext", "scattering >= 0", worst["neg_sca"], 1e-12),
            at_most(c, "(Q_sca - Q_ext) / Q_ext", "absorption >= 0", worst["neg_abs"], 1e-9),
            at_most(c, "|Q_ext - Q_sca| / Q_ext, k = 0", "lossless: no absorption", worst["lossless_abs"], 1e-8),
            at_most("mie: x = 2000, k = 1, zeta 30, 90", "|Q_ext / sin(zeta) - 2|", "extinction paradox",
                    worst["ext_limit"], 0.02)]


@case
def mie_against_mpmath() -> list[Check]:
    """Coefficients against 40-digit mpmath (no recurrences) where that is cheap."""
    try:
        from models.fiber import mie_reference as ref
    except ImportError:  # pragma: no cover - mpmath is in the test extra
        return [Check("mie vs mpmath", "coefficients", "needs mpmath (test extra)", np.nan, 0, False)]
    from models.fiber.mie import coefficients

    worst = 0.0
    for m, x, zeta in ((1.001 + 0j, 0.1, 1.0), (2.0 + 1j, 5.0, 1.0), (1.55 + 1e-6j, 20.0, 45.0), (2.0 + 0j, 3.0, 90.0)):
        ours = coefficients(m, x, zeta)
        orders = list(range(0, min(len(ours[0]), 12), 3))
        theirs = ref.coefficients(m, x, zeta, orders)
        scale = max(np.max(np.abs(a)) for a in ours)
        for a, b in zip(ours, theirs):
            worst = max(worst, max(abs(a[n] - complex(v)) for n, v in zip(orders, b)) / scale)
    return [at_most("mie vs mpmath: 4 stiff cases", "max |a - a_ref| / max |a|", "agrees with 40 digits",
                    worst, 1e-8)]


# -- ray model ---------------------------------------------------------------------
@case
def ray_extremes() -> list[Check]:
    from models.fiber.ray import Ap, RayFiber

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
            checks.append(at_most(c, "albedo - 1", "energy <= 1", np.max(E) - 1, 2e-3))
            if sigma_a == 0:
                checks.append(at_most(c, "|albedo - 1|, theta_i < 90", "lossless conserves", np.max(np.abs(E[:3] - 1)),
                                      1e-6))
            if sigma_a == 1e4:  # nothing crosses the fiber: every lobe but R (p = 0) is dark
                inner = sum(float(np.abs(lobe.azimuthal).max()) for lobe in t.lobes[1:])
                checks.append(at_most(c, "max N of the TT, TRT, residual lobes", "opaque: surface only", inner,
                                      1e-12))
    A = Ap(np.cos(np.deg2rad([0.0, 89.0]))[:, None], 1.55, np.array([-1.0, 1.0]), 0.0)
    checks += all_finite_nonneg("ray: h = +-1 (grazing offsets)", "A_p attenuation", [A])
    return checks


# -- baker -------------------------------------------------------------------------
def _bake(bundle, fiber_table, theta_i_deg, paths, max_bounces=100_000, n_phi=24, n_theta=18):
    import mitsuba as mi

    from models.bake import Baker, BakeSpec

    from . import bake as bake_stage

    mi.set_variant("llvm_ad_mono")
    spec = BakeSpec(np.deg2rad(theta_i_deg), [0.0], n_theta, n_phi, max_bounces=max_bounces)
    tally = Baker(bundle, fiber_table, spec).trace(0, paths, 1)
    table = bake_stage.tally_to_table(tally, spec, fiber_table, {"theta_i": None, "phi_i": None, "phi_o": "relative"})
    table.meta["vertices_per_path"] = tally.vertices / paths
    return table


def _isotropic(albedo=1.0):
    from models.fiber.patterns import PatternFiber

    t = PatternFiber(np.array([550.0]), "isotropic").tabulate(np.deg2rad(np.arange(0, 91, 10.0)))
    if albedo != 1.0:
        for lobe in t.lobes:
            lobe.azimuthal = lobe.azimuthal * albedo
    return t


@case
def baker_geometry() -> list[Check]:
    from models.bundle import Bundle, poisson

    fiber = _isotropic()
    r = 20.0
    checks = []
    # one fiber in a bounding circle twice its radius: passthrough = 1 - r / R_b exactly
    one = _bake(Bundle([[0.0, 0.0]], r, (2 * r, 2 * r)), fiber, [0.0, 60.0], 100_000)
    checks += all_finite_nonneg("baker: one fiber", "S, passthrough", [one.values, one.passthrough])
    checks.append(at_most("baker: one fiber", "|P_pass - (1 - r/R_b)|", "geometry", abs(one.passthrough[0] - 0.5),
                          4 * np.sqrt(0.25 / 100_000)))
    checks.append(at_most("baker: one fiber", "|total - 1|", "energy balance", np.max(np.abs(
        one.energy_balance()["total"] - 1)), 1e-6))
    # two fibers touching (distance 2r to 1e-7)
    two = _bake(Bundle([[-r, 0.0], [r * (1 + 1e-7), 0.0]], r, (2.2 * r, 2.2 * r)), fiber, [0.0, 89.9, 90.0], 50_000)
    checks += all_finite_nonneg("baker: two touching fibers", "S at theta_i 0, 89.9, 90", [two.values])
    checks.append(at_most("baker: two touching fibers", "|total - 1|", "energy balance",
                          np.max(np.abs(two.energy_balance()["total"] - 1)), 1e-6))
    # very sparse: 3 fibers in a circle of 40 r -> passthrough close to 1, geometric estimate
    sparse = Bundle([[-300.0, 100.0], [0.0, -200.0], [350.0, 300.0]], r, (800.0, 800.0))
    t = _bake(sparse, fiber, [0.0], 200_000)
    # rays cross the bounding width 2 R_b uniformly from every azimuth (a circle's table is
    # the rotation average): the mean shadow of 3 disjoint fibers over the azimuths
    shadow = float(np.mean([_shadow_fraction(sparse, a) for a in np.linspace(0, 2 * np.pi, 720, endpoint=False)]))
    checks.append(at_most("baker: very sparse (3 fibers, R_b 40 r)", "|P_pass - geometric|", "passthrough",
                          abs(t.passthrough[0] - (1 - shadow)), 4 * np.sqrt(shadow * (1 - shadow) / 200_000) + 1e-6))
    # ellipse of aspect 20
    thin = poisson((400.0, 20.0), 5.0, seed=2)
    t = _bake(thin, fiber, [0.0, 45.0], 50_000)
    checks += all_finite_nonneg("baker: ellipse aspect 20", "S", [t.values])
    checks.append(at_most("baker: ellipse aspect 20", "|total - 1|", "energy balance",
                          np.max(np.abs(t.energy_balance()["total"] - 1)), 1e-6))
    return checks


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
    checks.append(at_most(c, "|total - 1|", "energy balance", np.max(np.abs(bal["total"] - 1)), 1e-5))
    # the isotropic albedo is 1 in float32 (1 - 6e-8), lost at every bounce of every path
    checks.append(at_most(c, "absorbed", "lossless: float32 rounding only", np.max(bal["absorbed"]), 1e-4))
    checks.append(at_most(c, "lost at the bounce cap", "reported, small", np.max(bal["lost"]), 0.01))
    # a random walk that enters at the edge: the mean is tens of bounces, the tail
    # thousands; none may reach the cap of 10^6 (lost = 0 above)
    checks.append(at_most(c, "-(mean vertices per path)", "long walks (> 20 bounces)",
                          -t.meta["vertices_per_path"], -20))
    checks.append(at_most(c, "seconds for 10k paths", "completes", seconds, 600))
    return checks


def _hexagonal(r, R, packing):
    """Fibers of radius ``r`` on a hexagonal lattice inside a circle ``R`` at the given packing."""
    from models.bundle import Bundle

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
    from models.bundle import poisson

    t = _bake(poisson((100.0, 100.0), 10.0, seed=4), _isotropic(0.9), [0.0, 45.0], 50_000)
    s64 = np.einsum("abpql,pq->abl", t.values.astype(np.float64), t.solid_angle)
    s32 = np.einsum("abpql,pq->abl", t.values.astype(np.float32), t.solid_angle.astype(np.float32),
                    dtype=np.float32)
    return [at_most("baker: float32 against float64", "|sum S dw (f32) - (f64)|", "accumulation error",
                    np.max(np.abs(s32 - s64)), 1e-5)]


# -- neural ------------------------------------------------------------------------
@case
def neural_extremes() -> list[Check]:
    import tempfile

    import yaml

    from models.bundle_table import BundleTable
    from pipeline.stages import export as export_stage
    from pipeline.stages import train as train_stage
    from pipeline.config import BAKE_SECTIONS, load_config

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
        train_stage.run(cfg, tmp)
        export_stage.run(cfg, tmp)
        summary = json.loads((tmp / "stiff" / "train" / "tiny" / "summary.json").read_text())
        c = "neural: 1e5:1 targets"
        checks.append(at_most(c, "held-out relative L1", "trains without NaN", summary["relative_l1"], 1.0))
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
    import mitsuba as mi
    import torch

    from mitsuba_ext.neural import DrJitMLP, OnnxMLP
    from models.neural import NeuralSpec, make_export_module, make_torch_model

    q = _edge_queries()
    ckpt = torch.load(checkpoint, weights_only=True)
    spec = NeuralSpec.from_dict(ckpt["spec"])
    mlp = make_torch_model(spec)
    mlp.load_state_dict(ckpt["state"])
    module = make_export_module(spec, mlp).eval()
    with torch.no_grad():
        f32 = module(torch.from_numpy(q)).numpy()
        f64 = module.double()(torch.from_numpy(q).double()).numpy()
    onnx = OnnxMLP(export_dir / "model.onnx").eval(*q.T)
    mi.set_variant("llvm_ad_rgb")
    dj = DrJitMLP(export_dir / "weights.npz")
    jit = np.stack([np.asarray(v) for v in dj.eval(*(mi.Float(c) for c in q.T))], -1)
    c = "neural: inputs at and beyond the edges"
    checks = []
    for name, v in (("pytorch", f32), ("onnxruntime", onnx), ("Dr.Jit", jit)):
        checks += all_finite_nonneg(c, f"S ({name})", [v])
    scale = np.maximum(np.abs(f64), 1e-3 * np.abs(f64).max())
    checks.append(at_most("neural: float32 against float64", "max |f32 - f64| / |f64|", "float32 rounding",
                          np.max(np.abs(f32 - f64) / scale), 1e-4))
    return checks


# -- plugin ------------------------------------------------------------------------
@case
def plugin_extremes() -> list[Check]:
    import tempfile

    import mitsuba as mi

    import mitsuba_ext
    from models.bundle_table import BundleTable

    mi.set_variant("llvm_ad_rgb")
    mitsuba_ext.register()
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
                                  -0.01))
    return checks


# -- the stage ---------------------------------------------------------------------
def run_cases(names=None) -> list[Check]:
    from tqdm import tqdm

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


def run(cfg, out_root="artifacts") -> Path:
    out = stage_dir(cfg, "stability", out_root)
    checks = run_cases()
    rows = [asdict(c) for c in checks]
    write_text(out / "stability.json", json.dumps(rows, indent=1))
    from ..build import code_version
    write_text(out / "provenance.json", json.dumps({"config_hash": cfg.hash(), "code": code_version()}))
    md = ["| case | quantity | invariant | value | limit | result |", "|---|---|---|---|---|---|"]
    md += [f"| {c.case} | {c.quantity} | {c.invariant} | {c.value:.3e} | {c.limit:.1e} | "
           f"{'pass' if c.passed else '**FAIL**'} |" for c in checks]
    write_text(out / "stability.md", "\n".join(md) + "\n")
    failed = [c for c in checks if not c.passed]
    write_metrics(cfg, out_root, "stability", {"checks": len(checks), "passed": len(checks) - len(failed)})
    print(f"[stability] {len(checks) - len(failed)}/{len(checks)} checks passed; wrote {out}")
    if failed:
        raise FloatingPointError(f"{len(failed)} stability checks failed:\n" + "\n".join(c.line() for c in failed))
    return out
