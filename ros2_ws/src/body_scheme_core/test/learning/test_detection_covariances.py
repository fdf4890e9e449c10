"""Tests of the learner's use of each detection's own covariance (``update(..., covariances=...)``)."""

import json
import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import make_session, planar_2dof

LATERAL, DEPTH, ROTATION = 0.002, 0.010, math.radians(1.5)


def _covariance(Y, factor):
    """A tag detector's covariance of pose ``Y``: ``factor`` times a camera's lateral / depth / rotation noise."""
    ray = Y[:3, 3] / np.linalg.norm(Y[:3, 3])
    C = np.zeros((6, 6))
    C[:3, :3] = factor**2 * (LATERAL**2 * (np.eye(3) - np.outer(ray, ray)) + DEPTH**2 * np.outer(ray, ray))
    C[3:, 3:] = factor**2 * ROTATION**2 * np.eye(3)
    return C


def _detections(session, rng, claimed=1.0):
    """Observations whose noise differs per detection (one to five times the camera's), with covariances that claim
    ``claimed`` times the true one."""
    observations, covariances = [], []
    for k in range(len(session.actions)):
        obs, covs = {}, {}
        for column, part in enumerate(session.marker_ids):
            Y = session.true_poses[k, column]
            factor = rng.uniform(1.0, 5.0)
            e = rng.multivariate_normal(np.zeros(6), _covariance(Y, factor))
            obs[part] = transform_from_rotvec(e[3:], Y[:3, 3] + e[:3]) @ np.linalg.inv(
                transform_from_rotvec(np.zeros(3), Y[:3, 3])) @ Y
            covs[part] = _covariance(Y, factor * claimed)
        observations.append(obs)
        covariances.append(covs)
    return observations, covariances


@pytest.fixture(scope="module")
def learned():
    """The 2-DOF arm learned from 120 detections, each with its covariance (claiming half its noise)."""
    robot = planar_2dof()
    session = make_session(robot, 120, seed=3, sigma_trans=1e-9, sigma_rot=1e-9)
    observations, covariances = _detections(session, np.random.default_rng(3), claimed=0.5)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(detection_covariances=True))
    for a, obs, covs in zip(session.actions, observations, covariances, strict=True):
        learner.update(a, obs, covariances=covs)
    return learner, session, observations, covariances


def test_the_learner_learns_the_scale_on_the_detectors_covariances(learned):
    """Covariances that claim half the noise: the learned scale is about 2, and the body scheme is learned."""
    learner, *_ = learned
    assert learner.body_scheme is not None and not learner.rejected
    assert learner.noise.n_detected >= 100
    assert learner.noise.detection_scale == pytest.approx((2.0, 2.0), rel=0.2)


def test_a_saved_learner_keeps_the_covariances_and_continues_identically(learned):
    """The state file holds each step's covariances; the loaded learner predicts as the original after more steps
    with covariances."""
    learner, session, observations, covariances = learned
    state = json.loads(json.dumps(learner.to_state()))
    assert sum("covariances" in rec for rec in state["history"]) == len(state["history"])
    loaded = BodySchemeLearner.from_state(state)
    copy = BodySchemeLearner.from_state(state)
    for k in range(100, 120):
        a, obs, covs = session.actions[k], observations[k], covariances[k]
        events = [e.to_dict() for e in copy.update(a, obs, covariances=covs)]
        assert [e.to_dict() for e in loaded.update(a, obs, covariances=covs)] == events
    loaded.recalibrate()
    copy.recalibrate()
    p, q = loaded.predict(session.actions[0]), copy.predict(session.actions[0])
    assert all(np.array_equal(p[i], q[i]) for i in p)
    assert loaded.noise.detection_scale == copy.noise.detection_scale
    bad = json.loads(json.dumps(state))
    bad["history"][0]["covariances"][0][1] = [[1.0] * 6] * 6  # singular
    with pytest.raises(ModelFileError, match="positive definite"):
        BodySchemeLearner.from_state(bad)


def test_unusable_covariances_are_counted_and_their_poses_kept():
    """A covariance with NaN, one not symmetric, one of the wrong shape: each counted as bad_covariance and
    reported, its pose used; all zeros ("not estimated") is no error; a covariance of a part not observed is
    dropped with it; anything but a mapping is refused before the step."""
    robot = planar_2dof()
    session = make_session(robot, 2, seed=1)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(detection_covariances=True))
    ids = list(robot.marker_ids)
    obs = session.observations[0]
    good = np.eye(6) * 1e-4
    skew = good.copy()
    skew[0, 1] = 1e-5
    events = learner.update(session.actions[0], obs, covariances={ids[0]: np.full((6, 6), np.nan), ids[1]: skew,
                                                                  ids[2]: np.eye(3), 99: good})
    assert learner.rejected == {"bad_covariance": 3}
    reported = [e for e in events if e.kind == "input_rejected"]
    assert len(reported) == 3 and all("covariance rejected (bad_covariance)" in e.reason for e in reported)
    assert learner.to_state()["history"][0]["observations"] and "covariances" not in learner.to_state()["history"][0]
    learner.update(session.actions[1], session.observations[1], covariances={ids[0]: np.zeros(36), ids[1]: good})
    assert learner.rejected == {"bad_covariance": 3}
    assert [p for p, _ in learner.to_state()["history"][1]["covariances"]] == [ids[1]]
    with pytest.raises(InvalidInputError, match="covariances must be a mapping"):
        learner.update(session.actions[1], session.observations[1], covariances=[good])
    assert learner.step == 2


def test_by_default_the_covariances_are_not_used():
    """detection_covariances off (the default): covariances, even unusable ones, are neither kept nor counted."""
    robot = planar_2dof()
    session = make_session(robot, 1, seed=1)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions)
    learner.update(session.actions[0], session.observations[0],
                   covariances={p: np.full((6, 6), np.nan) for p in robot.marker_ids})
    assert not learner.rejected and "covariances" not in learner.to_state()["history"][0]


def test_a_pose_taken_in_as_its_mirror_image_loses_its_detections_covariance():
    """The detector's covariance belongs to the solution it gave, not to its mirror image: a flipped orientation the
    scheme corrects is kept without one, the other parts keep theirs."""
    from body_scheme_core.transforms import mirror_about_ray

    robot = planar_2dof()
    session = make_session(robot, 60, seed=4, sigma_trans=0.005, sigma_rot=math.radians(1.0))
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(detection_covariances=True))
    for k in range(59):
        learner.update(session.actions[k], session.observations[k])
    observations = dict(session.observations[59])
    observations[3] = mirror_about_ray(observations[3])
    learner.update(session.actions[59], observations, covariances={p: np.eye(6) * 1e-4 for p in observations})
    assert learner.corrected["flipped"] == 1
    kept = [p for p, _ in learner.to_state()["history"][-1]["covariances"]]
    assert 3 not in kept and sorted(kept) == sorted(p for p in observations if p != 3)
