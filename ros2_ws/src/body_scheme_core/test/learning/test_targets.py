"""Tests of what tracked models are tested against (targets.py): Targets and the lever-arm threshold."""

import math

import numpy as np
import pytest

from body_scheme_core.calibration.noise_model import NoiseModel
from body_scheme_core.learning.quality import prediction_errors
from body_scheme_core.learning.relative import PartPairs
from body_scheme_core.learning.targets import Targets, translation_threshold
from body_scheme_core.transforms import invert_transform, mirror_about_ray, transform_from_rotvec

THETA_T, THETA_R = 0.15, math.radians(45.0)


def _link(a):
    """True ``1->2`` transform of a one-joint link: yaw ``a``, 0.3 m along the rotated x axis."""
    return transform_from_rotvec([0.0, 0.0, a], [0.3 * np.cos(a), 0.3 * np.sin(a), 0.0])


def test_translation_threshold_grows_with_lever_arm():
    """At zero distance the threshold is theta_trans; it grows like the parent's orientation noise moves the child."""
    assert translation_threshold(THETA_T, THETA_R, 0.0) == pytest.approx(THETA_T)
    d = np.array([0.0, 0.5, 1.0])
    theta = translation_threshold(THETA_T, THETA_R, d)
    np.testing.assert_allclose(theta, np.sqrt(THETA_T**2 + 2.0 / 3.0 * THETA_R**2 * d**2))
    assert np.all(np.diff(theta) > 0)


def test_targets_select_rows():
    """Targets.select keeps the rows asked for, in order."""
    targets = Targets(np.stack([np.eye(4)] * 3), np.array([1.0, 2.0, 3.0]), np.full(3, 0.5), np.ones((3, 2)),
                      np.array([False, True, False]))
    sub = targets.select([2, 1])
    np.testing.assert_array_equal(sub.theta_trans, [3.0, 2.0])
    np.testing.assert_array_equal(sub.flip, [False, True])


def test_a_model_is_judged_against_a_mirrored_reading_only_where_that_explains_what_the_given_one_does_not():
    """Targets.nearest: a flipped child pose is read mirrored when the prediction is off by more than the
    thresholds and the mirrored reading is within them; a reading the prediction explains is kept as given, and a
    mirrored one that is not within the thresholds is not taken either."""
    pairs = PartPairs((1, 2), NoiseModel((1, 2), 0.005, np.radians(1.0)), mirrors=True)  # thresholds 15 mm, 3 deg
    world2base = transform_from_rotvec([0.2, -0.3, 0.1], [0.1, 0.0, 1.5])
    truth = world2base @ _link(0.7)
    tilted = truth @ transform_from_rotvec([0.0, 0.9, 0.0], [0.0, 0.0, 0.0])  # 52 deg from face-on: a large flip
    link = invert_transform(world2base) @ tilted
    flipped = pairs.observe({1: world2base, 2: mirror_about_ray(tilted)}).targets(np.array([0]))
    given = pairs.observe({1: world2base, 2: tilted}).targets(np.array([0]))
    assert prediction_errors(link[None], flipped.Z)[1][0] > np.radians(20)
    assert np.allclose(flipped.nearest(link[None]), link[None])
    assert np.array_equal(given.nearest(link[None]), given.Z)
    wrong = link @ transform_from_rotvec([0.0, 0.0, 1.5], [0.0, 0.0, 0.0])  # a model off either way
    assert np.array_equal(flipped.nearest(wrong[None]), flipped.Z)
