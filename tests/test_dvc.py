"""DVC as a DVC user expects it, on a fresh clone and a tiny config.

The repository is cloned into a temporary folder (DVC needs a git repository), dvc.yaml's
config lists pointed at a tiny config, and ``.venv/bin/bcsdf`` (the stages' command) is
this interpreter's ``pipeline.cli`` with Python's import trace on, so that the test sees
every module each stage really ran and can hold it against the stage's declared deps.
"""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

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
cloth: {swatch: {courses: 2, wales: 2}, width: 24, height: 16, spp: 2, max_depth: 4}
"""
STAGES = ("fiber", "bake", "train", "export", "render", "cloth", "stability", "report")
RUNNER = {"pipeline", "pipeline.cli", "pipeline.graph", "pipeline.stages", "pipeline.estimate", "models", "mitsuba_ext"}  # the runner


def _clone(tmp_path):
    dvc = shutil.which("dvc", path=os.path.dirname(sys.executable)) or shutil.which("dvc")
    if dvc is None or not (ROOT / ".git").exists():
        pytest.fail("dvc (test extra) and a git checkout are needed for this test")
    repo = tmp_path / "repo"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(repo)], check=True)
    for path in ("dvc.yaml", "pipeline", "models", "mitsuba_ext", "configs"):  # this working tree's state
        src, dst = ROOT / path, repo / path
        if src.is_dir():
            shutil.rmtree(dst)
            shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(src, dst)
    (repo / "configs" / "tiny.yaml").write_text(TINY)
    text = (repo / "dvc.yaml").read_text()
    text = re.sub(r"  - configs: \[[^\]]*\]", "  - configs: [tiny]", text)
    text = re.sub(r"  - bundles: \[[^\]]*\]", "  - bundles: [tiny]", text)
    text = re.sub(r"  - fibers_only: \[[^\]]*\]", "  - fibers_only: []", text)
    text = re.sub(r"  - sweeps: \[[^\]]*\]", "  - sweeps: []", text)
    text = re.sub(r"  - families: \[[^\]]*\]", "  - families: []", text)
    text = re.sub(r"  - cloths: \[[^\]]*\]", "  - cloths: [tiny]", text)
    text = re.sub(r"  - plain_bundles: \[[^\]]*\]", "  - plain_bundles: []", text)
    (repo / "dvc.yaml").write_text(text)
    trace = tmp_path / "trace"
    trace.mkdir()
    (repo / ".venv" / "bin").mkdir(parents=True)
    shim = repo / ".venv" / "bin" / "bcsdf"
    shim.write_text(f'#!/bin/sh\nPYTHONPROFILEIMPORTTIME=1 exec "{sys.executable}" -m pipeline.cli "$@" '
                    f'2>> "{trace}/$1.err"\n')
    shim.chmod(0o755)
    env = dict(os.environ, PYTHONPATH=str(repo), TQDM_DISABLE="1")

    def run(*args, ok=True):
        r = subprocess.run([dvc, *args], cwd=repo, env=env, capture_output=True, text=True, timeout=900)
        if ok:
            logs = "".join(f"\n--- {p.name}\n" + p.read_text()[-1500:] for p in trace.glob("*.err"))
            assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:] + logs
        return r
    return repo, trace, env, run


def _imported(err_log: Path) -> set:
    """Project modules in a ``-X importtime`` log."""
    names = re.findall(r"\|\s*((?:pipeline|models|mitsuba_ext)(?:\.\w+)*)\s*$", err_log.read_text(), re.M)
    return set(names)


def _covered(module: str, deps: list) -> bool:
    path = module.replace(".", "/")
    return any(path == d.removesuffix(".py") or path.startswith(d.rstrip("/") + "/") for d in deps)


def _stale(run) -> set:
    out = run("status", "--json").stdout
    names = {name.split("@")[0] for name in json.loads(out or "{}")}
    return {"report" if n == "report_cloth" else n for n in names}  # the tiny config's report reads its cloth


@pytest.mark.slow   # about two minutes (DVC runs each stage as its own process): `make test-slow`, CI
def test_dvc_pipeline_deps_metrics_and_staleness(tmp_path):
    repo, trace, env, run = _clone(tmp_path)
    assert (repo / ".dvc").is_dir()  # committed: `dvc repro` works on a fresh clone

    # -- the whole pipeline of the tiny config, each stage once --------------------------
    out = run("repro", "report_cloth@tiny").stdout
    for stage in STAGES:
        assert f"Running stage '{'report_cloth' if stage == 'report' else stage}@tiny'" in out
    assert (repo / "artifacts" / "tiny" / "report" / "index.html").exists()
    assert _stale(run) == set()

    # -- every module a stage ran is among its declared deps ---------------------------
    stages = yaml.safe_load((repo / "dvc.yaml").read_text())["stages"]
    for stage in STAGES:
        deps = [d for d in stages[stage]["do"]["deps"] if not d.startswith("artifacts/")]
        assert f"pipeline/stages/{stage}.py" in deps or "pipeline" in deps, (stage, "its own module")
        missing = sorted(m for m in _imported(trace / f"{stage}.err") - RUNNER if not _covered(m, deps))
        assert not missing, f"stage {stage} ran {missing}, which dvc.yaml does not list in its deps"

    # -- metrics and plots --------------------------------------------------------------
    metrics = run("metrics", "show", "--json").stdout
    for key in ("passthrough", "relative_l1", "albedo_max", "passed", "ns_per_query"):
        assert key in metrics, key
    run("plots", "show", "-o", str(tmp_path / "plots"))
    page = (tmp_path / "plots" / "index.html").read_text()
    assert "loss" in page and "error_vs_time" in page

    # -- bcsdf run and DVC agree: all up to date, then the same stages stale after a code edit
    bcsdf = [sys.executable, "-m", "pipeline.cli", "run", "configs/tiny.yaml"]
    r = subprocess.run(bcsdf, cwd=repo, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.count("up to date, skipped") == len(STAGES), r.stdout + r.stderr
    with open(repo / "mitsuba_ext" / "bsdf.py", "a") as fh:
        fh.write("\n# an edit\n")
    expected = {"export", "render", "cloth", "stability", "report"}  # what runs mitsuba_ext
    assert _stale(run) == expected
    probe = ("import sys, json; from pipeline.loading import load_config; from pipeline import graph; "
             "cfg = load_config('configs/tiny.yaml'); "
             "print(json.dumps([s for s in sys.argv[1:] if not graph.up_to_date(s, cfg)[0]]))")
    r = subprocess.run([sys.executable, "-c", probe, *STAGES], cwd=repo, env=env, capture_output=True, text=True)
    assert set(json.loads(r.stdout)) == expected, r.stderr

    # -- a failing stage leaves its last good outputs -----------------------------------
    render = repo / "artifacts" / "tiny" / "render"
    before = {p.name: p.read_bytes() for p in render.iterdir() if p.is_file()}
    (repo / "configs" / "tiny.yaml").write_text(TINY.replace("width: 24", "width: -24"))
    r = run("repro", "render@tiny", ok=False)
    assert r.returncode != 0
    assert {p.name: p.read_bytes() for p in render.iterdir() if p.is_file()} == before

    # -- a config change makes stale the stage that reads it, and only that, for both tools
    # (the stages after it follow once its outputs change: DVC's own rule, and bcsdf run's,
    # tests/test_pipeline.py). The code edit is undone first: only the config differs.
    shutil.copy(ROOT / "mitsuba_ext" / "bsdf.py", repo / "mitsuba_ext" / "bsdf.py")
    (repo / "configs" / "tiny.yaml").write_text(TINY.replace("epochs: 5", "epochs: 6"))
    expected = {"train"}
    assert _stale(run) == expected
    r = subprocess.run([sys.executable, "-c", probe, *STAGES], cwd=repo, env=env, capture_output=True, text=True)
    assert set(json.loads(r.stdout)) == expected, r.stderr

    # -- and the other way: `bcsdf run` records DVC's lock, so that DVC agrees it is up to date
    # (an edit of the cloth section: only the cloth and the report run again, the cheap end)
    (repo / "configs" / "tiny.yaml").write_text(TINY.replace("spp: 2, max_depth", "spp: 3, max_depth"))
    assert _stale(run) == {"cloth"}
    r = subprocess.run(bcsdf, cwd=repo, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "[run] cloth: its code, config or inputs changed" in r.stdout, r.stdout + r.stderr
    assert "[run] train: up to date, skipped" in r.stdout and "dvc.lock: recorded" in r.stdout, r.stdout
    assert _stale(run) == set()
    # a run with --set is not what dvc.yaml's params say: it records nothing
    r = subprocess.run(bcsdf + ["--set", "cloth.spp=4"], cwd=repo, env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0 and "dvc.lock" not in r.stdout, r.stdout + r.stderr
    assert "cloth" in _stale(run)  # its outputs are no longer what the lock recorded


def test_shipped_configs_match_dvc_yaml():
    """Every config is a DVC stage; each spells out the sections its stages track."""
    from pipeline.loading import load_config

    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    lists = {k: v for entry in dvc["vars"] for k, v in entry.items()}
    shipped = {p.stem: p for p in sorted((ROOT / "configs").glob("*.yaml"))}
    assert set(lists["configs"]) == set(shipped)
    with_bundle = {n for n, p in shipped.items() if load_config(p).bundle is not None}
    assert set(lists["bundles"]) == with_bundle
    assert set(lists["fibers_only"]) == set(shipped) - with_bundle
    assert set(lists["sweeps"]) == {n for n, p in shipped.items() if load_config(p).sweep}
    assert set(lists["cloths"]) == {n for n, p in shipped.items() if load_config(p).cloth is not None}
    assert set(lists["families"]) == {n for n, p in shipped.items() if load_config(p).family is not None}
    assert set(lists["plain_bundles"]) == with_bundle - set(lists["cloths"]) - set(lists["families"])
    for name, path in shipped.items():
        assert load_config(path).name == name, f"{path}: its name must be its file's stem (artifacts/<name>)"
        keys = set(yaml.safe_load(path.read_text()))
        for stage, spec in dvc["stages"].items():
            if name not in lists[spec["foreach"].strip("${}")]:
                continue
            for entry in spec["do"].get("params", []):
                tracked = {key.split(".")[0] for key in next(iter(entry.values()))}
                assert tracked <= keys, f"{path} lacks {set(tracked) - keys}, which stage {stage} tracks"

