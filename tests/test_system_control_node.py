"""System tests of control_node: the installed executable as its own process, IK requests over real DDS."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.world import default_world2root, planar_2dof
from body_scheme_msgs.msg import IKResult, IKTarget, ModelSnapshot
from body_scheme_nodes import conversions

pytestmark = pytest.mark.system

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def test_control_node_solves_reports_and_refuses(start_node, ros_node, spin_until):
    """control_node refuses without a model, reaches a reachable target and reports an unreachable one."""
    tree = planar_2dof()
    end_effector = max(tree.marker_ids)
    process = start_node("body_scheme_nodes", "control_node", {"part_id": end_effector, "tolerance": 0.002})
    results, commands = [], []
    ros_node.create_subscription(IKResult, "ik_result", results.append, 10)
    ros_node.create_subscription(JointState, "joint_commands", commands.append, 10)
    targets = ros_node.create_publisher(IKTarget, "ik_target", 10)
    snapshots = ros_node.create_publisher(ModelSnapshot, "body_scheme/snapshot", LATCHED)

    def send(position, part_id=-1):
        msg = IKTarget(part_id=part_id)
        msg.header.frame_id = "camera"
        msg.position.x, msg.position.y, msg.position.z = (float(v) for v in position)
        targets.publish(msg)

    # No model yet: a clear refusal, no command.
    assert spin_until(lambda: targets.get_subscription_count() > 0, timeout=30), process.output()
    send([0.0, 0.0, 1.0])
    assert spin_until(lambda: len(results) == 1, timeout=10), process.output()
    assert not results[0].success and "no body scheme yet" in results[0].reason and commands == []
    assert np.isnan(results[0].residual) and list(results[0].actions) == []  # refused: nothing evaluated

    # The engineered body scheme of the 2-DOF arm, in a camera frame 2 m away.
    world2root = default_world2root()
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    snapshots.publish(conversions.snapshot_msg(0.0, "camera", 1, scheme, tree.action_joint_names,
                                               tree.action_lower, tree.action_upper, world2root))
    a_true = np.array([0.4, -0.7])
    target = (world2root @ tree.marker_poses(a_true)[end_effector])[:3, 3]
    send(target)
    assert spin_until(lambda: len(results) == 2 and commands, timeout=10), process.output()
    assert results[1].success, results[1].reason
    _, commanded = conversions.actions_from_joint_state(commands[-1], tree.action_joint_names)
    reached = (world2root @ tree.marker_poses(commanded)[end_effector])[:3, 3]
    assert np.linalg.norm(reached - target) < 0.002
    assert np.all(commanded >= tree.action_lower) and np.all(commanded <= tree.action_upper)

    # Out of reach: failure with a reason, and no new command.
    n_commands = len(commands)
    send(target + [5.0, 0.0, 0.0])
    assert spin_until(lambda: len(results) == 3, timeout=20), process.output()
    assert not results[2].success and "unreachable" in results[2].reason
    assert results[2].residual > 1.0 and len(commands) == n_commands

    # A part the body scheme does not have: refused without evaluating, so no residual and no actions.
    send(target, part_id=99)
    assert spin_until(lambda: len(results) == 4, timeout=20), process.output()
    assert not results[3].success and "not in body scheme" in results[3].reason
    assert np.isnan(results[3].residual) and list(results[3].actions) == [] and len(commands) == n_commands


def test_control_node_executes_an_ik_answer_through_the_controller(start_node, ros_node, spin_until):
    """execute: true: the solution goes to sim_node as a JointTrajectoryController goal; once the arm settled,
    control_node reports where the camera saw the end effector, and the true end effector is within 10 mm of the
    target."""
    from trajectory_msgs.msg import JointTrajectory

    from body_scheme_msgs.msg import MarkerPoses
    from body_scheme_sim.camera import Camera
    from body_scheme_sim.robots import load_robot

    tree = load_robot("powercube_6dof")
    end_effector = max(tree.marker_ids)
    camera2root = np.linalg.inv(Camera().world2camera)  # sim_node: the root at the world origin
    start_node("body_scheme_nodes", "sim_node", {"robot": "powercube_6dof", "perception_mode": "noise",
                                                 "sigma_trans": 0.002, "sigma_rot": 0.01, "camera_period": 0.1})
    process = start_node("body_scheme_nodes", "control_node", {
        "part_id": end_effector, "tolerance": 0.002, "execute": True, "robot": "powercube_6dof",
        "max_velocity": 5.0, "max_acceleration": 20.0, "observe_timeout": 5.0})  # a loaded 2-core machine
    results, trajectories, truth = [], [], []
    ros_node.create_subscription(IKResult, "ik_result", results.append, 10)
    ros_node.create_subscription(JointTrajectory, "joint_trajectory_controller/joint_trajectory",
                                 trajectories.append, 10)
    ros_node.create_subscription(MarkerPoses, "ground_truth/marker_poses", truth.append, 100)
    targets = ros_node.create_publisher(IKTarget, "ik_target", 10)
    snapshots = ros_node.create_publisher(ModelSnapshot, "body_scheme/snapshot", LATCHED)
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    camera2root_marker = camera2root @ tree.marker_poses(np.zeros(tree.n_actions))[tree.root_marker]
    snapshots.publish(conversions.snapshot_msg(0.0, "camera", 1, scheme, tree.action_joint_names,
                                               tree.action_lower, tree.action_upper, camera2root_marker))
    a_true = np.array([0.17, 0.68, 0.45, -0.27, -0.1, -0.26])  # a posture in which the camera sees marker 7
    target = (camera2root @ tree.marker_poses(a_true)[end_effector])[:3, 3]
    assert spin_until(lambda: targets.get_subscription_count() > 0, timeout=30), process.output()
    spin_until(lambda: False, timeout=1.0)  # the latched snapshot reaches control_node
    msg = IKTarget(part_id=-1)
    msg.header.frame_id = "camera"
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in target)
    targets.publish(msg)
    assert spin_until(lambda: results, timeout=30), process.output()
    result = results[0]
    assert result.success and result.executed, result.reason
    assert result.reached_source == "observed" and result.reached_error < 0.02, result
    assert len(trajectories) == 1 and trajectories[0].points
    seen = len(truth)  # the arm has settled: the next ground-truth frames show where it stands
    assert spin_until(lambda: len(truth) > seen, timeout=30), "no ground truth from sim_node"
    _, last = conversions.observations_from_msg(truth[-1])[:2]
    assert np.linalg.norm(last[end_effector][:3, 3] - target) < 0.010
