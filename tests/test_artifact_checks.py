"""Artifacts are checked against themselves wherever they are loaded (issue 23, class 4):
a table or model that is inconsistent is refused, naming the file and the field, by the
loader every stage and plugin uses; nothing is rendered from it."""

import json

import numpy as np
import pytest

from models.bundle_table import BundleTable
from tests.synthetic import make_config, synthetic_table


@pytest.fixture
def table_path(tmp_path):
    cfg = make_config(tmp_path)
    path = tmp_path / "table.npz"
    synthetic_table(cfg, path, relative=True, passthrough=0.3)
    return path


def rewrite(path, **changes):
    """The table at ``path`` with some arrays (or ``meta``) replaced, written as the baker does."""
    t = BundleTable.load(path)
    for k, v in changes.items():
        if k == "meta":
            t.meta = v(t.meta)
        else:
            setattr(t, k, v(getattr(t, k)))
    t.save(path)  # save does not validate: this is the careless or hostile writer
    return path


CASES = {
    "passthrough above 1": (dict(passthrough=lambda p: p * 0 + 1.7), "passthrough reaches 1.7"),
    "negative passthrough": (dict(passthrough=lambda p: p * 0 - 0.5), "passthrough holds negative"),
    "passthrough of the wrong length": (dict(passthrough=lambda p: np.concatenate([p, p])), "passthrough has shape"),
    "theta_i out of order": (dict(theta_i=lambda t: t[::-1]), "axis theta_i: must increase"),
    "uneven phi_o edges": (dict(phi_o_edges=lambda e: np.pi * np.sign(e) * (np.abs(e) / np.pi) ** 1.2),
                           "axis phi_o_edges: steps"),
    "unknown phi_o reduction": (dict(meta=lambda m: {**m, "reductions": {**m["reductions"], "phi_o": "sideways"}}),
                                "meta.reductions.phi_o"),
    "values near float32's limit": (dict(values=lambda v: v * 0 + 3e38), "values reach"),
    "NaN in absorbed": (dict(absorbed=lambda a: a * np.nan), "absorbed holds NaN"),
    "Inf in values": (dict(values=lambda v: np.where(v == v.max(), np.inf, v)), "values holds NaN or Inf"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_inconsistent_tables_are_refused_by_the_loader_and_the_plugin(mi_plugins, table_path, case):
    changes, says = CASES[case]
    rewrite(table_path, **changes)
    with pytest.raises(ValueError, match=says) as e:
        BundleTable.load(table_path, expand=True)  # as every renderer and trainer reads it
    assert str(table_path) in str(e.value)
    with pytest.raises(Exception, match=says):  # the plugin reads through the same loader
        mi_plugins.load_dict({"type": "fiber_bundle", "table": str(table_path)})


def test_a_consistent_table_still_loads(table_path):
    assert BundleTable.load(table_path).passthrough.max() <= 1


def test_values_are_stored_in_half_precision_and_old_tables_read_as_before(table_path):
    """``values`` and ``stderr`` are written as float16 times a power of two: within 2^-11
    (float16's rounding) of what was saved over 24 binary orders of magnitude below the
    largest value, at any scale; a table written before (format /1, float32) reads as it was."""
    from models.bundle_table import READABLE

    t = BundleTable.load(table_path)
    rng = np.random.default_rng(1)
    for top in (1e-6, 3.0, 5e7):  # below, inside and above float16's own range (6e-5 .. 65504)
        t.values = (top * 10.0 ** rng.uniform(-7, 0, t.values.shape)).astype(np.float32)
        t.stderr = 0.03 * t.values
        t.save(table_path)
        with np.load(table_path) as z:
            assert z["values"].dtype == np.float16 and z["stderr"].dtype == np.float16
        back = BundleTable.load(table_path)
        assert back.values.dtype == np.float32
        for name in ("values", "stderr"):
            a, b = getattr(t, name).astype(np.float64), getattr(back, name).astype(np.float64)
            normal = a >= a.max() * 2.0**-24
            assert np.all(np.abs(b / a - 1)[normal] <= 2.0**-11), (top, name)
            assert np.all(np.abs(b - a)[~normal] <= a.max() * 2.0**-25), (top, name)
    # a float32 table of the first format
    with np.load(table_path) as z:
        arrays = {k: z[k] for k in z.files if k != "header"}
        header = json.loads(str(z["header"]))
    arrays["values"], arrays["stderr"] = t.values, t.stderr
    header = {"format": READABLE[0], "meta": header["meta"]}
    with open(table_path, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), **arrays)
    assert np.array_equal(BundleTable.load(table_path).values, t.values)
    # the second format without its scales: named, not misread
    header["format"] = READABLE[1]
    with open(table_path, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), **arrays)
    with pytest.raises(ValueError, match="not a readable bundle table"):
        BundleTable.load(table_path)


def test_the_singly_scattered_part_is_checked_and_optional(table_path):
    """``single`` is optional (tables baked before it have none and load as before); where
    present it is a part of the scattered light and cannot exceed it."""
    t = BundleTable.load(table_path)
    assert t.single is None and BundleTable.load(table_path, expand=True).single is None
    t.single = 0.5 * t.scattered
    t.save(table_path)
    assert np.allclose(BundleTable.load(table_path).single, 0.5 * t.scattered)
    t.single = np.minimum(1.0, 1.1 * t.scattered)  # a probability still, but more than its whole
    t.save(table_path)
    with pytest.raises(ValueError, match="single exceeds the scattered light"):
        BundleTable.load(table_path)


@pytest.mark.parametrize("field,value,says", [
    ("s0", float("nan"), "s0"), ("y_max", -1.0, "y_max"), ("cone_scale", 0.0, "cone_scale"),
    ("passthrough", [1.5], "passthrough"), ("wavelength", [550.0, 450.0], "wavelength"),
    ("single_share", [0.5, 1.5, 0.2], "single_share"), ("single_share", [0.5], "single_share"),
])
def test_model_metadata_out_of_its_domain_is_refused(trained, tmp_path, field, value, says):
    import shutil

    from mitsuba_ext.neural import load_weights

    cfg, root = trained
    size = next(iter(cfg.train.models))
    src = root / cfg.name / "export" / size / "weights.npz"
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    spec = json.loads(arrays["spec"].item().decode("utf-8"))
    spec[field] = value
    if field == "passthrough":
        spec["passthrough_phi_i"] = [0.0]
    arrays["spec"] = np.array(json.dumps(spec))
    bad = tmp_path / "weights.npz"
    np.savez(bad, **arrays)
    with pytest.raises(ValueError, match=says):
        load_weights(bad)
    shutil.copy(src, tmp_path / "good.npz")
    load_weights(tmp_path / "good.npz")


def test_onnx_graph_that_disagrees_with_its_metadata_is_refused(trained, tmp_path):
    import onnx

    from mitsuba_ext.neural import OnnxMLP

    cfg, root = trained
    size = next(iter(cfg.train.models))
    model = onnx.load(str(root / cfg.name / "export" / size / "model.onnx"))
    for entry in model.metadata_props:
        if entry.key == "bcsdf_spec":
            spec = json.loads(entry.value)
            spec["wavelength"] = spec["wavelength"] + [spec["wavelength"][-1] + 10.0]
            spec["gain"] = [row + row[-1:] for row in spec["gain"]]  # consistent in itself, not with the graph
            entry.value = json.dumps(spec)
    onnx.save(model, str(tmp_path / "model.onnx"))
    with pytest.raises(ValueError, match="metadata names"):
        OnnxMLP(tmp_path / "model.onnx")


def test_a_summary_is_written_and_read_through_its_schema(trained, tmp_path, capsys):
    """The train stage's summary holds its schema; one from other code (a field missing, one
    renamed) is refused by its path with the command that writes it again, also through
    ``bcsdf report``, which reads it."""
    import shutil

    from pipeline import cli
    from pipeline.summaries import StaleSummary, TrainSummary

    cfg, root = trained
    shutil.copytree(root / cfg.name, tmp_path / cfg.name)
    path = tmp_path / cfg.name / "train" / "tiny" / "summary.json"
    summary = TrainSummary.read(path)
    assert summary.parameters > 0 and 0 <= summary.relative_l1 < 10
    record = json.loads(path.read_text())
    record["held_out_l1"] = record.pop("relative_l1")  # what other code might have called it
    path.write_text(json.dumps(record))
    with pytest.raises(StaleSummary, match=r"summary.json.*relative_l1.*bcsdf train"):
        TrainSummary.read(path)
    config = tmp_path / f"{cfg.name}.yaml"
    shutil.copyfile(root / f"{cfg.name}.yaml", config)
    assert cli.main(["--artifacts", str(tmp_path), "report", str(config), "--force"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "bcsdf train" in err


def test_the_jitted_evaluator_given_an_onnx_graph_says_which_file_it_reads(trained):
    from mitsuba_ext.neural import DrJitMLP

    cfg, root = trained
    onnx = root / cfg.name / "export" / "tiny" / "model.onnx"
    with pytest.raises(ValueError, match="ONNX graph.*weights.npz") as e:
        DrJitMLP(onnx)
    assert "pickle" not in str(e.value)
    renamed = onnx.parent / "graph.bin"  # the same bytes under another name: still no numpy advice
    renamed.write_bytes(onnx.read_bytes())
    with pytest.raises(ValueError, match="not a readable model weights file") as e:
        DrJitMLP(renamed)
    assert "pickle" not in str(e.value)
