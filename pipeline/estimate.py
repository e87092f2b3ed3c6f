"""How long ``bcsdf run`` will take, said before it starts: a rough estimate per stage.

A stage's time is a fixed **overhead** (imports, kernel compilation) plus its **work** (a
size the config implies: paths times the chord of the bundle in fibers, epochs times bins
times the model's width, pixels times samples ...) times **seconds per unit of work**.
That rate comes from the last run of the same stage on this machine when there is one
(its stamp records work and seconds), else from the default config measured on the
reference 2-core machine (``REFERENCE`` below; figures in docs/BENCHMARKS.md). Good to a
factor of about two: enough to decide between waiting and coming back tomorrow, not a
benchmark.
"""

from __future__ import annotations

import json

from .graph import stamp_path

# seconds per unit of work of each stage beyond its overhead: `make run` on a fresh clone
# with a cold Dr.Jit kernel cache, session 10 (the stages' stamps; docs/BENCHMARKS.md,
# "The whole default pipeline"); export: session 19 (cooperative vectors for the large MLP);
# fiber, train and report: sessions 21-23 (fewer fiber slices; training 150-206 s on this
# machine from day to day, the median taken; the report no longer times anything)
OVERHEAD = {"fiber": 2.0, "bake": 3.0, "train": 3.0, "export": 3.0, "render": 4.0, "cloth": 8.0, "stability": 0.0,
            "sweep": 3.0, "report": 2.0}
REFERENCE = {"fiber": 4.4e-4, "bake": 8.4e-7, "train": 1.25e-6, "export": 3.3, "render": 1.9e-6,
             "cloth": 1.5e-5, "stability": 8.0, "sweep": 8.4e-7, "report": 0.0}  # a sweep's work: its members' bakes


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
        total += (t.epochs + t.calibration_steps) * bins * (1 + params / 10_000)
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
    from .config import sweep_members

    return sum(_bake_work(m) for _, m in sweep_members(cfg))


WORK = {"fiber": _fiber_work, "bake": _bake_work, "train": _train_work, "export": _export_work,
        "render": _render_work, "cloth": _cloth_work, "sweep": _sweep_work, "stability": lambda cfg: 1.0, "report": lambda cfg: 1.0}


def work(stage: str, cfg) -> float:
    return float(WORK[stage](cfg))


def estimate(stage: str, cfg, root="artifacts") -> tuple[float, str]:
    """Seconds ``stage`` should take for this config, and where the rate came from."""
    overhead = OVERHEAD[stage]
    try:
        record = json.loads(stamp_path(stage, cfg, root).read_text())
        rate = max(record["seconds"] - overhead, 0.0) / max(record["work"], 1e-30)
        source = "its last run here"
    except (OSError, ValueError, KeyError, TypeError):
        rate, source = REFERENCE[stage], "the reference machine"
    return overhead + work(stage, cfg) * rate, source


def describe(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, int(round(seconds)))} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def plan(cfg, stages, root="artifacts") -> str:
    """One line per stage to run and the total, for ``bcsdf run`` to print first."""
    lines, total = [], 0.0
    for stage in stages:
        seconds, source = estimate(stage, cfg, root)
        total += seconds
        lines.append(f"  {stage:<9} ~{describe(seconds):>7}   (rate from {source})")
    return "\n".join([f"[run] estimate for {cfg.name}: ~{describe(total)} in all (rough: a factor of 2)"] + lines)

