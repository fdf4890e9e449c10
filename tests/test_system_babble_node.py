"""System test of the graph a real robot uses: babble_node -> sim_node (as a JointTrajectoryController) ->
tracker_node -> scheme_node, as processes over DDS, from scratch."""

from __future__ import annotations

import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from body_scheme_core.control.motion import path_samples
from body_scheme_msgs.msg import BodySchemeStructure
from body_scheme_sim.babbling import CollisionScreen
from body_scheme_sim.robots import ROBOTS_DIR, load_robot
from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS

pytestmark = pytest.mark.system

ROBOT = "arm_4dof"  # the 6-DOF arm learns the same way through the same nodes, in more CI time
MARGIN = 0.05


class Watcher:
    """What the test node sees: the trajectories sim_node receives, the action signals, the structure and
    babble_node's status."""

    def __init__(self, node):
        self.trajectories, self.actions, self.structure, self.babbling, self.joint_states = [], [], None, {}, []
        self.n_babbling = 0  # babble_node statuses received (one a second of its clock)
        node.create_subscription(JointTrajectory, "joint_trajectory_controller/joint_trajectory",
                                 self.trajectories.append, 100)
        node.create_subscription(JointState, "joint_commands", self.actions.append, 100)
        node.create_subscription(JointState, "/joint_states", self.joint_states.append, 1000)
        node.create_subscription(BodySchemeStructure, "body_scheme/structure", self._structure, 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 10)

    def _structure(self, msg):
        self.structure = msg

    def _diagnostics(self, msg):
        for status in msg.status:
            if status.name.endswith(": babbling"):
                self.n_babbling += 1
                self.babbling = {"level": status.level, "message": status.message,
                                 **{kv.key: kv.value for kv in status.values}}

    def edges(self):
        return set() if self.structure is None else {frozenset((e.parent_id, e.child_id))
                                                     for e in self.structure.edges}

    def goals(self):
        return [np.array(t.points[-1].positions) for t in self.trajectories if t.points]


def _call(ros_node, spin_until, service):
    client = ros_node.create_client(Trigger, f"/babble_node/{service}")
    assert client.wait_for_service(timeout_sec=60)
    future = client.call_async(Trigger.Request())
    assert spin_until(future.done, timeout=60)
    return future.result()


def test_babbling_a_controller_learns_the_true_tree_safely_and_obeys_pause_stop_and_error(start_node, ros_node,
                                                                                         spin_until):
    """From scratch through the controller interface: the true tree; every goal sim_node received was inside the
    limits less the margin and collision-free from the previous one; every action signal is a received goal. Then
    pause holds the babbling, resume continues it, stop halts the arm (a trajectory to where it is), a status that stays
    ERROR stops it, and so does a camera that goes quiet."""
    tree = load_robot(ROBOT)
    ids, names = list(tree.marker_ids), list(tree.action_joint_names)
    watcher = Watcher(ros_node)
    start_node("body_scheme_nodes", "scheme_node", {
        "part_ids": ids, "joint_names": names, "action_lower": tree.action_lower.tolist(),
        "action_upper": tree.action_upper.tolist(), "learner.sigma_trans": RENDERED_SIGMA_TRANS,
        "learner.sigma_rot": RENDERED_SIGMA_ROT})
    tracker = start_node("body_scheme_nodes", "tracker_node", {
        "markers_path": str(ROBOTS_DIR / f"{ROBOT}.markers.yaml"), "image_reliability": "reliable"})
    start_node("body_scheme_nodes", "sim_node", {"robot": ROBOT, "perception_mode": "rendered",
                                                 "camera_period": 0.05})
    babble = start_node("body_scheme_nodes", "babble_node", {
        "robot": ROBOT, "max_velocity": 20.0, "max_acceleration": 100.0, "limit_margin": MARGIN, "dwell": 0.1,
        "settle_window": 0.05, "error_hold": 0.5, "start_paused": True,
        # sim_node renders on the same 2 cores as scheme_node and tracker_node: in CI its joint states paused for
        # 3 s, and babble_node saw no observations for 4 s.
        "camera_timeout": 10.0, "joint_state_timeout": 10.0,
        "watch_diagnostics": "/alarm"})  # the test's stand-in for scheme_node's status
    # Resumed once the test sees babble_node's publishers (else the first goal can go out before discovery).
    assert spin_until(lambda: ros_node.count_publishers("joint_trajectory_controller/joint_trajectory") >= 1
                      and ros_node.count_publishers("joint_commands") >= 1, timeout=60), babble.output()
    spin_until(lambda: False, timeout=1.0)
    assert _call(ros_node, spin_until, "resume").success
    true_edges = {frozenset(e) for e in tree.marker_tree_edges()}
    learned = spin_until(lambda: watcher.edges() == true_edges, timeout=240)
    assert learned, (watcher.edges(), len(watcher.actions), babble.output()[-2000:])

    screen = CollisionScreen(ROBOT)
    try:
        previous = np.zeros(len(names))
        for goal in watcher.goals():
            assert np.all(goal >= tree.action_lower + MARGIN - 1e-9) and np.all(goal <= tree.action_upper - MARGIN)
            assert not screen.collides(path_samples(previous, goal))
            previous = goal
    finally:
        screen.close()
    sent = {tuple(np.round(g, 9)) for g in watcher.goals()}
    unsent = [k for k, a in enumerate(watcher.actions) if tuple(np.round(a.position, 9)) not in sent]
    assert watcher.actions and not unsent, (unsent, len(watcher.actions), len(watcher.trajectories))

    # Pause: the current move ends, then nothing is sent; resume: babbling goes on.
    # (Windows counted in babble_node's own statuses, one a second of its clock, not in the test's wall clock.)
    assert _call(ros_node, spin_until, "pause").success
    assert spin_until(lambda: watcher.babbling.get("state") == "paused", timeout=60)
    statuses = watcher.n_babbling
    assert spin_until(lambda: watcher.n_babbling >= statuses + 1, timeout=60)  # what was in flight has arrived
    n, statuses = len(watcher.trajectories), watcher.n_babbling
    assert spin_until(lambda: watcher.n_babbling >= statuses + 2, timeout=60)
    assert len(watcher.trajectories) == n and watcher.babbling.get("state") == "paused"
    assert _call(ros_node, spin_until, "resume").success
    assert spin_until(lambda: len(watcher.trajectories) > n + 2, timeout=60)

    # Stop: one point where the arm is (a JointTrajectoryController rejects an empty trajectory), then nothing; the
    # arm stays there. A hostile joint state at 50 rad just before is refused: the hold stays within the limits.
    n = len(watcher.trajectories)
    hostile = ros_node.create_publisher(JointState, "/joint_states", 10)
    for _ in range(5):
        hostile.publish(JointState(name=names, position=[50.0] + [0.0] * (len(names) - 1)))
        spin_until(lambda: False, timeout=0.05)
    assert _call(ros_node, spin_until, "stop").success
    assert spin_until(lambda: watcher.babbling.get("state") == "stopped", timeout=60)
    statuses = watcher.n_babbling
    assert spin_until(lambda: watcher.n_babbling >= statuses + 1, timeout=60)  # the hold has arrived
    hold = watcher.trajectories[-1]
    assert len(watcher.trajectories) > n and len(hold.points) == 1
    limits = (tree.action_lower + MARGIN - 1e-9, tree.action_upper - MARGIN + 1e-9)
    assert np.all(hold.points[0].positions >= limits[0]) and np.all(hold.points[0].positions <= limits[1])
    assert int(watcher.babbling["driver.joint_states_out_of_range"]) >= 1, watcher.babbling
    n, statuses = len(watcher.trajectories), watcher.n_babbling
    assert spin_until(lambda: watcher.n_babbling >= statuses + 2, timeout=60)
    assert len(watcher.trajectories) == n
    assert np.allclose(watcher.joint_states[-1].position, hold.points[0].positions, atol=0.02)

    # A watched status that stays ERROR stops it (published by the test as scheme_node would publish its own), though
    # a second robot's scheme_node, whose status name contains this one's, says OK in between.
    assert _call(ros_node, spin_until, "resume").success
    assert spin_until(lambda: len(watcher.trajectories) > n + 1 and watcher.babbling.get("state") == "idle",
                      timeout=60)
    alarm = ros_node.create_publisher(DiagnosticArray, "/diagnostics", 10)
    error = DiagnosticArray(status=[DiagnosticStatus(name="/alarm: body scheme", level=DiagnosticStatus.ERROR,
                                                     message="2 local model(s) invalid (adapting)",
                                                     values=[KeyValue(key="step", value="1")])])
    other_robot = DiagnosticArray(status=[DiagnosticStatus(name="/robot2/alarm: body scheme",
                                                           level=DiagnosticStatus.OK)])
    deadline = time.monotonic() + 10
    while watcher.babbling.get("state") != "stopped" and time.monotonic() < deadline:
        alarm.publish(error)
        alarm.publish(other_robot)
        spin_until(lambda: False, timeout=0.2)
    assert watcher.babbling.get("state") == "stopped" and "ERROR" in watcher.babbling["message"], watcher.babbling
    assert watcher.babbling["level"] == DiagnosticStatus.ERROR

    # The camera goes quiet (the tracker dies): babbling stops within camera_timeout.
    ok = DiagnosticArray(status=[DiagnosticStatus(name="/alarm: body scheme", level=DiagnosticStatus.OK)])
    alarm.publish(ok)
    assert _call(ros_node, spin_until, "resume").success
    assert spin_until(lambda: watcher.babbling.get("state") == "idle", timeout=60)
    tracker.stop()
    assert spin_until(lambda: "camera is quiet" in watcher.babbling.get("message", ""), timeout=60), \
        watcher.babbling


def test_active_babbling_follows_the_scheme_nodes_suggestions_and_learns_the_true_tree(start_node, ros_node,
                                                                                        spin_until):
    """mode active with scheme_node's exploration on: the graph learns the true tree from scratch, commands are
    scheme_node's suggestions, or counted fallbacks and refusals (suggestions past babble_node's margin: random
    draws instead), after the first, random one, and every goal stays within the limits less the margin. The camera
    is sim_node's noise model (images and the tracker are the test above's; here they would only cost CI time)."""
    robot = ROBOT
    tree = load_robot(robot)
    ids, names = list(tree.marker_ids), list(tree.action_joint_names)
    watcher = Watcher(ros_node)
    suggestions = []
    ros_node.create_subscription(JointState, "body_scheme/exploration_command", suggestions.append, 100)
    sigma_trans, sigma_rot = 0.01, 0.05
    start_node("body_scheme_nodes", "scheme_node", {
        "part_ids": ids, "joint_names": names, "action_lower": tree.action_lower.tolist(),
        "action_upper": tree.action_upper.tolist(), "learner.sigma_trans": sigma_trans,
        "learner.sigma_rot": sigma_rot, "exploration": True,
        "pairing_grace": 0.05})  # the noise model's observations come at once: a suggestion per step, sooner
    sim = start_node("body_scheme_nodes", "sim_node", {"robot": robot, "perception_mode": "noise",
                                                       "sigma_trans": sigma_trans, "sigma_rot": sigma_rot,
                                                       "camera_period": 0.02})
    babble = start_node("body_scheme_nodes", "babble_node", {
        "robot": robot, "max_velocity": 20.0, "max_acceleration": 100.0, "limit_margin": MARGIN, "dwell": 0.05,
        "settle_window": 0.03, "mode": "active", "camera_timeout": 10.0,  # the watchdogs are tested elsewhere
        "joint_state_timeout": 10.0, "preflight_skip": ["camera_info"]})  # the noise model has no CameraInfo
    true_edges = {frozenset(e) for e in tree.marker_tree_edges()}
    assert spin_until(lambda: watcher.edges() == true_edges, timeout=240), (
        watcher.edges(), babble.output()[-2000:], sim.output()[-1500:])
    assert spin_until(lambda: "suggestions_followed" in watcher.babbling, timeout=60), watcher.babbling
    followed = int(watcher.babbling["suggestions_followed"])
    assert suggestions and followed >= 10, watcher.babbling
    for goal in watcher.goals():
        assert np.all(goal >= tree.action_lower + MARGIN - 1e-9) and np.all(goal <= tree.action_upper - MARGIN)
