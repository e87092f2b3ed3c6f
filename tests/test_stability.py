"""Every case of ``bcsdf stability`` is a test: it must pass, and say by how much if not."""

import pytest

from pipeline.stages.stability import CASES, Check, at_most


@pytest.mark.parametrize("name", list(CASES))
def test_stability_case(name):
    checks = CASES[name]()
    assert checks, "a case must check something"
    failed = [c.line() for c in checks if not c.passed]
    assert not failed, "\n".join(failed)


def test_a_failing_check_says_what_and_by_how_much():
    c = at_most("case", "|x - 1|", "agrees", 0.5, 1e-3)
    assert not c.passed and "FAIL" in c.line() and "5.000e-01" in c.line()
    assert not at_most("case", "x", "finite", float("nan"), 1.0).passed  # NaN never passes
    assert isinstance(c, Check)


def test_the_stage_runs_the_cases_once_per_code_and_machine(tmp_path, monkeypatch, capsys):
    """The cases read no config: a second config's stage reuses the first's rows (the same
    table), and a change of the code runs them again."""
    from pipeline.stages import stability
    from tests.synthetic import make_config

    ran = []
    monkeypatch.setattr(stability, "run_cases", lambda: ran.append(1) or [at_most("c", "x", "small", 0.5, 1.0)])
    a, b = make_config(tmp_path, name="a"), make_config(tmp_path, name="b")
    stability.run(a, tmp_path)
    stability.run(b, tmp_path)
    assert len(ran) == 1 and "reused" in capsys.readouterr().out
    assert (tmp_path / "a" / "stability" / "stability.json").read_text() == \
        (tmp_path / "b" / "stability" / "stability.json").read_text()
    monkeypatch.setattr(stability.graph, "digest", lambda paths, root: "other code")
    stability.run(b, tmp_path)
    assert len(ran) == 2


def test_failed_checks_are_not_kept_for_other_configs(tmp_path, monkeypatch):
    from pipeline.artifacts import StageFailed
    from pipeline.stages import stability
    from tests.synthetic import make_config

    monkeypatch.setattr(stability, "run_cases", lambda: [at_most("c", "x", "small", 2.0, 1.0)])
    cfg = make_config(tmp_path, name="a")
    with pytest.raises(StageFailed):
        stability.run(cfg, tmp_path)
    assert not stability.shared_result(cfg, tmp_path).exists()
