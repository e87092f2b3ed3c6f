"""What a bench records (``pipeline.bench.results``): the text it printed, when it finished."""

import json

import pytest

from pipeline.bench import results


def test_a_bench_that_exits_with_success_is_recorded_and_one_that_fails_is_not(tmp_path):
    """``raise SystemExit(main())`` inside ``recorded`` (the render, closure, cluster and
    highlight benches end so): a code of 0 or None is a finished run, recorded, and the exit
    goes on; any other code is a failure, not recorded; a ``--quick`` run is never recorded."""
    with pytest.raises(SystemExit) as done:
        with results.recorded("ok", folder=tmp_path):
            print("| row | 1.5 |")
            raise SystemExit(0)
    assert done.value.code == 0
    assert "| row | 1.5 |" in json.loads((tmp_path / "ok.json").read_text())["markdown"]
    with pytest.raises(SystemExit):
        with results.recorded("failed", folder=tmp_path):
            raise SystemExit(2)
    with results.recorded("quick", smoke=True, folder=tmp_path):
        print("a smoke run")
    assert not (tmp_path / "failed.json").exists() and not (tmp_path / "quick.json").exists()
