"""Tests of change detection, memory and repair of the tree's local models."""

import re
from collections import deque

import pytest

from body_scheme_core.adaptation import Adaptation, Mismatch, least_recently_used, tree_halves
from body_scheme_core.config import BodySchemeConfig
from body_scheme_core.errors import ModelFileError
from body_scheme_core.models.engineered import EngineeredModel, engineered_models
from body_scheme_core.pool import MEMORY, TREE, ModelPool, TrackedModel, new_batch, new_monitor, refine_window
from body_scheme_core.relative import PartPairs
from body_scheme_core.synthetic import REPAIR, Fault, make_session, planar_2dof

BLOCK = Fault("block_joint", action_index=1, angle=0.8)


class _Rig:
    """An Adaptation over a given tree (and memory) of fitted models, fed like the learner feeds it."""

    def __init__(self, robot, tree, memory=(), config=None):
        config = BodySchemeConfig() if config is None else config
        self.pairs = PartPairs(robot.marker_ids, config.theta_trans, config.theta_rot)
        max_dim = max([config.max_complexity] + [m.complexity for m in tree])
        self.pool = ModelPool(config, robot.n_actions, self.pairs,
                              new_batch(config, robot.n_actions, refine_window(config), max_dim), new_monitor(config))
        self.tree = [e.id for e in self.pool.add_fitted(tree, TREE, origin="test", last_used=0)]
        self.pool.add_fitted(list(memory), MEMORY, origin="test", last_used=0)
        self.history = deque(maxlen=config.history_length)
        self.adaptation = Adaptation(config, self.pool, self.history)
        self.events = []

    def run(self, session, start, stop, until=None):
        """Feed steps [start, stop); stop early after a step with an event of kind ``until``."""
        for t in range(start, stop):
            a, obs = session.actions[t], session.observations[t]
            self.history.append((t, a, obs))
            new = []
            self.adaptation.step(self.tree, a, self.pairs.observe(obs), t, new)
            self.events += new
            if until in [e.kind for e in new]:
                return t
        return stop

    def kinds(self, start=0):
        return [e.kind for e in self.events if e.step >= start]

    def edge(self, parent, child):
        return next(self.pool.tracked[i] for i in self.tree
                    if {self.pool.tracked[i].parent, self.pool.tracked[i].child} == {parent, child})


def test_least_recently_used_go_first():
    """Beyond the capacity the models last used longest ago are forgotten, ties by age (id)."""
    models = [TrackedModel(i, 1, 2, (), MEMORY, i, last_used=used) for i, used in enumerate([5, 2, 2, 9])]
    assert [e.id for e in least_recently_used(models, 2)] == [1, 2]
    assert least_recently_used(models, 4) == [] and len(least_recently_used(models, 0)) == 4


def test_removing_a_tree_edge_leaves_two_halves():
    """A chain 1-2-3-4-5 without edge 3-4 falls into {1, 2, 3} and {4, 5}."""
    halves = tree_halves([1, 2, 3, 4, 5], [(1, 2), (2, 3), (4, 5)])
    assert halves[1] == halves[2] == halves[3] != halves[4] == halves[5]


def test_mismatch_state_round_trip():
    """The edges in mismatch survive to_state / from_state; an unknown edge id is refused."""
    adaptation = Adaptation(BodySchemeConfig(), None, deque())
    adaptation.mismatch[4] = Mismatch(tau=10, detected=12, sampled_at=12, train_from=10, resamples=1)
    state = adaptation.mismatch_state()
    assert state == [{"edge": 4, "tau": 10, "detected": 12, "sampled_at": 12, "train_from": 10, "resamples": 1}]
    assert Adaptation.mismatch_from_state(state, {4: None}) == adaptation.mismatch
    with pytest.raises(ModelFileError, match="unknown model id 4"):
        Adaptation.mismatch_from_state(state, {})


def test_a_failing_model_is_detected_replaced_and_remembered():
    """A blocked joint: only its edge goes into mismatch, a replacement learned since the change point takes over,
    and the failed model goes to memory."""
    robot = planar_2dof()
    session = make_session(robot, 90, seed=0, faults=[(30, BLOCK)], visibility=0.95)
    models = engineered_models(robot)
    rig = _Rig(robot, models)
    rig.run(session, 0, 30)
    assert rig.events == []
    failed_id = rig.edge(2, 3).id
    replaced_at = rig.run(session, 30, 90, until="model_replaced")
    assert rig.kinds(30) == ["mismatch_detected", "model_sampled", "model_replaced", "model_retired"]
    detected, sampled, replaced, _ = rig.events
    assert {detected.parent, detected.child} == {2, 3}
    # The replacements were trained on exactly the pair's samples since the change point, replayed at once.
    used, start = map(int, re.search(r"trained on the (\d+) samples of this pair since step (\d+)",
                                     sampled.reason).groups())
    assert used == sum(1 for s, _, obs in rig.history if s >= start and 2 in obs and 3 in obs)
    assert f"after {used} training samples since step {start}" in replaced.reason
    new = rig.edge(2, 3)
    assert new.origin == "replacement" and new.n_train == used and rig.pool.n_now(new) == used
    assert rig.adaptation.mismatch == {} and rig.pool.candidates_of(failed_id) == []
    assert rig.pool.n_learning == 1  # the other replacements were dropped; the new tree model keeps refining
    rig.run(session, replaced_at + 1, 90)
    assert rig.kinds(replaced_at + 1) == [] and rig.edge(1, 2).model is models[0]
    (remembered,) = rig.pool.with_role(MEMORY)
    assert remembered.model is models[1]


def test_a_remembered_model_that_fits_again_is_put_back():
    """After the repair the engineered model beats the learned one in memory's challenge and is reinstated."""
    robot = planar_2dof()
    session = make_session(robot, 130, seed=0, faults=[(30, BLOCK), (80, REPAIR)], visibility=0.95)
    models = engineered_models(robot)
    rig = _Rig(robot, models)
    rig.run(session, 0, 80)
    learned = rig.edge(2, 3)
    rig.run(session, 80, 130)
    assert rig.kinds(80) == ["mismatch_detected", "model_reinstated", "model_retired"]
    detected, reinstated, retired = [e for e in rig.events if e.step >= 80]
    assert "remembered engineered(2->3 | a1)" in detected.reason and reinstated.step - 80 < 10
    assert rig.edge(2, 3).model is models[1] and retired.model == learned.describe()
    assert [e.id for e in rig.pool.with_role(MEMORY)] == [learned.id]


def test_a_reinstated_model_retired_while_refining_keeps_learning():
    """A replacement retired early (few samples) and reinstated for the same fault again resumes refining."""
    robot = planar_2dof()
    session = make_session(robot, 160, seed=0, faults=[(30, BLOCK), (60, REPAIR), (100, BLOCK)], visibility=0.95)
    rig = _Rig(robot, engineered_models(robot))
    rig.run(session, 0, 60)
    learned = rig.edge(2, 3)
    rig.run(session, 60, 100)
    assert learned.role == MEMORY and learned.slot == -1
    retired_with = learned.n_train
    assert 0 < retired_with < rig.pool.refine_window
    rig.run(session, 100, 160)
    assert "model_reinstated" in rig.kinds(100) and rig.edge(2, 3) is learned
    assert learned.slot >= 0 and rig.pool.n_now(learned) > retired_with


def test_unpromising_replacements_are_sampled_again_after_patience():
    """When no replacement becomes valid within replacement_patience steps, new ones are sampled."""
    robot = planar_2dof()
    session = make_session(robot, 90, seed=0, faults=[(30, BLOCK)], visibility=0.95)
    rig = _Rig(robot, engineered_models(robot), config=BodySchemeConfig(replacement_patience=1, min_test_samples=6))
    rig.run(session, 0, 90)
    again = [e for e in rig.events if e.kind == "model_sampled" and e.reason.startswith("none of the")]
    assert again and "within 1 steps" in again[0].reason
    assert rig.kinds(30)[-2:] == ["model_replaced", "model_retired"]


def test_a_remembered_model_of_another_pair_can_reconnect_the_tree():
    """With a wrong 1-3 model in the tree and a good 2-3 model in memory, 2-3 takes over: the structure changes."""
    robot = planar_2dof()
    session = make_session(robot, 40, seed=3, visibility=0.9)
    good12, good23 = EngineeredModel.from_tree(robot, 1, 2), EngineeredModel.from_tree(robot, 2, 3)
    wrong13 = EngineeredModel.from_tree(planar_2dof(l1=1.5, l2=1.5), 1, 3)
    rig = _Rig(robot, [good12, wrong13], memory=[good23])
    rig.run(session, 0, 40)
    changed = [e for e in rig.events if e.kind == "structure_changed"]
    assert len(changed) == 1 and changed[0].reason.startswith("edge 1-3 replaced by 2-3")
    assert {frozenset((rig.pool.tracked[i].parent, rig.pool.tracked[i].child)) for i in rig.tree} == {
        frozenset((1, 2)), frozenset((2, 3))}
    assert [e.model for e in rig.pool.with_role(MEMORY)] == [wrong13]


def test_memory_keeps_at_most_memory_size_models_per_pair():
    """With memory_size 1, the second retirement of the pair forgets the least recently used model."""
    robot = planar_2dof()
    other = Fault("block_joint", action_index=1, angle=-0.6)
    session = make_session(robot, 160, seed=0, faults=[(30, BLOCK), (90, other)], visibility=0.95)
    models = engineered_models(robot)
    rig = _Rig(robot, models, config=BodySchemeConfig(memory_size=1))
    rig.run(session, 0, 160)
    retired = [e for e in rig.events if e.kind == "model_retired"]
    assert len(retired) == 2
    assert "forgot engineered(2->3 | a1)" in retired[1].reason and "memory holds 1 model(s)" in retired[1].reason
    (remembered,) = rig.pool.with_role(MEMORY)
    assert remembered.model is not models[1]
