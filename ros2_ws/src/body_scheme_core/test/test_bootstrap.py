"""Tests of bootstrapping: candidates, the structure search per step, and the end of bootstrapping."""

import numpy as np

from body_scheme_core.bootstrap import Bootstrap
from body_scheme_core.config import BodySchemeConfig
from body_scheme_core.noise_model import NoiseModel
from body_scheme_core.pool import ModelPool
from body_scheme_core.relative import PartPairs
from body_scheme_core.structure import n_candidates
from body_scheme_core.tracked import CANDIDATE, TREE
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import Fault, make_session, planar_2dof


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
    """The fully connected network: C(3, 2) pairs times (1 static, 2 x (prismatic, revolute, GP), 1 two-action GP)."""
    robot = planar_2dof()
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
