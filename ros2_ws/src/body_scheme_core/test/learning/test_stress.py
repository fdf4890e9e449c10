"""Stress: the learner driven the way the world will drive it, over random bodies, noise, bad input and faults.

A property-based test (hypothesis): every example draws a body (serial or branching, revolute, prismatic and fixed
joints, links with two markers or none, dummy actions, shuffled ids), a camera's noise (anisotropic, mirrored
orientations), dropout, misdetections, malformed observations, stamps (some missing, some going back in time) and a
change of the body, and feeds the session to a learner from scratch. After every step: no exception, the step counter
equals the accepted calls, the learner's structure is sound
(:func:`~body_scheme_core.learning.learner_state.structural_problems`), and at the end every malformed observation was
counted under its reason.

``make test`` runs a small deterministic set (profile ``ci``: bodies of up to 6 joints, a few thousand steps);
``make stress`` runs the full space (profile ``stress``: up to 14 joints, at least 100,000 steps, random examples; a
failure prints the example to reproduce it) and writes its totals to ``out/stress/stress.json``.
"""

import json
import math
import os
import pathlib

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from body_scheme_core.errors import InvalidInputError, StampOrderError
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.learner_state import structural_problems
from body_scheme_core.world import RANDOM_FAULTS, make_session, random_fault, random_tree

STRESS = bool(os.environ.get("BODY_SCHEME_STRESS"))
_COMMON = {"deadline": None, "database": None, "print_blob": True,
           "suppress_health_check": [HealthCheck.too_slow, HealthCheck.data_too_large]}
settings.register_profile("ci", max_examples=6, derandomize=True, phases=[Phase.explicit, Phase.generate], **_COMMON)
settings.register_profile("stress", max_examples=600, **_COMMON)
PROFILE = "stress" if STRESS else "ci"
MAX_JOINTS = 14 if STRESS else 6
STEPS = (120, 300) if STRESS else (150, 260)
#: Totals over the examples run (``make stress`` writes them out).
TOTALS = {"examples": 0, "steps": 0, "events": 0, "rejected": 0}

scenarios = st.fixed_dictionaries({
    "seed": st.integers(0, 2**31 - 1),
    "n_joints": st.integers(1, MAX_JOINTS),
    "branching": st.booleans(),
    "prismatic_fraction": st.sampled_from([0.0, 0.3]),
    "second_marker_fraction": st.sampled_from([0.0, 0.3]),
    "fixed_fraction": st.sampled_from([0.0, 0.15]),
    "unmarked_fraction": st.sampled_from([0.0, 0.15]),
    "dummy_actions": st.integers(0, 2),
    "shuffle_ids": st.booleans(),
    "sigma_trans": st.floats(0.002, 0.08),
    "sigma_rot": st.floats(math.radians(0.5), math.radians(25.0)),
    "depth_ratio": st.sampled_from([1.0, 3.0, 7.0]),
    "flip_rate": st.sampled_from([0.0, 0.03, 0.1]),
    "visibility": st.floats(0.4, 1.0),
    "outlier_rate": st.sampled_from([0.0, 0.02, 0.1]),
    "bad_rate": st.sampled_from([0.0, 0.05]),
    "fault": st.sampled_from([None, *RANDOM_FAULTS]),
    "fault_at": st.floats(0.3, 0.8),
    "steps": st.integers(*STEPS),
})


def _world(s):
    """The body and its session of one example."""
    tree = random_tree(s["n_joints"], s["seed"], branching=s["branching"], prismatic_fraction=s["prismatic_fraction"],
                       link_length=(0.08, 0.25), marker_offset=0.08,
                       second_marker_fraction=s["second_marker_fraction"], fixed_fraction=s["fixed_fraction"],
                       unmarked_fraction=s["unmarked_fraction"], dummy_actions=s["dummy_actions"],
                       shuffle_ids=s["shuffle_ids"], revolute_range=(0.5, math.pi), prismatic_range=(0.1, 0.4))
    rng = np.random.default_rng(s["seed"])
    faults = []
    if s["fault"] is not None:
        try:
            faults = [(int(s["fault_at"] * s["steps"]),
                       random_fault(tree, s["fault"], rng, 3.0 * s["sigma_trans"]))]
        except InvalidInputError:
            pass  # a body the fault cannot act on (no commanded joint moving a marker, ...)
    session = make_session(tree, s["steps"], s["seed"], faults=faults, sigma_trans=s["sigma_trans"],
                           sigma_rot=s["sigma_rot"], visibility=s["visibility"], depth_ratio=s["depth_ratio"],
                           flip_rate=s["flip_rate"])
    return tree, session, rng


def _corrupt(observations, tree, s, rng, expected):
    """A copy of one step's observations with misdetections and malformed entries (counted in ``expected``)."""
    obs = dict(observations)
    for part in list(obs):
        if rng.uniform() < s["outlier_rate"]:  # a misdetection: a plausible pose in the wrong place
            wrong = np.eye(4)
            wrong[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
            if np.linalg.det(wrong[:3, :3]) < 0:
                wrong[:3, 0] *= -1
            wrong[:3, 3] = obs[part][:3, 3] + rng.uniform(-0.5, 0.5, 3)
            obs[part] = wrong
    if rng.uniform() < s["bad_rate"]:
        kind = rng.integers(3) if observations else 0  # a malformed pose needs a plausible place
        part = int(rng.choice(tree.marker_ids))
        if kind == 0:
            obs[max(tree.marker_ids) + 1000] = np.eye(4)
            expected["unknown_id"] += 1
        elif kind == 1:
            pose = np.eye(4)
            pose[0, 3] = np.nan
            obs[part] = pose
            expected["not_finite"] += 1
        else:  # where a part is, but scaled
            pose = np.array(observations.get(part, next(iter(observations.values()))))
            pose[:3, :3] *= 1.5
            obs[part] = pose
            expected["not_rigid"] += 1
    return obs


@pytest.mark.heavy(seconds=20)
@pytest.mark.timeout(1200)  # CPU-bound and always advancing: on a busy machine several times 300 s
@pytest.mark.slow
@settings(settings.get_profile(PROFILE))
@given(scenarios)
def test_the_learner_never_breaks(s):
    """On any body, noise, bad input and change: no exception, the step counter counts the accepted calls, the
    structure stays sound after every step, and every malformed observation is counted under its reason."""
    tree, session, rng = _world(s)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    expected = {"unknown_id": 0, "not_finite": 0, "not_rigid": 0}
    stamp, accepted = 0.0, 0
    for t in range(session.n_steps):
        observations = _corrupt(session.observations[t], tree, s, rng, expected)
        stamp += 0.1
        if learner.last_stamp is not None and rng.uniform() < 0.03:  # from the past: refused, the learner unchanged
            with pytest.raises(StampOrderError):
                learner.update(session.actions[t], observations, stamp=stamp - 1.0)
            assert learner.step == accepted
        given_stamp = None if rng.uniform() < 0.05 else stamp  # some steps come without a stamp
        events = learner.update(session.actions[t], observations, stamp=given_stamp)
        accepted += 1
        assert learner.step == accepted
        assert structural_problems(learner.state) == []
        TOTALS["events"] += len(events)
        if learner.body_scheme is not None:
            predicted = learner.predict(session.actions[t])
            assert all(np.all(np.isfinite(pose)) for pose in predicted.values())
    for reason, count in expected.items():
        assert learner.rejected[reason] == count
    assert math.isfinite(learner.noise.sigma_trans) and learner.noise.sigma_trans > 0
    TOTALS["examples"] += 1
    TOTALS["steps"] += accepted
    TOTALS["rejected"] += sum(learner.rejected.values())
    _write_totals()


def _write_totals():
    out = os.environ.get("BODY_SCHEME_STRESS_OUT")
    if out:
        path = pathlib.Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"profile": PROFILE, "max_joints": MAX_JOINTS, **TOTALS}, indent=1) + "\n")
