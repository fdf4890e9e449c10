"""Model quality: prediction errors, nesting of model classes and structure costs (paper Eq. 4, 6, 7, 11).

Errors are split into a translational part (m) and a rotational part (rad), because the two have different units
and noise levels; the paper's single norm ``||Z - Z'||`` (Eq. 6) mixes them (:func:`prediction_errors`). How the
errors of a model are collected over its test window, and when it counts as valid, is the job of the validity monitor
(:mod:`~body_scheme_core.learning.validity`).

Costs for the minimum spanning tree (lower is better) keep the paper's key property that complexity layers never
overlap (Eq. 7 and 12), and order the model classes within a layer by their own complexity (fewer parameters
first, in the spirit of Sturm's articulation models and BIC)::

    cost(M)      = C(M)      + (e(M)  + p rank(M))  / (1 + p (N_RANKS - 1))
    cost(M2|M1)  = C(M2|M1)  + (e(M2) + p rank(M2)) / (1 + p (N_RANKS - 1))

with ``e(M) = clip(mean(e_t / theta_t, e_r / theta_r), 0, 1)``, ``C(M2|M1) = |A(M2) symmetric-difference A(M1)|``,
``rank`` 0 for static and prismatic models, 1 for revolute and 2 for GP models (:data:`CLASS_RANKS`) and the rank
penalty ``p`` = :data:`RANK_PENALTY` thresholds. For a valid model both ratios are below 1, so the fraction lies in
``[0, 1)``: a model of a lower (relative) complexity is always cheaper than any model of a higher one, whatever the
data (the paper's non-overlapping layers). Within a layer the classes are ordered BIC-style, by error plus a penalty
per rank: a revolute joint takes the edge from a prismatic one only when it predicts better by more than ``p``
thresholds, a GP from a revolute joint likewise. Validity on relative observations is loose at the paper's noise, so a
strict class order would let a valid but wrong simple model (a prismatic joint where a revolute one is valid and far
better) win. See ``docs/core/learning-and-adaptation.md`` for why this orders models like the paper's ``log q``.
"""

from __future__ import annotations

import math

import numpy as np

from ..transforms import rotational_error, translational_error

__all__ = [
    "CLASS_RANKS",
    "N_RANKS",
    "RANK_PENALTY",
    "class_rank",
    "nests",
    "prediction_errors",
    "model_cost",
    "relative_complexity",
    "replacement_cost",
]

#: Largest normalised error entering a cost, so that ``C + e < C + 1`` holds in floating point.
_E_MAX = math.nextafter(1.0, 0.0)
#: Penalty per class rank, in mean threshold ratios (see the module docstring).
RANK_PENALTY = 0.1
#: Rank of each local-model class within its complexity layer: fewer parameters first (static 6, prismatic 9,
#: revolute 11, a chain of k joints about 4 k + 6, a GP one per training sample and output). Engineered models are a
#: specification, not a candidate.
CLASS_RANKS = {"static": 0, "prismatic": 0, "revolute": 1, "chain": 1, "gp": 2, "engineered": 0}
N_RANKS = 3
#: What a class can represent, for one set of actions: static < prismatic, revolute < chain < GP (prismatic and
#: revolute are different forms, neither nests the other; a chain of joints holds one of them for each of its
#: actions, a GP any smooth relation). Engineered models nest nothing and are nested by nothing.
_FLEXIBILITY = {"static": 0, "prismatic": 1, "revolute": 1, "chain": 1.5, "gp": 2}


def class_rank(kind):
    """Rank of a model class within its layer (:data:`CLASS_RANKS`); unknown classes rank last."""
    return CLASS_RANKS.get(kind, N_RANKS - 1)


def nests(kind_a, actions_a, kind_b, actions_b):
    """Whether model class ``kind_a`` on ``actions_a`` can represent every relation ``kind_b`` on ``actions_b`` can.

    True when the actions of ``b`` are a subset of ``a``'s and ``a``'s class is more flexible, or the class is the
    same and the subset strict (e.g. a GP on ``(a1, a2)`` nests a revolute joint on ``a1`` and a GP on ``a1``). A
    chain also nests a GP of fewer of its actions: it cannot represent every relation such a GP can, but what the
    dominance rule asks of a nesting model holds: when it predicts clearly better, the actions it adds matter.
    """
    return bool(nesting_matrix([kind_b, kind_a], [actions_b, actions_a], 1 + max((*actions_a, *actions_b, 0)))[0, 1])


def nesting_matrix(kinds, action_sets, n_actions, covers=None):
    """``M[k, q] = nests(kinds[q], covers[q], kinds[k], action_sets[k])`` for all pairs at once, shape (g, g).

    :func:`nests` for a group of models, with numpy instead of ``g**2`` calls (a bootstrap pair has about a hundred
    candidates). ``covers``: the actions each model covers as the nesting one (default its actions; a chain's with
    those found not to move its child)."""
    flex = np.array([_FLEXIBILITY.get(k, -1) for k in kinds])
    A = np.zeros((len(kinds), n_actions + 1), dtype=np.int64)
    for k, acts in enumerate(action_sets):
        A[k, list(acts)] = 1
    C = A.copy()
    for k, acts in enumerate(action_sets if covers is None else covers):
        C[k, list(acts)] = 1
    subset = (A @ (1 - C).T) == 0  # subset[k, q]: the actions of k are among those q covers
    same = subset & (((1 - A) @ C.T) == 0)
    kind_q, kind_k = np.asarray(kinds, dtype=object)[None, :], np.asarray(kinds, dtype=object)[:, None]
    more_flexible = flex[None, :] > flex[:, None]
    known = (flex[None, :] >= 0) & (flex[:, None] >= 0)
    chain_of_more = (kind_q == "chain") & ~same  # a chain of more actions nests any class (see nests)
    return known & subset & np.where(kind_q == kind_k, ~same, more_flexible | chain_of_more)


def prediction_errors(Z_pred, Z_obs):
    """Per-sample translational and rotational error between predicted and observed relative transforms.

    This is the paper's per-sample error (Eq. 6) evaluated at the model's maximum-likelihood prediction instead of
    integrated over its predictive distribution; it is what the validity thresholds ``theta = 3 sigma`` refer to.

    Parameters
    ----------
    Z_pred, Z_obs : array-like, shape (..., 4, 4)
        Predicted and observed ``parent2child``.

    Returns
    -------
    trans_error : ndarray, shape (...)
        Distance between the predicted and observed child origin, in m.
    rot_error : ndarray, shape (...)
        Angle of the rotation between them, in rad, in [0, pi].
    """
    return translational_error(Z_pred, Z_obs), rotational_error(Z_pred, Z_obs)


def model_cost(complexity, trans_ratio, rot_ratio, rank=0):
    """Cost of a valid local model for the minimum spanning tree (lower is better; paper Eq. 4 and 7).

    Parameters
    ----------
    complexity : int or array-like of int
        C(M), the number of actions the model depends on (or C(M2|M1) for a replacement).
    trans_ratio, rot_ratio : float or array-like
        Mean test-window errors in units of their thresholds (below 1 for a valid model).
    rank : int or array-like of int
        Class rank within the layer (:func:`class_rank`), 0 to ``N_RANKS - 1``: adds ``RANK_PENALTY`` thresholds
        per rank to the error.

    Returns
    -------
    cost : float or ndarray
        ``complexity + (e + RANK_PENALTY rank) / (1 + RANK_PENALTY (N_RANKS - 1))`` with
        ``e = clip((trans_ratio + rot_ratio) / 2, 0, 1 - ulp)``: layers never overlap.
    """
    e = np.clip(0.5 * (np.asarray(trans_ratio, dtype=float) + np.asarray(rot_ratio, dtype=float)), 0.0, _E_MAX)
    layer = np.asarray(complexity, dtype=float)
    cost = layer + (e + RANK_PENALTY * np.asarray(rank, dtype=float)) / (1.0 + RANK_PENALTY * (N_RANKS - 1))
    # The sum can round up to C + 1 in floating point; keep it strictly inside its layer.
    cost = np.minimum(cost, np.nextafter(layer + 1.0, layer))
    return float(cost) if cost.ndim == 0 else cost


def relative_complexity(actions_new, actions_old):
    """C(M2 | M1) of paper Eq. 11: the number of actions by which two models' action sets differ.

    The size of the symmetric difference is a metric on action sets (0 for the same set, 1 for one action added or
    removed, ...) and an integer, as Eq. 11 requires. The paper suggests "the ratio of shared nodes"; the symmetric
    difference orders candidates the same way for one pair of parts and is exact in integers.
    """
    return len(set(actions_new) ^ set(actions_old))


def replacement_cost(actions_new, actions_old, trans_ratio, rot_ratio, rank=0):
    """Cost of a valid replacement ``M2`` for a failed model ``M1`` (paper Eq. 11), see :func:`model_cost`."""
    return model_cost(relative_complexity(actions_new, actions_old), trans_ratio, rot_ratio, rank)
