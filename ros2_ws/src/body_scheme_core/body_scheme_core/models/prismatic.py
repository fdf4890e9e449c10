"""Prismatic local model: the child slides along a fixed direction of the parent frame with one action.

``Z(a) = [R0, p0 + a v]``: constant orientation ``R0``, position ``p0`` at ``a = 0``, and velocity ``v = s u`` (the
unit joint axis ``u`` times the scale ``s`` of the action: metres per command unit). By default the command is the
joint position in metres, ``s = 1`` and ``v`` is the unit axis (:class:`UnitPrismaticForm`, 8 degrees of freedom);
``fit_scale`` fits ``s`` too (:class:`PrismaticForm`, 9). Sturm's prismatic articulation model with the
configuration given by the action.

Parameters (storage layout, 9 numbers): ``p0`` (3), ``R0`` as a rotation vector (3), ``v`` (3). A local increment is
``[dp (3), w (3), dv (3)]`` with ``R0 -> R0 exp([w]x)``. The form is linear in ``p0`` and ``v``, so the closed-form
start (weighted linear least squares) is already the unweighted-loss optimum.
"""

from __future__ import annotations

import numpy as np

from ..rotations import chordal_mean, perpendicular_basis, rotation_log, rotvec_matrix
from .rigid import OneActionJointModel

__all__ = ["PrismaticModel", "PrismaticForm", "UnitPrismaticForm"]


class PrismaticForm:
    """The prismatic form, vectorised over a stack of k models (see :mod:`~body_scheme_core.models.rigid`)."""

    N_PARAMS = 9
    N_STORED = 9
    MIN_SAMPLES = 2
    LINEAR = True
    CLOSED_FORM_CANDIDATE = True

    @staticmethod
    def transforms(params, x):
        """``parent2child`` (k, n, 4, 4) of parameters (k, 9) at action values ``x`` (k, n)."""
        k, n = x.shape
        Z = np.zeros((k, n, 4, 4))
        Z[:, :, :3, :3] = rotvec_matrix(params[:, 3:6])[:, None]
        Z[:, :, :3, 3] = params[:, None, 0:3] + x[..., None] * params[:, None, 6:9]
        Z[:, :, 3, 3] = 1.0
        return Z

    @staticmethod
    def twists(params, x):
        """Twists (k, n, 6, 9): rows ``[dt, w]``, columns the increments ``dp``, ``w``, ``dv``."""
        k, n = x.shape
        T = np.zeros((k, n, 6, 9))
        T[:, :, 0:3, 0:3] = np.eye(3)
        T[:, :, 3:6, 3:6] = np.eye(3)
        T[:, :, 0:3, 6:9] = x[..., None, None] * np.eye(3)
        return T

    @staticmethod
    def evaluate(params, x, twists=True):
        """``(transforms, twists or None)`` at once."""
        return PrismaticForm.transforms(params, x), (PrismaticForm.twists(params, x) if twists else None)

    @staticmethod
    def retract(params, delta):
        """Parameters (k, 9) after increments (k, 9)."""
        out = params + delta
        out[:, 3:6] = rotation_log(rotvec_matrix(params[:, 3:6]) @ rotvec_matrix(delta[:, 3:6]))
        return out

    @staticmethod
    def initial(x, Z, S, mask, weights=None):
        """Chordal mean rotation and weighted linear least squares of ``t = p0 + x v`` per axis, (k, 9).

        ``weights`` (k, n, 6): robust weights per residual component (IRLS); default: the mask.
        """
        w = np.repeat(mask[..., None].astype(float), 6, axis=-1) if weights is None else weights
        wt = w[..., 0:3] / S[..., 0:1] ** 2  # (k, n, 3)
        params = np.zeros((Z.shape[0], 9))
        params[:, 3:6] = rotation_log(chordal_mean(Z[..., :3, :3], w[..., 3:6].mean(axis=-1) / S[..., 1] ** 2))
        # Normal equations of [1, x] per model and axis; a tiny ridge keeps a model whose action never changed
        # solvable.
        t = Z[..., :3, 3]
        xs = x[..., None]
        s0, s1, s2 = wt.sum(axis=1), (wt * xs).sum(axis=1), (wt * xs * xs).sum(axis=1)
        b0, b1 = (wt * t).sum(axis=1), (wt * xs * t).sum(axis=1)
        ridge = 1e-9 * np.maximum(s0, 1e-300)
        det = (s0 + ridge) * (s2 + ridge) - s1 * s1
        params[:, 0:3] = ((s2 + ridge) * b0 - s1 * b1) / det
        params[:, 6:9] = ((s0 + ridge) * b1 - s1 * b0) / det
        return params

    @staticmethod
    def compile(params):
        """A fast single-sample predictor ``x -> (4, 4)`` of fixed parameters (q,)."""
        Z0 = PrismaticForm.transforms(params[None], np.zeros((1, 1)))[0, 0]
        v = params[6:9].copy()

        def predict(x):
            Z = Z0.copy()
            Z[:3, 3] += x * v
            return Z
        return predict

    @staticmethod
    def action_derivative(params, x):
        """``dZ/da`` (4, 4): the velocity in the translation column."""
        D = np.zeros((4, 4))
        D[:3, 3] = params[6:9]
        return D

    @staticmethod
    def validate(params):
        """Stored parameters as they are."""
        return params


class UnitPrismaticForm(PrismaticForm):
    """The prismatic form with unit scale: ``v = u`` is the unit joint axis (actions are joint positions in m).

    Eight degrees of freedom: ``[dp (3), w (3), a1, a2]`` with the axis turned by ``exp([a1 e1 + a2 e2]x)`` in a
    basis ``e1, e2`` perpendicular to it. No longer linear in its parameters, so it is fitted by Gauss-Newton.
    """

    N_PARAMS = 8
    LINEAR = False
    #: Candidates take the closed form (its axis normalised) without iterations; fitted models are refined.
    CLOSED_FORM_CANDIDATE = True

    @staticmethod
    def twists(params, x):
        k, n = x.shape
        e1, e2 = perpendicular_basis(params[:, 6:9])
        T = np.zeros((k, n, 6, 8))
        T[:, :, 0:3, 0:3] = np.eye(3)
        T[:, :, 3:6, 3:6] = np.eye(3)
        # u turned about e1 moves by e1 x u = -e2, about e2 by e2 x u = e1
        T[:, :, 0:3, 6] = -x[..., None] * e2[:, None]
        T[:, :, 0:3, 7] = x[..., None] * e1[:, None]
        return T

    @staticmethod
    def evaluate(params, x, twists=True):
        return PrismaticForm.transforms(params, x), (UnitPrismaticForm.twists(params, x) if twists else None)

    @staticmethod
    def retract(params, delta):
        out = params.copy()
        out[:, 0:3] = params[:, 0:3] + delta[:, 0:3]
        out[:, 3:6] = rotation_log(rotvec_matrix(params[:, 3:6]) @ rotvec_matrix(delta[:, 3:6]))
        e1, e2 = perpendicular_basis(params[:, 6:9])
        u = np.einsum("kij,kj->ki", rotvec_matrix(delta[:, 6:7] * e1 + delta[:, 7:8] * e2), params[:, 6:9])
        out[:, 6:9] = u / np.linalg.norm(u, axis=1, keepdims=True)
        return out

    @staticmethod
    def initial(x, Z, S, mask, weights=None):
        """The free-scale estimate, its velocity normalised to the unit axis, then ``p0`` refitted, (k, 9)."""
        params = PrismaticForm.initial(x, Z, S, mask, weights)
        v = params[:, 6:9]
        norm = np.linalg.norm(v, axis=1, keepdims=True)
        u = np.where(norm > 1e-9, v / np.maximum(norm, 1e-300), [0.0, 0.0, 1.0])
        w = mask.astype(float)[..., None] / S[..., 0:1] ** 2
        params[:, 0:3] = (w * (Z[..., :3, 3] - x[..., None] * u[:, None])).sum(axis=1) / np.maximum(
            w.sum(axis=1), 1e-300)
        params[:, 6:9] = u
        return params

    @staticmethod
    def validate(params):
        if abs(np.linalg.norm(params[6:9]) - 1.0) > 1e-6:
            raise ValueError(f"a unit-scale prismatic joint has a unit axis, got {params[6:9]}")
        return params


class PrismaticModel(OneActionJointModel):
    """One-action prismatic joint ``Z(a) = [R0, p0 + a v]`` (see the module docstring).

    Parameters
    ----------
    parent, child : int
    actions : tuple of int
        Exactly one action index.
    fit_scale : bool
        Fit the scale ``s`` (m per action unit) instead of assuming ``s = 1`` (:class:`UnitPrismaticForm`).
    sigma_trans, sigma_rot, f_scale : float
        See :class:`~body_scheme_core.models.rigid.RigidJointModel`.
    """

    kind = "prismatic"
    form = unit_form = UnitPrismaticForm
    scaled_form = PrismaticForm
    class_rank = 0

    @property
    def axis_(self):
        """Unit joint axis ``u`` in the parent frame (3,)."""
        self._check_fitted()
        v = self.params_[6:9]
        norm = np.linalg.norm(v)
        return v / norm if norm > 0 else np.array([0.0, 0.0, 1.0])

    @property
    def scale_(self):
        """Joint displacement per action unit ``s = |v|`` (m)."""
        self._check_fitted()
        return float(np.linalg.norm(self.params_[6:9]))

    @property
    def origin_(self):
        """``parent2child`` at ``a = 0`` (4, 4)."""
        self._check_fitted()
        return PrismaticForm.transforms(self.params_[None], np.zeros((1, 1)))[0, 0]
