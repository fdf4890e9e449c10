"""Tests of the learner's state in memory and on disk: atomic steps, structure checks and strict state files
(learner_state.py)."""

import dataclasses
import json
from collections import deque

import numpy as np
import pytest

from body_scheme_core.errors import LearnerStepError, ModelFileError, StampOrderError
from body_scheme_core.learning import learner_fit, learner_step
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.learner_state import UNDO, LearnerState, restore, snapshot, structural_problems
from body_scheme_core.learning.learner_step import time_step
from body_scheme_core.learning.tracked import Journal
from body_scheme_core.world import make_session, planar_2dof, powercube_6dof


@pytest.fixture(scope="module")
def session():
    """The 6-DOF arm at the paper's noise."""
    return make_session(powercube_6dof(), 160, seed=0, visibility=0.9, above_ground=True)


def _learner(session, steps):
    tree = session.tree
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions)
    for t in range(steps):
        learner.update(session.actions[t], session.observations[t])
    return learner


@pytest.fixture(scope="module")
def at70(session):
    """The saved state after 70 steps (steady): each test continues from its own copy."""
    return _learner(session, 70).to_state()


def _learner_at(session, steps, at70):
    return BodySchemeLearner.from_state(at70) if steps == 70 else _learner(session, steps)


@pytest.mark.parametrize("module, where, steps", [(learner_step, "_bootstrap_step", 10),
                                                  (learner_fit, "calibrate_tree", 10),
                                                  (learner_step, "_adapt_step", 70), (learner_fit, "_learn_noise", 70)])
def test_a_step_that_fails_inside_is_undone_whole(session, at70, monkeypatch, module, where, steps):
    """A defect raised anywhere in a step (while bootstrapping or after) leaves the learner exactly as it was: the
    same state, step counter and structure; the error is a LearnerStepError caused by the original, and the next
    step goes on."""
    learner = _learner_at(session, steps, at70)
    original = getattr(module, where)

    def broken(*args, **kwargs):
        original(*args, **kwargs)  # change things first, then fail
        raise KeyError("a defect")

    monkeypatch.setattr(module, where, broken)
    for t in range(steps, steps + 80):  # until the broken piece runs (the joint fit is not due every step)
        before = json.dumps(learner.to_state(), sort_keys=True)
        try:
            learner.update(session.actions[t], session.observations[t])
        except LearnerStepError as error:
            assert isinstance(error.__cause__, KeyError) and "failed and was undone: KeyError" in str(error)
            break
    else:
        pytest.fail(f"{where} never ran")
    assert json.dumps(learner.to_state(), sort_keys=True) == before and learner.step == t
    assert structural_problems(learner.state) == []
    monkeypatch.undo()
    learner.update(session.actions[t], session.observations[t])
    assert learner.step == t + 1


def test_undone_means_identical_to_a_learner_that_never_saw_the_step(session, at70, monkeypatch):
    """After a failed step the learner continues exactly like one that never tried it."""
    a, b = BodySchemeLearner.from_state(at70), BodySchemeLearner.from_state(at70)

    def broken(*args, **kwargs):
        raise RuntimeError("a defect")

    monkeypatch.setattr(learner_fit, "_flag_unexplained", broken)
    monkeypatch.setattr(learner_step, "calibration_due", lambda state, step: True)
    with pytest.raises(LearnerStepError):
        a.update(session.actions[70], session.observations[70])
    monkeypatch.undo()
    for t in range(70, 80):
        events_a = a.update(session.actions[t], session.observations[t])
        events_b = b.update(session.actions[t], session.observations[t])
        assert events_a == events_b
    assert json.dumps(a.to_state(), sort_keys=True) == json.dumps(b.to_state(), sort_keys=True)


def test_a_joint_fit_on_demand_that_fails_is_undone(at70, monkeypatch):
    """``recalibrate`` is all or nothing like ``update``: a failure after the fit leaves the learner's state as it was
    and raises LearnerStepError."""
    learner = BodySchemeLearner.from_state(at70)
    before = learner.to_state()

    def broken(*args):
        raise RuntimeError("injected")

    monkeypatch.setattr(learner_fit, "_flag_unexplained", broken)
    with pytest.raises(LearnerStepError, match="undone"):
        learner.recalibrate()
    assert learner.to_state() == before


def test_every_field_says_how_it_is_undone_and_the_state_file_saves_every_field(session):
    """Each LearnerState field has an undo policy; the state file's keys are exactly the keys the fields name."""
    learner = _learner(session, 5)
    fields = dataclasses.fields(LearnerState)
    assert all(f.metadata["undo"] in UNDO for f in fields)
    named = {key for f in fields for key in f.metadata["file"]}
    assert named == set(learner.to_state()) - {"version"}


def test_a_restored_snapshot_is_the_state_it_was_taken_of():
    """Sixty steps through the end of bootstrapping (the 2-DOF arm's), run on the state directly, then restored: the
    saved state, the fields the file does not hold and the objects the phase objects share are as before."""
    session = make_session(planar_2dof(), 100, seed=0)
    learner = _learner(session, 20)
    s = learner.state

    def fingerprint():  # every field a step may change, by value (an object that undoes itself: what it keeps)
        return {f.name: _by_value(getattr(s, f.name).snapshot() if f.metadata["undo"] == "own" else getattr(s, f.name))
                for f in dataclasses.fields(s) if f.metadata["undo"] != "fixed"}

    before, fields = json.dumps(learner.to_state(), sort_keys=True), fingerprint()
    transient = (s.just_finished, s.reach, s.prediction, s.pairs, s.history, s.noise)
    with Journal() as journal:
        saved = snapshot(s)
        for t in range(20, 80):
            observations = {**session.observations[t], **({2: np.full((4, 4), np.nan)} if t == 30 else {})}
            time_step(s, session.actions[t], observations, None)
        assert s.step == 80 and learner.phase == "steady" and s.rejected["not_finite"] == 1
        changed = {name for name, value in fingerprint().items() if value != fields[name]}
        assert {"step", "bootstrapping", "rejected", "history", "pool", "root_pose", "calibrated", "noise"} <= changed
        restore(s, saved, journal)
    assert json.dumps(learner.to_state(), sort_keys=True) == before and fingerprint() == fields
    assert (s.just_finished, s.reach, s.prediction, s.pairs, s.history, s.noise) == transient
    assert s.bootstrap.history is s.history and s.adaptation.history is s.history and s.pairs.noise is s.noise
    assert s.bootstrap.pool is s.pool and s.adaptation.pool is s.pool
    assert structural_problems(s) == []
    assert learner.phase == "bootstrapping"
    for t in range(20, 25):  # and it goes on
        learner.update(session.actions[t], session.observations[t])


def _by_value(value, seen=None):
    """``value`` as nested tuples of plain values and array bytes, objects by their attributes (each once)."""
    seen = set() if seen is None else seen
    if value is None or isinstance(value, (bool, int, float, str, np.generic)):
        return value
    if isinstance(value, np.ndarray):
        return value.shape, value.tobytes()
    if isinstance(value, dict):
        return tuple((_by_value(k, seen), _by_value(v, seen)) for k, v in value.items())
    if isinstance(value, (list, tuple, deque)):
        return tuple(_by_value(v, seen) for v in value)
    if isinstance(value, (set, frozenset)):
        return tuple(sorted(repr(v) for v in value))
    if callable(value) or not hasattr(value, "__dict__") or id(value) in seen:
        return type(value).__name__
    seen.add(id(value))
    return type(value).__name__, _by_value(vars(value), seen)


def test_a_missing_stamp_does_not_reset_the_time_order():
    """Stamps 10, None, 5: the third goes back in time and is refused."""
    robot = planar_2dof()
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions)
    learner.update([0.0, 0.0], {}, stamp=10.0)
    learner.update([0.0, 0.0], {}, stamp=None)
    with pytest.raises(StampOrderError):
        learner.update([0.0, 0.0], {}, stamp=5.0)
    assert learner.step == 2 and learner.last_stamp == 10.0


def test_a_learner_without_actions_learns_static_relations():
    """n_actions 0: markers on one rigid body, every relation static."""
    rng = np.random.default_rng(0)
    learner = BodySchemeLearner([1, 2], 0)
    for _ in range(40):
        Y2 = np.eye(4)
        Y2[:3, 3] = [0.1, 0.0, 2.0] + rng.normal(scale=0.003, size=3)
        Y1 = np.eye(4)
        Y1[:3, 3] = [0.0, 0.0, 2.0] + rng.normal(scale=0.003, size=3)
        learner.update([], {1: Y1, 2: Y2})
    assert learner.phase == "steady" and [m.kind for m in learner.body_scheme.models] == ["static"]


@pytest.fixture(scope="module")
def state():
    """A JSON state of a learner in steady state."""
    robot = planar_2dof()
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions)
    session = make_session(robot, 60, seed=1)
    for t in range(60):
        learner.update(session.actions[t], session.observations[t], stamp=float(t))
    return json.loads(json.dumps(learner.to_state()))


@pytest.mark.parametrize("field, value, message", [
    ("last_stamp", "abc", "last_stamp must be a finite number"),
    ("step", -5, r"step must be an integer in \[0, "),
    ("step", 3.5, "step must be an integer"),
    ("step", 2**60, r"step must be an integer in \[0, "),  # beyond any learner: later sums would overflow int64
    ("next_id", True, "next_id must be an integer"),
    ("last_stamp", "inf", "last_stamp must be a finite number"),
    ("failed", [[1, 1, 5, 3]], "two distinct parts"),
    ("noise", {"pooled": [1e6, 1.0, 1.0], "n_observations": 0, "parts": []}, "pooled variance"),
    ("bootstrapping", 1, "bootstrapping must be true or false"),
    ("rejected", {"flipped": -1}, r"must be an integer in \[0, "),
    ("root", 99, "root refers to unknown part 99"),
    ("lack_of_fit", [7], "unknown part"),
    ("tree", [0, 0], "tree refers to unknown model ids"),
    ("root_offset", {"pose": (2 * np.eye(4)).tolist(), "n": 3}, "root_offset pose is not a rigid transform"),
    ("root_offset", {"pose": np.eye(4).tolist(), "n": -1}, r"root_offset n must be an integer in \[0, "),
    ("root_offset", [], "root_offset must be an object"),
])
def test_every_field_of_a_state_is_checked(state, field, value, message):
    """A field of the wrong type or out of range gives ModelFileError naming it."""
    with pytest.raises(ModelFileError, match=message):
        BodySchemeLearner.from_state(dict(state, **{field: value}))


def test_a_non_rigid_pose_in_the_history_is_refused(state):
    """A history observation that is not a rigid transform gives ModelFileError."""
    history = json.loads(json.dumps(state["history"]))
    pose = np.array(history[-1]["observations"][0][1])
    pose[:3, :3] *= 2.0
    history[-1]["observations"][0][1] = pose.tolist()
    with pytest.raises(ModelFileError, match="not a rigid transform"):
        BodySchemeLearner.from_state(dict(state, history=history))


def test_structural_problems_name_what_is_wrong(state):
    """A sound learner has none; a tree edge that is not tracked, or a monitor row shared by two models, is named."""
    learner = BodySchemeLearner.from_state(state)
    assert structural_problems(learner.state) == []
    learner.state.tree[0] = 10_000
    assert any("not tracked" in p for p in structural_problems(learner.state))
    learner = BodySchemeLearner.from_state(state)
    entries = list(learner.state.pool.tracked.values())
    entries[1].row = entries[0].row
    assert any("monitor rows" in p for p in structural_problems(learner.state))
