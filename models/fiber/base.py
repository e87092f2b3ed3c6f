"""The interface shared by all single-fiber models, and their tabulated form.

Frame and normalization are docs/DESIGN.md's: +y is the fiber axis, a direction ``w``
(pointing away from the fiber, for both ``w_i`` and ``w_o``) has
``sin(theta) = w.y`` and ``phi = atan2(w.z, w.x)``; ``f`` includes the cosine, so
``integral f d omega_o`` is the albedo of the fiber per geometric hit.

A single fiber is a circular cylinder, so ``f`` depends on the azimuths only through
``dphi = phi_o - phi_i`` (forward scattering is ``dphi = pi``). Every model here is a
sum of lobes

    f(theta_i, theta_o, dphi, lambda) = sum_p M_p(theta_i, theta_o) N_p(theta_i, [theta_o,] dphi, lambda)

with an analytic longitudinal lobe ``M_p`` (``integral M_p cos(theta_o) d theta_o = 1``)
and a tabulated azimuthal part ``N_p``. Separable lobes (Mie, the ray model's R, TT,
TRT, residual) keep ``N_p`` independent of theta_o, which lets a sharp longitudinal
lobe and a finely resolved diffraction peak live in a table of a few megabytes. Dense
lobes (measured data) carry a theta_o axis and ``M = 1``.

Only ``theta_i >= 0`` is stored: ``N_p`` depends on theta_i through ``cos(theta_i)``
only, and a dense lobe is mirror-symmetric along the axis,
``N(-theta_i, theta_o) = N(theta_i, -theta_o)``. The sign of theta_i lives in ``M``
(which also carries the cuticle tilt, which breaks that mirror symmetry).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field

import numpy as np

from ..grid import linear
from ..io import atomic_path, check_axis
from ..queries import check_albedo, check_theta, directions, wavelengths
from .longitudinal import Longitudinal
from .reciprocal import half_angle, scale_at

FORMAT = "bcsdf.fiber_table/1"


@dataclass
class Lobe:
    """One term ``M(theta_i, theta_o) N(theta_i, theta_o?, dphi, lambda)``.

    With ``scale`` (``[|theta| node, lambda]``, its own uniform nodes) a separable lobe takes the reciprocal
    form of :mod:`models.fiber.reciprocal`: ``N`` at the half angle ``|theta_i - theta_o| / 2``,
    times ``c(theta_i) c(theta_o) cos(theta_o) / cos(theta_d)``.
    """

    name: str
    longitudinal: Longitudinal
    azimuthal: np.ndarray  # float32 [theta_i, theta_o or 1, phi, lambda]
    scale: np.ndarray | None = None  # float64 [|theta| nodes over [0, pi/2], lambda]: the reciprocal c

    @property
    def dense(self) -> bool:
        return self.azimuthal.shape[1] > 1

    @property
    def reciprocal(self) -> bool:
        return self.scale is not None


@dataclass
class FiberTable:
    """A single-fiber scattering function, tabulated as a sum of lobes.

    Axes: ``theta_i`` (radians, ascending in [0, pi/2]), ``theta_o`` (radians, the
    grid of dense lobes; may be a single 0 when there are none), ``phi`` (``dphi``
    nodes, uniform over [-pi, pi), periodic) and ``wavelength`` (nm). ``meta`` holds
    the model name, its parameters, energy and extinction.
    """

    theta_i: np.ndarray
    theta_o: np.ndarray
    phi: np.ndarray
    wavelength: np.ndarray
    lobes: list[Lobe]
    meta: dict = field(default_factory=dict)
    _energy: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    # -- evaluation --------------------------------------------------------
    def eval(self, *, phi_i, theta_i, phi_o, theta_o, wavelength) -> np.ndarray:
        """``f`` at arbitrary arguments (broadcast), by multilinear interpolation of N.

        Radians and nanometres (:mod:`models.queries`): theta outside [-pi/2, pi/2], a
        wavelength outside the table's range or a value that is not a finite number is a
        ``ValueError`` naming the argument.
        """
        phi_i, theta_i, phi_o, theta_o = directions(phi_i, theta_i, phi_o, theta_o)
        theta_i, phi_i, theta_o, phi_o, wavelength = np.broadcast_arrays(
            theta_i, phi_i, theta_o, phi_o, wavelengths(wavelength, self.wavelength))
        f = self.eval_spectrum(theta_i, theta_o, phi_o - phi_i)  # [..., n_lambda]
        l0, l1, w = linear(self.wavelength, wavelength)
        take = lambda idx: np.take_along_axis(f, idx[..., None], axis=-1)[..., 0]  # noqa: E731
        return (1 - w) * take(l0) + w * take(l1)

    def eval_spectrum(self, theta_i, theta_o, dphi, lambda_index=None) -> np.ndarray:
        """``f`` at every tabulated wavelength: shape ``broadcast(...) + (n_lambda,)``.

        With ``lambda_index`` (an integer array broadcast like the angles) only that
        wavelength is gathered, and the result has no wavelength axis.
        """
        theta_i, theta_o, dphi = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                       for a in (theta_i, theta_o, dphi)))
        check_theta(theta_i, "theta_i")
        check_theta(theta_o, "theta_o")
        mirror = np.where(theta_i < 0, -1.0, 1.0)
        ti = linear(self.theta_i, np.abs(theta_i))
        to = linear(self.theta_o, mirror * theta_o)
        ph = linear(self.phi, dphi, periodic=True)
        if lambda_index is None:
            out, expand, pick = np.zeros(theta_i.shape + (len(self.wavelength),), np.float32), (..., None), ()
        else:
            out, expand, pick = np.zeros(theta_i.shape, np.float32), ..., (np.broadcast_to(lambda_index, theta_i.shape),)
        for lobe in self.lobes:
            N = lobe.azimuthal
            # separable lobes have no theta_o axis: 4 corners, not 8
            o_corners = ((to[0], 1 - to[2]), (to[1], to[2])) if lobe.dense else ((0, 1.0),)
            nodes, factor = ti, 1.0
            if lobe.reciprocal:  # N at the half angle, times the symmetric weight and scale
                abs_d, weight = half_angle(theta_i, theta_o, np)
                nodes = linear(self.theta_i, abs_d)
                cc = scale_at(lobe.scale, np.abs(theta_i)) * scale_at(lobe.scale, np.abs(theta_o))
                cc = cc if lambda_index is None else np.take_along_axis(cc, pick[0][..., None], -1)[..., 0]
                factor = (weight[expand] * cc).astype(np.float32)
            acc = np.zeros_like(out)
            for a, wa in ((nodes[0], 1 - nodes[2]), (nodes[1], nodes[2])):
                for b, wb in o_corners:
                    for c, wc in ((ph[0], 1 - ph[2]), (ph[1], ph[2])):
                        acc += (wa * wb * wc).astype(np.float32)[expand] * N[(a, b, c) + pick]
            out += lobe.longitudinal(theta_i, theta_o).astype(np.float32)[expand] * acc * factor
        return out.astype(np.float64)

    def albedo(self, theta_i) -> np.ndarray:
        """``integral f d omega_o`` at arbitrary theta_i: [..., n_lambda].

        Exact for the interpolated table: ``f`` is linear in theta_i between nodes and
        every ``M`` integrates to one for any theta_i.
        """
        i0, i1, w = linear(self.theta_i, np.abs(np.asarray(theta_i, dtype=np.float64)))
        E = self.energy()
        return (1 - w)[..., None] * E[i0] + w[..., None] * E[i1]  # [..., n_lambda]

    def dyed(self, albedo) -> "FiberTable":
        """This fiber with a dye: every event keeps a fraction ``albedo`` (a number, or one
        per wavelength, in [0, 1]) of its scattering, the rest absorbed. What
        ``BundleTable.recolour`` makes of an order-resolved bake of this fiber."""
        a = check_albedo(albedo, len(self.wavelength)).astype(np.float32)
        lobes = [Lobe(lobe.name, lobe.longitudinal, lobe.azimuthal * a, lobe.scale) for lobe in self.lobes]
        return FiberTable(self.theta_i, self.theta_o, self.phi, self.wavelength, lobes,
                          dict(self.meta, dye=a.astype(np.float64).tolist()))

    # -- energy ------------------------------------------------------------
    def energy(self) -> np.ndarray:
        """Albedo per (theta_i node, wavelength): ``integral f d omega_o``.

        Exact for the tabulated function: ``M`` integrates to one, ``N`` is
        integrated with the periodic trapezoid rule (its own linear interpolant),
        dense lobes also over theta_o with the cosine; a reciprocal lobe's scale was
        solved for this very energy (to 1e-10 at the nodes). Computed once (tables are
        not changed after construction) and returned read-only.
        """
        if self._energy is not None:
            return self._energy
        total = np.zeros((len(self.theta_i), len(self.wavelength)))
        dphi = 2 * np.pi / len(self.phi)
        for lobe in self.lobes:
            per_theta_o = lobe.azimuthal.astype(np.float64).sum(axis=2) * dphi  # [ti, to, wl]
            if lobe.dense:
                w = _trapezoid_cos_weights(self.theta_o)
                total += np.einsum("ioj,o->ij", per_theta_o, w)
            else:
                total += per_theta_o[:, 0, :]
        total.flags.writeable = False
        self._energy = total
        return total

    # -- storage -----------------------------------------------------------
    def save(self, path) -> None:
        """Write an ``.npz`` (atomically: temporary file, then rename)."""
        arrays = {
            "theta_i": self.theta_i, "theta_o": self.theta_o, "phi": self.phi,
            "wavelength": self.wavelength,
        }
        lobes_meta = []
        for k, lobe in enumerate(self.lobes):
            arrays[f"lobe{k}"] = lobe.azimuthal.astype(np.float32)
            if lobe.reciprocal:
                arrays[f"scale{k}"] = lobe.scale
            lobes_meta.append({"name": lobe.name, "longitudinal": lobe.longitudinal.to_dict(),
                               "reciprocal": lobe.reciprocal})
        header = {"format": FORMAT, "lobes": lobes_meta, "meta": self.meta}
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, header=np.array(json.dumps(header)), **arrays)

    @classmethod
    def load(cls, path) -> "FiberTable":
        """Read a table written by :meth:`save`; a foreign or corrupt file is refused."""
        try:
            with np.load(path, allow_pickle=False) as z:
                header = json.loads(str(z["header"]))
                if header.get("format") != FORMAT:
                    raise ValueError(f"format {header.get('format')!r}, expected {FORMAT!r}")
                lobes = [Lobe(m["name"], Longitudinal(**m["longitudinal"]), z[f"lobe{k}"],
                              z[f"scale{k}"] if m.get("reciprocal") else None)
                         for k, m in enumerate(header["lobes"])]
                table = cls(z["theta_i"], z["theta_o"], z["phi"], z["wavelength"], lobes, header["meta"])
            table.validate()
        except (OSError, KeyError, ValueError, json.JSONDecodeError, zipfile.BadZipFile) as e:
            raise ValueError(f"{path}: not a readable fiber table ({e}); re-run `bcsdf fiber`") from e
        return table

    def validate(self) -> None:
        check_axis(self.theta_i, "theta_i", -np.pi / 2, np.pi / 2)
        check_axis(self.theta_o, "theta_o", -np.pi / 2, np.pi / 2)
        check_axis(self.phi, "phi", -2 * np.pi, 2 * np.pi)
        check_axis(self.wavelength, "wavelength", 1.0, 1e5)
        shape = (len(self.theta_i), None, len(self.phi), len(self.wavelength))
        for lobe in self.lobes:
            s = lobe.azimuthal.shape
            if len(s) != 4 or s[0] != shape[0] or s[2:] != shape[2:] or s[1] not in (1, len(self.theta_o)):
                raise ValueError(f"lobe {lobe.name!r} has shape {s}, inconsistent with the axes")
            if not np.all(np.isfinite(lobe.azimuthal)) or np.any(lobe.azimuthal < 0):
                raise ValueError(f"lobe {lobe.name!r} holds negative or non-finite values")
            if lobe.reciprocal:
                c = lobe.scale
                if lobe.dense or c.ndim != 2 or c.shape[0] < 2 or c.shape[1] != shape[3] or \
                        not np.all(np.isfinite(c)) or np.any(c <= 0):
                    raise ValueError(f"lobe {lobe.name!r}: its reciprocal scale must be positive, finite and "
                                     f"[nodes >= 2, {shape[3]} wavelengths] on a separable lobe")


def _trapezoid_cos_weights(theta: np.ndarray) -> np.ndarray:
    """Weights of the trapezoid rule for ``integral g(theta) cos(theta) d theta``."""
    w = np.zeros(len(theta))
    d = np.diff(theta)
    w[:-1] += d / 2
    w[1:] += d / 2
    return w * np.cos(theta)


def sphere_quadrature(n_theta: int = 256, n_phi: int = 512):
    """Nodes and weights for ``integral g(theta, phi) cos(theta) d theta d phi``.

    Gauss-Legendre in ``sin(theta)`` (so the cosine is absorbed exactly) times the
    periodic trapezoid rule in phi.
    """
    u, wu = np.polynomial.legendre.leggauss(n_theta)  # u = sin(theta)
    theta = np.arcsin(u)
    phi = -np.pi + 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    W = np.outer(wu, np.full(n_phi, 2 * np.pi / n_phi))
    return T, P, W


class FiberModel:
    """Base class: a model evaluates ``f`` and tabulates itself.

    Subclasses implement :meth:`tabulate` (the form the baker looks up) and may
    override :meth:`eval` with a direct evaluation; the default evaluates the table.
    """

    name = "fiber"

    def __init__(self, wavelength: np.ndarray):
        self.wavelength = np.asarray(wavelength, dtype=np.float64)

    def tabulate(self, theta_i: np.ndarray) -> FiberTable:  # pragma: no cover - abstract
        raise NotImplementedError

    def eval(self, *, phi_i, theta_i, phi_o, theta_o, wavelength) -> np.ndarray:
        if not hasattr(self, "_table"):
            self._table = self.tabulate(np.deg2rad(np.arange(0, 91, 5.0)))
        return self._table.eval(phi_i=phi_i, theta_i=theta_i, phi_o=phi_o, theta_o=theta_o, wavelength=wavelength)

    def energy(self, theta_i: float, wavelength: float, n_theta=256, n_phi=1024) -> float:
        """``integral f d omega_o`` by quadrature over the sphere of :meth:`eval`."""
        T, P, W = sphere_quadrature(n_theta, n_phi)
        f = self.eval(phi_i=0.0, theta_i=theta_i, phi_o=P, theta_o=T, wavelength=wavelength)
        return float(np.sum(f * W))

    def extinction(self, theta_i: np.ndarray) -> np.ndarray | None:
        """Extinction per geometric cross-section [theta_i, lambda], or None (ray optics: 1)."""
        return None
