"""feed_message's checks before any conversion: size limits and the camera frame (issue 20)."""

import numpy as np
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from body_scheme_core.pairing import CommandObservationPairer
from body_scheme_nodes import conversions, view
from body_scheme_nodes.message_feed import MessageLimits, feed_message


def _observations(frame_id, n=1):
    return conversions.marker_poses_msg(1.0, frame_id, {k: np.eye(4) for k in range(1, n + 1)})


def test_observations_in_another_frame_are_refused_an_empty_frame_is_the_cameras():
    """frame_id "world" was learnt as if it were the camera's before issue 20."""
    pairer = CommandObservationPairer()
    assert feed_message(pairer, "observations", _observations("world"), ["a"], "camera")[1][0][0] == "wrong_frame"
    assert feed_message(pairer, "observations", _observations(""), ["a"], "camera") == ([], [])
    assert feed_message(pairer, "observations", _observations("camera"), ["a"], "camera") == ([], [])


def test_messages_beyond_the_limits_are_refused_whole_before_conversion():
    """100,000 joint names (a duplicate check quadratic in them froze the node 80 s) or more markers than allowed."""
    limits, pairer = MessageLimits(max_joint_names=10, max_markers=3), CommandObservationPairer()
    names = [f"j{k}" for k in range(100_000)]
    command = JointState(header=Header(stamp=conversions.stamp_from_seconds(1.0)), name=names,
                         position=[0.0] * len(names))
    samples, rejections = feed_message(pairer, "command", command, ["j0"], limits=limits)
    assert samples == [] and [code for code, _ in rejections] == ["oversized_message"]
    assert feed_message(pairer, "observations", _observations("camera", 4), ["j0"], limits=limits)[1][0][0] == \
        "oversized_message"
    assert feed_message(pairer, "observations", _observations("camera", 3), ["j0"], limits=limits) == ([], [])


def test_a_joint_state_with_many_distinct_names_is_converted():
    """30,000 distinct names: the duplicate check counts them once (it took 6.6 s in the node before issue 20)."""
    names = [f"j{k}" for k in range(30_000)]
    msg = JointState(name=names, position=[float(k) for k in range(30_000)])
    _, actions = conversions.actions_from_joint_state(msg, ["j29999", "j0"])
    assert actions.tolist() == [29999.0, 0.0]


def test_the_uncertainty_sphere_is_the_two_sigma_of_the_reported_covariance():
    """The sphere was sqrt(3) larger than the covariance on predicted_poses before issue 20."""
    poses, std = {1: np.eye(4)}, {1: (0.03, 0.1)}
    covariance = conversions.marker_poses_msg(0.0, "camera", poses, std).poses[0].covariance
    (sphere,) = [m for m in view.markers_msg(0.0, "camera", poses, std, []).markers if m.ns == "uncertainty"]
    assert np.isclose(sphere.scale.x, 2 * 2 * np.sqrt(covariance[0]))


def test_a_tag_detectors_covariances_reach_the_learner():
    """MarkerPoses' covariances (the tracker's, per detection) go with the poses into learner.update: an all-zero
    one means "not estimated"; with learner.detection_covariances a malformed one is counted by the learner as
    bad_covariance, its pose kept."""
    from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
    from body_scheme_nodes.message_feed import learn_sample

    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.0, 1.5]
    msg = conversions.tracked_poses_msgs(Header(stamp=conversions.stamp_from_seconds(1.1), frame_id="camera"),
                                         {1: pose, 2: pose, 3: pose}, {1: np.eye(6) * 1e-4, 3: -np.eye(6)})[0]
    pairer = CommandObservationPairer()
    command = JointState(header=Header(stamp=conversions.stamp_from_seconds(1.0)), name=["j0"], position=[0.1])
    feed_message(pairer, "command", command, ["j0"])
    assert feed_message(pairer, "observations", msg, ["j0"], "camera") == ([], [])
    ((stamp, actions, observed),) = pairer.flush(10.0)
    assert sorted(observed.poses) == [1, 2, 3] and sorted(observed.covariances) == [1, 3]
    assert np.array_equal(observed.covariances[1], np.eye(6) * 1e-4)
    learner = BodySchemeLearner((1, 2, 3), 1, BodySchemeConfig(detection_covariances=True))
    events, rejection = learn_sample(learner, stamp, actions, observed)
    assert rejection is None and learner.rejected == {"bad_covariance": 1}
    assert [e.child for e in events if e.kind == "input_rejected"] == [3]
    assert [p for p, _ in learner.to_state()["history"][0]["covariances"]] == [1]


def test_a_repeated_marker_id_gives_its_pose_no_covariance():
    """Which entry's pose is kept for a repeated id is not certain: none of their covariances is taken."""
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.0, 1.5]
    msg = conversions.tracked_poses_msgs(Header(frame_id="camera"), {1: pose, 2: pose},
                                         {1: np.eye(6) * 1e-4, 2: np.eye(6) * 1e-4})[0]
    msg.marker_ids = [1, 2, 2]
    msg.poses = [msg.poses[0], msg.poses[1], msg.poses[1]]
    _, observations, _ = conversions.observations_from_msg(msg)
    assert sorted(conversions.covariances_from_msg(msg, observations)) == [1]
