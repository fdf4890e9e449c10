"""Tests of body_scheme_core.rotations: the nearest rotation to a matrix, and the basis perpendicular to an axis."""

import itertools

import numpy as np
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from body_scheme_core.rotations import perpendicular_basis, project_to_rotation


def test_projection_of_noisy_rotation_is_close_rotation():
    """Projecting a perturbed rotation gives a valid rotation closer to the matrix than the original."""
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=1).as_matrix()
    M = R + 0.05 * rng.normal(size=R.shape)
    P = project_to_rotation(M)
    assert_allclose(np.swapaxes(P, 1, 2) @ P, np.broadcast_to(np.eye(3), P.shape), atol=1e-12)
    assert_allclose(np.linalg.det(P), 1.0, atol=1e-12)
    assert np.all(np.linalg.norm(P - M, axis=(1, 2)) <= np.linalg.norm(R - M, axis=(1, 2)) + 1e-12)
    angle = np.arccos(np.clip((np.einsum("nij,nij->n", P, R) - 1.0) / 2.0, -1.0, 1.0))
    assert np.all(angle < 0.2)


def test_projection_fixes_reflection():
    """A reflection is projected onto the nearest proper rotation, not onto itself."""
    M = np.diag([1.0, 1.0, -1.0])
    P = project_to_rotation(M)
    assert_allclose(np.linalg.det(P), 1.0)
    assert_allclose(P.T @ P, np.eye(3), atol=1e-12)


def test_projection_of_scaled_rotation_is_the_rotation():
    """The nearest rotation to s * R (s > 0) is R."""
    R = Rotation.from_rotvec([0.2, -0.4, 0.9]).as_matrix()
    assert_allclose(project_to_rotation(0.3 * R), R, atol=1e-12)


def test_the_perpendicular_basis_is_smooth_at_a_urdfs_axes():
    """perpendicular_basis completes u to a right-handed orthonormal basis, and moves by no more than u does near
    every coordinate axis, face and body diagonal (a URDF's joint axes): an increment's meaning, a covariance and a
    prior on an axis stay put while a fit turns it a little."""
    rng = np.random.default_rng(2)
    directions = [np.array(v, dtype=float) / np.linalg.norm(v)
                  for v in itertools.product((-1, 0, 1), repeat=3) if any(v)]
    for u in directions:
        e1, e2 = perpendicular_basis(u)
        assert np.allclose(np.stack([e1, e2, u]) @ np.stack([e1, e2, u]).T, np.eye(3), atol=1e-12)
        assert np.allclose(np.cross(e1, e2), u, atol=1e-12)
        for _ in range(20):
            v = u + rng.normal(0, 1e-4, 3)
            v /= np.linalg.norm(v)
            f1, _ = perpendicular_basis(v)
            assert np.linalg.norm(f1 - e1) < 10 * np.linalg.norm(v - u)
