"""The shipped example scenes (``scenes/*.xml``) load and render as they are, through
``bcsdf render-scene`` (the plugins registered), with only their ``$`` parameters pointed at
test artifacts; bad scene input gets a clear error and exit status 2."""

import numpy as np
import pytest

from pipeline import cli
from tests.test_cli import ROOT


@pytest.fixture(autouse=True)
def restore_variant(mi_llvm):
    yield
    mi_llvm.set_variant("llvm_ad_rgb")  # render-scene chose its own variant


def exr(path):
    import mitsuba as mi

    return np.asarray(mi.Bitmap(str(path)))


def test_ply_scene_renders_with_a_table(mi_llvm, tmp_path, capsys):
    from tests.synthetic import make_config, synthetic_table

    cfg = make_config(tmp_path)
    synthetic_table(cfg, tmp_path / "table.npz", passthrough=0.2)
    out = tmp_path / "ply.exr"
    rc = cli.main(["render-scene", str(ROOT / "scenes" / "ply.xml"), "-o", str(out), "--spp", "2",
                   "-D", f"table={tmp_path / 'table.npz'}", "-D", "width=48", "-D", "height=24"])
    assert rc == 0, capsys.readouterr().err
    img = exr(out)
    assert img.shape[:2] == (24, 48) and np.all(np.isfinite(img)) and img.mean() > 0
    assert out.with_suffix(".png").stat().st_size > 0


def test_a_bundle_under_another_integrator_is_refused(mi_llvm, tmp_path, capsys):
    """Under Mitsuba's ``path`` a fiber_bundle renders without an error but wrong (no
    passthrough, no displaced exits): render-scene says so instead of rendering."""
    from tests.synthetic import make_config, synthetic_table

    synthetic_table(make_config(tmp_path), tmp_path / "table.npz", passthrough=0.2)
    text = (ROOT / "scenes" / "ply.xml").read_text()
    assert '<integrator type="bundle_path">' in text
    scene = tmp_path / "ply_path.xml"
    scene.write_text(text.replace('<integrator type="bundle_path">', '<integrator type="path">'))
    rc = cli.main(["render-scene", str(scene), "-o", str(tmp_path / "x.exr"), "--spp", "1",
                   "-D", f"table={tmp_path / 'table.npz'}", "-D", "width=8", "-D", "height=4"])
    err = capsys.readouterr().err
    assert rc == 2 and "need the bundle_path integrator" in err and "Traceback" not in err, err
    assert not (tmp_path / "x.exr").exists()


def test_a_film_too_large_to_hold_is_refused_before_rendering(mi_llvm, tmp_path, capsys):
    """200000 x 100000 pixels: more values than a Dr.Jit array holds (2^32), said with the size."""
    from tests.synthetic import make_config, synthetic_table

    synthetic_table(make_config(tmp_path), tmp_path / "table.npz", passthrough=0.2)
    rc = cli.main(["render-scene", str(ROOT / "scenes" / "ply.xml"), "-o", str(tmp_path / "x.exr"), "--spp", "1",
                   "-D", f"table={tmp_path / 'table.npz'}", "-D", "width=200000", "-D", "height=100000"])
    err = capsys.readouterr().err
    assert rc == 2 and "200000 x 100000 pixels" in err and "smaller film" in err and "Traceback" not in err, err
    assert not (tmp_path / "x.exr").exists()


def test_glove_scene_renders_plies_with_an_mlp(mi_llvm, tmp_path, trained, capsys):
    from models.cloth.knit import stockinette
    from models.cloth.yarn import YarnSpec, build_plies, write_curves

    cfg, root = trained
    size = next(iter(cfg.train.models))
    write_curves(tmp_path / "plies.txt", build_plies(stockinette(2, 2, r=10.0), 1.0, YarnSpec(3, 4.0, 5.0, 60.0)))
    out = tmp_path / "glove.exr"
    rc = cli.main(["render-scene", str(ROOT / "scenes" / "glove.xml"), "-o", str(out), "--spp", "1",
                   "-D", f"plies={tmp_path / 'plies.txt'}", "-D", f"model={root / cfg.name / 'export' / size / 'weights.npz'}",
                   "-D", "ply_radius=4.0", "-D", "width=32", "-D", "height=24"])
    assert rc == 0, capsys.readouterr().err
    assert np.all(np.isfinite(exr(out)))


@pytest.mark.parametrize("args,says", [
    (["missing.xml"], "no such scene file"),
    ([str(ROOT / "scenes" / "ply.xml"), "-D", "oops"], "NAME=VALUE"),
    ([str(ROOT / "scenes" / "ply.xml"), "-D", "table=/nowhere/table.npz"], "not found"),
    ([str(ROOT / "scenes" / "ply.xml"), "--spp", "0"], "at least 1"),
    ([str(ROOT / "scenes" / "ply.xml"), "--variant", "cuda_nothing"], "not available"),
    ([str(ROOT / "scenes" / "ply.xml"), "--variant", "scalar_rgb"], "JIT variants"),
])
def test_bad_scene_input_is_refused_with_the_reason(mi_llvm, tmp_path, capsys, args, says):
    rc = cli.main(["render-scene", *args, "-o", str(tmp_path / "x.exr")])
    err = capsys.readouterr().err
    assert rc == 2 and says in err and "Traceback" not in err, err
    assert not (tmp_path / "x.exr").exists()


def test_plugin_reference_pages_match_the_docstrings(mi_llvm):
    """docs/plugins/ is generated from the classes' docstrings; a stale page fails here."""
    from pipeline import plugin_docs

    assert plugin_docs.main(["--check"]) == 0, "run `python -m pipeline.plugin_docs`"


def test_plugin_pages_xml_examples_load(mono, tmp_path):
    """Every plugin page's XML example, as printed, loads in a scene (its artifact paths
    pointed at small stand-ins), and every parameter in it is one the table documents."""
    import inspect
    import re

    import mitsuba_ext
    from models.fiber.ray import RayFiber
    from tests.synthetic import make_config, synthetic_table

    synthetic_table(make_config(tmp_path), tmp_path / "bundle_table.npz")
    RayFiber(np.array([450.0, 550.0, 650.0]), 1.55, 0.1, 0.3, 0.3, 2.0, n_h=32).tabulate(
        np.deg2rad(np.arange(0, 91, 5.0))).save(tmp_path / "fiber_table.npz")
    classes = {}
    for module in mitsuba_ext.plugin_modules():
        classes.update(module.PLUGINS)
    for name, cls in classes.items():
        doc = inspect.cleandoc(cls.__doc__)
        xml = re.search(r"\.\. code-block:: xml\n\n((?:    .*\n|\n)+)", doc + "\n").group(1)
        xml = re.sub(r'value="artifacts/[^"]*/(\w+\.npz)"', lambda m: f'value="{tmp_path / m.group(1)}"', xml)
        documented = set(re.findall(r"\* - (\w+)", doc))
        assert set(re.findall(r'name="(\w+)"', xml)) - {"p0", "p1", "radius"} <= documented, name
        body = xml if "<integrator" in xml else xml.replace("<shape", '<shape id="s"', 1)
        mono.load_string(f'<scene version="3.0.0">{body}</scene>')


def test_readme_render_example_runs_as_written(trained, tmp_path, monkeypatch):
    """The README's own-scene snippet, literally, in a folder laid out as a clone after
    ``make run`` (its weights a trained test model): it renders, and the ply stands out of
    its sky under the sun (not a furnace)."""
    import shutil

    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Rendering in your own Mitsuba scene"):]
    code = section[section.index("```python") + len("```python"):]
    code = code[: code.index("```")]
    _, art = trained
    dst = tmp_path / "artifacts" / "default" / "export" / "small"
    dst.mkdir(parents=True)
    shutil.copy(art / "n" / "export" / "tiny" / "weights.npz", dst / "weights.npz")
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    img = np.asarray(scope["image"])
    assert img.shape == (160, 320, 3) and np.all(np.isfinite(img))
    import time
    for _ in range(100):  # mi.util.write_bitmap writes in a thread of its own
        if (tmp_path / "artifacts" / "my_ply.png").exists() and \
                (tmp_path / "artifacts" / "my_ply.png").stat().st_size > 1000:
            break
        time.sleep(0.1)
    assert (tmp_path / "artifacts" / "my_ply.png").stat().st_size > 1000
    ply, sky = img[70:90, 100:220].mean(), img[:20].mean()
    assert abs(ply / sky - 1) > 0.5, (ply, sky)


@pytest.mark.parametrize("where,says", [("folder", "is a folder"), ("under a file", "cannot write into")])
def test_an_output_that_cannot_be_written_is_refused_before_rendering(mi_llvm, tmp_path, capsys, where, says):
    """``-o`` naming a folder, or a file under a file: refused before the scene loads (the
    scene's default table does not even exist here), nothing written beside it."""
    (tmp_path / "a_file").write_text("")
    out = tmp_path if where == "folder" else tmp_path / "a_file" / "x.exr"
    before = sorted(tmp_path.iterdir())
    rc = cli.main(["render-scene", str(ROOT / "scenes" / "ply.xml"), "-o", str(out), "-D", "table=/nowhere.npz"])
    err = capsys.readouterr().err
    assert rc == 2 and says in err and "Traceback" not in err, err
    assert sorted(tmp_path.iterdir()) == before


def test_an_onnx_bundle_in_an_xml_scene_renders(mi_llvm, tmp_path, trained, capsys):
    """The onnx backend needs Dr.Jit's evaluated mode: render-scene sets it itself."""
    cfg, root = trained
    size = next(iter(cfg.train.models))
    text = (ROOT / "scenes" / "ply.xml").read_text()
    old = '<string name="backend" value="table"/>\n            <string name="table" value="$table"/>'
    assert old in text
    onnx = root / cfg.name / "export" / size / "model.onnx"
    scene = tmp_path / "onnx.xml"
    scene.write_text(text.replace(old, '<string name="backend" value="onnx"/>\n            '
                                       f'<string name="model" value="{onnx}"/>'))
    out = tmp_path / "onnx.exr"
    rc = cli.main(["render-scene", str(scene), "-o", str(out), "--spp", "1", "-D", "width=16", "-D", "height=8"])
    assert rc == 0, capsys.readouterr().err
    img = exr(out)
    assert np.all(np.isfinite(img)) and img.mean() > 0
