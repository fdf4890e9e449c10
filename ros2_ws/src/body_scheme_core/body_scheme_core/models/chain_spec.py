"""A chain from the robot's specification, and how far the robot may be from it.

:func:`chain_from_engineered` turns an :class:`~body_scheme_core.models.engineered.EngineeredModel` (the URDF's joints
between two markers) into a :class:`~body_scheme_core.models.chain.ChainModel`: the start of a calibration. Its prior
(:func:`specification_covariance`) is the robot off its specification at every joint: each joint's origin, and the
child marker's mount, moved and turned by a tolerance per axis, independently. Moved through the chain, such errors
make the distal parameters far less certain than any one joint (seven joints 2 mm / 0.5 deg off move a tool by
15-28 mm), and they are correlated: a turned shoulder moves every axis after it.

The covariances are first-order, from numerical Jacobians of the stored parameters, mapped to a local increment by the
retraction's Jacobian (:func:`increment_jacobian`). :func:`increment_jacobian` also carries a chain's covariance
through any map of its parameters (:func:`~body_scheme_core.learning.chain_refit.register_chain` moving it onto the
markers' places).
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from ..rotations import axis_angle_matrix, rotation_log, rotvec_matrix
from ..transforms import transform_from_rotvec
from .chain import ChainModel

__all__ = ["chain_from_engineered", "specification_covariance", "increment_jacobian"]


def _specification_params(elements, q_ref, errors=None):
    """Stored chain parameters (per joint ``w, p`` or ``d``, then ``M``'s translation and rotation vector) and the
    joint types of the specification's ``elements`` at joint values ``q_ref`` ({action: q}). ``errors`` (k + 1, 6):
    each joint's origin moved by the rigid motion of translation ``errors[i, :3]`` and rotation vector
    ``errors[i, 3:]`` before its motion, and the child's mount after the last joint (a real robot off its
    specification)."""
    G, params, types, moved = np.eye(4), [], [], 0
    for element in elements:
        if element[0] == "fixed":
            G = G @ element[1]
            continue
        if errors is not None:
            G = G @ transform_from_rotvec(errors[moved, 3:], errors[moved, :3])
        moved += 1
        kind, axis, action, gain, _ = element
        w = gain * (G[:3, :3] @ axis)
        w /= np.linalg.norm(w)
        if kind == "revolute":
            params += [w, G[:3, 3] - (G[:3, 3] @ w) * w]
        else:
            params.append(w)
        types.append(kind)
        E = np.eye(4)
        if kind == "revolute":
            E[:3, :3] = axis_angle_matrix(axis, q_ref[action])
        else:
            E[:3, 3] = axis * q_ref[action]
        G = G @ E
    if errors is not None:
        G = G @ transform_from_rotvec(errors[moved, 3:], errors[moved, :3])
    return np.concatenate(params + [G[:3, 3], rotation_log(G[None, :3, :3])[0]]), tuple(types)


def _difference(stored0, stored):
    """``stored - stored0`` with ``M``'s rotation as ``log(R0^T R)`` (the increment's convention): no jump where a
    rotation vector's sign flips at a half turn."""
    d = np.asarray(stored, dtype=float) - stored0
    d[-3:] = rotation_log((rotvec_matrix(stored0[-3:]).T @ rotvec_matrix(np.asarray(stored)[-3:]))[None])[0]
    return d


def increment_jacobian(form, stored, f, n, eps=1e-6):
    """``d increment / dx`` (``form.N_PARAMS``, n) at ``x = 0`` of stored chain parameters ``f(x)`` (a map from
    R^n with ``f(0) = stored``): the numerical Jacobian of ``f``, mapped to a local increment at ``stored`` by the
    retraction's Jacobian (least squares: a stored parameter the increment cannot move, a unit vector's length, is
    left out)."""
    stored = np.asarray(stored, dtype=float)

    def column(g, size, k):
        step = np.zeros(size)
        step[k] = eps
        return (_difference(stored, g(step)) - _difference(stored, g(-step))) / (2 * eps)

    J_f = np.stack([column(f, n, k) for k in range(n)], axis=1)
    J_r = np.stack([column(lambda d: form.retract(stored[None], d[None])[0], form.N_PARAMS, k)
                    for k in range(form.N_PARAMS)], axis=1)
    return np.linalg.lstsq(J_r, J_f, rcond=None)[0]


def specification_covariance(form, elements, q_ref, sigma_trans, sigma_rot):
    """The covariance of a local increment of the chain of ``form`` when the robot is off its specification
    (``elements`` at joint values ``q_ref``, as :func:`chain_from_engineered` reads them) by ``sigma_trans`` (m, per
    axis) and ``sigma_rot`` (rad, per axis) at every joint's origin and at the child's mount, independently, to first
    order. A specification has no couplings."""
    if form.COUPLINGS:
        raise InvalidInputError("a specification's chain has no couplings")
    stored, _ = _specification_params(elements, q_ref)
    n_errors = 6 * (sum(e[0] != "fixed" for e in elements) + 1)
    A = increment_jacobian(form, stored, lambda e: _specification_params(elements, q_ref, e.reshape(-1, 6))[0],
                           n_errors)
    variance = np.tile(np.r_[[sigma_trans**2] * 3, [sigma_rot**2] * 3], n_errors // 6)
    cov = (A * variance) @ A.T
    return 0.5 * (cov + cov.T) + np.eye(form.N_PARAMS) * 1e-6 * max(sigma_trans, sigma_rot) ** 2


def chain_from_engineered(model, reference=None, prior=None, **hyperparameters):
    """The :class:`~body_scheme_core.models.chain.ChainModel` of an
    :class:`~body_scheme_core.models.engineered.EngineeredModel` (the robot's specification between two markers),
    with the specification's values at ``reference`` (the joints' actions, default zeros) as its parameters: the start
    of a calibration.

    Each joint's screw is its axis moved into the parent frame by the chain up to it at the reference posture; a
    joint traversed from child to parent (``sign -1``) turns the other way. Mimic joints (an action moving two
    joints) have no chain form and raise ``InvalidInputError``. ``prior`` ``(sigma_trans, sigma_rot)``: how far the
    robot may be from its specification, per joint (m and rad per axis, at every joint's origin and at the child
    marker's mount), as the chain's parameter covariance (:func:`specification_covariance`; a learner takes a given
    chain's covariance as its prior until data fills its window); default: the specification exact.
    """
    elements = list(model._elements)
    joints = [e for e in elements if e[0] != "fixed"]
    actions = tuple(e[2] for e in joints)
    if len(set(actions)) != len(actions) or any(abs(abs(e[3]) - 1.0) > 1e-12 for e in joints):
        raise InvalidInputError(f"{model.describe()}: an action moves several joints or a joint at another rate "
                                f"(a mimic joint); a chain takes one joint per action")
    reference = np.zeros(len(actions)) if reference is None else np.asarray(reference, dtype=float)
    q_ref = {e[2]: e[3] * r + e[4] for e, r in zip(joints, reference, strict=True)}
    params, types = _specification_params(elements, q_ref)
    chain = ChainModel(model.parent, model.child, actions, types, reference=reference, **hyperparameters)
    form = chain.form
    stored = form.canonical(params[None])[0]
    cov = (np.eye(form.N_PARAMS) * 1e-12 if prior is None
           else specification_covariance(form, elements, q_ref, *(float(v) for v in prior)))
    return chain._set_fit(stored, cov, 0, 0.0)
