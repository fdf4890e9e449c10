"""System tests of scheme_node: the installed executable as its own process, our messages over real DDS."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from body_scheme_core.world import make_session, planar_2dof
from body_scheme_msgs.msg import BodySchemeStructure, MarkerPoses, ModelSnapshot
from body_scheme_nodes import conversions

pytestmark = pytest.mark.system

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def scheme_parameters(tree):
    return {"part_ids": [int(i) for i in tree.marker_ids], "joint_names": list(tree.action_joint_names),
            "action_lower": [float(v) for v in tree.action_lower],
            "action_upper": [float(v) for v in tree.action_upper],
            "pairing_grace": 0.05, "learner.train_window": 20}


class Collector:
    """Keeps the latest message of each subscribed topic and all diagnostics statuses by name."""

    def __init__(self, node):
        self.structure = None
        self.snapshot = None
        self.diagnostics = {}
        node.create_subscription(BodySchemeStructure, "body_scheme/structure", self._structure, LATCHED)
        node.create_subscription(ModelSnapshot, "body_scheme/snapshot", self._snapshot, LATCHED)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 10)

    def _structure(self, msg):
        self.structure = msg

    def _snapshot(self, msg):
        self.snapshot = msg

    def _diagnostics(self, msg):
        for status in msg.status:
            self.diagnostics[status.name] = status

    @property
    def step(self):
        """scheme_node's learner step from its last /diagnostics, or None."""
        status = self.diagnostics.get("body_scheme: scheme")
        if status is None:
            return None
        return int(next(kv.value for kv in status.values if kv.key == "step"))


class Babbler:
    """Publishes a synthetic babbling session: each command, then the marker poses observed after it."""

    def __init__(self, node, session, period=0.02):
        self.node, self.session, self.period = node, session, period
        self.commands = node.create_publisher(JointState, "joint_commands", 100)
        self.observations = node.create_publisher(MarkerPoses, "observations", 100)
        self.k = 0
        self._next = time.monotonic()

    def __call__(self):
        """Publish the next sample if its time has come (called between spins)."""
        if self.k >= self.session.n_steps or time.monotonic() < self._next:
            return
        now = self.node.get_clock().now().nanoseconds * 1e-9
        command = JointState(name=list(self.session.tree.action_joint_names),
                             position=[float(v) for v in self.session.actions[self.k]])
        command.header.stamp = conversions.stamp_from_seconds(now)
        self.commands.publish(command)
        observed = self.session.observations[self.k]
        self.observations.publish(conversions.marker_poses_msg(now + 0.005, "camera", observed))
        self.k += 1
        self._next += self.period


def test_scheme_node_learns_structure_over_dds(start_node, ros_node, spin_until):
    """scheme_node, fed a babbling session over DDS, publishes the true body scheme and an OK diagnostic."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=120, seed=0, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", scheme_parameters(tree))
    collector = Collector(ros_node)

    # The latched structure arrives as soon as discovery completes, before any data: the node is up.
    assert spin_until(lambda: collector.structure is not None, timeout=30), process.output()
    assert collector.structure.phase == "bootstrapping" and list(collector.structure.edges) == []

    babbler = Babbler(ros_node, session)
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}

    def learned_true_structure():
        s = collector.structure
        return s is not None and {frozenset((e.parent_id, e.child_id)) for e in s.edges} == true_edges \
            and all(e.valid for e in s.edges)

    assert spin_until(learned_true_structure, timeout=60, during=babbler), (
        f"published {babbler.k} samples; last structure {collector.structure}\n{process.output()}")
    assert sorted(collector.structure.part_ids) == sorted(tree.marker_ids)
    # The snapshot for the control node follows the structure on its own latched topic.
    assert spin_until(lambda: collector.snapshot is not None and collector.snapshot.scheme_json, timeout=10)
    scheme, _, lower, _ = conversions.scheme_from_snapshot(collector.snapshot)
    assert {frozenset((p, c)) for p, c, _, _ in scheme.edges} == true_edges
    np.testing.assert_allclose(lower, tree.action_lower)

    def scheme_ok():
        status = collector.diagnostics.get("body_scheme: scheme")
        return status is not None and status.level == DiagnosticStatus.OK
    assert spin_until(scheme_ok, timeout=10, during=babbler), collector.diagnostics
    edge_statuses = [name for name in collector.diagnostics if name.startswith("body_scheme: local model")]
    assert len(edge_statuses) == len(true_edges)


def _learned(collector, true_edges):
    s = collector.structure
    return s is not None and {frozenset((e.parent_id, e.child_id)) for e in s.edges} == true_edges \
        and all(e.valid for e in s.edges)


def test_malformed_input_is_counted_and_the_node_keeps_learning(start_node, ros_node, spin_until):
    """NaN poses, zero quaternions, unknown ids, length mismatches and backward stamps are counted, not fatal."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=120, seed=1, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", scheme_parameters(tree))
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=30), process.output()
    babbler = Babbler(ros_node, session)
    names = list(tree.action_joint_names)
    now = ros_node.get_clock().now().nanoseconds * 1e-9

    # A command, then observations that are broken in every way the tracker or a bag could break them.
    good = JointState(name=names, position=[0.1, 0.2])
    good.header.stamp = conversions.stamp_from_seconds(now)
    babbler.commands.publish(good)
    broken = conversions.marker_poses_msg(now + 0.005, "camera", {k: np.eye(4) for k in (1, 2, 3, 99)})
    broken.poses[1].pose.position.x = float("nan")          # marker 2: NaN position
    broken.poses[2].pose.orientation.w = 0.0                 # marker 3: zero quaternion
    babbler.observations.publish(broken)                     # marker 99: unknown id
    mismatched = conversions.marker_poses_msg(now + 0.006, "camera", {1: np.eye(4)})
    mismatched.marker_ids = [1, 2]
    babbler.observations.publish(mismatched)
    backwards = JointState(name=names, position=[0.0, 0.0])
    backwards.header.stamp = conversions.stamp_from_seconds(now - 10.0)
    babbler.commands.publish(backwards)
    babbler.commands.publish(JointState(name=["nope"], position=[0.0]))
    nan_command = JointState(name=names, position=[float("nan"), 0.0])
    babbler.commands.publish(nan_command)

    expected = {"rejected.invalid_pose": 2, "rejected.unknown_id": 1, "rejected.bad_observations_message": 1,
                "rejected.out_of_order_command": 1, "rejected.bad_command_message": 2}

    def counted():
        status = collector.diagnostics.get("body_scheme: scheme")
        values = {} if status is None else {kv.key: kv.value for kv in status.values}
        return all(values.get(key) == str(count) for key, count in expected.items())

    assert spin_until(counted, timeout=15), (collector.diagnostics.get("body_scheme: scheme"), process.output())
    # ... and the node still learns from the good data that follows.
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: _learned(collector, true_edges), timeout=60, during=babbler), process.output()
    assert process.process.poll() is None


def test_kill_and_restart_restores_the_checkpoint(start_node, ros_node, spin_until, tmp_path):
    """After kill -9, a restarted scheme_node restores its checkpoint and publishes the same body scheme."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=150, seed=2, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    checkpoint = tmp_path / "state.json"
    parameters = dict(scheme_parameters(tree), checkpoint_path=str(checkpoint), checkpoint_period=0.5)
    first = start_node("body_scheme_nodes", "scheme_node", parameters)
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=30), first.output()  # discovery done
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    babbler = Babbler(ros_node, session)
    assert spin_until(lambda: _learned(collector, true_edges), timeout=60, during=babbler), first.output()

    def saved_step():
        try:
            return json.loads(checkpoint.read_text())["state"]["step"]
        except (OSError, ValueError, KeyError):
            return -1

    # Queued samples may still change the tree (bootstrapping goes on): wait until the checkpoint holds every step.
    assert spin_until(lambda: collector.step is not None and saved_step() == collector.step, timeout=20)
    learned = [(e.parent_id, e.child_id, e.description) for e in collector.structure.edges]
    first.kill()  # SIGKILL: no clean shutdown, no final save

    collector.structure = None
    second = start_node("body_scheme_nodes", "scheme_node", parameters)
    assert spin_until(lambda: collector.structure is not None and collector.structure.edges, timeout=30), \
        second.output()
    assert "restored checkpoint" in second.output()
    assert [(e.parent_id, e.child_id, e.description) for e in collector.structure.edges] == learned
