"""Twisted plies: the helical arrangement and the 3D bake, against independent references.

- geometry: a positive pitch makes right-handed helices (positive torsion, computed by
  finite differences), fibers lean ``atan(2 pi rho / |pitch|)``, and the closest approach
  of two fibers is the one dense 3D sampling of both helices finds;
- an arrangement whose leaning fibers intersect is refused with the amount;
- ``pitch -> infinity`` reproduces the parallel (2D) bake within Monte Carlo error;
- a single tilted fiber reproduces the fiber model rotated into the ply frame, averaged
  over the fiber's turn (hit fraction ``r cos theta' / (R_b cos lean cos theta_i)``);
- a lossless twisted ply loses nothing: scattered + passthrough = 1 for every theta_i;
- the reduction the twisted bake uses, rotation invariance of a circular ply (a turn of
  the ply is a shift along its axis), holds: absolute tables at two incident azimuths
  agree once shifted.
"""

import dataclasses
import re

import numpy as np
import pytest

from models.bake import Baker, BakeSpec
from models.bake.twisted import TwistedBaker
from models.bundle import Bundle, Migration, TwistedBundle, poisson
from models.fiber.patterns import PatternFiber
from models.bake import tally_to_table

WL = np.array([450.0, 650.0])
NODES = np.deg2rad(np.arange(0, 91, 5.0))
RELATIVE = {"theta_i": None, "phi_i": None, "phi_o": "relative"}


@pytest.fixture(scope="module", autouse=True)
def _variant(mi_llvm):
    return mi_llvm


def table_of(tally, spec, fiber, reductions=RELATIVE):
    return tally_to_table(tally, spec, fiber, reductions)


def agree(got, ref, err, rel=0.02, floor=2e-3):
    """|got - ref| within ``rel`` of ref plus 3.5 standard errors, plus 0.2% of the peak (a bin
    no path reached has no error estimate)."""
    tol = rel * np.abs(ref) + 3.5 * err + floor * np.abs(ref).max()
    return np.abs(got - ref) <= tol


# -- geometry ------------------------------------------------------------------------

def test_positive_pitch_is_a_right_handed_helix_leaning_as_expected():
    ply = TwistedBundle(Bundle(np.array([[60.0, 0.0]]), 10.0, (80.0, 80.0)), 900.0)
    y = np.linspace(0, 300, 3001)
    c = ply.centers_at(y)[:, 0]
    p = np.stack([c[:, 0], y, c[:, 1]], -1)
    d1, d2 = np.gradient(p, y, axis=0), np.gradient(np.gradient(p, y, axis=0), y, axis=0)
    d3 = np.gradient(d2, y, axis=0)
    torsion = np.einsum("ij,ij->i", np.cross(d1, d2), d3)[10:-10]
    assert np.all(torsion > 0)                                     # right-handed
    assert np.all(TwistedBundle(ply.bundle, -900.0).centers_at(y)[:, 0, 1] * c[:, 1] <= 1e-9)  # mirror
    lean = np.arccos(d1[10:-10, 1] / np.linalg.norm(d1[10:-10], axis=1))
    assert np.allclose(lean, np.arctan(2 * np.pi * 60.0 / 900.0), atol=1e-5)
    assert np.isclose(ply.max_lean, np.arctan(2 * np.pi * 60.0 / 900.0))
    assert np.allclose(ply.centers_at(y + 900.0), ply.centers_at(y), atol=1e-9)  # the period


def test_closest_approach_is_the_sampled_minimum():
    b = Bundle(np.array([[50.0, 0.0], [50.0 * np.cos(1.0), 50.0 * np.sin(1.0)]]), 20.0, (75.0, 75.0))
    ply = TwistedBundle(b, 600.0)
    gap, i, j = ply.closest_approach()
    # brute force: every pair of points 0.2 um apart along the two centre lines, a period and more
    y0, y1 = np.linspace(0, 600, 3001), np.linspace(-100, 700, 4001)
    c0, c1 = ply.centers_at(y0)[:, 0], ply.centers_at(y1)[:, 1]
    p0, p1 = np.stack([c0[:, 0], y0, c0[:, 1]], -1), np.stack([c1[:, 0], y1, c1[:, 1]], -1)
    d = np.sqrt(((p0[:, None, :] - p1[None, :, :]) ** 2).sum(-1))
    assert {i, j} == {0, 1}
    assert abs(gap - (d.min() - 40.0)) < 0.01


def test_leaning_fibers_that_intersect_are_refused_with_the_amount():
    b = poisson((200.0, 200.0), 20.0, seed=1)
    TwistedBundle(b, 5000.0)  # leans 13 deg: these fibers still clear each other
    with pytest.raises(ValueError, match=r"intersect by \d+(\.\d+)? um") as e:
        TwistedBundle(b, 2000.0)
    assert "bundle.gap_um" in str(e.value)
    with pytest.raises(ValueError, match="pitch must be a finite, non-zero"):
        TwistedBundle(b, 0.0)
    # an ellipse's fibers turn through it and pass closer than in its cross-section
    with pytest.raises(ValueError, match=r"intersect by \d+(\.\d+)? um where they lean past each other through the "
                                         r"ellipse \(200 x 120 um"):
        TwistedBundle(poisson((200.0, 120.0), 20.0, gap=3.0, seed=1), 20000.0)


def test_migrating_fibers_follow_zhao_and_repeat_after_whole_cycles():
    """Migration (Zhao et al. 2016): ``R(theta) = R_min rho + (1 - R_min) rho / 2 (cos(s theta
    + theta_0) + 1)`` with ``theta = 2 pi y / pitch``, written out here; the ply repeats
    after the fewest whole turns in which ``s`` makes whole cycles (s = 1.5: 2 turns; Cotton
    1's s = 1.1: 10), not after one; the lean from finite differences of the centre line."""
    rho0, phi0, pitch = 60.0, 0.4, -900.0
    m = Migration(0.8, 1.5, seed=5)
    ply = TwistedBundle(Bundle(np.array([[rho0 * np.cos(phi0), rho0 * np.sin(phi0)]]), 10.0, (80.0, 80.0)), pitch, m)
    theta0 = m.phases(1)[0]
    y = np.linspace(-2000.0, 2000.0, 40001)
    theta = 2 * np.pi * y / pitch
    R = 0.8 * rho0 + 0.2 * rho0 / 2 * (np.cos(1.5 * theta + theta0) + 1)
    c = ply.centers_at(y)[:, 0]
    assert np.allclose(np.hypot(*c.T), R, atol=1e-9)
    assert np.allclose(np.arctan2(c[:, 1], c[:, 0]), np.angle(np.exp(1j * (phi0 - theta))), atol=1e-9)  # the turn
    assert ply.period == 2 * 900.0 and Migration(0.8, 1.1).turns == 10 and Migration(0.9, 2.0).turns == 1
    assert np.allclose(ply.centers_at(y + 1800.0), c[:, None], atol=1e-9)
    assert not np.allclose(ply.centers_at(y + 900.0), c[:, None], atol=1.0)  # one turn is not a period
    p = np.stack([c[:, 0], y, c[:, 1]], -1)
    d1 = np.gradient(p, y, axis=0)[10:-10]
    lean = np.arccos(d1[:, 1] / np.linalg.norm(d1, axis=1))
    assert abs(lean.max() - ply.max_lean) < 1e-4
    assert lean.max() > np.arctan(2 * np.pi * 0.8 * rho0 / 900.0)  # the radial drift leans it past its innermost turn


def test_closest_approach_of_migrating_fibers_is_the_sampled_minimum():
    b = Bundle(np.array([[50.0, 0.0], [42.0 * np.cos(0.9), 42.0 * np.sin(0.9)]]), 15.0, (75.0, 75.0))
    ply = TwistedBundle(b, 700.0, Migration(0.85, 0.5, seed=1), checked=False)
    gap, i, j = ply.closest_approach()
    # brute force: every pair of points 0.2 um apart along the two centre lines, over a period (2 turns)
    y0, y1 = np.linspace(0, 1400, 7001), np.linspace(-150, 1550, 8501)
    c0, c1 = ply.centers_at(y0)[:, 0], ply.centers_at(y1)[:, 1]
    p0, p1 = np.stack([c0[:, 0], y0, c0[:, 1]], -1), np.stack([c1[:, 0], y1, c1[:, 1]], -1)
    d = min(np.sqrt(((p0[k:k + 500, None, :] - p1[None, :, :]) ** 2).sum(-1)).min() for k in range(0, len(y0), 500))
    assert {i, j} == {0, 1}
    assert abs(gap - (d - 30.0)) < 0.01
    rigid = TwistedBundle(b, 700.0).closest_approach()[0]
    assert gap < rigid - 1.0  # migration brings them closer than the rigid twist does


def test_an_elliptical_plys_fibers_turn_through_the_fixed_ellipse():
    """Zhao et al.'s elliptical ply: a fiber's place in the unit disk, ``(x / a, z / b)``, turns
    about the axis and is scaled back to the ellipse (written out here); so two fibers that
    lie side by side along the major axis pass each other closer when they have turned onto
    the minor axis (the closest approach against dense sampling over a turn)."""
    a, b, pitch = 100.0, 60.0, 2400.0
    bundle = Bundle(np.array([[20.0, 0.0], [60.0, 0.0]]), 10.0, (a, b))
    ply = TwistedBundle(bundle, pitch, checked=False)
    y = np.linspace(0.0, 2 * pitch, 4001)
    c = ply.centers_at(y)
    psi = -2 * np.pi * y / pitch
    assert np.allclose(c[:, 1], np.stack([60.0 * np.cos(psi), b * 0.6 * np.sin(psi)], -1), atol=1e-9)
    assert np.allclose(ply.centers_at(y + pitch), c, atol=1e-9) and ply.period == pitch and not ply.screw
    assert ply.max_lean == pytest.approx(np.arctan(2 * np.pi * 60.0 / pitch), rel=1e-4)  # leanest at the minor axis
    gap, i, j = ply.closest_approach()
    # brute force: fiber 0 every 2 um over a turn, fiber 1 every 0.2 um within 60 um of each height
    y0, dy = np.linspace(0, pitch, 1201)[:, None], np.linspace(-60.0, 60.0, 601)[None, :]
    d = np.sqrt(((ply.centers_at(y0, 0) - ply.centers_at(y0 + dy, 1)) ** 2).sum(-1) + dy**2).min()
    assert {i, j} == {0, 1} and abs(gap - (d - 20.0)) < 0.01
    assert gap == pytest.approx(40.0 * b / a - 20.0, abs=0.05)  # side by side on the minor axis: 24 um apart


def test_migration_that_collides_is_refused_with_the_amount():
    b = poisson((200.0, 200.0), 20.0, gap=3.0, seed=1)
    TwistedBundle(b, 5000.0)  # the rigid twist clears
    with pytest.raises(ValueError, match=r"intersect by \d+(\.\d+)? um where they lean and migrate") as e:
        TwistedBundle(b, 5000.0, Migration(0.8, 1.1))
    assert "r_min 0.8 nearer 1" in str(e.value)
    with pytest.raises(ValueError, match="more than 20 turns"):
        Migration(0.8, 1.13)
    with pytest.raises(ValueError, match=r"r_min 0 must lie in \(0, 1\]"):
        Migration(0.0, 1.0)


# -- the 3D bake ---------------------------------------------------------------------

@pytest.mark.parametrize("exit_model", ["uniform", "lobe"])
def test_untwisted_limit_is_the_parallel_bake(ray_fiber, exit_model):
    """Nearly straight helices (pitch 1e8 um) against the 2D bake of the same cross-section,
    with the uniform exit and with the lobe exit (each path sampled at its own offset ``h``
    and leaving where its lobe leaves: the 3D tracer's ``h`` and exit point must be the 2D
    bake's for the many-fiber paths to agree)."""
    b = poisson((100.0, 100.0), 20.0, seed=1)
    spec = BakeSpec(np.deg2rad([0.0, 30.0, 60.0]), [0.0], 12, 24, relative_phi=True, exit=exit_model)
    flat = table_of(Baker(b, ray_fiber, spec).trace(0, 200_000, 1), spec, ray_fiber)
    tw = TwistedBaker(TwistedBundle(b, 1e8), ray_fiber, spec).trace(0, 300_000, 2)
    twisted = table_of(tw, spec, ray_fiber)
    err = np.sqrt(flat.stderr**2 + twisted.stderr**2)
    ok = agree(twisted.values, flat.values, err)
    assert ok.mean() > 0.995 and np.abs(twisted.values - flat.values).max() < 0.1 * flat.values.max()
    p_theta = tw.passthrough_theta[0] / tw.paths_theta[0]
    assert np.allclose(p_theta, flat.passthrough[0], atol=4 * np.sqrt(flat.passthrough[0] / 1e5))
    assert np.allclose(twisted.scattered, flat.scattered, rtol=0.01)
    assert np.allclose(twisted.absorbed, flat.absorbed, rtol=0.02, atol=1e-4)


@pytest.mark.parametrize("layout,exit_model", [("uniform", "uniform"), ("cone", "uniform"), ("uniform", "lobe")])
def test_single_tilted_fiber_is_the_fiber_model_rotated(ray_fiber, layout, exit_model):
    """The 3D bake of one helical fiber against the fiber model rotated into the ply frame
    and averaged over its turn, bin by bin: in 12 equal theta_o bins, and in the cone
    layout's unequal ones (a 4-deg bin on the cones of nodes 10 deg apart, 6 deg between;
    five times the paths, so that no bin of 0.2% of the peak is left empty). With the lobe
    exit the fiber is sampled resolved in the ray's offset ``h``, which averages to the
    model only if ``h`` is the hit's true offset (uniform over the fiber's projected width)."""
    from models.grid import cone_edges

    rho, r, Rb, pitch = 60.0, 20.0, 80.0, 1500.0
    ply = TwistedBundle(Bundle(np.array([[rho, 0.0]]), r, (Rb, Rb)), pitch)
    spec = BakeSpec(np.deg2rad([0.0, 30.0, 50.0]), [0.0], 12, 24, relative_phi=True, exit=exit_model,
                    theta_o_edges=cone_edges(np.deg2rad(10.0), np.deg2rad(4.0)) if layout == "cone" else None)
    paths = 400_000 if layout == "uniform" else 2_000_000  # narrower bins: no empty bin of 0.2% of the peak
    table = table_of(TwistedBaker(ply, ray_fiber, spec).trace(0, paths, 2), spec, ray_fiber)

    check_rotated_fiber(table, ply, ray_fiber, spec, 650.0)


def rotated_fiber(ply, fiber, table, theta_i, wavelength):
    """One helical fiber's bundle table, bin by bin: the fiber model rotated into the ply frame
    along its turn (48 azimuths), weighed by the width it shows the light, averaged over 6 x 6
    points a bin: [phi_o, theta_o] at ``theta_i`` (phi_i = 0)."""
    r, Rb = float(ply.bundle.radii[0]), ply.bundle.bounding_radius
    rho = float(np.hypot(*ply.bundle.centers[0]))
    psi = (np.arange(48) + 0.5) / 48 * 2 * np.pi
    T = np.stack([-rho * ply.omega * np.sin(psi), np.ones_like(psi), rho * ply.omega * np.cos(psi)], -1)
    T /= np.linalg.norm(T, axis=-1, keepdims=True)
    e1 = np.cross(T, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(e1, T)

    def local(w, k):
        return (np.arctan2(np.sum(w * e2[k], -1), np.sum(w * e1[k], -1)),
                np.arcsin(np.clip(np.sum(w * T[k], -1), -1, 1)))

    n_sub = 6
    pe, te = table.phi_o_edges, table.theta_o_edges
    fp = (pe[:-1, None] + (np.arange(n_sub) + 0.5) / n_sub * np.diff(pe)[:, None]).ravel()
    s0, s1 = np.sin(te[:-1]), np.sin(te[1:])
    ft = np.arcsin(s0[:, None] + (np.arange(n_sub) + 0.5) / n_sub * (s1 - s0)[:, None]).ravel()
    P, Q = np.meshgrid(fp, ft, indexing="ij")
    wo = np.stack([np.cos(Q) * np.cos(P), np.sin(Q), np.cos(Q) * np.sin(P)], -1)
    wi = np.array([np.cos(theta_i), np.sin(theta_i), 0.0])   # phi_i = 0, outgoing phi relative to it
    ref = 0.0
    for k in range(len(psi)):
        phi_il, th_il = local(wi, k)
        hit = r * np.cos(th_il) / (Rb * np.cos(ply.max_lean) * np.cos(theta_i))
        phi_ol, th_ol = local(wo, k)
        ref = ref + hit * fiber.eval(phi_i=phi_il, theta_i=th_il, phi_o=phi_ol, theta_o=th_ol,
                                     wavelength=wavelength) / len(psi)
    return ref.reshape(len(pe) - 1, n_sub, len(te) - 1, n_sub).mean(axis=(1, 3))


def check_rotated_fiber(table, ply, fiber, spec, wavelength):
    """Every bin of a one-fiber twisted table whose light leaves below 60 deg within
    :func:`agree` of :func:`rotated_fiber` (light that leaves steeply can meet the same fiber a
    turn further on: not in the reference)."""
    lam = int(np.argmin(np.abs(table.wavelength - wavelength)))
    for j, ti in enumerate(spec.theta_i):
        ref = rotated_fiber(ply, fiber, table, ti, wavelength)
        got, err = table.values[0, j, :, :, lam], table.stderr[0, j, :, :, lam]
        shallow = np.abs(table.theta_o)[None, :] < np.deg2rad(60) + 0 * got
        bad = ~agree(got, ref, err) & shallow
        assert not bad.any(), (np.rad2deg(ti), np.argwhere(bad), got[bad], ref[bad], err[bad], ref.max())


@pytest.mark.parametrize("migration", [None, Migration(0.85, 1.5, seed=2)], ids=["rigid", "migrating"])
def test_lossless_twisted_ply_conserves_energy(migration):
    fiber = PatternFiber(WL, "isotropic").tabulate(NODES)
    ply = TwistedBundle(poisson((100.0, 100.0), 20.0, gap=2.0 if migration is None else 14.0, seed=4), 1800.0,
                        migration)
    assert np.degrees(ply.max_lean) > 10
    spec = BakeSpec(np.deg2rad([-60.0, 0.0, 40.0, 75.0]), [0.0], 12, 24, relative_phi=True, max_bounces=2000)
    tally = TwistedBaker(ply, fiber, spec).trace(0, 40_000, 5)
    table = table_of(tally, spec, fiber)
    p_theta = tally.passthrough_theta[0] / tally.paths_theta[0]
    total = table.scattered[0] + p_theta[:, None] + table.absorbed[0] + table.lost[0]
    assert np.allclose(total, 1.0, atol=1e-3), total  # a lossless path's weight stays 1: no noise
    assert np.all(table.absorbed < 1e-5) and np.all(table.lost < 1e-3)
    assert np.all(np.isfinite(table.values)) and np.all(table.values >= 0)
    # the singly scattered part, read independently: a bake capped at one fiber event keeps
    # exactly the paths that leave after their first (the same seed, the same paths)
    once = dataclasses.replace(spec, max_bounces=1)
    capped = table_of(TwistedBaker(ply, fiber, once).trace(0, 40_000, 5), once, fiber)
    assert np.allclose(table.single, capped.scattered, rtol=1e-5, atol=1e-9)
    assert np.all((table.single > 0.05 * table.scattered) & (table.single < 0.95 * table.scattered))


def test_a_turn_of_a_twisted_ply_is_a_shift_along_its_axis(ray_fiber):
    """Rotation invariance (the relative-phi reduction of circular plies) is exact for a
    twisted ply whose entry heights cover a period: absolute tables at phi_i = 0 and 75 deg
    agree once the second is turned back by 75 deg."""
    ply = TwistedBundle(poisson((120.0, 120.0), 20.0, gap=2.0, seed=2), 3000.0)
    phis = np.deg2rad([0.0, 75.0])  # 75 deg: five bins of 15 deg
    spec = BakeSpec(np.deg2rad([20.0]), phis, 12, 24, relative_phi=False)
    baker = TwistedBaker(ply, ray_fiber, spec)
    t0, t1 = baker.trace(0, 150_000, 7), baker.trace(1, 150_000, 8)
    t0.add(t1)
    table = table_of(t0, spec, ray_fiber, {"theta_i": None, "phi_i": None, "phi_o": "absolute"})
    a, b = table.values[0, 0], np.roll(table.values[1, 0], -5, axis=0)
    err = np.sqrt(table.stderr[0, 0] ** 2 + np.roll(table.stderr[1, 0], -5, axis=0) ** 2)
    assert agree(a, b, err, rel=0.03).mean() > 0.99
    # but not without the shift: the light does depend on where it comes from
    assert agree(a, table.values[1, 0], err, rel=0.03).mean() < 0.9


def test_a_twisted_ellipse_expands_by_its_half_turns(ray_fiber):
    """The ``half_turns`` reduction of a twisted ellipse, against direct bakes: a table baked
    at phi_i = 0..90 deg and expanded (``BundleTable.expanded``: the half turn about the axis,
    and the half turns about x and z, which flip theta) against the same ply baked at phi_i =
    120, 210 and 300 deg itself. The arrangement is symmetric under both mirrors of the
    cross-section, so each half turn maps this very ply onto itself (for a random one they
    hold for the ensemble, as an ellipse's mirrors do); the twist makes the table chiral, so
    the flips of theta are seen (asserted: every row with theta the other way disagrees)."""
    from models.bundle_table import BundleTable

    q = np.array([[30.0, 12.0], [70.0, 0.0], [40.0, 60.0]])
    centers = np.concatenate([q * [sx, sz] for sx in (1, -1) for sz in (1, -1)])
    ply = TwistedBundle(Bundle(np.unique(centers, axis=0), 10.0, (110.0, 80.0)), -900.0)
    theta_i = np.deg2rad([-40.0, 0.0, 40.0])
    reduced = BakeSpec(theta_i, np.deg2rad([0.0, 30.0, 60.0, 90.0]), 12, 24, relative_phi=False)
    baker = TwistedBaker(ply, ray_fiber, reduced)
    tally = baker.trace(0, 120_000, 1)
    for a in range(1, 4):
        tally.add(baker.trace(a, 120_000, 1 + a))
    table = table_of(tally, reduced, ray_fiber, {"theta_i": None, "phi_i": "half_turns", "phi_o": "absolute"})
    full = BundleTable(**{k: getattr(table, k) for k in ("wavelength", "phi_i", "theta_i", "phi_o_edges",
                                                          "theta_o_edges", "values", "stderr", "passthrough",
                                                          "passthrough_stderr", "absorbed", "lost")},
                       passthrough_theta=table.passthrough_theta, meta=dict(table.meta)).expanded()
    assert np.allclose(np.rad2deg(full.phi_i), np.arange(0, 360, 30))
    direct_spec = BakeSpec(theta_i, np.deg2rad([120.0, 210.0, 300.0]), 12, 24, relative_phi=False)
    direct_baker = TwistedBaker(ply, ray_fiber, direct_spec)
    direct = direct_baker.trace(0, 120_000, 11)
    for a in (1, 2):
        direct.add(direct_baker.trace(a, 120_000, 11 + a))
    direct = table_of(direct, direct_spec, ray_fiber, {"theta_i": None, "phi_i": None, "phi_o": "absolute"})
    checks = []
    for a, phi in enumerate((120.0, 210.0, 300.0)):
        k = int(round(phi / 30))
        got, ref = full.values[k], direct.values[a]
        err = np.sqrt(full.stderr[k] ** 2 + direct.stderr[a] ** 2)
        assert agree(got, ref, err, rel=0.03).mean() > 0.99, phi
        assert np.allclose(full.passthrough_theta[k], direct.passthrough_theta[a], atol=0.01)
        lit = err > 0
        chi2 = lambda v: np.mean(((v - ref)[lit] / err[lit]) ** 2)  # noqa: E731
        checks.append((chi2(got), chi2(got[::-1, :, ::-1])))  # the expansion, and theta the other way
    # each row within its noise, and each row with theta the other way is not: the ply is
    # chiral enough that a wrong flip shows (chi^2 per bin 0.93-0.99 against 3.9-15.7, seeds 1 and 11)
    assert all(right < 1.5 and wrong > 3.0 for right, wrong in checks), checks


# -- the config ----------------------------------------------------------------------

@pytest.mark.parametrize("twist,message", [
    ("{pitch_um: 0}", "non-zero length"),
    ("{pitch_um: 3000, yarn: Cotton 1}", "either pitch_um"),
    ("{}", "either pitch_um"),
    ("{pitch_um: .nan}", "finite"),
    ("{yarn: Wool 9}", "not in"),
    ("{pitch_um: 3000, migration: true}", "takes R_min and s from a Zhao 2016 yarn"),
    ("{yarn: Cotton 1, migration: {r_min: 0.8, s: 1.13}}", "more than 20 turns"),
    ("{yarn: Cotton 1, migration: {r_min: 1.5, s: 1}}", "r_min"),
    ("{yarn: Cotton 1, migration: {s: 1}}", "r_min"),
])
def test_a_bad_twist_is_refused_naming_the_key(twist, message):
    from pipeline.build import build_ply
    from pipeline.config import ConfigError
    from pipeline.loading import load_config

    with pytest.raises((ConfigError, ValueError), match=message):
        build_ply(load_config("configs/default.yaml", [f"bundle.twist={twist}"]))


@pytest.mark.parametrize("pitch,message", [(1e15, "straight to that precision"), (1e9, "straight to that precision"),
                                           (-1.5, "lengthen the pitch"), (1.0, "lengthen the pitch")])
def test_a_pitch_its_cylinders_cannot_hold_is_refused_before_building(monkeypatch, pitch, message):
    """Too long a pitch: Mitsuba's float32 cylinder frames misplace the fibers (a pitch of
    1e15 um baked passthrough 0.161 against the parallel ply's 0.099); too short: the period's
    cylinders outgrow memory (pitch 1 um ran out of memory building them). Both said before
    anything is built; a pitch of 1 mm to 1 m passes."""
    from pipeline import build, machine
    from pipeline.loading import load_config

    monkeypatch.setattr(machine, "memory_bytes", lambda: 16 * 2**30)  # the same answer on every machine
    for ok in (1000.0, -3000.0, 1e6):
        build.check_scene_fits(build.build_ply(load_config("configs/default.yaml", [f"bundle.twist={{pitch_um: {ok}}}"])))
    ply = build.build_ply(load_config("configs/default.yaml", [f"bundle.twist={{pitch_um: {pitch}}}"]))
    with pytest.raises(ValueError, match=message):
        build.check_scene_fits(ply)


def test_a_twisted_ellipse_keeps_its_azimuths_and_a_twist_needs_the_fast_estimator():
    from pipeline.build import build_ply, make_spec
    from pipeline.config import ConfigError
    from pipeline.loading import load_config

    cfg = load_config("configs/thesis_ellipse.yaml", ["bundle.twist={pitch_um: 3000}"])
    ply = build_ply(cfg)  # spaced out until its fibers clear where they pass the minor axis
    assert ply.closest_approach()[0] >= 0 and len(ply.bundle.radii) < len(build_ply(
        load_config("configs/thesis_ellipse.yaml")).radii)
    spec, reductions = make_spec(cfg, ply, PatternFiber(WL, "isotropic").tabulate(NODES))
    assert reductions == {"theta_i": None, "phi_i": "half_turns", "phi_o": "absolute"} and not spec.relative_phi
    assert np.allclose(np.rad2deg(spec.phi_i), np.arange(0, 91, 15)) and np.allclose(spec.theta_i, -spec.theta_i[::-1])
    with pytest.raises(ConfigError, match="estimator: fast"):
        load_config("configs/ray_ply.yaml", ["bundle.twist={pitch_um: 3000}", "bake.estimator=thesis"])
    ray = load_config("configs/ray_ply.yaml", ["bundle.twist={pitch_um: 3000}"])  # auto: the lobe exit, as parallel
    assert ray.bake.exit == "auto"


def test_a_zhao_yarn_gives_its_lean_and_the_spec_keeps_every_theta_i_but_the_poles():
    from pipeline.build import build_ply, make_spec
    from pipeline.loading import load_config

    cfg = load_config("configs/default.yaml", ["bundle.twist={yarn: Cotton 1}", "bundle.radius_um=260",
                                               "bake.theta_i_deg=[0, 15, 30, 45, 60, 65, 70, 75, 80, 90]",
                                               "bake.n_theta_o=35"])
    ply = build_ply(cfg)
    # Cotton 1: alpha = -0.369 cm on a ply of e_X = 0.026 cm: the rim leans atan(2 pi 260 / 3690) = 23.9 deg
    assert ply.pitch < 0 and np.isclose(abs(ply.pitch), 3690.0, rtol=1e-6)
    rim = np.arctan(2 * np.pi * 260.0 / 3690.0)
    assert np.degrees(rim) == pytest.approx(23.9, abs=0.1) and ply.max_lean <= rim
    fiber = PatternFiber(WL, "isotropic").tabulate(NODES)
    spec, reductions = make_spec(cfg, ply, fiber)
    # graded nodes with a pole, mirrored, without the poles
    assert np.allclose(np.rad2deg(spec.theta_i), [-80, -75, -70, -65, -60, -45, -30, -15, 0,
                                                  15, 30, 45, 60, 65, 70, 75, 80])
    assert reductions == {"theta_i": None, "phi_i": "rotation", "phi_o": "relative"}
    assert spec.exit == "uniform" and spec.relative_phi


def test_a_migrating_zhao_ply_is_spaced_until_its_fibers_clear(tmp_path):
    """``migration: true`` takes Cotton 1's R_min 0.8 and s 1.1: the ply repeats after 10 turns,
    the Poisson cross-section is spaced out until no two fibers meet anywhere along the period
    (checked here independently of the search, on a dense sampling of every pair), and a
    listed cross-section that cannot clear is refused with the amount."""
    from pipeline.build import build_bundle, build_ply
    from pipeline.loading import load_config

    cfg = load_config("configs/twisted_cotton1.yaml", ["bundle.twist.migration=true"])
    ply = build_ply(cfg)
    assert ply.migration.r_min == 0.8 and ply.migration.s == 1.1 and ply.period == pytest.approx(10 * abs(ply.pitch))
    rigid = build_bundle(cfg)
    assert 3 <= len(ply.bundle.radii) < len(rigid.radii)  # sparser than the rigid twist's
    # brute force: every pair, fiber j within 60 um of each height of fiber i (leaning fibers meet
    # off-level), on a 7 x 3.5 um grid; then the five nearest pairs on a 0.1 um grid about their
    # sampled minima
    i, j = np.triu_indices(len(ply.bundle.radii), 1)
    r = ply.bundle.radii

    def gaps(y, dy, i, j):
        return np.sqrt(((ply.centers_at(y, i) - ply.centers_at(y + dy, j)) ** 2).sum(-1) + dy**2) - r[i] - r[j]

    y, dy = np.arange(0.0, ply.period, 7.0)[:, None, None], 3.5 * np.arange(-17, 18)[None, :, None]
    g = gaps(y, dy, i, j).reshape(-1, len(i))
    near = np.argsort(g.min(0))[:5]
    u = 0.1 * np.arange(-70, 71)
    fine = []
    for p in near:
        k = np.argmin(g[:, p])
        y0, dy0 = y.ravel()[k // dy.size], dy.ravel()[k % dy.size]
        fine.append(gaps(y0 + u[:, None], dy0 + u[None, :] / 2, i[p], j[p]).min())
    sampled = min(fine)
    assert sampled > 0.0 and sampled - ply.closest_approach()[0] < 0.1, (sampled, ply.closest_approach())
    listed = tmp_path / "fibers.csv"
    listed.write_text("x_um,z_um,r_um\n" + "\n".join(f"{x},{z},{rr}" for (x, z), rr in zip(rigid.centers, rigid.radii)))
    with pytest.raises(ValueError, match=r"intersect by \d+(\.\d+)? um where they lean and migrate"):
        build_ply(load_config("configs/twisted_cotton1.yaml",
                              ["bundle.twist.migration=true", "bundle.arrangement=file", f"bundle.file={listed}"]))


# -- the stage: resumable, batch-seeded, the same table on Dask ------------------------

def test_a_twisted_bake_resumes_and_is_the_serial_one_on_a_cluster(tmp_path):
    """``bcsdf bake`` of a twisted ply: stopped after 3 of 8 batches and resumed on a local
    Dask cluster of two workers, the table is the serial bake's bit for bit, per-theta_i
    passthrough included; the table balances energy per theta_i."""
    import yaml

    from models.bundle_table import BundleTable
    from pipeline.loading import load_config
    from pipeline.stages import bake as bake_stage
    from pipeline.stages import fiber as fiber_stage

    cfg_data = {"name": "tw", "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
                "fiber": {"model": "mie", "radius_um": 3.0}, "tabulate": {"theta_i_step_deg": 30},
                "bundle": {"shape": "circle", "radius_um": 20.0, "seed": 2, "twist": {"pitch_um": 300.0}},
                "bake": {"paths_per_phi_i": 16384, "batch_paths": 2048, "theta_i_step_deg": 30,
                         "n_theta_o": 12, "n_phi_o": 24}}
    path = tmp_path / "tw.yaml"
    path.write_text(yaml.safe_dump(cfg_data))
    cfg = load_config(path)
    for root in ("serial", "cluster"):
        fiber_stage.run(cfg, tmp_path / root)
    bake_stage.run(cfg, tmp_path / "serial")
    bake_stage.run(cfg, tmp_path / "cluster", stop_after=3)
    assert (tmp_path / "cluster" / "tw" / "bake" / "checkpoint.npz").exists()
    bake_stage.run(cfg, tmp_path / "cluster", workers=2)
    a, b = (BundleTable.load(tmp_path / r / "tw" / "bake" / "bundle_table.npz") for r in ("serial", "cluster"))
    for k in ("values", "stderr", "passthrough", "passthrough_theta", "absorbed", "lost"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert a.meta["reductions"] == {"theta_i": None, "phi_i": "rotation", "phi_o": "relative"}
    assert np.allclose(np.rad2deg(a.theta_i), [-60, -30, 0, 30, 60])
    assert np.allclose(a.energy_balance()["total"], 1.0, atol=0.03)


# -- closure: explicit helical fibers against the twisted bake ------------------------

def test_helix_curves_follow_the_helix():
    """The B-spline control points of ``closure.helix_control_points``: the spline itself
    (evaluated here with the uniform cubic basis) stays within 0.001 um of the helix."""
    from pipeline import closure

    ply = TwistedBundle(Bundle(np.array([[260.0, 0.0], [0.0, -100.0]]), 10.0, (280.0, 280.0)), -2000.0)
    curves = closure.helix_control_points(ply, 3.0, unit=1e-3, per_turn=64)
    assert len(curves) == 2 and np.allclose(curves[0][:, 3], 10e-3)
    t = np.linspace(0.0, 1.0, 40)[:, None]
    basis = [(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3]
    for k, c in enumerate(curves):
        P = c[:, :3] / 1e-3
        pts = np.concatenate([sum(b * P[m + i] for i, b in enumerate(basis)) / 6 for m in range(len(P) - 3)])
        on = ply.centers_at(pts[:, 1])[:, k]
        assert np.abs(pts[:, [0, 2]] - on).max() < 1e-3
        assert np.isclose(pts[0, 1], -3000.0) and np.isclose(pts[-1, 1], 3000.0)  # the length asked



def test_migration_that_would_thin_the_ply_to_another_is_refused_with_the_packing_to_ask_for():
    """Fibers migrating nearly to the axis clear each other only in a ply spaced out to a few
    fibers: that ply is refused with what was asked and what would be built, and asking for
    the sparser packing it names builds it (checked against the cross-section's own count)."""
    from pipeline.build import build_ply
    from pipeline.loading import load_config

    hostile = ["bundle.twist.migration={r_min: 0.01, s: 0.95}"]
    with pytest.raises(ValueError, match=r"spaced out from \d+ fibers .* to \d+ .*bundle\.packing: (0\.\d+)") as e:
        build_ply(load_config("configs/twisted_cotton1.yaml", hostile))
    packing = re.search(r"bundle\.packing: (0\.\d+)", str(e.value)).group(1)
    ply = build_ply(load_config("configs/twisted_cotton1.yaml", hostile + [f"bundle.packing={packing}"]))
    b = ply.bundle
    assert len(b.radii) == round(float(packing) * b.semi_axes[0] * b.semi_axes[1] / b.radii[0] ** 2)
    assert ply.closest_approach()[0] >= 0.0


def test_a_twisted_cross_section_that_cannot_hold_its_leaning_fibers_names_the_twist_not_a_gap():
    """The gap a twist needs is the twist's doing (the user set none): the refusal says so."""
    from pipeline.build import build_ply
    from pipeline.loading import load_config

    with pytest.raises(ValueError, match=r"bundle\.twist: .*widened from bundle\.gap_um = 0 to .*lengthen the pitch"):
        build_ply(load_config("configs/twisted_cotton1.yaml", ["bundle.shape=ellipse", "bundle.semi_axes_um=[200, 25]"]))
