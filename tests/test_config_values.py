"""Silent nonsense in a config is refused, naming the key (issue 23, class 6): booleans
where numbers belong, an unsorted spectral table, sweep values that would share a folder."""

import pytest

from pipeline.config import ConfigError, load_config, sweep_members

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
