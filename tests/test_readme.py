"""The README's promises, tried as printed: its snippets run, its commands work.

The commands that bake and train (the quick trial, a ply of one's own) take a minute or
two each: they are ``slow`` tests, which ``.ci/run`` runs on every landing
(``make test-slow``), each in a copy of the repository's files.
"""

import re
import shlex
import sys
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def block(after: str, language: str, index: int = 0) -> str:
    """The ``index``-th fenced ``language`` block after the heading or words ``after``."""
    text = README[README.index(after):]
    for _ in range(index + 1):
        text = text[text.index(f"```{language}") + len(f"```{language}"):]
    return text[: text.index("```")]


def test_the_neural_snippet_runs_as_printed(trained, tmp_path, monkeypatch, mi_llvm):
    _, art = trained
    dst = tmp_path / "artifacts" / "default" / "export" / "small"
    dst.mkdir(parents=True)
    for name in ("model.onnx", "weights.npz"):
        shutil.copy(art / "n" / "export" / "tiny" / name, dst / name)
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(block("## Neural compression", "python"), "README.md", "exec"), scope)
    S, S_jit = scope["S"], scope["S_jit"]
    assert S.shape == S_jit.shape == (2, 3) and np.all(np.isfinite(S)) and np.all(S >= 0)
    assert np.allclose(S, S_jit, rtol=1e-3)  # two float32 backends (tests/test_neural.py bounds it)


def _clone(tmp_path) -> Path:
    """The repository's tracked files, with this checkout's virtual environment."""
    repo = tmp_path / "clone"
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split()
    for f in files:
        if (ROOT / f).is_file():
            (repo / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, repo / f)
    (repo / ".venv").symlink_to(ROOT / ".venv")
    return repo


def _commands(text: str) -> list[str]:
    """Shell lines of a bash block, continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", text)
    return [line.split("  #")[0].strip() for line in joined.splitlines() if line.strip()
            and not line.strip().startswith("#")]


def _run(line: str, cwd: Path) -> subprocess.CompletedProcess:
    # the clone's .venv/bin/bcsdf is this checkout's editable install: run the clone's code instead
    args = shlex.split(line.replace("$PWD", str(cwd)))
    if args[0] == ".venv/bin/bcsdf":
        args = [str(ROOT / ".venv" / "bin" / "python"), "-m", "pipeline.cli", *args[1:]]
    env = {"PATH": "/usr/bin:/bin", "HOME": str(cwd), "TQDM_DISABLE": "1", "PYTHONPATH": str(cwd)}
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_the_quick_trial_runs_as_printed(tmp_path):
    repo = _clone(tmp_path)
    (line,) = _commands(block("**Quick trials**", "bash"))
    t0 = time.perf_counter()
    r = _run(line, repo)
    seconds = time.perf_counter() - t0
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert (repo / "artifacts" / "trial" / "report" / "index.html").stat().st_size > 10_000
    print(f"the quick trial took {seconds:.0f} s")


@pytest.mark.slow
def test_a_ply_of_ones_own_runs_as_printed(tmp_path):
    repo = _clone(tmp_path)
    (repo / "my_ply.yaml").write_text(block("**A ply of your own**", "yaml"))
    for line in _commands(block("**A ply of your own**", "bash")):
        for part in line.split("&&"):
            r = _run(part.strip(), repo)
            assert r.returncode == 0, part + "\n" + r.stdout[-3000:] + r.stderr[-3000:]
    png = repo / "artifacts" / "my_ply.png"
    assert (repo / "artifacts" / "my_ply.exr").stat().st_size > 10_000 and png.stat().st_size > 10_000


@pytest.mark.slow
def test_the_dye_commands_and_snippet_run_as_printed(tmp_path):
    repo = _clone(tmp_path)
    for line in _commands(block("**Dyes.**", "bash")):
        r = _run(line, repo)
        assert r.returncode == 0, line + "\n" + r.stdout[-3000:] + r.stderr[-3000:]
    script = repo / "dye_snippet.py"
    script.write_text(block("**Dyes.**", "python"))
    r = _run(f"{sys.executable} {script}", repo)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    from models.bundle_table import BundleTable

    red = BundleTable.load(repo / "artifacts" / "dyed" / "red.npz")
    plain = BundleTable.load(repo / "artifacts" / "dyed" / "bake" / "bundle_table.npz")
    assert red.orders is None and plain.orders.shape[0] == 8
    s_red, s_plain = red.scattered.mean(axis=(0, 1)), plain.scattered.mean(axis=(0, 1))
    assert s_red[-1] / s_plain[-1] > 3 * s_red[0] / s_plain[0]   # red keeps red light, not blue
    from mitsuba_ext.neural import load_weights

    spec = load_weights(repo / "artifacts" / "dyed" / "export" / "small" / "weights.npz")[0]
    assert spec.orders == 8 and spec.n_outputs == 8 * len(spec.wavelength)   # the model the snippet dyes


def test_the_documents_quote_only_recorded_figures():
    """Every measured figure in README.md and docs/ is a bench's record, copied by
    ``python -m pipeline.figures``: a stale block or a figure typed by hand fails here."""
    r = subprocess.run([sys.executable, "-m", "pipeline.figures", "--check"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_the_figure_check_catches_typed_and_stale_figures(tmp_path, monkeypatch):
    from pipeline import figures
    from pipeline.bench import results

    typed = "The model is 570x smaller and renders in 301 s; FLIP\n0.066, within 3% + 3 standard errors.\n"
    found = [line for line, _ in figures.typed_figures(typed)]
    assert len(found) == 3, found  # the ratio, the time, the FLIP value; not the criterion
    assert figures.typed_figures("```\n570x\n```\n<!-- 12% -->\n`301 s`\n") == []
    monkeypatch.setattr(results, "RESULTS", tmp_path)
    results.save("probe", "| a |\n|---|\n| 1.5% |", cmd="python -m pipeline.bench.probe", folder=tmp_path)
    doc = "<!-- results: probe -->\nold\n<!-- /results -->\n"
    fresh = figures.regenerate(doc)
    assert "| 1.5% |" in fresh and "python -m pipeline.bench.probe" in fresh and fresh != doc
    assert figures.typed_figures(fresh) == []  # figures inside a block are the record's
    assert "Not measured yet" in figures.regenerate("<!-- results: never -->\n<!-- /results -->\n")
