"""Scene dictionaries for the render stage (units: millimetres).

* ``ply``: one bundle as a straight cylinder seen from the side, its cross-section
  winding ``twist_turns`` times along its length (the thesis's Figure 5.8);
* ``yarn``: ``K`` plies wound helically about the yarn axis (Zhao et al. 2016: ply
  count, ply radius and pitch from ``zhao2016_table2.csv``), each ply a B-spline
  curve carrying the bundle BSDF;
* ``explicit``: the ``ply`` with every fiber of the bake's arrangement as its own
  cylinder carrying the single-fiber model (``fiber_table``): the ground truth.

All share the lighting: a grey sky and a white sun (``rgb`` emitters, i.e. D65 white
in spectral variants), so that colour comes only from the fibers.
"""

from __future__ import annotations

import numpy as np

from models.bundle import TwistedBundle, zhao2016_row

from .closure import helix_control_points, write_curves

UM = 1e-3  # micrometres in scene units (mm)
FOV_DEG = 60.0  # the render stage's perspective camera, across the image


def _lights(mi):
    return {
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.05, 0.05]}},
        "sun": {"type": "directional", "direction": [-0.5, -0.6, -0.8],
                "irradiance": {"type": "rgb", "value": [3.0, 3.0, 3.0]}},
    }


def sun_alone(mi) -> dict:
    """The render stage's sun without its sky: one incident direction, where a table's far
    field is read at a few bins (the sky alone lights a nearly lossless ply as a white
    furnace does, which no error of its table's shape can change)."""
    return {"sun": _lights(mi)["sun"]}


def _sensor(mi, r, half_width, spp, seed=0, view=None):
    """Perspective camera on +z, 60 deg wide, framing ``half_width`` mm at the origin.

    A far-field BSDF under a sun looks the same wherever the view direction is the
    same: the perspective sweeps the view along the ply by +-30 deg, so the picture
    shows the specular cone of the parallel fibers as a highlight. ``view``: ``(fov_deg,
    turn_deg)``, another width (the same framing from further away: a narrower fov is a
    camera nearer the far field) and the camera turned about the vertical by ``turn_deg``
    (its view ``theta_o = turn_deg`` from the ply's normal plane).
    """
    fov, turn = (FOV_DEG, 0.0) if view is None else map(float, view)
    distance = half_width / np.tan(np.radians(fov / 2))
    eye = distance * np.array([np.sin(np.radians(turn)), 0.0, np.cos(np.radians(turn))])
    return {"type": "perspective", "fov": fov, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(eye.tolist(), [0, 0, 0], [0, 1, 0]),
            "film": {"type": "hdrfilm", "width": r.width, "height": r.height, "rfilter": {"type": "gaussian"},
                     "pixel_format": "luminance" if "mono" in mi.variant() else "rgb"},
            "sampler": {"type": "independent", "sample_count": spp, "seed": seed}}


def describe(cfg, name: str) -> str:
    """One sentence for the report: what the render stage's scene ``name`` shows, its
    camera and its light."""
    Rb = cfg.bundle.bounding_radius_um() * UM
    sun = np.array(_lights(None)["sun"]["direction"])
    sun_elevation = np.degrees(np.arcsin(-sun[2] / np.linalg.norm(sun)))
    light = (f"a white sun {sun_elevation:.0f} deg above the image plane, from the upper right and in front, and a "
             "dim grey sky (the colour is the fibers')")
    camera = f"a perspective camera {FOV_DEG:.0f} deg across, looking down -z at the ply's side"
    if name == "ply":
        turns = cfg.render.twist_turns
        return (f"One straight ply (radius {Rb:.3g} mm, {ply_length(cfg):.3g} mm long, along the image's x axis"
                + (f", its cross-section turned {turns:g} times along it" if turns else "")
                + f"), seen by {camera}, under {light}.")
    return (f"Plies of this bundle wound into a yarn (Zhao et al. 2016's {cfg.render.yarn}: its ply count, "
            f"radius and pitch), two turns of it along the image's x axis, seen by {camera}, under {light}.")


def ply_length(cfg) -> float:
    return 16 * cfg.bundle.bounding_radius_um() * UM


def ply_rows(cfg, height: int) -> slice:
    """The image rows of :func:`ply_scene`'s ply, its whole silhouette and a margin.

    The closure is a statement about the intensity per unit length, i.e. about the ply's
    whole width: the bundle BSDF spreads it evenly across the width, the explicit fibers
    do not (a ply's rim has fewer fibers). A band narrower than the silhouette compares
    different parts of the two (rows within 0.9 R made the sun-lit bundle 5% darker than
    its explicit fibers). The silhouette's half-height is ``R`` at the axis, a few per cent
    more for the near side in perspective, plus the reconstruction filter's footprint.
    """
    r = cfg.render
    half = (cfg.bundle.bounding_radius_um() * UM) / (0.5 * ply_length(cfg)) * (0.5 * r.width)  # pixels
    reach = 1.2 * half + 2
    return slice(max(0, int(height / 2 - reach)), min(height, int(np.ceil(height / 2 + reach))))


def _base(mi, cfg, half_width, spp, seed, lights=None, view=None):
    r = cfg.render
    return {"type": "scene", "integrator": {"type": "bundle_path", "max_depth": r.max_depth},
            "sensor": _sensor(mi, r, half_width, spp, seed, view), **(_lights(mi) if lights is None else lights)}


def ply_scene(mi, cfg, bsdf: dict, spp: int, seed: int = 0, twist_turns=None, lights=None, view=None) -> dict:
    """The bundle as a cylinder along x; ``bsdf`` is a ``fiber_bundle`` dict. ``lights``:
    emitter dicts instead of the sky and sun; ``view``: as :func:`_sensor`'s."""
    turns = cfg.render.twist_turns if twist_turns is None else twist_turns
    L, Rb = ply_length(cfg), cfg.bundle.bounding_radius_um() * UM
    scene = _base(mi, cfg, 0.5 * L, spp, seed, lights, view)
    scene["ply"] = {"type": "cylinder", "p0": [-0.5 * L, 0, 0], "p1": [0.5 * L, 0, 0], "radius": Rb,
                    "bsdf": {**bsdf, "twist_rate": 360.0 * turns / L, "up": [0.0, 1.0, 0.0]}}
    return scene


def explicit_scene(mi, cfg, bundle, fiber_table_path, spp: int, seed: int = 0, plugin: str = "fiber_table",
                   curve_file=None, reach: float = 0.0, lights=None, view=None) -> dict:
    """The same ply, every fiber its own shape with the fiber model (``plugin``:
    ``fiber_table``, or ``fiber_ray`` for a bake with the h-resolved exit), unturned: views
    of other turns of the arrangement, and of other heights of a twisted one, move its
    fibers in the loaded scene (``pipeline.closure.TurnedFibers``, at
    ``closure.view_placements``).

    Parallel fibers (a :class:`~models.bundle.Bundle`) are cylinders, not one
    ``bsplinecurve`` of all fibers: rays that leave a fiber next to a touching neighbour
    made Mitsuba 3.9's curve intersection read past its segment array (seen with Dr.Jit's
    debug mode), and cylinders need no curve end caps. A twisted ply's fibers
    (a :class:`~models.bundle.TwistedBundle`, spaced so that they never touch) are one
    ``bsplinecurve`` along their helices (``pipeline.closure.helix_control_points``),
    written to ``curve_file``, long enough to be moved by up to ``reach`` scene units
    along the axis. ``lights``, ``view``: as :func:`ply_scene`'s.
    """
    L = ply_length(cfg)
    scene = _base(mi, cfg, 0.5 * L, spp, seed, lights, view)
    fiber = {"type": plugin, "filename": str(fiber_table_path)}
    # the bundle frame (x, t, z) of ply_scene without twist is (y, x, -z) of the scene;
    # the fibers run past the image edges so that their ends stay out of view
    if isinstance(bundle, TwistedBundle):
        if curve_file is None:
            raise ValueError("explicit_scene: a twisted ply's helices need a curve_file to be written to")
        write_curves(helix_control_points(bundle, 0.6 * L + reach, UM), curve_file)
        T = mi.ScalarTransform4f
        to_scene = T([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]])  # (x, y, z) -> (y, x, -z): a rotation
        scene["fibers"] = {"type": "bsplinecurve", "filename": str(curve_file), "bsdf": fiber, "to_world": to_scene}
        return scene
    for k, ((cx, cz), r) in enumerate(zip(np.asarray(bundle.centers, float) * UM, bundle.radii * UM)):
        scene[f"fiber_{k:05d}"] = {"type": "cylinder", "p0": [-0.6 * L, cx, -cz], "p1": [0.6 * L, cx, -cz],
                                   "radius": float(r), "bsdf": {**fiber, "radius": float(r)}}
    return scene


def yarn_helices(cfg, row: dict, n_points: int = 64):
    """Control points ``[K][n, 4]`` of the plies' centre lines (mm) and the yarn length."""
    Rb = cfg.bundle.bounding_radius_um() * UM
    K = int(row["K_plies"])
    R_ply = float(row["R_ply"]) * 10.0            # cm -> mm
    pitch = abs(float(row["alpha_ply"])) * 10.0   # one turn of the plies, mm
    R_ply = max(R_ply, 1.05 * Rb / np.sin(np.pi / K))  # plies of this bundle's radius must not overlap
    L = 2.0 * pitch
    x = np.linspace(-0.6 * L, 0.6 * L, n_points)
    sign = np.sign(float(row["alpha_ply"])) or 1.0
    plies = []
    for k in range(K):
        a = sign * 2 * np.pi * x / pitch + 2 * np.pi * k / K
        plies.append(np.stack([x, R_ply * np.cos(a), R_ply * np.sin(a), np.full_like(x, Rb)], -1))
    return plies, L, R_ply


def yarn_scene(mi, cfg, bsdf: dict, curve_path, row: dict, spp: int, seed: int = 0) -> dict:

    plies, L, R_ply = yarn_helices(cfg, row)
    write_curves(plies, curve_path)
    scene = _base(mi, cfg, 0.5 * L, spp, seed)
    scene["yarn"] = {"type": "bsplinecurve", "filename": str(curve_path),
                     "bsdf": {**bsdf, "radius": cfg.bundle.bounding_radius_um() * UM, "up": [1.0, 0.0, 0.0]}}
    return scene


def ply_shape(curve_path, bsdf: dict, radius: float) -> dict:
    """One ``bsplinecurve`` file of plies carrying ``bsdf`` (a ``fiber_bundle`` of that radius)."""
    return {"type": "bsplinecurve", "filename": str(curve_path), "bsdf": {**bsdf, "radius": float(radius)}}


def cloth_view(c, bbox) -> tuple[np.ndarray, np.ndarray]:
    """``(eye, target)`` of the config's camera: the model's centre seen from
    ``camera_azimuth_deg`` / ``camera_elevation_deg`` (about the y axis, 0 = +z), at
    ``framing`` times the distance where its bounding sphere just fits the view's width."""
    lo, hi = (np.asarray(v, float) for v in bbox)
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    return centre + sky_direction(c.camera_azimuth_deg, c.camera_elevation_deg) * (
        c.framing * radius / np.sin(np.radians(c.fov_deg / 2))), centre


def sky_direction(azimuth_deg, elevation_deg) -> np.ndarray:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])


def cloth_scene(mi, c, shapes: dict, bbox, spp: int, seed: int = 0, view=None) -> dict:
    """``shapes`` (the plies, :func:`ply_shape`, or explicit fibers) on a floor under Mitsuba's
    sun and sky; ``c`` is the config's ``cloth`` section, ``bbox`` the model's ``(lo, hi)``
    corners (mm), ``view`` an ``(eye, target)`` (default :func:`cloth_view`)."""
    eye, target = cloth_view(c, bbox) if view is None else view
    lo, hi = (np.asarray(v, float) for v in bbox)
    scene = {
        "type": "scene",
        "integrator": {"type": "bundle_path", "max_depth": c.max_depth, "exit_split": c.exit_split},
        "sensor": {"type": "perspective", "fov": c.fov_deg, "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f().look_at(np.asarray(eye).tolist(), np.asarray(target).tolist(),
                                                              [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": c.width, "height": c.height,
                            "rfilter": {"type": "gaussian"},
                            "pixel_format": "luminance" if "mono" in mi.variant() else "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp, "seed": seed}},
        "sky": {"type": "sunsky", "turbidity": c.turbidity,
                "sun_direction": sky_direction(c.sun_azimuth_deg, c.sun_elevation_deg).tolist()},
        **shapes,
    }
    if c.ground:
        size = 10 * float(np.linalg.norm(hi - lo))
        scene["floor"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
            [0.5 * (lo[0] + hi[0]), lo[1], 0.5 * (lo[2] + hi[2])]).rotate([1, 0, 0], -90).scale(size),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "spectrum", "value": c.ground_reflectance}}}
    return scene


def named_scene(mi, cfg, name: str, bsdf: dict, spp: int, out, seed: int = 0) -> dict:
    """The render stage's scene ``name`` of ``render.scenes`` (``ply`` or ``yarn``; the
    yarn's ply curves are written to ``out``)."""
    if name == "ply":
        return ply_scene(mi, cfg, bsdf, spp, seed)
    return yarn_scene(mi, cfg, bsdf, out / "yarn_curves.txt", zhao2016_row(cfg.render.yarn), spp, seed)
