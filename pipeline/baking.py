"""A bake in progress (:class:`Bake`): its batches with fixed seeds, the running tally,
its checkpoint, and what it writes when it finishes (the table, its summary, metrics and
pictures). ``bcsdf bake`` runs one; the sweep keeps several at once, here or on a Dask
cluster (``pipeline.cluster``)."""

from __future__ import annotations

import copy
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from models import bundle as bundles
from models.bake import Baker, BakeSpec, Tally, tally_to_table
from models.bake.twisted import TwistedBaker
from models.bake.twisted_camera import TwistedCameraBaker
from models.bundle_table import BundleTable
from models.io import atomic_path, clear_torn

from . import cluster
from .artifacts import load_fiber_table, stage_dir
from .build import batch_seed, build_ply, code_version, cross_section, make_spec, tracer
from .config import BAKE_SECTIONS, theta_nodes
from .metrics import write_metrics
from .plots import save_figure, slice_nodes, spectral_image, theta_rows
from .summaries import BakeSummary


class Bake:
    """One bake in progress: its batches, the running tally and its checkpoint.

    The work is a fixed list of batches with fixed seeds (:func:`pipeline.build.batch_seed`), added in
    order, so that a bake resumed from its checkpoint, or traced on a cluster in any order
    (``pipeline.cluster``), gives the same table.
    """

    def __init__(self, cfg, out_root, bundle: bundles.Bundle | bundles.TwistedBundle | None = None):
        self.cfg, self.out_root = cfg, out_root
        self.out = stage_dir(cfg, "bake", out_root)
        self.fiber = load_fiber_table(cfg, out_root)
        self.ply = bundle or build_ply(cfg)             # what is traced
        self.bundle = cross_section(self.ply)           # its cross-section (a twisted one's at height 0)
        self.spec, self.reductions = make_spec(cfg, self.ply, self.fiber)
        c = cfg.bake
        self.work = [(a, k) for a in range(len(self.spec.phi_i)) for k in range(c.n_batches)]
        self.sizes = [c.batch_size(k) for _, k in self.work]
        self.key = cfg.hash(*BAKE_SECTIONS)
        # a checkpoint resumes only with the code that wrote it: batches of two codes never mix
        self.code = cluster.code_digest(cfg)
        self.ckpt = self.out / "checkpoint.npz"
        self.tally, self.done, self.elapsed = Tally.zeros(self.spec, len(self.fiber.wavelength)), 0, 0.0
        self.cpu = 0.0  # this process's CPU time while tracing (on a cluster: the client's and the scheduler's)
        # each batch's own estimates: the errors of the whole from batch means (paths are stratified
        # within a batch, so the binomial error of the passthrough would overstate it)
        self.batch_estimates: dict[str, list[float]] = {"scattered": [], "passthrough": []}
        self._baker = None
        self._resume()
        self._last_save = self._t_prev = time.perf_counter()
        self._cpu_prev = time.process_time()

    @property
    def baker(self) -> Baker:
        """The in-process tracer (built on first use: a cluster's client needs none)."""
        if self._baker is None:
            self._baker = tracer(self.ply, self.fiber, self.spec)
        return self._baker

    @property
    def finished(self) -> bool:
        return self.done == len(self.work)

    @property
    def total_paths(self) -> int:
        return sum(self.sizes)

    @property
    def paths_left(self) -> int:
        return sum(self.sizes[self.done:])

    def serial(self):
        """``(0, i, tally)`` for the remaining batches, traced here, in order."""
        # a bake's time is its own batches' (a sweep runs several in turn)
        self._t_prev, self._cpu_prev = time.perf_counter(), time.process_time()
        for i in range(self.done, len(self.work)):
            yield 0, i, self.baker.trace(self.work[i][0], self.sizes[i], batch_seed(self.cfg, *self.work[i]))

    def add(self, i: int, tally: Tally) -> int:
        """Add batch ``i`` (the next one); checkpoint on the clock. Returns its paths."""
        if i != self.done:
            raise RuntimeError(f"batch {i} arrived while {self.done} was expected (they add in order)")
        self.tally.add(tally)
        a = self.work[i][0]
        self.batch_estimates["scattered"].append(float(np.mean(tally.sum[a].sum(axis=(1, 2)))) / self.sizes[i])
        self.batch_estimates["passthrough"].append(float(tally.passthrough[a]) / self.sizes[i])
        now, cpu = time.perf_counter(), time.process_time()
        self.elapsed, self._t_prev = self.elapsed + (now - self._t_prev), now
        self.cpu, self._cpu_prev = self.cpu + (cpu - self._cpu_prev), cpu
        self.done += 1
        if now - self._last_save > self.cfg.bake.checkpoint_every_s and not self.finished:
            self.save_checkpoint()
            self._last_save = now
        return self.sizes[i]

    def _resume(self) -> None:
        clear_torn(self.ckpt)  # a kill -9 during a checkpoint write leaves its temporary behind
        if not self.ckpt.exists():
            return
        try:
            with np.load(self.ckpt, allow_pickle=False) as z:
                code = str(z["code"]) if "code" in z.files else None
                if str(z["key"]) == self.key and code != self.code:
                    print(f"[bake] {self.cfg.name}: checkpoint was written by other code (the baker or its stage "
                          "changed since); starting over")
                elif str(z["key"]) == self.key:
                    self.tally, self.done, self.elapsed = Tally.from_arrays(z), int(z["done"]), float(z["elapsed"])
                    self.cpu = float(z["cpu"]) if "cpu" in z.files else 0.0
                    for q in self.batch_estimates:  # unknown (NaN) in a checkpoint of older code
                        self.batch_estimates[q] = [float(x) for x in z[f"batch_{q}"]] if f"batch_{q}" in z.files \
                            else [np.nan] * self.done
                    print(f"[bake] {self.cfg.name}: resuming from checkpoint: {self.done}/{len(self.work)} "
                          "batches done")
                else:
                    print(f"[bake] {self.cfg.name}: checkpoint is from other settings; starting over")
        except Exception as e:  # a torn checkpoint cannot happen (atomic), but be safe
            print(f"[bake] {self.cfg.name}: unreadable checkpoint ({e}); starting over")

    def save_checkpoint(self) -> None:
        with atomic_path(self.ckpt, journaled=False) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, key=np.array(self.key), code=np.array(self.code), done=np.array(self.done), elapsed=np.array(self.elapsed),
                         cpu=np.array(self.cpu),
                         **{f"batch_{q}": np.array(v) for q, v in self.batch_estimates.items()}, **self.tally.arrays())

    def finish(self) -> Path:
        """Write the table, its summary, metrics and pictures; remove the checkpoint."""
        cfg, c, tally, out, bundle = self.cfg, self.cfg.bake, self.tally, self.out, self.bundle
        table = tally_to_table(tally, self.spec, self.fiber, self.reductions)
        table.meta.update(config_name=cfg.name, config_hash=self.key, config=cfg.model_dump(mode="json"),
                          fiber_model=cfg.fiber.model, estimator=c.estimator, exit=self.spec.exit, seed=c.seed,
                          samples_per_phi_i=c.paths_per_phi_i, vertices=int(tally.vertices),
                          bake_seconds=self.elapsed, n_fibers=len(bundle.radii),
                          packing_fraction=bundle.packing_fraction, bounding_radius_um=bundle.bounding_radius,
                          variant=c.variant, code_version=code_version())
        table.save(out / "bundle_table.npz")
        balance = table.energy_balance()
        elapsed = self.elapsed
        summary = {"config_hash": self.key, "exit": self.spec.exit, "bake_seconds": elapsed,
                   "tracing_cpu_seconds": self.cpu,
                   "paths": int(tally.paths.sum()),
                   "vertices": int(tally.vertices), "vertices_per_second": tally.vertices / max(elapsed, 1e-9),
                   "n_fibers": len(bundle.radii), "packing_fraction": bundle.packing_fraction,
                   **{k: float(np.mean(v)) for k, v in balance.items()},  # scattered, passthrough, ...
                   "max_abs_energy_error": float(np.max(np.abs(balance["total"] - 1))),
                   # the share of the scattered light that left after one fiber event, per wavelength
                   "single_share": table.single_share().tolist(),
                   **{f"{q}_mc_error": batch_means_error(v, self.sizes, [a for a, _ in self.work])
                      for q, v in self.batch_estimates.items()}}
        summary = BakeSummary(**summary, reductions={"used": self.reductions,
                                                     **reduction_cost(cfg, self.baker, elapsed)})
        summary.write(out / "summary.json")
        write_metrics(cfg, self.out_root, "bake", {
            "passthrough": float(np.mean(table.passthrough)), "albedo": summary.scattered,
            "max_abs_energy_error": summary.max_abs_energy_error, "bake_seconds": elapsed,
            "vertices_per_second": summary.vertices_per_second})
        # the pictures go with the table they show: a bake that fails before this point leaves
        # the last table and its own pictures, not a new arrangement beside an old table
        bundle.plot(out / "arrangement.png")
        plot_table(table, out / "slices")
        plot_balance(table, out / "energy.png")
        self.ckpt.unlink(missing_ok=True)
        print(f"[bake] {cfg.name} ({c.estimator}): {tally.paths.sum():.3g} paths, {tally.vertices:.3g} vertices "
              f"in {elapsed:.1f} s ({summary.vertices_per_second / 1e6:.2f} M vertices/s); passthrough "
              f"{table.passthrough.mean():.3f}; energy total {np.mean(balance['total']):.4f}; scattered after one "
              f"fiber {summary.single_share[0]:.0%} ({table.wavelength[0]:.0f} nm) .. "
              f"{summary.single_share[-1]:.0%} ({table.wavelength[-1]:.0f} nm); wrote {out}")
        return out


def batch_means_error(estimates, sizes, azimuths) -> float | None:
    """Standard error of a bake's mean (over incident azimuths) from its batches' own
    estimates: per azimuth, the batches are independent estimates of one mean, each
    with variance sigma^2 / n_k, so ``sigma^2 = sum n_k (x_k - x)^2 / (K - 1)`` and the
    mean's variance is ``sigma^2 / N``. ``None`` with a single batch per azimuth."""
    x, n, a = np.asarray(estimates), np.asarray(sizes, float), np.asarray(azimuths)
    if not np.all(np.isfinite(x)):
        return None
    variances = []
    for az in np.unique(a):
        xk, nk = x[a == az], n[a == az]
        if len(xk) < 2:
            return None
        mean = np.sum(nk * xk) / nk.sum()
        variances.append(np.sum(nk * (xk - mean) ** 2) / (len(xk) - 1) / nk.sum())
    return float(np.sqrt(np.sum(variances)) / len(variances))


def reduction_cost(cfg, baker: Baker, bake_seconds: float, probe_paths: int = 50_000) -> dict:
    """Table size and bake time with the symmetry reductions (this bake) and without them.

    Without: theta_i over [-90, 90] deg and phi_i over the whole circle at
    ``bake.phi_i_step_deg``, absolute phi_o. Its time is measured, not guessed: batches
    of probe paths at the first incident azimuth through both specs, alternating
    (kernels compiled by a warm-up first); the median of three ratios (one ratio alone
    ranged over 4x on this shared machine) times the ratio of azimuths, applied to this
    bake's time (a twisted ply's paths carry one theta_i each: its cost is per azimuth).
    """
    c, spec = cfg.bake, baker.spec
    probe_paths = min(probe_paths, c.paths_per_phi_i, c.batch_paths)
    full = BakeSpec(theta_nodes(c.theta_i_nodes_deg(), negative=True),
                    np.deg2rad(np.arange(0, 360 - 1e-9, c.phi_i_step_deg)), c.n_theta_o, c.n_phi_o,
                    relative_phi=False, estimator=c.estimator, max_bounces=c.max_bounces, rr_start=c.rr_start,
                    exit=spec.exit, theta_o_edges=spec.theta_o_edges)

    def seconds(b, k):
        t0 = time.perf_counter()
        b.trace(0, probe_paths, np.random.SeedSequence([c.seed, 999, k]))
        return time.perf_counter() - t0

    if isinstance(baker, (TwistedBaker, TwistedCameraBaker)):
        per_azimuth = 1.0  # each path carries one theta_i either way: the cost is per azimuth
    else:
        full_baker = copy.copy(baker)  # the same scene and fiber sampler, only the spec differs
        full_baker.spec = full
        for b in (baker, full_baker):
            b.trace(0, min(2000, probe_paths), np.random.SeedSequence([c.seed, 998]))  # compile
        per_azimuth = float(np.median([seconds(full_baker, k) / max(seconds(baker, k), 1e-9) for k in range(3)]))

    def nbytes(sp):  # values and stderr, float32
        return 2 * 4 * len(sp.phi_i) * len(sp.theta_i) * sp.n_phi_o * sp.n_theta_o * baker.n_lambda
    return {"reduced_bytes": nbytes(spec), "full_bytes": nbytes(full), "reduced_seconds": bake_seconds,
            "full_seconds": bake_seconds * per_azimuth * len(full.phi_i) / len(spec.phi_i),
            "reduced_incidences": [len(spec.phi_i), len(spec.theta_i)],
            "full_incidences": [len(full.phi_i), len(full.theta_i)], "probe_paths": probe_paths}


def plot_table(table: BundleTable, folder: Path) -> None:
    relative = table.meta["reductions"]["phi_o"] == "relative"
    n_phi = len(table.phi_o)
    for a, phi_i in enumerate(table.phi_i):
        for j in slice_nodes(table.theta_i):
            theta_i = table.theta_i[j]
            f = theta_rows(table.values[a, j].transpose(1, 0, 2), table.theta_o_edges)  # [theta_o, phi_o, lambda]
            if relative:  # dphi over [0, 360): forward (180) in the middle
                f = np.roll(f, n_phi // 2, axis=1)
                xlabel, extent = "dphi = phi_o - phi_i [deg]  (0: back to the light, 180: forward)", (0, 360, -90, 90)
            else:
                xlabel, extent = "phi_o [deg] (bundle frame)", (-180, 180, -90, 90)
            name = f"phi_i_{np.rad2deg(phi_i):05.1f}_theta_i_{np.rad2deg(theta_i):+05.1f}.png"
            spectral_image(f, table.wavelength, folder / name,
                           f"bundle: phi_i = {np.rad2deg(phi_i):.0f} deg, theta_i = {np.rad2deg(theta_i):.0f} deg, "
                           f"passthrough {table.passthrough[a]:.3f}", xlabel=xlabel, extent=extent)


def plot_balance(table: BundleTable, path: Path) -> None:
    bal = table.energy_balance()
    single = table.single is not None
    fig, axes = plt.subplots(1, 2 if single else 1, figsize=(11.5 if single else 6.5, 4.2), dpi=110, squeeze=False)
    ax = axes[0, 0]
    t = np.rad2deg(table.theta_i)
    parts = [("scattered", "#4c72b0"), ("passthrough", "#bbbbbb"), ("absorbed", "#c44e52"), ("lost", "#dd8452")]
    base = np.zeros(len(t))
    for name, color in parts:
        v = bal[name].mean(axis=(0, 2))  # over phi_i and wavelengths
        ax.fill_between(t, base, base + v, color=color, label=name, step=None, alpha=0.9)
        base = base + v
    ax.plot(t, base, "k--", lw=1, label="total")
    if single:  # the part of the scattered band that left after one fiber event
        ax.fill_between(t, 0, table.single.mean(axis=(0, 2)), facecolor="none", edgecolor="#1b2a49", hatch="//",
                        lw=0, label="of it, after one fiber")
    ax.set(xlabel="theta_i [deg]", ylabel="fraction of light entering 2 R_b", ylim=(0, max(1.05, base.max() * 1.02)),
           title="energy balance (mean over phi_i and wavelengths)")
    ax.legend(loc="lower left", fontsize=8)
    if single:
        ax = axes[0, 1]
        nodes = [j for j in slice_nodes(table.theta_i) if t[j] >= 0] or list(slice_nodes(table.theta_i))
        for k, j in enumerate(nodes):
            s = bal["scattered"][:, j].sum(0)
            ax.plot(table.wavelength, table.single[:, j].sum(0) / np.maximum(s, 1e-300),
                    color=plt.cm.viridis(k / max(1, len(nodes) - 1)), label=f"theta_i {t[j]:.0f} deg")
        ax.set(xlabel="wavelength [nm]", ylabel="share of the scattered light", ylim=(0, 1.02),
               title="scattered after one fiber event (over phi_i)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
