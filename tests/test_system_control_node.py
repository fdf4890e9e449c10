"""System tests of control_node: the installed executable as its own process, IK requests over real DDS."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.scheme import BodyScheme
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
