"""``bcsdf render CONFIG``: the bundle BSDF in Mitsuba, table against neural, and the
ground truth with every fiber as its own curve.

For each scene of ``render.scenes`` and each backend of ``render.backends`` one image
(EXR, linear; PNG, sRGB) at equal samples, each timed on a warm kernel cache; FLIP
(LDR, ``flip-evaluator``) and PSNR of every neural image against the table's, with
error maps and one side-by-side picture. Then two checks:

* ``mono_check``: the spectral variant against the thesis's way, one mono render per
  table wavelength combined with CIE 1931 and D65 into sRGB (mean colour of the ply);
* ``explicit``: the chain's closure (``pipeline.closure``): the bundle BSDF's far field
  against its table and MLP, the bake's own fibers rendered one by one against the
  bake bin by bin, and the ply scene with every fiber its own cylinder (16 turns of
  the arrangement averaged) against the bundle with the table and the MLP.

Everything lands in ``artifacts/<name>/render/`` with ``summary.json``. The neural
backends read only their exported files: no table is loaded for them.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from tqdm import tqdm

import mitsuba_ext
from mitsuba_ext.frame import spectral_weights
from models.bake import bake_unreduced
from models.bundle_table import BundleTable
from models.fiber.base import FiberTable
from models.io import atomic_path

from .. import closure, scenes
from ..artifacts import config_dir, model_size, stage_dir
from ..bsdfs import backend_props
from ..build import build_ply, cross_section, make_spec
from ..config import RENDER_SECTIONS
from ..images import exposure_of, flip_and_psnr, render_timed, save_images, save_png, to_srgb
from ..metrics import write_metrics
from ..noise import table_noise
from ..plots import save_figure
from ..scenes import FOV_DEG
from ..summaries import RenderSummary

# -- inputs ------------------------------------------------------------------------


# -- rendering ---------------------------------------------------------------------


# -- the stage ---------------------------------------------------------------------
def run(cfg, out_root="artifacts") -> Path:
    if cfg.bundle is None:
        raise ValueError("render: this config has no bundle; add a `bundle:` section")
    r = cfg.render
    out = stage_dir(cfg, "render", out_root)
    out.mkdir(parents=True, exist_ok=True)
    props = {b: backend_props(cfg, out_root, b) for b in r.backends}  # refuse mismatches before rendering
    with mitsuba_ext.variant(r.variant):

        summary = {"config_hash": cfg.hash(*RENDER_SECTIONS), "variant": r.variant, "spp": r.spp,
                   "size": [r.width, r.height],
                   "model": model_size(cfg) if set(r.backends) - {"table"} else None, "scenes": {}}
        bar = tqdm(total=len(r.scenes) * len(r.backends), desc="renders", unit="render")
        for name in r.scenes:
            images, entry = {}, {"description": scenes.describe(cfg, name)}
            for backend in r.backends:
                bar.update()
                scene = scenes.named_scene(mi, cfg, name, props[backend], r.spp, out)
                img, seconds, first = render_timed(mi, scene, backend)
                images[backend] = img
                entry[backend] = {"seconds": seconds, "first_seconds": first,
                                  "mean_radiance": img.mean(axis=(0, 1)).tolist()}
                print(f"[render] {name} / {backend}: {seconds:.2f} s ({first:.2f} s with compilation)")
            reference = "table" if "table" in images else r.backends[0]
            exposure = exposure_of(images[reference])
            entry["exposure"] = exposure
            flip_maps = {}
            for backend, img in images.items():
                save_images(mi, img, out / f"{name}_{backend}", exposure)
                if backend == reference:
                    continue
                mean_flip, psnr, error_map = flip_and_psnr(images[reference], img, exposure)
                save_png(error_map, out / f"{name}_{backend}_flip.png")
                flip_maps[backend] = error_map
                entry[backend].update(flip=mean_flip, psnr=psnr, reference=reference,
                                      time_ratio=entry[backend]["seconds"] / entry[reference]["seconds"])
                print(f"[render] {name} / {backend} vs {reference}: FLIP {mean_flip:.4f}, PSNR {psnr:.1f} dB, "
                      f"time x{entry[backend]['time_ratio']:.2f}")
            if "mlp" in images and "onnx" in images:
                entry["onnx_vs_mlp_max_abs"] = float(np.abs(images["onnx"] - images["mlp"]).max())
            side_by_side(images, flip_maps, entry, out / f"{name}_side_by_side.png", name)
            summary["scenes"][name] = entry
        bar.close()

        if r.mono_check and mi.is_spectral and "table" in props:
            summary["mono_check"] = mono_check(mi, cfg, props["table"], out)
        if r.explicit and "table" in props:
            summary["explicit"] = explicit_check(mi, cfg, props, out_root, out)

    RenderSummary(**summary).write(out / "summary.json")
    write_metrics(cfg, out_root, "render", headline(summary))
    return out


def headline(summary: dict) -> dict:
    """The render summary's figures for ``dvc metrics``: times, FLIP, closure ratios."""
    keys = ("seconds", "flip", "psnr", "time_ratio")
    out = {name: {b: {k: v[k] for k in keys if k in v} for b, v in scene.items() if isinstance(v, dict)}
           for name, scene in summary["scenes"].items()}
    if "mono_check" in summary:
        out["mono_check_max_rel_diff"] = summary["mono_check"]["max_rel_diff"]
    ply = summary.get("explicit", {}).get("ply", {})
    out.update({f"ply_{b}_vs_explicit": v["mean_vs_explicit"] for b, v in ply.items() if "mean_vs_explicit" in v})
    return out


def side_by_side(images: dict, flip_maps: dict, entry: dict, path: Path, name: str) -> None:
    """Each backend's image, and the FLIP map of each neural image, with their figures."""
    cols = list(images)
    h, w = next(iter(images.values())).shape[:2]
    # each render at twice its pixel size (at least 4 in wide), so that noise and detail can be judged
    width_in = max(4.0, 2 * w / 100)
    fig, axes = plt.subplots(2, len(cols), figsize=(width_in * len(cols) + 1.2, 2 * width_in * h / w + 1.4),
                             squeeze=False, dpi=100, layout="constrained")
    for k, b in enumerate(cols):
        axes[0, k].imshow(to_srgb(images[b], entry["exposure"]), interpolation="nearest")
        axes[0, k].set_title(f"{b}: {entry[b]['seconds']:.2f} s", fontsize=10)
        if b in flip_maps:
            axes[1, k].imshow(np.clip(flip_maps[b], 0, 1), interpolation="nearest")
            axes[1, k].set_title(f"{b} against the table: FLIP {entry[b]['flip']:.3f}, PSNR {entry[b]['psnr']:.1f} dB",
                                 fontsize=10)
        for row in range(2):
            axes[row, k].set_axis_off()
    if flip_maps:  # the FLIP maps are magma-coloured: their scale
        fig.colorbar(ScalarMappable(Normalize(0, 1), "magma"), ax=axes[1, :], shrink=0.8,
                     label="FLIP error (0: the same)")
    fig.suptitle(f"{name}: {w} x {h} pixels, equal samples, one exposure; FLIP against the table (bottom)",
                 fontsize=11)
    save_figure(fig, path)


def mono_check(mi, cfg, table_props: dict, out: Path) -> dict:
    """The spectral render against mono renders per table wavelength combined with CIE + D65."""

    r = cfg.render
    small = cfg.model_copy(update={"render": r.model_copy(update={"width": r.mono_check_size[0],
                                                                  "height": r.mono_check_size[1]})})
    wl = BundleTable.load(table_props["table"]).wavelength
    spectral, t_spec, _ = render_timed(mi, scenes.ply_scene(mi, small, table_props, r.mono_check_spp))
    mono_variant = r.variant.replace("spectral", "mono")
    with mitsuba_ext.variant(mono_variant):
        t0 = time.perf_counter()
        monos = []
        for lam in tqdm(wl, desc="mono check", unit="render"):
            bsdf = {**table_props, "wavelength": float(lam)}
            monos.append(np.array(mi.render(mi.load_dict(scenes.ply_scene(mi, small, bsdf, r.mono_check_spp))))[..., 0])
        t_mono = time.perf_counter() - t0
    combined = np.einsum("ck,khw->hwc", spectral_weights(wl, "rgb"), np.stack(monos)).astype(np.float32)
    h = combined.shape[0]
    band = slice(h // 2 - h // 8, h // 2 + h // 8)  # rows that see the ply
    a, b = spectral[band].reshape(-1, 3).mean(0), combined[band].reshape(-1, 3).mean(0)
    rel = float(np.max(np.abs(a / b - 1)))
    e = exposure_of(spectral)
    save_png(np.concatenate([to_srgb(spectral, e), to_srgb(combined, e)], 1), out / "mono_check.png")
    print(f"[render] spectral vs {len(wl)} mono renders + CIE: mean colour of the ply {a.round(4)} vs "
          f"{b.round(4)} (max rel. diff {rel:.3%})")
    return {"spectral_mean": a.tolist(), "mono_combined_mean": b.tolist(), "max_rel_diff": rel,
            "spectral_seconds": t_spec, "mono_seconds": t_mono, "n_wavelengths": len(wl)}


def explicit_check(mi, cfg, props: dict, out_root, out: Path) -> dict:
    """The chain's closure, measured (``pipeline.closure``), and the ply with explicit fibers.

    * **far field** (mono, one wavelength): ``fiber_bundle`` with the table and with the
      MLP, rendered / predicted at the closure direction pairs;
    * **explicit fibers against the bake**, bin by bin (mono): the bake's own arrangement
      and fiber, each fiber a cylinder, 16 turns x 16 views per bin beside the cone;
    * **the ply scene** (this stage's variant, sun and sky): the explicit fibers averaged
      over 16 views of the arrangement (a circle's turns: its table is the rotation average;
      an ellipse keeps its orientation; a twisted ply's views spread over its period's
      heights where a turn is no shift) against the bundle with the table and with the
      MLP: mean radiance over the ply, FLIP.

    Writes ``closure.png`` (the first two) and ``explicit_vs_bundle.png``.
    """
    r = cfg.render
    root = config_dir(cfg, out_root)
    fiber_table = root / "fiber" / "fiber_table.npz"
    ply_model = build_ply(cfg)                    # what the bake traced: parallel fibers or helices
    bundle = cross_section(ply_model)
    twisted = ply_model is not bundle
    raw = BundleTable.load(props["table"]["table"])
    lam = int(np.argmin(np.abs(raw.wavelength - 550.0)))
    wl = float(raw.wavelength[lam])
    result = {"fibers": len(bundle.centers), "wavelength_nm": wl}

    # -- far field and explicit bins, one wavelength ------------------------------------
    with mitsuba_ext.variant("llvm_ad_mono"):
        Rb = bundle.bounding_radius * scenes.UM
        # off the cone's exact line: a node's cone lies on a bin edge of the table, where it jumps
        pairs = closure.direction_pairs(cone_offsets_deg=(0.8, -1.7))
        far = {b: closure.far_field_ratios(mi, {**props[b], "wavelength": wl, "up": closure.UP}, Rb,
                                           closure.evaluator(mi, b, props[b].get("table") or props[b].get("model"), wl),
                                           pairs)
               for b in ("table", "mlp") if b in props}
        result["far_field"] = far
        # the explicit fibers leave their fibers as the bake did (closure compares like with like)
        exit_model = raw.meta.get("exit", "uniform")
        fiber_bsdf = closure.explicit_fiber(fiber_table, exit_model, wl)
        result["exit"] = exit_model
        # dphi ~ 20, 90, 160 deg; a twisted ply is chiral: -20 deg as well
        phi_bins = [int(len(raw.phi_o) * f) for f in ((0.45,) if twisted else ()) + (0.55, 0.75, 0.95)]
        nodes = [j for j, ti in enumerate(raw.theta_i) if 5 < abs(np.rad2deg(ti)) < 85][::2]
        cases = [c for c in closure.cone_cases(raw, phi_bins, beside=False) if c[0] in nodes]
        explicit = closure.explicit_bins(mi, ply_model, fiber_bsdf, raw, cases, lam, spp=8, resolution=32)
        result["explicit_bins"] = explicit
        kind = "helical fibers, " if twisted else ""
        closure.plot(far, {f"{cfg.fiber.model} fiber, {kind}{cfg.name} ply ({len(bundle.centers)} fibers)": explicit},
                     out / "closure.png", f"{cfg.name}: rendered against what each renderer was given ({wl:.0f} nm)")
        within = np.mean([abs(e["ratio"] - 1) <= 0.02 + 3 * e["sigma"] for e in explicit])
        ff = np.concatenate([[row[3] for row in rows] for rows in far.values()])
        print(f"[render] closure: far field {ff.min():.4f} .. {ff.max():.4f} ({len(ff)} renders); explicit fibers vs "
              f"bake {within:.0%} of {len(explicit)} bins within 3 sigma + 2%")

    # -- the ply scene: explicit fibers, 16 views, against the bundle ----------------------
    # a circle's table holds every turn of its arrangement, an ellipse's its one orientation;
    # a twisted ply's views also spread over the heights of its period where a turn is no shift
    turns = 16
    per_turn = max(1, r.explicit_spp // turns)
    placements = closure.view_placements(ply_model, turns, scenes.UM, bundle.is_circle)
    imgs, t_explicit = [], 0.0
    with tempfile.TemporaryDirectory(prefix="bcsdf-helices-") as tmp:
        # one scene, its fibers moved between views: one kernel for every view
        scene = mi.load_dict(scenes.explicit_scene(mi, cfg, ply_model, fiber_table, per_turn, plugin=fiber_bsdf["type"],
                                                   curve_file=Path(tmp) / "helices.txt",
                                                   reach=max(abs(shift) for _, shift in placements)))
        fibers = closure.TurnedFibers(mi, scene, [1.0, 0.0, 0.0])
        for k, (turn, shift) in enumerate(tqdm(placements, desc="explicit fibers", unit="view")):
            fibers.place(turn, shift)
            # each view once at its own seeds; the first also compiles the kernel, untimed
            img, seconds, _ = render_timed(mi, scene, warm=k == 0, seed=2 * k)
            imgs.append(img)
            t_explicit += seconds
    explicit_img = np.mean(imgs, 0)
    rows = scenes.ply_rows(cfg, explicit_img.shape[0])
    expo = exposure_of(explicit_img)
    save_images(mi, explicit_img, out / "explicit_fibers", expo)
    # the explicit mean's own uncertainty, from its views' spread: sun glints through the
    # fibers make a view's mean radiance vary by 10-20% at these samples
    view_means = np.array([img[rows].sum(-1).mean() for img in imgs])
    rel_stderr = float(view_means.std(ddof=1) / np.sqrt(len(view_means)) / max(view_means.mean(), 1e-30))
    ply = {"explicit": {"spp": per_turn * turns, "seconds": t_explicit, "mean_relative_stderr": rel_stderr,
                        "mean_radiance": explicit_img[rows].reshape(-1, 3).mean(0).tolist()}}
    strip = [to_srgb(explicit_img, expo)]
    noise = None
    for backend in [b for b in ("table", "mlp") if b in props]:
        img, seconds, _ = render_timed(mi, scenes.ply_scene(mi, cfg, props[backend], r.spp, 0, twist_turns=0.0),
                                       backend)
        flip, psnr, _ = flip_and_psnr(explicit_img, img, expo)
        mean = img[rows].reshape(-1, 3).mean(0)
        ratio = float(mean.sum() / explicit_img[rows].reshape(-1, 3).mean(0).sum())
        ply[backend] = {"spp": r.spp, "seconds": seconds, "mean_radiance": mean.tolist(),
                        "mean_vs_explicit": ratio, "mean_vs_explicit_stderr": ratio * rel_stderr,
                        "flip_vs_explicit": flip}
        if backend == "table":  # what the bake's own noise alone would put between the two
            noise = table_noise(mi, cfg, props["table"], img, rows)
            ply[backend]["table_noise"] = noise
        strip.append(to_srgb(img, expo))
        print(f"[render] ply: bundle ({backend}) / explicit fibers (16 views) mean radiance {ratio:.4f} "
              f"+- {ratio * rel_stderr:.4f}" + (f" (the table's own noise: {ratio * noise['mean_relative']:.4f})"
                                                if backend == "table" else "")
              + f", FLIP {flip:.4f}; {seconds:.2f} s against {t_explicit:.1f} s")
    save_png(np.concatenate(strip, 0), out / "explicit_vs_bundle.png")
    result["ply"] = ply
    if twisted and "table" in props:
        result["parallel"] = what_parallel_misses(mi, cfg, props["table"], ply_model, fiber_table, explicit_img,
                                                  out, noise)
    return result


def what_parallel_misses(mi, cfg, table_props: dict, ply_model, fiber_table: Path, explicit_img, out: Path,
                         noise: dict | None = None) -> dict:
    """A twisted ply's explicit fibers against its own (twisted) table and against the table
    of the same cross-section baked with parallel fibers (here, with the twisted bake's
    nodes and bins, and as many path-node pairs):

    * **the ply scene**: mean radiance over the ply, FLIP, and the brightness along the ply
      (the perspective sweeps the view by +-30 deg along it), its relative L1 difference, and
      for the twisted table beside it the table's own noise in that figure (``noise``:
      :func:`table_noise`);
    * **the highlight**: the far field along a cut through it (``closure.theta_cut``: light
      at ``theta_i`` = 30 deg, seen sideways, ``theta_o`` from -80 to 80 deg), the explicit
      helices rendered in the closure scene against both tables' lookups; its position (the
      centroid of its upper half: ``closure.peak_and_width``) and its full width at half
      maximum.

    Writes ``parallel_table.npz`` and ``twisted_vs_parallel.png``."""

    r = cfg.render
    fiber = FiberTable.load(fiber_table)
    spec, _ = make_spec(cfg, ply_model, fiber)           # the twisted table's nodes and bins
    with mitsuba_ext.variant(cfg.bake.variant):
        t0 = time.perf_counter()
        # a 2D path serves every theta_i node, a twisted one a single node: 1 / n_theta_i of the
        # paths makes the parallel table about as precise as the twisted one
        paths = max(cfg.bake.paths_per_phi_i // len(spec.theta_i), 1)
        parallel = bake_unreduced(ply_model.bundle, fiber, spec, paths, seed=cfg.bake.seed)
        if not ply_model.bundle.is_circle:  # phi_i over 0..90 deg: the parallel ellipse's mirrors give the rest
            parallel.meta["reductions"] = dict(parallel.meta["reductions"], phi_i="mirror_xz")
        t_bake = time.perf_counter() - t0
        parallel.save(out / "parallel_table.npz")
    tables = {"twisted table": table_props["table"], "parallel table": out / "parallel_table.npz"}

    # -- the highlight: a cut through the far field, explicit helices against both lookups
    with mitsuba_ext.variant("llvm_ad_mono"):
        lam_nm = float(fiber.wavelength[np.argmin(np.abs(fiber.wavelength - 550.0))])
        theta_i, dphi = np.deg2rad(30.0), np.deg2rad(90.0)
        theta_o = np.deg2rad(np.arange(-80.0, 80.1, 4.0))
        bsdf = closure.explicit_fiber(fiber_table, "uniform", lam_nm)
        S_explicit, S_err = closure.theta_cut(mi, ply_model, bsdf, theta_i, dphi, theta_o)
        cut = {"theta_i_deg": 30.0, "dphi_deg": 90.0, "wavelength_nm": lam_nm, "theta_o_deg": np.rad2deg(theta_o).tolist(),
               "explicit helical fibers": S_explicit.tolist(), "explicit_sigma": S_err.tolist()}
        for name, path in tables.items():
            S = closure.evaluator(mi, "table", path, lam_nm)
            cut[name] = [S(0.0, theta_i, dphi, to) for to in theta_o]

    # -- the ply scene ----------------------------------------------------------------
    rows = scenes.ply_rows(cfg, explicit_img.shape[0])
    expo = exposure_of(explicit_img)
    images = {"explicit helical fibers": explicit_img}
    for name, table in tables.items():
        images[name], _, _ = render_timed(mi, scenes.ply_scene(mi, cfg, {**table_props, "table": str(table)},
                                                               r.spp, 0, twist_turns=0.0))
    result = {"parallel_bake_seconds": t_bake, "cut": cut}
    ref = explicit_img[rows].reshape(-1, explicit_img.shape[-1]).mean(0).sum()
    ref_profile = explicit_img[rows].sum(-1).mean(0)
    profiles = {}
    for name, img in images.items():
        profiles[name] = img[rows].sum(-1).mean(0)
        pos, width = closure.peak_and_width(np.rad2deg(theta_o), cut[name], smooth=0)
        entry = {"mean_vs_explicit": float(img[rows].reshape(-1, img.shape[-1]).mean(0).sum() / ref),
                 "profile_l1_vs_explicit": float(np.abs(profiles[name] - ref_profile).mean() / ref_profile.mean()),
                 "highlight_deg": pos, "highlight_fwhm_deg": width, "highlight_peak": float(np.max(cut[name]))}
        if name != "explicit helical fibers":
            entry["flip_vs_explicit"] = flip_and_psnr(explicit_img, img, expo)[0]
        if name == "twisted table" and noise is not None:
            entry["profile_l1_table_noise"] = noise["profile_l1"]
        result[name] = entry
        print(f"[render] twisted ply, {name}: mean radiance / explicit {entry['mean_vs_explicit']:.3f}, brightness "
              f"along the ply off by {entry['profile_l1_vs_explicit']:.1%}"
              + (f" (the table's own noise: {noise['profile_l1']:.1%})" if "profile_l1_table_noise" in entry else "")
              + "; highlight (theta_i 30 deg, sideways) at "
              f"theta_o {pos:+.1f} deg (centroid of its upper half), {width:.0f} deg wide, "
              f"peak {entry['highlight_peak']:.3g} /sr"
              + (f"; FLIP {entry['flip_vs_explicit']:.3f}" if "flip_vs_explicit" in entry else ""))
    plot_parallel_misses(images, profiles, result, expo, out / "twisted_vs_parallel.png", cfg.name)
    return result


def view_angle(n: int) -> np.ndarray:
    """The view's angle along the ply (deg) at each of ``n`` image columns (the ply scene's
    perspective camera, ``scenes.FOV_DEG`` across)."""

    u = (np.arange(n) + 0.5) / n * 2 - 1
    return np.rad2deg(np.arctan(u * np.tan(np.radians(FOV_DEG / 2))))


def plot_parallel_misses(images: dict, profiles: dict, result: dict, exposure: float, path: Path, name: str) -> None:
    """The three renders, labelled; their brightness along the ply; the highlight's cut."""


    n = len(images)
    fig = plt.figure(figsize=(12, 2.0 * n + 1.0))
    grid = fig.add_gridspec(n, 2, width_ratios=[1.1, 1.0])
    for k, (label, img) in enumerate(images.items()):
        ax = fig.add_subplot(grid[k, 0])
        ax.imshow(to_srgb(img, exposure))
        e = result[label]
        extra = (f", FLIP {e['flip_vs_explicit']:.3f}, along the ply off by {e['profile_l1_vs_explicit']:.1%}"
                 if "flip_vs_explicit" in e else "")
        ax.set_title(f"{label}: mean {e['mean_vs_explicit']:.3f} of explicit{extra}", fontsize=8)
        ax.axis("off")
    ax = fig.add_subplot(grid[: n // 2 + 1 if n > 2 else 1, 1])
    for label, prof in profiles.items():
        ax.plot(view_angle(len(prof)), prof, label=label)
    ax.set(xlabel="view angle along the ply (deg; the camera's 60 deg sweep)",
           ylabel="radiance (sum of RGB)", title="the ply scene: brightness along the ply")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(grid[n // 2 + 1 if n > 2 else 1:, 1])
    cut = result["cut"]
    to = np.array(cut["theta_o_deg"])
    ax.errorbar(to, cut["explicit helical fibers"], yerr=cut["explicit_sigma"], fmt="o", ms=3, capsize=2,
                label=f"explicit helical fibers (centre {result['explicit helical fibers']['highlight_deg']:+.1f} deg, "
                      f"FWHM {result['explicit helical fibers']['highlight_fwhm_deg']:.0f} deg)")
    for label in ("twisted table", "parallel table"):
        ax.plot(to, cut[label], label=f"{label} (centre {result[label]['highlight_deg']:+.1f} deg, "
                                       f"FWHM {result[label]['highlight_fwhm_deg']:.0f} deg)")
    ax.set(xlabel="theta_o (deg)", ylabel="S (1/sr)",
           title=f"the highlight: theta_i {cut['theta_i_deg']:.0f} deg, dphi {cut['dphi_deg']:.0f} deg, "
                 f"{cut['wavelength_nm']:.0f} nm")
    ax.legend(fontsize=7)
    fig.suptitle(f"{name}: a twisted ply's explicit fibers, its own table, and the parallel fibers' table",
                 fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
