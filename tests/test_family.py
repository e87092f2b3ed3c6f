"""``bcsdf family``: one model of a sweep's packings, trained through the stages as a user runs
them (``bcsdf sweep``, ``bcsdf family``, ``bcsdf report``), its model file read back by
onnxruntime and held against the members' own tables (not against the stage's figures)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from models.bundle_table import BundleTable
from models.neural import bin_average, table_cells
from pipeline.loading import load_config, sweep_members
from tests.test_cli import ROOT
from tests.test_dvc import RUNNER, _covered, _imported

PACKINGS = [0.1, 0.2, 0.3]
BASE = {"wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
        "fiber": {"model": "mie", "radius_um": 3.0, "ior": {"k": 0.0}}, "tabulate": {"theta_i_step_deg": 30},
        "bundle": {"shape": "circle", "radius_um": 25.0, "seed": 1},
        "bake": {"paths_per_phi_i": 40000, "batch_paths": 8192, "theta_i_step_deg": 30, "n_theta_o": 12,
                 "n_phi_o": 24, "orders": 4},
        "train": {"models": {"s": [16, 16]}, "epochs": 300, "patience": 300},
        "render": {"width": 32, "height": 16, "spp": 2, "scenes": ["yarn"]},
        "sweep": {"bundle.packing": PACKINGS, "bundle.seed": [1, 2]},
        "family": {"held_out": [0.2], "held_out_seeds": [3]}}


def _bcsdf(tmp_path, *args, trace=False):
    env = dict(os.environ, PYTHONPATH=str(ROOT), TQDM_DISABLE="1", **({"PYTHONPROFILEIMPORTTIME": "1"} if trace else {}))
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(tmp_path / "a"), *args],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)


def _family(tmp, **bake):
    path = tmp / "fam.yaml"
    path.write_text(yaml.safe_dump({**BASE, "bake": {**BASE["bake"], **bake}}))
    r = _bcsdf(tmp, "sweep", str(path))
    assert r.returncode == 0, r.stderr[-3000:]
    r = _bcsdf(tmp, "family", str(path), trace=True)
    assert r.returncode == 0, r.stderr[-3000:]
    (tmp / "trace.err").write_text(r.stderr)
    return tmp, path, r.stdout


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """A sweep of three packings x two seeds baked with 4 orders of scattering, a third seed
    at 0.2, the family trained on 0.1 and 0.3 (0.2 held out) through the CLI, with Python's
    import trace (the stage's deps are checked below)."""
    return _family(tmp_path_factory.mktemp("family"))


@pytest.fixture(scope="module")
def plain_family(tmp_path_factory):
    """The same without orders: one output per wavelength, each with its energy gain (a model
    of orders holds a high order's gain at its limit where it is not learnt, by design)."""
    return _family(tmp_path_factory.mktemp("plain_family"), orders=0)


def test_the_family_model_holds_each_trained_packings_albedo_read_back_from_its_file(plain_family):
    """The model file, read by onnxruntime alone, at each trained packing: its albedo (its
    bin averages at 8 x 8 midpoints, the energy gain's, against the bins' solid angles) is the
    seeds' mean albedo of the members' own tables, per incident longitude and wavelength, to a
    few float32 roundings of the exported graph (~1e-6; 2e-5 leaves ten times that). The
    converse: at the held-out packing, which no gain was set on, it is not."""
    from mitsuba_ext.neural import OnnxMLP

    tmp, path, _ = plain_family
    cfg = load_config(path)
    out = tmp / "a" / "fam" / "family"
    model = OnnxMLP(out / "model.onnx")
    assert model.spec.input_range == {"packing": [0.1, 0.3]} and model.spec.orders == 0
    members = {}
    for point, m in sweep_members(cfg):
        members.setdefault(point["bundle.packing"], []).append(
            BundleTable.load(tmp / "a" / "fam" / "sweep" / m.name / "bake" / "bundle_table.npz", expand=True))
    t0 = members[0.1][0]
    cells = table_cells(t0)
    omega = t0.solid_angle.ravel()

    def albedo(p):
        S = bin_average(lambda *q: model.eval(*(np.asarray(a, np.float32) for a in q)).astype(np.float64),
                        cells, 8, np.full((len(cells), 1, 2), p))
        return (S.reshape(len(t0.phi_i), len(t0.theta_i), -1, S.shape[-1]) * omega[:, None]).sum(2)

    for p in (0.1, 0.3):
        truth = np.mean([t.scattered for t in members[p]], 0)
        np.testing.assert_allclose(albedo(p), truth, rtol=2e-5, err_msg=f"packing {p}")
    truth = np.mean([t.scattered for t in members[0.2]], 0)
    assert np.max(np.abs(albedo(0.2) / truth - 1)) > 1e-3


def test_the_family_stage_writes_its_files_summary_and_report_section(family):
    tmp, path, stdout = family
    out = tmp / "a" / "fam" / "family"
    for name in ("weights.npz", "model.onnx", "family.png", "strip.png", "direct_0.2.npz", "summary.json"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["trained"] == [0.1, 0.3] and summary["held_out"] == [0.2] and summary["members"] == 7
    assert summary["orders"] == 4 and all("worst dyed albedo error" in r for r in summary["rows"])
    assert [(r["packing"], r["set"]) for r in summary["rows"]] == [(0.1, "trained"), (0.2, "held out"),
                                                                   (0.3, "trained")]
    for r in summary["rows"]:
        assert all(np.isfinite(v) for v in r.values() if isinstance(v, float)), r
    assert len(summary["renders"]) == 1 and 0.0 <= summary["renders"][0]["FLIP vs direct table"] < 1.0
    # family.held_out_seeds draws the held-out packing once more, and no other
    sweep = tmp / "a" / "fam" / "sweep"
    assert sorted(p.name for p in sweep.glob("packing-*_seed-3")) == ["packing-0.2_seed-3"]
    held = [r for r in summary["rows"] if r["set"] == "held out"]
    assert [r["seeds"] for r in summary["rows"]] == [2, 3, 2]
    # the direct table at the held-out packing is the mean of all its seeds
    direct = BundleTable.load(out / "direct_0.2.npz")
    seeds = [BundleTable.load(p, expand=True) for p in sorted(sweep.glob("packing-0.2_*/bake/bundle_table.npz"))]
    assert len(seeds) == 3 and len(held) == 1
    # a table's values are stored as float16 times a power of two that puts its largest at
    # 2^15: rounded to 2^-11 relative, and below float16's normal range to steps of 2^-24 of
    # that scale (max 2^-39); a few steps for the two seeds' roundings and the mean's
    top = float(np.max(direct.values))
    np.testing.assert_allclose(direct.values, np.mean([s.values for s in seeds], 0), rtol=2.0**-11,
                               atol=4 * top * 2.0**-39)
    assert "[family] yarn at held-out packing 0.2" in stdout

    r = _bcsdf(tmp, "report", str(path))
    assert r.returncode == 0, r.stderr[-3000:]
    page = (tmp / "a" / "fam" / "report" / "index.html").read_text()
    assert "One model of the family" in page and "family_family.png" in page and "held out" in page


def test_the_family_stage_declares_the_code_it_runs(family):
    tmp, _, _ = family
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]["family"]["do"]["deps"]
    missing = sorted(m for m in _imported(tmp / "trace.err") - RUNNER
                     if not _covered(m, [d for d in dvc if not d.startswith("artifacts/")]))
    assert not missing, f"bcsdf family ran {missing}, which dvc.yaml's family stage does not list in its deps"


@pytest.mark.parametrize("change, says", [
    ({"sweep": {"bundle.seed": [1, 2]}}, "a sweep over them"),
    ({"family": {"held_out": [0.15]}}, "not among the sweep's bundle.packing"),
    ({"family": {"held_out": [0.3]}}, "does not extrapolate"),
    ({"family": {"held_out": [0.1, 0.2]}}, "at least two"),
    ({"sweep": {"bundle.packing": PACKINGS, "fiber.radius_um": [3.0, 4.0]}}, "one ply type"),
    ({"family": {"model": "m"}}, "not one of train.models"),
    ({"family": {"held_out": [0.2], "held_out_seeds": [2, 3]}}, "already drawn"),
    ({"family": {"held_out": [0.2], "held_out_seeds": [3, 3]}}, "named twice"),
    ({"family": {"held_out": [], "held_out_seeds": [3]}}, "need held-out packings"),
    ({"sweep": {"bundle.packing": PACKINGS}}, "a sweep over bundle.seed"),
    ({"train": {"models": {"s": [16]}, "inputs": ["offset"]}}, "leave train.inputs"),
])
def test_a_family_that_cannot_be_trained_is_refused_before_anything_runs(tmp_path, change, says):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({**BASE, **change}))
    r = _bcsdf(tmp_path, "sweep", str(path))
    assert r.returncode == 2 and says in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "a" / "bad" / "sweep").exists()


def test_a_family_before_its_sweep_names_the_command_that_bakes_it(tmp_path):
    path = tmp_path / "early.yaml"
    path.write_text(yaml.safe_dump(BASE))
    r = _bcsdf(tmp_path, "family", str(path))
    assert r.returncode == 2 and "bcsdf sweep early" in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "a" / "early" / "family" / "model.onnx").exists()
