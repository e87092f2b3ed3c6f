"""Cloth: yarn-level models in (BCC), centre lines as Mitsuba B-splines, plies wound about
them, and the cloth render's closure.

References are independent of the code under test: the BCC layout written here byte by
byte, circles (a Catmull-Rom and a Bezier circle are within known distances of the true
circle), Mitsuba's own curve intersection for what the renderer sees, a straight line for
the plies' helices, the plane of a planar loop for the rotation-minimizing frame, and the
far field of docs/DESIGN.md for the render.
"""

import struct

import numpy as np
import pytest

from models.cloth.bcc import BCCError, Curve, CurveCollection, read_bcc, write_bcc
from models.cloth.curves import bspline_samples, evaluate, interpolate_bspline, to_bspline
from models.cloth.knit import stockinette
from models.cloth.plies import nearest_other, transport_frames, wind_plies
from models.cloth.yarn import YarnSpec, build_plies, write_curves
from tests.test_cli import ROOT

GLOVE = ROOT / "data" / "glove.bcc"


def bcc_bytes(code=b"C0", curves=((False, [[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 1]]),), n_curves=None,
              n_points=None, size=0x44, magic=b"BCC"):
    """A BCC file written from the format's description (not by write_bcc)."""
    body = b""
    for closed, pts in curves:
        body += struct.pack("<i", -len(pts) if closed else len(pts)) + np.asarray(pts, "<f4").tobytes()
    n_c = len(curves) if n_curves is None else n_curves
    n_p = sum(len(p) for _, p in curves) if n_points is None else n_points
    return magic + bytes([size]) + code + bytes([3, 1]) + struct.pack("<QQ", n_c, n_p) + b"info".ljust(40, b"\0") + body


# -- BCC ---------------------------------------------------------------------------------
def test_reads_the_glove_as_its_attribution_describes():
    c = read_bcc(GLOVE)
    assert (len(c.curves), c.point_count, c.kind, c.up) == (70, 58537, "catmull_rom", 1)
    assert all(curve.closed for curve in c.curves)
    # yarns pass within about 0.2 units of each other (centimetres: a yarn of ~2 mm)
    spacing = np.linalg.norm(np.diff(c.curves[0].points, axis=0), axis=1)
    assert 0.1 < np.median(spacing) < 0.4


def test_reads_what_the_format_says_and_writes_it_back(tmp_path):
    pts = [[0, 0, 0], [1, 0, 0], [1, 1, 0.5]]
    path = tmp_path / "a.bcc"
    path.write_bytes(bcc_bytes(b"PL", curves=((True, pts), (False, pts + [[2, 2, 2]]))))
    c = read_bcc(path)
    assert c.kind == "polyline" and [cv.closed for cv in c.curves] == [True, False]
    assert np.array_equal(c.curves[1].points[-1], [2, 2, 2])
    write_bcc(tmp_path / "b.bcc", c)
    assert (tmp_path / "b.bcc").read_bytes()[:24] == path.read_bytes()[:24]
    assert (tmp_path / "b.bcc").read_bytes()[64:] == path.read_bytes()[64:]


@pytest.mark.parametrize("name,data,says", [
    ("truncated", bcc_bytes()[:-5], "truncated"),
    ("short", b"BCC", "shorter than the 64-byte"),
    ("signature", bcc_bytes(magic=b"OBJ"), "not a Binary Curve Collection"),
    ("type", bcc_bytes(code=b"XX"), "curve type"),
    ("sizes", bcc_bytes(size=0x48), "0x48"),
    ("curve count", bcc_bytes(n_curves=2), "promises 2 curves"),
    ("point count", bcc_bytes(n_points=5), "promises 1 curves and 5 points"),
    ("nan", bcc_bytes(curves=((False, [[0, 0, 0], [np.nan, 0, 0], [2, 0, 0], [3, 0, 0]]),)), "non-finite"),
    ("no curves", bcc_bytes(curves=()), "holds no curves"),
])
def test_malformed_files_are_refused_with_the_reason(tmp_path, name, data, says):
    path = tmp_path / "bad.bcc"
    path.write_bytes(data)
    with pytest.raises(BCCError, match=says):
        read_bcc(path)


def test_point_counts_that_disagree_with_the_data_are_refused(tmp_path):
    data = bytearray(bcc_bytes(curves=((False, [[0, 0, 0]] * 4), (False, [[1, 1, 1]] * 4))))
    data[64:68] = struct.pack("<i", 6)  # the first curve claims 6 of the 8 points: the total still fits
    (tmp_path / "bad.bcc").write_bytes(bytes(data))
    with pytest.raises(BCCError):
        read_bcc(tmp_path / "bad.bcc")


# -- centre lines as B-splines -----------------------------------------------------------
def circle(n, R=10.0):
    a = 2 * np.pi * np.arange(n) / n
    return np.stack([R * np.cos(a), R * np.sin(a), np.zeros(n)], -1)


def bezier_circle(R=10.0):
    """Four cubic Bezier quarter arcs, handles k R long (k = 4/3 (sqrt 2 - 1)): within
    2.7e-4 R of the circle (a classical closed form)."""
    k = 4 / 3 * (np.sqrt(2) - 1)
    pts = []
    for q in range(4):
        a, b = q * np.pi / 2, (q + 1) * np.pi / 2
        p0, p3 = R * np.array([np.cos(a), np.sin(a), 0]), R * np.array([np.cos(b), np.sin(b), 0])
        pts += [p0, p0 + k * R * np.array([-np.sin(a), np.cos(a), 0]), p3 - k * R * np.array([-np.sin(b), np.cos(b), 0])]
    return np.array(pts)


@pytest.mark.parametrize("kind,points,near", [("catmull_rom", circle(24), 2e-3), ("bezier", bezier_circle(), 3e-3),
                                              ("polyline", circle(96), 6e-3)])
def test_closed_loops_render_where_the_file_says_without_a_seam(mi_llvm, tmp_path, kind, points, near):
    """Mitsuba's own intersection of the converted loop: rays from the circle's centre, in its
    plane, at 720 azimuths (the seam included), all hit the tube's inner wall at R - r,
    within the conversion tolerance plus how far the file's curve is from the circle."""
    mi = mi_llvm
    R, r, tol = 10.0, 0.5, 0.01 * 0.5
    C, deviation, _ = to_bspline(points, True, kind, tol)
    assert deviation <= tol
    (tmp_path / "loop.txt").write_text("\n".join(f"{x} {y} {z} {r}" for x, y, z in C))
    scene = mi.load_dict({"type": "scene", "loop": {"type": "bsplinecurve", "filename": str(tmp_path / "loop.txt")}})
    a = 2 * np.pi * np.arange(720) / 720 + 1e-4
    rays = mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f(np.cos(a), np.sin(a), np.zeros_like(a)))
    t = np.asarray(scene.ray_intersect(rays).t)
    assert np.all(np.isfinite(t)), f"{np.sum(~np.isfinite(t))} rays found no curve (a gap at the seam?)"
    # the file's curve is within `near` R of the circle (Catmull-Rom of 24 points, the Bezier
    # circle, the chords of a 96-gon: 1 - cos(pi / 96) = 5.4e-4 R inwards)
    assert np.max(np.abs(t - (R - r))) < tol + near * R + 1e-3 * r, np.max(np.abs(t - (R - r)))


def test_bspline_input_is_kept_exactly_and_open_curves_end_at_their_ends():
    P = np.random.default_rng(1).normal(size=(9, 3))
    C, deviation, _ = to_bspline(P, True, "bspline", 1e-3)
    assert deviation == 0 and np.array_equal(C, np.concatenate([P, P[:3]]))
    # an open Catmull-Rom runs from its second point to its next-to-last (the BCC
    # specification: the ends are tangents), and so does its B-spline
    C, deviation, m = to_bspline(P, False, "catmull_rom", 1e-3)
    ends = evaluate(C, False, "bspline", np.array([0.0, len(C) - 3]))
    assert np.allclose(ends, P[[1, -2]], atol=1e-9)


def test_glove_centre_lines_stay_within_one_percent_of_the_yarn_radius():
    from models.cloth.yarn import centre_lines

    c = read_bcc(GLOVE)
    c.curves = c.curves[::10]
    lines, worst = centre_lines(c, 1.0, 0.01 * 0.09)
    assert worst <= 0.01 * 0.09
    # the measure is an upper bound of the distance: check it independently at random
    # parameters against the Catmull-Rom written as Hermite segments (tangents (P+1 - P-1) / 2)
    rng = np.random.default_rng(0)
    for (C, _), curve in zip(lines, c.curves):
        P = curve.points
        n = len(P)
        u = rng.uniform(0, n, 200)
        i, t = np.floor(u).astype(int), (u - np.floor(u))[:, None]
        p0, p1 = P[i % n], P[(i + 1) % n]
        m0, m1 = (P[(i + 1) % n] - P[(i - 1) % n]) / 2, (P[(i + 2) % n] - P[i % n]) / 2
        hermite = ((2 * t**3 - 3 * t**2 + 1) * p0 + (t**3 - 2 * t**2 + t) * m0 + (-2 * t**3 + 3 * t**2) * p1
                   + (t**3 - t**2) * m1)
        spline = evaluate(C, False, "bspline", u * (len(C) - 3) / n)
        assert np.max(np.linalg.norm(spline - hermite, axis=1)) <= 0.01 * 0.09


# -- frames and plies ----------------------------------------------------------------------
def test_frame_of_a_planar_loop_keeps_the_plane_and_closes():
    f = transport_frames(circle(200), closed=True)
    assert np.allclose(np.abs(f.b[:, 2]), 1.0, atol=1e-9) or np.allclose(np.abs(f.n[:, 2]), 1.0, atol=1e-9)
    assert np.allclose(np.sum(f.n * f.t, 1), 0, atol=1e-9)


def test_frame_of_a_twisted_loop_is_continuous_and_closes():
    s = np.linspace(0, 2 * np.pi, 600, endpoint=False)
    knot = np.stack([(2 + np.cos(3 * s)) * np.cos(2 * s), (2 + np.cos(3 * s)) * np.sin(2 * s), np.sin(3 * s)], -1)
    f = transport_frames(knot, closed=True, stride=4)
    turn = np.arccos(np.clip(np.sum(f.n * np.roll(f.n, -1, 0), 1), -1, 1))
    bend = np.arccos(np.clip(np.sum(f.t * np.roll(f.t, -1, 0), 1), -1, 1))
    assert np.max(turn) < 2 * np.max(bend) + 1e-3, "the normal jumps (or spins) somewhere, the seam included"
    assert np.allclose(np.linalg.norm(f.n, axis=1), 1) and np.allclose(np.sum(f.n * f.t, 1), 0, atol=1e-9)


def test_plies_of_a_straight_yarn_are_helices_of_the_pitch():
    z = np.linspace(0, 20, 401)
    line = np.stack([np.zeros_like(z), np.zeros_like(z), z], -1)
    plies, pitch = wind_plies(transport_frames(line, closed=False), K=3, R=0.6, pitch=-5.0)
    assert pitch == -5.0
    for k, p in enumerate(plies):
        assert np.allclose(np.hypot(p[:, 0], p[:, 1]), 0.6)
        angle = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
        slope = np.polyfit(p[:, 2], angle, 1)[0]
        assert abs(abs(slope) - 2 * np.pi / 5.0) < 1e-6
    a0 = [np.arctan2(p[0, 1], p[0, 0]) for p in plies]
    assert np.allclose(np.sort(np.mod(np.diff(a0), 2 * np.pi)), 2 * np.pi / 3)
    # opposite signs of the pitch turn opposite ways
    other, _ = wind_plies(transport_frames(line, closed=False), K=3, R=0.6, pitch=5.0)
    s1 = np.polyfit(plies[0][:, 2], np.unwrap(np.arctan2(plies[0][:, 1], plies[0][:, 0])), 1)[0]
    s2 = np.polyfit(other[0][:, 2], np.unwrap(np.arctan2(other[0][:, 1], other[0][:, 0])), 1)[0]
    assert s1 * s2 < 0


def test_plies_of_a_loop_close_on_themselves():
    f = transport_frames(circle(300), closed=True)
    plies, pitch = wind_plies(f, K=2, R=0.5, pitch=3.0)
    L = f.length  # the 300-gon's perimeter
    assert abs(L - 2 * np.pi * 10) < 1e-3 * L
    assert abs(L / pitch - round(L / pitch)) < 1e-9   # a whole number of turns
    for p in plies:
        step = np.linalg.norm(np.diff(np.concatenate([p, p[:1]]), axis=0), axis=1)
        assert step.max() < 1.5 * np.median(step)      # no jump where the loop closes


def test_ply_curves_of_a_loop_stay_on_their_torus():
    """The plies' B-splines (16 samples a turn of their helix, however finely the centre line
    is sampled) stay within 2e-4 of the winding radius of the torus they wind on (exact for
    a circular yarn); at 8 samples a turn they would stray 1.2e-3."""
    f = transport_frames(circle(20000), closed=True)
    plies, pitch = wind_plies(f, K=3, R=0.6, pitch=3.0)
    turns = 2 * np.pi * 10 / abs(pitch)
    for p in plies:
        assert len(p) == round(16 * turns)          # the helix sets the samples, not the centre line's 20,000
        q = bspline_samples(interpolate_bspline(p, closed=True), 16)
        off_axis = np.hypot(np.hypot(q[:, 0], q[:, 1]) - 10.0, q[:, 2])
        assert np.max(np.abs(off_axis - 0.6)) < 2e-4 * 0.6


def test_zhao_yarn_scaled_to_its_radius_and_plies_do_not_overlap():
    from models.bundle import zhao2016_row

    y = YarnSpec.from_zhao(zhao2016_row("Cotton 1"), 0.9)
    assert y.K == 3 and abs(y.radius - 0.9) < 1e-12 and y.overlap() == 0
    # Zhao's ratios: ply offset / ply semi-axis and pitch / offset are kept
    assert abs(y.R / y.r_ply - 0.038 / 0.026) < 1e-12 and abs(y.pitch / y.R - 0.453 / 0.038) < 1e-12
    assert YarnSpec(3, 1.0, 0.5, 5.0).overlap() > 0


def test_swatch_yarns_stay_a_diameter_apart_and_interpenetration_is_measured():
    r = 1.0
    sw = stockinette(4, 5, r=r)
    passes = [evaluate(c.points, False, sw.kind, np.linspace(0, len(c.points) - 1, 40 * len(c.points)))
              for c in sw.curves]
    near = nearest_other(passes, [False] * 4, along_min=4 * r)
    assert near.min() >= 2 * r * 0.999, near.min()
    g = build_plies(sw, 1.0, YarnSpec(3, 0.45, 0.55, 6.0))  # a yarn of radius r: the swatch's own
    assert g.overlapping == 0 and g.folded == 0 and g.overlap_warning(YarnSpec(3, 0.45, 0.55, 6.0)) is None
    # the same swatch with a yarn 1.8x as thick interpenetrates and folds at the loops' heads (the
    # closed form bends to 1.09 r there, Z / 2 and the sin 2t term's curvature at t = 0), and says
    # by how much
    thick = YarnSpec(3, 0.8, 1.0, 6.0)
    g = build_plies(sw, 1.0, thick)
    assert g.overlapping > 0 and 0 < g.folded < 0.5
    assert "interpenetrate" in g.overlap_warning(thick) and "folds through itself" in g.overlap_warning(thick)


@pytest.mark.parametrize("scale", [1.0, 1e-6], ids=["thick yarn", "tiny model"])
def test_a_yarn_thicker_than_its_centre_lines_bend_is_refused_before_winding(scale):
    """A yarn radius beyond the centre lines' median bend radius folds the yarn through itself
    along most of its length (a blob, not a yarn, whatever the nearest-pass count says):
    refused with the radius that fits, whether the yarn is too thick or the model too small."""
    sw = stockinette(2, 3, r=1.0)
    with pytest.raises(ValueError, match=r"yarn_radius_mm: .*median bend radius .*cloth\.units_mm"):
        build_plies(sw, scale, YarnSpec(3, 400.0, 500.0, 600.0))


def test_nearest_other_pass_is_found_however_many_samples_a_diameter_holds():
    """Two parallel straight yarns 3 apart, sampled 100 times a unit: the nearest sample of
    the other yarn lies behind hundreds of the yarn's own, and is still found."""
    x = np.linspace(0.0, 10.0, 1001)
    a = np.stack([x, 0 * x, 0 * x], -1)
    near = nearest_other([a, a + [0.0, 3.0, 0.0]], [False, False], along_min=4.0, within=8.0)
    assert np.allclose(near, 3.0)


def test_degenerate_centre_lines_are_refused():
    yarn = YarnSpec(1, 0.1, 0.0, 1.0)
    few = CurveCollection([Curve(np.zeros((3, 3)) + np.arange(3)[:, None], False)], "catmull_rom")
    with pytest.raises(ValueError, match="at least 4"):
        build_plies(few, 1.0, yarn)
    doubled = CurveCollection([Curve(np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0.0]]), False)],
                              "catmull_rom")
    with pytest.raises(ValueError, match="coincident"):
        build_plies(doubled, 1.0, yarn)
    # a yarn listed twice, or one that turns back over itself, is no yarn radius's fault
    sw = stockinette(2, 2, r=1.0)
    twice = CurveCollection(sw.curves + [Curve(sw.curves[1].points.copy(), False)], sw.kind)
    with pytest.raises(ValueError, match=r"curves 1 and 2 coincide .*no yarn radius separates them"):
        build_plies(twice, 1.0, YarnSpec(3, 0.4, 0.5, 6.0))
    t = np.linspace(0.0, 4 * np.pi, 64, endpoint=False)  # a loop of radius 10 drawn twice round
    twice_round = CurveCollection([Curve(10 * np.stack([np.cos(t), np.sin(t), 0 * t], -1), True)], "catmull_rom")
    with pytest.raises(ValueError, match=r"curve 0 runs back over itself"):
        build_plies(twice_round, 1.0, YarnSpec(1, 1.0, 0.0, 1.0))


# -- flyaways -------------------------------------------------------------------------------
def test_hair_draws_follow_their_distributions():
    """Each hair parameter against its (mu, sigma / 2) (Zhao et al.'s generator's spread), the
    count against density x length, the starts uniform along and round the ply."""
    from models.cloth.flyaways import SIGMA_SCALE, HairSpec, draw_hairs

    L, r_ply = 4000.0, 1.0
    spec = HairSpec(density=0.5, r0=(0.6, 0.2), r_span=(0.5, 0.3), s_span=(0.1, 1.0), phi_span=(0.4, 0.3))
    h = draw_hairs(np.random.default_rng(3), spec, r_ply, L)
    n = len(h.r0)
    assert n == round(0.5 * L)
    for got, (mu, sd) in ((h.r0, spec.r0), (h.phi_span, spec.phi_span)):    # untruncated (r0 > 0 at 3 sigma)
        assert abs(got.mean() - mu) < 4 * SIGMA_SCALE * sd / np.sqrt(n), (got.mean(), mu)
        assert abs(got.std() / (SIGMA_SCALE * sd) - 1) < 0.1, (got.std(), sd)
    assert h.r0.max() <= r_ply and h.r_span.min() > 0
    # the axial span: positive before its coin flip, so |s_span| is N(0.1, 0.5) truncated at 0:
    # E[X | X > 0] = mu + sigma pdf(a) / (1 - cdf(a)), a = -mu / sigma = -0.2: 0.4375
    assert 0.4 < np.mean(h.s_span > 0) < 0.6 and abs(np.abs(h.s_span).mean() - 0.4375) < 0.03
    assert abs(h.s0.mean() / L - 0.5) < 0.02 and abs(np.mean(np.exp(1j * h.phi0))) < 0.1


def test_hairs_about_a_straight_ply_start_where_they_leave_it():
    """About a straight ply along x its frame is plain (r = |(y, z)|, s = x): each placed hair
    runs from where its line (r0 + u r_span, phi0 + u phi_span, s0 + u s_span) crosses the
    radius r_out to its end; a hair that ends inside is not placed."""
    from models.cloth.flyaways import HAIR_SAMPLES, Hairs, place_hairs

    x = np.linspace(0, 100, 1001)
    f = transport_frames(np.stack([x, 0 * x, 0 * x], -1), closed=False)
    h = Hairs(s0=np.array([10.0, 50.0, 70.0]), phi0=np.array([0.0, 1.0, 2.0]), r0=np.array([0.5, 0.9, 0.2]),
              r_span=np.array([1.0, 0.4, 0.5]), s_span=np.array([2.0, -1.0, 1.0]), phi_span=np.array([0.5, 0.2, 0.1]))
    pts = place_hairs(f, h, r_out=1.0)
    assert pts.shape == (HAIR_SAMPLES, 2, 3)        # the third ends at 0.7, inside
    r = np.hypot(pts[..., 1], pts[..., 2])
    assert np.allclose(r[0], 1.0) and np.allclose(r[-1], [1.5, 1.3])
    u_in = np.array([0.5, 0.25])                    # where r0 + u r_span = 1
    assert np.allclose(pts[0, :, 0], [10 + 2 * 0.5, 50 - 0.25]) and np.allclose(pts[-1, :, 0], [12, 49])
    turn = np.angle(np.exp(1j * (np.arctan2(pts[-1, :, 2], pts[-1, :, 1]) - np.arctan2(pts[0, :, 2], pts[0, :, 1]))))
    assert np.allclose(turn, [0.5, 0.2] * (1 - u_in))


@pytest.mark.parametrize("curve", ["linearcurve", "bsplinecurve"])
def test_hair_flyaways_round_a_closed_loop_stay_about_it_and_pierce_no_other_ply(curve):
    """About a circular ply loop (radius 10, its B-spline closed as build_plies writes it), every
    hair point lies between the ply's surface and the longest hair (torus coordinates), and
    hairs cross the loop's seam; beside a second loop 1.2 radii away, no hair comes within a
    ply radius (and the margin) of the other's centre line. Hairs as polylines with a pointed
    tip at each end, or as B-splines with tapered tips."""
    from models.cloth.flyaways import HAIR_SAMPLES, HairSpec, hair_flyaways

    def bodies(hairs):  # points along each hair's body (its tips left out)
        if curve == "bsplinecurve":
            return np.concatenate([bspline_samples(h[3:-3, :3], 4) for h in hairs])
        u = np.linspace(0, 1, 5)[:, None, None]
        return np.concatenate([((1 - u) * h[1:-2, :3] + u * h[2:-1, :3]).reshape(-1, 3) for h in hairs])

    loop = interpolate_bspline(circle(400), closed=True)
    spec = HairSpec(density=5.0, r0=(0.4, 0.05), r_span=(0.3, 0.05), s_span=(1.5, 0.5), phi_span=(0.0, 0.5))
    hairs = hair_flyaways([loop], 0.5, spec, seed=0, hair_radius=0.02, curve=curve)
    assert 0.5 * 5.0 * 2 * np.pi * 10 < len(hairs) <= 5.0 * 2 * np.pi * 10 + 1   # some end inside the ply
    tip = 3 if curve == "bsplinecurve" else 1
    assert all(h.shape == ((HAIR_SAMPLES + 2 if curve == "bsplinecurve" else HAIR_SAMPLES) + 2 * tip, 4)
               and np.all(h[:tip, 3] == 0) and np.all(h[-tip:, 3] == 0) and np.all(h[tip:-tip, 3] == 0.02)
               for h in hairs)                                  # radius 0.02, tips of radius 0
    pts = bodies(hairs)
    rho = np.hypot(np.hypot(pts[:, 0], pts[:, 1]) - 10.0, pts[:, 2])   # distance from the centre circle
    assert rho.min() > 0.5 + 0.03 - 0.005 and rho.max() < 0.4 + 0.3 + 4 * 0.05 + 0.01
    assert np.any(np.abs(np.arctan2(pts[:, 1], pts[:, 0])) < 0.05)   # across the seam at angle 0
    other = interpolate_bspline(circle(400) + [0.0, 0.0, 1.2], closed=True)
    both = hair_flyaways([loop, other], 0.5, spec, seed=0, hair_radius=0.02, curve=curve)
    assert 0 < len(both) < 2 * len(hairs)
    P = bodies(both)
    d0 = np.hypot(np.hypot(P[:, 0], P[:, 1]) - 10.0, P[:, 2])
    d1 = np.hypot(np.hypot(P[:, 0], P[:, 1]) - 10.0, P[:, 2] - 1.2)
    assert np.all(np.minimum(d0, d1) > 0.5 + 0.03 - 0.005)   # every hair clear of both plies


def test_zhao_flyaways_are_scaled_with_the_ply():
    """The table's lengths are absolute (centimetres): at the ply's own size (e_X = 0.026 cm
    = 0.26 mm, in scene millimetres) the hairs are the table's values times 10 and the
    density per mm a tenth; a ply twice as large doubles the lengths and halves the density."""
    from models.bundle import zhao2016_row
    from models.cloth.flyaways import HairSpec

    row = zhao2016_row("Cotton 1")
    own = HairSpec.from_zhao(row, r_ply=0.26)
    assert own.density == pytest.approx(3.377, rel=1e-3) and own.r0 == pytest.approx((0.20, 0.06))
    assert own.r_span == pytest.approx((0.16, 0.09)) and own.phi_span == pytest.approx((0.377, 0.326))
    big = HairSpec.from_zhao(row, r_ply=0.52, density_scale=2.0)
    assert big.density == pytest.approx(own.density) and big.s_span == pytest.approx(tuple(2 * v for v in own.s_span))


# -- the render: a ply built by the cloth path reproduces its far field ------------------
def test_cloth_ply_curve_renders_the_far_field_of_its_table(mono, tmp_path):
    """A straight one-ply yarn from a BCC file, through the cloth path (read, B-spline, ply
    file), carrying fiber_bundle: the closure of docs/DESIGN.md, ``E 2R cos(theta_i) S``."""
    from pipeline import closure
    from tests.synthetic import make_config, synthetic_table

    mi = mono
    cfg = make_config(tmp_path)
    synthetic_table(cfg, tmp_path / "table.npz", relative=True, passthrough=0.3)
    S = closure.evaluator(mi, "table", tmp_path / "table.npz", 550.0)
    R = 0.2

    def ply(R_, bsdf, half_length):
        y = np.linspace(-half_length, half_length, 9)
        path = tmp_path / "yarn.bcc"
        (tmp_path / "yarn.bcc").write_bytes(bcc_bytes(b"PL", curves=((False, np.stack(
            [np.zeros_like(y), y, np.zeros_like(y)], -1)),)))
        g = build_plies(read_bcc(path), 1.0, YarnSpec(1, R_, 0.0, 1.0))
        write_curves(tmp_path / "plies.txt", g)
        return {"type": "bsplinecurve", "filename": str(tmp_path / "plies.txt"), "bsdf": bsdf}

    bsdf = {"type": "fiber_bundle", "table": str(tmp_path / "table.npz"), "wavelength": 550.0, "up": closure.UP}
    pairs = closure.direction_pairs(cone_offsets_deg=(0.8, 1.5, -1.7, -3.0))
    pairs = pairs[closure.continuous(S, pairs)][::2]
    rows = closure.far_field_ratios(mi, bsdf, R, S, pairs, shape=ply)
    r = np.array([row[3] for row in rows])
    print(np.round(r, 4))
    assert len(r) >= 8 and np.allclose(r, 1.0, atol=0.01), r


# -- explicit fibers, patches, and what is refused before building ------------------------
def test_explicit_fibers_of_a_straight_ply_keep_the_arrangement_scaled():
    from models.cloth.fibers import explicit_fibers

    z = np.linspace(0, 10, 41)
    ply = interpolate_bspline(np.stack([np.zeros_like(z), np.zeros_like(z), z], -1), closed=False)
    centres, radii = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, -150.0]]), np.full(3, 20.0)
    curves, r = explicit_fibers([ply], 0.5, centres, radii, R_b=200.0)
    assert np.allclose(r, 20.0 * 0.5 / 200.0)
    offsets = [np.hypot(*bspline_samples(cv, 4)[:, :2].T) for cv in curves]
    assert np.allclose([o.mean() for o in offsets], [0.0, 0.25, 0.375], atol=1e-9)
    assert max(np.ptp(o) for o in offsets) < 1e-9    # parallel to the ply, as the bake assumes



@pytest.mark.parametrize("pitch_um", [1500.0, -2838.0])
def test_explicit_fibers_of_a_twisted_ply_are_helices_of_its_handedness_and_lean(pitch_um):
    """A twisted ply's explicit fibers along a straight ply: helices about it whose torsion
    has the pitch's sign (> 0 right-handed, as the bake's: ``models.bundle.TwistedBundle``),
    at a constant distance from the axis, leaning ``atan(2 pi rho / |pitch|)`` as in the
    bake (lengths scale with the ply, angles do not)."""
    from models.cloth.fibers import explicit_fibers

    z = np.linspace(0, 10, 21)
    ply = interpolate_bspline(np.stack([np.zeros_like(z), 0.3 * np.ones_like(z), z], -1), closed=False)
    centres, radii = np.array([[120.0, 0.0], [0.0, -90.0]]), np.full(2, 20.0)
    curves, _ = explicit_fibers([ply], 0.5, centres, radii, R_b=200.0, pitch_um=pitch_um)
    for cv, rho in zip(curves, (120.0, 90.0)):
        p = bspline_samples(cv, 8)[40:-40]
        rho_scene = rho * 0.5 / 200.0
        assert np.allclose(np.hypot(p[:, 0], p[:, 1] - 0.3), rho_scene, rtol=1e-3)
        d1 = np.gradient(p, axis=0)
        d2 = np.gradient(d1, axis=0)
        d3 = np.gradient(d2, axis=0)
        torsion = np.einsum("ij,ij->i", np.cross(d1, d2), d3)[5:-5]
        assert np.all(np.sign(torsion) == np.sign(pitch_um))
        lean = np.arccos(np.abs(d1[:, 2]) / np.linalg.norm(d1, axis=1))[5:-5]
        assert np.allclose(lean, np.arctan(2 * np.pi * rho / abs(pitch_um)), atol=2e-3)

@pytest.mark.parametrize("pitch_um", [None, -2838.0])
def test_explicit_point_count_is_what_explicit_fibers_make(pitch_um):
    """The whole garment's fiber count (memory figures) without making its fibers: the
    count of the curves :func:`explicit_fibers` makes, on plies bent differently."""
    from models.cloth.curves import interpolate_bspline
    from models.cloth.fibers import explicit_fibers, explicit_point_count

    t = np.linspace(0, 3, 40)
    plies = [interpolate_bspline(np.stack([np.cos(a * t), np.sin(a * t), t], -1), closed=False)
             for a in (0.5, 2.0)]
    centres, radii = np.array([[120.0, 0.0], [0.0, -90.0], [30.0, 40.0]]), np.full(3, 20.0)
    curves, _ = explicit_fibers(plies, 0.2, centres, radii, R_b=200.0, pitch_um=pitch_um)
    assert explicit_point_count(plies, 0.2, 3, R_b=200.0, pitch_um=pitch_um) == sum(len(c) for c in curves)


def test_patch_cuts_runs_inside_the_sphere():
    from models.cloth.fibers import patch

    loop = CurveCollection([Curve(circle(40), True)], "catmull_rom")
    piece = patch(loop, [10.0, 0.0, 0.0], 5.0)
    assert len(piece.curves) == 1 and not piece.curves[0].closed   # one run, across the loop's start
    assert np.all(np.linalg.norm(piece.curves[0].points - [10, 0, 0], axis=1) <= 5.0)
    assert len(piece.curves[0].points) == np.sum(np.linalg.norm(circle(40) - [10, 0, 0], axis=1) <= 5.0)


def test_a_model_too_large_for_memory_is_refused_before_building(monkeypatch):
    """On a 16 GiB machine (users' laptops): the glove with its flyaways fits; 1e5 times its
    size, or 100 times Zhao's flyaway density, does not, and says so before building."""
    from pipeline import machine
    from pipeline.loading import load_config
    from pipeline.garment import check_fits, yarn_model, yarn_spec

    monkeypatch.setattr(machine, "memory_bytes", lambda: 16 * 2**30)

    cfg = load_config(ROOT / "configs" / "glove.yaml", ["cloth.units_mm=100000"])
    with pytest.raises(ValueError, match="more than half of this machine"):
        check_fits(yarn_model(cfg.cloth), cfg.cloth, yarn_spec(cfg.cloth))
    # Zhao's flyaway density times 100 (the largest allowed): some 1e8 hairs
    cfg = load_config(ROOT / "configs" / "glove.yaml", ["cloth.flyaways.density_scale=100"])
    with pytest.raises(ValueError, match=r"flyaways, .*cloth\.flyaways\.density_scale"):
        check_fits(yarn_model(cfg.cloth), cfg.cloth, yarn_spec(cfg.cloth))
    cfg = load_config(ROOT / "configs" / "glove.yaml")
    check_fits(yarn_model(cfg.cloth), cfg.cloth, yarn_spec(cfg.cloth))  # the glove itself fits


@pytest.mark.parametrize("sets,says", [
    (["cloth.yarn=Wool"], "is not in"),
    (["cloth.model=missing.bcc"], "cannot read"),
    (["cloth.swatch={courses: 2}"], "either cloth.model"),
    (["cloth.ply_pitch_mm=0"], "ply_pitch_mm"),
    (["cloth.flyaways={yarn: Wool}"], "is not in"),
    (["cloth.flyaways={density_scale: -1}"], "density_scale"),
    (["cloth.exit_split=both"], "exit_split"),
])
def test_bad_cloth_configs_are_refused_when_loaded(sets, says):
    from pipeline.config import ConfigError
    from pipeline.loading import load_config

    with pytest.raises(ConfigError, match=says):
        load_config(ROOT / "configs" / "glove.yaml", sets)


def test_the_cloth_scene_renders_with_the_configs_exit_model(mi_llvm):
    """``cloth.exit_split`` is what the scene's ``bundle_path`` is given (its effect on the
    picture: tests/test_plugin.py::test_light_that_scattered_once_leaves_where_it_entered)."""
    from pipeline import scenes
    from pipeline.loading import load_config

    for split in ("none", "emitter", "all"):
        c = load_config(ROOT / "configs" / "glove.yaml", [f"cloth.exit_split={split}"]).cloth
        scene = scenes.cloth_scene(mi_llvm, c, {}, ([0, 0, 0], [1, 1, 1]), 1)
        assert scene["integrator"]["exit_split"] == split


def test_readme_cloth_example_runs_as_written(tmp_path, monkeypatch):
    """The README's cloth snippet, literally, from a folder that has the repository's data/."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Cloth: a knitted glove"):]
    code = section[section.index("```python") + len("```python"):]
    code = code[: code.index("```")]
    (tmp_path / "data").symlink_to(ROOT / "data")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    lines = (tmp_path / "artifacts" / "plies.txt").read_text().split("\n\n")
    assert len(lines) == 210  # 70 loops x 3 plies, a blank line between curves
    assert len(lines[0].splitlines()[0].split()) == 4
