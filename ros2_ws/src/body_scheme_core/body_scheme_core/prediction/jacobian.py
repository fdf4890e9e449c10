"""The Jacobian of the body scheme's forward model (paper Eq. 10): how a part's pose moves with every action.

``root2part`` is the product of the local transforms along the path from the root (Eq. 8); its derivative with
respect to action ``a_k`` follows from the product rule, with each local model's own derivative (its ``jacobian``, or
forward differences from :meth:`~body_scheme_core.prediction.BodyScheme.chain_transforms`). An edge the tree
traverses against its model's direction uses ``d(Z^-1) = -Z^-1 dZ Z^-1``. The IK solver
(:mod:`body_scheme_core.control.ik`) drives the position Jacobian.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError

__all__ = ["jacobian", "position_jacobian"]


def _chain_derivatives(scheme, a, part, local_transforms, local_derivatives):
    """Validated ``a``, local transforms (k, 4, 4) and per-edge ``(actions, dT)`` pairs along the path to ``part``."""
    a = scheme.check_action_vector(a)
    chain = [(model, inverted, list(model.actions)) for _, _, model, inverted in scheme.path_edges(part)]
    if local_transforms is None:
        if local_derivatives is not None:
            raise InvalidInputError("local_derivatives needs the matching local_transforms")
        T = scheme.chain_transforms(a, part)
    else:
        T = np.asarray(local_transforms, dtype=float)
        if T.shape != (len(chain), 4, 4):
            raise InvalidInputError(
                f"local_transforms for part {part} must have shape ({len(chain)}, 4, 4), got {T.shape}")
    if local_derivatives is not None:
        if len(local_derivatives) != len(chain):
            raise InvalidInputError(f"local_derivatives for part {part} must have {len(chain)} entries, got "
                                    f"{len(local_derivatives)}")
        return a, T, [(acts, dT) for (_, _, acts), dT in zip(chain, local_derivatives, strict=True)]
    derivatives = []
    for Ti, (model, inverted, acts) in zip(T, chain, strict=True):
        if not acts:
            derivatives.append((acts, None))
            continue
        dZ = np.asarray(model.jacobian(a))[acts]
        if inverted:
            # d(Z^-1) = -Z^-1 dZ Z^-1, and Ti already is Z^-1.
            dZ = -(Ti @ dZ @ Ti)
        derivatives.append((acts, dZ))
    return a, T, derivatives


def jacobian(scheme, a, part, local_transforms=None, local_derivatives=None):
    """Derivative of ``root2part`` with respect to every action (Eq. 10), by the product rule along the path.

    Parameters
    ----------
    scheme : BodyScheme
    a : array-like, shape (m,)
    part : int
    local_transforms : ndarray, shape (k, 4, 4), optional
        Output of ``scheme.chain_transforms`` at the same ``a``, to skip recomputing it.
    local_derivatives : list, optional
        Per-edge derivatives from ``scheme.chain_transforms(..., derivative_step=h)`` to use instead of the models'
        analytic ``jacobian``; requires ``local_transforms``.

    Returns
    -------
    J : ndarray, shape (m, 4, 4)
        ``J[k] = d root2part / d a_k``; zero for actions that do not influence ``part``.
    """
    a, T, derivatives = _chain_derivatives(scheme, a, part, local_transforms, local_derivatives)
    k = T.shape[0]
    prefix = np.empty((k + 1, 4, 4))
    suffix = np.empty((k + 1, 4, 4))
    prefix[0] = suffix[k] = np.eye(4)
    for i in range(k):
        prefix[i + 1] = prefix[i] @ T[i]
        suffix[k - 1 - i] = T[k - 1 - i] @ suffix[k - i]
    J = np.zeros((a.shape[0], 4, 4))
    for i, (acts, dT) in enumerate(derivatives):
        if acts:
            J[acts] += prefix[i] @ dT @ suffix[i + 1]
    return J


def position_jacobian(scheme, a, part, local_transforms=None, local_derivatives=None):
    """Derivative of the position of ``part`` in the root frame with respect to every action.

    Parameters
    ----------
    scheme, a, part, local_transforms, local_derivatives
        As for :func:`jacobian`.

    Returns
    -------
    J : ndarray, shape (3, m)
    """
    a, T, derivatives = _chain_derivatives(scheme, a, part, local_transforms, local_derivatives)
    k = T.shape[0]
    # Only the last column of the suffix products matters: the part origin expressed after each edge.
    origin = np.empty((k + 1, 4))
    origin[k] = (0.0, 0.0, 0.0, 1.0)
    for i in range(k - 1, -1, -1):
        origin[i] = T[i] @ origin[i + 1]
    Jt = np.zeros((a.shape[0], 3))
    prefix = np.eye(4)
    for i, (acts, dT) in enumerate(derivatives):
        if acts:
            Jt[acts] += (dT @ origin[i + 1]) @ prefix[:3].T
        prefix = prefix @ T[i]
    return Jt.T
