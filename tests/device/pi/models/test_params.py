"""device/pi/models/params.py: one typed parameter class per model family, in one
table, and the family of a spec's kind and model."""
from __future__ import annotations

import dataclasses

import pytest

from device.pi.models.params import (PARAMS, ClassifierParams, FusedParams, LocaliserParams,
                                     RegressorParams, RuleParams, family_of, parse_params)


def test_each_family_has_one_dataclass_in_the_one_table():
    assert PARAMS == {"classifier": ClassifierParams, "rule": RuleParams,
                      "regressor": RegressorParams, "localiser": LocaliserParams,
                      "fused": FusedParams}
    assert all(dataclasses.is_dataclass(c) for c in PARAMS.values())
    assert family_of("surface", "fnn") == family_of("texture", "cnn") == "classifier"
    assert family_of("surface", "rule") == "rule"
    assert family_of("pressure", "ridge") == "regressor"
    assert (family_of("localiser", "localiser"), family_of("fused", "fused")) == (
        "localiser", "fused")


def test_measured_facts_are_no_parameter_of_any_family():
    measured = {"trained_on", "int8", "identity", "cost_per_decision"}
    for cls in PARAMS.values():
        assert not measured & {f.name for f in dataclasses.fields(cls)}


@pytest.mark.parametrize("doc, kind, model, match", [
    ({"target_mean": "x"}, "pressure", "ridge", r"^m: params\.target_mean must be a finite "
                                                r"number, got 'x'$"),
    ({"target_mean": float("nan")}, "pressure", "ridge", r"params\.target_mean .*got nan"),
    ({}, "pressure", "ridge", r"^m: params\.target_mean is required for a regressor model"),
    ({"roughness": 1}, "texture", "fnn", r"^m: params\.roughness must be true or false, got 1$"),
    ({"ignored_pins": [1, "2"]}, "texture", "fnn", r"params\.ignored_pins must be a list of "
                                                   r"whole numbers, got \[1, '2'\]"),
    ({"cost_per_decision": {}}, "surface", "fnn", r"params\.cost_per_decision is not a "
                                                  r"parameter of a classifier model"),
    ({"members": "x"}, "fused", "fused", r"params\.members must be a list"),
])
def test_a_bad_parameter_is_one_line_naming_the_field_and_the_value(doc, kind, model, match):
    with pytest.raises(ValueError, match=match):
        parse_params(doc, kind, model, "m")


def test_defaults_fill_the_optional_parameters():
    p = parse_params({"n_pins": 3, "size": 8, "crop_factor": 0.9,
                      "mean_layout_norm": [[0.0, 0.0]] * 3}, "localiser", "localiser", "m")
    assert p.fill_grid == 0 and p.max_dev_norm is None and p.fill_range == [0.0, 1.0]
    assert parse_params({}, "slip", "fnn", "m") == ClassifierParams()
