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


def snapshot(root: Path, skip=()) -> dict:
    """Every artifact's digest (the lock's note of who last ran is not an artifact)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != ".lock" and p.name not in skip}


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


def csv_of_other_radii(tmp):
    (tmp / "fibers.csv").write_text("x_um,z_um,r_um\n-10,0,1\n0,0,3\n10,0,5\n")  # the fiber table's is 3 um
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
    "cone layout, wrong bin count": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_o_layout": "cone", "n_theta_o": 36, "theta_i_step_deg": 10}))], ["bake", "n_theta_o: 36", "35, 53"]),
    "cone bin wider than the step": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_o_layout": "cone", "n_theta_o": 35, "theta_i_step_deg": 10, "cone_bin_deg": 12}))],
        ["cone_bin_deg", "narrower"]),
    "graded nodes not from 0 to 90": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_i_deg": [5, 30, 60, 95]}))], ["bake.theta_i_deg", "from 0 up to at most 90"]),
    "graded nodes not increasing": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_i_deg": [0, 60, 30, 85]}))], ["bake.theta_i_deg", "increasing"]),
    "graded nodes and a step": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_i_deg": [0, 45, 80, 90], "theta_i_step_deg": 10}))], ["theta_i_deg and theta_i_step_deg"]),
    "graded nodes, wrong cone bin count": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_o_layout": "cone", "n_theta_o": 36, "theta_i_deg": [0, 45, 80, 90]}))],
        ["n_theta_o: 36", "at 0, 45, 80, 90 deg", "11, 17"]),
    "graded nodes closer than the cone bin": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={
        "theta_o_layout": "cone", "n_theta_o": 11, "theta_i_deg": [0, 45, 88, 90], "cone_bin_deg": 2.5}))],
        ["cone_bin_deg", "narrowest", "2 deg"]),
    "odd uniform bin count": (lambda tmp: ["bake", str(config(tmp, **BUNDLE, bake={"n_theta_o": 35}))],
                              ["n_theta_o", "even", "theta_o_layout: cone"]),
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
    "CSV radii not the fiber's": (lambda tmp: ["bake", str(csv_of_other_radii(tmp))],
                                  ["fibers.csv", "2 of 3 fibers", "fiber.radius_um = 3 um", "one radius"]),
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
        from pipeline.stages import export as export_stage
        from pipeline.stages import train as train_stage
        root2 = tmp_path / "other"
        shutil.copytree(art / "n" / "bake", root2 / "n" / "bake")
        train_stage.run(other, root2)
        export_stage.run(other, root2)
        shutil.copy(root2 / "n" / "export" / "tiny" / "model.onnx", art / "n" / "export" / "tiny" / "model.onnx")
        words = ["model.onnx", "different settings"]
    argv = ["--artifacts", str(art), stage, str(tmp_path / "n.yaml"), "--set", "render.backends=[onnx]",
            "--set", "render.model=tiny"]
    assert_refused_cleanly(argv, art, words, capsys)



# -- the machine: a second run of one config, a full disk, a read-only one ------------
def test_a_second_run_of_one_config_waits_its_turn(fiber_artifacts, tmp_path, capsys):
    """Two runs of one config would write the same artifacts: the second is refused,
    naming the first (a killed run leaves no lock: tests/test_bake_stage.py runs again
    after kill -9)."""
    from models.io import exclusive

    art = tmp_path / "art"
    shutil.copytree(fiber_artifacts, art)
    path = config(tmp_path)
    with exclusive(art / "tiny", "bcsdf bake elsewhere"):
        assert_refused_cleanly(["--artifacts", str(art), "fiber", str(path)], art,
                               ["in use by `bcsdf bake elsewhere`", "wait for it"], capsys)
    assert cli.main(["--artifacts", str(art), "fiber", str(path)]) == 0  # its turn


class SmallDisk:
    """A real 8 MB file system (tmpfs) to fill up and to make read-only. Mounting needs
    root and a machine that lets it; where it cannot, the same faults are raised where
    the artifacts' writes begin (``models.io``'s temporary files), and the test says so."""

    def __init__(self, root: Path, monkeypatch):
        import subprocess

        self.path, self._mp = root / "disk", monkeypatch
        self.path.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(self.path)], capture_output=True,
                           text=True)
        self.real = r.returncode == 0
        if not self.real:
            import warnings
            warnings.warn(f"no tmpfs ({r.stderr.strip()}): full and read-only disks simulated in models.io")

    def _raise(self, code):
        import os

        from models import io

        def fail(*args, **kwargs):
            raise OSError(code, os.strerror(code), kwargs.get("dir"))
        for name in ("mkstemp", "TemporaryFile"):
            self._mp.setattr(io.tempfile, name, fail)

    def fill(self):
        import errno
        import os

        if not self.real:
            return self._raise(errno.ENOSPC)
        fd = os.open(self.path / "filler", os.O_WRONLY | os.O_CREAT)
        try:
            while True:
                os.write(fd, bytes(65536))
        except OSError as e:
            assert e.errno == errno.ENOSPC
        finally:
            os.close(fd)

    def free(self):
        if self.real:
            (self.path / "filler").unlink()
        else:
            self._mp.undo()

    def read_only(self):
        import errno
        import subprocess

        if not self.real:
            return self._raise(errno.EROFS)
        subprocess.run(["mount", "-o", "remount,ro", str(self.path)], check=True)

    def close(self):
        if self.real:
            import subprocess
            subprocess.run(["umount", "-l", str(self.path)], check=True)


@pytest.fixture
def small_disk(tmp_path, monkeypatch):
    disk = SmallDisk(tmp_path, monkeypatch)
    yield disk
    disk.close()


def test_a_full_disk_or_a_read_only_one_is_said_plainly_and_loses_nothing(fiber_artifacts, small_disk, tmp_path,
                                                                          capsys):
    art = small_disk.path / "art"
    shutil.copytree(fiber_artifacts, art)
    path = config(tmp_path, **BUNDLE, bake={"paths_per_phi_i": 4000, "batch_paths": 1024, "theta_i_step_deg": 45,
                                            "n_theta_o": 8, "n_phi_o": 8})
    assert cli.main(["--artifacts", str(art), "bake", str(path)]) == 0
    capsys.readouterr()

    # -- the disk fills up: the next bake cannot write its table ----------------------
    small_disk.fill()
    argv = ["--artifacts", str(art), "bake", str(path), "--set", "bake.seed=2"]
    before = snapshot(art, skip=("filler",))
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "No space left on device" in err and str(art / "tiny") in err, err
    assert snapshot(art, skip=("filler",)) == before
    assert not list(art.rglob("*.tmp"))
    small_disk.free()
    assert cli.main(argv) == 0  # space again: the same command finishes

    # -- read-only: refused before any work ---------------------------------------------
    small_disk.read_only()
    assert_refused_cleanly(["--artifacts", str(art), "bake", str(path), "--set", "bake.seed=3"], art,
                           ["Read-only file system", str(art / "tiny")], capsys)
