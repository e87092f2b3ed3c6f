"""Sweeps: every member is its own bake, bit for bit; bad axes are refused before any work.

A member's table is held against an independent ``bcsdf bake`` of the member's config
(not against another sweep); the Monte Carlo errors the family page prints are held
against the scatter of independent bakes.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from models.bundle_table import BundleTable
from pipeline.stages import bake as bake_stage
from pipeline import cli
from pipeline.stages import fiber as fiber_stage
from pipeline.loading import load_config, sweep_members
from tests.test_cli import ROOT
from tests.test_dvc import RUNNER, _covered, _imported

BASE = {"wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
        "fiber": {"model": "mie", "radius_um": 3.0, "ior": {"k": 1e-3}}, "tabulate": {"theta_i_step_deg": 30},
        "bundle": {"shape": "circle", "radius_um": 25.0, "seed": 1},
        "bake": {"paths_per_phi_i": 8000, "batch_paths": 2048, "theta_i_step_deg": 30, "n_theta_o": 12,
                 "n_phi_o": 24, "checkpoint_every_s": 0.01}}


def _config(tmp_path, sweep, name="fam"):
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump({**BASE, "sweep": sweep}))
    return path


def _table(root, member):
    return BundleTable.load(root / member / "bake" / "bundle_table.npz")


def _same(a, b):
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("values", "stderr", "passthrough", "absorbed",
                                                                                      "single"))


def test_a_sweep_on_a_cluster_bakes_each_member_as_its_own_bake_and_resumes(tmp_path, capsys, monkeypatch):
    path = _config(tmp_path, {"bundle.packing": [0.2, 0.3], "bundle.seed": [1, 2]})
    cfg = load_config(path)
    root = tmp_path / "a" / "fam" / "sweep"

    # -- Ctrl-C as the second member is written: the first is kept, the others resume ---
    finish, written = bake_stage.Bake.finish, []

    def finish_then_interrupt(self):
        if written:
            raise KeyboardInterrupt
        written.append(self.cfg.name)
        return finish(self)

    monkeypatch.setattr(bake_stage.Bake, "finish", finish_then_interrupt)
    assert cli.main(["--artifacts", str(tmp_path / "a"), "sweep", str(path), "--workers", "2"]) == 130
    monkeypatch.undo()
    members = [m for _, m in sweep_members(cfg)]
    assert [m.name for m in members] == ["packing-0.2_seed-1", "packing-0.2_seed-2", "packing-0.3_seed-1",
                                         "packing-0.3_seed-2"]
    tables = {m.name for m in members if (root / m.name / "bake" / "bundle_table.npz").exists()}
    assert tables == set(written)
    kept = (root / written[0] / "bake" / "bundle_table.npz").read_bytes()
    resumed = [m.name for m in members if (root / m.name / "bake" / "checkpoint.npz").exists()]
    assert resumed
    capsys.readouterr()
    assert cli.main(["--artifacts", str(tmp_path / "a"), "sweep", str(path)]) == 0  # here, not on the cluster
    out = capsys.readouterr().out
    assert "1 up to date, 3 to bake" in out and f"{resumed[0]}: resuming from checkpoint" in out
    assert (root / written[0] / "bake" / "bundle_table.npz").read_bytes() == kept  # not baked again

    # -- a member's table is a plain serial bake of the member's config, bit for bit: the
    # one the cluster finished, and one resumed from the cluster's checkpoint here ------
    for m in members:
        if m.name in (written[0], resumed[0]):
            fiber_stage.run(m, tmp_path / "serial")
            bake_stage.run(m, tmp_path / "serial")
            assert _same(_table(root, m.name), _table(tmp_path / "serial", m.name)), m.name

    # -- the family: every picture there, the seeds' spread beside the MC error -----------
    page = (root / "index.html").read_text()
    assert "missing picture" not in page and page.count("<img ") == 2 + 1 + len(members)
    assert "Arrangement against Monte Carlo" in page
    family = json.loads((root / "family.json").read_text())
    assert [r["member"] for r in family["members"]] == [m.name for m in members]
    for r in family["members"]:  # packing as asked, the arrangement drawn for it
        assert abs(r["packing_fraction"] - r["bundle.packing"]) < 0.05
    p = {r["bundle.packing"]: r["passthrough_mean"] for r in family["seed_spread"]}
    assert p[0.3] < p[0.2]  # denser plies let less light through
    assert json.loads((tmp_path / "a" / "fam" / "metrics" / "sweep.json").read_text())["members"] == 4

    # -- run again: every member up to date, nothing baked ---------------------------------
    assert cli.main(["--artifacts", str(tmp_path / "a"), "sweep", str(path)]) == 0
    assert "4 up to date, 0 to bake" in capsys.readouterr().out


def test_mc_errors_match_the_scatter_of_independent_bakes_and_deps_are_declared(tmp_path):
    """Six bakes that differ only in their random numbers (``bake.seed``): their albedos
    and passthroughs scatter as the errors each bake reports from its batches say (a
    binomial error would overstate the passthrough's: paths are stratified). Run through
    ``bcsdf sweep`` with Python's import trace, which also checks the sweep stage's deps."""
    path = _config(tmp_path, {"bake.seed": [1, 2, 3, 4, 5, 6]}, name="mc")
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONPROFILEIMPORTTIME="1", TQDM_DISABLE="1")
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(tmp_path / "a"), "sweep", str(path)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = json.loads((tmp_path / "a" / "mc" / "sweep" / "family.json").read_text())["members"]
    for q in ("albedo", "passthrough"):
        spread = np.std([x[q] for x in rows], ddof=1)
        predicted = np.sqrt(np.mean([x[f"{q}_mc_error"] ** 2 for x in rows]))
        # 5 degrees of freedom: the ratio lies in [0.48, 1.49] 95% of the time (the binomial
        # error of the passthrough gives 0.44 here, the albedo's bins in quadrature 0.08)
        assert 0.48 < spread / predicted < 1.49, (q, spread, predicted)

    (tmp_path / "trace.err").write_text(r.stderr)
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]["sweep"]["do"]["deps"]
    missing = sorted(m for m in _imported(tmp_path / "trace.err") - RUNNER
                     if not _covered(m, [d for d in dvc if not d.startswith("artifacts/")]))
    assert not missing, f"bcsdf sweep ran {missing}, which dvc.yaml's sweep stage does not list in its deps"


@pytest.mark.parametrize("sweep, says", [
    ({"bundle.pakcing": [0.2]}, ["pakcing-0.2", "bundle.pakcing", "unknown key"]),
    ({"bundle.seed": [1, 2], "bundle.packing": [0.2, 0.95]}, ["packing-0.95", "bundle.packing", "0.91"]),
    ({"bundle.packing": [0.2, 0.5]}, ["sweep member packing-0.5", "packing 0.5 is not reachable"]),
    ({}, ["sweep", "empty sweep"]),
    ({"bundle.seed": []}, ["sweep", "bundle.seed", "no values"]),
    ({"bundle.seed": [1, 1]}, ["sweep", "repeats a value"]),
    ({"name": ["a", "b"]}, ["sweep", "cannot be swept"]),
])
def test_a_bad_sweep_is_refused_before_anything_is_baked(tmp_path, capsys, sweep, says):
    path = _config(tmp_path, sweep)
    assert cli.main(["--artifacts", str(tmp_path / "a"), "sweep", str(path)]) == 2
    err = capsys.readouterr().err
    assert all(s in err for s in says) and "Traceback" not in err, err
    assert not (tmp_path / "a" / "fam" / "sweep").exists()


def test_a_config_without_a_sweep_is_told_how_to_add_one(tmp_path, capsys):
    path = tmp_path / "plain.yaml"
    path.write_text(yaml.safe_dump(BASE))
    assert cli.main(["--artifacts", str(tmp_path / "a"), "sweep", str(path)]) == 2
    assert "no 'sweep:' section" in capsys.readouterr().err
