"""System test of bag replay: bag_replay -> scheme_node over DDS ends where the offline replay ends."""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import pathlib
import time

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool

from body_scheme_apps.other_stacks import write_layout
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_msgs.msg import BodySchemeStructure, SchemeEvent
from body_scheme_nodes.offline_replay import default_params_file, replay_bag
from body_scheme_nodes.qos import LATCHED
from body_scheme_nodes.settings import SchemeSettings

pytestmark = pytest.mark.system

BAG = pathlib.Path(__file__).resolve().parents[1] / "bags" / "joint_blocked_seed0"


class Collector:
    """The latest structure, every event, bag_replay's done flag and scheme_node's step from /diagnostics."""

    def __init__(self, node):
        self.structure = None
        self.events = []
        self.done = None
        self.step = None
        node.create_subscription(BodySchemeStructure, "body_scheme/structure", self._structure, LATCHED)
        self.events_subscription = node.create_subscription(  # the publisher's latest 100 too (a late match)
            SchemeEvent, "body_scheme/events", self.events.append,
            QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        node.create_subscription(Bool, "bag_replay/done", self._done, LATCHED)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 10)

    def _structure(self, msg):
        self.structure = msg

    def _done(self, msg):
        self.done = msg.data

    def _diagnostics(self, msg):
        for status in msg.status:
            if status.name == "/scheme_node: body scheme":
                self.step = int(next(kv.value for kv in status.values if kv.key == "step"))


def _offline(params_file):
    """The offline replay's final edges, events, number of steps and phase (run in a process of its own)."""
    offline = replay_bag(BAG, SchemeSettings.from_yaml(params_file))
    return ([(e["parent"], e["child"], e["model"]) for e in offline.learner.edge_status()],
            [(e.kind, e.step, e.model or "") for e in offline.events], len(offline.steps), offline.learner.phase)


def test_replay_through_the_graph_equals_the_offline_replay(start_node, ros_node, spin_until):
    """bag_replay (rate 0, backpressure) into scheme_node gives the offline command's final structure and events."""
    params_file = default_params_file()
    collector = Collector(ros_node)
    parameters = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
    scheme = start_node("body_scheme_nodes", "scheme_node", parameters)
    # Replay once this test's subscription is matched with scheme_node's events (kept for late joiners anyway).
    assert spin_until(lambda: collector.structure is not None
                      and collector.events_subscription.get_publisher_count() > 0, timeout=60), scheme.output()
    replay = start_node("body_scheme_nodes", "bag_replay",
                        {"bag_path": str(BAG), "rate": 0.0, "start_delay": 0.5})
    started = time.monotonic()
    # The offline replay runs in a process of its own meanwhile (the other core).
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
        offline = pool.submit(_offline, params_file)
        # However busy the machine: wait while scheme_node's step advances, and 40 s after it last did.
        assert spin_until(lambda: collector.done is not None, timeout=60, progress=lambda: collector.step), (
            replay.output(), scheme.output())
        replay_seconds = time.monotonic() - started
        expected_edges, expected_events, n_steps, phase = offline.result()
    assert collector.done is True, replay.output()
    # The last observation is decided after pairing_grace; wait until scheme_node has learned every sample. One
    # learner step (a replacement and its structure search) can take many seconds on a busy 2-core machine: the
    # timeout is how long the step may stay the same, not a window for the whole wait.
    assert spin_until(lambda: collector.step == n_steps, timeout=60, progress=lambda: collector.step), (
        collector.step, scheme.output())
    assert spin_until(lambda: len(collector.events) >= len(expected_events), timeout=60,
                      progress=lambda: len(collector.events)), len(collector.events)

    learned = [(e.parent_id, e.child_id, e.description) for e in collector.structure.edges]
    assert learned == expected_edges, scheme.output()
    received = [(e.kind, e.step, e.model) for e in collector.events]
    assert received == expected_events
    assert collector.structure.phase == phase
    print(f"through-graph replay of {n_steps} steps: {replay_seconds:.1f} s until bag_replay/done")


@pytest.mark.parametrize("layout", ["aruco_ros", "apriltag_ros", "mocap", "csv"])
def test_other_stacks_recordings_replay_through_the_nodes_to_the_true_tree(layout, start_node, ros_node, spin_until,
                                                                            tmp_path):
    """bag_replay with a source map feeds another stack's recording (tags on /tf, a motion-capture PoseStamped per
    body, a table) to scheme_node, which learns the true tree."""
    tree = planar_2dof()
    session = make_session(tree, 30, seed=0, sigma_trans=0.01, sigma_rot=np.radians(3.0))  # true from step 4 on
    recording, map_path, params = write_layout(session, tmp_path / layout, layout)
    collector = Collector(ros_node)
    parameters = yaml.safe_load(params.read_text())["/**"]["ros__parameters"]
    scheme = start_node("body_scheme_nodes", "scheme_node", parameters)
    assert spin_until(lambda: collector.structure is not None, timeout=60), scheme.output()
    replay = start_node("body_scheme_nodes", "bag_replay", {"bag_path": str(recording), "source_map": str(map_path),
                                                             "rate": 0.0, "start_delay": 0.5})
    assert spin_until(lambda: collector.done is not None, timeout=60, progress=lambda: collector.step), (
        replay.output(), scheme.output())
    assert collector.done is True and "samples 30" in replay.output(), replay.output()
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: collector.step == 30, timeout=60, progress=lambda: collector.step), scheme.output()
    assert spin_until(lambda: {frozenset((e.parent_id, e.child_id)) for e in collector.structure.edges} == true_edges,
                      timeout=60), scheme.output()
