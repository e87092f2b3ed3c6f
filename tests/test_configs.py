"""Every shipped config runs end to end, shrunk with ``--set`` (the README's promise).

The configs are run as they are but for their sizes: fewer wavelengths, paths, bins,
epochs and pixels. Every stage but ``stability`` (the same cases for every config,
``tests/test_stability.py``) runs through ``bcsdf``'s own entry point, in one process.
"""

import re

import pytest

from pipeline import cli
from tests.test_cli import ROOT

SHRINK = ["tabulate.theta_i_step_deg=30", "bake.paths_per_phi_i=2000",
          "bake.batch_paths=1024", "bake.theta_i_deg=null", "bake.theta_i_step_deg=45", "bake.phi_i_step_deg=45",
          "bake.n_phi_o=8", "train.models={s: [4]}", "train.epochs=2",
          "render.width=16", "render.height=8", "render.spp=1", "render.mono_check=false",
          "render.explicit=false", "render.model=null", "render.backends=[table, mlp]", "report.queries=1000"]
CONFIGS = sorted(p.name for p in (ROOT / "configs").glob("*.yaml"))


# the packing sweep bakes its 33 members, however small: a long check (`make test-slow`, CI)
@pytest.mark.parametrize("name", [pytest.param(n, marks=[pytest.mark.slow] if n == "packing_sweep.yaml" else [])
                                  for n in CONFIGS])
def test_shipped_config_runs_end_to_end(name, tmp_path, capsys):
    from pipeline.loading import load_config

    path = ROOT / "configs" / name
    cfg = load_config(path)
    stages = ["fiber"] + (["bake", "train", "export", "render"] if cfg.bundle is not None else []) \
        + (["cloth"] if cfg.cloth else []) + (["sweep"] if cfg.sweep else []) + (["family"] if cfg.family else []) + ["report"]
    # 4 theta_o bins a quarter of the sphere; a cone layout: a bin on each cone, one between
    shrink = SHRINK + [f"bake.n_theta_o={7 if cfg.bake.theta_o_layout == 'cone' else 8}"] \
        + (["wavelengths.count=3"] if cfg.wavelengths.count > 3 else []) \
        + (["cloth.width=24", "cloth.height=16", "cloth.spp=1", "cloth.curves=2"] if cfg.cloth else []) \
        + (["family.model=s"] if cfg.family and cfg.family.model else [])   # SHRINK's one network
    sets = [a for s in shrink for a in ("--set", s)]
    for stage in stages:
        assert cli.main(["--artifacts", str(tmp_path), stage, str(path), *sets]) == 0, capsys.readouterr().err
    page = (tmp_path / cfg.name / "report" / "index.html").read_text()
    assert "missing picture" not in page
    if cfg.bundle is not None:
        assert len(re.findall(r"<img ", page)) >= 8
    if cfg.cloth is not None and cfg.cloth.flyaways is not None:  # the hairs were drawn, rendered, measured
        import json
        fly = json.loads((tmp_path / cfg.name / "cloth" / "summary.json").read_text())["flyaways"]
        assert fly["hairs"] > 0 and -1 < fly["share"]["cloth_pixels"] < 1 and "Flyaways:" in page
    if cfg.sweep:
        family = (tmp_path / cfg.name / "sweep" / "index.html").read_text()
        assert "missing picture" not in family and 'href="../sweep/index.html"' in page
    if cfg.family:
        assert "One model of the family" in page and "family_strip.png" in page
