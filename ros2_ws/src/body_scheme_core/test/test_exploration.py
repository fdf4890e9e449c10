"""The exploration policy (exploration.py): feasible, informative next commands."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.exploration import ExplorationPolicy
from body_scheme_core.learner import BodySchemeLearner
from body_scheme_core.world import make_session, planar_2dof


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


def test_with_a_body_scheme_it_picks_the_most_uncertain_posture_unless_travel_costs():
    """On a learned 2-DOF arm the suggestion maximises the predicted variance over the candidates; a high travel
    weight keeps it near the current posture."""
    tree = planar_2dof()
    session = make_session(tree, 60, 0)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    for t in range(60):
        learner.update(session.actions[t], session.observations[t])
    scheme = learner.body_scheme
    policy = ExplorationPolicy(tree.action_lower, tree.action_upper, n_candidates=64, rng=3)
    a = policy.suggest(scheme)
    candidates = np.random.default_rng(3).uniform(tree.action_lower, tree.action_upper, size=(64, 2))
    scores = policy.information(candidates, scheme)
    assert np.allclose(a, candidates[np.argmax(scores)]) and np.mean(scores) == pytest.approx(1.0)
    current = np.zeros(2)
    near = ExplorationPolicy(tree.action_lower, tree.action_upper, travel_weight=100.0, rng=3).suggest(
        scheme, current=current)
    assert np.linalg.norm(near - current) < np.linalg.norm(a - current)


@pytest.mark.parametrize("kwargs, match", [
    ({"lower": [0.0, np.inf]}, "limits"), ({"n_candidates": 0}, "n_candidates"), ({"travel_weight": -1.0}, "travel"),
    ({"feasible": 3}, "callable")])
def test_bad_settings_are_refused(kwargs, match):
    args = {"lower": [0.0, 0.0], "upper": [1.0, 1.0], **kwargs}
    with pytest.raises(InvalidInputError, match=match):
        ExplorationPolicy(**args)
