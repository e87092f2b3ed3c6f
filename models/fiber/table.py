"""Tabulated fiber data from elsewhere: Xia et al. 2023 raw files and generic npz.

**Xia et al. 2023** (``WaveFiber3d``): one file per incident direction, wavelength and
polarization, ``theta-{k}-phi-0/fiber_{f}_lambda{L}_T{M|E}_depth{d}.binary``: float32,
row-major, shape (450, 880) = (theta_o, phi_o) with ``theta_o = -pi/2 + pi i / 450``
and ``phi_o = 2 pi j / 880``, fiber axis z, direction
``(cos t cos p, cos t sin p, sin t)``. The incident vector (``t = -pi/2 + pi k / 180``,
``p = 0``) is the propagation direction. Wavelength ``400 + 12 L`` nm.

Conversion to this project's frame: our ``w_i`` points back to the light, so
``theta_i = -t_inc`` and the light's azimuth is ``phi_i = pi`` in their plane; the
scattered direction is already "away from the fiber", so ``theta_o = t`` and
``dphi = p - pi`` (forward scattering ``p = 0`` lands at ``dphi = -pi == pi``).
Values are ``|E|^2`` at 1 m, unnormalized: each (incidence, wavelength) slice is
divided by ``sum raw cos(theta_o) dtheta dphi`` and scaled to the given albedo. TM and
TE are averaged (unpolarized light). Incidence below the normal plane is mirrored
(``theta_i, theta_o -> -theta_i, -theta_o``), valid for an untilted fiber.

**Generic npz**: arrays ``values`` and ``axes`` (the names of its axes, in order,
a permutation of ``theta_i, theta_o, phi, wavelength``) plus one array per axis
(radians, nm; ``phi`` is ``dphi``, uniform over [-pi, pi)). Values are in the
project's normalization already.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import numpy as np

from .base import FiberModel, FiberTable, Lobe
from .longitudinal import Longitudinal

XIA_SHAPE = (450, 880)
XIA_NAME = re.compile(r"fiber_(?P<f>[^_]+)_lambda(?P<L>\d+)_T(?P<pol>[ME])_depth(?P<d>\d+)\.binary$")
XIA_DIR = re.compile(r"theta-(?P<k>\d+)-phi-0$")
AXES = ("theta_i", "theta_o", "phi", "wavelength")


def read_xia_file(path) -> np.ndarray:
    """One raw file as float64 (450, 880); a truncated or oversized file is refused."""
    path = Path(path)
    expected = XIA_SHAPE[0] * XIA_SHAPE[1] * 4
    size = path.stat().st_size
    if size != expected:
        raise ValueError(f"{path}: {size} bytes, expected {expected} (float32 {XIA_SHAPE[0]}x{XIA_SHAPE[1]}); "
                         "the file is truncated or not a Xia et al. 2023 raw file")
    raw = np.fromfile(path, dtype="<f4").reshape(XIA_SHAPE).astype(np.float64)
    if not np.all(np.isfinite(raw)) or np.any(raw < 0):
        raise ValueError(f"{path}: holds negative or non-finite intensities")
    return raw


def load_xia2023(directory, albedo: float = 1.0) -> FiberTable:
    """All incidences and wavelengths under ``directory`` as one dense-lobe table."""
    directory = Path(directory)
    files: dict[tuple[int, int], dict[str, Path]] = {}
    for path in sorted(directory.glob("theta-*-phi-0/*.binary")):
        mk, mn = XIA_DIR.match(path.parent.name), XIA_NAME.match(path.name)
        if mk and mn:
            files.setdefault((int(mk["k"]), int(mn["L"])), {})[mn["pol"]] = path
    if not files:
        raise ValueError(f"{directory}: no files theta-K-phi-0/fiber_*_lambdaL_T[M|E]_depthD.binary found")
    ks = sorted({k for k, _ in files})
    Ls = sorted({L for _, L in files})
    missing = [(k, L, pol) for k in ks for L in Ls for pol in "ME" if pol not in files.get((k, L), {})]
    if missing:
        k, L, pol = missing[0]
        raise ValueError(f"{directory}: incomplete data, e.g. no T{pol} file for theta-{k} lambda{L} "
                         f"({len(missing)} missing); every incidence needs every wavelength in TM and TE")

    theta_o = -np.pi / 2 + np.pi * np.arange(XIA_SHAPE[0]) / XIA_SHAPE[0]
    phi = 2 * np.pi * np.arange(XIA_SHAPE[1]) / XIA_SHAPE[1] - np.pi
    theta_i = np.pi / 2 - np.pi * np.asarray(ks) / 180.0
    order = np.argsort(np.abs(theta_i))
    if len(np.unique(np.abs(theta_i))) != len(theta_i):
        raise ValueError(f"{directory}: incidences mirror each other (k and 180-k both present)")
    N = np.empty((len(ks), XIA_SHAPE[0], XIA_SHAPE[1], len(Ls)), dtype=np.float32)
    cell = np.cos(theta_o)[:, None] * (np.pi / XIA_SHAPE[0]) * (2 * np.pi / XIA_SHAPE[1])
    for row, a in enumerate(order):
        k = ks[a]
        for j, L in enumerate(Ls):
            raw = 0.5 * (read_xia_file(files[k, L]["M"]) + read_xia_file(files[k, L]["E"]))
            total = np.sum(raw * cell)
            if total <= 0:
                raise ValueError(f"{directory}: theta-{k} lambda{L} scatters no energy")
            f = albedo * raw / total
            if theta_i[a] < 0:  # mirror along the axis: theta_o -> -theta_o
                f = _mirror_theta(f, theta_o)
            N[row, :, :, j] = f
    meta = {"model": "table", "source": "xia2023", "directory": str(directory), "albedo": albedo}
    wl = 400.0 + 12.0 * np.asarray(Ls, dtype=np.float64)
    return FiberTable(np.abs(theta_i[order]), theta_o, phi, wl, [Lobe("measured", Longitudinal("none"), N)], meta)


def _mirror_theta(f: np.ndarray, theta_o: np.ndarray) -> np.ndarray:
    """``f(-theta_o)`` on the same (asymmetric) grid, by linear interpolation."""
    out = np.empty_like(f)
    for c in range(f.shape[1]):
        out[:, c] = np.interp(-theta_o, theta_o, f[:, c])
    return out


def load_npz(path) -> FiberTable:
    """A generic tabulated fiber function (npz with named axes, see module docs)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            axes = [str(a) for a in z["axes"]]
            if sorted(axes) != sorted(AXES):
                raise ValueError(f"axes {axes}; expected a permutation of {list(AXES)}")
            values = np.transpose(z["values"], [axes.index(a) for a in AXES]).astype(np.float32)
            grids = {a: np.asarray(z[a], dtype=np.float64) for a in AXES}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: not a readable tabulated fiber ({e})") from e
    shape = tuple(len(grids[a]) for a in AXES)
    if values.shape != shape:
        raise ValueError(f"{path}: values have shape {values.shape} but the axes give {shape}")
    table = FiberTable(grids["theta_i"], grids["theta_o"], grids["phi"], grids["wavelength"],
                       [Lobe("tabulated", Longitudinal("none"), values)], {"model": "table", "source": str(path)})
    table.validate()
    return table


class TableFiber(FiberModel):
    """A fiber given by data: ``f`` is the table, interpolated; tabulation returns it."""

    name = "table"

    def __init__(self, table: FiberTable):
        super().__init__(table.wavelength)
        self._table = table

    def tabulate(self, theta_i=None) -> FiberTable:
        return self._table
