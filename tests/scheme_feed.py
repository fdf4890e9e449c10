"""Helpers of the system tests that feed scheme_node over DDS: its parameters for a tree, a collector of what it
publishes and a babbler that publishes a synthetic session."""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState

from body_scheme_msgs.msg import BodySchemeStructure, MarkerPoses, ModelSnapshot
from body_scheme_nodes import conversions
from body_scheme_nodes.qos import LATCHED


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
        self.n_diagnostics = 0  # arrays received
        node.create_subscription(BodySchemeStructure, "body_scheme/structure", self._structure, LATCHED)
        node.create_subscription(ModelSnapshot, "body_scheme/snapshot", self._snapshot, LATCHED)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 10)

    def _structure(self, msg):
        self.structure = msg

    def _snapshot(self, msg):
        self.snapshot = msg

    def _diagnostics(self, msg):
        self.n_diagnostics += 1
        for status in msg.status:
            self.diagnostics[status.name] = status

    @property
    def step(self):
        """scheme_node's learner step from its last /diagnostics, or None."""
        status = self.diagnostics.get("/scheme_node: body scheme")
        if status is None:
            return None
        return int(next(kv.value for kv in status.values if kv.key == "step"))


class Babbler:
    """Publishes a synthetic babbling session: each command, then the marker poses observed after it.

    Samples are never closer than ``period`` apart: after a pause (the test spun without it) the babbler goes on
    from now instead of publishing the samples that were due meanwhile in one burst, whose stamps would be too close
    for the node to pair each observation with its own command."""

    def __init__(self, node, session, period=0.02, depth=100):
        self.node, self.session, self.period = node, session, period
        self.commands = node.create_publisher(JointState, "joint_commands", depth)
        self.observations = node.create_publisher(MarkerPoses, "observations", depth)
        self.k = 0
        self._next = time.monotonic()

    def __call__(self):
        """Publish the next sample if its time has come (called between spins)."""
        due = time.monotonic()
        if self.k >= self.session.n_steps or due < self._next:
            return
        now = self.node.get_clock().now().nanoseconds * 1e-9
        command = JointState(name=list(self.session.tree.action_joint_names),
                             position=[float(v) for v in self.session.actions[self.k]])
        command.header.stamp = conversions.stamp_from_seconds(now)
        self.commands.publish(command)
        observed = self.session.observations[self.k]
        self.observations.publish(conversions.marker_poses_msg(now + 0.005, "camera", observed))
        self.k += 1
        self._next = max(self._next, due) + self.period


def learned_the_tree(collector, true_edges):
    s = collector.structure
    return s is not None and {frozenset((e.parent_id, e.child_id)) for e in s.edges} == true_edges \
        and all(e.valid for e in s.edges)
