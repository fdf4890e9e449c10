"""Rigid transforms and poses: validation, conversion, composition, inversion, error metrics, and the projection of
3x3 matrices onto rotations with its derivative.

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
    "project_to_rotation",
    "project_to_rotation_batch",
    "polar_derivative",
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


def project_to_rotation(M):
    """Nearest rotation matrix (Frobenius norm) to each 3x3 matrix, by SVD with the determinant fixed to +1.

    Parameters
    ----------
    M : array-like, shape (..., 3, 3)

    Returns
    -------
    R : ndarray, shape (..., 3, 3)
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0.0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def polar_derivative(M, dM):
    """Derivative of ``R = project_to_rotation(M)`` in the direction(s) ``dM``.

    With the signed SVD ``M = U' S' V^T`` used by the projection (``R = U' V^T``, last singular value negated when
    the determinant had to be fixed), ``dR = U' Omega V^T`` where ``Omega`` is skew with
    ``Omega_ij = (W_ij - W_ji) / (s'_i + s'_j)`` and ``W = U'^T dM V``. This is exact (no finite differences).

    Parameters
    ----------
    M : array-like, shape (3, 3)
    dM : array-like, shape (..., 3, 3)

    Returns
    -------
    dR : ndarray, shape (..., 3, 3)
    """
    M = np.asarray(M, dtype=float)
    dM = np.asarray(dM, dtype=float)
    U, s, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = 1.0 if d == 0.0 else d
    U = U.copy()
    U[:, 2] *= d
    s = s.copy()
    s[2] *= d
    W = U.T @ dM @ Vt.T
    denom = s[:, None] + s[None, :]
    # The sum only vanishes for a degenerate M (two singular values cancelling): the projection is not
    # differentiable there; a tiny denominator keeps the result finite instead of NaN.
    denom = np.where(np.abs(denom) < 1e-12, 1e-12, denom)
    Omega = (W - np.swapaxes(W, -1, -2)) / denom
    return U @ Omega @ Vt


# Cofactor entries of a row-major 3x3 matrix x (9, k): C = x[_P1] * x[_P2] - x[_P3] * x[_P4], so X^-T = C / det X.
_P1 = np.array([4, 5, 3, 2, 0, 1, 1, 2, 0])
_P2 = np.array([8, 6, 7, 7, 8, 6, 5, 3, 4])
_P3 = np.array([5, 3, 4, 1, 2, 0, 2, 0, 1])
_P4 = np.array([7, 8, 6, 8, 6, 7, 4, 5, 3])


def project_to_rotation_batch(M, tol=1e-8, max_iter=50):
    """Same result as :func:`project_to_rotation` (to ~1e-14), faster for stacks of matrices.

    LAPACK's SVD costs a few microseconds per 3x3 matrix, which dominated a 462-slot prediction. The orthogonal
    polar factor is computed instead by the scaled Newton iteration ``X <- (z X + X^-T / z) / 2`` (Higham,
    Frobenius-norm scaling ``z`` until the step is small, then unscaled for quadratic convergence), vectorised
    over the stack with explicit cofactors. A step below ``tol`` leaves an error of order ``tol^2``. For
    ``det M <= 0`` (nearly) the polar factor is not the nearest rotation, and those matrices take the SVD path.

    Parameters
    ----------
    M : ndarray, shape (k, 3, 3)

    Returns
    -------
    R : ndarray, shape (k, 3, 3)
    """
    k = M.shape[0]
    x = M.reshape(k, 9).T.copy()  # component-major: each entry a contiguous (k,) vector
    cof = x[_P1] * x[_P2] - x[_P3] * x[_P4]
    det = np.einsum("ik,ik->k", x[:3], cof[:3])
    sq = np.einsum("ik,ik->k", x, x)
    good = det > 1e-6 * sq**1.5
    all_good = bool(np.all(good))
    if not all_good:
        x, cof, det, sq = x[:, good], cof[:, good], det[good], sq[good]
    scale = True
    converged = x.shape[1] == 0
    for _ in range(max_iter):
        if converged:
            break
        inv_t = cof / det
        if scale:
            zeta = np.sqrt(np.sqrt(np.einsum("ik,ik->k", inv_t, inv_t) / sq))
            x_new = 0.5 * (zeta * x + inv_t / zeta)
        else:
            x_new = 0.5 * (x + inv_t)
        step = np.max(np.abs(x_new - x))
        x = x_new
        converged = step < tol
        scale = step > 1e-2
        cof = x[_P1] * x[_P2] - x[_P3] * x[_P4]
        det = np.einsum("ik,ik->k", x[:3], cof[:3])
        if scale:
            sq = np.einsum("ik,ik->k", x, x)
    if not converged:  # pragma: no cover - the scaled iteration converges in < 15 steps for det > 0
        return project_to_rotation(M)
    if all_good:
        return x.T.reshape(k, 3, 3)
    R = np.empty((k, 9))
    R[good] = x.T
    R[~good] = project_to_rotation(M[~good]).reshape(-1, 9)
    return R.reshape(k, 3, 3)


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


# ---------------------------------------------------------------------- rotation math of the rigid-joint models
def skew(v):
    """Cross-product matrices ``[v]x``, shape (..., 3, 3) for ``v`` of shape (..., 3)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def axis_angle_matrix(u, angle):
    """Rotations about unit axes ``u`` (..., 3) by ``angle`` (..., n): Rodrigues' formula, shape (..., n, 3, 3)."""
    u = np.asarray(u, dtype=float)[..., None, :]
    angle = np.asarray(angle, dtype=float)[..., None, None]
    K = skew(u)
    uu = u[..., :, None] * u[..., None, :]
    return np.cos(angle) * np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * uu


def rotvec_matrix(rotvec):
    """Rotation matrices of rotation vectors (..., 3), shape (..., 3, 3): Rodrigues' formula, vectorised."""
    v = np.asarray(rotvec, dtype=float)
    theta2 = np.sum(v * v, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    # sin(t)/t and (1 - cos(t))/t^2 with their series near 0
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / np.where(small, 1.0, theta))
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / np.where(small, 1.0, theta2))
    # [v]x^2 = v v^T - |v|^2 I
    return a * skew(v) + b * (v[..., :, None] * v[..., None, :]) + (1.0 - b * theta2) * np.eye(3)


#: Rotation angle (rad) beyond which :func:`rotation_log` leaves the closed form for scipy's quaternion route.
_NEAR_PI = 3.0


def rotation_log(R):
    """Rotation vectors of rotation matrices ``R`` (..., 3, 3), shape (..., 3); angles in [0, pi].

    Closed form ``angle / (2 sin angle) vee(R - R^T)`` (vectorised, the hot path of every fit); near pi, where that
    loses precision, scipy's quaternion conversion.
    """
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    if R.size == 0:
        return np.zeros(shape + (3,))
    cos = np.clip((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5, -1.0, 1.0)
    angle = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sqrt(np.maximum(1.0 - cos * cos, 0.0))
    # angle / sin(angle) -> 1 + angle^2 / 6 for small angles
    factor = np.where(angle < 1e-4, 0.5 * (1.0 + angle * angle / 6.0), 0.5 * angle / np.maximum(sin, 1e-300))
    out = v * factor[..., None]
    far = angle > _NEAR_PI
    if np.any(far):
        out[far] = Rotation.from_matrix(R[far].reshape(-1, 3, 3)).as_rotvec()
    return out


def chordal_mean(R, weights):
    """Weighted chordal L2 mean of rotations: the rotation nearest to ``sum w R``, batched.

    Parameters
    ----------
    R : ndarray, shape (k, n, 3, 3)
    weights : ndarray, shape (k, n)

    Returns
    -------
    mean : ndarray, shape (k, 3, 3)
    """
    return project_to_rotation(np.einsum("kn,knij->kij", weights, R))


#: The helper directions of :func:`perpendicular_basis`: a body diagonal, and a face diagonal perpendicular to it.
_BASIS_HELPER = np.array([1.0, 1.0, -1.0]) / np.sqrt(3.0)
_BASIS_HELPER_NEAR = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
#: Where the basis switches helpers: ``|u . helper|`` at this value.
_BASIS_SWITCH = 0.9


def perpendicular_basis(u):
    """Two unit vectors ``(e1, e2)`` completing unit ``u`` (..., 3) to a right-handed basis, each (..., 3).

    ``e1`` is the normalised cross product of ``u`` with the body diagonal ``(1, 1, -1) / sqrt 3``, or, within 26 deg
    of it (``|u . h| > 0.9``), with the face diagonal ``(1, -1, 0) / sqrt 2``. No basis is smooth on the whole sphere;
    this one switches only on that cone, at least 0.08 in ``|u . h|`` away from every coordinate axis, face and body
    diagonal and 30 / 60 deg direction in a coordinate plane: the axes a URDF's joints have. An axis near a switching
    point would change the meaning of its increments, its covariance and a prior on it as it moves (a basis that
    switched at the coordinate axes made the specification's prior of a chain pull towards wrong values).
    """
    u = np.asarray(u, dtype=float)
    near = np.abs(u @ _BASIS_HELPER) > _BASIS_SWITCH
    e1 = cross3(u, np.where(near[..., None], _BASIS_HELPER_NEAR, _BASIS_HELPER))
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, cross3(u, e1)


def cross3(a, b):
    """``np.cross`` for (..., 3) arrays without its axis bookkeeping (hot path)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


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
