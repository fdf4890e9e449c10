"""The exploration policy (exploration.py): feasible, informative next commands."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from body_scheme_core.control.exploration import ExplorationPolicy, NearFocus, explore_near, in_camera_view
from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.prediction.uncertainty import parameter_jacobian
from body_scheme_core.world import Body, ObservationModel, make_session, planar_2dof


@pytest.fixture(scope="module")
def learned():
    """The 2-DOF arm learned from 60 random commands (the paper's noise): a learner with a joint fit."""
    tree = planar_2dof()
    session = make_session(tree, 60, 0)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    for t in range(60):
        learner.update(session.actions[t], session.observations[t])
    return tree, learner


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-3, 3), st.floats(0, 2)), min_size=1, max_size=6), st.integers(0, 2**16),
       st.floats(-1.0, 1.0))
def test_never_outside_the_limits_nor_refused_by_the_feasibility_callback(joints, seed, cut):
    """Whatever the limits and a callback that refuses half the space (first joint below ``cut`` of its range):
    the suggestion lies within the limits and is one the callback accepts, or None (counted) when none is."""
    lower = np.array([lo for lo, _ in joints])
    upper = lower + np.array([width for _, width in joints])
    threshold = lower[0] + (cut + 1.0) / 2.0 * (upper[0] - lower[0])

    def feasible(C):
        return C[:, 0] >= threshold

    policy = ExplorationPolicy(lower, upper, n_candidates=32, feasible=feasible, rng=seed)
    for _ in range(2):
        a = policy.suggest(current=lower)
        if a is None:
            assert policy.n_infeasible >= 1
            continue
        assert np.all(a >= lower) and np.all(a <= upper) and feasible(a[None])[0]


def test_without_a_body_scheme_it_babbles_uniformly():
    """Before the body scheme exists the suggestion is a uniform draw, a travel cost notwithstanding: over many,
    every tenth of each range gets its share (within a factor 2)."""
    policy = ExplorationPolicy([0.0, -1.0], [1.0, 1.0], n_candidates=8, travel_weight=10.0, rng=0)
    draws = np.array([policy.suggest(current=[0.0, -1.0]) for _ in range(2000)])
    for k, (lo, hi) in enumerate(([0.0, 1.0], [-1.0, 1.0])):
        counts, _ = np.histogram(draws[:, k], bins=10, range=(lo, hi))
        assert counts.min() > 100 and counts.max() < 400


def test_with_a_body_scheme_it_picks_the_most_informative_posture_unless_travel_costs(learned):
    """On a learned 2-DOF arm the suggestion maximises the expected fall of the variance over the candidates; a high
    travel weight keeps it near the current posture."""
    tree, learner = learned
    scheme = learner.body_scheme
    policy = ExplorationPolicy(tree.action_lower, tree.action_upper, n_candidates=64, rng=3)
    a = policy.suggest(scheme)
    draws = np.random.default_rng(3)
    draws.uniform(tree.action_lower, tree.action_upper, size=(64, 2))  # the policy's reference postures come first
    candidates = draws.uniform(tree.action_lower, tree.action_upper, size=(64, 2))
    scores = policy.information(candidates, scheme)
    assert np.allclose(a, candidates[np.argmax(scores)]) and np.mean(scores) == pytest.approx(1.0)
    assert scores.max() > 1.2 * scores.min()  # the postures differ, or the test would prove nothing
    current = np.zeros(2)
    near = ExplorationPolicy(tree.action_lower, tree.action_upper, travel_weight=100.0, rng=3).suggest(
        scheme, current=current)
    assert np.linalg.norm(near - current) < np.linalg.norm(a - current)


def test_the_score_is_the_fall_of_the_reference_variance_after_one_observation(learned):
    """Each candidate's score is proportional to ``sum over the reference postures of tr(J_r (S - S') J_r')``,
    ``S'`` the covariance after observing every part at the candidate (a Kalman update, one candidate at a time)."""
    tree, learner = learned
    scheme = learner.body_scheme
    policy = ExplorationPolicy(tree.action_lower, tree.action_upper, n_reference=5, noise=0.02, rng=4)
    candidates = np.random.default_rng(5).uniform(tree.action_lower, tree.action_upper, size=(6, 2))
    S = scheme.param_covariance[1]
    Jr = parameter_jacobian(scheme, policy.reference).reshape(-1, S.shape[0])
    falls = []
    for c in candidates:
        Jc = parameter_jacobian(scheme, c[None]).reshape(-1, S.shape[0])
        after = S - S @ Jc.T @ np.linalg.solve(Jc @ S @ Jc.T + 0.02**2 * np.eye(Jc.shape[0]), Jc @ S)
        falls.append(np.trace(Jr @ (S - after) @ Jr.T))
    np.testing.assert_allclose(policy.information(candidates, scheme), np.array(falls) / np.mean(falls), rtol=1e-6)


@settings(max_examples=20, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.01, 0.5), st.integers(0, 2**16))
def test_near_a_posture_it_stays_within_the_radius_and_the_limits(u, v, radius, seed):
    """``near`` (clipped into the limits) draws candidates within ``radius`` of each joint's range around it."""
    lower, upper = np.array([-1.0, 0.0]), np.array([1.0, 3.0])
    near = np.array([-1.5 + 3.0 * u, -0.5 + 4.0 * v])  # may lie outside the limits
    a = ExplorationPolicy(lower, upper, n_candidates=16, rng=seed).suggest(near=near, radius=radius)
    centre = np.clip(near, lower, upper)
    assert np.all(a >= lower) and np.all(a <= upper)
    assert np.all(np.abs(a - centre) <= radius * (upper - lower) + 1e-12)


def test_explore_near_observes_each_chosen_command_then_refits(learned):
    """``explore_near`` executes and observes ``n_samples`` commands near the answer, the learner learns each, and
    its joint fit runs at the last of them."""
    tree, learner = learned
    learner = BodySchemeLearner.from_state(learner.to_state())
    body, observer = Body(tree), ObservationModel(0.01, 0.05, 1.0, np.random.default_rng(0))
    commanded = []

    def observe(a):
        commanded.append(a)
        return observer.observe_array(body.true_marker_array(a[None]), tree.marker_ids)[0]

    answer, step = np.array([0.3, -0.4]), learner.step
    policy = ExplorationPolicy(tree.action_lower, tree.action_upper, rng=0)
    explore_near(learner, policy, answer, observe, n_samples=4, radius=0.05)
    span = tree.action_upper - tree.action_lower
    assert len(commanded) == 4 and learner.step == step + 4
    assert all(np.all(np.abs(a - answer) <= 0.05 * span + 1e-12) for a in commanded)
    assert learner.state.calibrated.step == learner.step - 1
    with pytest.raises(InvalidInputError, match="n_samples"):
        explore_near(learner, policy, answer, observe, n_samples=0)


def test_a_near_focus_draws_its_samples_near_the_posture_then_is_done():
    """NearFocus hands out exactly ``n_samples`` suggestions within ``radius`` of the posture, none after; a
    suggestion that finds no feasible candidate is not counted; a posture of another size is refused."""
    lower, upper = np.array([-1.0, 0.0, -2.0]), np.array([1.0, 3.0, 2.0])
    policy, answer = ExplorationPolicy(lower, upper, n_candidates=8, rng=1), np.array([0.5, 2.9, -1.0])
    focus = NearFocus(answer, n_samples=3, radius=0.05)
    assert focus.suggest(policy, feasible=lambda C: np.zeros(len(C), bool)) is None and focus.left == 3
    drawn = [focus.suggest(policy) for _ in range(3)]
    assert focus.done and focus.suggest(policy) is None
    for a in drawn:
        assert np.all(np.abs(a - answer) <= 0.05 * (upper - lower) + 1e-12)
        assert np.all(a >= lower) and np.all(a <= upper)
    with pytest.raises(InvalidInputError, match="actions"):
        NearFocus([0.0, 1.0]).suggest(policy)


@pytest.mark.parametrize("args, match", [
    (([0.0, np.nan],), "finite"), (([[0.0]],), "finite"), (([0.0], 0), "n_samples"), (([0.0], True), "n_samples"),
    (([0.0], 2, 0.0), "radius"), (([0.0], 2, 1.5), "radius")])
def test_a_bad_near_focus_is_refused(args, match):
    with pytest.raises(InvalidInputError, match=match):
        NearFocus(*args)


def test_in_camera_view_keeps_the_postures_whose_markers_the_camera_would_see(learned):
    """The callback agrees with projecting each part's predicted position by hand, refuses some postures of a camera
    that sees part of the workspace, and the policy never suggests one it refuses."""
    tree, learner = learned
    scheme = learner.body_scheme
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    world2root = np.eye(4)
    world2root[:3, 3] = [0.1, 0.0, 1.5]
    view = in_camera_view(scheme, world2root, K, 640, 480, margin=0.1)
    C = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper, size=(200, tree.n_actions))
    expected = []
    for a in C:
        poses = scheme.predict(a)
        seen = True
        for part in scheme.parts:
            x = (world2root @ poses[part])[:3, 3]
            u, v = (K @ x)[:2] / x[2]
            seen &= bool(x[2] > 0 and 64 <= u <= 576 and 48 <= v <= 432)
        expected.append(seen)
    accepted = view(C)
    np.testing.assert_array_equal(accepted, expected)
    assert 0 < accepted.sum() < len(C)
    policy = ExplorationPolicy(tree.action_lower, tree.action_upper, n_candidates=32, rng=1)
    for _ in range(5):
        a = policy.suggest(scheme, feasible=view)
        assert a is None or view(a[None])[0]
    with pytest.raises(InvalidInputError, match="margin"):
        in_camera_view(scheme, world2root, K, 640, 480, margin=0.5)


@pytest.mark.parametrize("kwargs, match", [
    ({"lower": [0.0, np.inf]}, "limits"), ({"n_candidates": 0}, "n_candidates"), ({"travel_weight": -1.0}, "travel"),
    ({"feasible": 3}, "callable"), ({"noise": 0.0}, "noise"), ({"n_reference": 0}, "n_reference")])
def test_bad_settings_are_refused(kwargs, match):
    args = {"lower": [0.0, 0.0], "upper": [1.0, 1.0], **kwargs}
    with pytest.raises(InvalidInputError, match=match):
        ExplorationPolicy(**args)


def test_with_excursions_it_moves_each_joint_alone_then_pairs_before_babbling():
    """``excursions``: without a body scheme, the middle of the limits, then each joint alone (4 values), then one
    posture per pair of joints, skipping what the feasibility callback refuses; then uniform draws again; with a body
    scheme, no plan."""
    lower, upper = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 0.5])
    refuse = np.array([0.0, 0.8, 0.25])  # one excursion of joint 1, refused
    policy = ExplorationPolicy(lower, upper, 16, rng=0, excursions=True,
                               feasible=lambda C: ~np.all(np.isclose(C, refuse[None], atol=1e-6), axis=1))
    middle = 0.5 * (lower + upper)
    commands = [policy.suggest() for _ in range(1 + 3 * 4 + 3 - 1)]
    np.testing.assert_allclose(commands[0], middle)
    moved = [np.flatnonzero(~np.isclose(c, middle)) for c in commands[1:]]
    assert [len(m) for m in moved] == [1] * 11 + [2] * 3
    assert [int(m[0]) for m in moved[:11]] == [0] * 4 + [1] * 3 + [2] * 4
    assert not any(np.allclose(c, refuse) for c in commands)
    assert policy.plan == []
    assert not np.any(np.isclose(policy.suggest(), middle))  # uniform again
    with_scheme = ExplorationPolicy(lower, upper, 16, rng=0, excursions=True)
    assert len(with_scheme.plan) == 16 and with_scheme.suggest(scheme=None, near=middle) is not None
    assert len(with_scheme.plan) == 16  # a near request does not consume the plan
