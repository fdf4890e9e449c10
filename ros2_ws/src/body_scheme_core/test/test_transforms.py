"""Tests of body_scheme_core.transforms: round trips, hand-computed errors, and rejection of bad input."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import (
    check_quaternion,
    check_transform,
    concat,
    invert_transform,
    perpendicular_basis,
    pose_from_transform,
    project_to_rotation,
    relative_transform,
    rotational_error,
    transform_from_pose,
    transform_from_rotvec,
    transform_from_vector12,
    translational_error,
    vector12_from_transform,
)


def random_transforms(rng, n):
    return transform_from_rotvec(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))


def test_invert_then_concat_gives_identity():
    """A2B composed with its inverse is the identity, on both sides and for stacks."""
    rng = np.random.default_rng(0)
    A2B = random_transforms(rng, 10)
    B2A = invert_transform(A2B)
    assert_allclose(concat(A2B, B2A), np.broadcast_to(np.eye(4), (10, 4, 4)), atol=1e-12)
    assert_allclose(concat(B2A, A2B), np.broadcast_to(np.eye(4), (10, 4, 4)), atol=1e-12)
    assert_allclose(B2A, np.linalg.inv(A2B), atol=1e-12)


def test_concat_reads_left_to_right():
    """concat(A2B, B2C) maps a point given in C to A through B."""
    rng = np.random.default_rng(0)
    A2B, B2C = random_transforms(rng, 2)
    p_C = np.array([0.3, -0.2, 0.5, 1.0])
    assert_allclose(concat(A2B, B2C) @ p_C, A2B @ (B2C @ p_C))


def test_relative_transform_recovers_child_in_parent():
    """relative_transform(world2A, world2A @ A2B) gives A2B back."""
    rng = np.random.default_rng(0)
    world2A, A2B = random_transforms(rng, 2)
    assert_allclose(relative_transform(world2A, concat(world2A, A2B)), A2B, atol=1e-12)


def test_pose_transform_round_trip():
    """transform -> (position, quaternion) -> transform is the identity map, quaternions have w >= 0."""
    rng = np.random.default_rng(0)
    A2B = random_transforms(rng, 20)
    position, quaternion = pose_from_transform(A2B)
    assert position.shape == (20, 3) and quaternion.shape == (20, 4)
    assert np.all(quaternion[:, 3] >= 0.0)
    assert_allclose(transform_from_pose(position, quaternion), A2B, atol=1e-12)


def test_transform_from_pose_matches_scipy_xyzw():
    """Quaternions are (x, y, z, w) like scipy and geometry_msgs."""
    q = np.array([0.0, 0.0, math.sin(0.25), math.cos(0.25)])  # 0.5 rad about z
    A2B = transform_from_pose([1.0, 2.0, 3.0], q)
    assert_allclose(A2B[:3, :3], Rotation.from_rotvec([0.0, 0.0, 0.5]).as_matrix(), atol=1e-12)
    assert_allclose(A2B[:3, 3], [1.0, 2.0, 3.0])
    assert_allclose(A2B[3], [0.0, 0.0, 0.0, 1.0])


def test_transform_from_pose_matches_scipy_for_random_quaternions_and_stacks():
    """The closed-form quaternion to matrix agrees with scipy for any unit quaternion, one or a stack."""
    q = Rotation.random(50, random_state=3).as_quat()
    A2B = transform_from_pose(np.zeros((50, 3)), q)
    assert_allclose(A2B[:, :3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-12)
    assert_allclose(transform_from_pose([0.0, 0.0, 0.0], -q[7])[:3, :3], A2B[7, :3, :3], atol=1e-12)  # q ~ -q


def test_transform_from_rotvec_matches_scipy():
    """Rotation block from the rotation vector, translation copied, broadcasting over stacks."""
    rng = np.random.default_rng(0)
    rotvec = rng.normal(size=(5, 3))
    A2B = transform_from_rotvec(rotvec, [0.1, 0.2, 0.3])
    assert A2B.shape == (5, 4, 4)
    assert_allclose(A2B[:, :3, :3], Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    assert_allclose(A2B[:, :3, 3], np.tile([0.1, 0.2, 0.3], (5, 1)))


def test_vector12_round_trip():
    """vector12 layout is [R row-major, t] and maps back to the same transform."""
    rng = np.random.default_rng(0)
    A2B = random_transforms(rng, 7)
    v = vector12_from_transform(A2B)
    assert v.shape == (7, 12)
    assert_allclose(v[0, :9], A2B[0, :3, :3].ravel())
    assert_allclose(v[0, 9:], A2B[0, :3, 3])
    assert_allclose(transform_from_vector12(v), A2B, atol=1e-12)


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


def test_translational_error_hand_computed():
    """Distance between origins: a 3-4-5 triangle."""
    A2B = np.eye(4)
    A2C = np.eye(4)
    A2C[:3, 3] = [3.0, 4.0, 0.0]
    A2C[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 1.0]).as_matrix()  # rotation does not count
    assert_allclose(translational_error(A2B, A2C), 5.0)


def test_rotational_error_hand_computed():
    """Angle of the relative rotation, including 0 and pi, and independent of translation."""
    A2B = transform_from_rotvec([0.0, 0.0, 0.25], [1.0, 0.0, 0.0])
    A2C = transform_from_rotvec([0.0, 0.0, 0.75], [0.0, 0.0, 0.0])
    assert_allclose(rotational_error(A2B, A2C), 0.5, atol=1e-12)
    assert_allclose(rotational_error(A2B, A2B), 0.0, atol=1e-7)
    assert_allclose(rotational_error(np.eye(4), transform_from_rotvec([math.pi, 0.0, 0.0], np.zeros(3))), math.pi)
    errors = rotational_error(np.stack([A2B, A2B]), np.stack([A2C, A2B]))
    assert errors.shape == (2,)


def test_check_transform_accepts_stacks():
    """Valid transforms pass unchanged as float arrays."""
    rng = np.random.default_rng(0)
    A2B = random_transforms(rng, 3)
    assert_allclose(check_transform(A2B), A2B)
    assert check_transform(np.eye(4).tolist()).dtype == float


@pytest.mark.parametrize("bad", [
    np.eye(3),                                   # wrong shape
    np.zeros((4, 4, 1)),                         # wrong trailing shape
    np.full((4, 4), np.nan),                     # NaN
    np.where(np.eye(4) == 1, np.inf, 0.0),       # inf
    np.diag([2.0, 1.0, 1.0, 1.0]),               # not orthonormal
    np.diag([1.0, 1.0, -1.0, 1.0]),              # reflection
    np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1.0]]),  # bad last row
])
def test_check_transform_rejects_bad_input(bad):
    """Shapes, non-finite values and non-rigid matrices raise InvalidInputError (a ValueError)."""
    with pytest.raises(InvalidInputError):
        check_transform(bad)
    with pytest.raises(ValueError):
        check_transform(bad)


@pytest.mark.parametrize("bad", [
    [0.0, 0.0, 1.0],                 # wrong shape
    [0.0, 0.0, 0.0, 0.0],            # zero
    [0.0, 0.0, 0.0, 2.0],            # not unit
    [0.0, 0.0, np.nan, 1.0],         # NaN
    [np.inf, 0.0, 0.0, 1.0],         # inf
])
def test_check_quaternion_rejects_bad_input(bad):
    """Zero, non-unit, non-finite or wrongly shaped quaternions raise InvalidInputError."""
    with pytest.raises(InvalidInputError):
        check_quaternion(bad)
    with pytest.raises(InvalidInputError):
        transform_from_pose([0.0, 0.0, 0.0], bad)


def test_check_quaternion_normalises_small_deviation():
    """A quaternion within tolerance of unit norm is returned normalised."""
    q = check_quaternion([0.0, 0.0, 0.0, 1.0005])
    assert_allclose(np.linalg.norm(q), 1.0)


@pytest.mark.parametrize("bad", [[0.0, 0.0], [0.0, np.nan, 0.0], [np.inf, 0.0, 0.0]])
def test_transform_from_pose_rejects_bad_position(bad):
    """Positions must be finite 3-vectors."""
    with pytest.raises(InvalidInputError):
        transform_from_pose(bad, [0.0, 0.0, 0.0, 1.0])


def test_transform_from_vector12_rejects_wrong_shape():
    """The 12-vector must have 12 components."""
    with pytest.raises(InvalidInputError):
        transform_from_vector12(np.zeros(11))


def test_the_perpendicular_basis_is_smooth_at_a_urdfs_axes():
    """perpendicular_basis completes u to a right-handed orthonormal basis, and moves by no more than u does near
    every coordinate axis, face and body diagonal (a URDF's joint axes): an increment's meaning, a covariance and a
    prior on an axis stay put while a fit turns it a little."""
    import itertools

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
