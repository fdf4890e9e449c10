"""Tests of the lack-of-fit test of the joint fit's residuals (consistency.py)."""

import math

import numpy as np

from body_scheme_core.calibration.consistency import action_features, lack_of_fit, part_consistency


def test_noise_passes():
    """Residuals that are noise (independent of the commands) pass: over 400 parts at most 1 % have p below 0.01 (the
    Bonferroni correction over the actions makes the test conservative)."""
    rng = np.random.default_rng(0)
    p = np.array([lack_of_fit(rng.normal(size=(120, 6)), rng.uniform(-2, 2, (120, 5))).p for _ in range(400)])
    assert np.mean(p < 0.01) <= 0.01
    assert np.mean(p < 0.2) > 0.05


def test_a_missing_joint_leaves_residuals_that_follow_its_command():
    """Residuals that follow one command (a joint the model lacks) by about the noise's size fail."""
    rng = np.random.default_rng(1)
    A = rng.uniform(-1.5, 1.5, (100, 7))
    r = rng.normal(size=(100, 6))
    r[:, 0] += np.sin(A[:, 4])
    r[:, 2] += np.cos(A[:, 4])
    test = lack_of_fit(r, A)
    assert test.tested and test.p < 1e-5 and test.explained > 0.05


def test_one_wild_residual_is_clipped():
    """A single residual of 1000 sigmas does not make noise look explained."""
    rng = np.random.default_rng(2)
    A = rng.uniform(-1, 1, (100, 3))
    r = rng.normal(size=(100, 6))
    r[7] = 1000.0
    assert lack_of_fit(r, A).p > 1e-3


def test_too_few_observations_are_not_tested():
    """With fewer observations than one action's regression needs plus a margin, the part is untested (NaN), and
    constant commands give no features."""
    rng = np.random.default_rng(3)
    test = lack_of_fit(rng.normal(size=(10, 6)), rng.uniform(-1, 1, (10, 6)))
    assert not test.tested and math.isnan(test.F)
    assert action_features(np.ones(10)).shape == (10, 0)
    assert not lack_of_fit(rng.normal(size=(50, 6)), np.ones((50, 3))).tested


def test_every_part_is_tested_on_its_own_observations():
    """part_consistency groups the residuals by part: only the part with structured residuals fails."""
    rng = np.random.default_rng(4)
    A = rng.uniform(-1.5, 1.5, (200, 4))
    parts = np.repeat([1, 2], 100)
    r = rng.normal(size=(200, 6))
    r[parts == 2, 1] += np.sin(A[parts == 2, 0])
    result = part_consistency(parts, r, A)
    assert result[1].p > 1e-3 and result[2].p < 1e-6
