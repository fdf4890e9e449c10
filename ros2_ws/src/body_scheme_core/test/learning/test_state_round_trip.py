"""Every state the learner writes loads again: saved and loaded at every event and every few steps of sessions that
go through each phase and event kind (bootstrapping, mismatch, replacement, reinstatement, a moved root marker,
mirrored orientations, an explicit joint fit), the loaded learner's state is the saved one and it continues alike.

A state the learner wrote and then refused is worse than no checkpoint: scheme_node moves it aside and learning
starts again from step 0 (a prior of 10 x 10 was refused as not 13 x 13 after every reinstatement).
"""

import json
import math

import numpy as np
import pytest

from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.persistence import encode_state, load_state
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import REPAIR, Fault, arm_4dof, make_session, planar_2dof

#: Steps between two round trips when nothing happens.
EVERY = 20


def _document(learner):
    return json.dumps(learner.to_state(), sort_keys=True)


def _round_trip(learner, tmp_path):
    """Save ``learner`` as scheme_node does, load it, and check the state is the same; returns the loaded one."""
    path = tmp_path / "state.json"
    path.write_text(encode_state(learner, path))
    loaded = load_state(path)
    assert _document(loaded) == _document(learner), f"step {learner.step}: the loaded state differs"
    return loaded


def _run(robot, session, tmp_path, explore_at=()):
    """Learn ``session``, round-tripping the state after every step with an event (bar refused input) and every
    :data:`EVERY` steps; returns the event kinds seen and how many round trips carried a prior."""
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(),
                                action_lower=robot.action_lower, action_upper=robot.action_upper)
    kinds, with_prior, trips = set(), 0, 0
    for k in range(len(session.actions)):
        events = learner.update(session.actions[k], session.observations[k], stamp=0.1 * k)
        if k in explore_at and learner.body_scheme is not None:
            events += learner.recalibrate()
            kinds.add("explored")
        kinds.update(e.kind for e in events)
        if any(e.kind != "input_rejected" for e in events) or k % EVERY == 0:
            loaded = _round_trip(learner, tmp_path)
            trips += 1
            with_prior += any(e["prior"] is not None for e in learner.to_state()["entries"])
            if k + 1 < len(session.actions):  # the loaded learner takes the next step exactly as the original
                a, obs = session.actions[k + 1], session.observations[k + 1]
                assert ([e.to_dict() for e in loaded.update(a, obs, stamp=0.1 * (k + 1))]
                        == [e.to_dict() for e in _copy(learner).update(a, obs, stamp=0.1 * (k + 1))])
    return kinds, with_prior, trips


def _copy(learner):
    return BodySchemeLearner.from_state(json.loads(_document(learner)))


@pytest.mark.slow
def test_states_of_replacements_reinstatements_and_flips_load_again(tmp_path):
    """A blocked end-effector joint, its repair and the same block again, with 10 % mirrored orientations: states
    with a replaced, a reinstated model (which carry priors) and corrected flips all load and continue alike."""
    robot = arm_4dof()
    block = Fault("block_joint", action_index=3, angle=0.5)
    session = make_session(robot, 360, seed=1, sigma_trans=0.01, sigma_rot=math.radians(3.0), flip_rate=0.1,
                           faults=((120, block), (220, REPAIR), (300, block)))
    kinds, with_prior, trips = _run(robot, session, tmp_path, explore_at=(100, 260))
    assert {"bootstrap_finished", "mismatch_detected", "model_replaced", "model_reinstated", "model_retired",
            "explored"} <= kinds
    assert with_prior > 0 and trips > 20


@pytest.mark.slow
def test_states_after_a_moved_root_marker_and_a_bent_limb_load_again(tmp_path):
    """The root's marker moved on the base (the root pose is fitted again, priors at the root dropped) and a bent
    limb: the states load and continue alike."""
    robot = planar_2dof()
    moved = Fault("displace_marker", marker_id=robot.marker_ids[0],
                  delta=transform_from_rotvec(np.array([0.0, 0.0, 0.3]), np.array([0.05, 0.0, 0.0])))
    bent = Fault("deform_limb", joint_or_link=robot.joints[-1].name, delta_rotvec=[0.0, 0.0, 0.6])
    session = make_session(robot, 300, seed=2, sigma_trans=0.01, sigma_rot=math.radians(3.0),
                           faults=((100, moved), (200, bent)))
    kinds, _, trips = _run(robot, session, tmp_path)
    assert {"bootstrap_finished", "mismatch_detected", "model_replaced"} <= kinds and trips > 15
