"""Fitting a bundle table with a small MLP (CPU PyTorch): the training problem and its
two phases, shared by ``bcsdf train`` and the training bench.

The samples are the table *folded* by its symmetries (:func:`models.neural.fold_table`):
bins that the symmetric features cannot tell apart are one sample, their mean.
:func:`choose_folds` keeps a symmetry only if the table obeys it within its noise.

The table's values are bin averages, so the model's *bin average* is fitted: its mean
over ``bin_strata`` x ``bin_strata`` stratified random points of the bin (fresh every
step); the held-out errors compare bin averages (4 x 4 points) too. A model fitted and
measured at bin centres alone is free to peak unseen between them.

Phase 1 (:func:`fit_bins`) minimizes a weighted MSE in log space, ``y = log(1 + S / s0)``:
each sample and wavelength is weighted by ``1 / (sigma_y^2 + sigma_floor^2)`` where
``sigma_y`` is the table's own standard error carried into log space, so Monte Carlo
noise is not learned as signal. Log-space errors bias the albedo (worst at grazing
incidence), so phase 2 (:func:`energy_gain`) computes, in closed form, a gain per
incident longitude and wavelength that makes the model's albedo ``sum S solid_angle``
the table's scattered fraction (a row's sum includes its held-out bins: their values are
never fitted, only the row's total is the target). It is part of the model
(:func:`models.neural.energy_gain`), evaluated by every backend.

A model with extra inputs (``c.inputs``: ``offset``) learns the near field's cells: each
sample is a bin and a cell, its points drawn in the bin's directions and uniformly in the
cell's range of the input (:func:`models.neural.fold_table`).

A random ``val_fraction`` of the samples (all wavelengths of a bin, and all its mirror
images, together) is held out for early stopping and for the report. Same table, seed
and threads: the same weights.

The functions take the config's ``train`` section as ``c`` (any object with its fields).
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from scipy.interpolate import PchipInterpolator
from tqdm import tqdm

from . import errors
from .neural import (FoldedTable, NeuralSpec, bin_average, features, fold_table, make_export_module, make_torch_model,
                     order_sum, points_in_bins)


def load_checkpoint(path) -> dict:
    """A ``model.pt`` written by ``bcsdf train``, or a ``ValueError`` that names it."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path} does not exist; run `bcsdf train` with this config first")
    try:
        ckpt = torch.load(path, weights_only=True)
        if not isinstance(ckpt, dict) or not {"spec", "state"} <= set(ckpt):
            raise ValueError("no 'spec' and 'state' in it")
        return ckpt
    except Exception as e:  # torch raises RuntimeError, pickle and zip errors for a damaged file
        raise ValueError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e}); "
                         "re-run `bcsdf train`") from None


def file_hash(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def energy_bins(S: np.ndarray, fraction: float = 0.9) -> np.ndarray:
    """Flat indices of the largest values of ``S`` that hold ``fraction`` of its sum."""
    e = S.ravel()
    order = np.argsort(e)[::-1]
    k = int(np.searchsorted(np.cumsum(e[order]) / max(e.sum(), 1e-300), fraction)) + 1
    return order[:k]


def split_bins(n_bins: int, val_fraction: float, seed: int):
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n_bins)
    n_val = max(1, int(round(val_fraction * n_bins)))
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def choose_folds(table, relative: bool, limit: float = 1.5, inputs=()) -> list:
    """The symmetry folds of the features (models/neural.py) that this table obeys.

    Each candidate (``theta`` and ``dphi`` for a circle, ``theta`` and ``xz`` for an
    ellipse) is kept only if the bins it merges agree within their noise (chi^2 per
    degree of freedom below ``limit``). The table's own reductions (theta mirror, xz)
    pass exactly; a circle's mirror symmetry in ``phi_o - phi_i`` is statistical. With an
    ``offset`` input the near field's cells are checked (the mirror turns the offset's sign).
    """
    cells = len(table.near) if "offset" in inputs and table.near is not None else 0
    folds = []
    for fold in ("theta", "dphi") if relative else ("theta", "xz"):
        probe = NeuralSpec(relative_phi=relative, hidden=[1], s0=1.0, y_max=1.0,
                           wavelength=table.wavelength.tolist(), table_hash="", config_hash="",
                           reductions=table.meta["reductions"], folds=[fold], inputs=list(inputs),
                           offset_cells=cells)
        chi2 = fold_table(table, probe).chi2_per_dof
        if chi2 < limit:
            folds.append(fold)
        else:
            print(f"[train] the table does not obey the {fold!r} symmetry (merged bins differ by chi2/dof "
                  f"{chi2:.2f} >= {limit}); the model keeps both halves")
    return folds


def held_out_bins(table, spec: NeuralSpec, c) -> np.ndarray:
    """Flat indices (phi_i, theta_i, phi_o, theta_o) of the expanded bins held out from training."""
    data = fold_table(table, spec)
    _, val = split_bins(len(data.x), c.val_fraction, c.seed)
    return np.flatnonzero(np.isin(data.bin_class, val))


class Problem(NamedTuple):
    """What every model size of one config is fitted to: the spec they share but for
    their widths, the folded table, its split, the loss weights and, for a model of the
    orders, each output's scale (:func:`order_scales`)."""

    base: NeuralSpec
    data: object  # models.neural.FoldedTable
    train_idx: np.ndarray
    val_idx: np.ndarray
    w: np.ndarray
    scale: np.ndarray | None = None


def prepare(table, table_path, c, config_hash: str) -> Problem:
    """Fold the table, choose its symmetries, split it and weight it (one for every size).
    ``config_hash`` is recorded in the spec: what the exported model was trained from."""
    relative = table.meta["reductions"]["phi_o"] == "relative"
    inputs = list(getattr(c, "inputs", []))
    near = table.near if "offset" in inputs else None
    if "offset" in inputs and near is None:
        raise ValueError(f"{table_path}: train.inputs [offset] learns the near field, and this table has none; "
                         "bake it with `bake.offsets: N` (e.g. 8), or train without the offset input")
    positive = table.values[table.values > 0]
    s0 = float(np.mean(positive)) if positive.size else 1.0
    y_top = float(np.log1p((table.values if near is None else near).max() / s0))
    encoding = getattr(c, "encoding", "cone")
    folds = choose_folds(table, relative, inputs=inputs) if encoding == "cone" else []  # baselines learn every bin
    learns_orders = getattr(c, "orders", False)
    if learns_orders and table.orders is None:
        raise ValueError(f"{table_path}: train.orders learns the orders of scattering, and this table has none; "
                         "bake it with `bake.orders: K` (e.g. 8)")
    orders = len(table.orders) if learns_orders else 0
    bins = getattr(c, "gain_azimuth_bins", 0)
    half = len(table.phi_o) // 2
    if bins and (not relative or len(table.phi_o) % 2 or half % bins):
        raise ValueError(f"{table_path}: train.gain_azimuth_bins {bins} must divide the table's {half} bins of "
                         f"|phi_o - phi_i| (a circular ply's table; e.g. {half} or {half // 2 if half % 2 == 0 else 1})"
                         if relative else f"{table_path}: train.gain_azimuth_bins needs a circular ply's table")
    base = NeuralSpec(relative_phi=relative, hidden=[], s0=s0, y_max=1.5 * y_top + 1.0,
                      wavelength=table.wavelength.tolist(), table_hash=file_hash(table_path),
                      config_hash=config_hash, reductions=table.meta["reductions"],
                      folds=folds, passthrough=table.passthrough.tolist(), passthrough_phi_i=table.phi_i.tolist(),
                      passthrough_theta=[] if table.passthrough_theta is None else table.passthrough_theta.tolist(),
                      passthrough_theta_i=[] if table.passthrough_theta is None else table.theta_i.tolist(),
                      single_share=[] if table.single is None else table.single_share().tolist(),
                      lines=list(c.line_nodes), line_channels=c.line_channels if c.line_nodes else 0,
                      inputs=inputs, offset_cells=0 if near is None else len(near),
                      passthrough_offset=[] if near is None else table.near_passthrough[0].tolist(),
                      passthrough_offset_theta_i=[] if near is None else table.theta_i.tolist(), encoding=encoding,
                      orders=orders, tail_ratio=table.tail_ratio.tolist() if orders else [],
                      tail_ratio_theta_i=table.theta_i.tolist() if orders else [])
    data = fold_table(table, base)
    return split_and_weigh(base, data, c)


def order_scales(spec: NeuralSpec, data) -> np.ndarray:
    """Each output's scale for a model of the orders (``spec.orders``): the mean positive
    value of its order over ``s0``, so that each order is fitted in a log space of its own,
    ``y = log(1 + S_k / (s0 c_k))``. The orders fall by decades, and with the one ``s0`` of the
    sum the high ones would sit in the linear part of the log where their errors weigh
    nothing: the network leaves them near zero and their energy gain grows without bound
    (10^5 was seen), so that a query off the bins returns fireflies. The scale is folded into
    the exported energy gain, so no backend knows of it."""
    K, L = spec.orders, len(spec.wavelength)
    S = data.S.reshape(len(data.S), K, L)
    mean = np.array([S[:, k][S[:, k] > 0].mean() if np.any(S[:, k] > 0) else spec.s0 for k in range(K)])
    return np.repeat(mean / spec.s0, L)


def split_and_weigh(base: NeuralSpec, data, c) -> Problem:
    """The random split of ``data``'s samples (``c.val_fraction``, ``c.seed``) and the loss
    weights ``1 / (sigma_y^2 + sigma_floor^2)``, normalized to a mean of 1 over the training set;
    for a model of the orders, its targets in each order's log space (:func:`order_scales`)."""
    scale = None
    if base.orders:
        scale = order_scales(base, data)
        s = base.s0 * scale
        data = dataclasses.replace(data, y=np.log1p(data.S / s).astype(np.float32),
                                   sigma_y=(data.E / (s + data.S)).astype(np.float32))
        base = dataclasses.replace(base, y_max=1.5 * float(data.y.max()) + 1.0)
    train_idx, val_idx = split_bins(len(data.x), c.val_fraction, c.seed)
    w = 1.0 / (data.sigma_y.astype(np.float64) ** 2 + c.sigma_floor**2)
    w = (w / w[train_idx].mean()).astype(np.float32)
    return Problem(base, data, train_idx, val_idx, w, scale)


def prepare_family(members, c, config_hash: str) -> Problem:
    """:func:`prepare` for a family of bakes of one ply type (``bcsdf sweep``) whose
    ``packing`` differs: ``members`` ``[(packing, expanded table)]`` on one grid (several
    members per packing: arrangement seeds; the fit learns their mean). Each member is folded
    with its packing as a constant input and the samples concatenated; the split is random
    over all of them; the folds are those the first member obeys; the passthrough (and, with
    ``c.orders``, the tail's ratio) is kept per packing (the mean over its seeds), the range
    trained on in ``input_range``."""
    tables = [t for _, t in members]
    first = tables[0]
    if any(t.values.shape != first.values.shape or not np.allclose(t.wavelength, first.wavelength) for t in tables):
        raise ValueError("a family's tables must share their grid and wavelengths (bake them from one config)")
    relative = first.meta["reductions"]["phi_o"] == "relative"
    packing = np.array([p for p, _ in members], float)
    nodes = np.unique(packing)
    orders = len(first.orders) if getattr(c, "orders", False) and first.orders is not None else 0
    if getattr(c, "orders", False) and any(t.orders is None or len(t.orders) != orders for t in tables):
        raise ValueError("train.orders learns the orders of scattering: bake every member of the family with the "
                         "same `bake.orders: K` (e.g. 8)")
    # the mean over the seeds at each trained packing: the passthrough and the tail's ratio
    at_node = lambda name: [np.mean([getattr(t, name) for p, t in members if p == k], 0).tolist()  # noqa: E731
                            for k in nodes]
    positive = np.concatenate([t.values[t.values > 0] for t in tables])
    s0 = float(np.mean(positive)) if positive.size else 1.0
    y_top = float(np.log1p(max(t.values.max() for t in tables) / s0))
    digest = hashlib.sha256()
    for t in tables:
        digest.update(np.ascontiguousarray(t.values).tobytes())
    base = NeuralSpec(relative_phi=relative, hidden=[], s0=s0, y_max=1.5 * y_top + 1.0,
                      wavelength=first.wavelength.tolist(), table_hash="family:" + digest.hexdigest()[:16],
                      config_hash=config_hash, reductions=first.meta["reductions"], folds=choose_folds(first, relative),
                      passthrough=np.mean([t.passthrough for t in tables], 0).tolist(),
                      passthrough_phi_i=first.phi_i.tolist(),
                      single_share=[] if first.single is None else
                      np.mean([t.single_share() for t in tables], 0).tolist(),
                      inputs=["packing"], input_range={"packing": [float(nodes[0]), float(nodes[-1])]},
                      passthrough_packing=at_node("passthrough"), packings=nodes.tolist(), orders=orders,
                      tail_ratio=at_node("tail_ratio") if orders else [],
                      tail_ratio_theta_i=first.theta_i.tolist() if orders else [])
    data = concatenate([fold_table(t, base, {"packing": p}) for p, t in members])
    return split_and_weigh(base, data, c)


def concatenate(parts) -> FoldedTable:
    """Folded tables of one grid as one training set: their samples, classes and incident
    directions numbered on (the expanded bins stacked along the incident directions)."""
    cat = lambda name: np.concatenate([getattr(d, name) for d in parts])  # noqa: E731
    classes = np.cumsum([0] + [len(d.S) for d in parts[:-1]])
    groups = np.cumsum([0] + [len(d.albedo) for d in parts[:-1]])
    shape = parts[0].bins_shape
    return FoldedTable(
        x=cat("x"), y=cat("y"), sigma_y=cat("sigma_y"), S=cat("S"), E=cat("E"), count=cat("count"),
        bin_class=np.concatenate([d.bin_class + k for d, k in zip(parts, classes)]),
        group=np.concatenate([d.group + k for d, k in zip(parts, groups)]), omega=cat("omega"), albedo=cat("albedo"),
        chi2_per_dof=float(np.mean([d.chi2_per_dof for d in parts])), cell=cat("cell"), extra_cell=cat("extra_cell"),
        bins_S=cat("bins_S"), bins_E=cat("bins_E"), bins_shape=(len(parts) * shape[0],) + tuple(shape[1:]),
        row_omega=parts[0].row_omega)


def model_bin_averages(spec: NeuralSpec, model, cell, k: int = 4, extra_cell=None, orders: bool = False) -> np.ndarray:
    """The model's (exported transform's, its gain included) average over each bin of ``cell``
    (k x k midpoints; ``extra_cell``: the bins' ranges in the extra inputs), float64; ``orders``:
    its outputs (a model of orders: each order's), not their sum."""
    module = make_export_module(spec, model, orders=orders).eval()

    def predict(*queries):
        with torch.no_grad():
            out = module(torch.from_numpy(np.stack(queries, -1).astype(np.float32)))
            return (out[1] if orders else out).numpy().astype(np.float64)
    return bin_average(predict, cell, k, extra_cell)


def held_out_metrics(spec: NeuralSpec, model, data, val_idx) -> dict:
    """The model's error and the table's noise (:mod:`models.errors`: the core's relative L1)
    on the held-out bins, each expanded bin against its own baked value, the model's as its
    bin average (4 x 4 points); the log MAE over the held-out classes."""
    S_pred = model_bin_averages(spec, model, data.cell[val_idx],
                                extra_cell=None if data.extra_cell is None else data.extra_cell[val_idx],
                                orders=bool(spec.orders))   # the samples' outputs; the bins' errors of their sum
    position = np.full(len(data.S), -1)
    position[val_idx] = np.arange(len(val_idx))
    held = position[data.bin_class] >= 0
    pred = np.zeros_like(data.bins_S)
    pred[held] = order_sum(spec, S_pred)[position[data.bin_class[held]]]
    by_rows = lambda a: errors.by_rows(np.asarray(a).reshape(data.bins_shape))  # noqa: E731
    where = by_rows(np.broadcast_to(held[:, None], pred.shape))
    error = errors.core_l1(by_rows(pred), by_rows(data.bins_S), data.row_omega, where=where)
    noise = errors.noise_l1(by_rows(data.bins_S), by_rows(data.bins_E), data.row_omega, where=where)
    return {"relative_l1": error, "table_noise_l1": noise, "noise_ratio": errors.error_over_noise(error, noise),
            "log_mae": errors.log_mae(S_pred, data.S[val_idx], spec.s0, data.count[val_idx, None])}


class BinFit:
    """The training problem of one model: its folded table, split and weights, and the
    model's *bin averages*.

    The table holds bin averages, so the model's bin average is fitted: its mean, in
    linear space, over k x k stratified random points of the bin. Fitted at the centres
    alone, a network peaks unseen between them (too much energy); with unstratified points
    the estimate's variance biases the fit low.
    """

    def __init__(self, spec: NeuralSpec, problem: Problem):
        data = problem.data
        self.spec, self.data = spec, data
        # each output's scale (a model of the orders: order_scales), 1 without
        self.scale = 1.0 if problem.scale is None else torch.from_numpy(problem.scale.astype(np.float32))
        self.Y, self.W = torch.from_numpy(data.y), torch.from_numpy(problem.w)
        self.cell = torch.from_numpy(data.cell.astype(np.float32))
        self.extra = None if data.extra_cell is None else torch.from_numpy(data.extra_cell.astype(np.float32))
        self.tr, self.va = torch.from_numpy(problem.train_idx), torch.from_numpy(problem.val_idx)
        self.every = torch.arange(len(data.x))
        # the (incident direction, wavelength) rows that scatter: a row that scatters nothing
        # has no relative albedo error
        self.seen = data.albedo > 0

    def stratified(self, n, k, generator):
        """``[n, k * k, 2 + m]`` points of the unit cube of a bin's directions and its ``m``
        extra inputs: one uniform in each of the k x k strata of the directions, the extra
        coordinates uniform."""
        strata = torch.tensor([[i / k, j / k] for i in range(k) for j in range(k)])
        u = strata + torch.rand((n, k * k, 2), generator=generator) / k
        m = len(self.spec.inputs)
        return torch.cat([u, torch.rand((n, k * k, m), generator=generator)], -1) if m else u

    def encode(self, b, u):
        """Features at the points ``u [len(b), K, 2 + m]`` of bins ``b``: ``[len(b) * K, n_inputs]``."""
        K = u.shape[1]
        angles = points_in_bins(torch, self.cell[b].repeat_interleave(K, 0), u[..., :2].reshape(-1, 2))
        extra = []
        if self.extra is not None:
            lo, hi = self.extra[b, :, 0].repeat_interleave(K, 0), self.extra[b, :, 1].repeat_interleave(K, 0)
            extra = (lo + u[..., 2:].reshape(-1, lo.shape[1]) * (hi - lo)).unbind(-1)
        return torch.stack(features(torch, self.spec, *angles, *extra), -1)

    def bin_means(self, b, y):
        """From the raw outputs ``y`` at the points of bins ``b``: the log-space bin average
        for the fit and the exported one, ``S``, for the energy. The exported clamp at 0 is
        leaky for the fit (an output clamped everywhere would get no gradient and stay dead;
        it did, for one wavelength); the energy is that of the exported S, what a renderer
        gets (leaky negative values would count as negative energy)."""
        y = torch.nn.functional.leaky_relu(y, 0.01).clamp(max=self.spec.y_max)
        e = torch.expm1(y.reshape(len(b), -1, self.spec.n_outputs))  # < 0 exactly where the output is negative,
        # so relu(e) is the clamped expm1; e's bin mean is the leaky S / s0
        return torch.log1p(torch.clamp(e.mean(1), min=-0.5)), self.spec.s0 * self.scale * torch.relu(e).mean(1)

    def model_albedo(self, S) -> np.ndarray:
        """The model's albedo per (incident direction, wavelength) row, ``[groups, lambda]``,
        from its bin values ``S [samples, lambda]``: the sum of ``S d omega`` over each row's
        outgoing bins."""
        albedo = np.zeros_like(self.data.albedo)
        np.add.at(albedo, self.data.group, S * self.data.omega[:, None])
        return albedo

    def worst_albedo_error(self, albedo) -> float:
        """The largest relative error of ``albedo [groups, lambda]`` against the table's over
        the scattering rows."""
        return float(np.max(np.abs(albedo[self.seen] / self.data.albedo[self.seen] - 1)))

    def loss(self, b, y):
        """Weighted log-space MSE: the weights carry the table's own noise."""
        return (self.W[b] * (y - self.Y[b]) ** 2).mean()


def fit(spec: NeuralSpec, problem: Problem, c, name, on_epoch=None):
    """Train one MLP of ``spec``'s widths on ``problem``: :func:`fit_bins`, then :func:`energy_gain`
    (which sets ``spec``'s gain).

    Returns the model, the loss history, the best validation loss, the seconds taken and
    the worst albedo error over (incident direction, wavelength) before and after the
    energy gain (:func:`energy_gain`; empty without one). ``on_epoch(epoch, seconds,
    best_state)`` is called after every epoch (the training bench records with it).
    """
    torch.manual_seed(c.seed)
    model = make_torch_model(spec)
    p = BinFit(spec, problem)
    t0 = time.perf_counter()
    history, best = fit_bins(model, p, c, name, on_epoch, t0)
    t1 = time.perf_counter()
    bins = getattr(c, "gain_azimuth_bins", 0)
    calibration = energy_gain(model, spec, p, azimuth_bins=bins, rank=getattr(c, "gain_rank", 0)) \
        if c.energy_gain else {}
    if calibration:
        calibration["calibration_seconds"] = time.perf_counter() - t1
    elif problem.scale is not None:   # no gain computed: the outputs' scales alone, at one node
        per_node = problem.scale[None]
        spec.gain = (np.broadcast_to(per_node, (len(spec.packings),) + per_node.shape)
                     if "packing" in spec.inputs else per_node).tolist()
        spec.gain_theta_i = [0.0]
    return model, history, best, time.perf_counter() - t0, calibration


def adam(model, lr: float):
    """Phase 1's optimizer (the training bench profiles its steps with it too)."""
    return torch.optim.Adam(model.parameters(), lr=lr, fused=True)  # one kernel for all parameters


def fit_bins(model, p: BinFit, c, name, on_epoch=None, t0=None):
    """Phase 1: minibatch Adam on the bin averages, cosine learning rate, early stopping on
    the held-out loss. Leaves ``model`` at its best held-out state; returns the history
    ``[(train, validation)]`` per epoch and the best validation loss.

    The training loss of an epoch is the mean of its minibatch losses (no second pass);
    the held-out loss is measured on the held-out bins alone at fixed stratified points.
    """

    opt = adam(model, c.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, c.epochs)
    gen = torch.Generator().manual_seed(c.seed)
    fixed = p.stratified(len(p.data.x), c.bin_strata, torch.Generator().manual_seed(c.seed + 1))
    x_val = p.encode(p.va, fixed[p.va])  # the points of every bin drawn, so a bin's points do not depend on the split
    history, best, best_state, since = [], np.inf, None, 0
    t0 = time.perf_counter() if t0 is None else t0
    with tqdm(range(c.epochs), desc=f"train {name}", unit="epoch") as bar:
        for epoch in bar:
            perm = p.tr[torch.randperm(len(p.tr), generator=gen)]
            total = 0.0
            for lo in range(0, len(perm), c.batch_size):
                b = perm[lo: lo + c.batch_size]
                y, _ = p.bin_means(b, model(p.encode(b, p.stratified(len(b), c.bin_strata, gen))))
                loss = p.loss(b, y)
                opt.zero_grad()
                loss.backward()
                opt.step()
                total += float(loss.detach()) * len(b)
            with torch.no_grad():
                train_loss, val_loss = total / len(perm), float(p.loss(p.va, p.bin_means(p.va, model(x_val))[0]))
            if not (np.isfinite(train_loss) and np.isfinite(val_loss)):
                raise FloatingPointError(f"training {name} diverged at epoch {epoch} (loss {train_loss}); "
                                         "lower train.lr")
            sched.step()
            history.append((train_loss, val_loss))
            bar.set_postfix(train=f"{train_loss:.4g}", val=f"{val_loss:.4g}", refresh=False)
            if val_loss < best * (1 - 1e-4):
                best, since = val_loss, 0
                best_state = {k: v.clone() for k, v in model.state_dict().items()}
            else:
                since += 1
            if on_epoch is not None:
                on_epoch(epoch, time.perf_counter() - t0, best_state)
            if since >= c.patience:
                break
    model.load_state_dict(best_state)
    return history, best


# Between two trained packings a family's network has no data, and its albedo there is its own
# interpolation (it dipped below both neighbours and below what the passthrough leaves); the
# gain at this many steps per interval puts each output's albedo on the trained packings' curve
# instead (packing_gains, along_packing), and the passthrough and the tail's ratio are read off
# their own curves at the same nodes.
GAIN_PACKING_STEPS = 4
GAIN_STRATA = 8  # k x k midpoints per bin for the model's albedo in the gain (`bench.train --calibration` compares k)
# The gain corrects the albedo bias of a log-space fit, a few per cent to tens of per cent. A
# ratio beyond this factor is no bias but an output the network did not learn (near zero where
# the table is not): multiplied up it would return its noise as fireflies wherever the model is
# read between the nodes, so it is held at the limit and the albedo error is left to show.
GAIN_LIMIT = 4.0


def held_ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``num / den`` held within :data:`GAIN_LIMIT` either way; 1 where either holds no energy:
    every gain's factor (the rows', the azimuth classes', the packings' between)."""
    return np.where((num > 0) & (den > 0), np.clip(num / np.maximum(den, 1e-300), 1 / GAIN_LIMIT, GAIN_LIMIT), 1.0)


def _midpoint_means(model, p: BinFit, k: int, samples=None, extra_cell=None) -> np.ndarray:
    """The network's bin averages ``S [samples, lambda]`` (no gain) over k x k midpoints, of
    every sample or of ``samples``; ``extra_cell``: their ranges of the extra inputs instead
    of their own."""
    cell = p.data.cell if samples is None else p.data.cell[samples]
    if extra_cell is None:
        extra_cell = p.data.extra_cell if samples is None or p.data.extra_cell is None else p.data.extra_cell[samples]

    def predict(*queries):
        x = torch.stack(features(torch, p.spec, *(torch.from_numpy(np.asarray(a, np.float32)) for a in queries)), -1)
        with torch.no_grad():
            return p.bin_means(torch.arange(len(x)), model(x))[1].double().numpy()
    return bin_average(predict, cell, k, extra_cell)


def azimuth_bin(cell: np.ndarray, bins: int) -> np.ndarray:
    """Each sample's bin of ``|phi_o - phi_i|`` (``bins`` equal bins over [0, pi];
    :func:`models.neural.azimuth_gain`) from its directions ``cell [n, 6]``
    (:func:`models.neural.table_cells`), at its azimuth's centre."""
    d = 0.5 * (cell[:, 2] + cell[:, 3]) - cell[:, 0]
    return np.clip(np.floor(np.abs(np.angle(np.exp(1j * d))) * (bins / np.pi)), 0, bins - 1).astype(int)


def azimuth_energies(p: BinFit, S_model: np.ndarray, at: np.ndarray, n_nodes: int, bins: int) -> tuple:
    """``(table, model)``, each ``[bins, node, lambda]``: the table's energy and the model's in
    each class of (azimuth bin, gain node), summed over the *training* samples (a held-out
    bin's value is never a target)."""
    tr = p.tr.numpy()
    cls = azimuth_bin(p.data.cell[tr], bins) * n_nodes + at[p.data.group[tr]]
    w = p.data.omega[tr, None]
    num, den = np.zeros((bins * n_nodes, S_model.shape[1])), np.zeros((bins * n_nodes, S_model.shape[1]))
    np.add.at(num, cls, p.data.S[tr] * w)
    np.add.at(den, cls, S_model[tr] * w)
    return num.reshape(bins, n_nodes, -1), den.reshape(bins, n_nodes, -1)


def azimuth_ratio(p: BinFit, S_model: np.ndarray, at: np.ndarray, n_nodes: int, bins: int) -> np.ndarray:
    """``[bins, node, lambda]``: the table's energy over the model's in each class of
    :func:`azimuth_energies`, held within :data:`GAIN_LIMIT` either way; 1 where a class holds
    no energy."""
    return held_ratio(*azimuth_energies(p, S_model, at, n_nodes, bins))


def low_rank_log(ratio: np.ndarray, weight: np.ndarray, rank: int) -> tuple:
    """``(coefficients [..., rank], basis [rank, lambda])``, float32 values: the product
    closest to ``log(ratio)`` (``[..., lambda]``) in the least squares weighted by each
    class's ``weight`` (``[...]``, its energy: a class that holds little light fixes little).

    The classes' spectra ripple with the fiber's resonances, and the ripples of neighbouring
    azimuths and incidences share their shapes: a few spectral shapes, each class a mix of
    them, hold most of the ripple in a fraction of the numbers. Weighted by rows, the problem
    is the truncated SVD of the rows scaled by ``sqrt(weight)`` (Eckart-Young); each row's
    coefficients are then its projection on the basis, so a class of no weight still gets
    the closest mix of the shapes."""
    L = np.log(ratio).reshape(-1, ratio.shape[-1])
    w = np.sqrt(np.maximum(weight.reshape(-1), 0.0))
    basis = np.linalg.svd(w[:, None] * L, full_matrices=False)[2][:rank].astype(np.float32)
    coefficients = (L @ basis.T.astype(np.float64)).astype(np.float32)
    return coefficients.reshape(*ratio.shape[:-1], rank), basis


def along_packing(packings, values, at) -> np.ndarray:
    """``values [trained packing, ...]`` (the seeds' means) read at the packings ``at``, on one
    monotone cubic through them per element (PCHIP, Fritsch and Carlson).

    A ply's albedo and passthrough bend with the packing (the albedo rises ever more slowly as
    the ply fills), and the straight line between two trained packings cuts under the bend
    (``make bench-packing`` measures it at the held-out packings). PCHIP follows it from the
    neighbours' slopes, reproduces a straight line, and never leaves the range of an
    interval's two ends: a probability stays one, a positive albedo positive. It is odd
    (the curve of ``c - v`` is ``c`` minus the curve of ``v``), so quantities that sum to a
    constant at the trained packings (a lossless ply's albedo and passthrough) still do
    between them."""
    return PchipInterpolator(np.asarray(packings, float), np.asarray(values, float), axis=0)(np.asarray(at, float))


def packing_gains(model, p: BinFit, spec: NeuralSpec, albedo: np.ndarray, at: np.ndarray, strata: int):
    """A family's gain between its trained packings: ``(packings, gains [node, theta node,
    output])`` at ``GAIN_PACKING_STEPS - 1`` packings inside each interval, each the ratio of the
    albedo there on the trained packings' curve (:func:`along_packing` of ``albedo [trained
    packing, theta node, output]``, the seeds' mean per node) to the network's there (its bin
    averages over ``strata`` x ``strata`` midpoints, on the first trained packing's samples
    with the packing replaced),
    held within :data:`GAIN_LIMIT` either way; the outputs' scales not folded in."""
    P = np.asarray(spec.packings, float)
    column = spec.inputs.index("packing")
    first = np.flatnonzero(p.data.extra_cell[:, column, 0] == P[0])   # one packing's samples (its seeds')
    groups, where = np.unique(p.data.group[first], return_inverse=True)
    count = np.zeros(albedo.shape[1])
    np.add.at(count, at[groups], 1.0)
    extra = p.data.extra_cell[first].copy()
    nodes, gains = [], []
    for k in range(len(P) - 1):
        for step in range(1, GAIN_PACKING_STEPS):
            w = step / GAIN_PACKING_STEPS
            q = (1 - w) * P[k] + w * P[k + 1]
            extra[:, column] = q
            S = _midpoint_means(model, p, strata, first, extra)
            model_albedo = np.zeros((len(groups), S.shape[1]))
            np.add.at(model_albedo, where, S * p.data.omega[first, None])
            mean = np.zeros_like(albedo[0])
            np.add.at(mean, at[groups], model_albedo)
            mean /= np.maximum(count, 1)[:, None]
            target = along_packing(P, albedo, q)
            nodes.append(q)
            gains.append(held_ratio(target, mean))
    return nodes, np.array(gains)


def energy_gain(model, spec: NeuralSpec, p: BinFit, strata: int = GAIN_STRATA, azimuth_bins: int = 0,
                rank: int = 0) -> dict:
    """Phase 2: the energy gain, in closed form.

    Log-space errors alone bias the albedo (worst at grazing incidence). The gain
    (:func:`models.neural.energy_gain`) scales the network's spectrum per incident longitude
    and wavelength so that each incident direction's albedo, ``sum S d omega`` over all its
    outgoing bins, is the table's scattered fraction: at each of the table's ``theta_i``
    the ratio of the two (over the ``phi_i`` that share it), piecewise linear between them.
    The rows include the held-out bins: their values are never fitted, but the row's total
    is the target. A family's model (``packing`` input) gets one gain per trained packing. A
    ratio beyond :data:`GAIN_LIMIT` either way is held there; a model of the orders has each
    output's scale (:func:`order_scales`) folded in. Between the trained packings a family's gain
    has nodes of its own (:func:`packing_gains`), where it puts each
    output's albedo on the trained packings' curve (:func:`along_packing`), and the passthrough
    and the tail's ratio are read off theirs there: ``spec.packings`` becomes every node.
    The model's albedo is integrated over ``strata`` x ``strata`` midpoints of
    every bin: the ridge along the specular cone is narrower than a bin, and random points
    (the fit's) would put their own noise into the gain.

    With ``azimuth_bins``, first each class of (bin of ``|phi_o - phi_i|``, gain node) gets the
    ratio of the table's energy to the model's over its training samples
    (:func:`azimuth_ratio`, ``spec.azimuth_gain``: the spectra's ripple from one azimuth bin to
    the next, which a small network smooths), then the gain above holds each row's albedo.
    The bins should be the table's own (or unions of them): a bin of the table split between
    two of the gain's would be read with each half's factor, though its ratio is of the whole.
    With ``rank``, the classes' ratios are stored as a product of that rank in log space
    (:func:`low_rank_log`), and the row gain holds each row's albedo with that product.

    Sets ``spec.gain`` and ``spec.gain_theta_i``; returns the worst albedo error over the
    scattering rows before and after (after: integrated at ``strata + 1`` x ``strata + 1``
    midpoints; empty if no row scatters).
    """
    if not p.seen.any():  # no row scatters
        return {}
    table_albedo = p.data.albedo
    # each group's incident longitude (|theta_i| under the theta fold: the features cannot tell the sign)
    theta = np.zeros(len(table_albedo))
    theta[p.data.group] = p.data.cell[:, 1]
    theta = np.abs(theta) if "theta" in spec.folds else theta
    nodes = np.unique(np.round(theta, 12))
    at = np.searchsorted(nodes, np.round(theta, 12))
    S_model = _midpoint_means(model, p, strata)
    azimuthal = 1.0   # each sample's factor of its class ([samples, lambda] where resolved)
    if azimuth_bins:   # each class's energy first, the row's below
        num, den = azimuth_energies(p, S_model, at, len(nodes), azimuth_bins)
        ratio = held_ratio(num, den)
        if rank:
            coefficients, basis = low_rank_log(ratio, num.sum(-1), rank)
            spec.azimuth_gain, spec.azimuth_gain_basis = coefficients.tolist(), basis.tolist()
            ratio = spec.azimuth_gains()   # what every backend reads
        else:
            spec.azimuth_gain = ratio.tolist()
        azimuthal = ratio[azimuth_bin(p.data.cell, azimuth_bins), at[p.data.group]]
        S_model = S_model * azimuthal
    model_albedo = p.model_albedo(S_model)
    # a family's model: one gain per trained packing (each group is one member's direction)
    packing = np.zeros(len(table_albedo))
    if "packing" in spec.inputs:
        packing[p.data.group] = p.data.extra_cell[:, spec.inputs.index("packing"), 0]
    k = np.searchsorted(spec.packings, packing) if "packing" in spec.inputs else np.zeros_like(at)
    shape = (len(spec.packings) if "packing" in spec.inputs else 1, len(nodes), table_albedo.shape[1])
    num, den = np.zeros(shape), np.zeros(shape)
    np.add.at(num, (k, at), table_albedo)
    np.add.at(den, (k, at), model_albedo)
    gain = held_ratio(num, den)
    scale = 1.0 if isinstance(p.scale, float) else p.scale.double().numpy()
    exported = gain * scale   # the scales folded in
    if "packing" in spec.inputs and len(spec.packings) > 1:   # and between the trained packings
        count = np.zeros(shape[:2])
        np.add.at(count, (k, at), 1.0)
        inside, inside_gain = packing_gains(model, p, spec, num / np.maximum(count, 1)[..., None], at, strata)
        order = np.argsort(np.r_[spec.packings, inside])
        exported = np.concatenate([exported, inside_gain * scale])[order]
        every = np.r_[spec.packings, inside][order]
        spec.passthrough_packing = along_packing(spec.packings, spec.passthrough_packing, every).tolist()
        if spec.tail_ratio:
            spec.tail_ratio = along_packing(spec.packings, spec.tail_ratio, every).tolist()
        spec.packings = every.tolist()
    spec.gain = (exported if "packing" in spec.inputs else exported[0]).tolist()
    spec.gain_theta_i = np.clip(nodes, -np.pi / 2, np.pi / 2).tolist()  # (rounded up)
    # after: integrated on another grid (strata + 1 midpoints a side, none shared), so that the
    # figure holds the gain's own quadrature error, not zero by construction
    after = p.model_albedo(_midpoint_means(model, p, strata + 1) * azimuthal) * gain[k, at]
    return {"worst_albedo_error_before": p.worst_albedo_error(model_albedo),
            "worst_albedo_error_after": p.worst_albedo_error(after)}
