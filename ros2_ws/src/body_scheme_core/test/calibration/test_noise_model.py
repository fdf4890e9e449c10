"""Tests of the learned observation noise (noise_model.py): robust scales, rays, per-marker and pooled estimates."""

import math

import numpy as np
import pytest

from body_scheme_core.calibration.noise_model import (
    MAX_DETECTION_SCALE,
    MIN_DETECTION_SCALE,
    MIN_SIGMA_ROT,
    MIN_SIGMA_TRANS,
    NoiseModel,
    ray_components,
    robust_variance,
)
from body_scheme_core.errors import ModelFileError


@pytest.mark.parametrize("dof", [1, 2, 3])
def test_robust_variance_is_unbiased_on_gaussian_residuals(dof):
    """On chi-square residual norms the estimate's mean over many draws is the per-axis variance."""
    rng = np.random.default_rng(0)
    estimates = [robust_variance((rng.normal(scale=0.5, size=(60, dof)) ** 2).sum(axis=1), dof) for _ in range(500)]
    assert np.mean(estimates) == pytest.approx(0.25, rel=0.03)


def test_robust_variance_ignores_a_few_outliers():
    """Five percent of residuals twenty times larger (mirrored markers) move the estimate by less than 5 %."""
    rng = np.random.default_rng(1)
    q = (rng.normal(size=(400, 3)) ** 2).sum(axis=1)
    q[:20] *= 400.0
    assert robust_variance(q, 3) == pytest.approx(1.0, rel=0.05)
    assert math.isnan(robust_variance([], 3))


def test_ray_components_split_a_residual_along_and_across_the_ray():
    """A residual along the ray to the marker is all depth; one perpendicular to it all lateral."""
    position = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 1.0]])
    along = position / np.linalg.norm(position, axis=1, keepdims=True) * 0.03
    lateral, depth = ray_components(along, position)
    np.testing.assert_allclose(depth, [0.03**2] * 2)
    np.testing.assert_allclose(lateral, [0.0, 0.0], atol=1e-15)
    lateral, depth = ray_components(np.array([[0.02, 0.0, 0.0], [0.0, 0.02, 0.0]]), position)
    np.testing.assert_allclose(lateral, [0.02**2] * 2)
    np.testing.assert_allclose(depth, [0.0, 0.0], atol=1e-15)


def _camera_residuals(rng, parts, n, lateral, depth, rot, positions=None):
    """Residuals of ``n`` observations per part with per-axis noise across and along the ray."""
    P, RT, RR, POS = [], [], [], []
    for k, part in enumerate(parts):
        pos = rng.normal(scale=0.3, size=(n, 3)) + [0.0, 0.3, 2.0] if positions is None else positions[k]
        ray = pos / np.linalg.norm(pos, axis=1, keepdims=True)
        r = rng.normal(scale=lateral, size=(n, 3))
        r += (depth / lateral - 1.0) * np.sum(r * ray, axis=1, keepdims=True) * ray
        P += [part] * n
        RT.append(r)
        RR.append(rng.normal(scale=rot, size=(n, 3)))
        POS.append(pos)
    return np.array(P), np.concatenate(RT), np.concatenate(RR), np.concatenate(POS)


def test_lateral_depth_and_rotation_are_estimated_per_marker_and_pooled():
    """A camera 3 mm across the ray and 20 mm along it, 2 deg: every marker's estimate and the pooled one are within
    10 % (200 observations each), and the 3D RMS follows."""
    rng = np.random.default_rng(2)
    noise = NoiseModel((1, 2, 3, 4), 0.05, math.radians(15.0), auto=(True, True))
    rot = math.radians(2.0) / math.sqrt(3.0)
    noise.update(*_camera_residuals(rng, (1, 2, 3, 4), 200, 0.003, 0.020, rot))
    for lateral, depth, rotation, n in noise.per_part().values():
        assert n == 200
        assert lateral == pytest.approx(0.003, rel=0.1) and depth == pytest.approx(0.020, rel=0.1)
        assert rotation == pytest.approx(rot, rel=0.1)
    assert noise.sigma_trans == pytest.approx(math.sqrt(2 * 0.003**2 + 0.020**2), rel=0.1)
    assert noise.sigma_rot == pytest.approx(math.radians(2.0), rel=0.1)
    assert noise.theta_trans > 3 * noise.sigma_trans  # the upper confidence bound of the estimate


def test_one_marker_with_a_wrong_model_does_not_move_the_pooled_noise():
    """One marker of five with residuals ten times the noise (a wrong model above it): the pooled estimate, which
    sets every threshold, stays within 10 % of the others' noise; that marker's own weight is kept within a factor 2."""
    rng = np.random.default_rng(3)
    noise = NoiseModel((1, 2, 3, 4, 5), 0.05, 0.2, auto=(True, True))
    parts, rt, rr, pos = _camera_residuals(rng, (1, 2, 3, 4, 5), 100, 0.01, 0.01, 0.05)
    wrong = parts == 5
    rt[wrong] *= 10.0
    rr[wrong] *= 10.0
    noise.update(parts, rt, rr, pos)
    assert noise.axis_sigmas()[0] == pytest.approx(0.01, rel=0.1)
    assert noise.axis_sigmas(5)[0] == pytest.approx(2 * noise.axis_sigmas()[0])


def test_a_marker_seen_from_one_viewpoint_is_left_out_of_the_pooled_estimate():
    """Three of five markers never move (spread under STILL_SPREAD) and their residuals are larger (a still
    marker's errors repeat): the pooled estimate follows the two that move, although a median over all five would
    follow the still majority; with nothing moving, the still markers are all there is."""
    from body_scheme_core.calibration.noise_model import STILL_SPREAD

    rng = np.random.default_rng(6)
    still = [np.tile([0.1 * k, 0.3, 2.0], (100, 1)) + rng.normal(scale=STILL_SPREAD / 10, size=(100, 3))
             for k in range(3)]
    moving = [rng.normal(scale=0.3, size=(100, 3)) + [0.0, 0.3, 2.0] for _ in range(2)]
    parts, rt, rr, pos = _camera_residuals(rng, (1, 2, 3, 4, 5), 100, 0.004, 0.004, 0.02, still + moving)
    rt[parts <= 3] *= 3.0
    noise = NoiseModel((1, 2, 3, 4, 5), 0.05, 0.2, auto=(True, True))
    noise.update(parts, rt, rr, pos)
    assert noise.axis_sigmas()[0] == pytest.approx(0.004, rel=0.1)
    assert noise.n_observations == 200
    only_still = parts <= 3
    noise.update(parts[only_still], rt[only_still], rr[only_still], pos[only_still])
    assert noise.axis_sigmas()[0] == pytest.approx(0.012, rel=0.1) and noise.n_observations == 300


def test_an_auto_prior_yields_to_data_and_a_given_prior_weighs_like_fifty_observations():
    """With "auto" the first estimate replaces the prior; a prior the user gave is averaged with the data."""
    rng = np.random.default_rng(4)
    data = _camera_residuals(rng, (1, 2), 100, 0.01, 0.01, 0.05)
    auto = NoiseModel((1, 2), 0.05, 0.2, auto=(True, True))
    assert auto.sigma_trans == pytest.approx(0.05)
    auto.update(*data)
    assert auto.axis_sigmas()[0] == pytest.approx(0.01, rel=0.1)
    given = NoiseModel((1, 2), 0.05, 0.2)
    given.update(*data)
    prior_var = 0.05**2 / 3
    expected = math.sqrt((50 * prior_var + 200 * auto.pooled[0]) / 250)
    assert given.axis_sigmas()[0] == pytest.approx(expected)


def test_fixed_thresholds_are_kept():
    """theta_trans and theta_rot given in the configuration do not follow the estimate."""
    noise = NoiseModel((1, 2), 0.05, 0.2, theta_trans=0.1, theta_rot=0.5)
    noise.update(*_camera_residuals(np.random.default_rng(5), (1, 2), 100, 0.01, 0.01, 0.05))
    assert (noise.theta_trans, noise.theta_rot) == (0.1, 0.5)


def test_the_noise_state_round_trips_and_bad_states_are_refused():
    """to_dict / load_dict restores the estimate; unknown parts and negative variances give ModelFileError."""
    noise = NoiseModel((1, 2), 0.05, 0.2, auto=(True, True))
    noise.update(*_camera_residuals(np.random.default_rng(6), (1, 2), 50, 0.01, 0.02, 0.05))
    state = noise.to_dict()
    restored = NoiseModel((1, 2), 0.05, 0.2, auto=(True, True)).load_dict(state)
    assert restored.axis_sigmas() == noise.axis_sigmas() and restored.axis_sigmas(1) == noise.axis_sigmas(1)
    with pytest.raises(ModelFileError, match="unknown part"):
        NoiseModel((1, 3), 0.05, 0.2).load_dict(state)
    with pytest.raises(ModelFileError, match="pooled"):
        NoiseModel((1, 2), 0.05, 0.2).load_dict(dict(state, pooled=[-1.0, 1.0, 1.0]))
    with pytest.raises(ModelFileError):
        NoiseModel((1, 2), 0.05, 0.2).load_dict({"pooled": [1, 1, 1]})


def test_a_scale_on_the_detections_own_covariances_is_learned_and_kept():
    """Residuals whitened by covariances that claim half the true noise in position and the true noise in rotation:
    the learned scale is 2 and 1 (within 10 %, 200 detections of moving markers) and the joint fit's covariance is
    the given one scaled, plus the floor; fewer than MIN_OBSERVATIONS detections, or a scale near 0 (residuals a fit
    absorbed), do not take it below the floor; it round-trips through the state."""
    rng = np.random.default_rng(8)
    noise = NoiseModel((1, 2), 0.05, 0.2, auto=(True, True))
    assert noise.detection_scale == (1.0, 1.0)
    parts, rt, rr, pos = _camera_residuals(rng, (1, 2), 150, 0.01, 0.02, 0.05)
    whitened = np.hstack([rng.normal(scale=2.0, size=(300, 3)), rng.normal(scale=1.0, size=(300, 3))])
    detected = np.arange(300) % 3 > 0  # two thirds came with a covariance
    noise.update(parts, rt, rr, pos, detected=(detected, whitened))
    assert noise.n_detected == 200
    assert noise.detection_scale == pytest.approx((2.0, 1.0), rel=0.1)
    C = np.diag([1e-4, 1e-4, 4e-4, 1e-3, 1e-3, 1e-3])
    s_t, s_r = noise.detection_scale
    expected = np.diag(np.diag(C) * np.repeat([s_t**2, s_r**2], 3) + np.repeat([MIN_SIGMA_TRANS**2,
                                                                                 MIN_SIGMA_ROT**2], 3))
    np.testing.assert_allclose(noise.detection_covariance(C), expected)
    learned = noise.detection_scale
    few = np.zeros(300, dtype=bool)
    few[:5] = True
    noise.update(parts, rt, rr, pos, detected=(few, whitened * 10))
    assert noise.detection_scale == learned
    noise.update(parts, rt, rr, pos, detected=(detected, whitened * 1e-6))
    assert noise.detection_scale == pytest.approx((MIN_DETECTION_SCALE, MIN_DETECTION_SCALE))
    noise.update(parts, rt, rr, pos, detected=(detected, whitened * 1e6))  # a detector far off: capped, still saved
    assert noise.detection_scale == pytest.approx((MAX_DETECTION_SCALE, MAX_DETECTION_SCALE))
    assert NoiseModel((1, 2), 0.05, 0.2).load_dict(noise.to_dict()).detection_scale == noise.detection_scale
    restored = NoiseModel((1, 2), 0.05, 0.2, auto=(True, True)).load_dict(noise.to_dict())
    assert restored.detection_scale == noise.detection_scale
    old = {k: v for k, v in noise.to_dict().items() if k not in ("detection", "n_detected")}
    assert NoiseModel((1, 2), 0.05, 0.2).load_dict(old).detection_scale == (1.0, 1.0)  # a file from before
