"""The Levenberg-Marquardt step: a damped Gauss-Newton increment and the damping's schedule.

One step for every nonlinear least-squares fit of the core: the rigid-joint candidates' batched fit
(:func:`~body_scheme_core.models.rigid_fit.gauss_newton`, a stack of problems each with its own damping) and the body
scheme's joint fit (:mod:`body_scheme_core.calibration.joint_fit`, one problem with priors). Their loops differ (a
fixed number of iterations per time step; iterate to convergence); the step and the damping do not.
"""

from __future__ import annotations

import numpy as np

__all__ = ["INITIAL_DAMPING", "damped_increment", "next_damping"]

#: Damping at the start of a fit, relative to the diagonal of the information matrix ``J^T W J``.
INITIAL_DAMPING = 1e-3


def damped_increment(info, g, damping, floor):
    """The Levenberg-Marquardt increment ``-(info + diag(damping * diag(info) + floor))^-1 g``.

    Gauss-Newton's step, damped towards gradient descent scaled by the information's diagonal (Marquardt). One
    problem: ``info`` (p, p), ``g`` (p,), ``damping`` a float; or a stack of problems, each with its own damping:
    (k, p, p), (k, p), (k,).
    """
    diag = np.einsum("...ii->...i", info)
    H = info + (np.asarray(damping)[..., None] * diag + floor)[..., :, None] * np.eye(info.shape[-1])
    return -np.linalg.solve(H, g[..., None])[..., 0]


def next_damping(improved, damping, minimum):
    """The damping after a trial step: a third of it (not below ``minimum``) where the step lowered the cost, ten
    times where it did not (the step is then tried again, shorter and nearer the gradient)."""
    return np.where(improved, np.maximum(damping / 3.0, minimum), damping * 10.0)
