"""Revolute local model: the child turns about a fixed axis line of the parent frame with one action.

``Z(a) = A Rot(z, s a + o) B`` written with parameters that have a physical meaning (Sturm's rotational
articulation model, with the configuration given by the action)::

    R(a) = Rot(u, s a) R0
    t(a) = p0 + (I - Rot(u, s a)) r

- ``u`` (unit, 3): the joint axis in the parent frame; ``s > 0`` its sign is in ``u``;
- ``s``: rad of joint rotation per action unit: 1 when the command is the joint angle (the default,
  :class:`UnitRevoluteForm`, the paper's setting), fitted with ``fit_scale`` (commands in other units, a gear);
- ``p0``, ``R0``: the child's pose at ``a = 0`` (the offset ``o`` is absorbed here);
- ``r`` (3, perpendicular to ``u``): from the child's origin at ``a = 0`` to the nearest point of the axis, so the
  axis passes through ``p0 + r`` and the child's origin circles it at radius ``|r|``.

Storage layout (13 numbers): ``u`` (3), ``r`` (3), ``p0`` (3), ``R0`` as a rotation vector (3), ``s`` (1); 11
degrees of freedom (10 with ``s = 1``). A local increment is ``[w1, w2, rho1, rho2, dp (3), w (3), ds]``: the axis
(and ``r`` with it) turned by ``exp([w1 e1 + w2 e2]x)``, ``r -> r + rho1 e1 + rho2 e2`` in a basis ``e1, e2``
perpendicular to ``u``, ``p0 -> p0 + dp``, ``R0 -> R0 exp([w]x)``, ``s -> s + ds``.

The closed-form start: the axis direction and scale from the rotations (``log(R_k R_ref^T) = u s (a_k - a_ref)``,
least squares), ``R0`` as a chordal mean, then ``p0`` and ``r`` by linear least squares (the translation is linear in
them once ``u`` and ``s`` are known), with a weak prior on the radius (``_RADIUS_PRIOR`` m) so that a joint that barely
moved its child cannot produce a huge one.
"""

from __future__ import annotations

import math

import numpy as np

from ..rotations import axis_angle_matrix, chordal_mean, cross3, perpendicular_basis, rotation_log, rotvec_matrix, skew
from .rigid import OneActionJointModel

__all__ = ["RevoluteModel", "RevoluteForm", "UnitRevoluteForm"]

#: Action differences (rad at s = 1) used for the axis estimate stay below this, so rotation vectors do not wrap.
_MAX_ANGLE = 2.5
#: Std (m) of the weak zero-mean prior on the radius vector in the closed-form start.
_RADIUS_PRIOR = 2.0
#: Scale below which the axis is undetermined (the action does not turn the child).
_MIN_SCALE = 1e-6


class RevoluteForm:
    """The revolute form, vectorised over a stack of k models (see :mod:`~body_scheme_core.models.rigid`)."""

    N_PARAMS = 11
    N_STORED = 13
    MIN_SAMPLES = 3

    @staticmethod
    def _unpack(params):
        return params[:, 0:3], params[:, 3:6], params[:, 6:9], params[:, 9:12], params[:, 12]

    @staticmethod
    def transforms(params, x):
        """``parent2child`` (k, n, 4, 4) of parameters (k, 13) at action values ``x`` (k, n)."""
        return RevoluteForm.evaluate(params, x, twists=False)[0]

    @staticmethod
    def twists(params, x):
        """Twists (k, n, 6, 11): rows ``[dt, w]``, one column per increment (module docstring)."""
        return RevoluteForm.evaluate(params, x)[1]

    @staticmethod
    def evaluate(params, x, twists=True):
        """``(transforms (k, n, 4, 4), twists (k, n, 6, 11) or None)``, sharing the joint rotations."""
        u, r, p0, w0, s = RevoluteForm._unpack(params)
        k, n = x.shape
        Rot = axis_angle_matrix(u, s[:, None] * x)  # (k, n, 3, 3)
        R0 = rotvec_matrix(w0)[:, None]  # (k, 1, 3, 3)
        Rot_r = (Rot @ r[:, None, :, None])[..., 0]  # (k, n, 3)
        arm = r[:, None] - Rot_r  # (I - Rot) r
        Z = np.zeros((k, n, 4, 4))
        Z[..., :3, :3] = Rot @ R0
        Z[..., :3, 3] = p0[:, None] + arm
        Z[..., 3, 3] = 1.0
        if not twists:
            return Z, None
        e1, e2 = perpendicular_basis(u)
        E = np.stack([e1, e2], axis=-1)[:, None]  # (k, 1, 3, 2)
        R0t = np.swapaxes(R0, -1, -2)
        RotT = np.swapaxes(Rot, -1, -2)
        T = np.zeros((k, n, 6, 11))
        T[..., 0:3, 0] = cross3(e1[:, None], arm)  # e x arm
        T[..., 0:3, 1] = cross3(e2[:, None], arm)
        T[..., 3:6, 0:2] = R0t @ (RotT @ E - E)  # R0^T (Rot^T - I) e
        T[..., 0:3, 2:4] = E - Rot @ E  # (I - Rot) e
        T[..., 0:3, 4:7] = np.eye(3)
        T[..., 3:6, 7:10] = np.eye(3)
        T[..., 0:3, 10] = -x[..., None] * cross3(u[:, None], Rot_r)
        T[..., 3:6, 10] = x[..., None] * (R0t @ (RotT @ u[:, None, :, None]))[..., 0]
        return Z, T

    @staticmethod
    def retract(params, delta):
        """Parameters (k, 13) after increments (k, 11)."""
        u, r, p0, w0, s = RevoluteForm._unpack(params)
        e1, e2 = perpendicular_basis(u)
        E = rotvec_matrix(delta[:, 0:1] * e1 + delta[:, 1:2] * e2)
        out = np.empty_like(params)
        u_new = np.einsum("kij,kj->ki", E, u)
        out[:, 0:3] = u_new / np.linalg.norm(u_new, axis=1, keepdims=True)
        r_new = np.einsum("kij,kj->ki", E, r + delta[:, 2:3] * e1 + delta[:, 3:4] * e2)
        # Remove the round-off component along the axis so that r stays perpendicular to it.
        out[:, 3:6] = r_new - np.sum(r_new * out[:, 0:3], axis=1, keepdims=True) * out[:, 0:3]
        out[:, 6:9] = p0 + delta[:, 4:7]
        out[:, 9:12] = rotation_log(rotvec_matrix(w0) @ rotvec_matrix(delta[:, 7:10]))
        out[:, 12] = s + delta[:, 10]
        return out

    @staticmethod
    def axis_estimate(x, Z, S, mask, unit=False):
        """Axis ``u`` (k, 3) and scale ``s`` (k,) from the rotations: ``log(R_k R_ref^T) = u s (a_k - a_ref)``. With
        ``unit`` (``s = 1``: the actions are angles) the differences are taken modulo a turn, so that a joint swept
        over more than a turn (a wrist at -360 and +216 deg) still shows its axis."""
        k, n = x.shape
        w = mask.astype(float)
        ref = np.argmax(mask, axis=1)  # the first sample of each model
        rows = np.arange(k)
        R = Z[..., :3, :3]
        dx = x - x[rows, ref][:, None]
        if unit:
            dx = (dx + math.pi) % (2 * math.pi) - math.pi
        rv = rotation_log(R @ np.swapaxes(R[rows, ref], -1, -2)[:, None])  # (k, n, 3)
        use = w * (np.abs(dx) <= _MAX_ANGLE) / S[..., 1] ** 2
        v = np.einsum("kn,kn,kni->ki", use, dx, rv) / np.maximum(np.einsum("kn,kn->k", use, dx * dx), 1e-300)[:, None]
        s = np.linalg.norm(v, axis=1)
        turning = s > _MIN_SCALE
        u = np.where(turning[:, None], v / np.maximum(s, 1e-300)[:, None], [0.0, 0.0, 1.0])
        return u, np.where(turning, s, _MIN_SCALE)

    @staticmethod
    def solve_given_axis(u, s, x, Z, S, mask):
        """``R0`` (chordal mean) and ``p0``, ``r`` (linear least squares, weak radius prior) for given ``u``, ``s``;
        parameters (k, 13)."""
        k, n = x.shape
        w = mask.astype(float)
        Rot = axis_angle_matrix(u, s[:, None] * x)
        R0 = chordal_mean(np.swapaxes(Rot, -1, -2) @ Z[..., :3, :3], w / S[..., 1] ** 2)
        # t_k = p0 + (I - Rot_k) B rho: weighted linear least squares in (p0, rho) with a weak prior on rho.
        e1, e2 = perpendicular_basis(u)
        B = np.stack([e1, e2], axis=-1)  # (k, 3, 2)
        D = np.zeros((k, n, 3, 5))
        D[..., 0:3] = np.eye(3)
        D[..., 3:5] = np.einsum("knij,kjl->knil", np.eye(3) - Rot, B)
        wt = w / S[..., 0] ** 2
        H = np.einsum("kn,knia,knib->kab", wt, D, D)
        H[:, 3:5, 3:5] += np.eye(2) / _RADIUS_PRIOR**2
        g = np.einsum("kn,knia,kni->ka", wt, D, Z[..., :3, 3])
        sol = np.linalg.solve(H + 1e-12 * np.eye(5), g[..., None])[..., 0]
        params = np.empty((k, 13))
        params[:, 0:3] = u
        params[:, 3:6] = np.einsum("kia,ka->ki", B, sol[:, 3:5])
        params[:, 6:9] = sol[:, 0:3]
        params[:, 9:12] = rotation_log(R0)
        params[:, 12] = s
        return params

    @classmethod
    def initial(cls, x, Z, S, mask):
        """Closed-form start (module docstring), (k, 13)."""
        u, s = cls.axis_estimate(x, Z, S, mask)
        return cls.solve_given_axis(u, s, x, Z, S, mask)

    @staticmethod
    def compile(params):
        """A fast single-sample predictor ``x -> (4, 4)`` of fixed parameters (13,): Rodrigues' formula on cached
        ``[u]x``, ``R0``, ``r``, ``p0``."""
        u, r, p0, w0, s = params[0:3], params[3:6], params[6:9], params[9:12], float(params[12])
        K = skew(u)
        K2 = K @ K
        R0 = rotvec_matrix(w0)
        pr = p0 + r
        eye = np.eye(3)

        def predict(x):
            angle = s * x
            Rot = eye + math.sin(angle) * K + (1.0 - math.cos(angle)) * K2
            Z = np.eye(4)
            Z[:3, :3] = Rot @ R0
            Z[:3, 3] = pr - Rot @ r
            return Z
        return predict

    @staticmethod
    def action_derivative(params, x):
        """``dZ/da`` (4, 4) at one action value ``x``: ``s [u]x R`` and ``-s u x (Rot r)``."""
        u, r, _, w0, s = RevoluteForm._unpack(params[None])
        Rot = axis_angle_matrix(u, s[:, None] * np.array([[x]]))[0, 0]
        D = np.zeros((4, 4))
        D[:3, :3] = s[0] * skew(u[0]) @ Rot @ rotvec_matrix(w0[0])
        D[:3, 3] = -s[0] * cross3(u[0], Rot @ r[0])
        return D

    #: Signs of the increment components when the axis is flipped (``e1``, ``rho1`` and ``ds`` change sign).
    FLIP = np.array([-1.0, 1.0, -1.0, 1.0, 1, 1, 1, 1, 1, 1, -1.0])

    @staticmethod
    def canonical(params):
        """The same joint with ``s >= 0`` (axis flipped where the scale was negative), (k, 13), and the flip mask."""
        out = params.copy()
        flip = out[:, 12] < 0
        out[flip, 0:3] *= -1.0
        out[flip, 12] *= -1.0
        return out, flip

    @staticmethod
    def validate(params):
        """Stored parameters with a unit axis and ``r`` perpendicular to it; raises ValueError otherwise."""
        u, r = params[0:3], params[3:6]
        if abs(np.linalg.norm(u) - 1.0) > 1e-6 or abs(float(u @ r)) > 1e-6 * max(1.0, np.linalg.norm(r)):
            raise ValueError(f"revolute axis must be a unit vector perpendicular to r, got u {u}, r {r}")
        return params


class UnitRevoluteForm(RevoluteForm):
    """The revolute form with the scale fixed at ``s = 1``: actions are joint angles in rad (the paper's setting).

    Ten degrees of freedom: the increment of :class:`RevoluteForm` without ``ds``.
    """

    N_PARAMS = 10

    @staticmethod
    def evaluate(params, x, twists=True):
        Z, T = RevoluteForm.evaluate(params, x, twists)
        return Z, (None if T is None else T[..., :10])

    @staticmethod
    def twists(params, x):
        return UnitRevoluteForm.evaluate(params, x)[1]

    @staticmethod
    def transforms(params, x):
        return RevoluteForm.evaluate(params, x, twists=False)[0]

    @staticmethod
    def retract(params, delta):
        return RevoluteForm.retract(params, np.concatenate([delta, np.zeros((delta.shape[0], 1))], axis=1))

    @classmethod
    def initial(cls, x, Z, S, mask):
        u, _ = cls.axis_estimate(x, Z, S, mask, unit=True)
        return cls.solve_given_axis(u, np.ones(x.shape[0]), x, Z, S, mask)

    @staticmethod
    def validate(params):
        if abs(params[12] - 1.0) > 1e-12:
            raise ValueError(f"a unit-scale revolute joint has s = 1, got {params[12]}")
        return RevoluteForm.validate(params)


class RevoluteModel(OneActionJointModel):
    """One-action revolute joint (see the module docstring).

    Parameters
    ----------
    parent, child : int
    actions : tuple of int
        Exactly one action index.
    fit_scale : bool
        Fit the scale ``s`` (rad of joint rotation per action unit) instead of assuming ``s = 1``
        (:class:`UnitRevoluteForm`).
    sigma_trans, sigma_rot, f_scale : float
        See :class:`~body_scheme_core.models.rigid.RigidJointModel`.
    """

    kind = "revolute"
    form = unit_form = UnitRevoluteForm
    scaled_form = RevoluteForm
    class_rank = 1

    def _set_fit(self, params, cov, n, rms):
        if self.fit_scale:
            params, flip = RevoluteForm.canonical(np.asarray(params, dtype=float)[None])
            if flip[0]:  # the increment basis of -u is (-e1, e2), and s changes sign
                cov = np.asarray(cov) * np.outer(RevoluteForm.FLIP, RevoluteForm.FLIP)
            params = params[0]
        return super()._set_fit(params, cov, n, rms)

    @property
    def axis_(self):
        """Unit joint axis ``u`` in the parent frame (3,)."""
        self._check_fitted()
        return self.params_[0:3].copy()

    @property
    def axis_point_(self):
        """The point of the axis nearest to the child's origin at ``a = 0``, ``p0 + r`` (3,)."""
        self._check_fitted()
        return self.params_[6:9] + self.params_[3:6]

    @property
    def scale_(self):
        """Joint rotation per action unit ``s`` (rad)."""
        self._check_fitted()
        return float(self.params_[12])

    @property
    def origin_(self):
        """``parent2child`` at ``a = 0`` (4, 4)."""
        self._check_fitted()
        return RevoluteForm.transforms(self.params_[None], np.zeros((1, 1)))[0, 0]
