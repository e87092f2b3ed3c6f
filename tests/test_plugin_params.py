"""Plugin parameters of the wrong type are refused when the scene loads, naming the key
(issue 23, class 5): nothing is coerced (``bool('false')`` is true, ``int(3.7)`` is 3)."""

import pytest

from tests.synthetic import make_config, synthetic_table


@pytest.fixture
def table_path(tmp_path):
    path = tmp_path / "table.npz"
    synthetic_table(make_config(tmp_path), path, relative=True, passthrough=0.3)
    return str(path)


BSDF_CASES = {  # key: (wrong value, what the message says)
    "passthrough": ("false", "'passthrough' must be a boolean"),
    "up": ("0 0 1", "'up' must be a 3-vector"),
    "twist": ("30", "'twist' must be a number"),
    "twist_rate": (True, "'twist_rate' must be a number"),
    "radius": (-1.0, "'radius' must be >= 0"),
    "sampling_uniform": (1.5, "'sampling_uniform' must be \\[0, 1\\]"),
}


@pytest.mark.parametrize("key", sorted(BSDF_CASES))
def test_fiber_bundle_refuses_a_wrongly_typed_parameter(mi_plugins, table_path, key):
    value, says = BSDF_CASES[key]
    with pytest.raises(Exception, match=says):
        mi_plugins.load_dict({"type": "fiber_bundle", "table": table_path, key: value})


INTEGRATOR_CASES = {
    "max_depth": (3.7, "'max_depth' must be an integer"),
    "rr_depth": (0, "'rr_depth' must be an integer >= 1"),
    "displaced_exit": ("false", "'displaced_exit' must be a boolean"),
    "exit_split": (True, "'exit_split' must be one of 'none', 'emitter', 'all'"),
    "max_passes": ("64", "'max_passes' must be an integer"),
    "hide_emitters": (1, "hide_emitters\" has the wrong type"),  # Mitsuba's own Integrator checks this one
}


@pytest.mark.parametrize("key", sorted(INTEGRATOR_CASES))
def test_bundle_path_refuses_a_wrongly_typed_parameter(mi_plugins, key):
    value, says = INTEGRATOR_CASES[key]
    with pytest.raises(Exception, match=says):
        mi_plugins.load_dict({"type": "bundle_path", key: value})


def test_well_typed_parameters_load_and_take_effect(mi_plugins, table_path):
    """The same keys with their own types load (a whole float is a whole number)."""
    bsdf = mi_plugins.load_dict({"type": "fiber_bundle", "table": table_path, "passthrough": False,
                                 "up": [0, 1, 0], "twist": 30, "sampling_uniform": 0.2})
    params = mi_plugins.traverse(bsdf)  # loaded: a BSDF object
    assert params is not None
    integrator = mi_plugins.load_dict({"type": "bundle_path", "max_depth": 5.0, "displaced_exit": False})
    assert integrator.max_depth == 5 and integrator.displace is False


def test_xml_booleans_are_read_and_xml_strings_refused(mi_plugins, table_path):
    """As a Mitsuba user writes it: ``<boolean>`` is a boolean, ``<string value="false">`` is not."""
    xml = ('<scene version="3.0.0"><bsdf type="fiber_bundle"><string name="table" value="{t}"/>'
           '<{kind} name="passthrough" value="false"/></bsdf></scene>')
    mi_plugins.load_string(xml.format(t=table_path, kind="boolean"))
    with pytest.raises(Exception, match="'passthrough' must be a boolean"):
        mi_plugins.load_string(xml.format(t=table_path, kind="string"))
