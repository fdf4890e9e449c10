"""Rotation matrices: the nearest rotation to a 3x3 matrix (SVD and a batched polar iteration) with its derivative,
Rodrigues' formula and the rotation log, the chordal mean, cross products and a basis perpendicular to an axis.

The rotation math under :mod:`~body_scheme_core.transforms` and the rigid-joint models; every function takes a single
matrix or vector or a stack ``(..., 3, 3)`` / ``(..., 3)`` unless it says otherwise.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "project_to_rotation",
    "project_to_rotation_batch",
    "polar_derivative",
    "skew",
    "axis_angle_matrix",
    "rotvec_matrix",
    "rotation_log",
    "chordal_mean",
    "perpendicular_basis",
    "cross3",
]


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
