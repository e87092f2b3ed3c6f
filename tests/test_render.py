"""The render stage and the ground truth of the whole idea: a ply rendered with every
fiber as its own cylinder (single-fiber model) against the baked bundle BSDF."""

import json

import numpy as np
import pytest
import yaml

from pipeline.cli import main as cli
from pipeline.config import load_config

RAY_PLY = {
    "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
    "fiber": {"model": "ray", "radius_um": 20.0,
              "ior": {"cauchy_a": 1.57, "cauchy_b_um2": 0.004, "k": [[400, 2.0e-4], [700, 1.0e-5]]},
              "ray": {"longitudinal_roughness": 0.2, "azimuthal_roughness": 0.4, "scale_tilt_deg": 0.0}},
    "tabulate": {"theta_i_step_deg": 5},
    "bundle": {"arrangement": "poisson", "shape": "circle", "radius_um": 100, "seed": 1},
    "bake": {"estimator": "fast", "paths_per_phi_i": 400_000, "theta_i_step_deg": 5, "n_theta_o": 36, "n_phi_o": 72},
    "train": {"models": {"tiny": [16, 16]}, "epochs": 20, "batch_size": 4096},
    "render": {"width": 48, "height": 24, "spp": 16, "scenes": ["ply"], "mono_check": False,
               "explicit": False, "backends": ["table", "mlp"]},
}


def write_config(tmp_path, name="ply", **sections):
    data = {**RAY_PLY, "name": name}
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("render")
    path = write_config(tmp)
    art = tmp / "artifacts"
    for stage in ("fiber", "bake"):
        assert cli(["--artifacts", str(art), stage, str(path)]) == 0
    return path, art


def orthographic(mi, r, half_width, spp, seed=0):
    """One view direction (normal to the ply) for every pixel: the table's own setting."""
    return {"type": "orthographic",
            "to_world": mi.ScalarTransform4f().look_at([0, 0, 50], [0, 0, 0], [0, 1, 0])
            @ mi.ScalarTransform4f().scale([half_width, half_width, 1]),
            "film": {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp, "seed": seed}}


def test_explicit_fibers_and_the_baked_bundle_look_the_same(baked, mi_plugins, monkeypatch):
    """The mean radiance of the ply, lit by a sun off the specular cone (so multiple
    scattering matters) and a grey sky: each fiber its own cylinder (fiber_table, with the
    baker's displaced exit) against one cylinder with the bundle table."""
    from pipeline import render, scenes
    from pipeline.bake import build_bundle

    mi = mi_plugins
    monkeypatch.setattr(scenes, "_sensor", orthographic)
    path, art = baked
    cfg = load_config(path)
    table = render.backend_props(cfg, art, "table")
    bundle = build_bundle(cfg)
    fiber = art / cfg.name / "fiber" / "fiber_table.npz"
    rows = slice(29, 35)  # inside the ply (half-height 4 px of 64: 100 um of 800 um)
    explicit = np.array(mi.render(mi.load_dict(scenes.explicit_scene(mi, cfg, bundle, fiber, 512))))[rows]
    ply = np.array(mi.render(mi.load_dict(scenes.ply_scene(mi, cfg, table, 256, twist_turns=0.0))))[rows]
    e, b = explicit.reshape(-1, 3).mean(0), ply.reshape(-1, 3).mean(0)
    assert np.all(np.isfinite(explicit)) and np.all(np.isfinite(ply))
    assert np.allclose(e, b, rtol=0.04), (e, b)
    # not trivially equal: single scattering alone (depth 2) is far darker
    single = scenes.explicit_scene(mi, cfg, bundle, fiber, 128)
    single["integrator"]["max_depth"] = 2
    assert np.array(mi.render(mi.load_dict(single)))[rows].mean() < 0.8 * e.mean()


def test_fiber_table_in_a_white_sky_is_white(baked, mi_plugins):
    """A lossless-ish fiber in a uniform sky (a furnace): light crossing its far wall
    passes, the forward lobe leaves from the displaced exit; no darkening but absorption."""
    from models.fiber.base import FiberTable

    mi = mi_plugins
    path, art = baked
    fiber = art / "ply" / "fiber" / "fiber_table.npz"
    albedo = FiberTable.load(fiber).energy()[0]  # theta_i = 0, per wavelength
    for integrator in ("path", "bundle_path"):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": integrator},
            "sensor": {"type": "orthographic",
                       "to_world": mi.ScalarTransform4f().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0])
                       @ mi.ScalarTransform4f().scale([0.01, 0.01, 1]),  # the fiber fills the view
                       "film": {"type": "hdrfilm", "width": 8, "height": 16, "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 256}},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "fiber": {"type": "cylinder", "p0": [-1, 0, 0], "p1": [1, 0, 0], "radius": 0.02,
                      "bsdf": {"type": "fiber_table", "filename": str(fiber), "radius": 0.02}}})
        img = np.array(mi.render(scene))
        assert np.all(np.isfinite(img))
        assert img.mean() == pytest.approx(albedo.mean(), abs=0.02), (integrator, img.mean(), albedo)


def test_render_stage_writes_images_flip_and_summary(baked, tmp_path):
    path, art = baked
    assert cli(["--artifacts", str(art), "train", str(path)]) == 0
    assert cli(["--artifacts", str(art), "export", str(path)]) == 0
    assert cli(["--artifacts", str(art), "render", str(path)]) == 0
    out = art / "ply" / "render"
    summary = json.loads((out / "summary.json").read_text())
    ply = summary["scenes"]["ply"]
    assert 0 <= ply["mlp"]["flip"] < 1 and ply["mlp"]["reference"] == "table"
    for name in ("ply_table.png", "ply_mlp.png", "ply_table.exr", "ply_mlp_flip.png", "ply_side_by_side.png"):
        assert (out / name).stat().st_size > 0, name


def test_render_refuses_models_from_other_settings(baked, tmp_path, capsys):
    path, art = baked
    assert cli(["--artifacts", str(art), "train", str(path)]) == 0
    assert cli(["--artifacts", str(art), "export", str(path)]) == 0
    capsys.readouterr()
    other = write_config(tmp_path, name="ply", train={"epochs": 21})  # same name, other training
    assert cli(["--artifacts", str(art), "render", str(other)]) == 2
    assert "trained with different settings" in capsys.readouterr().err
