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


def test_the_cloth_record_names_each_parts_commands_and_refuses_a_near_field_without_cells(capsys):
    """The cloth bench's parts, and a part's distances, are measured by separate commands:
    each part's table names every command its rows came from; ``--near`` asks for at least
    two cells and the explicit part alone, refused before anything is rendered."""
    from pipeline.bench import cloth

    a = {"command": "python -m pipeline.bench.cloth --parts explicit --ply-px 4", "date": "d1", "machine": "m1"}
    b = {"command": "python -m pipeline.bench.cloth --parts explicit --ply-px 8", "date": "d2", "machine": "m2"}
    record = {"explicit": [{"ply_px": 4, "flip": 0.1, "by": a}, {"ply_px": 8, "flip": 0.2, "by": b}],
              "memory": {"table_bytes": 3, "by": a}, "explicit_near16": [{"ply_px": 4, "flip": 0.3, "by": b}]}
    text = cloth.markdown(record)
    explicit, memory, near = (block for block in text.split("\n\n**"))
    assert a["command"] in explicit and b["command"] in explicit and "d1" in explicit and "m2" in explicit
    assert a["command"] in memory and b["command"] not in memory
    assert "16 cells" in near and b["command"] in near and a["command"] not in near
    assert "| by |" not in text   # the provenance is in the titles, not a column
    for argv in (["--near", "1", "--parts", "explicit"], ["--near", "16"], ["--near", "16", "--parts", "scale"]):
        with pytest.raises(SystemExit) as refused:
            cloth.main(argv)
        assert refused.value.code == 2
        assert "--near" in capsys.readouterr().err
