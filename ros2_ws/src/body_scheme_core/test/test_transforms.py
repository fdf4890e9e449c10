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
    pose_from_transform,
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
