"""Stage ``family``: one model of a sweep's plies, the packing fraction as an input.

A look-development artist turns the ply's density in the scene; a bake and a training run
per value would take minutes each. The sweep (``bcsdf sweep``) bakes the ply type at a
few packings, several Poisson draws each; this stage trains **one** model on all of them
(``models.fit.prepare_family``: each member's samples with its packing as a fifth input;
the passthrough, and with ``bake.orders`` the tail's ratio, kept per trained packing, and
the albedo held there by the energy gain; between the trained packings all three follow one
monotone cubic through them, ``models.fit.along_packing``), so that ``fiber_bundle``'s
``packing`` (a value or a texture) picks any packing in the trained range at render time,
and its ``albedo`` dyes it where the sweep baked the orders of scattering.

==========================  =========================================================
``family.model``            which of ``train.models`` is the network (default: the first)
``family.held_out``         packings of the sweep measured, not trained on (between trained
                            ones)
``family.held_out_seeds``   more draws baked at each held-out packing, where the seeds' mean
                            is the truth the model is held to
``family.strip``            render the yarn at five packings (and three dyes) from the file
==========================  =========================================================

The schedule and the loss are ``train:``'s. An example (``configs/packing_sweep.yaml``)::

    sweep:
      bundle.packing: [0.1, 0.2, 0.3]
      bundle.seed: [1, 2, 3]
    family: {held_out: [0.2]}

    bcsdf sweep configs/packing_sweep.yaml && bcsdf family configs/packing_sweep.yaml

Writes ``artifacts/<name>/family/``:

* ``weights.npz``, ``model.onnx``  the model (``fiber_bundle``'s ``mlp`` and ``onnx``
  backends; outside the trained packings the plugin refuses, it does not extrapolate);
* ``direct_<packing>.npz``  the seeds' mean table at each held-out packing (the truth);
* ``family.png``  the scattered fraction and the passthrough against packing: the seeds'
  means with their arrangement spread as bars, and the model across its range;
* ``strip.png``   the render stage's yarn at five packings (rows: three dyes) from the one file;
* ``summary.json``  per packing (trained and held out), against the seeds' mean there: the
  worst albedo error, dyed too, the share of the core's bins within the arrangement spread,
  the core's relative L1 beside one seed's own; per held-out packing the yarn rendered with
  the model against the direct table (FLIP).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import torch

from mitsuba_ext.neural import OnnxMLP
from models.fit import fit, prepare_family
from models.neural import save_onnx, save_weights

from .. import family
from ..artifacts import stage_dir
from ..config import FAMILY_SECTIONS
from ..metrics import rows_table, write_metrics
from ..summaries import FamilySummary


def run(cfg, out_root="artifacts") -> Path:
    f = cfg.family
    if f is None:
        raise ValueError(f"config {cfg.name} has no 'family:' section; add one beside its sweep over bundle.packing, "
                         "e.g. family: {held_out: []}")
    torch.set_num_threads(cfg.train.threads)
    out = stage_dir(cfg, "family", out_root)

    # -- the members: trained and held out -----------------------------------------------
    members = family.members(cfg, stage_dir(cfg, "sweep", out_root))
    trained = [(p, t) for p, t in members if not f.holds_out(p)]
    held_out = [(p, t) for p, t in members if f.holds_out(p)]
    if cfg.bake.orders and any(t.orders is None for _, t in members):
        raise ValueError(f"bake.orders: {cfg.bake.orders}, but the sweep's tables hold no orders; re-run "
                         f"`bcsdf sweep {cfg.name}`")

    # -- one model of the trained members --------------------------------------------------
    name = f.model or next(iter(cfg.train.models))
    c = cfg.train.model_copy(update={"inputs": ["packing"], "orders": bool(cfg.bake.orders)})
    problem = prepare_family(trained, c, cfg.hash(*FAMILY_SECTIONS))
    spec = dataclasses.replace(problem.base, hidden=list(cfg.train.models[name]))
    model, history, _, seconds, _ = fit(spec, problem, c, f"family {name}")
    nbytes = save_weights(out / "weights.npz", spec, model)
    save_onnx(out / "model.onnx", spec, model)
    packings = sorted({p for p, _ in trained})
    print(f"[family] {name} {spec.hidden} on {len(trained)} bakes at packings {packings}"
          + (f" ({spec.orders} orders)" if spec.orders else "") + f": {len(history)} epochs in {seconds:.1f} s")

    # -- against the seeds' mean at every packing ------------------------------------------
    onnx = OnnxMLP(out / "model.onnx")   # measured as a renderer reads it
    rows = [{"set": "held out" if f.holds_out(p) else "trained", **family.measure(onnx, members, p)}
            for p in sorted({p for p, _ in members})]
    print(rows_table(rows))
    family.figure(out / "model.onnx", members, f.held_out, out / "family.png", f"{cfg.name}: a family of plies")
    renders = []
    with tempfile.TemporaryDirectory(prefix="bcsdf-family-") as tmp:  # the yarn's curves
        for p in f.held_out:
            family.seed_mean(held_out, p).save(out / f"direct_{p:g}.npz")
            renders.append({"packing": p, **family.render_against_table(cfg, out / "weights.npz",
                                                                        out / f"direct_{p:g}.npz", p, Path(tmp))})
            print(f"[family] yarn at held-out packing {p:g}: model against the seeds' mean table FLIP "
                  f"{renders[-1]['FLIP vs direct table']:.4f}")
        if f.strip:
            family.strip(cfg, out / "weights.npz", members[0][1].wavelength, np.linspace(packings[0], packings[-1], 5),
                         bool(spec.orders), out / "strip.png", Path(tmp))

    summary = FamilySummary(
        config_hash=cfg.hash(*FAMILY_SECTIONS), model=name, hidden=list(spec.hidden),
        parameters=int(sum(q.numel() for q in model.parameters())), parameter_bytes=nbytes, orders=spec.orders,
        epochs=len(history), train_seconds=seconds, trained=packings, held_out=list(f.held_out),
        members=len(members), rows=rows, renders=renders)
    summary.write(out / "summary.json")
    worst = {f"worst_albedo_error_{kind.replace(' ', '_')}": max(r["worst albedo error"] for r in rows if r["set"] == kind)
             for kind in ("trained", "held out") if any(r["set"] == kind for r in rows)}
    write_metrics(cfg, out_root, "family", {**worst, "train_seconds": seconds, "parameter_bytes": nbytes})
    print(f"[family] wrote {out / 'weights.npz'}, {out / 'model.onnx'}, {out / 'family.png'}")
    return out
