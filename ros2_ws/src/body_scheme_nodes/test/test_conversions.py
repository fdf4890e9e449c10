"""Tests of message <-> core conversions (real generated message classes, no node)."""

import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovariance
from sensor_msgs.msg import JointState

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.events import Event
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes import conversions


def _random_transforms(n, rng):
    return transform_from_rotvec(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))


def test_pose_round_trip():
    """Transform -> Pose -> transform is the identity map."""
    rng = np.random.default_rng(0)
    for A2B in _random_transforms(5, rng):
        np.testing.assert_allclose(conversions.transform_from_pose_msg(conversions.pose_msg_from_transform(A2B)), A2B,
                                   atol=1e-12)


def test_stamp_round_trip():
    """Seconds -> Time -> seconds keeps nanosecond precision."""
    for seconds in [0.0, 1.5, 1700000000.123456789]:
        stamp = conversions.stamp_from_seconds(seconds)
        assert conversions.seconds_from_stamp(stamp) == pytest.approx(seconds, abs=1e-9)


def test_marker_poses_round_trip_with_covariance():
    """MarkerPoses built from poses reads back the same poses; std becomes a diagonal covariance."""
    rng = np.random.default_rng(0)
    poses = dict(zip([7, 3, 12], _random_transforms(3, rng), strict=True))
    msg = conversions.marker_poses_msg(2.5, "camera", poses, std={7: (0.03, 0.1)})
    stamp, observations, rejected = conversions.observations_from_msg(msg)
    assert stamp == pytest.approx(2.5) and rejected == [] and sorted(observations) == [3, 7, 12]
    for marker_id, A2B in poses.items():
        np.testing.assert_allclose(observations[marker_id], A2B, atol=1e-12)
    covariance = np.reshape(msg.poses[msg.marker_ids.tolist().index(7)].covariance, (6, 6))
    np.testing.assert_allclose(np.diag(covariance), [0.03**2 / 3] * 3 + [0.1**2 / 3] * 3)


def test_bad_markers_rejected_individually():
    """NaN positions, zero quaternions and repeated ids are rejected with reasons; good markers survive."""
    msg = conversions.marker_poses_msg(0.0, "camera", {1: np.eye(4)})
    bad_nan, bad_zero, repeated = PoseWithCovariance(), PoseWithCovariance(), PoseWithCovariance()
    bad_nan.pose.position.x = math.nan
    bad_zero.pose.orientation.w = 0.0
    repeated.pose.orientation.w = 1.0
    msg.marker_ids = [1, 2, 3, 1]
    msg.poses = [msg.poses[0], bad_nan, bad_zero, repeated]
    _, observations, rejected = conversions.observations_from_msg(msg)
    assert sorted(observations) == [1]
    codes = [(marker_id, code) for marker_id, code, _ in rejected]
    assert codes == [(2, "invalid_pose"), (3, "invalid_pose"), (1, "repeated_id")]
    msg.poses = [msg.poses[0], repeated, repeated, repeated]  # all valid: converted in one vectorised call
    _, observations, rejected = conversions.observations_from_msg(msg)
    assert sorted(observations) == [1, 2, 3] and [(i, code) for i, code, _ in rejected] == [(1, "repeated_id")]
    np.testing.assert_array_equal(observations[1], np.eye(4))  # the first of a repeated id is kept


def test_mismatched_lengths_rejected():
    """A MarkerPoses whose ids and poses differ in length is rejected as a whole."""
    msg = MarkerPoses()
    msg.marker_ids = [1, 2]
    msg.poses = [PoseWithCovariance()]
    with pytest.raises(InvalidInputError, match="2 marker_ids but 1 poses"):
        conversions.observations_from_msg(msg)


def test_actions_follow_joint_names_order():
    """Joint positions are reordered to the configured joint order; missing joints and NaN raise."""
    msg = JointState(name=["b", "a"], position=[2.0, 1.0])
    _, actions = conversions.actions_from_joint_state(msg, ["a", "b"])
    np.testing.assert_array_equal(actions, [1.0, 2.0])
    with pytest.raises(InvalidInputError, match="lacks joint"):
        conversions.actions_from_joint_state(msg, ["a", "c"])
    with pytest.raises(InvalidInputError, match="finite"):
        conversions.actions_from_joint_state(JointState(name=["a", "b"], position=[math.nan, 0.0]), ["a", "b"])


def test_event_msg_maps_missing_values():
    """Events without a model get -1 ids and NaN errors, not zeros that look like data."""
    msg = conversions.event_msg(1.0, Event(step=4, kind="structure_found", reason="spanning tree found"))
    assert (msg.step, msg.kind, msg.parent_id, msg.child_id) == (4, "structure_found", -1, -1)
    assert math.isnan(msg.trans_error) and math.isnan(msg.rot_error)


def test_a_joint_named_twice_is_refused_not_last_wins():
    """Duplicate joint names in one JointState make the command ambiguous: refused, never the last value."""
    msg = JointState(name=["a", "b", "a"], position=[1.0, 2.0, 3.0])
    with pytest.raises(InvalidInputError, match=r"\['a'\] more than once"):
        conversions.actions_from_joint_state(msg, ["a", "b"])


def test_tracked_poses_carry_each_detections_covariance():
    from std_msgs.msg import Header

    poses = {3: np.eye(4), 5: np.eye(4)}
    covariance = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    markers, array = conversions.tracked_poses_msgs(Header(frame_id="camera"), poses, {5: covariance})
    assert list(markers.marker_ids) == [3, 5] and len(array.poses) == 2
    assert np.all(np.array(markers.poses[0].covariance) == 0.0)  # not estimated
    assert np.array_equal(np.array(markers.poses[1].covariance).reshape(6, 6), covariance)
