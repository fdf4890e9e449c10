"""Rigid transforms and poses: validation, conversion, composition, inversion, error metrics, URDF's xyz/rpy and a
planar marker's mirror pose (the rotation math under them is :mod:`~body_scheme_core.rotations`).

Convention (the ROS/TF one, not pytransform3d's): ``A2B`` is the pose of frame ``B`` expressed in frame ``A``, a
(4, 4) homogeneous matrix that maps points in ``B`` coordinates to ``A`` coordinates. Composition therefore reads
left to right: ``A2C = concat(A2B, B2C) = A2B @ B2C``. In the paper's notation the observed pose of part ``i`` is
``Y_i = world2part_i`` and the relative observation is ``Z_ij = Y_i^-1 Y_j = part_i2part_j``.

Quaternions are ``(x, y, z, w)`` like ``geometry_msgs/Quaternion`` and ``scipy.spatial.transform.Rotation``.
Every function accepts a single transform ``(4, 4)`` or a stack ``(..., 4, 4)`` unless it says otherwise.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import InvalidInputError
from .rotations import project_to_rotation

__all__ = [
    "check_transform",
    "check_quaternion",
    "transform_from_pose",
    "pose_from_transform",
    "transform_from_rotvec",
    "invert_transform",
    "concat",
    "relative_transform",
    "translational_error",
    "rotational_error",
    "vector12_from_transform",
    "transform_from_vector12",
    "mirror_about_ray",
]

#: Tolerance on ``|R^T R - I|`` and ``det R`` for a matrix to count as a rotation.
ROTATION_TOLERANCE = 1e-5
#: Quaternions whose norm differs from 1 by more than this are rejected instead of normalised.
QUATERNION_NORM_TOLERANCE = 1e-3


def check_transform(A2B, name="transform", tolerance=ROTATION_TOLERANCE):
    """Validate one or a stack of homogeneous transforms.

    Parameters
    ----------
    A2B : array-like, shape (..., 4, 4)
        Transform(s) to check.
    name : str
        Name used in error messages.
    tolerance : float
        Allowed deviation of the rotation block from orthonormality and of the last row from ``[0, 0, 0, 1]``.

    Returns
    -------
    A2B : ndarray, shape (..., 4, 4)
        The input as a float64 array.

    Raises
    ------
    InvalidInputError
        If the shape is wrong, a value is not finite, or the matrix is not a rigid transform.
    """
    A2B = np.asarray(A2B, dtype=float)
    if A2B.ndim < 2 or A2B.shape[-2:] != (4, 4):
        raise InvalidInputError(f"{name} must have shape (..., 4, 4), got {A2B.shape}")
    if not np.all(np.isfinite(A2B)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    R = A2B[..., :3, :3]
    RtR = np.swapaxes(R, -1, -2) @ R
    if np.any(np.abs(RtR - np.eye(3)) > tolerance) or np.any(np.linalg.det(R) < 0.0):
        raise InvalidInputError(f"{name} has a rotation block that is not orthonormal with det +1")
    if np.any(np.abs(A2B[..., 3, :] - [0.0, 0.0, 0.0, 1.0]) > tolerance):
        raise InvalidInputError(f"{name} must have last row [0, 0, 0, 1], got {A2B[..., 3, :].tolist()}")
    return A2B


def check_quaternion(q, name="quaternion", tolerance=QUATERNION_NORM_TOLERANCE):
    """Validate quaternion(s) ``(x, y, z, w)`` and return them normalised.

    Parameters
    ----------
    q : array-like, shape (..., 4)
    name : str
    tolerance : float
        Largest accepted deviation of the norm from 1. A zero or far-from-unit quaternion is a sender's bug,
        not noise, so it is rejected rather than silently normalised.

    Returns
    -------
    q : ndarray, shape (..., 4)
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1:] != (4,):
        raise InvalidInputError(f"{name} must have shape (..., 4), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(np.abs(norm - 1.0) > tolerance):
        raise InvalidInputError(f"{name} must be a unit quaternion, got norm(s) {np.ravel(norm).tolist()}")
    return q / norm


def transform_from_pose(position, quaternion):
    """Build transform(s) from position(s) and unit quaternion(s) ``(x, y, z, w)``.

    Parameters
    ----------
    position : array-like, shape (..., 3)
    quaternion : array-like, shape (..., 4)

    Returns
    -------
    A2B : ndarray, shape (..., 4, 4)
    """
    position = np.asarray(position, dtype=float)
    if position.shape[-1:] != (3,):
        raise InvalidInputError(f"position must have shape (..., 3), got {position.shape}")
    if not np.all(np.isfinite(position)):
        raise InvalidInputError("position contains NaN or inf")
    q = check_quaternion(quaternion)
    batch = np.broadcast_shapes(position.shape[:-1], q.shape[:-1])
    A2B = np.zeros(batch + (4, 4))
    A2B[..., :3, :3] = _matrix_from_unit_quaternion(q)
    A2B[..., :3, 3] = position
    A2B[..., 3, 3] = 1.0
    return A2B


def _matrix_from_unit_quaternion(q):
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) ``(x, y, z, w)``: the closed form, vectorised
    (scipy's ``Rotation`` costs ~50 us of overhead per call, which the node pays per marker of every message)."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    return R


def pose_from_transform(A2B):
    """Split transform(s) into position(s) and unit quaternion(s) ``(x, y, z, w)`` with ``w >= 0``.

    Parameters
    ----------
    A2B : array-like, shape (..., 4, 4)

    Returns
    -------
    position : ndarray, shape (..., 3)
    quaternion : ndarray, shape (..., 4)
    """
    A2B = np.asarray(A2B, dtype=float)
    R = A2B[..., :3, :3].reshape(-1, 3, 3)
    q = Rotation.from_matrix(R).as_quat(canonical=True).reshape(A2B.shape[:-2] + (4,))
    return A2B[..., :3, 3].copy(), q


def transform_from_rotvec(rotvec, translation):
    """Build transform(s) from rotation vector(s) (axis times angle, rad) and translation(s).

    Parameters
    ----------
    rotvec : array-like, shape (..., 3)
    translation : array-like, shape (..., 3)

    Returns
    -------
    A2B : ndarray, shape (..., 4, 4)
    """
    rotvec = np.asarray(rotvec, dtype=float)
    translation = np.asarray(translation, dtype=float)
    batch = np.broadcast_shapes(rotvec.shape[:-1], translation.shape[:-1])
    A2B = np.zeros(batch + (4, 4))
    # copy: scipy rejects the read-only view that broadcast_to returns
    R = Rotation.from_rotvec(np.broadcast_to(rotvec, batch + (3,)).reshape(-1, 3).copy()).as_matrix()
    A2B[..., :3, :3] = R.reshape(batch + (3, 3))
    A2B[..., :3, 3] = translation
    A2B[..., 3, 3] = 1.0
    return A2B


def invert_transform(A2B):
    """Invert rigid transform(s) exactly (``R^T``, ``-R^T t``), without a general matrix inverse.

    Parameters
    ----------
    A2B : array-like, shape (..., 4, 4)

    Returns
    -------
    B2A : ndarray, shape (..., 4, 4)
    """
    A2B = np.asarray(A2B, dtype=float)
    B2A = np.zeros_like(A2B)
    Rt = np.swapaxes(A2B[..., :3, :3], -1, -2)
    B2A[..., :3, :3] = Rt
    B2A[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, A2B[..., :3, 3])
    B2A[..., 3, 3] = 1.0
    return B2A


def concat(A2B, B2C):
    """Compose transforms: ``A2C = A2B @ B2C`` (broadcasts over leading dimensions)."""
    return np.asarray(A2B, dtype=float) @ np.asarray(B2C, dtype=float)


def relative_transform(world2A, world2B):
    """Relative transform ``A2B = world2A^-1 world2B`` (the paper's ``Z_AB = Y_A^-1 Y_B``)."""
    return concat(invert_transform(world2A), world2B)


def translational_error(A2B, A2C):
    """Euclidean distance between the origins of two (stacks of) frames, shape ``(...)``."""
    A2B = np.asarray(A2B, dtype=float)
    A2C = np.asarray(A2C, dtype=float)
    return np.linalg.norm(A2B[..., :3, 3] - A2C[..., :3, 3], axis=-1)


def rotational_error(A2B, A2C):
    """Angle in rad, in [0, pi], of the rotation between two (stacks of) frames, shape ``(...)``."""
    A2B = np.asarray(A2B, dtype=float)
    A2C = np.asarray(A2C, dtype=float)
    # trace(R_B^T R_C) = sum of elementwise products; avoids a matmul per pair.
    trace = np.sum(A2B[..., :3, :3] * A2C[..., :3, :3], axis=(-2, -1))
    return np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))


def vector12_from_transform(A2B):
    """Flatten transform(s) into the 12 free components ``[R (row-major, 9), t (3)]``, shape ``(..., 12)``."""
    A2B = np.asarray(A2B, dtype=float)
    batch = A2B.shape[:-2]
    return np.concatenate([A2B[..., :3, :3].reshape(batch + (9,)), A2B[..., :3, 3]], axis=-1)


def transform_from_vector12(v):
    """Map 12 regressed components back onto valid rigid transforms (the paper's normalisation step).

    Parameters
    ----------
    v : array-like, shape (..., 12)
        ``[R (row-major, 9), t (3)]``; the rotation block need not be orthonormal.

    Returns
    -------
    A2B : ndarray, shape (..., 4, 4)
    """
    v = np.asarray(v, dtype=float)
    if v.shape[-1:] != (12,):
        raise InvalidInputError(f"vector must have shape (..., 12), got {v.shape}")
    batch = v.shape[:-1]
    A2B = np.zeros(batch + (4, 4))
    A2B[..., :3, :3] = project_to_rotation(v[..., :9].reshape(batch + (3, 3)))
    A2B[..., :3, 3] = v[..., 9:]
    A2B[..., 3, 3] = 1.0
    return A2B


# ---------------------------------------------------------------------- URDF's xyz / roll-pitch-yaw
def transform_from_xyz_rpy(xyz, rpy):
    """Transform from a translation and URDF roll-pitch-yaw (fixed axes x, y, z).

    Parameters
    ----------
    xyz : array-like, shape (3,)
    rpy : array-like, shape (3,)

    Returns
    -------
    A2B : ndarray, shape (4, 4)
    """
    xyz = np.asarray(xyz, dtype=float)
    rpy = np.asarray(rpy, dtype=float)
    if xyz.shape != (3,) or rpy.shape != (3,):
        raise InvalidInputError(f"xyz and rpy must have shape (3,), got {xyz.shape} and {rpy.shape}")
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(rpy))):
        raise InvalidInputError("xyz or rpy contains NaN or inf")
    A2B = np.eye(4)
    A2B[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    A2B[:3, 3] = xyz
    return A2B


def xyz_rpy_from_transform(A2B):
    """Translation and URDF roll-pitch-yaw of a transform (inverse of :func:`transform_from_xyz_rpy`).

    Parameters
    ----------
    A2B : array-like, shape (4, 4)

    Returns
    -------
    xyz, rpy : ndarray, shape (3,)
    """
    A2B = check_transform(A2B)
    with warnings.catch_warnings():
        # At pitch = +-pi/2 scipy warns and sets one angle to zero; the angles still represent the same rotation.
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(A2B[:3, :3]).as_euler("xyz")
    return A2B[:3, 3].copy(), rpy


def mirror_about_ray(camera2marker):
    """The other pose of a planar marker that looks alike from the camera: its orientation mirrored about the ray.

    Seen from the camera's optical centre (the origin of the frame the pose is expressed in), a small planar marker
    tilted one way across the line of sight projects almost like one tilted the other way: the two solutions of
    planar pose estimation (IPPE), of which a tracker sometimes reports the wrong one. The mirrored pose keeps the
    position; with ``v`` the unit ray to the marker and ``H = I - 2 v v^T``, its in-plane axes are ``H x`` and
    ``H y`` (the same image, depth negated) and its normal ``-H z`` is the normal reflected about the ray, so its
    rotation ``H R diag(1, 1, -1)`` is proper. A marker seen face-on is its own mirror.

    Parameters
    ----------
    camera2marker : array-like, shape (..., 4, 4)

    Returns
    -------
    mirrored : ndarray, shape (..., 4, 4)
    """
    T = np.array(camera2marker, dtype=float)
    v = T[..., :3, 3] / np.maximum(np.linalg.norm(T[..., :3, 3], axis=-1, keepdims=True), 1e-12)
    R = T[..., :3, :3]
    mirrored = R - 2.0 * v[..., :, None] * np.einsum("...i,...ij->...j", v, R)[..., None, :]
    mirrored[..., :, 2] *= -1.0
    T[..., :3, :3] = mirrored
    return T
