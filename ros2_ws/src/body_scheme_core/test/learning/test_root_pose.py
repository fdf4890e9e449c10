"""Tests of the root-pose estimate (robust mean of the root's observations, then registration of all markers) and of
the root's change detector."""

import numpy as np

from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.root_pose import OFFSET_SAMPLES, RootPoseEstimator, RootWatch, register_points
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.transforms import rotational_error, transform_from_rotvec, translational_error
from body_scheme_core.world import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS, make_session, powercube_6dof

A0 = np.zeros(2)


def test_identity_until_the_root_is_seen():
    """Without observations (or with none of the root) the estimate is the identity."""
    estimator = RootPoseEstimator(5, root=1)
    np.testing.assert_array_equal(estimator.pose(), np.eye(4))
    estimator.add(A0, {2: transform_from_rotvec([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])})
    np.testing.assert_array_equal(estimator.pose(), np.eye(4))


def test_outliers_do_not_move_the_root_mean():
    """Without a body scheme: four wild root poses among eleven noisy ones leave the median estimate near the truth."""
    rng = np.random.default_rng(0)
    truth = transform_from_rotvec([0.1, -0.2, 0.3], [1.0, 2.0, 0.5])
    estimator = RootPoseEstimator(20, root=1)
    for _ in range(11):
        estimator.add(A0, {1: truth @ transform_from_rotvec(rng.normal(scale=0.05, size=3),
                                                              rng.normal(scale=0.02, size=3))})
    for _ in range(4):
        estimator.add(A0, {1: transform_from_rotvec(rng.normal(size=3), rng.uniform(-5.0, 5.0, size=3))})
    pose = estimator.pose()
    assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.03
    assert rotational_error(pose, truth) < 0.1
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(pose[:3, :3]) > 0.0


def test_only_the_last_window_samples_count():
    """Beyond the window the oldest sample is dropped, and the estimate follows the new ones."""
    estimator = RootPoseEstimator(3, 1, [(A0, {1: transform_from_rotvec([0.0, 0.0, 0.0], [9.0, 9.0, 9.0])})])
    first = estimator.pose().copy()
    for x in (1.0, 2.0, 3.0):
        estimator.add(A0, {1: transform_from_rotvec([0.0, 0.0, 0.0], [x, 0.0, 0.0])})
    assert len(estimator.samples) == 3
    np.testing.assert_allclose(first[:3, 3], [9.0, 9.0, 9.0])
    np.testing.assert_allclose(estimator.pose()[:3, 3], [2.0, 0.0, 0.0])


def test_register_points_recovers_a_rigid_transform():
    """Noise-free corresponding points give back the transform exactly, a proper rotation."""
    rng = np.random.default_rng(1)
    T = transform_from_rotvec([0.4, -1.0, 2.0], [0.3, -0.2, 1.5])
    P = rng.normal(size=(10, 3))
    np.testing.assert_allclose(register_points(P, P @ T[:3, :3].T + T[:3, 3]), T, atol=1e-12)


def test_registration_of_all_markers_beats_the_root_markers_own_observations():
    """With a correct body scheme, the paper's noise and 50 samples, registering all markers' positions puts the root
    (and so the end effector, ~1 m away) several times closer to the truth than the root marker's median pose."""
    tree = powercube_6dof()
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    errors = {"mean": [], "registered": []}
    for seed in range(5):
        session = make_session(tree, 50, seed, sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT,
                               visibility=0.9, above_ground=True)
        estimator = RootPoseEstimator(50, root=tree.root_marker)
        for a, observations in zip(session.actions, session.observations, strict=True):
            estimator.add(a, observations)
        truth = session.true_poses[0, session.marker_ids.index(tree.root_marker)]
        effector = scheme.predict(session.actions[-1])[max(tree.marker_ids)]
        for name, pose in (("mean", estimator.pose()), ("registered", estimator.pose(scheme))):
            errors[name].append(np.linalg.norm((pose @ effector)[:3, 3] - (truth @ effector)[:3, 3]))
    assert np.mean(errors["registered"]) < 0.015
    assert np.mean(errors["registered"]) < 0.3 * np.mean(errors["mean"])


def test_registration_drops_a_marker_the_body_scheme_mispredicts():
    """A marker observed 0.5 m from where the scheme puts it (a fault) does not drag the registered root."""
    tree = powercube_6dof()
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    session = make_session(tree, 30, 0, sigma_trans=0.005, sigma_rot=0.01, above_ground=True)
    estimator = RootPoseEstimator(30, root=tree.root_marker)
    shift = transform_from_rotvec([0.0, 0.0, 0.0], [0.5, 0.0, 0.0])
    for a, observations in zip(session.actions, session.observations, strict=True):
        estimator.add(a, {part: shift @ Y if part == 7 else Y for part, Y in observations.items()})
    truth = session.true_poses[0, session.marker_ids.index(tree.root_marker)]
    pose = estimator.pose(scheme)
    assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.01
    assert rotational_error(pose, truth) < np.radians(1.0)


def test_pose_is_cached_per_scheme_until_the_next_sample():
    """The same scheme object gets the cached pose; a new sample recomputes it."""
    tree = powercube_6dof()
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    session = make_session(tree, 10, 0, above_ground=True)
    estimator = RootPoseEstimator(10, root=tree.root_marker)
    for a, observations in zip(session.actions[:9], session.observations[:9], strict=True):
        estimator.add(a, observations)
    first = estimator.pose(scheme)
    assert estimator.pose(scheme) is first
    estimator.add(session.actions[9], session.observations[9])
    assert estimator.pose(scheme) is not first


def _watch(observed, world2root, theta=0.015):
    """Feed ``observed`` poses of the root's marker to a RootWatch; the steps at which it alarms."""
    watch, alarms = RootWatch(BodySchemeConfig()), []
    for t, Y in enumerate(observed):
        expected = watch.expected(world2root)
        errors = None if expected is None else (translational_error(expected, Y), rotational_error(expected, Y))
        if watch.check(errors, t, theta, 0.1) is not None:
            alarms.append(t)
        watch.learn_offset(world2root, Y)
    return alarms


def test_the_root_watch_alarms_once_for_an_offset_the_fit_does_not_follow_and_once_when_the_marker_moves():
    """A real tracker may see the root's marker 19 mm deeper than the joint fit puts it, for ever: one alarm, not one
    every 3 steps as before the offset. A marker moved later by 5 thresholds alarms once more, within a few steps."""
    rng = np.random.default_rng(0)
    world2root = transform_from_rotvec([0.1, 0.2, 0.3], [0.1, 0.0, 2.0])
    biased = world2root @ transform_from_rotvec(np.zeros(3), [0.0, 0.0, 0.019])
    noisy = [biased @ transform_from_rotvec(rng.normal(0, 0.01, 3), rng.normal(0, 0.002, 3)) for _ in range(120)]
    alarms = _watch(noisy, world2root)
    assert len(alarms) == 1 and alarms[0] < 10
    moved = noisy[:60] + [Y @ transform_from_rotvec(np.zeros(3), [0.075, 0.0, 0.0]) for Y in noisy[60:]]
    alarms = _watch(moved, world2root)
    assert len(alarms) == 2 and 60 <= alarms[1] <= 60 + 5
    assert alarms[0] + OFFSET_SAMPLES < 60


def test_without_an_offset_the_root_watch_is_quiet_on_noise():
    rng = np.random.default_rng(1)
    world2root = transform_from_rotvec([0.1, 0.2, 0.3], [0.1, 0.0, 2.0])
    noisy = [world2root @ transform_from_rotvec(rng.normal(0, 0.01, 3), rng.normal(0, 0.0029, 3)) for _ in range(300)]
    assert _watch(noisy, world2root) == []
