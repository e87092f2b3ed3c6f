"""The `bcsdf` command: config validation, bad input, artifacts, and nothing lost."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from models.fiber.base import FiberTable

ROOT = Path(__file__).resolve().parents[1]


def bcsdf(*args, cwd):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


def write_config(path, **fiber):
    cfg = {"wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
           "fiber": {"model": "mie", "radius_um": 3.0, **fiber},
           "tabulate": {"theta_i_step_deg": 30}}
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.parametrize("edit,key,words", [
    (lambda c: c["fiber"].update(radius_um=-1), "fiber.radius_um", "greater than 0"),
    (lambda c: c["wavelengths"].update(start_nm=100), "wavelengths.start_nm", "greater than or equal to 200"),
    (lambda c: c["wavelengths"].update(stop_nm=2500), "wavelengths.stop_nm", "less than or equal to 2000"),
    (lambda c: c["fiber"]["ior"].update(k=-0.01), "fiber.ior.k", "must be >= 0"),
    (lambda c: c["fiber"].update(radiuss=3), "fiber.radiuss", "unknown key"),
    (lambda c: c["fiber"].pop("model"), "fiber.model", "required"),
    (lambda c: c["fiber"].update(model="wave"), "fiber.model", "mie"),
    (lambda c: c["tabulate"].update(theta_i_step_deg=7), "tabulate.theta_i_step_deg", "divide 90"),
    (lambda c: c["fiber"].update(model="table"), "fiber", "table"),
    # the README's quick trial without render.model: refused before any work, not at render
    (lambda c: c.update(bundle={"radius_um": 20.0}, train={"models": {"s": [16]}}, render={"model": "small"}),
     "render.model", "not one of train.models ['s']"),
])
def test_bad_config_names_the_key(tmp_path, edit, key, words):
    cfg = {"wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
           "fiber": {"model": "mie", "radius_um": 3.0, "ior": {"k": 0.0}}, "tabulate": {"theta_i_step_deg": 30}}
    edit(cfg)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = bcsdf("fiber", str(path), cwd=ROOT)
    assert r.returncode == 2
    assert key in r.stderr and words in r.stderr, r.stderr


def test_missing_config_file(tmp_path):
    r = bcsdf("fiber", str(tmp_path / "nope.yaml"), cwd=ROOT)
    assert r.returncode == 2 and "does not exist" in r.stderr


def test_the_stages_draw_the_slices_nearest_every_15_deg():
    """A slice per node took most of the fiber stage (19 figures for 5-deg nodes): the
    fiber and bake stages draw the node nearest every 15 deg of the nodes' range, once each."""
    from pipeline.plots import slice_nodes

    def drawn(nodes_deg):
        t = np.deg2rad(np.asarray(nodes_deg, float))
        return np.rad2deg(t[slice_nodes(t)]).round(6).tolist()
    assert drawn(range(0, 91, 5)) == [0, 15, 30, 45, 60, 75, 90]
    assert drawn([0, 15, 30, 45, 60, 65, 70, 75, 80, 90]) == [0, 15, 30, 45, 60, 75, 90]
    assert drawn([0, 30, 60, 90]) == [0, 30, 60, 90]
    assert drawn([-80, -40, 0, 40, 80]) == [-80, -40, 0, 40, 80]   # a twisted ply's, no mirror
    assert drawn([30]) == [30]


@pytest.mark.parametrize("model", ["ray", "grid"])
def test_a_fiber_slice_averaged_before_the_product_is_the_same(model):
    """``slice_at_node`` averages adjacent azimuths before multiplying by the longitudinal
    lobe (which has no azimuth): the same image as averaging the full slice after (to the
    float32 lobes' rounding)."""
    from models.fiber.patterns import PatternFiber
    from models.fiber.ray import RayFiber
    from pipeline.stages.fiber import slice_at_node

    wl, nodes = np.array([450.0, 650.0]), np.deg2rad(np.arange(0, 91, 30.0))
    table = (RayFiber(wl, [1.55] * 2, [0.2, 0.0], 0.3, 0.3, 2.0, n_h=32) if model == "ray"
             else PatternFiber(wl, "grid", n_stripes_theta=6, n_stripes_phi=8, albedo=0.9)).tabulate(nodes)
    theta_o = np.linspace(-np.pi / 2, np.pi / 2, 91)
    for i in range(len(nodes)):
        full = slice_at_node(table, i, theta_o)
        n = full.shape[1] // 4
        after = full[:, : 4 * n].reshape(len(theta_o), n, 4, -1).mean(2)
        assert np.allclose(slice_at_node(table, i, theta_o, group=4), after, rtol=1e-6, atol=1e-9 * after.max())


def test_fiber_stage_end_to_end_and_failure_keeps_artifacts(tmp_path):
    cfg = write_config(tmp_path / "tiny.yaml", ior={"cauchy_a": 1.55, "k": 1e-3})
    out = tmp_path / "art"
    r = bcsdf("--artifacts", str(out), "fiber", str(cfg), cwd=ROOT)
    assert r.returncode == 0, r.stderr
    d = out / "tiny" / "fiber"
    table = FiberTable.load(d / "fiber_table.npz")
    summary = json.loads((d / "summary.json").read_text())
    assert len(list(d.glob("theta_i_*.png"))) == 4 and (d / "energy.png").stat().st_size > 1000
    E = np.asarray(summary["energy"])
    assert np.all((E > 0) & (E < 1))  # absorbing fiber
    assert table.meta["config_hash"] == summary["config_hash"]
    before = (d / "fiber_table.npz").read_bytes()

    # A table model pointing at a corrupt file fails cleanly and touches nothing
    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(b"not a table")
    cfg2 = tmp_path / "tiny2.yaml"
    c = yaml.safe_load(cfg.read_text())
    c["name"] = "tiny"
    c["fiber"] = {"model": "table", "table": {"path": str(bad), "format": "npz"}}
    cfg2.write_text(yaml.safe_dump(c))
    # another config file of the same name is refused first (tests/test_safety.py); --force gets past that
    r = bcsdf("--artifacts", str(out), "fiber", str(cfg2), cwd=ROOT)
    assert r.returncode == 2 and "holds the artifacts of tiny.yaml" in r.stderr
    r = bcsdf("--artifacts", str(out), "fiber", "--force", str(cfg2), cwd=ROOT)
    assert r.returncode == 2 and "corrupt.npz" in r.stderr
    assert (d / "fiber_table.npz").read_bytes() == before
    assert not list(d.glob(".*.tmp"))


def test_run_skips_what_is_up_to_date_and_force_reruns_it(tmp_path, monkeypatch, capsys):
    """``bcsdf run``'s bookkeeping, with stand-in stages that only write their outputs."""
    from pipeline import cli, graph

    ran = []

    class Stage:
        def __init__(self, name):
            self.name = name

        def run(self, cfg, root):
            ran.append(self.name)
            out = Path(root) / cfg.name / self.name
            out.mkdir(parents=True, exist_ok=True)
            (out / "result.txt").write_text(self.name)
            metrics = Path(root) / cfg.name / "metrics"
            metrics.mkdir(exist_ok=True)
            (metrics / f"{self.name}.json").write_text("{}")  # what dvc.yaml lists as its metrics

    monkeypatch.setattr(graph, "stage_module", Stage)
    cfg = write_config(tmp_path / "tiny.yaml")
    art = str(tmp_path / "art")
    assert cli.main(["--artifacts", art, "run", str(cfg)]) == 0
    assert ran == ["fiber", "stability", "report"]  # a config without a bundle
    ran.clear()
    assert cli.main(["--artifacts", art, "run", str(cfg)]) == 0 and ran == []
    (tmp_path / "art" / "tiny" / "stability" / "result.txt").write_text("edited by hand")
    assert cli.main(["--artifacts", art, "run", str(cfg)]) == 0 and ran == ["stability"]
    ran.clear()
    assert cli.main(["--artifacts", art, "run", str(cfg), "--force"]) == 0
    assert ran == ["fiber", "stability", "report"]
    assert "[run] fiber: forced" in capsys.readouterr().out
    # the run measured the machine's pace for its estimate, and its stamps record it
    stamp = json.loads((tmp_path / "art" / "tiny" / ".stamps" / "fiber.json").read_text())
    assert stamp["probe"] > 0 and stamp["seconds"] >= 0 and stamp["work"] > 0


def test_a_failed_stage_keeps_its_diagnosis_and_the_report_says_so(tmp_path, monkeypatch, capsys):
    """A stability check that fails: exit 2 with the failing rows printed; the table is kept
    under failed/stability/ while the last good outputs stay; the report, still written by
    `bcsdf run`, says 'stability failed', and a later success clears the record."""
    from pipeline import cli
    from pipeline.stages import stability

    cfg = write_config(tmp_path / "tiny.yaml")
    art = tmp_path / "art"
    good = [stability.at_most("case", "x", "small", 0.5, 1.0, "a limit")]
    monkeypatch.setattr(stability, "CASES", {"fine": lambda: good})
    assert cli.main(["--artifacts", str(art), "stability", str(cfg)]) == 0
    table = (art / "tiny" / "stability" / "stability.md").read_text()
    assert "a limit" in table and "pass" in table

    bad = [stability.at_most("case", "x", "small", 2.0, 1.0, "a limit")]
    monkeypatch.setattr(stability, "CASES", {"fine": lambda: good, "broken": lambda: bad})
    assert cli.main(["--artifacts", str(art), "run", str(cfg), "--force"]) == 2  # CASES changed, not its file
    err = capsys.readouterr().err
    assert "1 of 2 stability checks failed" in err and "FAIL case" in err
    failed = art / "tiny" / "failed" / "stability"
    assert "stability checks failed" in (failed / "reason.txt").read_text()
    assert "**FAIL**" in (failed / "stability.md").read_text()
    assert json.loads((failed / "stability.json").read_text())[1]["passed"] is False
    assert (art / "tiny" / "stability" / "stability.md").read_text() == table  # the last good one
    page = (art / "tiny" / "report" / "index.html").read_text()
    assert "stability failed" in page and "FAIL" in page

    monkeypatch.setattr(stability, "CASES", {"fine": lambda: good})
    assert cli.main(["--artifacts", str(art), "stability", str(cfg)]) == 0
    assert not failed.exists()


def test_the_stage_graph_follows_dvc_yaml_and_refuses_a_broken_one(tmp_path, monkeypatch):
    """``dvc.yaml`` is parsed once per version of its text: an edit is seen at once, and a
    file that is not YAML or lacks the stage is refused with what to do."""
    from pipeline import graph
    from pipeline.loading import load_config

    cfg = load_config(write_config(tmp_path / "tiny.yaml"))
    dvc = tmp_path / "dvc.yaml"
    dvc.write_text((ROOT / "dvc.yaml").read_text())
    monkeypatch.setattr(graph, "DVC_YAML", dvc)
    assert graph.spec("fiber", cfg)["params"] == graph.spec("fiber", cfg)["params"] != []
    text = yaml.safe_load(dvc.read_text())
    text["stages"]["fiber"]["do"]["params"] = [{"${item}.yaml": ["fiber"]}]
    dvc.write_text(yaml.safe_dump(text))
    assert graph.spec("fiber", cfg)["params"] == ["fiber"]
    for broken in ("stages: [unclosed", "stages: {}"):
        dvc.write_text(broken)
        with pytest.raises(ValueError, match="restore dvc.yaml"):
            graph.spec("fiber", cfg)


def test_the_estimate_follows_the_machines_pace(tmp_path, monkeypatch):
    """A stage's rate is scaled by the pace now over the pace it was measured at: its last
    run's (a stamp's probe), or the reference machine's; a stamp without one, unscaled."""
    from pipeline import estimate, graph
    from pipeline.loading import load_config

    cfg = load_config(ROOT / "configs" / "default.yaml")
    w = estimate.work("train", cfg)
    path = graph.stamp_path("train", cfg, tmp_path)
    path.parent.mkdir(parents=True)
    monkeypatch.setattr(estimate, "_PROBE", [0.02])  # twice as slow as the stamp's run
    path.write_text(json.dumps({"seconds": 3.0 + 100.0, "work": w, "probe": 0.01}))
    seconds, source = estimate.estimate("train", cfg, tmp_path)
    assert seconds == pytest.approx(3.0 + 200.0) and "last run here, pace x2.00" in source
    path.write_text(json.dumps({"seconds": 3.0 + 100.0, "work": w}))
    assert estimate.estimate("train", cfg, tmp_path)[0] == pytest.approx(103.0)
    path.unlink()
    seconds, source = estimate.estimate("train", cfg, tmp_path)
    pace = 0.02 / estimate.PROBE_REFERENCE
    assert seconds == pytest.approx(3.0 + w * estimate.REFERENCE["train"] * pace) and "reference" in source
    # and the probe is a real measurement, milliseconds of work
    monkeypatch.setattr(estimate, "_PROBE", [])
    assert 1e-4 < estimate.probe() < 1.0 and estimate.measured_probe() == estimate.probe()


def test_atomic_writes_keep_the_old_file_on_failure_and_give_the_usual_mode(tmp_path):
    """A failed write leaves the earlier artifact as it was; a new one is readable like any
    file the process creates (0666 less the umask), not mkstemp's private 0600."""
    import os
    import stat

    from models.io import atomic_path, write_text

    path = tmp_path / "a.txt"
    write_text(path, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old" and os.listdir(tmp_path) == ["a.txt"]
    write_text(tmp_path / "b.txt", "new")
    (tmp_path / "c.txt").write_text("plain")
    mode = stat.S_IMODE(os.stat(tmp_path / "b.txt").st_mode)
    assert mode == stat.S_IMODE(os.stat(tmp_path / "c.txt").st_mode), oct(mode)


def test_ctrl_c_inside_a_traced_loop_is_an_interruption(tmp_path, monkeypatch, capsys):
    """Dr.Jit re-raises a Ctrl-C that lands in ``dr.while_loop`` as a RuntimeError from it:
    still exit 130 with the interruption message, not a traceback."""
    from pipeline import cli, graph

    class Stage:
        def run(self, cfg, root):
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as e:
                raise RuntimeError("dr.while_loop(): encountered an exception (see above).") from e

    monkeypatch.setattr(graph, "stage_module", lambda name: Stage())
    assert cli.main(["--artifacts", str(tmp_path / "art"), "fiber", str(write_config(tmp_path / "t.yaml"))]) == 130
    assert "interrupted" in capsys.readouterr().err

    class Failing:
        def run(self, cfg, root):
            raise RuntimeError("a real bug")

    monkeypatch.setattr(graph, "stage_module", lambda name: Failing())
    with pytest.raises(RuntimeError, match="a real bug"):  # other errors are not swallowed
        cli.main(["--artifacts", str(tmp_path / "art"), "fiber", str(tmp_path / "t.yaml")])
