"""Stage ``report``: one self-contained HTML page with its PNGs beside it.

``artifacts/<name>/report/index.html`` shows, for one config: the fiber model, the
bundle arrangement, table slices, the energy balance, the neural models against the
table (slices and error maps), error against run time, the exact versions and the
config. Every picture is copied next to the page, so the folder can be sent as is.
Parts of the pipeline that have not run (or do not exist yet) are said to be missing,
not silently dropped.
"""

from __future__ import annotations

import html
import json
from importlib import metadata
from pathlib import Path

import drjit as dr
import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
import yaml

from mitsuba_ext.neural import DrJitMLP
from models.io import write_text
from models.jit import to_drjit
from models.neural import bin_average, far_field, table_cells

from ..artifacts import config_dir, failure_dir, load_bundle_table, model_size, read_failure, stage_dir
from ..build import code_version
from ..graph import stamp_path
from ..html import html_page, img_tag, not_run
from ..loading import sweep_axes
from ..plots import pareto, save_figure, spectral_image, theta_rows
from ..summaries import BakeSummary, ClothSummary, FamilySummary, FiberSummary, RenderSummary, TrainSummary

PACKAGES = ("numpy", "scipy", "mitsuba", "drjit", "torch", "onnx", "onnxruntime", "colour-science", "pydantic")


def run(cfg, out_root="artifacts") -> Path:
    root = config_dir(cfg, out_root)
    out = root / "report"
    out.mkdir(parents=True, exist_ok=True)
    sections = []

    # -- fiber -----------------------------------------------------------------
    fiber = root / "fiber"
    if (fiber / "summary.json").exists():
        s = FiberSummary.read(fiber / "summary.json")
        E = np.asarray(s.energy)
        pics = sorted(fiber.glob("theta_i_*.png"))
        chosen = [p for p in pics if p.name in ("theta_i_00.0.png", "theta_i_30.0.png", "theta_i_60.0.png")] or pics[:3]
        body = (f"<p>Model <b>{html.escape(s.model)}</b>, {len(s.theta_i_deg)} incident longitudes x "
                f"{len(s.wavelength_nm)} wavelengths, tabulated in {s.tabulate_seconds:.2f} s; albedo "
                f"{E.min():.4f} .. {E.max():.4f}.</p>")
        body += "".join(img_tag(out, p, f"fiber, {p.stem}") for p in chosen + [fiber / "energy.png"])
        sections.append(("Single-fiber model", body))
    else:
        sections.append(("Single-fiber model", not_run("bcsdf fiber")))

    # -- bake --------------------------------------------------------------------
    bake = root / "bake"
    if (bake / "summary.json").exists():
        s = BakeSummary.read(bake / "summary.json")
        body = (f"<p>{s.n_fibers} fibers, packing {s.packing_fraction:.3f}; {s.paths:,} paths, "
                f"{s.vertices:,} vertices in {s.bake_seconds:.1f} s. Energy (mean over incidence and "
                f"wavelength): scattered {s.scattered:.4f}, passthrough {s.passthrough:.4f}, "
                f"absorbed {_f4(s.absorbed)}, lost {_f4(s.lost)}, total {s.total:.4f} (largest "
                f"deviation from 1 of any incidence and wavelength: {s.max_abs_energy_error:.4f}).</p>")
        share, wl = s.single_share, cfg.wavelengths.grid()
        body += (f"<p>Of the scattered light, {share[0]:.0%} at {wl[0]:.0f} nm and {share[-1]:.0%} at "
                 f"{wl[-1]:.0f} nm left the ply after one fiber event (the rest after several; "
                 "<code>single</code> in the table, right panel of the energy plot).</p>")
        b = cfg.bake
        body += (f"<p>Output bins: {b.n_phi_o} in phi_o; {b.n_theta_o} in theta_o, "
                 + (f"following the specular cone (a {b.cone_bin_deg:g}-deg bin centred on the cone of every "
                    f"theta_i node ({b.theta_i_said()}), equal bins between)"
                    if b.theta_o_layout == "cone" else "equal") + ".</p>")
        r = s.reductions
        used = ", ".join(f"{k}: {v}" for k, v in r.used.items() if v) or "none"
        body += (f"<p>Symmetry reductions ({html.escape(used)}): {r.reduced_incidences[0]} x "
                 f"{r.reduced_incidences[1]} incidences (phi_i x theta_i), table {r.reduced_bytes / 1e6:.2f} MB, "
                 f"bake {r.reduced_seconds:.1f} s; without them {r.full_incidences[0]} x "
                 f"{r.full_incidences[1]} incidences, {r.full_bytes / 1e6:.2f} MB and "
                 f"{r.full_seconds:.1f} s (the cost per azimuth measured on {r.probe_paths:,} paths "
                 f"through both, scaled to this bake).</p>")
        slices = sorted((bake / "slices").glob("*.png"))
        chosen = [p for p in slices if "theta_i_+30.0" in p.name or "theta_i_+60.0" in p.name][:4] or slices[:2]
        body += "".join(img_tag(out, p, p.stem) for p in [bake / "arrangement.png", *chosen, bake / "energy.png"])
        body += exit_section(s.exit)
        sections.append(("Bundle and baked table", body))
    else:
        sections.append(("Bundle and baked table", not_run("bcsdf bake")))

    # -- neural ------------------------------------------------------------------
    train = root / "train"
    if cfg.bundle is not None and (root / "export").exists():
        rows, points = [], []
        for name in cfg.train.models:
            p = train / name / "summary.json"
            if p.exists():
                m = TrainSummary.read(p)
                points.append({"label": f"{name} {cfg.train.models[name]}", "bytes": 4 * (m.parameters + m.gain_values),
                               "train_s": m.train_seconds, "error": m.relative_l1, "noise": m.table_noise_l1})
                calibration = (f"{m.worst_albedo_error_before:.2%} &rarr; {m.worst_albedo_error_after:.2%}"
                               if m.worst_albedo_error_after is not None else "-")
                rows.append(f"<tr><td>{name}</td><td>{cfg.train.models[name]}</td><td>{m.parameters}</td>"
                            f"<td>{m.epochs}</td><td>{m.train_seconds:.1f}</td><td>{m.relative_l1:.2%}</td>"
                            f"<td>{m.table_noise_l1:.2%}</td><td>{m.noise_ratio:.2f}</td>"
                            f"<td>{calibration}</td></tr>")
        body = ("<table><tr><th>model</th><th>hidden</th><th>parameters</th><th>epochs</th><th>train s</th>"
                "<th>held-out core rel. L1</th><th>table noise, same bins</th><th>error / table noise</th>"
                "<th>worst albedo error, energy gain</th></tr>"
                + "".join(rows) + "</table>"
                "<p>Error and noise are one definition (docs/DESIGN.md, \"The neural model\"): the relative L1 "
                "over the held-out bins among those holding 90% of each incident direction's energy, the model's "
                "bin averages against the table, and the table's expected distance from its own mean on the same "
                "bins; an error / noise near 1 is as close as the bake can tell.</p>")
        if points:   # the models' Pareto front: error against size and training time (make bench-encoding: more)
            pareto(points, out / "pareto.png", "held-out relative L1 of the core",
                   f"{cfg.name}: the trained models, error against size and training time",
                   (points[0]["noise"], "the table's own noise on the same bins"))
            body += img_tag(out, out / "pareto.png", "error against bytes and training seconds", copy=False)
        body += "".join(img_tag(out, train / n / "loss.png", f"loss, {n}") for n in cfg.train.models
                        if (train / n / "loss.png").exists())
        body += ("<p>Training schedules and where a step's time goes: <code>make bench-train</code>, "
                 "docs/BENCHMARKS.md, \"Training schedules\".</p>")
        body += compare_slices(cfg, out_root, out)
        bench = root / "export" / "error_vs_time.json"
        if bench.exists():  # measured by the export stage
            result = json.loads(bench.read_text())
            body += (f"<p>Error against run time ({result['queries']:,} queries per timing; the errors as above, "
                     f"the table's own noise on those bins {result['table_noise_l1']:.2%}).</p>")
            body += img_tag(out, root / "export" / "error_vs_time.png", "error against run time")
            body += _rows_table(result["rows"])
        else:
            body += not_run("bcsdf export")
        sections.append(("Neural compression", body))
    else:
        sections.append(("Neural compression", not_run("bcsdf train && bcsdf export")))

    sections.append(("Renders and FLIP maps", render_section(cfg, root, out)))
    if cfg.cloth is not None:
        sections.append(("Cloth", cloth_section(root, out)))
    sections.append(("Numerical stability", stability_section(root, failure_dir(cfg, "stability", out_root))))
    if cfg.sweep:
        sections.append(("Family (sweep)", sweep_section(cfg, root)))
    if cfg.family is not None:
        sections.append(("One model of the family", family_section(cfg, root, out)))

    # -- versions and config ---------------------------------------------------------
    versions = "".join(f"<tr><td>{p}</td><td>{_version(p)}</td></tr>" for p in PACKAGES)
    sections.append(("Versions and config",
                     f"<p>code {code_version()}, config hash {cfg.hash()}</p><table>{versions}</table>"
                     f"<pre>{html.escape(yaml.safe_dump(cfg.model_dump(mode='json'), sort_keys=False))}</pre>"))

    sections = [(title, "".join(failure_note(cfg, st, out_root) for st in SECTION_STAGES.get(title, ())) + body)
                for title, body in sections]
    sections.insert(0, ("Summary", summary_section(cfg, root, out_root)))
    page = html_page(cfg.name, sections)
    write_text(out / "index.html", page)
    print(f"[report] wrote {out / 'index.html'}")
    return out


def _f4(x: float) -> str:
    """Four decimals, without the ``-0.0000`` of a float error below them."""
    return f"{0.0 if abs(x) < 5e-5 else x:.4f}"


def summary_section(cfg, root: Path, out_root) -> str:
    """What to use, at what error and cost, and how long each stage took: the page in short.

    The model to render with is the smallest whose held-out error is within 1.2x of the
    best one's and whose albedo error is below 2% (the one the renders use is named too);
    its cost is the Dr.Jit evaluator's against the table's multilinear lookup, from the
    export stage's measurement.
    """

    lines = []
    summaries = {n: TrainSummary.read(root / "train" / n / "summary.json") for n in cfg.train.models
                 if (root / "train" / n / "summary.json").exists()}
    if cfg.bundle is not None and summaries:
        best = min(m.relative_l1 for m in summaries.values())
        fits = [n for n, m in summaries.items() if m.relative_l1 <= 1.2 * best
                and (m.worst_albedo_error_after or 0.0) < 0.02]
        pick = min(fits or summaries, key=lambda n: summaries[n].parameters)
        m = summaries[pick]
        cost = ""
        evt = root / "export" / "error_vs_time.json"
        if evt.exists():
            rows = json.loads(evt.read_text())["rows"]
            jit = next((r for r in rows if r["method"] == f"mlp {pick}" and r["backend"] == "drjit"), None)
            lin = next((r for r in rows if r["method"] == "table linear" and r["backend"] == "drjit"), None)
            if jit and lin:
                cost = (f", {jit['ns_per_query']:.0f} ns per query in Dr.Jit ({jit['ns_per_query'] / lin['ns_per_query']:.2f}x "
                        f"the table's lookup), {lin['bytes'] / jit['bytes']:.0f}x smaller than the table")
        albedo = m.worst_albedo_error_after
        lines.append(f"<p><b>Model to render with: {html.escape(pick)}</b> {cfg.train.models[pick]} "
                     f"({m.parameters:,} parameters): held-out relative L1 {m.relative_l1:.1%} (the table's own "
                     f"noise on those bins {m.table_noise_l1:.1%})"
                     + (f", worst albedo error {albedo:.2%}" if albedo is not None else "") + f"{cost}.")
        used = model_size(cfg)
        lines.append(f" The renders below use <b>{html.escape(used)}</b> (<code>render.model</code>).</p>"
                     if used != pick else " The renders below use it (<code>render.model</code>).</p>")
    times = []
    for stage in ("fiber", "bake", "train", "export", "render", "cloth", "stability", "sweep", "family"):
        p = stamp_path(stage, cfg, out_root)
        if p.exists():
            times.append(f"<td>{stage}</td><td>{json.loads(p.read_text()).get('seconds', float('nan')):.1f}</td>")
    if times:
        lines.append("<p>Seconds per stage (the last run of each):</p><table><tr><th>stage</th><th>seconds</th></tr>"
                     + "".join(f"<tr>{t}</tr>" for t in times) + "</table>")
    return "".join(lines) or "<p>Nothing has run yet: <code>bcsdf run CONFIG</code>.</p>"


def compare_slices(cfg, out_root, out) -> str:
    """Table against each model at two incidences: sRGB slices and a relative error map."""

    mi.set_variant(cfg.bake.variant)
    table, _ = load_bundle_table(cfg, out_root)
    relative = table.meta["reductions"]["phi_o"] == "relative"
    name = model_size(cfg)  # the model the renders use
    mlp = DrJitMLP(stage_dir(cfg, "export", out_root) / name / "weights.npz")
    body = (f"<p>Table against model <b>{name}</b> (Dr.Jit evaluator), the model's bin averages (4 x 4 "
            "points per bin) as a table value is an average over its bin.</p>")

    def predict(*queries):
        S = mlp.eval(*(to_drjit(mi.Float, np.asarray(a, np.float32)) for a in queries))
        dr.eval(S)
        return np.stack([s.numpy() for s in S], -1).astype(np.float64)
    predict = far_field(predict, mlp.spec)   # a near-field model's far field: its mean over the offset
    cells = table_cells(table).reshape(table.values.shape[:4] + (6,))
    for target in (30.0, 60.0):
        j = int(np.argmin(np.abs(np.rad2deg(table.theta_i) - target)))
        ref = table.values[0, j].astype(np.float64)
        pred = bin_average(predict, cells[0, j].reshape(-1, 6)).reshape(ref.shape)
        tag = f"{int(target):02d}"
        extent = (0, 360, -90, 90) if relative else (-180, 180, -90, 90)
        roll = len(table.phi_o) // 2 if relative else 0
        scale = None  # the model's image on the table's tone map, so that their greys compare
        for label, data in (("table", ref), (f"model {name}", pred)):
            scale = spectral_image(np.roll(theta_rows(data.transpose(1, 0, 2), table.theta_o_edges), roll, axis=1),
                                   table.wavelength,
                                   out / f"compare_{label.split()[0]}_{tag}.png",
                                   f"{label}: S at theta_i = {np.rad2deg(table.theta_i[j]):.0f} deg, "
                                   f"bin averages (tone map of the table)", extent=extent, scale=scale)
        err = np.abs(pred - ref).mean(-1) / max(ref.mean(-1).max(), 1e-30)
        fig, ax = plt.subplots(figsize=(12, 3.6), dpi=110)
        im = ax.imshow(np.roll(theta_rows(err.T, table.theta_o_edges), roll, axis=1), origin="lower", aspect="auto",
                       extent=extent, cmap="magma")
        fig.colorbar(im, ax=ax, label="|model - table| / table peak\n(mean over wavelengths)")
        xlabel = "dphi = phi_o - phi_i [deg]" if relative else "phi_o [deg] (bundle frame)"
        ax.set(xlabel=xlabel, ylabel="theta_o [deg]", title=f"error map, theta_i = {target:.0f} deg")
        fig.tight_layout()
        save_figure(fig, out / f"compare_error_{tag}.png")
        body += "".join(f'<img src="compare_{k}_{tag}.png" alt="{k} {tag}">' for k in ("table", "model", "error"))
    return body


EXIT_WORDS = {"uniform": "light leaves a fiber anywhere on its outgoing side (h uniform), whatever its path",
              "entry": "every path leaves where the light entered",
              "lobe": "each path of the ray model leaves from its own exit point, at the ray's real offset h",
              "curve": "as from Mitsuba's curves: light lights both ends of its chord, each shows the BSDF at its "
                       "own offset (what Mitsuba's hair on curves renders; docs/DESIGN.md)"}


def exit_section(exit_model: str) -> str:
    """Which exit model the bake used, in words; every exit model against exact geometry is
    the exit bench's (docs/BENCHMARKS.md, "Exit models")."""
    return (f"<p>Exit model <b>{html.escape(exit_model)}</b>: {html.escape(EXIT_WORDS.get(exit_model, ''))}. "
            "Every exit model against exact geometry (smooth dielectric circles: Snell, Fresnel, nothing "
            "modelled): <code>make bench-exit</code>, docs/BENCHMARKS.md, \"Exit models\".</p>")


def stability_section(root: Path, failed: Path) -> str:
    path = root / "stability" / "stability.json"
    partial = failed / "stability.json"
    if partial.exists():  # the last run failed: its table is the diagnosis
        path = partial
    if not path.exists():
        return not_run("bcsdf stability")
    rows = json.loads(path.read_text())
    failed = sum(not r["passed"] for r in rows)
    body = (f"<p>{len(rows) - failed} of {len(rows)} checks pass (<code>bcsdf stability</code>; the cases are "
            "listed in <code>pipeline/stages/stability.py</code>, each is also a test; a limit that rounding "
            "sets is derived from the arithmetic, as its last column says).</p>")
    body += ("<table><tr><th>case</th><th>quantity</th><th>invariant</th><th>value</th><th>limit</th><th></th>"
             "<th>where the limit comes from</th></tr>")
    body += "".join(f"<tr><td>{html.escape(r['case'])}</td><td>{html.escape(r['quantity'])}</td>"
                    f"<td>{html.escape(r['invariant'])}</td><td>{r['value']:.3e}</td><td>{r['limit']:.1e}</td>"
                    f"<td>{'pass' if r['passed'] else '<b>FAIL</b>'}</td>"
                    f"<td style='text-align:left'>{html.escape(r.get('derivation', ''))}</td></tr>" for r in rows)
    return body + "</table>"


# the stages each section shows, for the note that one of them failed
SECTION_STAGES = {"Single-fiber model": ("fiber",), "Bundle and baked table": ("bake",),
                  "Neural compression": ("train", "export"), "Renders and FLIP maps": ("render",),
                  "Cloth": ("cloth",), "Numerical stability": ("stability",), "Family (sweep)": ("sweep",),
                  "One model of the family": ("family",)}


def failure_note(cfg, stage: str, out_root) -> str:
    """A paragraph saying that ``stage``'s last run failed and why ('' if it did not)."""
    reason = read_failure(cfg, stage, out_root)
    if reason is None:
        return ""
    return (f"<div class=missing><p><b>{html.escape(stage)} failed</b> (its last good outputs, if any, are shown; "
            f"its partial results are in <code>failed/{html.escape(stage)}/</code>):</p>"
            f"<pre>{html.escape(reason)}</pre></div>")


def render_section(cfg, root: Path, out: Path) -> str:
    """Table against neural renders (times, FLIP, PSNR), the spectral check and the
    explicit-fiber ground truth, from ``render/summary.json``."""
    path = root / "render" / "summary.json"
    if cfg.bundle is None:
        return "<p>This config has no bundle, so nothing to render.</p>"
    if not path.exists():
        return not_run("bcsdf render")
    s = RenderSummary.read(path)
    body = (f"<p>Mitsuba {html.escape(s.variant)}, {s.size[0]} x {s.size[1]} pixels, {s.spp} samples "
            f"per pixel, integrator <code>bundle_path</code>; neural model: {s.model or '-'}. Times are of a "
            "second render (kernels compiled); FLIP (LDR) and PSNR against the table's image.</p>")
    rows = []
    for scene, entry in s.scenes.items():
        for backend, e in entry.items():
            if not isinstance(e, dict):
                continue
            flip = f"{e['flip']:.4f}" if "flip" in e else "reference"
            psnr = f"{e['psnr']:.1f}" if "psnr" in e else ""
            ratio = f"{e['time_ratio']:.2f}" if "time_ratio" in e else "1"
            rows.append(f"<tr><td>{scene}</td><td>{backend}</td><td>{e['seconds']:.2f}</td><td>{ratio}</td>"
                        f"<td>{flip}</td><td>{psnr}</td></tr>")
    body += ("<table><tr><th>scene</th><th>backend</th><th>render s</th><th>time / table</th><th>FLIP</th>"
             "<th>PSNR dB</th></tr>" + "".join(rows) + "</table>")
    for scene, entry in s.scenes.items():
        if "description" in entry:
            body += f"<p><b>{html.escape(scene)}</b>: {html.escape(entry['description'])}</p>"
        body += img_tag(out, root / "render" / f"{scene}_side_by_side.png", f"{scene}: table, neural, FLIP")
    if s.mono_check is not None:
        m = s.mono_check
        body += (f"<p>Spectral variant against {m['n_wavelengths']} mono renders combined with CIE 1931 and D65 "
                 f"(left and right): mean colour of the ply {np.round(m['spectral_mean'], 4).tolist()} against "
                 f"{np.round(m['mono_combined_mean'], 4).tolist()}, largest relative difference "
                 f"{m['max_rel_diff']:.2%}.</p>")
        body += img_tag(out, root / "render" / "mono_check.png", "spectral against mono renders + CIE")
    if s.explicit is not None:
        e = s.explicit
        ff = {k: np.array([row[3] for row in rows]) for k, rows in e["far_field"].items()}
        body += ("<h3>Closure: does a render reproduce what it was given?</h3>"
                 f"<p>Far field (docs/DESIGN.md; one cylinder, directional light, orthographic camera, "
                 f"{e['wavelength_nm']:.0f} nm): rendered / predicted "
                 + ", ".join(f"{k} {v.min():.4f} .. {v.max():.4f}" for k, v in ff.items())
                 + f" over {len(next(iter(ff.values())))} direction pairs.")
        bins = e["explicit_bins"]
        twisted = "parallel" in e
        within = np.mean([abs(b["ratio"] - 1) <= 0.02 + 3 * b["sigma"] for b in bins])
        shape = "a B-spline curve along its helix" if twisted else "a cylinder"
        body += (f" The bake's own {e['fibers']} fibers, "
                 f"each rendered as {shape} with the fiber model and averaged over the bin and 16 views "
                 f"(turns, or heights) of the arrangement, against the bake: {within:.0%} of {len(bins)} bins "
                 "within 3 standard errors + 2% "
                 f"(right, error bars 1 sigma of bake and render).</p>")
        body += img_tag(out, root / "render" / "closure.png", "closure: far field and explicit fibers against the bake")
        p_ = e["ply"]
        body += ("<p>The ply scene (sun and sky): every fiber its own cylinder, averaged over 16 views of the "
                 "arrangement (a circle's turns; a twisted ply's heights along its period where a turn is no shift) "
                 f"({p_['explicit']['spp']} samples in all, {p_['explicit']['seconds']:.1f} s; top), "
                 "against the bundle BSDF: "
                 + "; ".join(f"{k}: mean radiance x{v['mean_vs_explicit']:.3f}"
                             + (f" &plusmn; {v['mean_vs_explicit_stderr']:.3f}" if "mean_vs_explicit_stderr" in v else "")
                             + (f" (the table's own noise &plusmn; {v['mean_vs_explicit'] * v['table_noise']['mean_relative']:.3f})"
                                if "table_noise" in v else "")
                             + f", FLIP {v['flip_vs_explicit']:.3f}, {v['seconds']:.2f} s"
                             for k, v in p_.items() if k != "explicit")
                 + " (&plusmn; one standard error of the explicit mean, from its views' spread; the table's own "
                   "noise: the spread over tables redrawn within the bake's standard errors; the explicit "
                   "fibers are resolved, the bundle is its far field).</p>")
        body += img_tag(out, root / "render" / "explicit_vs_bundle.png",
                     "explicit fibers (16 views) against the bundle with the table and the MLP")
        if twisted:
            par = e["parallel"]
            cut = par["cut"]
            body += ("<h3>What the parallel table misses</h3><p>The twisted ply's explicit helical fibers against "
                     "its own table and against the table of the same cross-section baked with parallel fibers "
                     f"(baked here in {par['parallel_bake_seconds']:.0f} s). In the ply scene: "
                     + "; ".join(f"{k}: mean radiance x{v['mean_vs_explicit']:.3f}, brightness along the ply off by "
                                 f"{v['profile_l1_vs_explicit']:.1%}"
                                 + (f" (the table's own noise alone: {v['profile_l1_table_noise']:.1%})"
                                    if "profile_l1_table_noise" in v else "")
                                 + f", FLIP {v['flip_vs_explicit']:.3f}"
                                 for k, v in par.items() if isinstance(v, dict) and "flip_vs_explicit" in v)
                     + f". The highlight, a cut through the far field (light at theta_i {cut['theta_i_deg']:.0f} deg, "
                     f"seen at dphi {cut['dphi_deg']:.0f} deg, {cut['wavelength_nm']:.0f} nm; the explicit fibers "
                     "rendered in the closure scene; its position the centroid of its upper half): "
                     + "; ".join(f"{k}: at theta_o {v['highlight_deg']:+.1f} deg, peak {v['highlight_peak']:.3g} /sr, "
                                 f"{v['highlight_fwhm_deg']:.0f} deg wide (FWHM)"
                                 for k, v in par.items() if isinstance(v, dict) and "highlight_deg" in v)
                     + ".</p>")
            body += img_tag(out, root / "render" / "twisted_vs_parallel.png",
                            "explicit helical fibers, the twisted table, the parallel table; brightness along the ply; "
                            "the highlight's cut through the far field")
    return body


def cloth_section(root: Path, out: Path) -> str:
    """The yarn-level model's geometry, render times and pictures, from ``cloth/summary.json``."""
    path = root / "cloth" / "summary.json"
    if not path.exists():
        return not_run("bcsdf cloth")
    s = ClothSummary.read(path)
    g = s.geometry
    body = (f"<p>{g['yarn_curves']} yarn curves ({html.escape(g['curve_type'])}, {g['closed']} closed) wound into "
            f"{g['ply_curves']} plies of {g['plies']} per yarn (ply radius {g['ply_radius_mm']:.3g} mm at "
            f"{g['ply_offset_mm']:.3g} mm, pitch {g['ply_pitch_mm']:.3g} mm; yarn radius {g['yarn_radius_mm']:.3g} "
            f"mm), {g['control_points']:,} B-spline control points, built in {g['build_seconds']:.1f} s. The "
            f"centre lines' B-splines stay within {100 * g['centre_deviation_yarn_radii']:.2f}% of a yarn radius "
            f"of the file's curves. Ply table: {html.escape(g['ply_table'])}.</p>")
    if g.get("overlap_warning"):
        body += f"<p class=missing>{html.escape(g['overlap_warning'])}.</p>"
    if s.flyaways is not None:
        f, share = s.flyaways, s.flyaways["share"]
        body += (f"<p>Flyaways: {f['hairs']:,} hair-type flyaways of {html.escape(f['yarn'])} (Zhao et al. 2016; "
                 f"{f['hairs_per_mm']:.3g} per mm of ply, density x{f['density_scale']:g}), explicit fibers of radius "
                 f"{1000 * f['fiber_radius_mm']:.0f} um with <code>{html.escape(f['plugin'])}</code>, "
                 f"{f['control_points']:,} control points. Their share of the rendered radiance (the render with "
                 f"them minus the one without, over the one with; negative where they shade the plies more than "
                 f"they scatter; table, "
                 f"{share['size'][0]} x {share['size'][1]}): <b>{share['cloth_pixels']:.1%}</b> on the cloth's pixels "
                 f"({share['cloth_pixel_fraction']:.0%} of the frame), {share['frame']:.1%} of the whole frame.</p>")
    rows = "".join(f"<tr><td>{b}</td><td>{e['seconds']:.1f}</td><td>{e.get('flip', float('nan')):.4f}</td></tr>"
                   for b, e in s.backends.items())
    body += (f"<p>Mitsuba {html.escape(s.variant)}, {s.size[0]} x {s.size[1]} pixels, {s.spp} samples "
             f"per pixel, sun and sky (<code>sunsky</code>), <code>bundle_path</code> (<code>exit_split</code> "
             f"{html.escape(s.exit_split)}: where a ply's singly scattered light leaves it); "
             "times include the kernels' compilation; FLIP against the table's image.</p><table><tr><th>backend</th><th>render s</th>"
             f"<th>FLIP</th></tr>{rows}</table>")
    body += "".join(img_tag(out, root / "cloth" / f"cloth_{b}.png", f"cloth, {b}") for b in s.backends)
    return body


def sweep_section(cfg, root: Path) -> str:
    """A link to the family page ``bcsdf sweep`` writes (its own page: it is rewritten
    whenever the sweep grows, without this report)."""
    axes = ", ".join(f"{html.escape(k)} ({len(v)} values)" for k, v in sweep_axes(cfg).items())
    if not (root / "sweep" / "index.html").exists():
        return f"<p>Axes: {axes}.</p>" + not_run(f"bcsdf sweep {cfg.name}")
    return (f"<p>Axes: {axes}. The family's passthrough, albedo, profiles, slices and the spread of the "
            'arrangement against the Monte Carlo error: <a href="../sweep/index.html">the family page</a>.</p>')


def family_section(cfg, root: Path, out: Path) -> str:
    """The family's one model (``bcsdf family``): against packing beside the seeds' means,
    its errors at every packing (held out and trained), the held-out renders, the strip."""
    path = root / "family" / "summary.json"
    if not path.exists():
        return not_run(f"bcsdf family {cfg.name}")
    s = FamilySummary.read(path, cfg.name)
    pct = lambda v: "" if v is None else f"{v:.2%}"  # noqa: E731
    ONE_SEED = "one seed's core L1 vs the mean"  # noqa: N806
    SE, Z = "seeds' mean albedo se (median)", "albedo error over se (rms)"  # noqa: N806
    head = ("<tr><th>packing</th><th>set</th><th>seeds</th><th>worst albedo error</th>"
            "<th>the seeds' mean's albedo se (median)</th><th>albedo error / se (rms)</th><th>dyed (worst of three)</th>"
            "<th>core bins within the arrangement spread</th><th>core relative L1</th>"
            "<th>one seed's own core L1</th></tr>")
    body = "".join(f"<tr><td>{r['packing']:g}</td><td>{r['set']}</td><td>{r['seeds']}</td>"
                   f"<td>{pct(r['worst albedo error'])}</td><td>{pct(r.get(SE))}</td>"
                   f"<td>{'' if r.get(Z) is None else format(r[Z], '.2f')}</td>"
                   f"<td>{pct(r.get('worst dyed albedo error'))}</td>"
                   f"<td>{pct(r.get('core bins within the spread'))}</td><td>{pct(r['core L1 vs seed mean'])}</td>"
                   f"<td>{pct(r.get(ONE_SEED))}</td></tr>" for r in s.rows)
    text = (f"<p>One model, {html.escape(s.model)} {s.hidden} ({s.parameters:,} parameters, {s.parameter_bytes:,} "
            f"bytes of float32)" + (f", {s.orders} orders of scattering (dyed by <code>fiber_bundle</code>'s albedo)"
                                    if s.orders else "")
            + f", trained on {sum(r['seeds'] for r in s.rows if r['set'] == 'trained')} bakes at "
              f"packings {', '.join(f'{p:g}' for p in s.trained)} in {s.train_seconds:.0f} s ({s.epochs} epochs); "
              "<code>fiber_bundle</code>'s <code>packing</code> picks any packing between them at render time. Each "
              "packing against the mean of its seeds' direct bakes (the arrangement spread: their standard deviation)"
            + (f"; held out, never trained on: {', '.join(f'{p:g}' for p in s.held_out)}" if s.held_out else "")
            + ". The seeds' mean is known to its standard error (the arrangement spread over the root of the "
              "seeds' number): an albedo error below it cannot be told from zero.</p>")
    text += f"<table>{head}{body}</table>"
    if s.renders:
        text += "<p>The yarn rendered with the model against the seeds' mean table at each held-out packing:</p>"
        text += ("<table><tr><th>packing</th><th>FLIP</th><th>PSNR (dB)</th><th>model s</th><th>table s</th></tr>"
                 + "".join(f"<tr><td>{r['packing']:g}</td><td>{r['FLIP vs direct table']:.4f}</td>"
                           f"<td>{r['PSNR dB']:.1f}</td><td>{r['model s']:.2f}</td><td>{r['table s']:.2f}</td></tr>"
                           for r in s.renders) + "</table>")
    text += img_tag(out, root / "family" / "family.png", "the family against packing")
    if (root / "family" / "strip.png").exists():
        text += img_tag(out, root / "family" / "strip.png", "the yarn at five packings from one model file")
    return text


def _rows_table(rows) -> str:
    head = ("<tr><th>method</th><th>backend</th><th>bytes</th><th>ns/query</th><th>rel. L1</th><th>log MAE</th>"
            "<th>worst bin</th><th>albedo error</th></tr>")
    body = "".join(f"<tr><td>{r['method']}</td><td>{r['backend']}</td><td>{r['bytes']}</td>"
                   f"<td>{r['ns_per_query']:.1f}</td><td>{r['relative_l1']:.2%}</td><td>{r['log_mae']:.4f}</td>"
                   f"<td>{r['worst_bin']:.2%}</td><td>{r['albedo_error']:.2%}</td></tr>" for r in rows)
    return f"<table>{head}{body}</table>"


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


