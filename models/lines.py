"""Feature lines: learned 1D feature curves along the ridge's own coordinates.

A bundle table is a narrow ridge along the specular cone ``theta_o = -theta_i`` (a few
degrees wide) over a smooth floor of multiple scattering. A ReLU network given the angles
(or their sines) carves that ridge out of many kinks; it is most of what the plain MLP's
parameters and training time go to. Feature lines hand the network the ridge instead:
three learned curves of ``C`` channels each, one per coordinate of the ridge,

* ``t``: the incident longitude ``theta_i / (pi / 2)`` (uniform in angle: most of the
  light is scattered at grazing incidence, where ``sin theta_i`` crowds its nodes);
* ``x``: the distance from the cone, ``theta_o + theta_i``, on a knee scale
  ``|x| / (|x| + knee)`` whose nodes are dense near the cone (spacing about
  ``knee / n`` there) and sparse in the floor;
* ``d``: the azimuth difference ``phi_o - phi_i`` (periodic),

each sampled by linear interpolation between its nodes; the network's extra inputs are
the products ``A_c(t) B_c(x) D_c(d)``, ``c = 1..C`` (a rank-``C`` factorization of a
3D grid, as TensoRF's vector-matrix split keeps only its vectors). The symmetry folds
of the features (models/neural.py) fold the coordinates too: ``theta`` takes ``|t|`` and
``|x|``, ``dphi`` or ``xz`` takes ``|d|``; so a line holds each distinct value once.

**Held-out bins and interpolation.** Every node of a line is shared by every bin of the
table at that coordinate (thousands), so no node is fitted by one bin alone, and a
held-out bin's value is the lines interpolated linearly between nodes that other bins
fixed. A node that no bin's points reach (beyond the table's theta_i range, say) keeps
its initial value, 1: the product is then that of the other two lines.

Evaluation is a gather and a lerp per line and channel in every backend (PyTorch and the
ONNX graph exported from it: ``Gather``; Dr.Jit: ``dr.gather`` from the flat node array
traced into the caller's kernel; the rounding bound: :func:`bounded_sample`).
"""

from __future__ import annotations

import numpy as np

from . import rounding as rd

KNEE = 0.25  # radians: half the x-line's nodes lie within about 0.25 rad (14 deg) of the cone


def coordinates(lib, folds, ti, x, d) -> list:
    """The three line coordinates in [0, 1] from ``ti = theta_i`` (clamped), ``x = theta_o
    + theta_i`` and ``d = phi_o - phi_i`` (any value); ``lib`` is numpy, torch, drjit or
    :data:`models.rounding.BOUNDED`. The azimuth coordinate is periodic unless folded."""
    two_pi = float(2 * np.pi)
    knee = KNEE
    norm = float(np.pi / (np.pi + knee))  # |x| = pi maps to 1
    s = ti * float(2 / np.pi)  # the angle, not its sine: the energy is at grazing incidence, where sines crowd
    w = d - two_pi * lib.floor((d + float(np.pi)) * float(1 / (2 * np.pi)))  # d wrapped to [-pi, pi)
    r = lib.abs(x)
    if "theta" in folds:
        t_c, x_c = lib.abs(s), r * (1.0 / norm) / (r + knee)
    else:
        t_c, x_c = 0.5 * s + 0.5, (x * (0.5 / norm)) / (r + knee) + 0.5
    if any(f in folds for f in ("dphi", "xz")):  # both map d to -d
        d_c = lib.abs(w) * float(1 / np.pi)
    else:
        d_c = w * float(1 / two_pi) + 0.5
    return [t_c, x_c, d_c]


def periodic(folds) -> tuple:
    """Which of the three lines wrap around (the azimuth, unless a fold made it |d|)."""
    return (False, False, not any(f in folds for f in ("dphi", "xz")))


def node_position(lib, coord, n: int, wraps: bool):
    """``(i0, t)``: the node left of ``coord`` (a float holding an integer) and the weight
    of the node right of it. ``n`` nodes span [0, 1]; a periodic line's node ``n`` is its
    node 0 again (stored twice, so that ``i0 + 1`` needs no wrap)."""
    clip = getattr(lib, "clip", None) or getattr(lib, "clamp")
    p = clip(coord, 0.0, 1.0) * float(n if wraps else n - 1)
    i0 = clip(lib.floor(p), 0.0, float(n - 1 if wraps else n - 2))
    return i0, p - i0


def stored(line: np.ndarray, wraps: bool) -> np.ndarray:
    """The nodes ``[n, C]`` as gathered: a periodic line with its node 0 again at the end."""
    return np.concatenate([line, line[:1]]) if wraps else line


def bounded_sample(line: np.ndarray, coord: rd.Bounded, wraps: bool) -> list:
    """One line at ``coord`` in bounded arithmetic: a list of ``C`` channels.

    The nodes are float32 constants (exact); the lerp ``a + t (b - a)`` rounds three
    times; the coordinate's error moves the sample along the line, by at most the
    steepest of the segments it may reach (the one it lies in and its two neighbours)."""
    n = len(line)
    nodes = stored(np.asarray(line, np.float64), wraps)
    scale = float(n if wraps else n - 1)
    i0, t = node_position(np, coord.value, n, wraps)  # the backends' index arithmetic, in float64
    p, i0 = i0 + t, i0.astype(np.int64)
    a, b = nodes[i0], nodes[i0 + 1]  # [m, C]
    slopes = np.abs(np.diff(nodes, axis=0))  # per segment
    near = np.maximum(slopes[i0], np.maximum(slopes[np.maximum(i0 - 1, 0)], slopes[np.minimum(i0 + 1, len(slopes) - 1)]))
    p_err = coord.err * scale + rd.gamma(2, coord.u) * np.abs(p)  # scaled and clipped: two roundings
    value = a + t[:, None] * (b - a)
    err = near * p_err[:, None] + rd.gamma(3, coord.u) * (np.abs(a) + np.abs(t[:, None] * (b - a)))
    return [rd.Bounded(value[:, c], err[:, c], coord.u) for c in range(value.shape[1])]


def torch_lines(nodes, channels: int, wraps, seed_generator=None):
    """The PyTorch module of the lines: ``[n, F + 3]`` (features, then the three line
    coordinates) -> ``[n, F + C]`` (features, then the products). Its parameters
    ``lines.k`` are the nodes ``[n_k, C]``, initially 1 with a little noise (the product
    starts near 1, and the channels differ so that they learn different things)."""
    import torch

    class Lines(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.lines = torch.nn.ParameterList(
                [torch.nn.Parameter(1.0 + 0.1 * torch.randn((n, channels), generator=seed_generator)) for n in nodes])
            self.wraps, self.nodes = tuple(wraps), tuple(int(n) for n in nodes)  # Python ints: constants in a trace

        def forward(self, z):
            feats, coords = z[:, :-3], z[:, -3:]
            product = None
            for k, (line, n, wrap) in enumerate(zip(self.lines, self.nodes, self.wraps)):
                i0, t = node_position(torch, coords[:, k], n, wrap)
                nodes = torch.cat([line, line[:1]]) if wrap else line
                i = i0.long()
                a, b = nodes[i], nodes[i + 1]
                v = a + t[:, None] * (b - a)
                product = v if product is None else product * v
            return torch.cat([feats, product], -1)

    return Lines()
