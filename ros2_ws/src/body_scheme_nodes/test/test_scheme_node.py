"""scheme_node's ROS-free parts: its parameter file and the engineered start."""

import dataclasses
import math
import pathlib

import numpy as np
import pytest
import yaml

from body_scheme_core.config import BodySchemeConfig
from body_scheme_core.errors import InvalidInputError
from body_scheme_core.kinematics import markers_to_yaml
from body_scheme_core.scheme import BodyScheme
from body_scheme_core.synthetic import powercube_6dof
from body_scheme_nodes.scheme_node import _NONE_SENTINELS, engineered_body_scheme

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


def test_engineered_start_from_urdf_and_marker_file(tmp_path):
    """URDF + marker file give one engineered model per marker-tree edge; joints map to actions by name."""
    tree = powercube_6dof()
    urdf, markers = tmp_path / "arm.urdf", tmp_path / "markers.yaml"
    urdf.write_text(tree.to_urdf("arm"))
    markers.write_text(markers_to_yaml(tree.markers))
    names = list(tree.action_joint_names)
    models = engineered_body_scheme(str(urdf), str(markers), names, list(tree.marker_ids))
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, models)
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    expected = tree.marker_poses(a)
    root_inverse = np.linalg.inv(expected[tree.root_marker])
    for part, root2part in scheme.predict(a).items():
        np.testing.assert_allclose(root2part, root_inverse @ expected[part], atol=1e-9)
    # Reversed joint order: action k now commands the joint named names[::-1][k].
    reversed_models = engineered_body_scheme(str(urdf), str(markers), names[::-1], list(tree.marker_ids))
    reversed_scheme = BodyScheme(tree.marker_ids, tree.root_marker, reversed_models)
    for part, root2part in reversed_scheme.predict(a[::-1]).items():
        np.testing.assert_allclose(root2part, root_inverse @ expected[part], atol=1e-9)


def test_engineered_start_rejects_missing_marker_file_and_wrong_parts(tmp_path):
    """Without a marker file, or with markers other than part_ids, the start is refused with a reason."""
    tree = powercube_6dof()
    urdf, markers = tmp_path / "arm.urdf", tmp_path / "markers.yaml"
    urdf.write_text(tree.to_urdf("arm"))
    markers.write_text(markers_to_yaml(tree.markers))
    names = list(tree.action_joint_names)
    with pytest.raises(InvalidInputError, match="markers_path"):
        engineered_body_scheme(str(urdf), "", names, list(tree.marker_ids))
    with pytest.raises(InvalidInputError, match="part_ids"):
        engineered_body_scheme(str(urdf), str(markers), names, [1, 2, 3])
