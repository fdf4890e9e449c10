"""System tests of control_node: the installed executable as its own process, IK requests over real DDS."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import JointState

from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.world import Body, ObservationModel, default_world2root, planar_2dof
from body_scheme_msgs.msg import IKResult, IKTarget, ModelSnapshot
from body_scheme_nodes import conversions
from body_scheme_nodes.qos import LATCHED

pytestmark = pytest.mark.system



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
    assert spin_until(lambda: targets.get_subscription_count() > 0, timeout=60), process.output()
    send([0.0, 0.0, 1.0])
    assert spin_until(lambda: len(results) == 1, timeout=60), process.output()
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
    assert spin_until(lambda: len(results) == 2 and commands, timeout=60), process.output()
    assert results[1].success, results[1].reason
    _, commanded = conversions.actions_from_joint_state(commands[-1], tree.action_joint_names)
    reached = (world2root @ tree.marker_poses(commanded)[end_effector])[:3, 3]
    assert np.linalg.norm(reached - target) < 0.002
    assert np.all(commanded >= tree.action_lower) and np.all(commanded <= tree.action_upper)

    # Out of reach: failure with a reason, and no new command.
    n_commands = len(commands)
    send(target + [5.0, 0.0, 0.0])
    assert spin_until(lambda: len(results) == 3, timeout=60), process.output()
    assert not results[2].success and "unreachable" in results[2].reason
    assert results[2].residual > 1.0 and len(commands) == n_commands

    # A part the body scheme does not have: refused without evaluating, so no residual and no actions.
    send(target, part_id=99)
    assert spin_until(lambda: len(results) == 4, timeout=60), process.output()
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
    assert spin_until(lambda: targets.get_subscription_count() > 0, timeout=60), process.output()
    spin_until(lambda: False, timeout=1.0)  # the latched snapshot reaches control_node
    msg = IKTarget(part_id=-1)
    msg.header.frame_id = "camera"
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in target)
    for _ in range(30):  # until the snapshot and sim_node's first joint state reached control_node (a loaded machine)
        results.clear()
        targets.publish(msg)
        assert spin_until(lambda: results, timeout=60), process.output()
        if not results[0].reason.endswith("no joint state yet") and \
                not results[0].reason.startswith("no body scheme yet"):
            break
        spin_until(lambda: False, timeout=0.5)
    result = results[0]
    assert result.success and result.executed, result.reason
    assert result.reached_source == "observed" and result.reached_error < 0.02, result
    assert len(trajectories) == 1 and trajectories[0].points
    seen = len(truth)  # the arm has settled: the next ground-truth frames show where it stands
    assert spin_until(lambda: len(truth) > seen, timeout=60), "no ground truth from sim_node"
    _, last = conversions.observations_from_msg(truth[-1])[:2]
    assert np.linalg.norm(last[end_effector][:3, 3] - target) < 0.010


class Follower:
    """An arm under active babbling, as babble_node's ``mode: active`` drives it: it executes scheme_node's latest
    suggestion (a uniform draw when none came within ``patience`` s) and publishes the command, then what the
    camera sees after it."""

    def __init__(self, node, tree, seed, patience=0.3):
        from body_scheme_msgs.msg import MarkerPoses

        self.node, self.tree, self.patience = node, tree, patience
        self.body, self.camera = Body(tree), ObservationModel(0.02, np.radians(5.0), 1.0, seed)
        self.rng = np.random.default_rng(seed)
        self.commands = node.create_publisher(JointState, "joint_commands", 10)
        self.observations = node.create_publisher(MarkerPoses, "observations", 10)
        self.suggestions = []
        node.create_subscription(JointState, "body_scheme/exploration_command", self.suggestions.append, 100)
        self._used, self._last = 0, -np.inf

    def __call__(self):
        """Execute the next suggestion as soon as it is there, or a uniform draw after ``patience`` s."""
        now = self.node.get_clock().now().nanoseconds * 1e-9
        if len(self.suggestions) > self._used:
            _, a = conversions.actions_from_joint_state(self.suggestions[-1], self.tree.action_joint_names)
            self._used = len(self.suggestions)
        elif now - self._last > self.patience:
            a = self.rng.uniform(self.tree.action_lower, self.tree.action_upper)
        else:
            return
        self._last = now
        self.commands.publish(conversions.joint_state_msg(now, self.tree.action_joint_names, a))
        seen = self.camera.observe_array(self.body.true_marker_array(a[None]), self.tree.marker_ids)[0]
        self.observations.publish(conversions.marker_poses_msg(now + 0.005, "camera", seen))


def test_an_unsure_answer_is_explored_near_then_solved_again(start_node, ros_node, spin_until):
    """explore_when_unsure: an answer that reaches the target but is not sure enough asks scheme_node to explore
    near it; scheme_node's next suggestions lie near the answer, then it runs the joint fit and answers, and
    control_node solves the request again on the new snapshot, once. A request scheme_node cannot serve is answered
    with the reason and counted."""
    from diagnostic_msgs.msg import DiagnosticArray

    from body_scheme_msgs.msg import BodySchemeStructure, ExploreNear

    tree = planar_2dof()
    end_effector, samples, radius = max(tree.marker_ids), 4, 0.05
    scheme_node = start_node("body_scheme_nodes", "scheme_node", {
        "part_ids": [int(i) for i in tree.marker_ids], "joint_names": list(tree.action_joint_names),
        "action_lower": tree.action_lower.tolist(), "action_upper": tree.action_upper.tolist(),
        "pairing_grace": 0.05, "exploration": True, "exploration_candidates": 16})
    control = start_node("body_scheme_nodes", "control_node", {
        "part_id": int(end_effector), "tolerance": 0.003, "explore_when_unsure": True,
        "explore_samples": samples, "explore_radius": radius})
    results, requests, answers, structure, diagnostics = [], [], [], [], {}
    ros_node.create_subscription(IKResult, "ik_result", results.append, 10)
    ros_node.create_subscription(ExploreNear, "body_scheme/explore_near", requests.append, 10)
    ros_node.create_subscription(ExploreNear, "body_scheme/explore_near/done", answers.append, 10)
    ros_node.create_subscription(BodySchemeStructure, "body_scheme/structure", structure.append, LATCHED)
    snapshots = []
    ros_node.create_subscription(ModelSnapshot, "body_scheme/snapshot", snapshots.append, LATCHED)
    ros_node.create_subscription(DiagnosticArray, "/diagnostics", lambda msg: diagnostics.update(
        {s.name: {kv.key: kv.value for kv in s.values} for s in msg.status}), 10)
    follower = Follower(ros_node, tree, seed=3)
    true_edges = {frozenset(e) for e in tree.marker_tree_edges()}

    def learned():
        return structure and structure[-1].phase != "bootstrapping" and all(e.valid for e in structure[-1].edges) \
            and {frozenset((e.parent_id, e.child_id)) for e in structure[-1].edges} == true_edges

    assert spin_until(learned, timeout=90, during=follower), scheme_node.output()[-3000:]
    for _ in range(40):  # a few more samples: a joint fit with a covariance
        spin_until(lambda: False, timeout=0.05, during=follower)

    targets = ros_node.create_publisher(IKTarget, "ik_target", 10)
    assert spin_until(lambda: targets.get_subscription_count() > 0, timeout=60), control.output()
    # The target is a point the learned model reaches (the true arm's point can lie a few mm off the plane of a
    # model learnt at 20 mm noise, past the 3 mm tolerance): no samples until the last joint fit's snapshot is out
    # and stays the newest, so control_node solves on the same model.
    for _ in range(15):
        seen = len(snapshots)
        spin_until(lambda: False, timeout=2.0)
        if snapshots and len(snapshots) == seen:
            break
    else:
        raise AssertionError(f"no snapshot, or one every 2 s without new samples: {len(snapshots)}")
    scheme, world2root, _, _ = conversions.scheme_from_snapshot(snapshots[-1])
    target = IKTarget(part_id=-1)
    target.header.frame_id = "camera"
    reached = world2root @ scheme.predict(np.array([0.5, -0.8]))[end_effector]
    target.position.x, target.position.y, target.position.z = (float(v) for v in reached[:3, 3])
    targets.publish(target)
    assert spin_until(lambda: results, timeout=60), control.output()
    first = results[0]
    assert first.converged and not first.success and f"exploring {samples} postures near it" in first.reason, first
    assert first.explored_samples == 0
    assert spin_until(lambda: answers and len(results) == 2, timeout=60, during=follower), (
        results, answers, control.output()[-2000:], scheme_node.output()[-2000:])
    assert len(requests) == 1 and answers[0].outcome == "" and answers[0].header.stamp == requests[0].header.stamp
    span = tree.action_upper - tree.action_lower
    near = [s for s in follower.suggestions
            if np.all(np.abs(np.array(s.position) - np.array(first.actions)) <= radius * span + 1e-9)]
    assert len(near) >= samples, f"{len(near)} of {len(follower.suggestions)} suggestions near the answer"
    second = results[1]
    assert second.explored_samples == samples and second.reason.startswith(f"after exploring {samples} postures")
    assert "exploring" not in second.reason.split(":", 1)[1], second.reason  # once, not again
    assert spin_until(lambda: diagnostics.get("/control_node: control", {}).get("explored") == "1"
                      and diagnostics.get("/scheme_node: body scheme", {}).get("exploration.near_answered") == "1",
                      timeout=60, during=follower), diagnostics

    # A request scheme_node cannot serve (joints it does not have): answered at once with why, and counted.
    bad = ExploreNear(joint_names=["elbow"], positions=[0.1], samples=2, radius=0.1)
    bad.header.stamp.sec = 7
    pub = ros_node.create_publisher(ExploreNear, "body_scheme/explore_near", 10)
    assert spin_until(lambda: pub.get_subscription_count() > 0, timeout=60)
    pub.publish(bad)
    assert spin_until(lambda: len(answers) == 2, timeout=60, during=follower), answers
    assert answers[1].header.stamp.sec == 7 and answers[1].outcome.startswith("refused:") and "lacks" in \
        answers[1].outcome, answers[1].outcome
    assert spin_until(lambda: diagnostics.get("/scheme_node: body scheme", {}).get("rejected.bad_explore_near")
                      == "1", timeout=60, during=follower), diagnostics
    assert len(results) == 2  # control_node ignores answers to requests it did not make


def test_an_unsure_answer_is_answered_again_when_exploring_is_refused_or_unanswered(start_node, ros_node,
                                                                                    spin_until):
    """explore_when_unsure without a scheme_node that explores: a refusal, or no answer within explore_timeout,
    still gives the request its second answer, which says why it was not explored; answers to requests
    control_node did not make change nothing."""
    from body_scheme_core.learning import BodySchemeLearner
    from body_scheme_core.world import make_session
    from body_scheme_msgs.msg import ExploreNear

    tree = planar_2dof()
    end_effector = max(tree.marker_ids)
    session = make_session(tree, 60, 0)  # the paper's noise: an unsure body scheme
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    for t in range(60):
        learner.update(session.actions[t], session.observations[t])
    control = start_node("body_scheme_nodes", "control_node", {
        "part_id": int(end_effector), "tolerance": 0.003, "explore_when_unsure": True, "explore_samples": 3,
        "explore_timeout": 6.0})  # well past the refusal's delivery on a loaded machine
    results, requests = [], []
    ros_node.create_subscription(IKResult, "ik_result", results.append, 10)
    ros_node.create_subscription(ExploreNear, "body_scheme/explore_near", requests.append, 10)
    answers = ros_node.create_publisher(ExploreNear, "body_scheme/explore_near/done", 10)
    targets = ros_node.create_publisher(IKTarget, "ik_target", 10)
    snapshots = ros_node.create_publisher(ModelSnapshot, "body_scheme/snapshot", LATCHED)
    snapshots.publish(conversions.snapshot_msg(0.0, "camera", learner.step, learner.body_scheme,
                                               tree.action_joint_names, tree.action_lower, tree.action_upper,
                                               learner.root_pose))
    assert spin_until(lambda: targets.get_subscription_count() > 0 and answers.get_subscription_count() > 0,
                      timeout=60), control.output()
    spin_until(lambda: False, timeout=1.0)  # the latched snapshot reaches control_node

    def send():
        target = IKTarget(part_id=-1)
        target.header.frame_id = "camera"
        p = (learner.root_pose @ learner.body_scheme.predict(np.array([0.5, -0.8]))[end_effector])[:3, 3]
        target.position.x, target.position.y, target.position.z = (float(v) for v in p)
        targets.publish(target)

    send()
    assert spin_until(lambda: results and requests, timeout=60), control.output()
    assert "exploring 3 postures near it" in results[0].reason, results[0].reason
    stranger = ExploreNear(outcome="refused: not yours")
    stranger.header.stamp.sec = 12345
    answers.publish(stranger)  # an answer to another control_node's request
    refusal = ExploreNear(header=requests[0].header, outcome="refused: exploration is false on this scheme_node")
    answers.publish(refusal)
    assert spin_until(lambda: len(results) == 2, timeout=60), control.output()
    assert results[1].reason.startswith("not explored (refused: exploration is false") and \
        results[1].explored_samples == 0, results[1].reason
    spin_until(lambda: False, timeout=0.5)
    assert len(results) == 2, [r.reason for r in results]  # the stranger's answer changed nothing

    send()  # no answer this time
    assert spin_until(lambda: len(results) == 4, timeout=60), control.output()
    assert "exploring 3 postures near it" in results[2].reason
    assert results[3].reason.startswith("not explored (no answer from scheme_node within 6.0 s)"), results[3].reason


def test_every_target_is_answered_or_counted_and_every_command_is_within_the_limits(start_node, ros_node,
                                                                                    spin_until):
    """3,000 targets at once (2,805 got no IKResult before): each one taken is answered (solved, refused or "busy"),
    each one DDS overwrote is counted (lost.ik_target_messages), each one over max_message_bytes is refused unread;
    they add up to what was sent. A start command of 50 rad (anyone may publish one) never makes an interpolated
    command leave the joint limits."""
    from diagnostic_msgs.msg import DiagnosticArray

    tree = planar_2dof()
    end_effector = max(tree.marker_ids)
    process = start_node("body_scheme_nodes", "control_node", {"part_id": end_effector, "tolerance": 0.002,
                                                                "trajectory_steps": 4, "max_message_bytes": 65536})
    results, commands, status = [], [], {}
    ros_node.create_subscription(IKResult, "ik_result", results.append, 5000)
    ros_node.create_subscription(JointState, "joint_commands", commands.append, 100)

    def on_diagnostics(msg):
        for s in msg.status:
            if s.name == "/control_node: control":
                status.clear()
                status.update({kv.key: kv.value for kv in s.values})

    ros_node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    targets = ros_node.create_publisher(IKTarget, "ik_target", 5000)
    others = ros_node.create_publisher(JointState, "joint_commands", 10)
    snapshots = ros_node.create_publisher(ModelSnapshot, "body_scheme/snapshot", LATCHED)
    assert spin_until(lambda: targets.get_subscription_count() > 0 and status, timeout=60), process.output()

    # The limits: someone else's command far outside them is the start of the next interpolation.
    world2root = default_world2root()
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    snapshots.publish(conversions.snapshot_msg(0.0, "camera", 1, scheme, tree.action_joint_names,
                                               tree.action_lower, tree.action_upper, world2root))
    spin_until(lambda: False, timeout=1.0)
    others.publish(conversions.joint_state_msg(0.0, tree.action_joint_names, [50.0, -7.0]))
    spin_until(lambda: False, timeout=0.5)
    commands.clear()
    target = IKTarget(part_id=-1)
    target.header.frame_id = "camera"
    target.position.x, target.position.y, target.position.z = (float(v) for v in (
        world2root @ tree.marker_poses(np.array([0.4, -0.7]))[end_effector])[:3, 3])
    targets.publish(target)
    assert spin_until(lambda: len(commands) == 4, timeout=60), process.output()
    for command in commands:
        _, a = conversions.actions_from_joint_state(command, tree.action_joint_names)
        assert np.all(a >= tree.action_lower) and np.all(a <= tree.action_upper), a

    # The flood, and three targets too large to read.
    results.clear()
    for _ in range(3000):
        targets.publish(target)
    huge = IKTarget(part_id=-1)
    huge.header.frame_id = "x" * 100_000
    for _ in range(3):
        targets.publish(huge)

    def accounted():
        if not status:
            return False
        taken, lost = int(status["received"]), int(status["lost.ik_target_messages"])
        answered = int(status["requests"]) - 1 + int(status["busy"])  # solved or busy, the flood's
        return (taken + lost + int(status["rejected.oversized_message"]) == 3004
                and len(results) == taken - 1 == answered)

    def progress():  # the node still taking, counting or answering: waited for however slow the machine is
        return tuple(status.get(key) for key in ("received", "lost.ik_target_messages", "busy")), len(results)

    assert spin_until(accounted, timeout=120, progress=progress), (status, len(results), process.output()[-2000:])
    assert int(status["rejected.oversized_message"]) == 3 and process.running()
    assert sum(r.reason.startswith("busy") for r in results) == int(status["busy"])
