"""Rigid-joint local models: a parameter vector, fitted by robust weighted nonlinear least squares on poses.

The static, prismatic and revolute models (their own modules) describe ``Z = parent2child`` by a handful of
parameters with a physical meaning, in the spirit of Sturm's articulation models (rigid, prismatic, rotational).
This module holds what they share:

- the **pose residual** of one sample, in units of its noise::

      r = [(t_pred - t_obs) / s_t,  log(R_obs^T R_pred) / s_r]      (6,)

  with per-axis standard deviations ``s_t`` (m) and ``s_r`` (rad), so position and orientation are weighed by their
  sigmas; its derivative with respect to a parameter increment is the *twist* ``[dt, w]`` of the prediction (a
  translation and a right-multiplied rotation vector, ``R_pred -> R_pred exp([w]x)``), divided by the sigmas. The
  rotational part uses ``d log(R_obs^T R exp(w)) ~ w``, exact at the optimum up to the noise squared (<1 % at 15 deg);
- a **robust loss**, Huber on every residual component with threshold ``f_scale`` (in sigmas), so a mirrored marker
  orientation or a misdetection cannot drag a fit;
- :func:`least_squares_fit`: the fit of one model with ``scipy.optimize.least_squares`` in a local chart around the
  current estimate (re-centred until the step vanishes), and the parameter covariance
  ``(J^T W J)^-1``, inflated by the residual variance when that exceeds the assumed noise;
- :func:`gauss_newton`: the same problem for a stack of models at once (damped Gauss-Newton with iteratively
  re-weighted residuals, pure numpy), used by :class:`~body_scheme_core.models.rigid_batch.RigidBatch` for hundreds of
  candidates per time step and checked against :func:`least_squares_fit` in the tests;
- :class:`RigidJointModel`, the scikit-learn-shaped base class (``fit``, ``predict(return_std)``, ``jacobian``,
  ``to_dict``/``from_dict``) and its parameter interface for the joint fit of the whole body scheme
  (:mod:`body_scheme_core.calibration`): ``params_``, ``param_cov_``, ``retract(delta)``, ``twists(A)``.

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
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError, ModelFileError
from ..transforms import check_transform
from .base import LocalModel, check_action_batch, check_observations

__all__ = [
    "RigidJointModel",
    "pose_residuals",
    "rotation_log",
    "rotvec_matrix",
    "chordal_mean",
    "skew",
    "axis_angle_matrix",
    "perpendicular_basis",
    "huber_weights",
    "gauss_newton",
    "fit_stack",
    "robust_cost",
    "covariance",
    "least_squares_fit",
    "DEFAULT_F_SCALE",
]

#: Huber threshold of the robust loss, in sigmas of one residual component: a component beyond 3 sigma counts
#: linearly instead of quadratically (0.3 % of the components of a correct model under Gaussian noise).
DEFAULT_F_SCALE = 3.0
#: Default per-axis noise of an observed relative transform: the paper's 50 mm / 15 deg 3D RMS per marker.
_SIGMA_TRANS = 0.05 / math.sqrt(3.0)
_SIGMA_ROT = math.radians(15.0) / math.sqrt(3.0)
#: Up to this many action vectors, :meth:`RigidJointModel.predict` loops over its compiled single-sample predictor
#: (cheaper than the vectorised form for so few).
_FEW = 8
#: Levenberg-Marquardt damping of :func:`gauss_newton`, relative to the diagonal of ``J^T W J``, and its floor.
_DAMPING = 1e-3
_DAMPING_FLOOR = 1e-9


def skew(v):
    """Cross-product matrices ``[v]x``, shape (..., 3, 3) for ``v`` of shape (..., 3)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def axis_angle_matrix(u, angle):
    """Rotations about unit axes ``u`` (..., 3) by ``angle`` (..., n): Rodrigues' formula, shape (..., n, 3, 3)."""
    u = np.asarray(u, dtype=float)[..., None, :]
    angle = np.asarray(angle, dtype=float)[..., None, None]
    K = skew(u)
    uu = u[..., :, None] * u[..., None, :]
    return np.cos(angle) * np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * uu


def rotvec_matrix(rotvec):
    """Rotation matrices of rotation vectors (..., 3), shape (..., 3, 3): Rodrigues' formula, vectorised."""
    v = np.asarray(rotvec, dtype=float)
    theta2 = np.sum(v * v, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    # sin(t)/t and (1 - cos(t))/t^2 with their series near 0
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / np.where(small, 1.0, theta))
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / np.where(small, 1.0, theta2))
    # [v]x^2 = v v^T - |v|^2 I
    return a * skew(v) + b * (v[..., :, None] * v[..., None, :]) + (1.0 - b * theta2) * np.eye(3)


#: Rotation angle (rad) beyond which :func:`rotation_log` leaves the closed form for scipy's quaternion route.
_NEAR_PI = 3.0


def rotation_log(R):
    """Rotation vectors of rotation matrices ``R`` (..., 3, 3), shape (..., 3); angles in [0, pi].

    Closed form ``angle / (2 sin angle) vee(R - R^T)`` (vectorised, the hot path of every fit); near pi, where that
    loses precision, scipy's quaternion conversion.
    """
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    if R.size == 0:
        return np.zeros(shape + (3,))
    cos = np.clip((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5, -1.0, 1.0)
    angle = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sqrt(np.maximum(1.0 - cos * cos, 0.0))
    # angle / sin(angle) -> 1 + angle^2 / 6 for small angles
    factor = np.where(angle < 1e-4, 0.5 * (1.0 + angle * angle / 6.0), 0.5 * angle / np.maximum(sin, 1e-300))
    out = v * factor[..., None]
    far = angle > _NEAR_PI
    if np.any(far):
        out[far] = Rotation.from_matrix(R[far].reshape(-1, 3, 3)).as_rotvec()
    return out


def chordal_mean(R, weights):
    """Weighted chordal L2 mean of rotations: the rotation nearest to ``sum w R``, batched.

    Parameters
    ----------
    R : ndarray, shape (k, n, 3, 3)
    weights : ndarray, shape (k, n)

    Returns
    -------
    mean : ndarray, shape (k, 3, 3)
    """
    M = np.einsum("kn,knij->kij", weights, R)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0.0, 1.0, d)
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def perpendicular_basis(u):
    """Two unit vectors ``(e1, e2)`` completing unit ``u`` (..., 3) to a right-handed basis, each (..., 3).

    ``e1`` is the normalised cross product of ``u`` with the coordinate axis least aligned with it, so the basis is a
    smooth function of ``u`` away from the switching points and deterministic everywhere.
    """
    u = np.asarray(u, dtype=float)
    helper = np.zeros_like(u)
    idx = np.argmin(np.abs(u), axis=-1)
    np.put_along_axis(helper, idx[..., None], 1.0, axis=-1)
    e1 = _cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, _cross(u, e1)


def _cross(a, b):
    """``np.cross`` for (..., 3) arrays without its axis bookkeeping (hot path)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def pose_residuals(Z_pred, Z_obs, S):
    """Normalised pose residuals ``[(t_pred - t_obs) / s_t, log(R_obs^T R_pred) / s_r]``, shape (..., 6).

    Parameters
    ----------
    Z_pred, Z_obs : ndarray, shape (..., 4, 4)
    S : ndarray, shape (..., 2)
        Per-axis noise std of each sample: translation (m), rotation (rad).
    """
    dt = (Z_pred[..., :3, 3] - Z_obs[..., :3, 3]) / S[..., 0:1]
    dr = rotation_log(np.swapaxes(Z_obs[..., :3, :3], -1, -2) @ Z_pred[..., :3, :3]) / S[..., 1:2]
    return np.concatenate([dt, dr], axis=-1)


def huber_weights(r, f_scale):
    """IRLS weights of the Huber loss per residual component: 1 inside ``f_scale``, ``f_scale / |r|`` beyond."""
    a = np.abs(r)
    return np.where(a <= f_scale, 1.0, f_scale / np.maximum(a, 1e-300))


def robust_cost(r, f_scale, mask=None):
    """Huber cost ``sum rho(r^2)`` per model of residuals (k, n, 6) (samples outside ``mask`` (k, n) excluded)."""
    a = np.abs(r)
    rho = np.where(a <= f_scale, r * r, 2.0 * f_scale * a - f_scale * f_scale)
    if mask is not None:
        rho = rho * mask[..., None]
    return rho.sum(axis=(-2, -1))


def fit_stack(form, params, x, Z, S, mask, iterations, f_scale=DEFAULT_F_SCALE):
    """Robust fit of a stack of models of one form: closed-form IRLS for linear forms, else :func:`gauss_newton`.

    Returns ``(params, cost)``.
    """
    if not getattr(form, "LINEAR", False):
        params, cost, _ = gauss_newton(form, params, x, Z, S, mask, iterations, f_scale, information=False)
        return params, cost
    w_mask = mask[..., None].astype(float)
    for _ in range(iterations):
        r = pose_residuals(form.transforms(params, x), Z, S)
        params = form.initial(x, Z, S, mask, weights=huber_weights(r, f_scale) * w_mask)
    return params, robust_cost(pose_residuals(form.transforms(params, x), Z, S), f_scale, mask)


def _component_sigmas(S):
    """Per-component sigmas (..., 6) of per-sample ``[s_t, s_r]`` (..., 2)."""
    return np.repeat(S, 3, axis=-1)


def gauss_newton(form, params, x, Z, S, mask, iterations=2, f_scale=DEFAULT_F_SCALE, information=True):
    """Damped Gauss-Newton with Huber re-weighting for a stack of models of one form, all in numpy.

    Parameters
    ----------
    form : module-like
        Provides ``transforms``, ``twists``, ``retract`` and ``N_PARAMS`` (see the module docstring).
    params : ndarray, shape (k, q)
        Current estimates (the form's storage layout).
    x : ndarray, shape (k, n)
        The models' action values per sample (ignored by a static form).
    Z : ndarray, shape (k, n, 4, 4)
    S : ndarray, shape (k, n, 2)
        Per-axis sigmas per sample.
    mask : ndarray of bool, shape (k, n)
        Which samples exist.
    iterations : int
    f_scale : float
    information : bool
        Also return ``J^T W J`` at the result (one more Jacobian evaluation).

    Returns
    -------
    params : ndarray, shape (k, q)
        After the iterations; a step that does not lower a model's robust cost is not taken (that model's damping
        grows instead).
    cost : ndarray, shape (k,)
        Robust cost ``sum rho(r^2)`` at the returned estimates.
    JtWJ : ndarray, shape (k, p, p) or None
        Gauss-Newton information matrix at the returned estimates (for the covariance); None unless
        ``information``.
    """
    p = form.N_PARAMS
    k = x.shape[0]
    w_mask = mask.astype(float)[..., None]
    damping = np.full(k, _DAMPING)
    inv_sigma = 1.0 / _component_sigmas(S)  # (k, n, 6)
    # J = twists / sigma, so J^T W J = twists^T (w / sigma^2) twists and J^T W r = twists^T (w / sigma) r.
    ws2 = (inv_sigma * inv_sigma).reshape(k, -1, 1)

    def evaluate(prm):
        Zp, T = form.evaluate(prm, x)
        r = pose_residuals(Zp, Z, S)
        return r, huber_weights(r, f_scale) * w_mask, robust_cost(r, f_scale, mask), T.reshape(k, -1, p)

    def normal_equations(T, r, w):
        # w (robust weight per component) is zero for missing samples.
        hub = w.reshape(k, -1, 1)
        Tw = np.swapaxes(T * (hub * ws2), 1, 2)
        g = np.swapaxes(T * (hub * inv_sigma.reshape(k, -1, 1)), 1, 2) @ r.reshape(k, -1, 1)
        return Tw @ T, g[..., 0]

    r, w, cost, T = evaluate(params)
    for _ in range(iterations):
        JtWJ, g = normal_equations(T, r, w)
        diag = np.einsum("kpp->kp", JtWJ)
        H = JtWJ + (damping[:, None] * diag + _DAMPING_FLOOR)[:, :, None] * np.eye(p)
        delta = -np.linalg.solve(H, g[..., None])[..., 0]
        trial = form.retract(params, delta)
        r_new, w_new, cost_new, T_new = evaluate(trial)
        better = cost_new <= cost
        params = np.where(better[:, None], trial, params)
        r = np.where(better[:, None, None], r_new, r)
        w = np.where(better[:, None, None], w_new, w)
        T = np.where(better[:, None, None], T_new, T)
        cost = np.where(better, cost_new, cost)
        damping = np.where(better, np.maximum(damping / 3.0, 1e-7), damping * 10.0)
    JtWJ = normal_equations(T, r, w)[0] if information else None
    return params, cost, JtWJ


def fit_rms(cost, n):
    """Root mean square of the whitened residuals of a fit to ``n`` poses (6 residuals each) with robust ``cost``."""
    return math.sqrt(float(cost) / max(6 * int(n), 1))


def covariance(JtWJ, cost, n_residuals, n_params):
    """Parameter covariance ``(J^T W J)^-1``, inflated by ``cost / dof`` when the residuals exceed the assumed noise.

    Parameters
    ----------
    JtWJ : ndarray, shape (..., p, p)
    cost : ndarray, shape (...)
    n_residuals : ndarray of int, shape (...)
    n_params : int

    Returns
    -------
    cov : ndarray, shape (..., p, p)
        Directions the data do not determine (e.g. the axis position of a joint that never moved) get a large but
        finite variance through the pseudo-inverse's floor.
    """
    dof = np.maximum(np.asarray(n_residuals, dtype=float) - n_params, 1.0)
    scale = np.maximum(1.0, np.asarray(cost, dtype=float) / dof)
    cov = np.linalg.pinv(JtWJ + 1e-9 * np.eye(n_params), hermitian=True)
    return cov * np.asarray(scale)[..., None, None]


def least_squares_fit(form, params, x, Z, S, f_scale=DEFAULT_F_SCALE, max_rounds=4):
    """Fit one model of ``form`` with ``scipy.optimize.least_squares`` (trust region, Huber loss).

    The problem is solved for an increment ``delta`` in the local chart ``form.retract(params, delta)``; the chart is
    re-centred on the solution until the increment vanishes (at most ``max_rounds`` times).

    Parameters
    ----------
    form : module-like
    params : ndarray, shape (q,)
        Initial estimate.
    x : ndarray, shape (n,)
    Z : ndarray, shape (n, 4, 4)
    S : ndarray, shape (n, 2)

    Returns
    -------
    params : ndarray, shape (q,)
    cov : ndarray, shape (p, p)
    cost : float
        Robust cost at the solution (sum over components, in sigma units).
    """
    p = form.N_PARAMS
    params = np.asarray(params, dtype=float)
    x1, Z1, S1 = x[None], Z[None], S[None]
    scale = _component_sigmas(S)

    def fun(delta):
        prm = form.retract(params[None], delta[None])
        return pose_residuals(form.transforms(prm, x1), Z1, S1)[0].ravel()

    def jac(delta):
        prm = form.retract(params[None], delta[None])
        tw = form.twists(prm, x1)[0]  # (n, 6, p)
        return (tw / scale[:, :, None]).reshape(-1, p)

    for _ in range(max_rounds):
        result = least_squares(fun, np.zeros(p), jac=jac, loss="huber", f_scale=f_scale, method="trf",
                               x_scale="jac", max_nfev=50)
        params = form.retract(params[None], result.x[None])[0]
        if np.max(np.abs(result.x)) < 1e-9:
            break
    r = pose_residuals(form.transforms(params[None], x1), Z1, S1)[0]
    w = huber_weights(r, f_scale)
    cost = float(robust_cost(r, f_scale))
    J = (form.twists(params[None], x1)[0] / scale[:, :, None]).reshape(-1, p)
    JtWJ = J.T @ (J * w.reshape(-1, 1))
    return params, covariance(JtWJ, cost, r.size, p), cost


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

    @classmethod
    def from_dict(cls, data):
        try:
            if data["kind"] != cls.kind:
                raise ModelFileError(f"expected kind {cls.kind!r}, got {data['kind']!r}")
            model = cls(data["parent"], data["child"], data["actions"], **data["hyperparameters"])
            if "params" in data:
                params = np.asarray(data["params"], dtype=float)
                cov = np.asarray(data["param_cov"], dtype=float)
                form = model.form
                p = form.N_PARAMS
                if params.shape != (form.N_STORED,) or cov.shape != (p, p):
                    raise ModelFileError(f"{cls.kind} model needs params ({form.N_STORED},) and param_cov "
                                         f"({p}, {p}), got {params.shape} and {cov.shape}")
                if not (np.all(np.isfinite(params)) and np.all(np.isfinite(cov))):
                    raise ModelFileError(f"{cls.kind} model parameters contain NaN or inf")
                params = form.validate(params)
                n, rms = int(data["n_samples"]), float(data["rms"])
                if n < 0 or not (math.isfinite(rms) and rms >= 0):
                    raise ModelFileError(f"bad {cls.kind} fit statistics n_samples {n!r}, rms {rms!r}")
                model._set_fit(params, cov, n, rms)
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, InvalidInputError) as exc:
            keys = sorted(data) if isinstance(data, dict) else data
            raise ModelFileError(f"cannot read {cls.kind} model from {keys!r}: {exc}") from exc
        return model


def check_pose_stack(Z, name="Z"):
    """Validated stack of rigid transforms (n, 4, 4)."""
    Z = check_transform(Z, name=name, tolerance=1e-4)
    if Z.ndim != 3:
        raise InvalidInputError(f"{name} must have shape (n, 4, 4), got {Z.shape}")
    return Z
