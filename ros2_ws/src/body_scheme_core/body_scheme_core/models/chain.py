"""Chain local model: several one-degree-of-freedom joints between two observed parts (product of exponentials).

Real robots are observed at the tool, not on every link: between two observed parts lie k joints (revolute or
prismatic) and k - 1 unmarked links. The chain model describes ``parent2child`` as a product of exponentials, the
parametrisation of kinematic calibration (Brockett; Park and Okamura's minimal POE)::

    parent2child(a) = exp([S_1] q_1) ... exp([S_k] q_k) M,      q_i = a[action_i] - ref_i

- ``S_i``: the screw of joint i in the parent frame at the reference posture ``ref`` (all ``q = 0``): a revolute
  joint's unit axis ``w`` and the point ``p`` of its axis nearest the parent's origin (``S = (w, p x w)``), a
  prismatic joint's unit direction ``d`` (``S = (0, d)``);
- ``M``: the child's pose at the reference posture.

The joints are in chain order, from the parent to the child; ``actions`` lists their actions in that order. A joint
may be *coupled* to another joint's action (``couplings``: pairs ``(i, j)``), as industrial arms couple their shoulder
and elbow (a Fanuc's J3 command is the elbow's angle to the horizontal): then ``q_i = a[action_i] - ref_i + c_ij
(a[action_j] - ref_j)``, with ``c_ij`` a parameter. The joints' zero offsets are not parameters: a product of
exponentials about a reference posture absorbs them into the screws and ``M``, which is what makes it minimal. A
revolute joint has 4 degrees of freedom (its axis line), a prismatic one 2 (its direction: where its line lies is
invisible), ``M`` 6: ``4 R + 2 P + 6`` in all, the count of identifiable kinematic parameters of a serial chain
observed in 6D at its end (Everett, Driels and Mooring). What such an observation cannot tell apart (the joints' zero
positions, where along its axis a link frame sits, a prismatic joint's line) is therefore not in the model;
:mod:`body_scheme_core.prediction.learned_body` puts the unmarked links' frames where the robot's specification has
them, when one is given.

Storage layout: per joint, a revolute ``w`` (3) and ``p`` (3) with ``p . w = 0``, a prismatic ``d`` (3); then the
coupling coefficients (one each); then ``M``'s translation (3) and rotation vector (3). A local increment: per
revolute joint, ``[r1, r2, t1, t2]``, its axis line turned by ``r1 e1 + r2 e2`` about the point ``p`` and moved by
``t1 e1 + t2 e2`` (``e1, e2`` perpendicular to ``w``); per prismatic joint ``[r1, r2]``, its direction turned; the
coupling coefficients added; then ``M``'s ``[dt (3), w (3)]`` (translation added in the parent frame, rotation
right-multiplied), the twist convention of :mod:`body_scheme_core.models.rigid_fit`.

The form is generated per sequence of joint types and couplings (:func:`chain_form`), so the joint fit
(:mod:`body_scheme_core.calibration.joint_fit`) refines a chain like any rigid-joint model: its twists come from the
adjoint maps of the partial products (a joint's screw moved by ``eta`` moves the chain by ``Ad_P (I - Ad_E) eta``).
"""

from __future__ import annotations

import functools
import math
import operator

import numpy as np

from ..errors import InvalidInputError, ModelFileError
from ..limits import MAX_CHAIN_JOINTS
from ..rotations import cross3, perpendicular_basis, rotation_log, rotvec_matrix, skew
from .base import check_observations
from .rigid import RigidJointModel, _sigmas
from .rigid_fit import fit_rms, least_squares_fit

__all__ = ["ChainModel", "chain_form", "JOINT_TYPES", "screw_transforms"]

#: Most actions a chain records as inert (found not to move its child).
MAX_INERT_ACTIONS = 1000
#: Joint types of a chain and their degrees of freedom in a local increment.
JOINT_TYPES = {"revolute": 4, "prismatic": 2}
#: Stored numbers per joint type.
_STORED = {"revolute": 6, "prismatic": 3}


def screw_transforms(kind, screw, q):
    """``exp([S] q)`` (..., n, 4, 4) of a revolute joint (``screw = (w, p)``, each (..., 3)) or a prismatic joint
    (``screw = d``, (..., 3)) at joint values ``q`` (..., n)."""
    q = np.asarray(q, dtype=float)
    E = np.zeros(q.shape + (4, 4))
    E[..., 3, 3] = 1.0
    if kind == "revolute":
        w, p = screw
        R = _rodrigues(w, q)
        E[..., :3, :3] = R
        E[..., :3, 3] = p[..., None, :] - (R @ p[..., None, :, None])[..., 0]
    else:
        E[..., :3, :3] = np.eye(3)
        E[..., :3, 3] = screw[..., None, :] * q[..., None]
    return E


def _rodrigues(w, q):
    """Rotations about unit axes ``w`` (..., 3) by angles ``q`` (..., n): (..., n, 3, 3)."""
    K = skew(w)[..., None, :, :]
    K2 = K @ K
    s, c = np.sin(q)[..., None, None], np.cos(q)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * K2


def _adjoint(G, xi):
    """``Ad_G xi`` of spatial twists ``xi = (w, v)`` (..., 6, p) by transforms ``G`` (..., 4, 4)."""
    R, t = G[..., :3, :3], G[..., :3, 3]
    w = R @ xi[..., :3, :]
    v = cross3(t[..., None, :], np.swapaxes(w, -1, -2)) + np.swapaxes(R @ xi[..., 3:, :], -1, -2)
    return np.concatenate([w, np.swapaxes(v, -1, -2)], axis=-2)


class _ChainForm:
    """The chain form of one sequence of joint types and couplings, vectorised over k models and n samples (see
    :mod:`~body_scheme_core.models.rigid`); made by :func:`chain_form`. ``x`` is (k, n, d): per joint its action's
    offset from the reference."""

    TYPES: tuple = ()
    COUPLINGS: tuple = ()
    N_PARAMS = 6
    N_STORED = 6
    MIN_SAMPLES = 2
    #: Start index of each joint in the stored parameters and in an increment, and of the coupling coefficients.
    STORED_AT: tuple = ()
    PARAMS_AT: tuple = ()
    COUPLING_STORED_AT = 0
    COUPLING_PARAMS_AT = 0

    @classmethod
    def joint_values(cls, params, x):
        """``q`` (k, n, d): the actions' offsets plus the couplings."""
        if not cls.COUPLINGS:
            return x
        q = x.copy()
        for c, (i, j) in enumerate(cls.COUPLINGS):
            q[..., i] += params[:, None, cls.COUPLING_STORED_AT + c] * x[..., j]
        return q

    @classmethod
    def _unpack(cls, params):
        """Per joint its screw (``(w, p)`` or ``d``), then ``M`` (k, 4, 4)."""
        screws = []
        for kind, at in zip(cls.TYPES, cls.STORED_AT, strict=True):
            screws.append((params[:, at:at + 3], params[:, at + 3:at + 6]) if kind == "revolute"
                          else params[:, at:at + 3])
        M = np.zeros((params.shape[0], 4, 4))
        M[:, :3, :3] = rotvec_matrix(params[:, -3:])
        M[:, :3, 3] = params[:, -6:-3]
        M[:, 3, 3] = 1.0
        return screws, M

    @classmethod
    def transforms(cls, params, x):
        return cls.evaluate(params, x, twists=False)[0]

    @classmethod
    def twists(cls, params, x):
        return cls.evaluate(params, x)[1]

    @classmethod
    def evaluate(cls, params, x, twists=True):
        """``(transforms (k, n, 4, 4), twists (k, n, 6, p) or None)`` at joint values ``x`` (k, n, d)."""
        params = np.asarray(params, dtype=float)
        x = np.asarray(x, dtype=float).reshape(params.shape[0], -1, len(cls.TYPES))
        k, n, _ = x.shape
        screws, M = cls._unpack(params)
        q = cls.joint_values(params, x)
        P = np.broadcast_to(np.eye(4), (k, n, 4, 4)).copy()
        partial = []  # P_{i-1} and E_i per joint
        for i, (kind, screw) in enumerate(zip(cls.TYPES, screws, strict=True)):
            E = screw_transforms(kind, screw, q[..., i])
            partial.append((P, E))
            P = P @ E
        Z = P @ M[:, None]
        if not twists:
            return Z, None
        xi = np.zeros((k, n, 6, cls.N_PARAMS))  # spatial twists (w, v) in the parent frame
        _, E1, E2 = cls._directions(params)
        for i, (kind, screw) in enumerate(zip(cls.TYPES, screws, strict=True)):
            before, E = partial[i]
            e1, e2 = E1[:, i], E2[:, i]
            if kind == "revolute":
                p = screw[1]
                eta = np.zeros((k, 6, 4))
                eta[:, :3, 0], eta[:, 3:, 0] = e1, cross3(p, e1)
                eta[:, :3, 1], eta[:, 3:, 1] = e2, cross3(p, e2)
                eta[:, 3:, 2], eta[:, 3:, 3] = e1, e2
            else:
                eta = np.zeros((k, 6, 2))
                eta[:, :3, 0], eta[:, :3, 1] = e1, e2
            eta = np.broadcast_to(eta[:, None], (k, n) + eta.shape[1:])
            at = cls.PARAMS_AT[i]
            xi[..., at:at + eta.shape[-1]] = _adjoint(before, eta - _adjoint(E, eta))
        for c, (i, j) in enumerate(cls.COUPLINGS):  # dq_i / dc_ij = x_j moves the chain by Ad_P S_i x_j
            before = partial[i][0]
            xi[..., cls.COUPLING_PARAMS_AT + c] = _adjoint(before, cls._screw_twist(screws[i], cls.TYPES[i], k, n))[
                ..., 0] * x[..., j, None]
        # From spatial twists to the convention [dt, w]: dt = w_s x t + v_s, w = R^T w_s.
        R, t = Z[..., :3, :3], Z[..., :3, 3]
        T = np.empty_like(xi)
        T[..., :3, :] = np.swapaxes(cross3(np.swapaxes(xi[..., :3, :], -1, -2), t[..., None, :]), -1, -2) \
            + xi[..., 3:, :]
        T[..., 3:, :] = np.swapaxes(R, -1, -2) @ xi[..., :3, :]
        # M's increment: dt in the parent frame after the joints (R_P dt), w right-multiplied as it is.
        T[..., :3, -6:-3] = P[..., :3, :3]
        T[..., 3:, -6:-3] = 0.0
        T[..., :3, -3:] = 0.0
        T[..., 3:, -3:] = np.eye(3)
        return Z, T

    @staticmethod
    def _screw_twist(screw, kind, k, n):
        """The joint's spatial screw (k, n, 6, 1): ``(w, p x w)`` or ``(0, d)``."""
        S = np.zeros((k, n, 6, 1))
        if kind == "revolute":
            S[..., :3, 0] = screw[0][:, None]
            S[..., 3:, 0] = cross3(screw[1], screw[0])[:, None]
        else:
            S[..., 3:, 0] = screw[:, None]
        return S

    @classmethod
    def _directions(cls, params):
        """Every joint's unit direction (k, d, 3) and its perpendicular basis ``e1, e2`` (each (k, d, 3)), at once."""
        W = params[:, np.asarray(cls.STORED_AT)[:, None] + np.arange(3)]
        return (W, *perpendicular_basis(W))

    @classmethod
    def retract(cls, params, delta):
        """Parameters (k, q) after increments (k, p) (module docstring)."""
        params = np.asarray(params, dtype=float)
        out = params.copy()
        W, E1, E2 = cls._directions(params)
        d = np.asarray(cls.PARAMS_AT)
        turns = rotvec_matrix(delta[:, d, None] * E1 + delta[:, d + 1, None] * E2)  # (k, d, 3, 3)
        W_new = np.einsum("kdij,kdj->kdi", turns, W)
        W_new /= np.linalg.norm(W_new, axis=2, keepdims=True)
        for i, (kind, at, d) in enumerate(zip(cls.TYPES, cls.STORED_AT, cls.PARAMS_AT, strict=True)):
            w_new = W_new[:, i]
            out[:, at:at + 3] = w_new
            if kind == "revolute":
                p = params[:, at + 3:at + 6] + delta[:, d + 2:d + 3] * E1[:, i] + delta[:, d + 3:d + 4] * E2[:, i]
                out[:, at + 3:at + 6] = p - np.sum(p * w_new, axis=1, keepdims=True) * w_new
        n_c = len(cls.COUPLINGS)
        out[:, cls.COUPLING_STORED_AT:cls.COUPLING_STORED_AT + n_c] += delta[:, cls.COUPLING_PARAMS_AT:
                                                                          cls.COUPLING_PARAMS_AT + n_c]
        out[:, -6:-3] = params[:, -6:-3] + delta[:, -6:-3]
        out[:, -3:] = rotation_log(rotvec_matrix(params[:, -3:]) @ rotvec_matrix(delta[:, -3:]))
        return out

    @classmethod
    def validate(cls, params):
        """Stored parameters (q,) with unit joint directions and each revolute point perpendicular to its axis."""
        params = np.asarray(params, dtype=float)
        if params.shape != (cls.N_STORED,):
            raise ValueError(f"a {'-'.join(cls.TYPES)} chain has {cls.N_STORED} stored parameters, got "
                             f"{params.shape}")
        for kind, at in zip(cls.TYPES, cls.STORED_AT, strict=True):
            w = params[at:at + 3]
            if abs(np.linalg.norm(w) - 1.0) > 1e-6:
                raise ValueError(f"a chain joint's direction must be a unit vector, got {w}")
            if kind == "revolute" and abs(float(w @ params[at + 3:at + 6])) > 1e-6 * max(
                    1.0, np.linalg.norm(params[at + 3:at + 6])):
                raise ValueError("a revolute chain joint's point must be the nearest to the parent's origin")
        return params

    @classmethod
    def canonical(cls, params):
        """Stored parameters (k, q) with every revolute point projected onto its axis' normal plane."""
        out = np.array(params, dtype=float)
        for kind, at in zip(cls.TYPES, cls.STORED_AT, strict=True):
            w = out[:, at:at + 3] / np.linalg.norm(out[:, at:at + 3], axis=1, keepdims=True)
            out[:, at:at + 3] = w
            if kind == "revolute":
                p = out[:, at + 3:at + 6]
                out[:, at + 3:at + 6] = p - np.sum(p * w, axis=1, keepdims=True) * w
        return out

    @classmethod
    def compile(cls, params):
        """A single-sample predictor ``x (d,) -> (4, 4)`` of fixed parameters (q,)."""
        params = np.asarray(params, dtype=float)[None]

        def predict(x):
            return cls.evaluate(params, np.asarray(x, dtype=float)[None, None], twists=False)[0][0, 0]
        return predict

    @classmethod
    def action_derivative(cls, params, x):
        """``dZ/dx_j`` (d, 4, 4) at one sample ``x`` (d,): ``sum_i dq_i/dx_j [Ad_{P_{i-1}} S_i] Z``."""
        params = np.asarray(params, dtype=float)[None]
        x = np.asarray(x, dtype=float)
        screws, M = cls._unpack(params)
        q = cls.joint_values(params, x[None, None])[0, 0]
        P, spatial = np.eye(4), []
        for i, (kind, screw) in enumerate(zip(cls.TYPES, screws, strict=True)):
            spatial.append(_adjoint(P, cls._screw_twist(screw, kind, 1, 1)[0, 0])[:, 0])
            P = P @ screw_transforms(kind, screw, q[None, i:i + 1])[0, 0]
        Z = P @ M[0]
        gain = np.eye(len(cls.TYPES))  # dq_i / dx_j
        for c, (i, j) in enumerate(cls.COUPLINGS):
            gain[i, j] += params[0, cls.COUPLING_STORED_AT + c]
        D = []
        for j in range(len(cls.TYPES)):
            xi = gain[:, j] @ np.array(spatial)
            Dm = np.zeros((4, 4))
            Dm[:3, :3] = skew(xi[:3]) @ Z[:3, :3]
            Dm[:3, 3] = cross3(xi[:3], Z[:3, 3]) + xi[3:]
            D.append(Dm)
        return np.stack(D)


@functools.cache
def chain_form(types, couplings=()):
    """The form (a class) of chains with joint ``types`` (a tuple of ``"revolute"`` / ``"prismatic"``, parent to
    child) and ``couplings`` (a tuple of ``(joint, other joint)`` index pairs); one class per shape, so the joint fit
    groups chains of equal shape."""
    types, couplings = tuple(types), tuple((int(i), int(j)) for i, j in couplings)
    if not 1 <= len(types) <= MAX_CHAIN_JOINTS or any(t not in JOINT_TYPES for t in types):
        raise InvalidInputError(f"a chain has 1 to {MAX_CHAIN_JOINTS} joints of types {sorted(JOINT_TYPES)}, got "
                                f"{list(types)!r:.120}")
    if len(set(couplings)) != len(couplings) or any(
            i == j or not (0 <= i < len(types) and 0 <= j < len(types)) for i, j in couplings):
        raise InvalidInputError(f"couplings must be distinct pairs of two of the chain's {len(types)} joints, got "
                                f"{list(couplings)!r:.120}")
    stored_at = tuple(int(v) for v in np.cumsum([0] + [_STORED[t] for t in types])[:-1])
    params_at = tuple(int(v) for v in np.cumsum([0] + [JOINT_TYPES[t] for t in types])[:-1])
    n_joint_params = sum(JOINT_TYPES[t] for t in types)
    n_params = n_joint_params + len(couplings) + 6
    name = "".join(t[0].upper() for t in types) + "".join(f"_c{i}{j}" for i, j in couplings)
    return type(f"ChainForm_{name}", (_ChainForm,), {
        "TYPES": types, "COUPLINGS": couplings, "STORED_AT": stored_at, "PARAMS_AT": params_at,
        "COUPLING_STORED_AT": sum(_STORED[t] for t in types), "COUPLING_PARAMS_AT": n_joint_params,
        "N_PARAMS": n_params, "N_STORED": sum(_STORED[t] for t in types) + len(couplings) + 6,
        # A 6D observation gives 6 equations: enough samples for the parameters, and one more.
        "MIN_SAMPLES": math.ceil(n_params / 6) + 1})


class ChainModel(RigidJointModel):
    """k one-degree-of-freedom joints between two parts (see the module docstring).

    Parameters
    ----------
    parent, child : int
    actions : tuple of int
        One action per joint, in chain order (parent to child); each at most once.
    types : tuple of str
        ``"revolute"`` or ``"prismatic"`` per joint.
    reference : array-like, shape (k,), optional
        The joints' actions at the reference posture (default: zeros).
    couplings : tuple of (int, int)
        Joint ``i``'s value also follows joint ``j``'s action (module docstring).
    order_evidence : int
        Samples in which several of its joints moved when the chain was identified: with fewer than about two per
        joint their order was not determined by data (a learner then does not freeze it).
    inert_actions : tuple of int
        Actions the identification found not to move the child (their excursions left it still): a model of the same
        pair that uses them besides some of the chain's actions is nested by the chain (the dominance rule).
    sigma_trans, sigma_rot, f_scale : float
        See :class:`~body_scheme_core.models.rigid.RigidJointModel`.
    """

    kind = "chain"
    class_rank = 2

    def __init__(self, parent, child, actions, types, reference=None, couplings=(), order_evidence=0,
                 inert_actions=(), **hyperparameters):
        super().__init__(parent, child, actions, **hyperparameters)
        if isinstance(order_evidence, bool) or not isinstance(order_evidence, int) or order_evidence < 0:
            raise InvalidInputError(f"order_evidence must be a count, got {order_evidence!r}")
        self.order_evidence = order_evidence
        try:
            inert = tuple(sorted({operator.index(a) for a in inert_actions}))
        except TypeError:
            raise InvalidInputError(f"inert_actions must be action indices, got {inert_actions!r:.80}") from None
        if any(a < 0 or a in self.actions for a in inert) or len(inert) > MAX_INERT_ACTIONS:
            raise InvalidInputError(f"inert_actions must be up to {MAX_INERT_ACTIONS} indices >= 0 outside the "
                                    f"chain's actions, got {inert_actions!r:.80}")
        self.inert_actions = inert
        if len(set(self.actions)) != len(self.actions):
            raise InvalidInputError(f"a chain's actions must be distinct, got {self.actions}")
        self.types = tuple(types)
        self.couplings = tuple((int(i), int(j)) for i, j in couplings)
        self.form = chain_form(self.types, self.couplings)
        if len(self.types) != len(self.actions):
            raise InvalidInputError(f"a chain needs one joint type per action, got {len(self.types)} types for "
                                    f"{len(self.actions)} actions")
        reference = np.zeros(len(self.actions)) if reference is None else np.asarray(reference, dtype=float)
        if reference.shape != (len(self.actions),) or not np.all(np.isfinite(reference)):
            raise InvalidInputError(f"reference must be {len(self.actions)} finite action values, got {reference}")
        self.reference = reference

    def screws(self):
        """The fitted joints' screws in the parent frame at the reference posture, in order (revolute ``(w, p)``: the
        unit axis and a point of it; prismatic ``d``: the unit direction), and the reference pose ``M`` (4, 4)."""
        self._check_fitted()
        screws, M = self.form._unpack(self.params_[None])
        return [tuple(s[0] for s in screw) if kind == "revolute" else screw[0]
                for kind, screw in zip(self.types, screws, strict=True)], M[0]

    def _x(self, A):
        """Joint values (n, d) of full action vectors (validated)."""
        return self._select(A) - self.reference

    def predict_one(self, a):
        self._check_fitted()
        return self._one(np.asarray(a, dtype=float)[list(self.actions)] - self.reference)

    def predict(self, A, return_std=False):
        """Predict ``parent2child`` (k, 4, 4) [and the per-axis std (k, 2) propagated from ``param_cov_``]."""
        self._check_fitted()
        x = self._x(A)
        Z, tw = self.form.evaluate(self.params_[None], x[None], twists=return_std)
        if not return_std:
            return Z[0]
        cov6 = tw[0] @ self.param_cov_ @ np.swapaxes(tw[0], 1, 2)
        var_t = np.trace(cov6[:, :3, :3], axis1=1, axis2=2) / 3.0
        var_r = np.trace(cov6[:, 3:, 3:], axis1=1, axis2=2) / 3.0
        return Z[0], np.sqrt(np.maximum(np.stack([var_t, var_r], axis=1), 0.0))

    def jacobian(self, a, eps=None):
        """Analytic ``dZ/da`` (m, 4, 4) at one full action vector ``a``."""
        self._check_fitted()
        a = np.asarray(a, dtype=float).reshape(-1)
        J = np.zeros((a.size, 4, 4))
        J[list(self.actions)] = self.form.action_derivative(self.params_, self._x(a[None])[0])
        return J

    def fit(self, A, Z, sigma=None, start=None):
        """Robust weighted least squares on poses from ``start`` (stored parameters, e.g. from the robot's
        specification or :func:`~body_scheme_core.learning.chain_search.identify_chain`); without one, from the
        chain's parameters if it is fitted already."""
        A, Z = check_observations(A, Z)
        n = Z.shape[0]
        if n < self.form.MIN_SAMPLES:
            raise InvalidInputError(f"{self.describe()} needs at least {self.form.MIN_SAMPLES} samples, got {n}")
        if start is None:
            if not self.is_fitted:
                raise InvalidInputError(f"{self.describe()} needs a start (from the specification or "
                                        "identify_chain): a chain has no closed-form fit")
            start = self.params_
        start = self.form.canonical(np.asarray(start, dtype=float)[None])[0]
        S = _sigmas(sigma, n, (self.sigma_trans, self.sigma_rot))
        params, cov, cost = least_squares_fit(self.form, start, self._x(A), Z, S, self.f_scale)
        return self._set_fit(self.form.canonical(params[None])[0], cov, n, fit_rms(cost, n))

    def _hyperparameters(self):
        return {**super()._hyperparameters(), "types": list(self.types),
                "reference": [float(v) for v in self.reference], "couplings": [list(c) for c in self.couplings],
                "order_evidence": self.order_evidence, "inert_actions": list(self.inert_actions)}

    @classmethod
    def _unfitted_from_dict(cls, data):
        h = dict(data["hyperparameters"])
        types = h.pop("types")
        if not isinstance(types, list) or not all(isinstance(t, str) for t in types):
            raise ModelFileError(f"chain types must be a list of joint types, got {types!r:.80}")
        return cls(data["parent"], data["child"], data["actions"], types, **h)
