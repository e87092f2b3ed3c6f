"""The whole pipeline on a tiny config, end to end, and its report."""

import copy
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml

from tests.test_cli import ROOT

TINY = {
    "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
    "fiber": {"model": "mie", "radius_um": 3.0, "ior": {"k": 1e-3}, "mie": {"roughness_deg": 5.0}},
    "tabulate": {"theta_i_step_deg": 15},
    "bundle": {"shape": "circle", "radius_um": 20.0, "seed": 1},
    "bake": {"paths_per_phi_i": 20000, "batch_paths": 8192, "theta_i_step_deg": 30, "n_theta_o": 12,
             "n_phi_o": 16},
    "train": {"models": {"s": [8], "m": [16, 16]}, "epochs": 20, "batch_size": 256},
    "render": {"width": 32, "height": 16, "spp": 4, "mono_check_size": [16, 8], "mono_check_spp": 4,
               "explicit_spp": 4},
    "report": {"queries": 5000},
}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """``bcsdf run`` of the tiny config, once for this module's tests: (artifacts, its stderr)."""
    tmp = tmp_path_factory.mktemp("pipeline")
    cfg = tmp / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    art = tmp / "art"
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(art), "run", str(cfg)],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return art, r.stderr


def test_run_writes_every_stage_and_a_complete_report(tiny_run):
    art, stderr = tiny_run
    # a log, not a terminal: progress bars print on a 30 s clock, not once per epoch or batch
    assert stderr.count("%|") < 60, stderr.count("%|")
    root = art / "tiny"
    for f in ("fiber/fiber_table.npz", "bake/bundle_table.npz", "train/m/model.pt", "export/m/model.onnx",
              "export/s/weights.npz", "render/summary.json", "render/ply_side_by_side.png",
              "report/index.html", "export/error_vs_time.png", "report/export_error_vs_time.png",
              "metrics/train.json", "metrics/loss/m.csv"):
        assert (root / f).exists(), f
    page = (root / "report" / "index.html").read_text()
    images = re.findall(r'<img src="([^"]+)"', page)
    assert len(images) >= 12
    for name in images:
        assert (root / "report" / name).stat().st_size > 300, name  # tiny renders make small PNGs
    assert "missing picture" not in page and "Not run yet" not in page
    # the summary on top: a model named, with its error, and every stage's time
    top = page[page.index("<h2>Summary</h2>"): page.index("<h2>Single-fiber model</h2>")]
    assert "Model to render with" in top and "held-out relative L1" in top
    assert all(f"<td>{stage}</td>" in top for stage in ("fiber", "bake", "train", "export", "render"))
    assert "-0.0000" not in page
    for word in ("Single-fiber model", "Bundle and baked table", "Neural compression", "Versions and config",
                 "mitsuba"):
        assert word in page
    assert np.isfinite(float(re.search(r"total ([0-9.]+)", page).group(1)))


def test_run_skips_up_to_date_stages_and_reruns_what_changed(tiny_run, tmp_path):
    """On a copy of the first test's artifacts (stamps hold paths relative to the artifacts
    folder, so a copy is as up to date as its original). ``--force`` is left to test_cli."""
    import shutil

    art = tmp_path / "art"
    shutil.copytree(tiny_run[0], art)
    cfg = tmp_path / "tiny.yaml"
    data = copy.deepcopy(TINY)
    cfg.write_text(yaml.safe_dump(data))

    def run(*extra):
        r = subprocess.run([sys.executable, "-m", "pipeline.cli", "--artifacts", str(art), "run", str(cfg), *extra],
                           cwd=ROOT, capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stdout
    table_mtime = (art / "tiny" / "bake" / "bundle_table.npz").stat().st_mtime_ns
    out = run()
    for stage in ("fiber", "bake", "train", "export", "render", "stability", "report"):
        assert f"[run] {stage}: up to date, skipped" in out
    # a training parameter changes: train, export, render and report rerun, the bake does not
    data["train"]["epochs"] += 1
    cfg.write_text(yaml.safe_dump(data))
    out = run()
    assert "[run] bake: up to date" in out and "[train]" in out and "[export]" in out and "[report]" in out
    assert "[render]" in out
    assert (art / "tiny" / "bake" / "bundle_table.npz").stat().st_mtime_ns == table_mtime
    # an output gone: its stage is not up to date, whatever its stamp says
    (art / "tiny" / "report" / "index.html").unlink()
    out = run()
    assert "[run] render: up to date" in out
    assert re.search(r"\[run\] report: \S*report (changed since the stage wrote it|is gone)", out), out
    assert (art / "tiny" / "report" / "index.html").exists()


def test_report_loads_in_headless_chromium(tiny_run, tmp_path):
    """The page loads in a real browser and every picture it references is shown."""
    import shutil

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    assert chromium, "chromium is installed by scripts/setup.sh for the tests"
    art, _ = tiny_run
    page = art / "tiny" / "report" / "index.html"
    r = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                        "--disable-background-networking", "--disable-component-update", "--disable-sync",
                        f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000", "--dump-dom",
                        page.as_uri()], capture_output=True, text=True, timeout=120)
    dom = r.stdout
    images = re.search(r'data-images="(\d+)"', dom)
    broken = re.search(r'data-broken="(\d+)"', dom)
    assert images and broken, dom[-1000:] + r.stderr[-1000:]
    assert int(images.group(1)) >= 12 and int(broken.group(1)) == 0
