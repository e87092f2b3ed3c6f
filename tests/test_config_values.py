"""Silent nonsense in a config is refused, naming the key (issue 23, class 6): booleans
where numbers belong, an unsorted spectral table, sweep values that would share a folder."""

import pytest

from pipeline.config import ConfigError

from pipeline.loading import load_config, sweep_members

DEFAULT = "configs/default.yaml"


@pytest.mark.parametrize("key", ["bake.paths_per_phi_i", "render.spp", "train.lr", "bundle.radius_um",
                                 "fiber.ior.k", "wavelengths.count"])
def test_a_boolean_is_not_a_number(key):
    """YAML's ``true`` read as 1 would bake 1 path, render 1 spp or train at lr 1."""
    with pytest.raises(ConfigError, match=f"{key}: must be a number, not a boolean"):
        load_config(DEFAULT, [f"{key}=true"])


def test_booleans_are_still_booleans():
    assert load_config(DEFAULT, ["render.mono_check=false"]).render.mono_check is False


def test_an_unsorted_k_table_is_refused():
    """Read unsorted, the absorbing fiber of the table rendered as k = 0 (albedo 1)."""
    with pytest.raises(ConfigError, match="fiber.ior.k: the .* rows of k must be in increasing nm"):
        load_config(DEFAULT, ["fiber.ior.k=[[700, 1e-4], [400, 3e-4], [550, 2e-4]]"])
    k = load_config(DEFAULT, ["fiber.ior.k=[[400, 3e-4], [550, 2e-4], [700, 1e-4]]"]).fiber.ior.k
    assert [nm for nm, _ in k] == [400, 550, 700]


def test_sweep_values_that_print_alike_get_folders_of_their_own():
    cfg = load_config(DEFAULT, ["sweep={bundle.seed: [1, 2], bundle.packing: [0.3, 0.30000001]}"])
    names = [m.name for _, m in sweep_members(cfg)]
    assert len(set(names)) == len(names) == 4, names
    assert all("packing-v0" in n or "packing-v1" in n for n in names), names
    plain = load_config(DEFAULT, ["sweep={bundle.packing: [0.3, 0.4]}"])
    assert [m.name for _, m in sweep_members(plain)] == ["packing-0.3", "packing-0.4"]


@pytest.mark.parametrize("override, says", [
    ("bundle.seed=99999999999", "bundle.seed: Input should be less than or equal to 4294967295"),
    ("render.mono_check_size=[1, 2, 3]", "render.mono_check_size"),
    ("render.mono_check_size=[2, 48]", "render.mono_check_size.0"),
    ("render.twist_turns=1000000.0", "render.twist_turns"),
    ("train.patience=1000000000", "train.patience"),
])
def test_values_that_had_no_bounds_have_them(override, says):
    with pytest.raises(ConfigError, match=says.replace(".", r"\.")):
        load_config(DEFAULT, [override])


# -- issue 23, class 7: a message where a traceback was --------------------------------
@pytest.mark.parametrize("text, says", [
    ("a: &x [1, 2]\nb: *x\n", "YAML aliases"),
    ("? [1, 2]\n: 3\n", "a key must be a plain name or number"),
    ("name: " + "[" * 3000 + "]" * 3000 + "\n", "nested too deeply|not valid YAML"),
])
def test_yaml_that_is_no_config_gets_a_message(tmp_path, text, says):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=says):
        load_config(path)


def test_a_billion_laughs_is_refused_at_once(tmp_path):
    """947 bytes that expand to 10^9 values ran out of memory after 92 s."""
    import time

    lines = ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    for k in range(1, 9):
        lines.append(f"{chr(97 + k)}: &{chr(97 + k)} [{', '.join(['*' + chr(96 + k)] * 10)}]")
    (tmp_path / "lol.yaml").write_text("\n".join(lines) + "\n")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match="YAML aliases"):
        load_config(tmp_path / "lol.yaml")
    assert time.perf_counter() - t0 < 5


@pytest.mark.parametrize("key, value", [("bake.variant", "llvm_ad_rgb"), ("bake.variant", "whatever"),
                                        ("render.variant", "llvm_ad_mono"), ("render.variant", "scalar_rgb")])
def test_variants_a_stage_cannot_run_are_refused(key, value):
    with pytest.raises(ConfigError, match=key):
        load_config(DEFAULT, [f"{key}={value}"])


def test_a_cuda_variant_without_a_gpu_is_refused_before_work(tmp_path, capsys):
    import drjit as dr

    from pipeline import cli

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a GPU: a cuda variant runs here")  # the CI machines have none
    code = cli.main(["fiber", DEFAULT, "--artifacts", str(tmp_path), "--set", "render.variant=cuda_ad_spectral"])
    assert code == 2
    err = capsys.readouterr().err
    assert "render.variant: cuda_ad_spectral needs an NVIDIA GPU" in err and "llvm_ad_spectral" in err
    assert not (tmp_path / "default" / "fiber").exists()


@pytest.mark.parametrize("name, value", [("TQDM_MININTERVAL", "soon"), ("BCSDF_SCHEDULER", "localhost")])
def test_garbage_in_an_environment_variable_is_named(tmp_path, capsys, monkeypatch, name, value):
    from pipeline import cli

    monkeypatch.setenv(name, value)
    assert cli.main(["fiber", DEFAULT, "--artifacts", str(tmp_path)]) == 2
    assert f"the environment variable {name}={value!r}" in capsys.readouterr().err


def test_an_obstacle_in_the_artifacts_tree_is_named(tmp_path, capsys):
    """A file where the stage's folder belongs: a message, not a NotADirectoryError traceback."""
    from pipeline import cli

    (tmp_path / "default").mkdir()
    (tmp_path / "default" / "fiber").write_text("in the way")
    assert cli.main(["fiber", DEFAULT, "--artifacts", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "in the way" in err and "Traceback" not in err
    assert (tmp_path / "default" / "fiber").read_text() == "in the way"


# -- issue 23, class 8: the bound before the work ----------------------------------------
def test_a_bundle_of_millions_of_fibers_is_refused_at_once():
    import time

    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match="would hold about 10,000,000 fibers"):
        load_config(DEFAULT, ["bundle.radius_um=100000", "fiber.radius_um=10", "bundle.packing=0.1"])
    assert time.perf_counter() - t0 < 5


def test_a_sweep_of_millions_of_members_is_refused_before_expanding():
    import time

    t0 = time.perf_counter()
    axes = ", ".join(f"bundle.{k}: [{', '.join(str(v) for v in values)}]"
                     for k, values in (("seed", range(1, 101)), ("packing", [0.1 + 0.001 * i for i in range(100)]),
                                       ("gap_um", [0.01 * i for i in range(100)])))
    with pytest.raises(ConfigError, match="1,000,000 members"):
        load_config(DEFAULT, [f"sweep={{{axes}}}"])
    assert time.perf_counter() - t0 < 5


def test_a_full_disk_inside_torch_or_mitsuba_is_said(tmp_path, capsys, monkeypatch):
    """torch and Mitsuba raise ENOSPC as a RuntimeError with the OS's words in it."""
    import errno
    import os

    from pipeline import cli
    from pipeline.stages import fiber

    def full(cfg, out_root="artifacts"):
        raise RuntimeError(f"[Bitmap] write(): {os.strerror(errno.ENOSPC)}")
    monkeypatch.setattr(fiber, "run", full)
    assert cli.main(["fiber", DEFAULT, "--artifacts", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "a write failed (No space left on device): free some space" in err and "Traceback" not in err
