"""Tests of the pair index and the relative observations of one time step."""

import itertools
import math

import numpy as np
import pytest

from body_scheme_core.calibration.noise_model import NoiseModel
from body_scheme_core.learning.relative import PartPairs
from body_scheme_core.learning.targets import translation_threshold
from body_scheme_core.transforms import invert_transform, relative_transform, transform_from_rotvec

THETA_T, THETA_R = 0.15, np.radians(45.0)


def _noise(parts):
    """The noise of the thresholds THETA_T, THETA_R (3 sigma)."""
    return NoiseModel(parts, THETA_T / 3, THETA_R / 3)


def _poses(rng, parts):
    return {p: transform_from_rotvec(rng.normal(size=3), rng.normal(size=3)) for p in parts}


def test_pairs_are_numbered_once_and_symmetrically():
    """Every unordered pair gets one index; both directions map to it; flip follows the part order."""
    pairs = PartPairs((7, 3, 5), _noise((7, 3, 5)))
    assert pairs.n_pairs == 3
    indices = {pairs.index(i, j) for i, j in itertools.combinations((7, 3, 5), 2)}
    assert indices == {0, 1, 2}
    assert all(pairs.index(i, j) == pairs.index(j, i) for i, j in itertools.permutations((7, 3, 5), 2))
    assert not pairs.flip(7, 5) and pairs.flip(5, 7) and pairs.flip(3, 7)


def test_relative_observations_of_observed_pairs():
    """Z of each pair with both parts seen is Y_i^-1 Y_j in the part order; pairs with a missing part get row -1."""
    rng = np.random.default_rng(0)
    parts = (7, 3, 5, 9)
    pairs = PartPairs(parts, _noise(parts))
    Y = _poses(rng, (9, 7, 5))  # part 3 not observed
    rel = pairs.observe(Y)
    for i, j in itertools.combinations(parts, 2):
        row = rel.row[pairs.index(i, j)]
        if 3 in (i, j):
            assert row == -1
        else:
            np.testing.assert_allclose(rel.Z[row], relative_transform(Y[i], Y[j]), atol=1e-12)
    assert rel.Z.shape == (3, 4, 4) and sorted(rel.row[rel.row >= 0]) == [0, 1, 2]


def test_thresholds_grow_with_the_observed_distance():
    """Each row's translational threshold is translation_threshold at the distance of its parts."""
    rng = np.random.default_rng(1)
    pairs = PartPairs((1, 2, 3), _noise((1, 2, 3)))
    rel = pairs.observe(_poses(rng, (1, 2, 3)))
    distance = np.linalg.norm(rel.Z[:, :3, 3], axis=1)
    np.testing.assert_allclose(rel.theta_trans, translation_threshold(THETA_T, THETA_R, distance))
    assert pairs.threshold(np.eye(4)) == pytest.approx(THETA_T)


def test_a_part_given_without_noise_adds_no_noise_and_no_lever_arm():
    """With part 1 exact (the sensor as root), its pairs carry one marker's noise and no lever arm of its orientation
    in both the noise and the threshold; the pair of two markers keeps both."""
    rng = np.random.default_rng(3)
    noise = _noise((1, 2, 3))
    rel = PartPairs((1, 2, 3), noise, exact=(1,)).observe(_poses(rng, (1, 2, 3)))
    both = PartPairs((1, 2, 3), noise).observe(_poses(np.random.default_rng(3), (1, 2, 3)))
    exact, markers = rel.row[0], rel.row[2]  # pairs (1, 2) and (2, 3)
    assert rel.sigma[exact, 0] == pytest.approx(noise.sigma_trans / math.sqrt(3))
    assert rel.sigma[exact, 1] == pytest.approx(noise.sigma_rot / math.sqrt(3))
    assert rel.theta_trans[exact] == pytest.approx(THETA_T)
    np.testing.assert_allclose(rel.sigma[markers], both.sigma[markers])
    np.testing.assert_allclose(rel.theta_trans[markers], both.theta_trans[markers])
    assert rel.theta_trans[markers] > THETA_T


def test_of_pairs_inverts_flipped_directions():
    """A model predicting child2parent of the canonical pair sees the inverse transform; the source is unchanged."""
    rng = np.random.default_rng(2)
    pairs = PartPairs((1, 2, 3), _noise((1, 2, 3)))
    Y = _poses(rng, (1, 2, 3))
    rel = pairs.observe(Y)
    before = rel.Z.copy()
    idx = np.array([pairs.index(3, 1), pairs.index(1, 2)])
    Z = rel.of_pairs(idx, np.array([pairs.flip(3, 1), pairs.flip(1, 2)]))
    np.testing.assert_allclose(Z[0], relative_transform(Y[3], Y[1]), atol=1e-12)
    np.testing.assert_allclose(Z[1], relative_transform(Y[1], Y[2]), atol=1e-12)
    np.testing.assert_allclose(Z[0] @ invert_transform(Z[0]), np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(rel.Z, before)


def test_fewer_than_two_observed_parts_give_no_relative_observation():
    """With one part seen, nothing is observed and every row is -1."""
    pairs = PartPairs((1, 2, 3), _noise((1, 2, 3)))
    rel = pairs.observe({2: np.eye(4)})
    assert rel.Z.shape == (0, 4, 4) and rel.theta_trans.shape == (0,) and np.all(rel.row == -1)


def test_mirror_hypotheses_give_each_pair_its_three_other_readings_and_never_mirror_an_exact_part():
    """With ``mirrors``, row k's alternatives are Y_i'^-1 Y_j, Y_i^-1 Y_j', Y_i'^-1 Y_j' (' = mirrored about the
    camera's ray); the sensor root, exact, is never mirrored; without ``mirrors`` there are none."""
    from body_scheme_core.transforms import mirror_about_ray

    rng = np.random.default_rng(4)
    parts = (1, 2, 3)
    Y = {p: transform_from_rotvec(rng.normal(size=3), [0.2 * p, -0.1, 1.5]) for p in parts}
    rel = PartPairs(parts, _noise(parts), mirrors=True).observe(Y)
    M = {p: mirror_about_ray(Y[p]) for p in parts}
    for (i, j), k in zip(itertools.combinations(parts, 2), range(3), strict=True):
        row = rel.row[k]
        assert np.allclose(rel.Z[row], relative_transform(Y[i], Y[j]))
        assert np.allclose(rel.alternatives[row], [relative_transform(M[i], Y[j]), relative_transform(Y[i], M[j]),
                                                   relative_transform(M[i], M[j])])
    assert np.allclose(rel.targets(np.array([2])).alternatives[0][1], relative_transform(Y[2], M[3]))
    exact = PartPairs(parts, _noise(parts), exact=(1,), mirrors=True).observe({**Y, 1: np.eye(4)})
    assert np.allclose(exact.alternatives[exact.row[0]][0], exact.Z[exact.row[0]])  # part 1 stays as given
    assert PartPairs(parts, _noise(parts)).observe(Y).alternatives is None
