"""Stage ``sweep``: a family of bakes over the axes of a config's ``sweep:`` section.

A researcher's unit of work is seldom one ply: it is a packing fraction against
another, a fiber colour against another, or several Poisson draws of one ply type. A
``sweep:`` section names config keys and their values; its **members** are every
combination (a grid, the first axis slowest), each a whole config named after its
values and validated like one (a bad axis or value is refused before anything runs,
naming the member and the key)::

    sweep:
      bundle.packing: [0.3, 0.5]
      bundle.seed: [1, 2, 3]        # seeds: the arrangement-to-arrangement spread

===============================  ====================================================
``bcsdf sweep CONFIG``           fiber and bake of every member, then the family page
``--workers N``                  on a local Dask cluster of N single-threaded workers
``--scheduler ADDRESS``          on an existing Dask cluster (or ``BCSDF_SCHEDULER``)
===============================  ====================================================

Each member has its own artifacts, ``artifacts/<name>/sweep/<member>/{fiber,bake}/``, and
stamps: a member that is up to date (``pipeline.graph``) is skipped, so a sweep grows
by editing its axes. Members that share their fiber settings share one tabulation. On
a cluster every remaining batch of every member is submitted at once (members x batches
as tasks; ``pipeline.cluster``), and each member's table is its own ``bcsdf bake``'s, bit
for bit. Interrupted, finished members are kept and partial ones resume from their
checkpoints.

The family summary, ``artifacts/<name>/sweep/``:

* ``family.json``, ``family.csv``: per member its values, fibers, packing, passthrough,
  albedo and absorption, each with its Monte Carlo error;
* ``family_<axis>.png``: passthrough and albedo against each axis;
* ``profile.png``: the azimuthal distribution of scattered light per member;
* ``spread.json`` (a ``bundle.seed`` axis): per ply type, the spread of passthrough and
  albedo across arrangements beside the Monte Carlo error of one bake;
* ``index.html``: all of it on one page, with each member's table slice.
"""

from __future__ import annotations

import contextlib
import html
import json
import shutil
from pathlib import Path

import matplotlib.pyplot as plt
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from models.bundle_table import BundleTable
from models.io import atomic_path, write_text

from .. import cluster, estimate, graph
from ..artifacts import stage_dir
from ..baking import Bake
from ..build import build_ply
from ..config import FIBER_SECTIONS
from ..loading import sweep_axes, sweep_members
from ..html import html_page, img_tag
from ..metrics import write_curve, write_metrics
from ..plots import save_figure
from ..summaries import BakeSummary

SEED = "bundle.seed"
THETA_I_SHOWN = 30.0  # deg: the incidence of the slices and profiles on the family page


def run(cfg, out_root="artifacts", workers=None, scheduler=None) -> Path:
    """Bake every member that is not up to date, then write the family summary."""
    if not cfg.sweep:
        raise ValueError(f"config {cfg.name} has no 'sweep:' section; add one, e.g. "
                         "sweep: {bundle.packing: [0.3, 0.5], bundle.seed: [1, 2]}")
    if cfg.bundle is None:
        raise ValueError(f"config {cfg.name} has no 'bundle:' section: a sweep bakes bundles")

    expanded = sweep_members(cfg)
    members = [m for _, m in expanded]
    root = stage_dir(cfg, "sweep", out_root)
    # every member's fibers are placed before any work: an arrangement that cannot be
    # drawn (a packing too dense for its radius) is refused before anything is baked
    bundles = {}
    for m in members:
        try:
            bundles[m.name] = build_ply(m)
        except ValueError as e:
            raise ValueError(f"sweep member {m.name}: {e}") from None

    tabulate_fibers(members, root)
    todo = [m for m in members if not graph.up_to_date("bake", m, root)[0]]
    print(f"[sweep] {cfg.name}: {len(members)} members, {len(members) - len(todo)} up to date, "
          f"{len(todo)} to bake", flush=True)
    if todo:
        bake_members(todo, bundles, root, workers, scheduler)
    return write_family(cfg, expanded, root, out_root)


# -- Fibers: one tabulation per distinct fiber setting -------------------------------
def tabulate_fibers(members, root: Path) -> None:
    made: dict[str, object] = {}  # fiber settings -> the member that holds their table
    for m in members:
        key = m.hash(*FIBER_SECTIONS)
        if graph.up_to_date("fiber", m, root)[0]:
            made.setdefault(key, m)
            continue
        if key in made:  # the same fiber: copy its artifacts rather than tabulate again
            for out in graph.spec("fiber", made[key], root)["outs"]:  # its folder and its metrics
                files = [out] if out.is_file() else sorted(p for p in out.rglob("*") if p.is_file())
                for f in files:
                    with atomic_path(root / m.name / f.relative_to(root / made[key].name)) as tmp:
                        shutil.copyfile(f, tmp)
        else:
            graph.run_stage("fiber", m, root)
            made[key] = m
        graph.stamp("fiber", m, root)


# -- Bakes: members x batches, here or on a cluster ----------------------------------
def bake_members(todo, bundles: dict, root: Path, workers, scheduler) -> None:
    """Bake ``todo``: each member is written and stamped as soon as its last batch is in;
    interrupted, the others keep their checkpoints (saved on ``bake.checkpoint_every_s``)."""

    bakes = [Bake(m, root, bundles[m.name]) for m in todo]

    def serial():
        for j, b in enumerate(bakes):
            mi.set_variant(b.cfg.bake.variant)  # a swept bake.variant changes it per member
            for _, i, tally in b.serial():
                yield j, i, tally

    left = sum(b.paths_left for b in bakes)
    with cluster.client(workers, scheduler) as dask_client, \
            tqdm(total=left, unit="path", unit_scale=True, desc=f"sweep ({len(bakes)} bakes)") as bar:
        batches = serial() if dask_client is None else cluster.ordered_tallies(dask_client, bakes)
        with contextlib.closing(batches):
            for j, i, tally in batches:
                b = bakes[j]
                bar.update(b.add(i, tally))
                if b.finished:
                    mi.set_variant(b.cfg.bake.variant)  # the summary's probe traces here
                    b.finish()
                    graph.stamp("bake", b.cfg, root, seconds=b.elapsed, work=estimate.work("bake", b.cfg),
                                probe=estimate.measured_probe())
                    bar.set_postfix(members=f"{sum(x.finished for x in bakes)}/{len(bakes)}", refresh=False)


# -- The family ----------------------------------------------------------------------
def member_record(point: dict, table, summary: BakeSummary) -> dict:
    """One member's row: its values and its figures with their Monte Carlo errors.

    The errors are the bake's own, from its batches' estimates (``baking.batch_means_error``):
    paths are stratified within a batch, so the binomial error of the passthrough would
    overstate its error, and the bins' errors in quadrature would overstate the albedo's
    (bins of one path are correlated).
    """
    def error(e):
        return float("nan") if e is None else e

    return {**point,
            "n_fibers": summary.n_fibers, "packing_fraction": summary.packing_fraction,
            "passthrough": float(np.mean(table.passthrough)),
            "passthrough_mc_error": error(summary.passthrough_mc_error),
            "albedo": float(np.mean(table.scattered)),
            "albedo_mc_error": error(summary.scattered_mc_error),
            "absorbed": float(np.mean(table.absorbed)), "bake_seconds": summary.bake_seconds}


def seed_spread(rows: list[dict], axes: dict) -> list[dict]:
    """Per ply type (the other axes' values): mean and spread over the seeds of
    passthrough and albedo, beside one bake's Monte Carlo error (rms over the seeds)."""
    others = [k for k in axes if k != SEED]
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(json.dumps({k: r[k] for k in others}, sort_keys=True), []).append(r)
    out = []
    for key, g in groups.items():
        rec = {**json.loads(key), "seeds": len(g)}
        for q in ("passthrough", "albedo"):
            v = np.array([r[q] for r in g])
            rec[f"{q}_mean"] = float(v.mean())
            rec[f"{q}_spread"] = float(v.std(ddof=1)) if len(v) > 1 else 0.0  # one draw to the next
            rec[f"{q}_mc_error"] = float(np.sqrt(np.mean([r[f"{q}_mc_error"] ** 2 for r in g])))
        out.append(rec)
    return out


def write_family(cfg, expanded, root: Path, out_root) -> Path:
    """The family summary of the members ``expanded`` (``sweep_members(cfg)``)."""

    axes, members = sweep_axes(cfg), [m for _, m in expanded]
    rows, tables = [], []
    for point, m in expanded:
        bake = root / m.name / "bake"
        table = BundleTable.load(bake / "bundle_table.npz")
        rows.append({"member": m.name, **member_record(point, table, BakeSummary.read(bake / "summary.json"))})
        tables.append(table)
    spread = seed_spread(rows, axes) if SEED in axes and len(axes[SEED]) > 1 else []

    write_text(root / "family.json", _json({"axes": axes, "members": rows, "seed_spread": spread}))
    write_curve(root / "family.csv", [{k: (json.dumps(v) if isinstance(v, (list, dict)) else v)
                                       for k, v in r.items()} for r in rows])
    if spread:
        write_text(root / "spread.json", _json(spread))
    for key in axes:
        plot_axis(rows, axes, key, root / f"family_{_file_part(key)}.png")
    plot_profiles(rows, tables, root / "profile.png")
    write_metrics(cfg, out_root, "sweep", {
        "members": len(rows),
        "passthrough": {r["member"]: r["passthrough"] for r in rows},
        "albedo": {r["member"]: r["albedo"] for r in rows},
        **({"seed_spread_over_mc_error": max(s["albedo_spread"] / max(s["albedo_mc_error"], 1e-12)
                                             for s in spread)} if spread else {})})
    write_text(root / "index.html", family_page(cfg, members, rows, spread, tables, root))
    print(f"[sweep] {cfg.name}: wrote {root / 'index.html'}")
    return root


def _json(data) -> str:
    """JSON with an unknown error (NaN: a bake of one batch per azimuth) as null."""
    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        return None if isinstance(v, float) and not np.isfinite(v) else v
    return json.dumps(clean(data), indent=1)


# -- Pictures ------------------------------------------------------------------------
def _file_part(key: str) -> str:
    return key.replace(".", "_")


def _numeric(values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def plot_axis(rows, axes, key, path: Path) -> None:
    """Passthrough and albedo against one axis: a line per combination of the other
    axes (seeds averaged, their spread as bars; thin bars: Monte Carlo error)."""

    values = axes[key]
    xs = values if _numeric(values) else list(range(len(values)))
    pos = {json.dumps(v, sort_keys=True): x for v, x in zip(values, xs)}
    others = [k for k in axes if k not in (key, SEED)]
    lines: dict[str, list[dict]] = {}
    for r in rows:
        lines.setdefault(", ".join(f"{k.rsplit('.', 1)[-1]}={r[k]}" for k in others), []).append(r)
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.8), dpi=110)
    for ax, q in zip(axs, ("passthrough", "albedo")):
        for label, group in lines.items():
            at: dict[float, list[dict]] = {}
            for r in group:
                at.setdefault(pos[json.dumps(r[key], sort_keys=True)], []).append(r)
            x = np.array(sorted(at))
            y = np.array([np.mean([r[q] for r in at[v]]) for v in x])
            mc = np.array([np.sqrt(np.mean([r[f"{q}_mc_error"] ** 2 for r in at[v]])) for v in x])
            if key == SEED:  # every draw is its own point
                ax.errorbar(x, y, yerr=mc, fmt="o", capsize=3, label=label or None)
                continue
            spread = np.array([np.std([r[q] for r in at[v]], ddof=1) if len(at[v]) > 1 else 0.0 for v in x])
            line = ax.errorbar(x, y, yerr=spread, fmt="o-", capsize=4, label=label or None)
            ax.errorbar(x, y, yerr=mc, fmt="none", elinewidth=3, alpha=0.4, color=line[0].get_color())
        ax.set(xlabel=key, ylabel=q, title=f"{q} (mean over incidence and wavelength)")
        if not _numeric(values):
            ax.set_xticks(xs, [str(v)[:16] for v in values], rotation=20)
        if any(lines):
            ax.legend(fontsize=7)
    note = "bars: spread over seeds; thick pale bars: Monte Carlo error" if SEED in axes and key != SEED \
        else "bars: Monte Carlo error of one bake"
    fig.suptitle(f"sweep over {key} ({note})", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def _shown(table) -> int:
    """The incidence the family page shows (a swept theta_i step may move it per member)."""
    return int(np.argmin(np.abs(np.rad2deg(table.theta_i) - THETA_I_SHOWN)))


def plot_profiles(rows, tables, path: Path) -> None:
    """Scattered light per radian of outgoing azimuth at one incidence (over theta_o
    and wavelength), one curve per member: where the family differs, not only by how much."""

    fig, ax = plt.subplots(figsize=(8, 4), dpi=110)
    cmap = plt.get_cmap("viridis", max(len(rows), 2))
    relative = tables[0].meta["reductions"]["phi_o"] == "relative"
    for n, (r, t) in enumerate(zip(rows, tables)):
        per_bin = np.einsum("pql,pq->p", t.values[0, _shown(t)].astype(np.float64), t.solid_angle) / t.values.shape[-1]
        phi = np.rad2deg(t.phi_o) % 360 if relative else np.rad2deg(t.phi_o)  # as the slices: forward mid-plot
        order = np.argsort(phi)
        ax.plot(phi[order], (per_bin / np.diff(t.phi_o_edges))[order], color=cmap(n), lw=1.2, label=r["member"])
    xlabel = "phi_o - phi_i [deg] (0: back to the light, 180: forward)" if relative else "phi_o [deg] (bundle frame)"
    ax.set(xlabel=xlabel,
           ylabel="scattered per radian of phi_o", yscale="log",
           title=f"azimuthal profile at theta_i = {np.rad2deg(tables[0].theta_i[_shown(tables[0])]):.0f} deg, phi_i = "
                 f"{np.rad2deg(tables[0].phi_i[0]):.0f} deg")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    save_figure(fig, path)


def family_page(cfg, members, rows, spread, tables, root: Path) -> str:
    axes = list(cfg.sweep)
    # (bake_seconds stays in family.json: on a cluster it is when a member finished, not its cost)
    quantities = ("n_fibers", "packing_fraction", "passthrough", "albedo", "absorbed")
    head = "".join(f"<th>{html.escape(h)}</th>" for h in ["member", *axes, *quantities])

    def cell(r, q):
        if q in ("passthrough", "albedo"):
            return f"{r[q]:.4f} &plusmn; {r[q + '_mc_error']:.4f}"
        if q == "absorbed":  # a lossless fiber's is rounding noise around 0 (1e-10)
            return f"{0.0 if abs(r[q]) < 1e-9 else r[q]:.4f}"
        return f"{r[q]:.4g}" if isinstance(r[q], float) else html.escape(str(r[q]))
    body = "".join("<tr>" + "".join(f"<td>{cell(r, q)}</td>" for q in ["member", *axes, *quantities]) + "</tr>"
                   for r in rows)
    paths = sorted({m.bake.paths_per_phi_i for m in members})
    sections = [("Members", f"<p>{len(rows)} members of {html.escape(cfg.name)}, baked with "
                            f"{' or '.join(f'{n:,}' for n in paths)} paths per incident azimuth (figures: mean "
                            "over incidence and wavelength &plusmn; Monte Carlo error, from the bake's batches)."
                            f"</p><table><tr>{head}</tr>{body}</table>")]
    sections.append(("Against each axis", "".join(img_tag(root, root / f"family_{_file_part(k)}.png", k)
                                                 for k in axes) + img_tag(root, root / "profile.png", "profiles")))
    if spread:
        others = [k for k in axes if k != SEED]
        head = "".join(f"<th>{html.escape(h)}</th>" for h in [*others, "seeds", "passthrough", "spread over seeds",
                                                                 "MC error", "albedo", "spread over seeds",
                                                                 "MC error"])
        body = "".join("<tr>" + "".join(f"<td>{html.escape(str(s[k]))}</td>" for k in others)
                       + f"<td>{s['seeds']}</td>"
                       + "".join(f"<td>{s[f'{q}_mean']:.4f}</td><td>{s[f'{q}_spread']:.4f}</td>"
                                 f"<td>{s[f'{q}_mc_error']:.4f}</td>" for q in ("passthrough", "albedo")) + "</tr>"
                       for s in spread)
        sections.append(("Arrangement against Monte Carlo", (
            "<p>One Poisson draw of the fibers differs from the next: the spread over seeds (standard deviation) is "
            "what a ply type's table is uncertain by, however many paths one bake traces; the Monte Carlo error "
            f"is one bake's.</p><table><tr>{head}</tr>{body}</table>")))
    # each member's slice as its bake drew it, linked where it lies (the page's folder holds the members)
    theta = [np.rad2deg(t.theta_i[_shown(t)]) for t in tables]
    pics = "".join(f"<h3>{html.escape(r['member'])}</h3>" + img_tag(
        root, root / r["member"] / "bake" / "slices" / f"phi_i_000.0_theta_i_{th:+05.1f}.png", r["member"],
        copy=False) for r, th in zip(rows, theta))
    sections.append((f"Table slices at theta_i = {theta[0]:.0f} deg", pics))
    return html_page(f"{cfg.name}, sweep", sections)
