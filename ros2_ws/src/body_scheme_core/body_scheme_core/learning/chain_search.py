"""Finding the chain of joints between two observed parts from scratch: which actions, which types, which order.

What a calibration tool is given (the robot's URDF), the learner finds from its own motions, the way circle point
analysis measures a robot's joint axes (Mooring, Roth and Driels): moving one joint at a time from a reference
posture, the child turns about (or slides along) that joint's screw, expressed in the parent frame at the reference
posture, whatever the other joints' order. So from *excursions* (samples that differ from the reference posture in one
action only) each joint's screw and type follow from a one-action local model, and an action that moves nothing is no
joint of the chain (the dependence test). A sample that differs in two actions, one of whose screws is known, gives
the other's screw and which of the two comes first. The order of the whole chain is then the one that explains the
samples in which several joints moved, found by insertion and swaps of neighbours (:func:`best_order`), and the chain
is refined on every sample (:meth:`~body_scheme_core.models.chain.ChainModel.fit`).

The exploration policy proposes such excursions while the learner bootstraps
(:func:`~body_scheme_core.control.exploration.excursion_plan`); a user's calibration
data often consists of them already (one joint swept at a time).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..errors import BodySchemeError
from ..models import ChainModel, PrismaticModel, RevoluteModel, chain_form, pose_residuals
from ..rotations import chordal_mean, rotation_log
from ..transforms import invert_transform

__all__ = ["Excursions", "find_excursions", "JointScrew", "identify_chain", "best_order", "same_chain",
           "order_decided", "ORDER_SAMPLES", "ChainNotIdentified", "stored_screw"]

#: Two action values closer than this (rad, m) are the same posture of that joint.
SAME = 1e-6
#: A joint whose excursions scatter the child's pose about their mean by less than this mean squared residual (in
#: noise units; 1 for noise alone) moves nothing: it is not part of the chain; nor is one whose best one-joint model
#: leaves more than 1 / EXPLAINED of that scatter.
STILL_CHI2 = 4.0
EXPLAINED = 4.0
#: A prismatic fit wins over a revolute one unless its normalised residual is this much larger.
PRISMATIC_MARGIN = 1.5
#: Samples in which several joints moved, per joint, before their order is decided (with fewer, several orders
#: explain the samples alike, and a wrong one fails on the next posture).
ORDER_SAMPLES = 2


class ChainNotIdentified(BodySchemeError):
    """The data does not (yet) determine the chain: too few excursions, or joints that cannot be told apart."""


@dataclass(frozen=True)
class Excursions:
    """Samples that differ from a reference posture in few actions.

    Attributes
    ----------
    reference : ndarray, shape (m,)
        The reference posture: per action its most frequent value.
    single : dict of int to ndarray of int
        Per action, the samples that differ from the reference in that action alone (the reference itself, if it
        was sampled, in none: it is in ``at_reference``).
    pairs : dict of tuple to ndarray of int
        Per pair of actions, the samples that differ in exactly those two.
    at_reference : ndarray of int
        Samples at the reference posture.
    """

    reference: np.ndarray
    single: dict
    pairs: dict
    at_reference: np.ndarray


def find_excursions(A, actions):
    """The :class:`Excursions` of action vectors ``A`` (n, m) over the columns ``actions``."""
    A = np.asarray(A, dtype=float)
    cols = list(actions)
    reference = A[0].copy()
    for j in cols:
        values, counts = np.unique(np.round(A[:, j] / SAME) * SAME, return_counts=True)
        reference[j] = values[np.argmax(counts)]
    differs = np.abs(A[:, cols] - reference[cols]) > 10 * SAME
    n_diff = differs.sum(axis=1)
    single = {j: np.flatnonzero((n_diff == 1) & differs[:, c]) for c, j in enumerate(cols)}
    pairs = {}
    for (c1, j1), (c2, j2) in itertools.combinations(enumerate(cols), 2):
        rows = np.flatnonzero((n_diff == 2) & differs[:, c1] & differs[:, c2])
        if rows.size:
            pairs[(j1, j2)] = rows
    return Excursions(reference, single, pairs, np.flatnonzero(n_diff == 0))


@dataclass(frozen=True)
class JointScrew:
    """One joint of a chain, found from its excursions: ``kind``, its screw in the parent frame at the reference
    posture (a revolute ``(w, p)``, a prismatic ``d``), and how well its one-action model fit (``rms``, in sigmas)."""

    action: int
    kind: str
    screw: tuple
    rms: float


def _joint_fits(action, A, Z, S, parent, child):
    """The revolute and prismatic one-action fits of one joint's excursions that succeed, by kind."""
    fits = {}
    for kind, cls in (("revolute", RevoluteModel), ("prismatic", PrismaticModel)):
        if len(Z) < cls.unit_form.MIN_SAMPLES:
            continue
        try:
            fits[kind] = cls(parent, child, (action,)).fit(A, Z, S)
        except (BodySchemeError, np.linalg.LinAlgError, ValueError):
            continue
    return fits


def _one_joint(action, A, Z, S, parent, child, fits=None, scale=1.0):
    """The better of the revolute and prismatic fits of one joint's excursions as a :class:`JointScrew`, and the
    pose at the reference (M) it implies, or None when the joint moves nothing. ``fits``: :func:`_joint_fits` made
    with ``S`` divided by ``scale`` (their residuals are rescaled)."""
    scatter = _scatter(Z, S)
    if scatter < STILL_CHI2:
        return None
    if fits is None:
        fits, scale = _joint_fits(action, A, Z, S, parent, child), 1.0
    rms = {kind: fit.rms_ / scale for kind, fit in fits.items()}
    if fits and min(rms.values()) ** 2 > scatter / EXPLAINED:
        # One sample may be an outlier (the reference posture is in every joint's excursions): both tests again
        # without the one the better fit explains worst.
        fits, rms, scatter = _without_worst(action, A, Z, S, parent, child, fits, rms)
    if not fits or scatter < STILL_CHI2 or min(rms.values()) ** 2 > scatter / EXPLAINED:
        return None  # the scatter is not a joint's motion: no one-joint model explains most of it
    kind = "revolute" if "revolute" in fits else "prismatic"
    if "prismatic" in fits and "revolute" in fits and rms["prismatic"] <= PRISMATIC_MARGIN * max(
            rms["revolute"], 1.0):
        kind = "prismatic"
    model = fits[kind]
    if kind == "revolute":
        u, r, p0 = model.params_[0:3], model.params_[3:6], model.params_[6:9]
        point = p0 + r
        screw = (u, point - (point @ u) * u)
    else:
        screw = model.params_[6:9] / np.linalg.norm(model.params_[6:9])
    return JointScrew(action, kind, screw, rms[kind]), model


def _scatter(Z, S):
    """The dependence test's statistic: the mean squared normalised residual of the poses ``Z`` about their mean (1
    for noise alone)."""
    still = np.eye(4)
    still[:3, :3] = chordal_mean(Z[None, :, :3, :3], np.ones((1, len(Z))))[0]
    still[:3, 3] = Z[:, :3, 3].mean(axis=0)
    return float(np.mean(pose_residuals(np.broadcast_to(still, Z.shape), Z, S) ** 2))


def _without_worst(action, A, Z, S, parent, child, fits, rms):
    """``(fits, rms, scatter)`` of ``action``'s excursions without the sample that the better of ``fits`` explains
    worst (:func:`_joint_fits`, their normalised rms, :func:`_scatter`); no fits when too few samples would be left."""
    if len(Z) - 1 < RevoluteModel.unit_form.MIN_SAMPLES + 1:
        return {}, {}, 0.0
    best = fits[min(rms, key=rms.get)]
    keep = np.ones(len(Z), dtype=bool)
    keep[np.argmax(np.sum(pose_residuals(best.predict(A), Z, S) ** 2, axis=1))] = False
    fits = _joint_fits(action, A[keep], Z[keep], S[keep], parent, child)
    return fits, {kind: fit.rms_ for kind, fit in fits.items()}, _scatter(Z[keep], S[keep])


def _noise_scale(fits):
    """How much larger the noise is than the samples' sigma says, from the excursions themselves: the median over
    actions of the best one-joint fit's normalised residual (``fits``: :func:`_joint_fits` per action; a joint's
    fit, or a still action's, leaves the noise). A learner's noise is unknown until a rigid model explains the
    child, and a tool seen past several joints has none before its chain: so the dependence test is judged against
    the noise the data show. 1 without fits."""
    scales = [min(fit.rms_ for fit in f.values()) for f in fits.values() if f]
    return float(np.clip(np.median(scales), 1e-3, 1e3)) if scales else 1.0


def stored_screw(kind, screw):
    """A joint's screw as a chain's parameters store it: ``(w, p)`` of a revolute joint as six numbers, a prismatic
    joint's direction as three."""
    return np.concatenate(screw) if kind == "revolute" else np.asarray(screw, dtype=float)


def _chain_shape(joints, couplings):
    """``(types, index couplings, coefficients)`` of ``joints`` in order and ``couplings`` ``{(action i, action j):
    c}``."""
    at = {j.action: k for k, j in enumerate(joints)}
    pairs = sorted(pair for pair in couplings if pair[0] in at and pair[1] in at)  # a partial order: its own
    return (tuple(j.kind for j in joints), tuple((at[i], at[j]) for i, j in pairs),
            [couplings[pair] for pair in pairs])


def _chain_params(joints, M, couplings=None):
    """Stored chain parameters of ``joints`` (JointScrew, in order), ``couplings`` and the reference pose ``M``."""
    _, _, coefficients = _chain_shape(joints, couplings or {})
    return np.concatenate([stored_screw(j.kind, j.screw) for j in joints] + [coefficients]
                          + [M[:3, 3], rotation_log(M[None, :3, :3])[0]])


def _chain_error(joints, M, A, Z, S, reference, couplings=None):
    """Mean squared normalised residual of the chain ``joints`` (in order) with reference pose ``M`` over samples."""
    types, pairs, _ = _chain_shape(joints, couplings or {})
    form = chain_form(types, pairs)
    x = A[:, [j.action for j in joints]] - reference[[j.action for j in joints]]
    pred = form.transforms(_chain_params(joints, M, couplings)[None], x[None])[0]
    r = pose_residuals(pred, Z, S)
    return float(np.mean(np.minimum(r * r, 100.0)))


def best_order(joints, M, A, Z, S, reference, couplings=None):
    """The order of ``joints`` that best explains samples in which several moved: insert each at its best place,
    then swap neighbours while that helps. Returns ``(ordered joints, error)``; the given order when no sample tells
    orders apart."""
    if len(joints) < 2 or len(A) == 0:
        return list(joints), _chain_error(joints, M, A, Z, S, reference, couplings) if len(A) else 0.0

    def error_of(order):
        return _chain_error(order, M, A, Z, S, reference, couplings)

    order = [joints[0]]
    for joint in joints[1:]:
        trials = [order[:i] + [joint] + order[i:] for i in range(len(order) + 1)]
        order = trials[int(np.argmin([error_of(t) for t in trials]))]
    error = error_of(order)
    improved = True
    while improved:
        improved = False
        for i in range(len(order) - 1):
            trial = order[:i] + [order[i + 1], order[i]] + order[i + 2:]
            trial_error = error_of(trial)
            if trial_error < error - 1e-9:
                order, error, improved = trial, trial_error, True
    return order, error


def identify_chain(A, Z, sigma, parent, child, actions, sigma_trans=None, sigma_rot=None):
    """The chain between ``parent`` and ``child`` from scratch (module docstring).

    Parameters
    ----------
    A : ndarray, shape (n, m)
        Full action vectors of the samples in which both parts were observed.
    Z : ndarray, shape (n, 4, 4)
        ``parent2child`` observed.
    sigma : ndarray, shape (n, 2) or (2,)
        Per-sample noise std (trans m, rot rad) of ``Z``.
    parent, child : int
    actions : sequence of int
        The actions that may drive the chain (those that move nothing are left out).

    Returns
    -------
    model : ChainModel
        Fitted on every sample.

    Raises
    ------
    ChainNotIdentified
        When some action moved without an excursion that tells its screw, or no joint moved.
    """
    A, Z = np.asarray(A, dtype=float), np.asarray(Z, dtype=float)
    S = np.broadcast_to(np.asarray(sigma, dtype=float), (len(Z), 2)).copy()
    ex = find_excursions(A, actions)
    rows_of = {j: np.concatenate([ex.at_reference, ex.single[j]]) for j in actions if ex.single[j].size >= 2}
    fits = {j: _joint_fits(j, A[rows], Z[rows], S[rows], parent, child) for j, rows in rows_of.items()}
    scale = _noise_scale(fits)
    S *= scale
    joints, M_estimates = {}, []
    for j, rows in rows_of.items():
        found = _one_joint(j, A[rows], Z[rows], S[rows], parent, child, fits[j], scale)
        if found is None:
            continue
        joints[j] = found[0]
        M_estimates.append(found[1].predict(ex.reference[None])[0])
    moving = [j for j in actions if np.ptp(A[:, j]) > 10 * SAME and j not in joints
              and ex.single[j].size < 2]
    if not joints:
        raise ChainNotIdentified(f"no excursion of a single action moves part {child} relative to {parent} yet")
    M = _mean_pose(np.array(M_estimates))
    # Actions without single excursions: from pair excursions with a known partner (the partner's screw known).
    couplings = {}
    for j in list(moving):
        for (j1, j2), rows in ex.pairs.items():
            if j not in (j1, j2) or rows.size < 2:
                continue
            other = j2 if j == j1 else j1
            if other not in joints:
                continue
            found = _from_pair(j, joints[other], rows, A, Z, S, ex.reference, M, parent, child)
            if found is not None:
                joints[j], coupling = found
                if coupling is not None:
                    couplings[(other, j)] = coupling
                moving.remove(j)
                break
    if moving:
        raise ChainNotIdentified(f"actions {moving} move part {child} but have no excursion that tells their screw")
    several = np.flatnonzero(np.sum(np.abs(A[:, list(joints)] - ex.reference[list(joints)]) > 10 * SAME,
                                    axis=1) >= 2)
    order, _ = best_order(list(joints.values()), M, A[several], Z[several], S[several], ex.reference, couplings)
    hyper = {} if sigma_trans is None else {"sigma_trans": sigma_trans, "sigma_rot": sigma_rot}

    inert = tuple(j for j in rows_of if j not in joints)  # excursions that left the child still

    def fitted(order):
        types, pairs, _ = _chain_shape(order, couplings)
        model = ChainModel(parent, child, tuple(j.action for j in order), types,
                           reference=ex.reference[[j.action for j in order]], couplings=pairs,
                           order_evidence=int(several.size), inert_actions=inert, **hyper)
        return model.fit(A, Z, S, start=_chain_params(order, M, couplings))

    model = fitted(order)
    if several.size >= ORDER_SAMPLES * len(order):
        model = _polish_order(model, order, fitted)
    return model


def _polish_order(model, order, fitted):
    """Swap neighbours of ``order`` while the whole chain, fitted again on every sample, explains them better (the
    screws at the reference posture do not depend on the order, so each swap starts from the same ones)."""
    improved = True
    while improved:
        improved = False
        for i in range(len(order) - 1):
            trial = order[:i] + [order[i + 1], order[i]] + order[i + 2:]
            try:
                candidate = fitted(trial)
            except (BodySchemeError, np.linalg.LinAlgError, ValueError):
                continue
            if candidate.rms_ < model.rms_ * (1.0 - 1e-3):
                model, order, improved = candidate, trial, True
    return model


def order_decided(model):
    """Whether a model's joints' order was decided by data: always, but for a chain identified from fewer than
    :data:`ORDER_SAMPLES` samples per joint in which several of its joints moved (a learner neither freezes nor
    installs it, and identifies it again as they come)."""
    return not isinstance(model, ChainModel) or len(model.actions) < 2 or \
        model.order_evidence >= ORDER_SAMPLES * len(model.actions)


def _mean_pose(Ms):
    out = np.eye(4)
    out[:3, :3] = chordal_mean(Ms[None, :, :3, :3], np.ones((1, len(Ms))))[0]
    out[:3, 3] = np.median(Ms[:, :3, 3], axis=0)
    return out


def _from_pair(j, known, rows, A, Z, S, reference, M, parent, child):
    """Joint ``j``'s screw from samples in which it and the ``known`` joint moved; returns ``(JointScrew,
    coupling coefficient or None)``, or None. Three explanations are tried and the best kept: the known joint first
    (``Z = E_known E_j M``), last (``Z = E_j E_known M``), or not moving at all because its command follows ``j``'s
    (``Z = E_j M`` while ``q_known + c q_j = 0``: a coupled joint, ``c`` then a parameter of the chain)."""
    form_known = chain_form((known.kind,))
    q_known = A[rows, known.action] - reference[known.action]
    q_j = A[rows, j] - reference[j]
    E_known = form_known.transforms(np.concatenate([stored_screw(known.kind, known.screw), np.zeros(6)])[None],
                                    q_known[None, :, None])[0]
    best = None
    for hypothesis in ("known first", "known last", "coupled"):
        # Turn the samples into excursions of j alone: E_j M = E_known^-1 Z (known first), Z M^-1 E_known^-1 M
        # (known last), or Z itself (the known joint did not move).
        if hypothesis == "known first":
            Zj = invert_transform(E_known) @ Z[rows]
        elif hypothesis == "known last":
            Zj = Z[rows] @ invert_transform(M) @ invert_transform(E_known) @ M
        else:
            Zj = Z[rows]
        Aj = A[rows].copy()
        Aj[:, known.action] = reference[known.action]
        found = _one_joint(j, np.vstack([reference[None], Aj]), np.concatenate([M[None], Zj]),
                           np.vstack([S[rows[:1]], S[rows]]), parent, child)
        if found is not None and (best is None or found[0].rms < best[0].rms):
            coupling = -float(q_known @ q_j / (q_j @ q_j)) if hypothesis == "coupled" else None
            best = (found[0], coupling)
    return best


def _commute(kind_a, screw_a, kind_b, screw_b, tol=1e-3):
    """Whether two joints' screws commute (either order gives the same motion): two prismatic joints always, a
    prismatic and a revolute one when parallel, two revolute ones when coaxial."""
    if kind_a == kind_b == "prismatic":
        return True
    if kind_a == "prismatic" or kind_b == "prismatic":
        d, (w, _) = (screw_a, screw_b) if kind_a == "prismatic" else (screw_b, screw_a)
        return abs(abs(float(d @ w)) - 1.0) < tol
    (w1, p1), (w2, p2) = screw_a, screw_b
    return abs(abs(float(w1 @ w2)) - 1.0) < tol and np.linalg.norm(np.cross(w1, p2 - p1)) < tol


def same_chain(model, truth):
    """Whether chain ``model`` has the joints (actions and types) of chain ``truth`` in its order, up to the order of
    neighbours whose screws commute (two sliding joints, say): the order a tool's observations can tell."""
    if sorted(zip(model.actions, model.types, strict=True)) != sorted(zip(truth.actions, truth.types, strict=True)):
        return False
    screws, _ = truth.screws()
    at = {a: k for k, a in enumerate(model.actions)}
    for i, j in itertools.combinations(range(len(truth.actions)), 2):
        if not _commute(truth.types[i], screws[i], truth.types[j], screws[j]) and \
                at[truth.actions[i]] > at[truth.actions[j]]:
            return False
    return True
