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
