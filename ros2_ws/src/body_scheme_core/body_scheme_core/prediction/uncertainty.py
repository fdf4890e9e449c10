"""How sure the body scheme is of where a part is: the covariance of its predicted position.

The joint fit estimates every rigid-joint model of the tree from the same absolute observations, so their errors are
correlated: a model that is too long is followed by one that is too short, and the tip lands close to where it was
seen. Summing the models' own uncertainties along the chain as if they were independent
(:meth:`~body_scheme_core.prediction.scheme.BodyScheme.predict_batch`, what the learner's thresholds use) overstates the
tip's uncertainty; measured on the paper's 6-DOF arm learned from scratch (300 steps, every marker seen), the end
effector's true error was a third of that bound while each model's own covariance matched its own error
(``python -m body_scheme_apps.experiments --only iksure``).

:func:`position_covariance` propagates the joint fit's covariance with its cross terms
(:attr:`BodyScheme.param_covariance <body_scheme_core.prediction.scheme.BodyScheme>`) to first order, by differentiating
the chain with respect to each parameter increment; rigid models outside it add their own covariance, and models without
parameters (GP, engineered) their predictive std, isotropically with the lever arm of a rotation error. The root's
pose in the world is not included (the position is in the root part's frame).

:func:`error_radius` turns such a covariance into a radius that holds the true position with a stated probability:
the distribution of a Gaussian error's length depends on the covariance's shape, so ``k sqrt(trace)`` (the
isotropic bound this module gave before) holds 95 % at ``k = 2`` only when one axis dominates and 99.3 % when all
three are equal, several times more than the level it names.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
from scipy import stats

from ..errors import InvalidInputError
from ..transforms import invert_transform

__all__ = ["error_radius", "parameter_jacobian", "perturbed_models", "position_covariance", "position_std"]

#: Step of the forward differences in a parameter increment (its units: m, rad).
_STEP = 1e-6
#: model -> (its parameters then, the model after a step in each parameter): a retraction costs more than the
#: prediction it serves, and the same models are differentiated at every IK answer and exploration candidate.
_PERTURBED = weakref.WeakKeyDictionary()


def perturbed_models(model):
    """The rigid-joint ``model`` after an increment of :data:`_STEP` in each of its parameters (cached per model
    while its parameters stay the same)."""
    cached = _PERTURBED.get(model)
    if cached is None or not np.array_equal(cached[0], model.params_):
        moved = []
        for d in range(model.n_params):
            delta = np.zeros(model.n_params)
            delta[d] = _STEP
            moved.append(model.with_params(model.retract(delta)))
        cached = (model.params_.copy(), moved)
        _PERTURBED[model] = cached
    return cached[1]


def position_covariance(scheme, a, part):
    """First-order covariance (3, 3) of ``part``'s predicted position in the root frame at actions ``a`` (m,)."""
    a = np.asarray(a, dtype=float)
    if a.ndim != 1 or not np.all(np.isfinite(a)):
        raise InvalidInputError(f"a must be a finite vector, got shape {a.shape}")
    edges = scheme.path_edges(part)
    A = a[None]
    local = [scheme.edge_transform(model, inverted, A)[0] for _, _, model, inverted in edges]
    prefix = [np.eye(4)]
    for T in local:
        prefix.append(prefix[-1] @ T)
    suffix = [np.eye(4)]
    for T in reversed(local):
        suffix.append(T @ suffix[-1])
    suffix.reverse()  # suffix[i]: the product of the transforms after edge i
    tip = prefix[-1][:3, 3]
    joint, offsets = {}, {}
    if scheme.param_covariance is not None:
        indices, matrix = scheme.param_covariance
        offset = 0
        for k in indices:
            offsets[id(scheme.models[k])] = offset
            offset += scheme.models[k].n_params
        joint = matrix
    jacobian = np.zeros((3, joint.shape[0])) if offsets else None
    cov = np.zeros((3, 3))
    for i, (_, _, model, inverted) in enumerate(edges):
        if hasattr(model, "retract"):  # a rigid-joint model: differentiate the tip in its parameter increments
            J = np.empty((3, model.n_params))
            for d, perturbed in enumerate(perturbed_models(model)):
                moved = scheme.edge_transform(perturbed, inverted, A)[0]
                J[:, d] = ((prefix[i] @ moved @ suffix[i + 1])[:3, 3] - tip) / _STEP
            if id(model) in offsets:
                start = offsets[id(model)]
                jacobian[:, start:start + model.n_params] = J
            else:
                cov += J @ model.param_cov_ @ J.T
        else:
            _, std = scheme.edge_transform(model, inverted, A, return_std=True)
            s_t, s_r = np.asarray(std, dtype=float).reshape(-1)[:2]
            # The model's rotation error turns what follows about its own child: the traversal's child, or for an
            # inverted edge (the model predicts child2parent) the traversal's parent.
            pivot = prefix[i] if inverted else prefix[i + 1]
            lever = tip - pivot[:3, 3]
            cov += s_t**2 * np.eye(3) + s_r**2 * (float(lever @ lever) * np.eye(3) - np.outer(lever, lever))
    if jacobian is not None:
        cov += jacobian @ joint @ jacobian.T
    return 0.5 * (cov + cov.T)


def position_std(scheme, a, part):
    """The RMS length of the error of ``part``'s predicted position: ``sqrt(trace(cov))`` (m)."""
    return float(np.sqrt(max(np.trace(position_covariance(scheme, a, part)), 0.0)))


def error_radius(cov, confidence):
    """The radius (m) within which a zero-mean Gaussian error of covariance ``cov`` (3, 3) lies with the probability
    that a normal variable lies within ``confidence`` standard deviations of its mean (95.4 % at 2; 0: radius 0).

    The squared length of the error is a weighted sum of chi-square variables (the weights: ``cov``'s eigenvalues);
    its quantile is Patnaik's scaled chi-square with the same mean and variance, exact for one dominant axis and for
    three equal ones. In between, at confidence 2, it is within 0.2 % in coverage (Monte Carlo, 400,000 draws); at 1
    and 3 within about 2 % and 0.15 % (it is an approximation of the tail). A covariance that is not finite gives an
    infinite radius (nothing is sure of it).
    """
    if not (math.isfinite(confidence) and confidence >= 0.0):
        raise InvalidInputError(f"confidence must be a finite number >= 0, got {confidence!r}")
    cov = np.asarray(cov, dtype=float)
    if not np.all(np.isfinite(cov)):
        return math.inf
    eigenvalues = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
    largest = float(eigenvalues.max(initial=0.0))
    if confidence == 0.0 or largest == 0.0:
        return 0.0
    w = eigenvalues / largest  # scaled: the squares of tiny variances do not underflow
    scale, dof = largest * float(w @ w) / float(w.sum()), float(w.sum()) ** 2 / float(w @ w)
    return math.sqrt(scale * stats.chi2.isf(math.erfc(confidence / math.sqrt(2.0)), dof))


def parameter_jacobian(scheme, A):
    """Derivatives (n, n_parts, 3, P) of every part's position in the root frame, at each action vector of ``A``
    (n, m), with respect to the joint fit's parameter increments (the order of ``scheme.param_covariance``); ``None``
    when the scheme has no joint covariance.

    Forward differences, one edge at a time: an increment of the model on edge ``parent -> child`` moves every part
    below ``child`` rigidly by ``W_parent T' W_child^-1`` (``W``: predicted poses in the root frame, ``T'``: the
    edge's transform after the increment), so each parameter costs one prediction of its own model, not of the
    whole chain.
    """
    if scheme.param_covariance is None:
        return None
    A = np.asarray(A, dtype=float)
    base = scheme.predict_batch(A)
    positions = base[:, :, :3, 3]
    indices, matrix = scheme.param_covariance
    J = np.zeros(positions.shape + (matrix.shape[0],))
    column, offset = {}, 0
    for k in indices:
        column[id(scheme.models[k])] = offset
        offset += scheme.models[k].n_params
    for parent, child, model, inverted in scheme.edges:
        if id(model) not in column:
            continue
        below = [i for i, part in enumerate(scheme.parts) if child in scheme.path(part)]
        W_parent = base[:, scheme.parts.index(parent)]
        child_inv = invert_transform(base[:, scheme.parts.index(child)])
        for d, perturbed in enumerate(perturbed_models(model)):
            moved = scheme.edge_transform(perturbed, inverted, A)
            shift = W_parent @ moved @ child_inv  # (n, 4, 4)
            p = positions[:, below]
            p_moved = np.einsum("nij,nkj->nki", shift[:, :3, :3], p) + shift[:, None, :3, 3]
            J[..., column[id(model)] + d][:, below] = (p_moved - p) / _STEP
    return J
