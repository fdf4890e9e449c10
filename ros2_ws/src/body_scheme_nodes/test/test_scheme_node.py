"""scheme_node's settings: its parameter file, parsing and validation, and the engineered start."""

import dataclasses
import math
import pathlib

import numpy as np
import pytest
import yaml

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.world import markers_to_yaml, powercube_6dof
from body_scheme_nodes.settings import (
    AUTO_SENTINELS,
    NONE_SENTINELS,
    SchemeSettings,
    engineered_body_scheme,
    parameter_defaults,
)

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config" / "scheme_node.yaml"


def test_yaml_lists_every_learner_field_with_its_default():
    """config/scheme_node.yaml has exactly the BodySchemeConfig fields, each at its default, typed alike."""
    learner = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]["learner"]
    fields = {f.name: f.default for f in dataclasses.fields(BodySchemeConfig)}
    assert set(learner) == set(fields)
    for name, default in fields.items():
        expected = NONE_SENTINELS[name] if default is None else default
        expected = AUTO_SENTINELS[name] if default == "auto" else expected
        if isinstance(expected, tuple):  # a list in YAML and as a ROS parameter
            assert learner[name] == list(expected), name
            continue
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


def test_a_tool_only_urdf_start_is_the_urdfs_chain_calibrated_from_the_tolerance(tmp_path):
    """Markers on the base and the tool only: the engineered start joins them by the URDF's chain of six joints,
    every joint off by the tolerance as its prior covariance (0, 0: the URDF exact, an engineered model), predicting
    as the URDF."""
    from body_scheme_core.models import EngineeredModel, chain_from_engineered
    from body_scheme_core.world import KinematicTree

    arm = powercube_6dof()
    markers = [m for m in arm.markers if m.id in (arm.root_marker, max(arm.marker_ids))]
    tree = KinematicTree(arm.joints, markers, root_link=arm.root_link)
    urdf, markers_file = tmp_path / "arm.urdf", tmp_path / "markers.yaml"
    urdf.write_text(tree.to_urdf("arm"))
    markers_file.write_text(markers_to_yaml(tree.markers))
    names, parts = list(tree.action_joint_names), list(tree.marker_ids)
    (chain,) = engineered_body_scheme(str(urdf), str(markers_file), names, parts, (0.005, math.radians(1.0)))
    assert chain.kind == "chain" and len(chain.actions) == 6
    spec = chain_from_engineered(EngineeredModel.from_tree(tree, tree.root_marker, max(parts)),
                                 prior=(0.005, math.radians(1.0)))  # every joint off by the tolerance
    assert np.allclose(chain.param_cov_, spec.param_cov_)
    assert np.all(np.sqrt(chain.param_cov_[-6:-3, -6:-3].diagonal()) > 0.005)  # the tool: more than one joint's
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    poses = tree.marker_poses(a)
    expected = np.linalg.inv(poses[tree.root_marker]) @ poses[max(parts)]
    np.testing.assert_allclose(chain.predict(a[None])[0], expected, atol=1e-9)
    (exact,) = engineered_body_scheme(str(urdf), str(markers_file), names, parts, (0.0, 0.0))
    assert exact.kind == "engineered"
    settings = SchemeSettings.from_parameters({"part_ids": parts, "joint_names": names, "urdf_path": str(urdf),
                                               "markers_path": str(markers_file)})
    assert settings.new_learner().body_scheme.models[0].kind == "chain"
    with pytest.raises(InvalidInputError, match="urdf_tolerance_rot"):
        SchemeSettings.from_parameters({"part_ids": parts, "joint_names": names, "urdf_tolerance_rot": -1.0})


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


def test_shipped_yaml_parses_into_settings():
    """config/scheme_node.yaml builds settings whose learner config equals the core defaults."""
    settings = SchemeSettings.from_yaml(CONFIG)
    assert settings.config == BodySchemeConfig()
    assert settings.part_ids == (1, 2, 3, 4, 5, 6, 7) and len(settings.joint_names) == 6


def test_every_node_parameter_is_in_the_yaml():
    """The YAML names every scheme_node parameter (flattening the learner block)."""
    parameters = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    flat = {k for k, v in parameters.items() if not isinstance(v, dict)}
    flat |= {f"learner.{k}" for k in parameters["learner"]}
    assert flat == set(parameter_defaults(6))


def test_bad_settings_are_refused_with_reasons():
    """Unknown parameters, mismatched limits, duplicate joints and too few parts raise InvalidInputError."""
    good = {"part_ids": [1, 2], "joint_names": ["a"], "action_lower": [-1.0], "action_upper": [1.0]}
    assert SchemeSettings.from_parameters(good).joint_names == ("a",)
    bad = [({"learner.sigma": 1.0}, "unknown"), ({"action_lower": [-1.0, 0.0]}, "action_lower"),
           ({"joint_names": ["a", "a"], "action_lower": [-1.0, -1.0], "action_upper": [1.0, 1.0]}, "unique"),
           ({"part_ids": [1]}, "part_ids"), ({"learner.test_window": 0}, "test_window"),
           ({"checkpoint_period": -5.0}, "checkpoint_period"), ({"stamp_tolerance": 0.0}, "stamp_tolerance"),
           ({"unstamped_policy": "guess"}, "unstamped_policy"), ({"learner.max_distance": -1.0}, "max_distance"),
           # issue 20: sizes, infinities, frame prefixes and special directories
           ({"queue_depth": 10**11}, "queue_depth must be an integer from 1 to"),
           ({"learner.workspace_margin": math.inf}, "workspace_margin must be a finite number"),
           ({"tf_prefix": "bad prefix//../x"}, "tf_prefix must be a TF frame prefix"),
           ({"tf_prefix": "/robot"}, "tf_prefix"), ({"state_dir": "/proc/self"}, "state_dir .* inside /proc"),
           ({"checkpoint_path": "/dev/zero"}, "checkpoint_path"),
           ({"part_ids": list(range(200))}, "200 parts: a learner takes at most"),
           ({"joint_names": [f"j{k}" for k in range(300)], "action_lower": [-1.0] * 300,
             "action_upper": [1.0] * 300}, "300 actions: a learner takes at most"),
           ({"part_ids": list(range(40)), "joint_names": [f"j{k}" for k in range(30)], "action_lower": [-1.0] * 30,
             "action_upper": [1.0] * 30}, "candidate models to bootstrap")]
    for change, match in bad:
        with pytest.raises(InvalidInputError, match=match):
            SchemeSettings.from_parameters(dict(good, **change)).new_learner()
    for prefix in ("robot_a/", "lab/robot_a", "r2_"):
        assert SchemeSettings.from_parameters(dict(good, tf_prefix=prefix)).tf_prefix == prefix


def test_parameter_files_keyed_by_any_node_name_or_wildcard_read_alike(tmp_path):
    """The shipped file is keyed /** (any node name or namespace); files keyed by the node name still read."""
    assert next(iter(yaml.safe_load(CONFIG.read_text()))) == "/**"
    parameters = yaml.safe_load(CONFIG.read_text())["/**"]
    named = tmp_path / "named.yaml"
    named.write_text(yaml.safe_dump({"scheme_node": parameters}))
    assert SchemeSettings.from_yaml(named) == SchemeSettings.from_yaml(CONFIG)
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({"tracker_node": parameters}))
    with pytest.raises(InvalidInputError, match="not a parameter file"):
        SchemeSettings.from_yaml(other)
