"""Bad input, case by case: a clear message, no traceback, nothing lost.

Each case runs through ``bcsdf``'s entry point (in process: ``pipeline.cli.main``) or
loads the plugin, on a copy of a small artifacts folder, and asserts the exit status 2
(or the plugin's error), that the message names the offending key or file, and that the
artifacts are byte-identical afterwards. ``CASES`` is what docs/BENCHMARKS.md counts
("Reliability").
"""

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline import cli
from tests.test_plugin import error_chain

BASE = {"name": "tiny", "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
        "fiber": {"model": "mie", "radius_um": 3.0, "ior": {"k": 1e-3}}, "tabulate": {"theta_i_step_deg": 30}}
BUNDLE = {"bundle": {"shape": "circle", "radius_um": 20.0}}


@pytest.fixture(scope="module")
def fiber_artifacts(tmp_path_factory):
    """A config and the artifacts of its fiber stage (what a bad run must not touch)."""
    tmp = tmp_path_factory.mktemp("bad")
    path = tmp / "tiny.yaml"
    path.write_text(yaml.safe_dump(BASE))
    assert cli.main(["--artifacts", str(tmp / "art"), "fiber", str(path)]) == 0
    return tmp / "art"


def snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def config(tmp, text=None, **sections):
    path = tmp / "tiny.yaml"
    if text is not None:
        path.write_bytes(text) if isinstance(text, bytes) else path.write_text(text)
    else:
        data = {**BASE, **sections}
        path.write_text(yaml.safe_dump(data))
    return path


def csv_with_nan(tmp):
    (tmp / "fibers.csv").write_text("x_um,z_um,r_um\n0,0,3\n10,0,nan\n")
    return config(tmp, bundle={"arrangement": "file", "file": "fibers.csv", "shape": "circle", "radius_um": 20.0})


def fiber_table_at_other_wavelengths(tmp):
    from models.fiber.base import FiberTable

    src = FiberTable.load(tmp / "art" / "tiny" / "fiber" / "fiber_table.npz")
    lobe = src.lobes[0].azimuthal  # [theta_i, theta_o or 1, phi, lambda]
    theta_o = src.theta_o if lobe.shape[1] > 1 else np.linspace(-1.5, 1.5, 4)
    values = np.broadcast_to(lobe, (lobe.shape[0], len(theta_o)) + lobe.shape[2:])
    np.savez(tmp / "measured.npz", values=values, axes=np.array(["theta_i", "theta_o", "phi", "wavelength"]),
             theta_i=src.theta_i, theta_o=theta_o, phi=src.phi, wavelength=src.wavelength)
    return config(tmp, fiber={"model": "table", "table": {"path": "measured.npz", "format": "npz"}},
                  wavelengths={"start_nm": 800, "stop_nm": 1000, "count": 3})


# id: (what makes the bad input -> argv after `bcsdf`, words the message must hold)
CASES = {
    "config is a folder": (lambda tmp: ["fiber", str(tmp)], ["is a folder"]),
    "config not UTF-8": (lambda tmp: ["fiber", str(config(tmp, b"fiber: {model: mie}\nname: \xff\xfe\n"))],
                         ["tiny.yaml", "not UTF-8"]),
    "config not YAML": (lambda tmp: ["fiber", str(config(tmp, "fiber: [model: mie\n"))], ["tiny.yaml", "not valid YAML"]),
    "duplicate key": (lambda tmp: ["fiber", str(config(tmp, "fiber: {model: mie}\nfiber: {model: ray}\n"))],
                      ["'fiber' is given twice"]),
    "name '..'": (lambda tmp: ["fiber", str(config(tmp, name=".."))], ["name", "outside artifacts"]),
    "NaN in fiber.ior.k": (lambda tmp: ["fiber", str(config(tmp, fiber={**BASE["fiber"], "ior": {"k": float("nan")}}))],
                           ["fiber.ior.k", "finite"]),
    "NaN in fiber.ior.cauchy_a": (lambda tmp: ["fiber", str(config(tmp, fiber={**BASE["fiber"],
                                                                                 "ior": {"cauchy_a": float("nan")}}))],
                                  ["fiber.ior.cauchy_a"]),
    "paths 1e15": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={"paths_per_phi_i": 10**15}))],
                   ["bake.paths_per_phi_i", "less than or equal"]),
    "table of 48 GiB": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={"n_theta_o": 3600, "n_phi_o": 7200}))],
                        ["GiB", "bake.n_theta_o"]),
    "a million batches": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={"paths_per_phi_i": 10**9,
                                                                               "batch_paths": 64}))],
                          ["batches", "bake.batch_paths"]),
    "--set without '='": (lambda tmp: ["fiber", str(config(tmp)), "--set", "bake.paths"], ["KEY=VALUE"]),
    "--set unknown key": (lambda tmp: ["fiber", str(config(tmp)), "--set", "fiber.radiuss=3"],
                          ["fiber.radiuss", "unknown key"]),
    "--set into a value": (lambda tmp: ["fiber", str(config(tmp)), "--set", "fiber.radius_um.x=3"],
                           ["fiber.radius_um is a value"]),
    "--artifacts is a file": (lambda tmp: ["--artifacts", str(tmp / "tiny.yaml"), "fiber", str(config(tmp))],
                              ["is a file", "--artifacts"]),
    "NaN radius in a CSV": (lambda tmp: ["bake", str(csv_with_nan(tmp))], ["fibers.csv", "row 3", "radius > 0"]),
    "table fiber at other wavelengths": (lambda tmp: ["fiber", str(fiber_table_at_other_wavelengths(tmp))],
                                         ["measured.npz", "wavelengths", "800"]),
}


def assert_refused_cleanly(argv, art, words, capsys):
    """``bcsdf argv`` exits 2 with a message holding ``words``, no traceback, and leaves
    the artifacts under ``art`` byte-identical."""
    before = snapshot(art)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for w in words:
        assert w in err, (argv, w, err)
    assert snapshot(art) == before


@pytest.mark.parametrize("case", list(CASES))
def test_bad_config_or_command_is_refused_cleanly(case, fiber_artifacts, tmp_path, capsys):
    art = tmp_path / "art"
    shutil.copytree(fiber_artifacts, art)
    make, words = CASES[case]
    argv = make(tmp_path)
    if argv[0] != "--artifacts":
        argv = ["--artifacts", str(art), *argv]
    assert_refused_cleanly(argv, art, words, capsys)


# -- damaged or foreign artifacts ----------------------------------------------------
def _copy(trained, tmp_path):
    cfg, src = trained
    shutil.copytree(src, tmp_path / "art")
    shutil.copy(src / "n.yaml", tmp_path / "n.yaml")
    return cfg, tmp_path / "art"


def _truncate(path: Path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _plugin_error(mi, props) -> str:
    with pytest.raises(Exception) as e:
        mi.load_dict({"type": "fiber_bundle", **props})
    return "\n".join(error_chain(e.value))


def test_truncated_exports_are_named_by_the_plugin(trained, mi_plugins, tmp_path):
    cfg, art = _copy(trained, tmp_path)
    weights, onnx = art / "n" / "export" / "tiny" / "weights.npz", art / "n" / "export" / "tiny" / "model.onnx"
    _truncate(weights)
    _truncate(onnx)
    msg = _plugin_error(mi_plugins, {"backend": "mlp", "model": str(weights)})
    assert "weights.npz" in msg and "re-run `bcsdf export`" in msg
    msg = _plugin_error(mi_plugins, {"backend": "onnx", "model": str(onnx)})
    assert "model.onnx" in msg and "re-run `bcsdf export`" in msg


@pytest.mark.parametrize("damage", ["truncated model.pt", "NaN in a table axis", "negative table values",
                                    "onnx from another config"])
def test_damaged_or_foreign_artifacts_are_named(trained, tmp_path, capsys, damage):
    from models.bundle_table import BundleTable

    cfg, art = _copy(trained, tmp_path)
    table_path = art / "n" / "bake" / "bundle_table.npz"
    stage = {"truncated model.pt": "export", "onnx from another config": "render"}.get(damage, "train")
    if damage == "truncated model.pt":
        _truncate(art / "n" / "train" / "tiny" / "model.pt")
        words = ["model.pt", "re-run `bcsdf train`"]
    elif damage in ("NaN in a table axis", "negative table values"):
        t = BundleTable.load(table_path)
        if damage == "NaN in a table axis":
            t.theta_o_edges = t.theta_o_edges.copy()
            t.theta_o_edges[3] = np.nan
            words = ["bundle_table.npz", "axis theta_o_edges"]
        else:
            t.values = t.values.copy()
            t.values[0, 0, 0, 0, 0] = -1.0
            words = ["bundle_table.npz", "negative"]
        t.save(table_path)  # save writes what it is given; load is what checks
    else:  # the same name, other training settings: its model.onnx copied over this one's
        other = cfg.model_copy(update={"train": cfg.train.model_copy(update={"epochs": 7})})
        from pipeline import export as export_stage
        from pipeline import train as train_stage
        root2 = tmp_path / "other"
        shutil.copytree(art / "n" / "bake", root2 / "n" / "bake")
        train_stage.run(other, root2)
        export_stage.run(other, root2)
        shutil.copy(root2 / "n" / "export" / "tiny" / "model.onnx", art / "n" / "export" / "tiny" / "model.onnx")
        words = ["model.onnx", "different settings"]
    argv = ["--artifacts", str(art), stage, str(tmp_path / "n.yaml"), "--set", "render.backends=[onnx]",
            "--set", "render.model=tiny"]
    assert_refused_cleanly(argv, art, words, capsys)

