"""Tests of bootstrapping: candidates, the structure search per step, and the end of bootstrapping."""

import numpy as np
import pytest

from body_scheme_core.calibration.noise_model import NoiseModel
from body_scheme_core.learning.bootstrap import Bootstrap
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.pool import ModelPool
from body_scheme_core.learning.relative import PartPairs
from body_scheme_core.learning.structure import n_candidates
from body_scheme_core.learning.tracked import CANDIDATE, TREE
from body_scheme_core.learning.validity import ValidityMonitor
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import (
    Fault,
    KinematicTree,
    arm_4dof,
    branching_tree,
    is_true_tree,
    make_session,
    planar_2dof,
    powercube_6dof,
)

#: Lazy layers and racing (off by default).
LAZY = BodySchemeConfig(lazy_layers=True, race_samples=3)


def _bootstrap(robot, config):
    pairs = PartPairs(robot.marker_ids, NoiseModel.from_config(robot.marker_ids, config))
    pool = ModelPool(config, robot.n_actions)
    Bootstrap.add_candidates(pool, robot.marker_ids, robot.n_actions, config)
    return Bootstrap(config, pool, pairs)


def _run(boot, session, observations=None, stop_when_finished=True):
    """Feed the session; returns (tree per step, events, step at which bootstrapping finished or None)."""
    observations = session.observations if observations is None else observations
    tree, trees, events = None, [], []
    for t in range(session.n_steps):
        relative = boot.pairs.observe(observations[t])
        tree, _ = boot.step(tree, session.actions[t], relative, t, events)
        trees.append(tree)
        if boot.finish_if_ready(tree, t, events):
            if stop_when_finished:
                return trees, events, t
    return trees, events, None


def test_every_pair_and_action_subset_is_a_candidate():
    """The fully connected network: C(3, 2) pairs times (1 static, 2 x (prismatic, revolute, GP), 1 two-action GP);
    with lazy layers the two-action GPs wait until they are needed."""
    robot = planar_2dof()
    assert len(_bootstrap(robot, LAZY).pool.tracked) == n_candidates(3, 2, 1) == 21
    boot = _bootstrap(robot, BodySchemeConfig())
    assert len(boot.pool.tracked) == n_candidates(3, 2, 2) == 24
    assert all(e.role == CANDIDATE and e.slot >= 0 and e.origin == "bootstrap" for e in boot.pool.tracked.values())


def test_the_true_tree_is_found_and_kept_after_bootstrapping():
    """On clean babbling the first tree event is structure_found; at the end only the true tree's models remain."""
    robot = planar_2dof()
    config = BodySchemeConfig()
    session = make_session(robot, 80, seed=0, visibility=0.9)
    boot = _bootstrap(robot, config)
    trees, events, finished = _run(boot, session)
    assert finished is not None and events[0].kind == "structure_found"
    assert [e.kind for e in events].count("bootstrap_finished") == 1 and events[-1].kind == "bootstrap_finished"
    assert "all candidates are frozen" in events[-1].reason and "dropped 22 other candidates" in events[-1].reason
    tree = trees[-1]
    edges = {frozenset((boot.pool.tracked[i].parent, boot.pool.tracked[i].child)) for i in tree}
    assert edges == {frozenset(e) for e in robot.marker_tree_edges()}
    assert set(boot.pool.tracked) == set(tree)
    assert all(e.role == TREE and e.last_used == finished and e.slot == -1 for e in boot.pool.tracked.values())
    assert {e.kind for e in boot.pool.tracked.values()} == {"revolute"}  # rigid joints where they fit
    # The tree was found long before its models had learned train_window samples: it waited for them.
    first = next(t for t, tree in enumerate(trees) if tree is not None)
    assert first < config.train_window <= finished


def test_a_stable_tree_ends_bootstrapping_although_some_pair_is_rarely_seen():
    """Markers 1 and 3 are seen together only at the start: their candidates never freeze; patience ends it."""
    robot = planar_2dof()
    config = BodySchemeConfig(bootstrap_patience=5)
    session = make_session(robot, 150, seed=1)
    observations = [obs if t < 5 else {k: v for k, v in obs.items() if k != (1 if t % 2 else 3)}
                    for t, obs in enumerate(session.observations)]
    boot = _bootstrap(robot, config)
    _, events, finished = _run(boot, session, observations)
    assert finished is not None
    assert "the tree was stable for" in events[-1].reason
    assert boot.pool.n_learning == 0 and len(boot.pool.tracked) == 2  # the 1-3 candidates are gone


def test_losing_every_valid_tree_is_reported():
    """A marker knocked during bootstrapping invalidates its candidates: the tree is lost and that is said."""
    robot = planar_2dof()
    knock = transform_from_rotvec([0.0, 2.0, 0.0], [0.0, 0.4, 0.3])
    session = make_session(robot, 120, seed=1, faults=[(18, Fault("displace_marker", marker_id=2, delta=knock))])
    boot = _bootstrap(robot, BodySchemeConfig(train_window=40))
    trees, events, _ = _run(boot, session)
    lost = [e for e in events if e.reason.startswith("no valid spanning tree any more")]
    assert lost and lost[0].kind == "structure_changed"
    assert trees[lost[0].step] is None and trees[lost[0].step - 1] is not None
    assert boot.tree_since >= lost[0].step
    assert np.all([e.kind != "structure_found" for e in events[1:]])


def test_a_vetoed_candidate_is_left_out_until_it_has_learned_more():
    """veto() removes a tree model from the search; the tree changes; the veto lapses after 50 % more samples."""
    robot = planar_2dof()
    session = make_session(robot, 60, seed=0, visibility=1.0)
    boot = _bootstrap(robot, BodySchemeConfig())
    tree, events = None, []
    for t in range(12):
        tree, _ = boot.step(tree, session.actions[t], boot.pairs.observe(session.observations[t]), t, events)
    vetoed = tree[0]
    boot.veto(vetoed)
    n_at_veto = boot.vetoed[vetoed]
    trial = boot.search(tree, 12, None, exclude=[tree[1]])  # a trial search changes nothing
    assert trial is None or tree[1] not in trial
    new = boot.search(tree, 12, events, " (test)")
    assert new is None or vetoed not in new
    assert " (test)" in events[-1].reason
    tree = new
    t = 12
    while boot.pool.n_now(boot.pool.tracked[vetoed]) < 1.5 * n_at_veto + 1:
        t += 1
        tree, _ = boot.step(tree, session.actions[t], boot.pairs.observe(session.observations[t]), t, events)
    tree, _ = boot.step(tree, session.actions[t + 1], boot.pairs.observe(session.observations[t + 1]), t + 1, events)
    assert vetoed not in boot.vetoed


# ---------------------------------------------------------------------- lazy layers and racing (issue 21)
def _learn(robot, config, n_steps=120, seed=0, watch=None):
    """Bootstrap a learner on a paper-noise session; ``watch(learner)`` after every step. Returns the learner."""
    session = make_session(robot, n_steps, seed=seed, visibility=0.9)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, config, action_lower=robot.action_lower,
                                action_upper=robot.action_upper)
    for t in range(n_steps):
        learner.update(session.actions[t], session.observations[t])
        if watch is not None:
            watch(learner)
        if learner.phase != "bootstrapping":
            break
    assert learner.phase != "bootstrapping"
    return learner


def _edges(learner):
    return sorted((m.parent, m.child, m.kind, m.actions) for m in learner.body_scheme.models)


def _head_arm():
    """arm_4dof without the marker of link 2: the pair of markers 2 and 4 needs actions 1 and 2 (layer 2)."""
    robot = arm_4dof()
    return KinematicTree(robot.joints, [m for m in robot.markers if m.id != 3])


EAGER = BodySchemeConfig()  # the defaults


@pytest.mark.parametrize("make", [pytest.param(powercube_6dof, marks=pytest.mark.slow),
                                  pytest.param(branching_tree, marks=pytest.mark.slow), _head_arm],
                         ids=["serial", "branching", "layer2"])
def test_lazy_layers_and_racing_learn_the_tree_of_the_eager_search(make):
    robot = make()
    lazy, eager = _learn(robot, LAZY), _learn(robot, EAGER)
    assert _edges(lazy) == _edges(eager)
    assert is_true_tree(robot, lazy.body_scheme)
    assert lazy.n_raced > 0 and eager.n_raced == 0
    if make is _head_arm:
        assert max(len(m.actions) for m in lazy.body_scheme.models) == 2  # the next layer was instantiated


def test_a_serial_chain_with_one_joint_per_link_never_instantiates_layer_two():
    seen = []
    _learn(powercube_6dof(), LAZY, watch=lambda learner: seen.append(
        max(e.complexity for e in learner.state.pool.tracked.values())))
    assert seen and max(seen) == 1


def test_a_raced_out_candidate_never_comes_back_as_a_tree_model():
    """Every candidate that leaves the pool while bootstrapping is raced out; none of their (pair, actions, class)
    is instantiated again or in the final tree."""
    robot = _head_arm()
    raced, alive = set(), {}

    def watch(learner):
        now = {i: (e.parent, e.child, e.actions, e.kind) for i, e in learner.state.pool.tracked.items()}
        if learner.phase == "bootstrapping":
            raced.update(spec for i, spec in alive.items() if i not in now)
            assert not raced & {spec for i, spec in now.items() if i not in alive}  # never instantiated again
        alive.clear()
        alive.update(now)

    learner = _learn(robot, LAZY, watch=watch)
    assert 0 < len(raced) <= learner.n_raced  # those raced in the last step are dropped with the rest
    assert not raced & {(m.parent, m.child, m.actions, m.kind) for m in learner.body_scheme.models}


def test_hopeless_needs_every_recent_error_far_beyond_the_threshold_after_enough_training():
    monitor = ValidityMonitor(window=5, capacity=3, theta_trans=0.1, theta_rot=0.5)
    monitor.in_use[:] = True
    for step in range(3):
        monitor.record([0, 1, 2], [0.25, 0.25, 0.15], [0.0, 0.0, 0.0], step, n_train=[6, 2, 6])
    # row 0: three errors 2.5 x the threshold after 6 samples; row 1 trained on too few; row 2 only 1.5 x
    assert monitor.hopeless([0, 1, 2], 3, 2.0, 5).tolist() == [True, False, False]
    assert not monitor.hopeless([0], 4, 2.0, 5)[0]  # only three recorded
    monitor.record([0], [0.05], [0.0], 3, n_train=[7])
    assert not monitor.hopeless([0], 3, 2.0, 5)[0]  # the last one is fine
