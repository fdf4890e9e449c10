"""Rigid-joint local models: a parameter vector, fitted by robust weighted nonlinear least squares on poses.

The static, prismatic and revolute models (their own modules) describe ``Z = parent2child`` by a handful of
parameters with a physical meaning, in the spirit of Sturm's articulation models (rigid, prismatic, rotational).
This module holds their base class; the fit itself (pose residuals, the robust loss, :func:`least_squares_fit` and
the stacked :func:`gauss_newton`) is :mod:`~body_scheme_core.models.rigid_fit`, and the rotation math
(``rotation_log``, ``rotvec_matrix``, ...) is in :mod:`~body_scheme_core.transforms`.

- :class:`RigidJointModel`, the scikit-learn-shaped base class (``fit``, ``predict(return_std)``, ``jacobian``,
  ``to_dict``/``from_dict``) and its parameter interface for the joint fit of the whole body scheme
  (:mod:`body_scheme_core.calibration.joint_fit`): ``params_``, ``param_cov_``, ``retract(delta)``, ``twists(A)``.

Each model class has a *form*: a class of static functions vectorised over a stack of k models (``params`` (k, q)
in the form's storage layout, action values ``x`` (k, n)): ``transforms(params, x) -> (k, n, 4, 4)``,
``twists(params, x) -> (k, n, 6, p)`` (rows ``[dt, w]``, one column per increment), ``evaluate(params, x,
twists=True)`` (both at once; the twists None without), ``retract(params, delta)``, ``initial(x, Z, S, mask)`` (a
closed-form first estimate), ``action_derivative`` and ``validate``, with the constants ``N_PARAMS`` (p),
``N_STORED`` (q) and ``MIN_SAMPLES``.
"""

from __future__ import annotations

import copy
import math
from typing import ClassVar

import numpy as np

from ..errors import InvalidInputError, ModelFileError
from ..limits import MAX_COORDINATE
from ..state_values import covariance, finite_array, integer, number
from ..transforms import check_transform
from .base import LocalModel, check_action_batch, check_observations
from .rigid_fit import DEFAULT_F_SCALE, fit_rms, least_squares_fit

__all__ = ["RigidJointModel", "OneActionJointModel", "check_pose_stack"]

#: Default per-axis noise of an observed relative transform: the paper's 50 mm / 15 deg 3D RMS per marker.
_SIGMA_TRANS = 0.05 / math.sqrt(3.0)
_SIGMA_ROT = math.radians(15.0) / math.sqrt(3.0)
#: Up to this many action vectors, :meth:`RigidJointModel.predict` loops over its compiled single-sample predictor
#: (cheaper than the vectorised form for so few).
_FEW = 8


def _sigmas(S, n, default):
    """Per-sample sigmas (n, 2) from ``None`` (the model's defaults), a pair, or an (n, 2) array."""
    if S is None:
        S = default
    S = np.asarray(S, dtype=float)
    if S.shape == (2,):
        S = np.broadcast_to(S, (n, 2))
    if S.shape != (n, 2) or not np.all(np.isfinite(S)) or np.any(S <= 0):
        raise InvalidInputError(f"sigma must be a pair or shape ({n}, 2) of finite values > 0, got shape {S.shape}")
    return np.array(S)


class RigidJointModel(LocalModel):
    """Base of the parametric local models (static, prismatic, revolute).

    Parameters
    ----------
    parent, child : int
    actions : tuple of int
        ``()`` for a static model, one action for a joint.
    sigma_trans, sigma_rot : float
        Default per-axis noise std of an observed ``Z`` (m, rad), used when ``fit`` gets no per-sample sigmas.
    f_scale : float
        Huber threshold in sigmas.

    Attributes
    ----------
    params_ : ndarray, shape (q,)
        The form's parameters (storage layout of its module).
    param_cov_ : ndarray, shape (p, p)
        Covariance of a parameter increment in the local chart at ``params_``.
    n_samples_ : int
        Samples of the last fit.
    rms_ : float
        Root mean square normalised residual of the last fit (about 1 when the noise model holds).
    """

    #: The model's form (see the module docstring); a class attribute, replaced per instance where a hyperparameter
    #: (``fit_scale``) selects among variants.
    form: ClassVar = None
    #: Rank of the class within its complexity layer: the structure search prefers lower ranks (fewer parameters).
    class_rank: ClassVar[int] = 0

    def __init__(self, parent, child, actions=(), sigma_trans=_SIGMA_TRANS, sigma_rot=_SIGMA_ROT,
                 f_scale=DEFAULT_F_SCALE):
        super().__init__(parent, child, actions)
        for name, value in (("sigma_trans", sigma_trans), ("sigma_rot", sigma_rot), ("f_scale", f_scale)):
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not (
                    math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be a finite number > 0, got {value!r}")
        self.sigma_trans = float(sigma_trans)
        self.sigma_rot = float(sigma_rot)
        self.f_scale = float(f_scale)

    # ------------------------------------------------------------------ estimator API
    @property
    def n_params(self):
        """Degrees of freedom of the form (length of a parameter increment)."""
        return self.form.N_PARAMS

    @property
    def is_fitted(self):
        return hasattr(self, "params_")

    def _x(self, A):
        """The model's action values (k,) of full action vectors (validated); zeros for a static model."""
        A = check_action_batch(A)
        if not self.actions:
            return np.zeros(A.shape[0])
        return self._select(A)[:, 0]

    def form_input(self, A):
        """What the form evaluates at for full action vectors ``A`` (n, m): per sample the model's action value
        (n,), or for a chain its joints' (n, d) (:mod:`~body_scheme_core.calibration.joint_fit` stacks them)."""
        return self._x(A)

    def fit(self, A, Z, sigma=None):
        """Robust weighted least squares on poses (:func:`least_squares_fit`) from a closed-form start.

        Parameters
        ----------
        A : array-like, shape (n, m)
        Z : array-like, shape (n, 4, 4)
        sigma : array-like, shape (2,) or (n, 2), optional
            Per-axis noise std of each sample (trans m, rot rad); default ``(sigma_trans, sigma_rot)``.

        Returns
        -------
        self
        """
        A, Z = check_observations(A, Z)
        n = Z.shape[0]
        if n < self.form.MIN_SAMPLES:
            raise InvalidInputError(f"{self.describe()} needs at least {self.form.MIN_SAMPLES} samples, got {n}")
        S = _sigmas(sigma, n, (self.sigma_trans, self.sigma_rot))
        x = self._x(A)
        start = self.form.initial(x[None], Z[None], S[None], np.ones((1, n), dtype=bool))[0]
        params, cov, cost = least_squares_fit(self.form, start, x, Z, S, self.f_scale)
        return self._set_fit(params, cov, n, fit_rms(cost, n))

    def _set_fit(self, params, cov, n, rms):
        self.params_ = np.array(params, dtype=float)  # copies: never a view into a batch's storage
        self.param_cov_ = np.array(cov, dtype=float)
        self._one = self.form.compile(self.params_)  # fast path of predict for one action vector
        self.n_samples_ = int(n)
        self.rms_ = float(rms)
        return self

    def with_params(self, params, cov=None):
        """A copy with other parameters (and covariance); e.g. from the joint fit of the body scheme."""
        model = copy.copy(self)
        cov = self.param_cov_ if cov is None else cov
        return model._set_fit(params, cov, self.n_samples_, self.rms_)

    def retract(self, delta):
        """Parameters after a local increment ``delta`` (p,), storage layout."""
        self._check_fitted()
        return self.form.retract(self.params_[None], np.asarray(delta, dtype=float)[None])[0]

    def twists(self, A):
        """Derivative of the prediction w.r.t. a parameter increment as twists ``[dt, w]``, shape (k, 6, p)."""
        self._check_fitted()
        return self.form.twists(self.params_[None], self._x(A)[None])[0]

    def evaluate(self, A):
        """``(predict(A), twists(A))`` at once, sharing their intermediate results: (k, 4, 4) and (k, 6, p)."""
        self._check_fitted()
        Z, T = self.form.evaluate(self.params_[None], self._x(A)[None])
        return Z[0], T[0]

    def predict_one(self, a):
        self._check_fitted()
        return self._one(a[self.actions[0]] if self.actions else 0.0)

    def predict(self, A, return_std=False):
        """Predict ``parent2child`` (k, 4, 4) [and the per-axis std (k, 2) propagated from ``param_cov_``]."""
        self._check_fitted()
        if not return_std:
            A = np.asarray(A, dtype=float)
            if A.ndim == 2 and A.shape[0] <= _FEW and np.all(np.isfinite(A)):
                # A few action vectors (prediction, and IK's forward differences): the compiled predictor.
                if self.actions and A.shape[1] <= self.actions[0]:
                    self._select(A)  # raises the usual error
                values = A[:, self.actions[0]] if self.actions else np.zeros(A.shape[0])
                return np.stack([self._one(x) for x in values])
        x = self._x(A)
        Z = self.form.transforms(self.params_[None], x[None])[0]
        if not return_std:
            return Z
        tw = self.form.twists(self.params_[None], x[None])[0]  # (k, 6, p)
        cov6 = tw @ self.param_cov_ @ np.swapaxes(tw, 1, 2)
        var_t = np.trace(cov6[:, :3, :3], axis1=1, axis2=2) / 3.0
        var_r = np.trace(cov6[:, 3:, 3:], axis1=1, axis2=2) / 3.0
        return Z, np.sqrt(np.maximum(np.stack([var_t, var_r], axis=1), 0.0))

    def jacobian(self, a, eps=None):
        """Analytic ``dZ/da`` (m, 4, 4) at one full action vector ``a``; ``eps`` is ignored."""
        self._check_fitted()
        A = check_action_batch(a)
        J = np.zeros((A.shape[1], 4, 4))
        if self.actions:
            J[self.actions[0]] = self.form.action_derivative(self.params_, self._x(A)[0])
        return J

    # ------------------------------------------------------------------ persistence
    def _hyperparameters(self):
        return {"sigma_trans": self.sigma_trans, "sigma_rot": self.sigma_rot, "f_scale": self.f_scale}

    def to_dict(self):
        data = {"kind": self.kind, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "hyperparameters": self._hyperparameters()}
        if self.is_fitted:
            data.update({"params": self.params_.tolist(), "param_cov": self.param_cov_.tolist(),
                         "n_samples": self.n_samples_, "rms": self.rms_})
        return data

    def read_params(self, params, cov, name):
        """``(params, cov)`` of this model's form read from a state file: parameters in the storage layout
        (``N_STORED``, within :data:`~body_scheme_core.limits.MAX_COORDINATE`, valid for the form) and the
        covariance of a local increment (``N_PARAMS`` square); ``ModelFileError`` otherwise."""
        form = self.form
        params = finite_array(params, (form.N_STORED,), f"{name} params")
        if np.abs(params).max(initial=0.0) > MAX_COORDINATE:
            raise ModelFileError(f"{name} parameters beyond {MAX_COORDINATE:g} (m, rad or scale)")
        try:
            params = form.validate(params)
        except (ValueError, InvalidInputError) as exc:
            raise ModelFileError(f"{name} params: {exc}") from None
        return params, covariance(cov, form.N_PARAMS, f"{name} param_cov")

    @classmethod
    def from_dict(cls, data):
        try:
            model = cls._unfitted_from_dict(data)
            if "params" in data:
                params, cov = model.read_params(data["params"], data["param_cov"], f"{cls.kind} model")
                n, rms = integer(data["n_samples"], "n_samples"), number(data["rms"], "rms", 0.0)
                model._set_fit(params, cov, n, rms)
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, InvalidInputError) as exc:
            keys = sorted(data) if isinstance(data, dict) else data
            raise ModelFileError(f"cannot read {cls.kind} model from {keys!r}: {exc}") from exc
        return model


class OneActionJointModel(RigidJointModel):
    """A joint driven by exactly one action, its scale assumed 1 or fitted (``fit_scale``): prismatic, revolute.

    Subclasses name their two forms, ``unit_form`` (``s = 1``) and ``scaled_form``.
    """

    unit_form: ClassVar[type]
    scaled_form: ClassVar[type]

    def __init__(self, parent, child, actions, fit_scale=False, **hyperparameters):
        super().__init__(parent, child, actions, **hyperparameters)
        if len(self.actions) != 1:
            raise InvalidInputError(f"a {self.kind} model depends on exactly one action, got {self.actions!r}")
        self.fit_scale = bool(fit_scale)
        self.form = self.form_for(self.fit_scale)

    @classmethod
    def form_for(cls, fit_scale):
        """The form with or without the scale."""
        return cls.scaled_form if fit_scale else cls.unit_form

    def _hyperparameters(self):
        return {**super()._hyperparameters(), "fit_scale": self.fit_scale}


def check_pose_stack(Z, name="Z"):
    """Validated stack of rigid transforms (n, 4, 4)."""
    Z = check_transform(Z, name=name, tolerance=1e-4)
    if Z.ndim != 3:
        raise InvalidInputError(f"{name} must have shape (n, 4, 4), got {Z.shape}")
    return Z
