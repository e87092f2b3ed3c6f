"""Dyes from an order-resolved bake, measured (docs/DESIGN.md, "Order-resolved tables").

On the default ply's geometry (200 um, 20 um fibers, Poisson-disk tight, seed 1) with a
lossless ``ray`` fiber (eta 1.55, roughness 0.2 / 0.3, no tilt), three questions:

1. **The tail** (``bake.orders: K``): orders ``k >= K`` are kept as one sum and recoloured
   as a geometric series of the ratio their mean order gives. Against a bake of the same
   paths resolved to 64 orders (same seed: only the tail's model differs), the worst
   relative albedo error and the worst bin error (relative to the largest value) per
   per-event albedo ``a``.
2. **Dyes**: ``BundleTable.recolour(a)`` against a direct bake of the dyed fiber
   (``FiberTable.dyed(a)``, another seed) for a grey, the ColorChecker's red patch (Ohta's
   reflectance, as colour-science ships it) and a dark fiber: z of every bin holding 2% of
   its incidence's peak (mean and mean square: 0 and 1 when they agree) and the albedo ratio.
3. **An absorbing fiber is not a dyed one**: a ray fiber with ``sigma_a`` changes its lobes
   (TT and TRT lose more than R), and so does a Mie fiber with an imaginary index ``k``
   (20 um, n 1.55, roughness 3 deg), where a dye scales them alike. The lossless bake
   recoloured with the absorbing fiber's own albedo (its mean over incidences, per
   wavelength) against a direct bake of the absorbing fiber: albedo ratio and the relative
   L1 over the bins, worst over incidences and wavelengths.

Records ``benchmarks/dye.json``::

    .venv/bin/python -m pipeline.bench.dye            # about 2 minutes on 2 cores
    .venv/bin/python -m pipeline.bench.dye --quick    # fewer paths, not recorded
"""

from __future__ import annotations

import argparse

import colour
import mitsuba as mi
import numpy as np

from models.bake import BakeSpec, bake_unreduced
from models.bundle import poisson
from models.fiber.mie import MieFiber
from models.fiber.ray import RayFiber

from . import results

WL = np.array([450.0, 550.0, 650.0])
THETA_I = np.deg2rad([0.0, 45.0, 80.0])
ALBEDOS = (0.99, 0.95, 0.8, 0.5, 0.3)
NODES = np.deg2rad(np.arange(0, 91, 5.0))
ABSORBING = {"ray": ("sigma_a per radius", (0.05, 0.3, 1.0)), "mie": ("k", (1e-4, 5e-4, 2e-3))}


def ray(sigma_a=0.0):
    return RayFiber(WL, eta=1.55, sigma_a=sigma_a, longitudinal_roughness=0.2, azimuthal_roughness=0.3,
                    scale_tilt_deg=0.0, n_h=64, n_phi=180).tabulate(NODES)


def mie(k=0.0):
    return MieFiber(WL, 20.0, [1.55] * len(WL), [k] * len(WL), 3.0).tabulate(NODES)


def bake(ply, fiber, paths, seed, orders=0):
    return bake_unreduced(ply, fiber, BakeSpec(THETA_I, np.zeros(1), 12, 32, orders=orders), paths, seed)


def tail_rows(ply, fiber, paths):
    ref = bake(ply, fiber, paths, 3, 64)
    rows = []
    for K in (2, 4, 6, 8, 12):
        T = bake(ply, fiber, paths, 3, K)
        row = {"K": K}
        for a in ALBEDOS:
            t, r = T.recolour(a), ref.recolour(a)
            row[f"albedo a={a}"] = f"{np.abs(t.scattered / r.scattered - 1).max():.1e}"
            row[f"bins a={a}"] = f"{np.abs(t.values - r.values).max() / r.values.max():.1e}"
        rows.append(row)
    return rows


def z_row(name, R, D):
    se = np.sqrt(R.stderr.astype(np.float64) ** 2 + D.stderr.astype(np.float64) ** 2)
    big = (D.values > 0.02 * D.values.max(axis=(2, 3), keepdims=True)) & (se > 0)
    z = ((R.values - D.values) / np.where(se > 0, se, 1))[big]
    ratio = R.scattered / D.scattered
    return {"fiber": name, "bins": int(z.size), "mean z": float(z.mean()), "mean z^2": float(np.mean(z**2)),
            "albedo ratio min": float(ratio.min()), "albedo ratio max": float(ratio.max())}


def l1(R, D):
    """Relative L1 over the bins, per incidence and wavelength, worst of them."""
    w = D.solid_angle[None, None, :, :, None]
    return float(((np.abs(R.values - D.values) * w).sum((2, 3)) / (D.values * w).sum((2, 3))).max())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer paths (not recorded)")
    args = ap.parse_args(argv)
    mi.set_variant("llvm_ad_mono")
    paths = 50_000 if args.quick else 400_000
    ply = poisson((200.0, 200.0), 20.0, seed=1)
    clear = ray()
    with results.recorded("dye", smoke=args.quick):
        print(f"ply: {len(ply.radii)} fibers of 20 um in 200 um; {paths} paths per bake; theta_i 0, 45, 80 deg; "
              f"lambda {WL.tolist()} nm")
        print("\n1. the tail's model against 64 orders of the same paths (worst over theta_i and lambda)")
        print(results.rows_table(tail_rows(ply, clear, paths)))
        resolved = bake(ply, clear, paths, 3, 8)
        red = np.asarray(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]["red"][WL])
        dyes = {"grey 0.95": np.full(3, 0.95), "ColorChecker red": red, "dark 0.3": np.full(3, 0.3)}
        rows = [z_row(name, resolved.recolour(a), bake(ply, clear.dyed(a), paths, 17)) for name, a in dyes.items()]
        print("\n2. recoloured (K = 8) against direct bakes of the dyed fiber")
        print(results.rows_table(rows))
        rows = []
        for family, make in (("ray", ray), ("mie", mie)):
            what, levels = ABSORBING[family]
            lossless = resolved if family == "ray" else bake(ply, make(), paths, 3, 8)
            for level in levels:
                absorbing = make(level)
                a = absorbing.albedo(THETA_I).mean(axis=0)      # the fiber's own albedo per wavelength
                R, D = lossless.recolour(a), bake(ply, absorbing, paths, 17)
                ratio = R.scattered / D.scattered
                rows.append({"fiber": f"{family}, {what} {level:g}", "fiber albedo": f"{a.min():.3f}..{a.max():.3f}",
                             "albedo ratio min": float(ratio.min()), "albedo ratio max": float(ratio.max()),
                             "worst relative L1": l1(R, D)})
        print("\n3. absorbing fibers against the lossless bake recoloured with their albedo")
        print(results.rows_table(rows))

if __name__ == "__main__":
    main()
