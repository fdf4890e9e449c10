"""Tests of change detection, memory and repair of the tree's local models.

Detection and repair work on the chain-consistent targets of the calibrated body scheme, so the scenarios run a
:class:`BodySchemeLearner` started from a given tree (the learner is what feeds :class:`Adaptation`); the pure
helpers are tested on their own.
"""

import math
import re

import numpy as np
import pytest

from body_scheme_core.errors import ModelFileError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.detection import Mismatch, mismatch_from_state, mismatch_state, root_most_rising
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.memory import least_recently_used
from body_scheme_core.learning.repair import (
    bridge_relative_complexity,
    failed_from_state,
    failed_state,
    refining_from_state,
    refining_state,
    tree_halves,
)
from body_scheme_core.learning.tracked import MEMORY, TrackedModel
from body_scheme_core.models import RevoluteModel
from body_scheme_core.models.engineered import EngineeredModel, engineered_models
from body_scheme_core.world import REPAIR, Fault, arm_4dof, make_session, planar_2dof

BLOCK = Fault("block_joint", action_index=1, angle=0.8)


class _Run:
    """A learner over a given tree (and memory), with its events and session."""

    def __init__(self, robot, models, session, memory=(), config=None):
        self.learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, config, initial_models=models)
        if memory:
            self.learner.state.pool.add_fitted(list(memory), MEMORY, origin="test", last_used=0)
        self.session = session
        self.events = []

    def run(self, start, stop, until=None):
        """Feed steps [start, stop); stop early after a step with an event of kind ``until``."""
        for t in range(start, stop):
            new = self.learner.update(self.session.actions[t], self.session.observations[t])
            self.events += new
            if until in [e.kind for e in new]:
                return t
        return stop

    def kinds(self, start=0):
        return [e.kind for e in self.events if e.step >= start]

    def edge(self, parent, child):
        pool = self.learner.state.pool
        return next(pool.tracked[i] for i in self.learner.state.tree
                    if {pool.tracked[i].parent, pool.tracked[i].child} == {parent, child})


def test_least_recently_used_go_first():
    """Beyond the capacity the models last used longest ago are forgotten, ties by age (id)."""
    models = [TrackedModel(i, 1, 2, (), "static", MEMORY, i, last_used=used) for i, used in enumerate([5, 2, 2, 9])]
    assert [e.id for e in least_recently_used(models, 2)] == [1, 2]
    assert least_recently_used(models, 4) == [] and len(least_recently_used(models, 0)) == 4


def test_removing_a_tree_edge_leaves_two_halves():
    """A chain 1-2-3-4-5 without edge 3-4 falls into {1, 2, 3} and {4, 5}."""
    halves = tree_halves([1, 2, 3, 4, 5], [(1, 2), (2, 3), (4, 5)])
    assert halves[1] == halves[2] == halves[3] != halves[4] == halves[5]


def test_relative_complexity_counts_actions_and_another_pair():
    """C(M2|M1): actions added or removed, plus one when the candidate connects another pair of parts."""
    failed = TrackedModel(0, 1, 3, (0,), "gp", "tree", 0)
    assert bridge_relative_complexity(TrackedModel(1, 3, 1, (0,), "revolute", "candidate", 1), failed) == 0
    assert bridge_relative_complexity(TrackedModel(2, 2, 3, (1,), "revolute", "candidate", 2), failed) == 3


def test_adaptation_state_round_trip():
    """The edges in mismatch and the replacements still refining survive their state; unknown ids are refused."""
    mismatch = {4: Mismatch(tau=10, detected=12, sampled_at=12, train_from=10, resamples=1)}
    state = mismatch_state(mismatch)
    assert state == [{"edge": 4, "tau": 10, "detected": 12, "sampled_at": 12, "train_from": 10, "resamples": 1,
                      "bridged_at": -1, "search": 0}]
    assert mismatch_from_state(state, {4: None}) == mismatch
    with pytest.raises(ModelFileError, match="unknown model id 4"):
        mismatch_from_state(state, {})
    refining = {7: (4, 10)}
    assert refining_from_state(refining_state(refining), {7: None}, 8) == {7: (4, 10)}
    with pytest.raises(ModelFileError, match="unknown model id 7"):
        refining_from_state(refining_state(refining), {}, 8)
    with pytest.raises(ModelFileError, match="refining failed id"):  # an id the pool has not given out
        refining_from_state(refining_state(refining), {7: None}, 4)
    failed = {frozenset((1, 2)): (5, 3)}
    assert failed_from_state(failed_state(failed), {1, 2}) == failed
    with pytest.raises(ModelFileError, match="two distinct parts"):
        failed_from_state([[1, 1, 5, 3]], {1, 2})
    with pytest.raises(ModelFileError, match="failed step"):
        failed_from_state([[1, 2, 1e308, 3]], {1, 2})


def test_a_failing_model_is_detected_replaced_and_remembered():
    """A blocked joint: only its edge goes into mismatch, a replacement learned since the change point takes over,
    and the failed model goes to memory."""
    robot = planar_2dof()
    session = make_session(robot, 90, seed=0, faults=[(30, BLOCK)], visibility=0.95)
    models = engineered_models(robot)
    run = _Run(robot, models, session)
    run.run(0, 30)
    assert run.events == []
    failed_id = run.edge(2, 3).id
    replaced_at = run.run(30, 90, until="model_replaced")
    assert run.kinds(30)[:4] == ["mismatch_detected", "model_sampled", "model_replaced", "model_retired"]
    detected, sampled, replaced, _ = run.events[:4]
    assert {detected.parent, detected.child} == {2, 3} and detected.step < 40
    # The replacements were trained on exactly the child's samples since the change point, replayed at once.
    used, start = map(int, re.search(r"trained on the (\d+) samples since step (\d+)", sampled.reason).groups())
    assert used == sum(1 for s, _, obs in run.learner.state.history if start <= s <= sampled.step and 3 in obs)
    assert f"since step {start}" in replaced.reason
    new = run.edge(2, 3)
    assert new.origin == "replacement" and new.since == start and new.model is not None
    assert run.learner.state.adaptation.mismatch == {}
    run.run(replaced_at + 1, 90)
    assert "mismatch_detected" not in run.kinds(replaced_at + 1)
    assert run.edge(1, 2).model is models[0]  # engineered models are never refitted
    (remembered,) = run.learner.state.pool.with_role(MEMORY)
    assert remembered.id == failed_id
    assert run.learner.state.pool.candidates_of(failed_id) == []  # siblings were dropped once frozen or superseded


def test_a_simpler_sibling_that_becomes_valid_takes_over():
    """A GP is valid a few samples before a revolute joint (which predicts from its third sample); once the revolute
    sibling is valid it replaces the GP, which is dropped, not remembered."""
    robot = arm_4dof()
    bend = Fault("deform_limb", joint_or_link="link2", delta_rotvec=(0.0, math.pi / 4, 0.0))
    session = make_session(robot, 160, seed=1, faults=[(60, bend)])
    run = _Run(robot, engineered_models(robot), session)
    run.run(0, 160)
    replaced = [e for e in run.events if e.kind == "model_replaced"]
    assert replaced[0].model.startswith("gp(3->4")
    assert replaced[1].model.startswith("revolute(3->4") and "installed first" in replaced[1].reason
    assert run.edge(3, 4).kind == "revolute"
    assert [e.kind for e in run.learner.state.pool.with_role(MEMORY)] == ["engineered"]


def test_edges_below_a_changed_edge_wait_for_it():
    """The bent upper arm moves the forearm and the hand: only the edge into the forearm is blamed."""
    robot = arm_4dof()
    bend = Fault("deform_limb", joint_or_link="link2", delta_rotvec=(0.0, math.pi / 4, 0.0))
    session = make_session(robot, 120, seed=1, faults=[(60, bend)])
    run = _Run(robot, engineered_models(robot), session)
    run.run(0, 120)
    detected = [e for e in run.events if e.kind == "mismatch_detected"]
    assert [{e.parent, e.child} for e in detected] == [{3, 4}]
    assert all(s["valid"] for s in run.learner.edge_status())


def test_an_alarm_is_blamed_on_an_edge_above_only_if_that_edge_rose_too():
    """The edge nearest the root whose CUSUM rose with the alarming one's takes the blame; a healthy edge above it
    whose statistic only wanders a little above zero (noise) does not."""
    robot = arm_4dof()
    run = _Run(robot, engineered_models(robot), make_session(robot, 30, seed=0))
    run.run(0, 30)
    learner = run.learner
    pool, threshold = learner.state.pool, learner.config.cusum_threshold
    monitor = pool.monitor
    upper, lower = run.edge(2, 3), run.edge(4, 5)
    monitor.cusum[lower.row] = [2.5, 0.0]
    monitor.cusum_start[lower.row] = [25, -1]
    monitor.cusum_start[upper.row] = [24, -1]
    half = 0.5 * threshold
    monitor.cusum[upper.row] = [0.6 * half, 0.0]
    assert root_most_rising(pool, threshold, [upper.id], lower) is None
    monitor.cusum[upper.row] = [1.1 * half, 0.0]
    assert root_most_rising(pool, threshold, [upper.id], lower) == upper.id


def test_a_remembered_model_that_fits_again_is_put_back():
    """After the repair the engineered model beats the learned one in memory's challenge and is reinstated."""
    robot = planar_2dof()
    session = make_session(robot, 130, seed=0, faults=[(30, BLOCK), (80, REPAIR)], visibility=0.95)
    models = engineered_models(robot)
    run = _Run(robot, models, session)
    run.run(0, 80)
    learned = run.edge(2, 3)
    run.run(80, 130)
    assert run.kinds(80) == ["mismatch_detected", "model_reinstated", "model_retired"]
    detected, reinstated, retired = [e for e in run.events if e.step >= 80]
    assert "remembered engineered(2->3 | a1)" in detected.reason and reinstated.step - 80 < 10
    assert run.edge(2, 3).model is models[1] and retired.model == learned.describe()
    assert [e.id for e in run.learner.state.pool.with_role(MEMORY)] == [learned.id]


def test_unpromising_replacements_are_sampled_again_after_patience():
    """When no replacement becomes valid within replacement_patience steps, new ones are sampled."""
    robot = planar_2dof()
    session = make_session(robot, 90, seed=0, faults=[(30, BLOCK)], visibility=0.95)
    run = _Run(robot, engineered_models(robot), session,
               config=BodySchemeConfig(replacement_patience=1, min_test_samples=6))
    run.run(0, 90)
    again = [e for e in run.events if e.kind == "model_sampled" and e.reason.startswith("none of the")]
    assert again and "within 1 steps" in again[0].reason
    assert "model_replaced" in run.kinds(30)


def test_a_remembered_model_of_another_pair_can_reconnect_the_tree():
    """With a wrong 1-3 model in the tree and a good 2-3 model in memory, 2-3 takes over: the structure changes."""
    robot = planar_2dof()
    session = make_session(robot, 40, seed=3, visibility=0.9)
    good12, good23 = EngineeredModel.from_tree(robot, 1, 2), EngineeredModel.from_tree(robot, 2, 3)
    wrong13 = EngineeredModel.from_tree(planar_2dof(l1=1.5, l2=1.5), 1, 3)
    run = _Run(robot, [good12, wrong13], session, memory=[good23])
    run.run(0, 40)
    changed = [e for e in run.events if e.kind == "structure_changed"]
    assert len(changed) == 1 and changed[0].reason.startswith("edge 1-3 replaced by 2-3")
    assert {frozenset((e.parent, e.child)) for e in (run.edge(1, 2), run.edge(2, 3))} == {
        frozenset((1, 2)), frozenset((2, 3))}
    assert [e.model for e in run.learner.state.pool.with_role(MEMORY)] == [wrong13]


def test_a_wrong_edge_is_replaced_by_a_pair_across_the_cut():
    """No model of the pair 1-3 on one action at most can be valid (it needs both): after bridge_patience steps
    candidates of the other pairs across the cut are sampled, and 2-3 (revolute on a1) replaces it: a wrong tree is
    repaired."""
    robot = planar_2dof()
    session = make_session(robot, 120, seed=2, visibility=0.95)
    wrong13 = RevoluteModel(1, 3, (1,))._set_fit(np.r_[0, 0, 1.0, np.zeros(9), 1.0], np.eye(10), 1, 0.0)
    run = _Run(robot, [EngineeredModel.from_tree(robot, 1, 2), wrong13], session,
               config=BodySchemeConfig(max_complexity=1))
    run.run(0, 120)
    sampled = [e for e in run.events if e.kind == "model_sampled"]
    assert any("across the cut" in e.reason for e in sampled)
    changed = [e for e in run.events if e.kind == "structure_changed"]
    assert changed and changed[0].reason.startswith("edge 1-3 replaced by 2-3")
    assert run.edge(2, 3).kind == "revolute" and run.edge(2, 3).actions == (1,)
    assert run.learner.phase == "steady"


def test_memory_keeps_at_most_memory_size_models_per_pair():
    """With memory_size 1, the second retirement of the pair forgets the least recently used model."""
    robot = planar_2dof()
    other = Fault("block_joint", action_index=1, angle=-0.6)
    session = make_session(robot, 160, seed=0, faults=[(30, BLOCK), (90, other)], visibility=0.95)
    models = engineered_models(robot)
    run = _Run(robot, models, session, config=BodySchemeConfig(memory_size=1))
    run.run(0, 160)
    retired = [e for e in run.events if e.kind == "model_retired"]
    assert len(retired) == 2
    assert "forgot engineered(2->3 | a1)" in retired[1].reason and "memory holds 1 model(s)" in retired[1].reason
    (remembered,) = run.learner.state.pool.with_role(MEMORY)
    assert remembered.model is not models[1]
    assert np.isfinite(run.learner.calibration_rms)
