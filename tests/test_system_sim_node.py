"""System tests of sim_node: the installed executable as its own process, talking over real DDS."""

from __future__ import annotations

import time

import numpy as np
import pytest
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import UInt64

from body_scheme_msgs.msg import MarkerPoses
from body_scheme_msgs.srv import InjectFault
from body_scheme_nodes import conversions
from body_scheme_nodes.qos import LATCHED
from body_scheme_sim.camera import Camera
from body_scheme_sim.robots import load_robot

pytestmark = pytest.mark.system


class Recorder:
    """Keeps every message of the subscribed topics, in arrival order."""

    def __init__(self, node, topics):
        self.messages = {topic: [] for topic, _, _ in topics}
        for topic, msg_type, qos in topics:
            node.create_subscription(msg_type, topic, lambda msg, topic=topic: self.messages[topic].append(msg), qos)

    def count(self, topic):
        return len(self.messages[topic])


def truth_of_command(tree, camera, actions):
    """Expected ground truth ``{id: camera2marker}`` for executed joint positions."""
    camera2root = np.linalg.inv(camera.world2camera)
    return {marker_id: camera2root @ pose for marker_id, pose in tree.marker_poses(actions).items()}


def pairs(commands, truths):
    """(command actions, command stamp, ground-truth poses) for each ground truth, matched to the latest command
    stamped no later than it."""
    stamped = sorted((conversions.seconds_from_stamp(c.header.stamp), np.array(c.position)) for c in commands)
    result = []
    for msg in truths:
        stamp, poses, _ = conversions.observations_from_msg(msg)
        earlier = [(s, a) for s, a in stamped if s <= stamp]
        if earlier:
            result.append((earlier[-1][1], earlier[-1][0], poses))
    return result


def matches(poses, expected, tolerance=1e-6):
    return all(np.allclose(poses[i], expected[i], atol=tolerance) for i in expected)


def test_babbling_noise_mode_and_a_blocked_joint_over_dds(start_node, ros_node, spin_until):
    """Babbling sim_node publishes commands, noisy observations and ground truth; a block_joint call shows in it."""
    tree, camera = load_robot("powercube_6dof"), Camera()
    process = start_node("body_scheme_nodes", "sim_node", {
        "robot": "powercube_6dof", "perception_mode": "noise", "babbling": True, "babbling_period": 0.05,
        "sigma_trans": 0.01, "visibility": 0.9, "markers_of_interest": [1], "seed": 4})
    recorder = Recorder(ros_node, [("joint_commands", JointState, 100), ("observations", MarkerPoses, 100),
                                   ("ground_truth/marker_poses", MarkerPoses, 100)])
    assert spin_until(lambda: recorder.count("ground_truth/marker_poses") >= 10, timeout=60), process.output()
    commands = recorder.messages["joint_commands"]
    assert list(commands[0].name) == list(tree.action_joint_names)
    for msg in recorder.messages["observations"]:
        _, observed, rejected = conversions.observations_from_msg(msg)
        assert not rejected and set(observed) <= set(tree.marker_ids)
    for actions, _, poses in pairs(commands, recorder.messages["ground_truth/marker_poses"]):
        assert set(poses) == set(tree.marker_ids)
        assert matches(poses, truth_of_command(tree, camera, actions))

    client = ros_node.create_client(InjectFault, "/sim_node/inject_fault")
    assert client.wait_for_service(timeout_sec=60)
    future = client.call_async(InjectFault.Request(kind="block_joint", action_index=0, angle=0.5))
    assert spin_until(future.done, timeout=60)
    assert future.result().success, future.result().message
    blocked_since = ros_node.get_clock().now().nanoseconds * 1e-9
    n_before = recorder.count("ground_truth/marker_poses")
    assert spin_until(lambda: recorder.count("ground_truth/marker_poses") >= n_before + 8, timeout=60)

    after = [(a, p) for a, s, p in pairs(recorder.messages["joint_commands"],
                                         recorder.messages["ground_truth/marker_poses"]) if s > blocked_since]
    assert len(after) >= 5
    for actions, poses in after:
        blocked = np.r_[0.5, actions[1:]]
        assert matches(poses, truth_of_command(tree, camera, blocked))
        assert not matches(poses, truth_of_command(tree, camera, actions))  # the commanded a0 is never 0.5

    bad = client.call_async(InjectFault.Request(kind="block_joint", action_index=9))
    assert spin_until(bad.done, timeout=60)
    assert not bad.result().success and "action_index" in bad.result().message


def test_rendered_mode_answers_commands_with_images_over_dds(start_node, ros_node, spin_until):
    """sim_node executes commands and sends an rgb8 Image + CameraInfo of the configured size.

    The subscriber uses sensor-data (best effort) QoS: the sim's reliable image publisher must serve it too.
    """
    tree = load_robot("arm_4dof")
    process = start_node("body_scheme_nodes", "sim_node", {
        "robot": "arm_4dof", "perception_mode": "rendered", "camera.width": 320, "camera.height": 240,
        "camera.fx": 280.0, "camera.fy": 280.0, "camera.cx": 159.5, "camera.cy": 119.5, "image_encoding": "rgb8"})
    recorder = Recorder(ros_node, [("camera/image_raw", Image, qos_profile_sensor_data),
                                   ("camera/camera_info", CameraInfo, qos_profile_sensor_data),
                                   ("ground_truth/marker_poses", MarkerPoses, 100)])
    publisher = ros_node.create_publisher(JointState, "joint_commands", 10)
    rng = np.random.default_rng(0)
    sent = []

    def command():
        if time.monotonic() - (sent[-1][0] if sent else 0.0) > 0.2:
            actions = rng.uniform(tree.action_lower, tree.action_upper)
            stamp = ros_node.get_clock().now().nanoseconds * 1e-9
            publisher.publish(conversions.joint_state_msg(stamp, tree.action_joint_names, actions))
            sent.append((time.monotonic(), stamp, actions))

    assert spin_until(lambda: min(recorder.count(t) for t in recorder.messages) >= 3, timeout=60, during=command), \
        process.output()
    image, info = recorder.messages["camera/image_raw"][0], recorder.messages["camera/camera_info"][0]
    assert (image.width, image.height, image.encoding) == (320, 240, "rgb8")
    assert conversions.image_from_msg(image).shape == (240, 320, 3)
    assert (info.width, info.height) == (320, 240)
    np.testing.assert_allclose(conversions.camera_from_info(info)[0], [[280, 0, 159.5], [0, 280, 119.5], [0, 0, 1]])
    info_stamps = {conversions.seconds_from_stamp(m.header.stamp) for m in recorder.messages["camera/camera_info"]}
    first_command = min(stamp for _, stamp, _ in sent)
    for msg in recorder.messages["camera/image_raw"]:
        stamp = conversions.seconds_from_stamp(msg.header.stamp)
        assert stamp >= first_command and msg.header.frame_id == "camera"
    assert conversions.seconds_from_stamp(image.header.stamp) in info_stamps
    # each ground truth belongs to one of the commands sent, executed as commanded (no faults)
    camera = Camera(width=320, height=240, fx=280.0, fy=280.0, cx=159.5, cy=119.5)
    for msg in recorder.messages["ground_truth/marker_poses"]:
        _, poses, _ = conversions.observations_from_msg(msg)
        assert any(matches(poses, truth_of_command(tree, camera, actions)) for _, _, actions in sent)


def test_as_a_controller_it_follows_the_cubic_of_a_partial_trajectory_and_rejects_an_empty_one(
        start_node, ros_node, spin_until):
    """A one-point trajectory naming one joint, with zero velocity, over 2 s: that joint follows the cubic a
    JointTrajectoryController would (at a quarter of the time, 5/32 of the way, not the 1/4 of a straight line), the
    others hold, it ends at the goal; an empty trajectory is rejected and does not stop the arm."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    start_node("body_scheme_nodes", "sim_node", {"robot": "powercube_6dof", "perception_mode": "noise"})
    states = []
    ros_node.create_subscription(JointState, "/joint_states", states.append, 100)
    trajectories = ros_node.create_publisher(JointTrajectory, "joint_trajectory_controller/joint_trajectory", 10)
    assert spin_until(lambda: len(states) > 5 and trajectories.get_subscription_count() > 0, timeout=60)
    spin_until(lambda: False, timeout=0.5)
    goal, duration = 0.8, 2.0
    trajectories.publish(JointTrajectory(joint_names=["joint2"], points=[JointTrajectoryPoint(
        positions=[goal], velocities=[0.0], time_from_start=Duration(sec=2))]))
    spin_until(lambda: False, timeout=0.5)
    trajectories.publish(JointTrajectory(joint_names=["joint2"]))  # empty: rejected, the move goes on
    assert spin_until(lambda: abs(states[-1].position[1] - goal) < 1e-6, timeout=60)
    readings = [(conversions.seconds_from_stamp(m.header.stamp), np.array(m.position)) for m in states]
    t0 = max(t for t, p in readings if p[1] == 0.0)  # the last reading before the move
    quarter = min(readings, key=lambda r: abs(r[0] - t0 - duration / 4))
    assert quarter[1][1] == pytest.approx(goal * 5 / 32, abs=0.03 * goal)
    assert all(np.all(p[[0, 2, 3, 4, 5]] == 0.0) for _, p in readings)


def test_babbling_waits_for_scheme_nodes_progress_with_max_in_flight(start_node, ros_node, spin_until):
    """``max_in_flight`` 2: from scheme_node's first count on, two pictures undecided and sim_node babbles no more
    (its timeout is far away) until body_scheme/progress moves: each decided picture lets one more command go."""
    process = start_node("body_scheme_nodes", "sim_node", {
        "robot": "arm_4dof", "perception_mode": "noise", "babbling": True, "babbling_period": 0.05,
        "max_in_flight": 2, "in_flight_timeout": 600.0, "wait_for_subscribers": 1})  # none of them lost
    recorder = Recorder(ros_node, [("joint_commands", JointState, 100), ("observations", MarkerPoses, 100),
                                   ("ground_truth/marker_poses", MarkerPoses, 100)])
    progress = ros_node.create_publisher(UInt64, "body_scheme/progress", LATCHED)
    progress.publish(UInt64(data=7))  # a scheme_node that has decided 7 observations already (transient local)
    assert spin_until(lambda: recorder.count("joint_commands") >= 2, timeout=60), process.output()
    spin_until(lambda: False, timeout=1.0)  # 20 babbling periods
    assert recorder.count("joint_commands") == 2
    for decided, expected in ((8, 3), (10, 5)):
        progress.publish(UInt64(data=decided))
        assert spin_until(lambda n=expected: recorder.count("joint_commands") >= n, timeout=60), process.output()
        spin_until(lambda: False, timeout=1.0)
        assert recorder.count("joint_commands") == expected


def test_babbling_goes_on_when_pictures_in_flight_are_never_decided(start_node, ros_node, spin_until):
    """Without scheme_node's count sim_node does not babble; with a count that never moves each picture in flight
    counts as lost after ``in_flight_timeout`` and babbling goes on; the end of babbling says how many were lost."""
    process = start_node("body_scheme_nodes", "sim_node", {
        "robot": "arm_4dof", "perception_mode": "noise", "babbling": True, "babbling_period": 0.05,
        "babbling_steps": 5, "max_in_flight": 1, "in_flight_timeout": 0.3})
    recorder = Recorder(ros_node, [("joint_commands", JointState, 100)])
    waiting = "waiting for scheme_node's body_scheme/progress before babbling"
    assert spin_until(lambda: waiting in process.output(), timeout=60), process.output()
    assert recorder.count("joint_commands") == 0
    ros_node.create_publisher(UInt64, "body_scheme/progress", LATCHED).publish(UInt64(data=0))
    assert spin_until(lambda: "now executing joint_commands" in process.output(), timeout=60), process.output()
    assert "babbled 5 commands (4 of their pictures never decided by scheme_node)" in process.output()
