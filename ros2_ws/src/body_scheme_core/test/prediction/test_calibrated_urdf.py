"""The robot's own URDF with the learned joint axes: a drop-in whose forward kinematics is the body scheme's."""

import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.prediction import calibrated_urdf, format_diff, learned_tree
from body_scheme_core.world import Marker, arm_4dof, deform_limb, make_session, tree_from_urdf, tree_to_urdf

SIGMA_T, SIGMA_R = 0.002, math.radians(0.5)


@pytest.fixture(scope="module")
def bent():
    """arm_4dof whose third joint's limb is 30 mm longer and bent 3 deg, learned from a low-noise session."""
    nominal = arm_4dof()
    truth = deform_limb(nominal, nominal.action_joint(2).name, delta_length=0.03,
                        delta_rotvec=(0.0, math.radians(3.0), 0.0))
    session = make_session(truth, 250, seed=0, sigma_trans=SIGMA_T, sigma_rot=SIGMA_R)
    learner = BodySchemeLearner(nominal.marker_ids, nominal.n_actions, BodySchemeConfig(sigma_trans=SIGMA_T,
                                                                                        sigma_rot=SIGMA_R))
    for a, y in zip(session.actions, session.observations, strict=True):
        learner.update(a, y)
    body = learned_tree(learner.body_scheme, nominal.action_joint_names, *learner.trained_range(), nominal=nominal)
    return nominal, truth, learner, body


def _marker_errors_mm(tree, reference, actions, root):
    """Largest distance of every marker from the reference's, both relative to the root marker (mm)."""
    worst = 0.0
    for a in actions:
        got, want = tree.marker_poses(a), reference(a)
        for part in want:
            g = np.linalg.inv(got[root]) @ got[part]
            w = np.linalg.inv(want[root]) @ want[part]
            worst = max(worst, 1e3 * float(np.linalg.norm(g[:3, 3] - w[:3, 3])))
    return worst


def test_the_calibrated_urdf_moves_the_bent_joint_and_predicts_as_the_body_scheme(bent):
    nominal, truth, learner, body = bent
    result = calibrated_urdf(tree_to_urdf(nominal), body, nominal, learner.root)
    calibrated = tree_from_urdf(result.text, [Marker(p, link, T) for p, (link, T) in result.markers.items()])
    assert [j.name for j in calibrated.joints] == [j.name for j in nominal.joints]
    actions = np.random.default_rng(1).uniform(*learner.trained_range(), size=(30, nominal.n_actions))
    # Its forward kinematics is the learned body scheme's, ...
    assert _marker_errors_mm(calibrated, body.marker_poses, actions, learner.root) < 1e-6
    # ... near the bent truth where the specification is centimetres off.
    assert _marker_errors_mm(calibrated, truth.true_marker_poses, actions, learner.root) < 3.0
    assert _marker_errors_mm(nominal, truth.true_marker_poses, actions, learner.root) > 20.0
    # The diff: joint3's origin 30 mm further out; the 3 deg bend about link2's origin, about joint2's own axis, is
    # joint2's zero offset (its origin turned 3 deg); the other joints stay.
    moved = {row["joint"]: row for row in result.diff}
    assert set(moved) == set(nominal.action_joint_names)
    assert moved["joint3"]["origin_mm"] == pytest.approx(30.0, abs=2.0) and moved["joint3"]["origin_deg"] < 0.3
    assert moved["joint2"]["origin_deg"] == pytest.approx(3.0, abs=0.3) and moved["joint2"]["origin_mm"] < 1.0
    assert all(moved[j]["origin_mm"] < 1.0 and moved[j]["origin_deg"] < 0.3 for j in ("joint1", "joint4"))
    assert all(row["axis_deg"] < 0.3 for row in result.diff)
    assert "joint3" in format_diff(result) and "<calibration" not in result.text


def test_a_continuous_joint_is_calibrated_and_ros2_control_joints_are_left_alone(bent):
    """A continuous joint is a revolute one; the <joint> elements of <ros2_control> and <transmission> are not
    joints of the kinematics and get no <origin>."""
    nominal, _, learner, body = bent
    text = tree_to_urdf(nominal).replace('type="revolute"', 'type="continuous"', 1).replace(
        "</robot>", '<ros2_control name="arm" type="system"><joint name="joint3"><command_interface name="position"/>'
                    '</joint></ros2_control><transmission name="t"><joint name="joint2"/></transmission></robot>')
    specified = tree_from_urdf(text, nominal.markers)
    assert specified.joint("joint1").type == "continuous"
    result = calibrated_urdf(text, body, specified, learner.root)
    assert {row["joint"] for row in result.diff} == set(nominal.action_joint_names)
    assert '<joint name="joint3"><command_interface' in result.text and '<joint name="joint2" />' in result.text


def test_a_urdf_that_does_not_parse_or_lacks_the_root_marker_is_refused(bent):
    nominal, _, learner, body = bent
    with pytest.raises(InvalidInputError, match="does not parse"):
        calibrated_urdf("<robot", body, nominal, learner.root)
    other = tree_from_urdf(tree_to_urdf(nominal), [m for m in nominal.markers if m.id != learner.root])
    with pytest.raises(InvalidInputError, match="lack the learned body's"):
        calibrated_urdf(tree_to_urdf(nominal), body, other, learner.root)
