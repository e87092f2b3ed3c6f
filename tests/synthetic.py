"""Synthetic bundle tables and configs, so that neural and plugin tests need no bake.

The table is an analytic ridge along the specular cone (``sin theta_o = -sin theta_i``)
with a 1e5:1 dynamic range, a cosine lobe in azimuth, three wavelengths and 1% noise,
averaged over each bin as a baked table is.
"""

import numpy as np
import yaml

from models.bundle_table import BundleTable
from models.grid import cone_edges
from pipeline.config import BAKE_SECTIONS
from pipeline.loading import load_config

WL = [450.0, 550.0, 650.0]


def synthetic_table(cfg, path, relative=True, dynamic_range=1e5, passthrough=0.0, cone=None, theta_i_deg=None,
                    offsets=0):
    """A bake-like table of a ridge on the cone; ``cone``: theta_o bins of the cone layout
    with a bin of ``cone`` degrees on every node's cone and one bin between, else 18 equal
    bins; theta_i nodes 15 deg apart, or ``theta_i_deg`` (0..90, e.g. graded). ``offsets``:
    a near field of that many cells, ``S (1 + 0.6 h sin dphi)`` at the cells' midpoints ``h``
    (the cells average to ``S``, and a circle's mirror, ``(h, dphi) -> (-h, -dphi)``, holds)
    and a passthrough rising towards the rims."""
    theta_i = np.deg2rad(np.arange(0, 91, 15.0) if theta_i_deg is None else np.asarray(theta_i_deg, float))
    phi_i = np.zeros(1) if relative else np.deg2rad([0.0, 45.0, 90.0])
    pe = np.linspace(-np.pi, np.pi, 37)
    te = cone_edges(theta_i, np.deg2rad(cone)) if cone else np.linspace(-np.pi / 2, np.pi / 2, 19)
    pc, tc = 0.5 * (pe[1:] + pe[:-1]), 0.5 * (te[1:] + te[:-1])
    PI, TI, PO, TO = np.meshgrid(phi_i, theta_i, pc, tc, indexing="ij")

    def f(po, so):
        ridge = np.exp(-(((so + np.sin(TI)) / 0.12) ** 2))
        lobe = 0.6 + 0.4 * np.cos(po - (0 if relative else PI))
        if not relative:  # an elliptical bundle: brighter seen across its major axis
            lobe = lobe * (1.0 + 0.5 * np.cos(2 * PI))
        return ridge * lobe
    # a baked table holds bin averages (per solid angle: uniform in phi_o and sin theta_o)
    sub = (np.arange(6) + 0.5) / 6
    s0, s1 = np.sin(te[:-1]), np.sin(te[1:])
    avg = np.mean([f(PO + (a - 0.5) * (pe[1] - pe[0]), s0 + b * (s1 - s0)) for a in sub for b in sub], axis=0)
    spectral = np.array([0.6, 0.8, 1.0])
    S = (1.0 / dynamic_range + avg)[..., None] * spectral
    rng = np.random.default_rng(0)
    E = 0.01 * S
    S = S + E * rng.standard_normal(S.shape)
    shape_pi = (len(phi_i), len(theta_i), len(WL))
    near = {}
    if offsets:
        h = -1 + (np.arange(offsets) + 0.5) * 2 / offsets
        w = 1 + 0.6 * h[:, None, None, None, None, None] * np.sin(PO - (0 if relative else PI))[None, ..., None]
        rim = (1 + np.abs(h)) / np.mean(1 + np.abs(h))
        near = {"near": (S[None] * w).astype(np.float32), "near_stderr": (E[None] * np.sqrt(offsets)).astype(np.float32)
                * np.ones((offsets,) + (1,) * S.ndim, np.float32),
                "near_passthrough": np.broadcast_to(np.clip(passthrough * rim, 0, 1), shape_pi[:2] + (offsets,)).copy()}
    table = BundleTable(**near,
        values=S.astype(np.float32), stderr=E.astype(np.float32), passthrough=np.full(len(phi_i), passthrough),
        passthrough_stderr=np.zeros(len(phi_i)), absorbed=np.zeros(shape_pi), lost=np.zeros(shape_pi),
        phi_i=phi_i, theta_i=theta_i, phi_o_edges=pe, theta_o_edges=te, wavelength=np.array(WL),
        meta={"reductions": {"theta_i": "mirror", "phi_i": "rotation" if relative else "mirror_xz",
                             "phi_o": "relative" if relative else "absolute"},
              "config_hash": cfg.hash(*BAKE_SECTIONS)})
    table.save(path)
    return table


def with_ripple(table, bins: int, depth: float = 0.3):
    """``table`` times a spectral ripple that changes from one bin of ``|phi_o - phi_i|`` to
    the next (``bins`` over [0, pi]; ``1 + depth sin(7 b + 2 l)`` in bin ``b`` at wavelength
    ``l``), as a fiber's Mie resonances make it: what a small network smooths and
    ``train.gain_azimuth_bins`` keeps. Mirror-symmetric in the azimuth, as a circle's is."""
    d = np.abs(np.angle(np.exp(1j * (table.phi_o[None, :] - table.phi_i[:, None]))))   # [phi_i, phi_o]
    b = np.minimum((d / np.pi * bins).astype(int), bins - 1)
    ripple = 1 + depth * np.sin(7.0 * b[..., None] + 2.0 * np.arange(len(table.wavelength)))   # [phi_i, phi_o, l]
    r = ripple[:, None, :, None, :]
    return table._replace(values=(table.values * r).astype(np.float32), stderr=(table.stderr * r).astype(np.float32))


def make_config(tmp_path, name="n", bake=None, **train):
    cfg = {"name": name, "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
           **({"bake": bake} if bake else {}),
           "fiber": {"model": "isotropic"},
           "bundle": {"shape": "circle", "radius_um": 100},
           "train": {"models": {"tiny": [16, 16], "wide": [32, 32, 32]}, "epochs": 60, "batch_size": 128,
                     "patience": 60, **train},
           "report": {"queries": 5000}}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return load_config(path)


