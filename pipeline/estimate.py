"""How long ``bcsdf run`` will take, said before it starts: a rough estimate per stage.

A stage's time is a fixed **overhead** (imports, kernel compilation) plus its **work** (a
size the config implies: paths times the chord of the bundle in fibers, epochs times bins
times the model's width, pixels times samples ...) times **seconds per unit of work**.
That rate comes from the last run of the same stage on this machine when there is one
(its stamp records work and seconds), else from the default config measured on the
reference 2-core machine (``REFERENCE`` below).

The same machine runs the same stages markedly faster on one day than on another (shared
hosts). So the rate is scaled by the machine's **pace**: a fixed short :func:`probe` (matrix
products on two threads, array arithmetic, a Python loop) timed now, over the same probe
when the rate was measured (``PROBE_REFERENCE``, or the one a stamp recorded). Good to
about a third: enough to decide between waiting and coming back tomorrow, not a benchmark.
"""

from __future__ import annotations

import json
import time

import torch

from .loading import sweep_members
from .graph import stamp_path

# seconds per unit of work of each stage beyond its overhead, from the stamps of `make run` on a
# fresh clone with a fresh HOME (cold Dr.Jit kernel cache) at the pace PROBE_REFERENCE; cloth and
# sweep from their own runs, scaled to that pace. The estimate is a forecast, printed beside the
# seconds each stage then takes: a machine or code that drifts from it shows there
OVERHEAD = {"fiber": 2.0, "bake": 3.0, "train": 3.0, "export": 3.0, "render": 4.0, "cloth": 8.0, "stability": 0.0,
            "sweep": 3.0, "family": 5.0, "report": 1.0}
REFERENCE = {"fiber": 2.9e-4, "bake": 5.75e-7, "train": 8.5e-7, "export": 1.97, "render": 1.23e-6,
             "cloth": 1.0e-5, "stability": 6.3, "sweep": 5.75e-7, "family": 2.9e-6, "report": 0.0}  # a sweep's work: its members' bakes; a family's:
# its one model's training (train units: wider, the orders and the packing, it costs more a unit), its
# measures and renders (from configs/packing_sweep.yaml's run)
PROBE_REFERENCE = 10.6e-3  # seconds of probe() on the machine and day REFERENCE was measured
_PROBE: list = []  # this process's probe, measured once


def probe() -> float:
    """Seconds of a fixed piece of work like the stages' (float32 matrix products on the
    BLAS threads, array arithmetic, a Python loop), the median of 30 repeats after one to
    warm up: this machine's pace now. The whole probe (~0.3 s, once per process) spans
    several periods of a CPU quota (0.1 s), so a throttled machine shows, as a busy one
    does; the median, not the mean, so that a few repeats that lost their core to another
    process (BLAS threads waiting on each other) do not make the whole run look 30x slower."""
    if not _PROBE:
        import numpy as np

        rng = np.random.default_rng(0)
        a = rng.standard_normal((256, 256)).astype(np.float32)
        x = rng.standard_normal(200_000).astype(np.float32)

        def once():
            for _ in range(60):
                a @ a
            np.exp(-x * x) + np.sqrt(np.abs(x))
            s = 0.0
            for k in range(10_000):
                s += 0.5 * k
        once()
        times = []
        for _ in range(30):
            t0 = time.perf_counter()
            once()
            times.append(time.perf_counter() - t0)
        _PROBE.append(float(np.median(times)))
    return _PROBE[0]


def measured_probe() -> float | None:
    """:func:`probe`, if this process has measured it (what a stage's stamp records)."""
    return _PROBE[0] if _PROBE else None


def _fiber_work(cfg) -> float:
    nodes = 90 / cfg.tabulate.theta_i_step_deg + 1
    f = cfg.fiber
    if f.model == "mie":  # the azimuthal resolution follows the size parameter
        per = f.radius_um / (cfg.wavelengths.start_nm / 1000)
    elif f.model == "ray":
        per = 50 * f.ray.n_h * f.ray.n_phi / (256 * 360)
    else:
        per = 5.0
    return nodes * cfg.wavelengths.count * per


# a twisted ply's path costs this many parallel ones (3D casts against helix segments, wraps
# of the period): `make bench-twisted`, docs/BENCHMARKS.md "Twisted plies" (5.6x measured)
TWISTED_PATH = 5.6


def _bake_work(cfg, twisted=None) -> float:
    n_phi_i, _ = cfg.incidences()
    chord = cfg.bundle.bounding_radius_um() / cfg.fiber.radius_um  # a path's length in fibers, roughly
    twisted = cfg.bundle.twist is not None if twisted is None else twisted
    return cfg.bake.paths_per_phi_i * n_phi_i * chord * (TWISTED_PATH if twisted else 1.0)


def _train_work(cfg) -> float:
    n_phi_i, n_theta_i = cfg.incidences()
    bins = n_phi_i * n_theta_i * cfg.bake.n_phi_o * cfg.bake.n_theta_o
    t = cfg.train
    total = 0.0
    for hidden in t.models.values():
        widths = [16] + list(hidden) + [cfg.wavelengths.count]
        params = sum((a + 1) * b for a, b in zip(widths[:-1], widths[1:]))
        # the energy gain: 8 x 8 forward passes over every bin, an epoch 2 x 2 forward and
        # backward (~3 forwards): ~5 epochs' work
        total += (t.epochs + 5 * t.energy_gain) * bins * (1 + params / 10_000)
    return total


def _export_work(cfg) -> float:
    return len(cfg.train.models) * (1 + cfg.report.queries / 200_000)


def _render_work(cfg) -> float:
    r = cfg.render
    pixels = r.width * r.height
    work = pixels * r.spp * len(r.scenes) * len(r.backends)
    if r.mono_check:
        work += r.mono_check_size[0] * r.mono_check_size[1] * r.mono_check_spp * (cfg.wavelengths.count + 1)
    if r.explicit:
        work += pixels * r.explicit_spp * 4
        if cfg.bundle.twist is not None:
            # beyond a parallel ply's closure (in the rate): the twisted closure's explicit bins
            # (16 nodes x 4 azimuths x 16 views of 32 x 32 pixels, 8 spp; the scenes' loads and
            # kernels dominate, ~30x the pixels), the parallel table's 2D bake (a bake unit in
            # render units) and the highlight's cut (41 points x 8 views)
            _, n_theta_i = cfg.incidences()
            per_view = 32 * 32 * 8 * 30
            work += ((n_theta_i // 2) * 4 * 16 + 41 * 8) * per_view
            work += _bake_work(cfg, twisted=False) / n_theta_i * REFERENCE["bake"] / REFERENCE["render"]
    return float(work)


def _cloth_work(cfg) -> float:
    c = cfg.cloth
    return float(c.width * c.height * c.spp * len(c.backends))


def _sweep_work(cfg) -> float:
    return sum(_bake_work(m) for _, m in sweep_members(cfg))


def _family_work(cfg) -> float:
    """One model trained on every member not held out (a train unit per member's bins), and
    the yarn's renders: two per held-out packing, five (or fifteen, dyed) for the strip."""
    f = cfg.family
    trained = [m for point, m in sweep_members(cfg) if not f.holds_out(point["bundle.packing"])]
    one = cfg.model_copy(update={"train": cfg.train.model_copy(
        update={"models": {"family": cfg.train.models[f.model or next(iter(cfg.train.models))]}})})
    r = cfg.render
    renders = 2 * len(f.held_out) + (5 * (3 if cfg.bake.orders else 1) if f.strip else 0)
    return len(trained) * _train_work(one) + renders * r.width * r.height * r.spp * REFERENCE["render"] / REFERENCE[
        "family"]


WORK = {"fiber": _fiber_work, "bake": _bake_work, "train": _train_work, "export": _export_work,
        "render": _render_work, "cloth": _cloth_work, "sweep": _sweep_work, "family": _family_work,
        "stability": lambda cfg: 1.0, "report": lambda cfg: 1.0}


def work(stage: str, cfg) -> float:
    return float(WORK[stage](cfg))


def estimate(stage: str, cfg, root="artifacts") -> tuple[float, str]:
    """Seconds ``stage`` should take for this config, and where the rate came from; the
    rate scaled by the machine's pace now against its pace when the rate was measured."""
    overhead = OVERHEAD[stage]
    try:
        record = json.loads(stamp_path(stage, cfg, root).read_text())
        rate = max(record["seconds"] - overhead, 0.0) / max(record["work"], 1e-30)
        then, source = record.get("probe"), "its last run here"
    except (OSError, ValueError, KeyError, TypeError):
        rate, then, source = REFERENCE[stage], PROBE_REFERENCE, "the reference machine"
    pace = probe() / then if then else 1.0
    return overhead + work(stage, cfg) * rate * pace, source + (f", pace x{pace:.2f}" if then else "")


def describe(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, int(round(seconds)))} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


_PLANNED: dict = {}  # this process's estimates, for against_measured


def plan(cfg, stages, root="artifacts") -> str:
    """One line per stage to run and the total, for ``bcsdf run`` to print first."""
    lines, total = [], 0.0
    for stage in stages:
        seconds, source = estimate(stage, cfg, root)
        _PLANNED[stage] = seconds
        total += seconds
        lines.append(f"  {stage:<9} ~{describe(seconds):>7}   (rate from {source})")
    head = f"[run] estimate for {cfg.name}: ~{describe(total)} in all (rough: a third either way)"
    if "train" in stages:
        head += "\n" + kernels_note()
    return "\n".join([head] + lines)


def kernels_note() -> str:
    """Which CPU kernels torch chose (``ATEN_CPU_CAPABILITY`` overrides), and what that means
    for training: the rates above were measured with vector kernels."""

    capability = torch.backends.cpu.get_cpu_capability()
    if capability.upper() in ("DEFAULT", "NO AVX"):
        return (f"  torch runs its scalar kernels ({capability}: no AVX2 here, or ATEN_CPU_CAPABILITY=default): "
                "training runs slower than this estimate (its rates come from vector kernels); the results are "
                "checked against the same derived bounds")
    return f"  torch's CPU kernels: {capability}"


def against_measured(cfg, measured: dict) -> str:
    """The estimate :func:`plan` printed beside the seconds each stage took, for ``bcsdf run``
    to print last: how far to trust the next estimate on this machine."""
    lines = [f"[run] {cfg.name}: stage times, estimated and measured",
             f"  {'stage':<9} {'estimated':>10} {'measured':>10} {'ratio':>6}"]
    for stage, seconds in measured.items():
        guess = _PLANNED.get(stage)
        ratio = f"{seconds / guess:6.2f}" if guess else "     -"
        lines.append(f"  {stage:<9} {describe(guess) if guess else '-':>10} {describe(seconds):>10} {ratio}")
    total, guess = sum(measured.values()), sum(_PLANNED.get(s, 0.0) for s in measured)
    lines.append(f"  {'all':<9} {describe(guess) if guess else '-':>10} {describe(total):>10} "
                 + (f"{total / guess:6.2f}" if guess else "     -"))
    return "\n".join(lines)
