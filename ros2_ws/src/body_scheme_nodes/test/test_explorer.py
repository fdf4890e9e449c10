"""scheme_node's exploration topics (explorer.py) with the real rclpy, in-process: requests to explore near a
posture are served, replaced or refused, and each is answered once."""

import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_msgs.msg import ExploreNear
from body_scheme_nodes.explorer import SchemeExplorer
from body_scheme_nodes.settings import SchemeSettings

TREE = planar_2dof()


@pytest.fixture(scope="module")
def learned():
    """The 2-DOF arm learnt from 60 random commands: a learner with a body scheme and a joint fit."""
    session = make_session(TREE, 60, 0)
    learner = BodySchemeLearner(TREE.marker_ids, TREE.n_actions, action_lower=TREE.action_lower,
                                action_upper=TREE.action_upper)
    for t in range(60):
        learner.update(session.actions[t], session.observations[t])
    return learner


@pytest.fixture
def ros(context):
    """A node with a SchemeExplorer factory, and the answers it published."""
    node = rclpy.create_node("explorer_test", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    answers, snapshots, commands = [], [], []
    node.create_subscription(ExploreNear, "body_scheme/explore_near/done", answers.append, 10)
    node.create_subscription(JointState, "body_scheme/exploration_command", commands.append, 10)

    def make(exploration=True):
        settings = SchemeSettings(tuple(TREE.marker_ids), tuple(TREE.action_joint_names), tuple(TREE.action_lower),
                                  tuple(TREE.action_upper), BodySchemeConfig(), exploration=exploration,
                                  exploration_candidates=8)
        return SchemeExplorer(node, settings, 0.02, lambda: snapshots.append(True))

    def received(n, messages=answers):
        """The answers (or other ``messages``) after spinning until ``n`` came or 60 s passed, then 0.2 s more (so
        that one too many would show)."""
        deadline = time.monotonic() + 60.0
        while len(messages) < n and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        settle = time.monotonic() + 0.2
        while time.monotonic() < settle:
            executor.spin_once(timeout_sec=0.05)
        return messages

    make.commands = commands
    yield make, received, snapshots
    executor.shutdown()
    node.destroy_node()


def request(positions, samples=3, radius=0.05, names=None, sec=1):
    msg = ExploreNear(joint_names=list(names or TREE.action_joint_names), positions=[float(v) for v in positions],
                      samples=samples, radius=radius)
    msg.header.stamp.sec = sec
    return msg


def test_the_next_samples_are_drawn_near_the_posture_then_the_joint_fit_runs_and_the_request_is_answered(ros,
                                                                                                          learned):
    make, received, snapshots = ros
    explorer, learner = make(), BodySchemeLearner.from_state(learned.to_state())
    answer, span = np.array([0.3, -0.4]), TREE.action_upper - TREE.action_lower
    explorer._on_explore_near(request(answer, samples=3))
    session = make_session(TREE, 4, 5)
    for k in range(3):  # three suggestions near the answer, each learnt; no answer yet
        assert explorer.after_learning(learner, float(k), session.actions[k]) == []
        learner.update(session.actions[k], session.observations[k])
    assert received(0) == [] and snapshots == [] and explorer._to_finish is not None
    step = learner.step
    explorer.after_learning(learner, 3.0, session.actions[3])  # the last one was learnt: fit, snapshot, answer
    answers = received(1)
    assert len(answers) == 1 and answers[0].outcome == "" and answers[0].step == step and snapshots == [True]
    assert learner.state.calibrated.step == step - 1
    commands = received(4, make.commands)
    assert len(commands) == 4
    for command in commands[:3]:
        assert np.all(np.abs(np.array(command.position) - answer) <= 0.05 * span + 1e-12), command.position
    _, values = explorer.diagnostics()
    assert values["exploration.near_requests"] == 1 and values["exploration.near_answered"] == 1


def test_requests_that_cannot_be_served_are_answered_at_once_with_why(ros, learned):
    make, received, _ = ros
    off = make(exploration=False)
    off._on_explore_near(request([0.1, 0.2], sec=1))
    assert "exploration is false" in received(1)[0].outcome
    on = make()
    on._on_explore_near(request([0.1], names=["elbow"], sec=2))  # a joint scheme_node does not have
    on._on_explore_near(request([0.1, np.nan], sec=3))
    on._on_explore_near(request([0.1, 0.2], samples=0, sec=4))
    answers = received(4)[1:]
    assert [a.header.stamp.sec for a in answers] == [2, 3, 4]
    assert all(a.outcome.startswith("refused:") for a in answers), [a.outcome for a in answers]
    rejected, _ = on.diagnostics()
    assert rejected["bad_explore_near"] == 3


def test_a_newer_request_replaces_an_older_one_and_both_are_answered(ros, learned):
    make, received, _ = ros
    explorer, learner = make(), BodySchemeLearner.from_state(learned.to_state())
    explorer._on_explore_near(request([0.1, 0.2], sec=1))
    explorer._on_explore_near(request([0.3, 0.4], sec=2))  # before the learning thread took the first
    assert received(1)[0].header.stamp.sec == 1 and "before it started" in received(1)[0].outcome
    explorer.after_learning(learner, 0.0, np.zeros(2))  # the second is being explored
    explorer._on_explore_near(request([0.5, 0.6], sec=3))
    explorer.after_learning(learner, 1.0, np.zeros(2))  # the third replaces it
    answers = received(2)
    assert answers[1].header.stamp.sec == 2 and answers[1].outcome == "replaced by a newer request"
    assert np.allclose(explorer._focus[1].actions, [0.5, 0.6])


def test_no_feasible_posture_near_it_is_answered_and_exploration_goes_on(ros, learned, monkeypatch):
    make, received, _ = ros
    explorer, learner = make(), BodySchemeLearner.from_state(learned.to_state())
    explorer._on_explore_near(request([0.1, 0.2], sec=1))
    explorer.policy.feasible = lambda C: np.zeros(len(C), dtype=bool)  # e.g. a collision screen refusing all
    for k in range(2):  # tried again at the next samples
        explorer.after_learning(learner, float(k), np.zeros(2))
    assert received(0) == [] and explorer._focus is not None
    explorer.after_learning(learner, 2.0, np.zeros(2))
    answers = received(1)
    assert len(answers) == 1 and "no feasible posture" in answers[0].outcome and explorer._focus is None


def test_a_reset_cancels_the_exploration_under_way_and_a_learner_without_a_scheme_has_no_joint_fit(ros, learned):
    make, received, _ = ros
    explorer, learner = make(), BodySchemeLearner.from_state(learned.to_state())
    explorer._on_explore_near(request([0.1, 0.2], samples=1, sec=1))
    explorer.after_learning(learner, 0.0, np.zeros(2))  # its one suggestion was drawn: the joint fit is next
    explorer._on_explore_near(request([0.3, 0.4], sec=2))  # taken up, not started
    explorer.cancel(0, "the learner was reset")
    answers = received(2)
    assert sorted(a.header.stamp.sec for a in answers) == [1, 2]
    assert all(a.outcome == "cancelled: the learner was reset" for a in answers)
    fresh = BodySchemeLearner(TREE.marker_ids, TREE.n_actions)
    explorer._on_explore_near(request([0.1, 0.2], samples=1, sec=3))
    explorer.after_learning(fresh, 0.0, np.zeros(2))
    explorer.after_learning(fresh, 1.0, np.zeros(2))
    assert received(3)[2].outcome == "no joint fit: the learner has no body scheme"


def test_every_request_sent_is_answered_counted_lost_or_refused_unread_and_no_refusal_echoes_it(ros):
    """A flood of 300 requests, one too large to read and one naming 20,000 joints (an 80 MB request froze the node
    14 s, and its refusal echoed it whole): answered + lost + refused = sent; the refusal names the request by its
    header, carries no arrays and says why in a few hundred characters."""
    make, received, _ = ros
    explorer = make()
    node = explorer.node
    publisher = node.create_publisher(ExploreNear, "body_scheme/explore_near", 1000)
    deadline = time.monotonic() + 60
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    big = request([0.0] * 20_000, names=[f"joint_{k}" for k in range(20_000)], sec=7)
    publisher.publish(big)
    huge = request([0.0] * 200_000, sec=8)  # 1.6 MB: over max_message_bytes
    publisher.publish(huge)
    deadline = time.monotonic() + 60
    while explorer.diagnostics()[0]["oversized_message"] == 0 and time.monotonic() < deadline:
        explorer.take_requests()  # the two are taken before the flood could overwrite them
        time.sleep(0.01)
    refusal = next(a for a in received(1) if a.header.stamp.sec == 7)
    assert list(refusal.joint_names) == [] and list(refusal.positions) == [] and len(refusal.outcome) < 400
    assert refusal.outcome.startswith("refused: JointState"), refusal.outcome
    for k in range(300):
        publisher.publish(request([0.1, 0.2], sec=100 + k))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        explorer.take_requests()
        rejected, values = explorer.diagnostics()
        if values["exploration.near_requests"] + values["lost.explore_near_messages"] + \
                rejected["oversized_message"] == 302:
            break
        time.sleep(0.01)
    rejected, values = explorer.diagnostics()  # each request replaced the one before: only the newest waits
    assert rejected["oversized_message"] == 1 and rejected["bad_explore_near"] == 1
    assert values["exploration.near_answered"] == values["exploration.near_requests"] - 1 > 0
    assert values["exploration.near_requests"] + values["lost.explore_near_messages"] + 1 == 302
