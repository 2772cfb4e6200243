"""The node's parameters have one source, config/odg_node.schema.yaml: the generated
config/odg.yaml and README table are current, the schema's rules reject what they should,
and `odg_node --help` prints every parameter without starting ROS."""
from __future__ import annotations

import math

import pytest
import yaml

from odg_ros.model_config import load_preset
from odg_ros.network.precision import NODE_PRECISIONS
from odg_ros.online import parameters
from odg_ros.online.extrinsics import SOURCES as EXTRINSICS_SOURCES
from odg_ros.resources import resource_path


def test_generated_files_are_current():
    from tools import node_parameters
    for path, text in node_parameters.generated().items():
        assert path.read_text() == text, f"{path} is stale: python -m tools.node_parameters --write"


def test_params_file_holds_every_parameter_at_its_default():
    schema = parameters.load_schema()
    shipped = yaml.safe_load(resource_path("config/odg.yaml").read_text())["/**"][
        "ros__parameters"]
    assert list(shipped) == list(schema)
    assert parameters.validate(shipped, schema) == {n: p.default for n, p in schema.items()}


def test_schema_enums_match_the_code():
    schema = parameters.load_schema()
    assert schema["precision"].enum == NODE_PRECISIONS
    assert schema["extrinsics_source"].enum == EXTRINSICS_SOURCES
    for preset in schema["preset"].enum:
        load_preset(preset)           # every listed preset exists
    # the node's default visibility is the step's (precision first), and a value the step
    # refuses (a ray clear with probability 1) never passes the schema
    from odg_ros.network.visibility import DEFAULT_MIN_CLEAR
    assert schema["visibility_min_clear"].default == DEFAULT_MIN_CLEAR
    assert schema["visibility_min_clear"].maximum < 1.0


@pytest.mark.parametrize("name, value, expected", [
    ("slop", 0.0, "slop=0.0: expected > 0"),
    ("slop", math.nan, "slop=nan"),
    ("history_frames", -1, "history_frames=-1: expected >= 0"),
    ("history_frames", 1.5, "expected int"),
    ("score_threshold", 1.5, "expected -1 to 1"),
    ("precision", "fp64", "expected one of: auto, fp32, bf16, bf16-encoder, int8-encoder, fp16"),
    ("camera_names", ["CAM_FRONT", 3], "list of strings"),
    ("warn_throttle", "abc", "expected float"),
    ("no_such_parameter", 1, "unknown parameter 'no_such_parameter'"),
    ("query_budget", "half", "query_budget='half': expected one of: full, auto or a fraction"),
    ("query_budget", 0.0, "query_budget=0.0: expected"),
    ("query_budget", "1.5", "query_budget='1.5': expected"),
    ("query_budget", math.nan, "query_budget=nan: expected"),
    ("query_budget", True, "query_budget=True: expected"),
    ("visibility_min_clear", 1.0, "visibility_min_clear=1.0: expected 0 to 0.99"),
])
def test_bad_values_are_named(name, value, expected):
    with pytest.raises(ValueError, match=None) as info:
        parameters.validate({name: value})
    assert expected in str(info.value)


def test_every_problem_in_one_message_and_integers_become_floats():
    with pytest.raises(ValueError) as info:
        parameters.validate({"slop": -1.0, "precision": "x"})
    assert "slop" in str(info.value) and "precision" in str(info.value)
    values = parameters.validate({"slop": 1})
    assert values["slop"] == 1.0 and isinstance(values["slop"], float)


def test_query_budget_takes_a_mode_or_a_fraction():
    """As a params file or -p gives it: a word, a number, or a number written as text."""
    for value in ("full", "auto", 0.6, "0.35", 1, 1.0):
        assert parameters.validate({"query_budget": value})["query_budget"] == value


def test_a_malformed_schema_entry_is_refused(tmp_path):
    schema = tmp_path / "schema.yaml"
    schema.write_text("parameters:\n  x:\n    type: float\n    default: -1.0\n"
                      "    minimum: 0.0\n    group: sync\n    description: d\n")
    with pytest.raises(ValueError, match="default breaks"):
        parameters.load_schema(schema)
    schema.write_text("parameters:\n  x:\n    type: double\n    default: 1.0\n"
                      "    group: sync\n    description: d\n")
    with pytest.raises(ValueError, match="needs type"):
        parameters.load_schema(schema)


def test_help_lists_every_parameter():
    text = parameters.help_text()
    for name, parameter in parameters.load_schema().items():
        assert f"    {name} ({parameter.type}, default" in text
    table = parameters.markdown_table()
    assert table.count("\n| `") == len(parameters.load_schema())
