"""Fitting rigid-joint models: robust weighted nonlinear least squares on poses.

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
  its step is :mod:`body_scheme_core.levenberg_marquardt`'s, as the joint fit's.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from ..levenberg_marquardt import INITIAL_DAMPING, damped_increment, next_damping
from ..rotations import rotation_log

__all__ = ["pose_residuals", "huber_weights", "robust_cost", "fit_stack", "gauss_newton", "fit_rms", "covariance",
           "least_squares_fit", "DEFAULT_F_SCALE"]

#: Huber threshold of the robust loss, in sigmas of one residual component: a component beyond 3 sigma counts
#: linearly instead of quadratically (0.3 % of the components of a correct model under Gaussian noise).
DEFAULT_F_SCALE = 3.0
#: :func:`gauss_newton`'s smallest damping, and the constant it adds to the diagonal.
_DAMPING_MIN = 1e-7
_DAMPING_FLOOR = 1e-9


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
    damping = np.full(k, INITIAL_DAMPING)
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
        delta = damped_increment(JtWJ, g, damping, _DAMPING_FLOOR)
        trial = form.retract(params, delta)
        r_new, w_new, cost_new, T_new = evaluate(trial)
        better = cost_new <= cost
        params = np.where(better[:, None], trial, params)
        r = np.where(better[:, None, None], r_new, r)
        w = np.where(better[:, None, None], w_new, w)
        T = np.where(better[:, None, None], T_new, T)
        cost = np.where(better, cost_new, cost)
        damping = next_damping(better, damping, _DAMPING_MIN)
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
