"""Bad input, second round (issue 23): nothing is written outside the artifacts root, a
stage is all or nothing, and a bake's checkpoint resumes only with the code that wrote it.

Each test fails without its mechanism (``models.io.confined``, ``models.io.journal``,
the checkpoint's code digest) and runs through ``bcsdf``'s entry point where it can.
"""

import hashlib
import os

import numpy as np
import pytest
import yaml

from pipeline import cli
from tests.test_bad_input import BASE, BUNDLE, snapshot


def write_config(tmp, **sections):
    path = tmp / "tiny.yaml"
    path.write_text(yaml.safe_dump({**BASE, **sections}))
    return path


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_lock_that_links_out_of_the_root_is_refused_and_its_target_untouched(tmp_path, capsys):
    victim = tmp_path / "precious.txt"
    victim.write_text("do not truncate me\n")
    art = tmp_path / "art"
    (art / "tiny").mkdir(parents=True)
    os.symlink(victim, art / "tiny" / ".lock")
    assert cli.main(["--artifacts", str(art), "fiber", str(write_config(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert ".lock" in err and "Traceback" not in err
    assert victim.read_text() == "do not truncate me\n"


@pytest.mark.parametrize("where", ["stage folder", "config folder"])
def test_writes_through_a_linked_folder_are_refused(tmp_path, capsys, where):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("mine\n")
    art = tmp_path / "art"
    if where == "stage folder":
        (art / "tiny").mkdir(parents=True)
        os.symlink(outside, art / "tiny" / "fiber")
    else:
        art.mkdir()
        os.symlink(outside, art / "tiny")
    assert cli.main(["--artifacts", str(art), "fiber", str(write_config(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert "outside the artifacts root" in err and "Traceback" not in err
    assert sorted(p.name for p in outside.iterdir()) == ["keep.txt"]


def test_a_stage_that_fails_late_leaves_the_earlier_set_whole(tmp_path, monkeypatch, capsys):
    """The fiber stage writes its table, summary and metrics, then its pictures: a plotting
    failure after the first writes must restore every file it replaced and remove those
    it created."""
    from pipeline.stages import fiber as fiber_stage

    art, cfg = tmp_path / "art", write_config(tmp_path)
    assert cli.main(["--artifacts", str(art), "fiber", str(cfg)]) == 0
    before = snapshot(art / "tiny", skip=(".lock",))
    # another setting, so that every output changes; the plot fails after the table is written
    cfg.write_text(yaml.safe_dump({**BASE, "fiber": {**BASE["fiber"], "radius_um": 4.0}}))

    def broken(*args, **kwargs):
        raise ValueError("a plotting backend error")

    monkeypatch.setattr(fiber_stage, "plot_energy", broken, raising=False)
    monkeypatch.setattr(fiber_stage, "save_figure", broken)
    assert cli.main(["--artifacts", str(art), "fiber", str(cfg)]) == 2
    assert "plotting backend" in capsys.readouterr().err
    after = {k: v for k, v in snapshot(art / "tiny", skip=(".lock",)).items() if not k.startswith(".stamps")}
    assert after == {k: v for k, v in before.items() if not k.startswith(".stamps")}
    assert not (art / "tiny" / ".journal").exists()


def test_a_stage_killed_mid_way_is_rolled_back_by_the_next_command(tmp_path):
    """A journal left by a killed process (files replaced, a file created) is undone before
    the next stage runs."""
    from models import io
    from models.io import journal, write_text

    folder = tmp_path / "art" / "tiny"
    old = folder / "fiber" / "summary.json"
    write_text(old, "earlier")
    killed = io._Journal(folder / ".journal")  # the stage starts ...
    killed.folder.mkdir(parents=True)
    io._JOURNAL.append(killed)
    write_text(old, "half of a new set")
    write_text(folder / "fiber" / "new.png", "new")
    io._JOURNAL.remove(killed)  # ... and its process dies here: the next command opens the journal
    with journal(folder):
        assert old.read_text() == "earlier" and not (folder / "fiber" / "new.png").exists()


def test_a_checkpoint_does_not_resume_across_a_code_change(tmp_path, monkeypatch, capsys, mi_llvm):
    from models.bundle_table import BundleTable
    from pipeline import cluster
    from pipeline.loading import load_config
    from pipeline.stages import bake as bake_stage
    from pipeline.stages import fiber as fiber_stage

    path = write_config(tmp_path, **BUNDLE, bake={"paths_per_phi_i": 20_000, "batch_paths": 2000,
                                                     "theta_i_step_deg": 30, "n_theta_o": 6, "n_phi_o": 8})
    cfg = load_config(path)
    for root in ("a", "b"):
        fiber_stage.run(cfg, tmp_path / root)
    bake_stage.run(cfg, tmp_path / "a")  # the new code alone
    real = cluster.code_digest
    monkeypatch.setattr(cluster, "code_digest", lambda c: "old code")
    bake_stage.run(cfg, tmp_path / "b", stop_after=4)  # interrupted under the old code
    monkeypatch.setattr(cluster, "code_digest", real)
    capsys.readouterr()
    bake_stage.run(cfg, tmp_path / "b")
    assert "written by other code" in capsys.readouterr().out
    ta = BundleTable.load(tmp_path / "a" / "tiny" / "bake" / "bundle_table.npz")
    tb = BundleTable.load(tmp_path / "b" / "tiny" / "bake" / "bundle_table.npz")
    assert np.array_equal(ta.values, tb.values)  # nothing of the old code's batches in it


def test_another_config_of_the_same_name_is_refused_until_forced(tmp_path, capsys):
    """Two config files with one ``name:``: the second must not write over what the first
    made (a bake can be hours); refused naming both files and ``--force``, which takes over."""
    art = tmp_path / "art"
    first = write_config(tmp_path)
    (tmp_path / "other").mkdir()
    second = tmp_path / "other" / "tiny.yaml"
    second.write_text(yaml.safe_dump({**BASE, "fiber": {**BASE["fiber"], "radius_um": 4.0}}))
    assert cli.main(["--artifacts", str(art), "fiber", str(first)]) == 0
    before = snapshot(art / "tiny", skip=(".lock",))
    capsys.readouterr()
    assert cli.main(["--artifacts", str(art), "fiber", str(second)]) == 2
    err = capsys.readouterr().err
    assert "holds the artifacts of tiny.yaml" in err and str(second) in err and "--force" in err
    assert "Traceback" not in err
    assert snapshot(art / "tiny", skip=(".lock",)) == before
    assert cli.main(["--artifacts", str(art), "fiber", str(first)]) == 0   # its own config runs on
    assert cli.main(["--artifacts", str(art), "fiber", "--force", str(second)]) == 0
    assert cli.main(["--artifacts", str(art), "fiber", str(second)]) == 0   # now its owner


def test_a_file_the_config_names_is_part_of_the_stage_by_its_content(tmp_path):
    """A user's own fiber arrangement (``bundle.file``, outside data/) rewritten in place
    makes the bake stale, though the config's text is unchanged; the fiber stage, which does
    not read it, stays as it was."""
    from pipeline import graph
    from pipeline.loading import load_config

    csv = tmp_path / "mine" / "fibers.csv"
    csv.parent.mkdir()
    csv.write_text("x_um,z_um,r_um\n0,0,3\n10,0,3\n")
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({**BASE, "bundle": {"arrangement": "file", "file": "mine/fibers.csv",
                                                        "shape": "circle", "radius_um": 20.0}}))
    before = {s: graph.fingerprint(s, load_config(path), tmp_path) for s in ("fiber", "bake")}
    csv.write_text("x_um,z_um,r_um\n0,0,3\n-10,0,3\n")  # the same name, another arrangement
    after = {s: graph.fingerprint(s, load_config(path), tmp_path) for s in ("fiber", "bake")}
    assert after["bake"] != before["bake"] and after["fiber"] == before["fiber"]
