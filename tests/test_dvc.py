"""`dvc repro` runs the pipeline, and a training change reruns only what depends on it.

The repository is cloned into a temporary folder (DVC needs a git repository), its
dvc.yaml pointed at a tiny config; `bcsdf` is this interpreter's `pipeline.cli`.
"""

import os
import shutil
import subprocess
import sys

import pytest

from tests.test_cli import ROOT

TINY = """\
wavelengths: {start_nm: 450, stop_nm: 650, count: 3}
fiber: {model: mie, radius_um: 3.0, ior: {k: 0.001}, mie: {roughness_deg: 5.0}}
tabulate: {theta_i_step_deg: 15}
bundle: {shape: circle, radius_um: 20.0, seed: 1}
bake: {paths_per_phi_i: 20000, batch_paths: 8192, theta_i_step_deg: 30, n_theta_o: 12, n_phi_o: 16}
train: {models: {s: [8]}, epochs: 5, batch_size: 256}
render: {width: 24, height: 12, spp: 2, scenes: [ply], mono_check: false, explicit: false}
report: {queries: 5000}
"""


def test_dvc_repro_reruns_only_what_changed(tmp_path):
    dvc = shutil.which("dvc", path=os.path.dirname(sys.executable)) or shutil.which("dvc")
    if dvc is None or not (ROOT / ".git").exists():
        pytest.fail("dvc (test extra) and a git checkout are needed for this test")
    repo = tmp_path / "repo"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(repo)], check=True)
    (repo / "configs" / "tiny.yaml").write_text(TINY)
    dvc_yaml = (repo / "dvc.yaml").read_text()
    (repo / "dvc.yaml").write_text(dvc_yaml.replace("configs/default.yaml", "configs/tiny.yaml")
                                   .replace("artifacts/default", "artifacts/tiny"))
    shim = tmp_path / "bin"
    shim.mkdir()
    (shim / "bcsdf").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m pipeline.cli "$@"\n')
    (shim / "bcsdf").chmod(0o755)
    env = dict(os.environ, PATH=f"{shim}:{os.environ['PATH']}", PYTHONPATH=str(repo), TQDM_DISABLE="1")

    def run(*args):
        r = subprocess.run([dvc, *args], cwd=repo, env=env, capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        return r.stdout
    assert (repo / ".dvc").is_dir()  # committed: `dvc repro` works on a fresh clone
    out = run("repro")
    for stage in ("fiber", "bake", "train", "export", "render", "report"):
        assert f"Running stage '{stage}'" in out
    assert (repo / "artifacts" / "tiny" / "report" / "index.html").exists()
    assert "up to date" in run("status")
    (repo / "configs" / "tiny.yaml").write_text(TINY.replace("epochs: 5", "epochs: 6"))
    out = run("repro")
    assert "Stage 'fiber' didn't change" in out and "Stage 'bake' didn't change" in out
    for stage in ("train", "export", "render", "report"):
        assert f"Running stage '{stage}'" in out
