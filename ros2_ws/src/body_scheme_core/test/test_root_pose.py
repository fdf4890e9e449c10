"""Tests of the robust root-pose estimate."""

import numpy as np

from body_scheme_core.root_pose import RootPoseEstimator
from body_scheme_core.transforms import rotational_error, transform_from_rotvec


def test_identity_until_the_root_is_seen():
    """Without observations the estimate is the identity."""
    np.testing.assert_array_equal(RootPoseEstimator(5).pose, np.eye(4))


def test_outliers_do_not_move_the_estimate():
    """Four wild poses among eleven noisy ones leave the median estimate near the true pose."""
    rng = np.random.default_rng(0)
    truth = transform_from_rotvec([0.1, -0.2, 0.3], [1.0, 2.0, 0.5])
    estimator = RootPoseEstimator(20)
    for _ in range(11):
        estimator.add(truth @ transform_from_rotvec(rng.normal(scale=0.05, size=3), rng.normal(scale=0.02, size=3)))
    for _ in range(4):
        estimator.add(transform_from_rotvec(rng.normal(size=3), rng.uniform(-5.0, 5.0, size=3)))
    pose = estimator.pose
    assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.03
    assert rotational_error(pose, truth) < 0.1
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(pose[:3, :3]) > 0.0


def test_only_the_last_window_observations_count():
    """Beyond the window the oldest observation is dropped, and the estimate follows the new ones."""
    estimator = RootPoseEstimator(3, [transform_from_rotvec([0.0, 0.0, 0.0], [9.0, 9.0, 9.0])])
    first = estimator.pose.copy()
    for x in (1.0, 2.0, 3.0):
        estimator.add(transform_from_rotvec([0.0, 0.0, 0.0], [x, 0.0, 0.0]))
    assert len(estimator.observations) == 3
    np.testing.assert_allclose(first[:3, 3], [9.0, 9.0, 9.0])
    np.testing.assert_allclose(estimator.pose[:3, 3], [2.0, 0.0, 0.0])
