"""The shipped parameter file and the core configuration must not drift apart."""

import dataclasses
import math
import pathlib

import yaml

from body_scheme_core.config import BodySchemeConfig
from body_scheme_nodes.scheme_node import _NONE_SENTINELS

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config" / "scheme_node.yaml"


def test_yaml_lists_every_learner_field_with_its_default():
    """config/scheme_node.yaml has exactly the BodySchemeConfig fields, each at its default, typed alike."""
    learner = yaml.safe_load(CONFIG.read_text())["scheme_node"]["ros__parameters"]["learner"]
    fields = {f.name: f.default for f in dataclasses.fields(BodySchemeConfig)}
    assert set(learner) == set(fields)
    for name, default in fields.items():
        expected = _NONE_SENTINELS[name] if default is None else default
        assert type(learner[name]) is type(expected), name
        assert math.isclose(learner[name], expected), name
