"""numpy and Dr.Jit read the grids alike: node interpolation, cells, and the bundle-table
lookup, on random inputs and where a backend's rounding decides (on nodes, on bin edges,
on the specular cone at a theta_i node, at the poles).

Each formula exists once (``models.grid``, ``models.bundle_table.cone_lookup``) with an
array-module parameter; these tests run it on both modules and compare.
"""

import numpy as np
import pytest

from models import grid
from models.bundle_table import lookup
from tests.synthetic import make_config, synthetic_table


@pytest.fixture(scope="module")
def dr_float():
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return mi.Float


def _awkward(rng, nodes, n=4000):
    """Random values, exact nodes, midpoints and values beyond both ends."""
    mid = 0.5 * (nodes[1:] + nodes[:-1])
    span = nodes[-1] - nodes[0]
    return np.concatenate([rng.uniform(nodes[0] - 0.2 * span, nodes[-1] + 0.2 * span, n), nodes, mid,
                           [nodes[0] - 1.0, nodes[-1] + 1.0]])


GRADED = [0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 75.0, 80.0, 85.0, 90.0]  # theta_i nodes finer near grazing
HELD = [0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 75.0, 80.0, 85.0, 87.5]  # ... and without a pole node


@pytest.mark.parametrize("periodic,graded", [(False, False), (True, False), (False, True)])
def test_node_interpolation_agrees(dr_float, periodic, graded):
    import drjit as dr

    rng = np.random.default_rng(3)
    nodes = (np.linspace(-np.pi, np.pi, 72, endpoint=False) if periodic
             else np.deg2rad(np.concatenate([-np.array(GRADED[:0:-1]), GRADED])) if graded
             else np.deg2rad(np.arange(0, 91, 5.0)))
    values = rng.uniform(0.5, 2.0, len(nodes))
    x = _awkward(rng, nodes) + (rng.uniform(-10, 10, 1) if periodic else 0)
    i0, i1, w = grid.linear(nodes, x, periodic=periodic)
    want = (1 - w) * values[i0] + w * values[i1]
    j0, j1, v = grid.linear(nodes, dr_float(x), periodic=periodic, xp=dr)
    got = (1 - v.numpy()) * values[j0.numpy()] + v.numpy() * values[j1.numpy()]
    # float32 input: the value moves by at most the slope times the input's rounding
    slope = np.max(np.abs(np.diff(values))) / (np.min(np.diff(nodes)) if not periodic else 2 * np.pi / 72)
    assert np.allclose(got, want, rtol=0, atol=slope * 1e-5 * (1 + np.abs(x)).max())
    assert np.all((v.numpy() >= 0) & (v.numpy() <= 1))
    if not periodic:  # interpolating the nodes themselves gives x back, clamped to the ends
        assert np.allclose((1 - v.numpy()) * nodes[j0.numpy()] + v.numpy() * nodes[j1.numpy()],
                           np.clip(x, nodes[0], nodes[-1]), rtol=0, atol=1e-5 * (1 + np.abs(x)).max())


@pytest.mark.parametrize("periodic", [False, True])
def test_cells_agree_on_edges(dr_float, periodic):
    """With the lookup's tie, a point on an edge is in the cell above it, on both backends,
    whatever float32 rounding did to it."""
    import drjit as dr

    n, lo, span = (72, -np.pi, 2 * np.pi) if periodic else (36, -np.pi / 2, np.pi)
    edges = lo + span * np.arange(n + 1) / n
    rng = np.random.default_rng(4)
    x = np.concatenate([edges, rng.uniform(lo, lo + span, 5000)])
    k_np, _ = grid.cell(x, lo, span, n, periodic=periodic, tie=grid.TIE)
    k_dr, _ = grid.cell(dr_float(x), lo, span, n, periodic=periodic, tie=grid.TIE, xp=dr)
    assert np.array_equal(k_np, k_dr.numpy())
    # an edge is its upper cell's (the last edge: the last cell, or the first when periodic)
    upper = np.minimum(np.arange(n + 1), n - 1) if not periodic else np.arange(n + 1) % n
    assert np.array_equal(k_np[: n + 1], upper)


def test_cone_edges_centre_a_narrow_bin_on_every_cone():
    """The cone layout: symmetric, spanning the sphere, a bin of the asked width centred on
    every multiple of the node step but the poles, ``m`` equal bins between, and as many
    bins as :func:`grid.cone_bin_counts` says."""
    for step_deg, bin_deg, m in [(10.0, 2.0, 1), (15.0, 3.0, 1), (30.0, 6.0, 2), (5.0, 1.0, 3)]:
        step, width = np.deg2rad(step_deg), np.deg2rad(bin_deg)
        e = grid.cone_edges(step, width, m)
        P = round(180 / step_deg)
        assert len(e) - 1 == P * (m + 1) - 1 == grid.cone_bin_counts(step)[m - 1]
        assert e[0] == -np.pi / 2 and e[-1] == np.pi / 2 and np.all(np.diff(e) > 0)
        assert np.allclose(e, -e[::-1], atol=1e-12)
        cells = grid.Cells(e)
        for cone in np.deg2rad(np.arange(-90 + step_deg, 90, step_deg)):
            k = int(cells.index(np.array(cone)))
            assert np.isclose(e[k + 1] - e[k], width) and np.isclose(0.5 * (e[k] + e[k + 1]), cone)
        gaps = np.diff(e)[1:-1]
        assert np.allclose(np.sort(gaps)[-(P - 2) * m:], (step - width) / m)  # the bins between cones
    for bad in [(np.deg2rad(7.0), np.deg2rad(2.0), 1), (np.deg2rad(10.0), np.deg2rad(10.0), 1),
                (np.deg2rad(10.0), np.deg2rad(2.0), 0), (np.deg2rad(GRADED), np.deg2rad(5.0), 1)]:
        with pytest.raises(ValueError):
            grid.cone_edges(*bad)


@pytest.mark.parametrize("m", [1, 2])
def test_cone_edges_of_graded_nodes(m):
    """Graded theta_i nodes (finer near grazing): a cone bin centred on the cone of every
    node and its mirror, ``m`` equal bins in every gap between two cones, however wide; the
    nodes at a step give the same edges as the step itself."""
    nodes, width = np.deg2rad(GRADED), np.deg2rad(2.0)
    e = grid.cone_edges(nodes, width, m)
    cones = np.deg2rad(sorted({-t for t in GRADED} | set(GRADED)))
    assert len(e) - 1 == (len(cones) - 1) * (m + 1) - 1 == grid.cone_bin_counts(nodes)[m - 1]
    assert e[0] == -np.pi / 2 and e[-1] == np.pi / 2 and np.all(np.diff(e) > 0)
    assert np.allclose(e, -e[::-1], atol=1e-12)
    cells = grid.Cells(e)
    for cone in cones[1:-1]:
        k = int(cells.index(np.array(cone)))
        assert np.isclose(e[k + 1] - e[k], width) and np.isclose(0.5 * (e[k] + e[k + 1]), cone)
    for lo, hi in zip(cones[1:-2], cones[2:-1]):  # the gap between two inner cones: m equal bins
        inside = e[(e > lo + 1e-9) & (e < hi - 1e-9)]
        assert len(inside) == m + 1 and np.allclose(np.diff(inside), (hi - lo - width) / m)
    assert np.allclose(grid.cone_edges(np.deg2rad(np.arange(0, 91, 10.0)), width, m),
                       grid.cone_edges(np.deg2rad(10.0), width, m), atol=1e-12)


@pytest.mark.parametrize("edges", ["cone", "random"])
def test_cells_of_unequal_edges_on_both_backends(dr_float, edges):
    """``Cells`` of unequal edges finds what a search finds (numpy: exactly; Dr.Jit: of the
    float32 edges), on random points, on every edge (the cell above) and beyond the ends
    (clamped); the lookup's tie puts a point a hair below an edge in the cell above."""
    import drjit as dr

    rng = np.random.default_rng(8)
    e = (grid.cone_edges(np.deg2rad(10.0), np.deg2rad(2.0)) if edges == "cone"
         else np.sort(np.concatenate([[-np.pi / 2, np.pi / 2], rng.uniform(-np.pi / 2, np.pi / 2, 40)])))
    cells = grid.Cells(e)
    assert not cells.uniform
    x = np.concatenate([rng.uniform(-2.0, 2.0, 20000), e, e - 1e-12, [-np.pi, np.pi]])
    searched = np.clip(np.searchsorted(e, x, side="right") - 1, 0, len(e) - 2)
    assert np.array_equal(cells.index(x), searched)
    x32 = x.astype(np.float32)
    searched32 = np.clip(np.searchsorted(e.astype(np.float32), x32, side="right") - 1, 0, len(e) - 2)
    assert np.array_equal(cells.index(dr_float(x32), xp=dr).numpy(), searched32)
    below = e[1:-1] - 1e-6 * cells.min_width
    assert np.array_equal(cells.index(below, tie=grid.TIE), np.arange(1, len(e) - 1))
    assert np.array_equal(cells.index(dr_float(below), tie=grid.TIE, xp=dr).numpy(), np.arange(1, len(e) - 1))


@pytest.mark.parametrize("relative,cone,nodes", [(True, False, None), (False, False, None), (True, True, None),
                                                 (False, True, GRADED), (True, True, HELD)])
def test_table_lookups_agree_on_the_cone_edges_and_poles(dr_float, tmp_path, relative, cone, nodes):
    """numpy's ``lookup`` and the plugin's ``DrJitTable`` are one algorithm (``cone_lookup``):
    they agree to float32 rounding on random directions and on every direction where a
    backend's trigonometry decides the bin (the cone at a theta_i node lies on a theta_o
    edge; dphi = 0 and pi lie on phi_o edges; the poles), with theta_i nodes 15 deg apart,
    graded, or stopping short of the pole (the last node held beyond it)."""

    from mitsuba_ext.table import DrJitTable
    from models.bundle_table import BundleTable

    cfg = make_config(tmp_path)
    synthetic_table(cfg, tmp_path / "t.npz", relative=relative, cone=2.0 if cone else None, theta_i_deg=nodes)
    table = BundleTable.load(tmp_path / "t.npz", expand=True)
    rng = np.random.default_rng(5)
    n = 3000
    random = [rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n),
              rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n)]
    nodes = np.concatenate([table.theta_i, [np.pi / 2, -np.pi / 2]])
    phi_i = np.repeat(rng.uniform(-np.pi, np.pi, len(nodes)) if not relative else np.zeros(len(nodes)), 4)
    theta_i = np.repeat(nodes, 4)
    dphi = np.tile([0.0, np.pi, -np.pi, 0.5 * np.pi], len(nodes))
    special = [phi_i, theta_i, phi_i + dphi, -theta_i]             # on the cone, on phi_o edges
    poles = [np.zeros(8), np.full(8, 0.3), np.linspace(-3, 3, 8), np.array([np.pi / 2, -np.pi / 2] * 4)]
    q = [np.concatenate(a) for a in zip(random, special, poles)]
    q32 = [a.astype(np.float32).astype(np.float64) for a in q]     # both read the same float32 directions
    dj = DrJitTable(table, dr_float)
    for mode in ("linear", "nearest"):
        want = lookup(table, *q32, mode=mode)
        got = np.stack([o.numpy() for o in dj.eval(*(dr_float(a) for a in q32), mode=mode)], -1)
        assert np.all(np.isfinite(got))
        scale = table.values.max()
        bad = ~np.isclose(got, want, rtol=1e-4, atol=1e-5 * scale)
        assert not bad.any(), (mode, np.argwhere(bad)[:5], got[bad][:5], want[bad][:5])


def test_importance_sampler_conditions_on_the_nearest_graded_node(dr_float):
    """The plugin's sampler draws from the distribution of the ``theta_i`` node nearest the
    light, graded nodes too: its condition index against a search for the nearest node."""
    from mitsuba_ext.sampling import DirectionGrid

    nodes = np.deg2rad(np.concatenate([-np.array(GRADED[:0:-1]), GRADED]))
    phi_i = np.deg2rad([0.0, 90.0, 180.0, 270.0])
    pe, te = np.linspace(-np.pi, np.pi, 9), np.linspace(-np.pi / 2, np.pi / 2, 5)
    sampler = DirectionGrid(np.ones((len(phi_i), len(nodes), 8, 4)), phi_i, nodes, pe, te, False, dr_float)
    rng = np.random.default_rng(4)
    theta = np.concatenate([rng.uniform(-np.pi / 2, np.pi / 2, 4000), nodes, [-2.0, 2.0]])
    phi = rng.uniform(-3 * np.pi, 3 * np.pi, len(theta))
    cond = sampler._condition(dr_float(phi), dr_float(theta)).numpy()
    b = np.argmin(np.abs(theta[:, None] - nodes[None, :]), 1)
    a = np.round(np.mod(phi, 2 * np.pi) / (np.pi / 2)).astype(int) % 4
    near_tie = np.min(np.abs(np.abs(theta[:, None] - nodes) - np.abs(theta[:, None] - nodes[b][:, None])) +
                      np.where(np.arange(len(nodes)) == b[:, None], 9.0, 0.0), 1) < 1e-5
    ok = (cond == a * len(nodes) + b) | near_tie
    assert ok.all(), (theta[~ok][:5], cond[~ok][:5], (a * len(nodes) + b)[~ok][:5])


def test_bin_slopes_are_a_ramps_own_slopes_and_flat_at_an_extremum(tmp_path):
    """The lookup's limited slopes (``bin_slopes``), against a closed form: S linear in
    ``phi_o`` and in ``u = sin(theta_o)`` over the bins' centres, with slopes that differ by
    ``theta_i`` node and by channel, has those slopes in every bin with neighbours on both
    sides; a bin holding a maximum along ``phi_o`` is flat there (minmod)."""
    from models.bundle_table import BundleTable, bin_slopes

    synthetic_table(make_config(tmp_path), tmp_path / "t.npz")
    table = BundleTable.load(tmp_path / "t.npz", expand=True)
    n_a, n_b, n_p, n_t, n_l = table.values.shape
    phi = 0.5 * (table.phi_o_edges[1:] + table.phi_o_edges[:-1])
    u_edges = np.sin(table.theta_o_edges)
    u = 0.5 * (u_edges[1:] + u_edges[:-1])
    a = 0.01 * (1 + np.arange(n_b))[None, :, None, None, None] * (1 + np.arange(n_l))   # per radian of phi_o
    b = 0.02 * (2 + np.arange(n_b))[None, :, None, None, None] * (3 - np.arange(n_l) / n_l)  # per unit of u
    ramp = 1.0 + a * phi[:, None, None] + b * u[:, None]
    s_phi, s_u = bin_slopes(table._replace(values=ramp.astype(np.float32)))
    eps = 8 * np.finfo(np.float32).eps   # the float32 values' rounding over differences of neighbours
    scale = np.abs(ramp).max() / np.diff(phi).min()
    assert np.allclose(s_phi[:, :, 1:-1], np.broadcast_to(a, s_phi.shape)[:, :, 1:-1], rtol=0, atol=eps * scale)
    scale = np.abs(ramp).max() / np.diff(u).min()
    assert np.allclose(s_u[:, :, :, 1:-1], np.broadcast_to(b, s_u.shape)[:, :, :, 1:-1], rtol=0, atol=eps * scale)
    assert np.all(s_u[:, :, :, [0, -1]] == 0)                  # the first and last theta_o bins are flat
    peak = np.exp(-((phi - phi[n_p // 2]) / 0.5) ** 2)[:, None, None] * np.ones(table.values.shape)
    s_phi, _ = bin_slopes(table._replace(values=peak.astype(np.float32)))
    assert np.all(s_phi[:, :, n_p // 2] == 0) and np.all(s_phi[:, :, n_p // 2 - 1] > 0)
    peak = np.exp(-((u - u[n_t // 2]) / 0.3) ** 2)[:, None] * np.ones(table.values.shape)
    _, s_u = bin_slopes(table._replace(values=peak.astype(np.float32)))
    assert np.all(s_u[:, :, :, n_t // 2] == 0) and np.all(s_u[:, :, :, n_t // 2 - 1] > 0)
