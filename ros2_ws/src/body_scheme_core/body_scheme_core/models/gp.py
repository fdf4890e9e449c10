"""Gaussian-process local models (paper Sec. III-B) and the batched incremental engine used for bootstrapping.

A GP local model regresses the 12 free components of ``Z = parent2child``, ``[R (row-major, 9), t (3)]``, on the
actions it depends on, each component independently (the paper's simplification). The prediction is mapped back
onto SE(3) by the nearest rotation in the Frobenius norm (the paper's "normalisation step").

Parametrisation (all hyperparameters fixed, no marginal-likelihood optimisation, so that models stay comparable
and cheap to update online):

- kernel ``k(a, a') = s_o^2 exp(-|a - a'|^2 / (2 l^2))`` over the model's actions, one length scale ``l`` (rad);
- prior mean per output = the mean of that output over the training set (constant mean, recomputed as data
  arrive), so a GP far from its data predicts the training mean;
- signal std ``s_o``: ``signal_std_rot`` for the nine rotation-matrix entries, ``signal_std_trans`` (m) for the
  three translations;
- white observation noise ``n_o``: ``noise_std_rot`` (matrix entries), ``noise_std_trans`` (m).

Only the ratio ``r_o = n_o / s_o`` enters the posterior mean: ``mu = ybar + k*^T (K + r^2 I)^-1 (y - ybar)`` with the
unit-amplitude kernel ``K``. When the translational and rotational ratios are equal, ONE factorisation per model
serves all 12 outputs; :meth:`GPHyperparameters.from_config` makes them equal (see its docstring). Unequal
ratios are supported, at twice the cost.

Uncertainty: ``predict(..., return_std=True)`` returns the latent (noise-free) predictive std, summarised per
sample as a per-axis translational std (m) and a per-axis rotational std (rad); see :func:`summarise_std`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from ..config import BodySchemeConfig
from ..errors import BodySchemeError, InvalidInputError, ModelFileError
from ..transforms import check_transform, project_to_rotation, transform_from_vector12, vector12_from_transform
from .base import LocalModel, check_actions, check_observations

__all__ = [
    "squared_exponential",
    "squared_exponential_gradient",
    "polar_derivative",
    "summarise_std",
    "GPHyperparameters",
    "log_marginal_likelihood",
    "marginal_likelihood_hyperparameters",
    "GPModel",
    "GPBatch",
]

#: Index of the rotation-matrix outputs and of the translation outputs in the 12-vector.
ROT_OUTPUTS = slice(0, 9)
TRANS_OUTPUTS = slice(9, 12)
#: Per-axis rotation std (rad) of a small random rotation whose matrix entries have std 1: E|[w]x R|_F^2 = 6 s^2
#: spread over 9 entries gives an entry variance of (2/3) s^2.
ROT_STD_PER_ENTRY_STD = math.sqrt(1.5)


def squared_exponential(X1, X2, length_scale):
    """Unit-amplitude squared-exponential kernel ``exp(-|x1 - x2|^2 / (2 l^2))``, batched over leading dims.

    Parameters
    ----------
    X1 : array-like, shape (..., n1, d)
    X2 : array-like, shape (..., n2, d)
    length_scale : float

    Returns
    -------
    K : ndarray, shape (..., n1, n2)
    """
    X1 = np.asarray(X1, dtype=float)
    X2 = np.asarray(X2, dtype=float)
    diff = X1[..., :, None, :] - X2[..., None, :, :]
    return np.exp(-0.5 / length_scale**2 * np.sum(diff * diff, axis=-1))


def squared_exponential_gradient(x, X, length_scale):
    """Gradient of ``k(x, X_i)`` with respect to ``x``, batched over leading dims.

    Parameters
    ----------
    x : array-like, shape (..., d)
    X : array-like, shape (..., n, d)
    length_scale : float

    Returns
    -------
    dk : ndarray, shape (..., n, d)
    """
    x = np.asarray(x, dtype=float)
    X = np.asarray(X, dtype=float)
    diff = x[..., None, :] - X
    k = np.exp(-0.5 / length_scale**2 * np.sum(diff * diff, axis=-1))
    return -(k[..., None] / length_scale**2) * diff


def polar_derivative(M, dM):
    """Derivative of ``R = project_to_rotation(M)`` in the direction(s) ``dM``.

    With the signed SVD ``M = U' S' V^T`` used by the projection (``R = U' V^T``, last singular value negated when
    the determinant had to be fixed), ``dR = U' Omega V^T`` where ``Omega`` is skew with
    ``Omega_ij = (W_ij - W_ji) / (s'_i + s'_j)`` and ``W = U'^T dM V``. This is exact (no finite differences).

    Parameters
    ----------
    M : array-like, shape (3, 3)
    dM : array-like, shape (..., 3, 3)

    Returns
    -------
    dR : ndarray, shape (..., 3, 3)
    """
    M = np.asarray(M, dtype=float)
    dM = np.asarray(dM, dtype=float)
    U, s, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = 1.0 if d == 0.0 else d
    U = U.copy()
    U[:, 2] *= d
    s = s.copy()
    s[2] *= d
    W = U.T @ dM @ Vt.T
    denom = s[:, None] + s[None, :]
    # The sum only vanishes for a degenerate M (two singular values cancelling): the projection is not
    # differentiable there; a tiny denominator keeps the result finite instead of NaN.
    denom = np.where(np.abs(denom) < 1e-12, 1e-12, denom)
    Omega = (W - np.swapaxes(W, -1, -2)) / denom
    return U @ Omega @ Vt


# Cofactor entries of a row-major 3x3 matrix x (9, k): C = x[_P1] * x[_P2] - x[_P3] * x[_P4], so X^-T = C / det X.
_P1 = np.array([4, 5, 3, 2, 0, 1, 1, 2, 0])
_P2 = np.array([8, 6, 7, 7, 8, 6, 5, 3, 4])
_P3 = np.array([5, 3, 4, 1, 2, 0, 2, 0, 1])
_P4 = np.array([7, 8, 6, 8, 6, 7, 4, 5, 3])


def _project_to_rotation_batch(M, tol=1e-8, max_iter=50):
    """Same result as :func:`~body_scheme_core.transforms.project_to_rotation` (to ~1e-14), faster for stacks.

    LAPACK's SVD costs a few microseconds per 3x3 matrix, which dominated a 462-slot prediction. The orthogonal
    polar factor is computed instead by the scaled Newton iteration ``X <- (z X + X^-T / z) / 2`` (Higham,
    Frobenius-norm scaling ``z`` until the step is small, then unscaled for quadratic convergence), vectorised
    over the stack with explicit cofactors. A step below ``tol`` leaves an error of order ``tol^2``. For
    ``det M <= 0`` (nearly) the polar factor is not the nearest rotation, and those matrices take the SVD path.

    Parameters
    ----------
    M : ndarray, shape (k, 3, 3)

    Returns
    -------
    R : ndarray, shape (k, 3, 3)
    """
    k = M.shape[0]
    x = M.reshape(k, 9).T.copy()  # component-major: each entry a contiguous (k,) vector
    cof = x[_P1] * x[_P2] - x[_P3] * x[_P4]
    det = np.einsum("ik,ik->k", x[:3], cof[:3])
    sq = np.einsum("ik,ik->k", x, x)
    good = det > 1e-6 * sq**1.5
    all_good = bool(np.all(good))
    if not all_good:
        x, cof, det, sq = x[:, good], cof[:, good], det[good], sq[good]
    scale = True
    converged = x.shape[1] == 0
    for _ in range(max_iter):
        if converged:
            break
        inv_t = cof / det
        if scale:
            zeta = np.sqrt(np.sqrt(np.einsum("ik,ik->k", inv_t, inv_t) / sq))
            x_new = 0.5 * (zeta * x + inv_t / zeta)
        else:
            x_new = 0.5 * (x + inv_t)
        step = np.max(np.abs(x_new - x))
        x = x_new
        converged = step < tol
        scale = step > 1e-2
        cof = x[_P1] * x[_P2] - x[_P3] * x[_P4]
        det = np.einsum("ik,ik->k", x[:3], cof[:3])
        if scale:
            sq = np.einsum("ik,ik->k", x, x)
    if not converged:  # pragma: no cover - the scaled iteration converges in < 15 steps for det > 0
        return project_to_rotation(M)
    if all_good:
        return x.T.reshape(k, 3, 3)
    R = np.empty((k, 9))
    R[good] = x.T
    R[~good] = project_to_rotation(M[~good]).reshape(-1, 9)
    return R.reshape(k, 3, 3)


def summarise_std(std12):
    """Summarise per-output latent stds of the 12-vector as ``[trans (m), rot (rad)]`` per-axis stds.

    Translation: root mean square of the three translational stds. Rotation: ``sqrt(3/2)`` times the root mean
    square of the nine matrix-entry stds, the per-axis rotation-vector std whose first-order effect on the matrix
    entries has that spread (a rotation ``exp([w]x) R`` with ``w ~ N(0, s^2 I)`` has entry variance ``2 s^2 / 3``).

    Parameters
    ----------
    std12 : ndarray, shape (k, 12)

    Returns
    -------
    std : ndarray, shape (k, 2)
    """
    std12 = np.asarray(std12, dtype=float)
    trans = np.sqrt(np.mean(std12[:, TRANS_OUTPUTS] ** 2, axis=1))
    rot = ROT_STD_PER_ENTRY_STD * np.sqrt(np.mean(std12[:, ROT_OUTPUTS] ** 2, axis=1))
    return np.stack([trans, rot], axis=1)


def _clamp_variance(var):
    """Clamp negative predictive variances (round-off) to 0 with a warning, like scikit-learn."""
    negative = var < 0.0
    if np.any(negative):
        warnings.warn(f"Predicted variances smaller than 0 (min {var[negative].min():.3g}); setting those to 0.",
                      RuntimeWarning, stacklevel=3)
        var = np.where(negative, 0.0, var)
    return var


def _positive(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InvalidInputError(f"{name} must be a finite number > 0, got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise InvalidInputError(f"{name} must be a finite number > 0, got {value!r}")
    return value


@dataclass(frozen=True)
class GPHyperparameters:
    """Fixed hyperparameters of the GP local models (see the module docstring for the parametrisation).

    Attributes
    ----------
    length_scale : float
        Length scale of the squared-exponential kernel over actions (rad).
    signal_std_trans, signal_std_rot : float
        Prior std of the translational (m) and rotation-matrix outputs around their training mean.
    noise_std_trans, noise_std_rot : float
        Std of the white noise on one observed translational component (m) and rotation-matrix entry.
    """

    length_scale: float
    signal_std_trans: float
    signal_std_rot: float
    noise_std_trans: float
    noise_std_rot: float

    def __post_init__(self):
        for name, value in asdict(self).items():
            object.__setattr__(self, name, _positive(name, value))

    @classmethod
    def from_config(cls, config):
        """Derive the hyperparameters from a :class:`~body_scheme_core.config.BodySchemeConfig`.

        Physical noise: ``sigma_trans`` and ``sigma_rot`` are the RMS 3D errors of one marker's position (m) and
        rotation vector (rad), so per axis ``s_t = sigma_trans / sqrt(3)`` and ``s_r = sigma_rot / sqrt(3)``. A
        relative observation ``Z = Y_i^-1 Y_j`` combines two markers, so per axis its translation has std
        ``sqrt(2) s_t`` and its rotation vector ``sqrt(2) s_r``; a rotation vector with per-axis std ``s`` perturbs
        each matrix entry with std ``sqrt(2/3) s`` on average, giving a per-entry noise ``(2 / sqrt(3)) s_r``.
        Signal stds are ``gp_signal_std_trans`` and ``gp_signal_std_rot``.

        One ratio: the posterior mean only depends on noise/signal, so both output groups get the LARGER of the
        two physical ratios and the noise of the other group is raised to match; one factorisation then serves all
        12 outputs. For translation this is also physically right: the orientation noise of ``Y_i`` moves the
        origin of ``Y_j`` by ``|t_ij| s_r``, a lever-arm term the ``sqrt(2) s_t`` estimate leaves out (with the
        defaults the raised translational noise, 0.075 m, is about that per axis at ``|t_ij|`` = 0.5 m). On simulated
        chains this choice predicted better than two separate ratios and than the translational ratio for all
        outputs (docs/core/local-models.md).
        """
        noise_trans = math.sqrt(2.0) * config.sigma_trans / math.sqrt(3.0)
        noise_rot = 2.0 / math.sqrt(3.0) * config.sigma_rot / math.sqrt(3.0)
        ratio = max(noise_trans / config.gp_signal_std_trans, noise_rot / config.gp_signal_std_rot)
        return cls(length_scale=config.gp_length_scale, signal_std_trans=config.gp_signal_std_trans,
                   signal_std_rot=config.gp_signal_std_rot, noise_std_trans=ratio * config.gp_signal_std_trans,
                   noise_std_rot=ratio * config.gp_signal_std_rot)

    def to_dict(self):
        """Plain dict of the five values."""
        return asdict(self)

    @property
    def ratios(self):
        """Distinct noise-to-signal ratios, shape (G,) with G = 1 when rotation and translation share one."""
        r_rot = self.noise_std_rot / self.signal_std_rot
        r_trans = self.noise_std_trans / self.signal_std_trans
        if math.isclose(r_rot, r_trans, rel_tol=1e-9):
            return np.array([r_trans])
        return np.array([r_rot, r_trans])

    @property
    def output_group(self):
        """Index into :attr:`ratios` for each of the 12 outputs, shape (12,)."""
        group = np.zeros(12, dtype=int)
        group[TRANS_OUTPUTS] = len(self.ratios) - 1
        return group

    @property
    def signal_std(self):
        """Signal std of each of the 12 outputs, shape (12,)."""
        std = np.empty(12)
        std[ROT_OUTPUTS] = self.signal_std_rot
        std[TRANS_OUTPUTS] = self.signal_std_trans
        return std


#: Search box of :func:`marginal_likelihood_hyperparameters`: length scale (rad) and noise-to-signal ratio.
LENGTH_SCALE_BOUNDS = (0.2, 5.0)
RATIO_BOUNDS = (0.01, 2.0)


def log_marginal_likelihood(X, Y, length_scale, ratio):
    """Profile log marginal likelihood of 12 outputs sharing one kernel (up to a constant).

    Each centred output ``y_o ~ N(0, s_o^2 (K + r^2 I))`` with the unit-amplitude kernel ``K`` of ``length_scale``; its
    signal variance ``s_o^2`` is profiled out at its maximum ``y_o^T (K + r^2 I)^-1 y_o / n``, leaving
    ``-sum_o n/2 log(s_o^2) - 12/2 log|K + r^2 I|``.

    Parameters
    ----------
    X : ndarray, shape (n, d)
    Y : ndarray, shape (n, 12)
    length_scale, ratio : float
    """
    n = X.shape[0]
    C = squared_exponential(X, X, length_scale) + ratio**2 * np.eye(n)
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return -np.inf
    Yc = Y - Y.mean(axis=0)
    quad = np.sum(Yc * cho_solve((L, True), Yc), axis=0) / n
    return float(-0.5 * n * np.sum(np.log(np.maximum(quad, 1e-300))) - Y.shape[1] * np.sum(np.log(np.diag(L))))


def marginal_likelihood_hyperparameters(X, Y, current):
    """Hyperparameters with the length scale and one noise-to-signal ratio of maximum marginal likelihood.

    A coarse log-spaced grid over :data:`LENGTH_SCALE_BOUNDS` x :data:`RATIO_BOUNDS`, then a bounded Nelder-Mead
    refinement in log space. The signal stds keep ``current``'s (only the ratio enters the posterior mean); the
    noise stds follow from the ratio.

    Parameters
    ----------
    X : ndarray, shape (n, d)
    Y : ndarray, shape (n, 12)
    current : GPHyperparameters

    Returns
    -------
    GPHyperparameters
    """
    from scipy.optimize import minimize

    lo = np.log([LENGTH_SCALE_BOUNDS[0], RATIO_BOUNDS[0]])
    hi = np.log([LENGTH_SCALE_BOUNDS[1], RATIO_BOUNDS[1]])

    def cost(z):
        z = np.clip(z, lo, hi)
        return -log_marginal_likelihood(X, Y, math.exp(z[0]), math.exp(z[1]))

    grid = [np.array([a, b]) for a in np.linspace(lo[0], hi[0], 6) for b in np.linspace(lo[1], hi[1], 6)]
    start = min(grid, key=cost)
    result = minimize(cost, start, method="Nelder-Mead", options={"xatol": 0.02, "fatol": 1e-3, "maxiter": 80})
    length_scale, ratio = np.exp(np.clip(result.x, lo, hi))
    return GPHyperparameters(length_scale=float(length_scale), signal_std_trans=current.signal_std_trans,
                             signal_std_rot=current.signal_std_rot,
                             noise_std_trans=float(ratio) * current.signal_std_trans,
                             noise_std_rot=float(ratio) * current.signal_std_rot)


def _training_arrays(X, Y, d):
    """Saved training inputs and targets as float arrays (n, d) and (n, 12); empty lists give n = 0."""
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    if Y.size == 0:
        Y = Y.reshape(0, 12)
    if X.size == 0:  # also the n rows of a 0-dim GP, saved as [[], [], ...]
        X = X.reshape(Y.shape[0] if X.ndim == 2 else 0, d)
    if X.ndim != 2 or X.shape[1] != d:
        raise ModelFileError(f"training inputs must have shape (n, {d}), got {X.shape}")
    return X, Y


def _default_hyperparameters():
    return GPHyperparameters.from_config(BodySchemeConfig())


class GPModel(LocalModel):
    """GP regression from the model's actions to the 12 components of ``parent2child``.

    Parameters
    ----------
    parent, child : int
        Part ids; the model predicts ``parent2child``.
    actions : tuple of int
        Indices of the actions the model depends on; ``()`` gives a GP that predicts the training mean.
    length_scale, signal_std_trans, signal_std_rot, noise_std_trans, noise_std_rot : float or None
        See :class:`GPHyperparameters`; ``None`` takes the value derived from the default ``BodySchemeConfig``.

    Attributes
    ----------
    X_train_ : ndarray, shape (n, d)
        Training inputs (the model's own action columns).
    Y_train_ : ndarray, shape (n, 12)
        Training targets ``vector12_from_transform(Z)``.
    y_mean_ : ndarray, shape (12,)
        Constant prior mean.
    L_ : ndarray, shape (G, n, n)
        Lower Cholesky factor of ``K + r_g^2 I`` per noise-to-signal ratio (unit-amplitude kernel).
    alpha_ : ndarray, shape (n, 12)
        ``(K + r^2 I)^-1 (Y - y_mean)`` with each output's ratio.
    """

    kind = "gp"

    def __init__(self, parent, child, actions=(), length_scale=None, signal_std_trans=None, signal_std_rot=None,
                 noise_std_trans=None, noise_std_rot=None):
        super().__init__(parent, child, actions)
        if len(set(self.actions)) != len(self.actions) or any(a < 0 for a in self.actions):
            raise InvalidInputError(f"actions must be distinct indices >= 0, got {self.actions}")
        given = {"length_scale": length_scale, "signal_std_trans": signal_std_trans,
                 "signal_std_rot": signal_std_rot, "noise_std_trans": noise_std_trans, "noise_std_rot": noise_std_rot}
        if any(value is None for value in given.values()):
            defaults = _default_hyperparameters().to_dict()
            given = {name: defaults[name] if value is None else value for name, value in given.items()}
        self.hyperparameters = GPHyperparameters(**given)

    @classmethod
    def from_config(cls, parent, child, actions, config):
        """GP local model with hyperparameters derived from ``config`` (:meth:`GPHyperparameters.from_config`)."""
        return cls(parent, child, actions, **GPHyperparameters.from_config(config).to_dict())

    @property
    def is_fitted(self):
        return hasattr(self, "alpha_")

    @property
    def n_samples(self):
        """Number of training samples (0 before ``fit``)."""
        return self.X_train_.shape[0] if self.is_fitted else 0

    def fit(self, A, Z, optimize=False):
        """Fit on full action vectors ``A`` (n, m) and relative observations ``Z`` (n, 4, 4); returns ``self``.

        With ``optimize`` the length scale and the noise-to-signal ratio are first chosen by maximising the marginal
        likelihood (:func:`marginal_likelihood_hyperparameters`); otherwise the given hyperparameters are used.
        """
        A, Z = check_observations(A, Z)
        X, Y = self._select(A), vector12_from_transform(Z)
        if optimize and self.actions and X.shape[0] >= 3:
            self.hyperparameters = marginal_likelihood_hyperparameters(X, Y, self.hyperparameters)
        return self._fit_components(X, Y)

    def _fit_components(self, X, Y):
        """Fit on the model's own inputs ``X`` (n, d) and 12-vector targets ``Y`` (n, 12)."""
        hp = self.hyperparameters
        n = X.shape[0]
        K = squared_exponential(X, X, hp.length_scale)
        ratios = hp.ratios
        group = hp.output_group
        y_mean = Y.mean(axis=0)
        L = np.empty((len(ratios), n, n))
        alpha = np.empty((n, 12))
        for g, ratio in enumerate(ratios):
            try:
                L[g] = np.linalg.cholesky(K + ratio**2 * np.eye(n))
            except np.linalg.LinAlgError as exc:
                raise BodySchemeError(
                    f"The kernel matrix of {self.describe()} ({n} samples) is not positive definite "
                    f"(noise-to-signal ratio {ratio:.3g}). Increase the noise std relative to the signal std, "
                    "or reduce the length scale.") from exc
            alpha[:, group == g] = cho_solve((L[g], True), Y[:, group == g] - y_mean[group == g])
        self.X_train_ = X
        self.Y_train_ = Y
        self.y_mean_ = y_mean
        self.L_ = L
        self.alpha_ = alpha
        return self

    def training_range(self):
        """``(low, high)``, each shape (d,): the box of the training inputs (see :meth:`LocalModel.training_range`).

        Far outside it the GP mean falls back to the training mean, so predictions there are guesses.
        """
        self._check_fitted()
        return self.X_train_.min(axis=0), self.X_train_.max(axis=0)

    def predict_components(self, A, return_std=False):
        """Posterior mean (and latent std) of the 12 components, before projection onto SE(3).

        Parameters
        ----------
        A : array-like, shape (k, m) or (m,)
        return_std : bool

        Returns
        -------
        mean : ndarray, shape (k, 12)
        std : ndarray, shape (k, 12)
            Only if ``return_std``: latent (noise-free) predictive std of each component.
        """
        self._check_fitted()
        X = self._select(A)
        hp = self.hyperparameters
        Ks = squared_exponential(X, self.X_train_, hp.length_scale)
        mean = self.y_mean_ + Ks @ self.alpha_
        if not return_std:
            return mean
        var = np.empty((X.shape[0], self.L_.shape[0]))
        for g in range(self.L_.shape[0]):
            V = solve_triangular(self.L_[g], Ks.T, lower=True)
            var[:, g] = 1.0 - np.sum(V * V, axis=0)
        var = _clamp_variance(var)
        return mean, hp.signal_std * np.sqrt(var[:, hp.output_group])

    def predict(self, A, return_std=False):
        """Predict ``parent2child`` (k, 4, 4) [and the latent std (k, 2): per-axis trans m, rot rad]."""
        if not return_std:
            return transform_from_vector12(self.predict_components(A))
        mean, std12 = self.predict_components(A, return_std=True)
        return transform_from_vector12(mean), summarise_std(std12)

    def jacobian(self, a, eps=None):
        """Analytic ``dZ/da`` (m, 4, 4) at one full action vector ``a`` (m,), through the GP mean and the projection.

        ``eps`` is accepted for interface compatibility and ignored.
        """
        self._check_fitted()
        a = check_actions(a)
        x = self._select(a)[0]
        J = np.zeros((a.shape[1], 4, 4))
        if not self.actions:
            return J
        hp = self.hyperparameters
        dk = squared_exponential_gradient(x, self.X_train_, hp.length_scale)  # (n, d)
        k = squared_exponential(x[None, :], self.X_train_, hp.length_scale)[0]
        mean = self.y_mean_ + k @ self.alpha_
        dmean = dk.T @ self.alpha_  # (d, 12)
        idx = list(self.actions)
        J[idx, :3, :3] = polar_derivative(mean[ROT_OUTPUTS].reshape(3, 3), dmean[:, ROT_OUTPUTS].reshape(-1, 3, 3))
        J[idx, :3, 3] = dmean[:, TRANS_OUTPUTS]
        return J

    def to_dict(self):
        data = {"kind": self.kind, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "hyperparameters": self.hyperparameters.to_dict()}
        if self.is_fitted:
            data["X"] = self.X_train_.tolist()
            data["Y"] = self.Y_train_.tolist()
        return data

    @classmethod
    def from_dict(cls, data):
        try:
            if data["kind"] != cls.kind:
                raise ModelFileError(f"expected kind {cls.kind!r}, got {data['kind']!r}")
            model = cls(data["parent"], data["child"], data["actions"], **data["hyperparameters"])
            if "X" in data:
                d = len(model.actions)
                X, Y = _training_arrays(data["X"], data["Y"], d)
                if Y.ndim != 2 or Y.shape[1] != 12 or Y.shape[0] != X.shape[0] or X.shape[0] == 0:
                    raise ModelFileError(f"GP training data must be X (n, {d}) and Y (n, 12), n >= 1, got "
                                         f"X {X.shape} and Y {Y.shape}")
                if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
                    raise ModelFileError("GP training data contains NaN or inf")
                model._fit_components(X, Y)
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            keys = sorted(data) if isinstance(data, dict) else data
            raise ModelFileError(f"cannot read GP model from {keys!r}: {exc}") from exc
        return model


class GPBatch:
    """Many incremental GP local models ("slots") in stacked arrays, updated together without Python loops.

    Each slot is a GP of :class:`GPModel` over its own action indices, holding at most ``capacity`` samples. The
    inverse ``(K + r^2 I)^-1`` of every slot is kept and extended by one row and column per sample with the block
    (Schur complement) formula, O(n^2) per slot. Arrays are padded to ``capacity`` samples and ``max_dim`` inputs;
    padded inputs are 0 in both training and query inputs, so they do not change distances.

    Parameters
    ----------
    n_actions : int
        Length m of the full action vectors.
    capacity : int
        Largest number of training samples per slot (the paper's |D_train|).
    max_dim : int
        Largest number of actions a slot may depend on.
    length_scale, signal_std_trans, signal_std_rot, noise_std_trans, noise_std_rot : float
        See :class:`GPHyperparameters`.
    """

    def __init__(self, n_actions, capacity, max_dim, length_scale, signal_std_trans, signal_std_rot,
                 noise_std_trans, noise_std_rot):
        for name, value in [("n_actions", n_actions), ("capacity", capacity), ("max_dim", max_dim)]:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise InvalidInputError(f"{name} must be an integer >= 0, got {value!r}")
        if capacity < 1:
            raise InvalidInputError(f"capacity must be >= 1, got {capacity}")
        self.n_actions = int(n_actions)
        self.capacity = int(capacity)
        self.max_dim = int(max_dim)
        self.hyperparameters = GPHyperparameters(length_scale, signal_std_trans, signal_std_rot, noise_std_trans,
                                                 noise_std_rot)
        hp = self.hyperparameters
        self._ratios2 = hp.ratios**2
        self._group = hp.output_group
        self._signal_std = hp.signal_std
        self._n_groups = len(self._ratios2)
        self._gamma = -0.5 / hp.length_scale**2
        self._storage = 0
        self._allocated = np.zeros(0, dtype=bool)
        self._dim = np.zeros(0, dtype=int)
        self._n = np.zeros(0, dtype=int)
        # Padded action indices point at an extra 0 appended to the action vector.
        self._actions = np.zeros((0, self.max_dim), dtype=int)
        # Inputs component-major (slot, dim, sample): distances then run over contiguous rows of samples.
        self._X = np.zeros((0, self.max_dim, self.capacity))
        self._Y = np.zeros((0, self.capacity, 12))
        self._Ysum = np.zeros((0, 12))
        self._Kinv = np.zeros((0, self._n_groups, self.capacity, self.capacity))
        self._version = 0
        self._cache = None

    @classmethod
    def from_config(cls, n_actions, config, max_dim=None):
        """Batch with ``capacity = config.train_window`` and ``max_dim = config.max_complexity`` unless given."""
        max_dim = config.max_complexity if max_dim is None else max_dim
        return cls(n_actions, config.train_window, max_dim, **GPHyperparameters.from_config(config).to_dict())

    # ------------------------------------------------------------------ slots

    @property
    def n_allocated(self):
        """Number of allocated slots."""
        return int(np.count_nonzero(self._allocated))

    @property
    def allocated_slots(self):
        """Allocated slot indices, ascending."""
        return np.flatnonzero(self._allocated)

    def slot_actions(self, slot):
        """Action indices (tuple) of one allocated slot."""
        slot = int(self._check_slots([slot])[0])
        return tuple(int(a) for a in self._actions[slot, :self._dim[slot]])

    def _grow(self, storage):
        extra = storage - self._storage
        self._allocated = np.concatenate([self._allocated, np.zeros(extra, dtype=bool)])
        self._dim = np.concatenate([self._dim, np.zeros(extra, dtype=int)])
        self._n = np.concatenate([self._n, np.zeros(extra, dtype=int)])
        self._actions = np.concatenate([self._actions, np.full((extra, self.max_dim), self.n_actions, dtype=int)])
        self._X = np.concatenate([self._X, np.zeros((extra,) + self._X.shape[1:])])
        self._Y = np.concatenate([self._Y, np.zeros((extra,) + self._Y.shape[1:])])
        self._Ysum = np.concatenate([self._Ysum, np.zeros((extra, 12))])
        self._Kinv = np.concatenate([self._Kinv, np.zeros((extra,) + self._Kinv.shape[1:])])
        self._storage = storage

    def _check_slot_actions(self, actions):
        try:
            actions = tuple(int(a) for a in actions)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"actions must be a tuple of ints, got {actions!r}") from exc
        if len(actions) > self.max_dim:
            raise InvalidInputError(f"a slot may depend on at most max_dim={self.max_dim} actions, got {actions}")
        if len(set(actions)) != len(actions) or any(not 0 <= a < self.n_actions for a in actions):
            raise InvalidInputError(f"actions must be distinct indices in [0, {self.n_actions}), got {actions}")
        return actions

    def _assign(self, slot, actions):
        self._actions[slot] = self.n_actions
        self._actions[slot, :len(actions)] = actions
        self._dim[slot] = len(actions)
        self._n[slot] = 0
        self._allocated[slot] = True

    def allocate(self, actions_list):
        """Allocate empty GPs, one per tuple of action indices; returns their slot indices, shape (k,).

        Released slots are reused, lowest first; storage grows (doubling) when none is free.
        """
        checked = [self._check_slot_actions(actions) for actions in actions_list]
        free = np.flatnonzero(~self._allocated)
        if free.size < len(checked):
            self._grow(max(2 * self._storage, self._storage + len(checked) - free.size, 16))
            free = np.flatnonzero(~self._allocated)
        slots = free[:len(checked)]
        for slot, actions in zip(slots, checked, strict=True):
            self._assign(slot, actions)
        self._version += 1
        return slots

    def release(self, slots):
        """Free slots for reuse; their data are discarded."""
        slots = self._check_slots(slots)
        self._allocated[slots] = False
        self._n[slots] = 0
        self._dim[slots] = 0
        self._actions[slots] = self.n_actions
        self._X[slots] = 0.0
        self._Y[slots] = 0.0
        self._Ysum[slots] = 0.0
        self._Kinv[slots] = 0.0
        self._version += 1

    def size(self, slots):
        """Number of training samples of each slot, shape (k,)."""
        return self._n[self._check_slots(slots)].copy()

    def _check_slots(self, slots, unique=False):
        slots = np.atleast_1d(np.asarray(slots))
        if slots.ndim != 1 or not (np.issubdtype(slots.dtype, np.integer) or slots.size == 0):
            raise InvalidInputError(f"slots must be a 1-d array of ints, got shape {slots.shape} dtype {slots.dtype}")
        slots = slots.astype(np.intp, copy=False)
        if slots.size and (slots.min() < 0 or slots.max() >= self._storage):
            raise InvalidInputError(f"slot index out of range [0, {self._storage}): {slots.min()}..{slots.max()}")
        if not np.all(self._allocated[slots]):
            raise InvalidInputError(f"slots not allocated: {slots[~self._allocated[slots]].tolist()}")
        if unique and np.unique(slots).size != slots.size:
            raise InvalidInputError("slots must not repeat in one update")
        return slots

    def _check_a(self, a):
        a = np.asarray(a, dtype=float)
        if a.ndim == 2 and a.shape[0] == 1:
            a = a[0]
        if a.shape != (self.n_actions,):
            raise InvalidInputError(f"a must be one action vector of shape ({self.n_actions},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InvalidInputError("a contains NaN or inf")
        return a

    @staticmethod
    def _index(slots):
        """A slice when the slots are consecutive (views, no copies), else the index array."""
        if slots.size and slots[-1] - slots[0] == slots.size - 1 and np.all(np.diff(slots) == 1):
            return slice(int(slots[0]), int(slots[-1]) + 1)
        return slots

    # -------------------------------------------------------------- inference

    def _kernel_solve(self, idx, x, ne):
        """Kernel vector to the first ``ne`` training inputs (k, ne) and ``Kinv k`` per ratio (k, G, ne)."""
        X = self._X[idx, :, :ne]
        sqdist = np.zeros((x.shape[0], ne))
        for d in range(self.max_dim):  # a loop over at most max_dim input dimensions, not over slots
            diff = X[:, d] - x[:, d, None]
            sqdist += diff * diff
        kb = np.exp(self._gamma * sqdist)
        v = (self._Kinv[idx, :, :ne, :ne] @ kb[:, None, :, None])[..., 0]
        return kb, v

    def _inputs(self, slots, a):
        return np.append(a, 0.0)[self._actions[slots]]

    def predict(self, slots, a, return_std=False):
        """Predict every slot at one full action vector.

        Parameters
        ----------
        slots : array-like of int, shape (k,)
        a : array-like, shape (m,)
            One action vector shared by all slots; each slot reads its own action indices.
        return_std : bool

        Returns
        -------
        Z : ndarray, shape (k, 4, 4)
            Identity for empty slots.
        std : ndarray, shape (k, 2)
            Only if ``return_std``: latent per-axis std ``[trans m, rot rad]``; ``inf`` for empty slots.
        """
        slots = self._check_slots(slots)
        a = self._check_a(a)
        k = slots.size
        idx = self._index(slots)
        n = self._n[idx]
        ne = int(n.max()) if k else 0
        x = self._inputs(idx, a)
        kb, v = self._kernel_solve(idx, x, ne)
        self._cache = (self._version, slots.copy(), a.tobytes(), kb, v)
        ybar = self._Ysum[idx] / np.maximum(n, 1)[:, None]
        # mu = ybar + v^T (Y - ybar) = ybar (1 - sum(v)) + v^T Y; Kinv is zero-padded, so is v.
        vY = v @ self._Y[idx, :ne]  # (k, G, 12)
        vsum = v.sum(axis=2)
        if self._n_groups == 1:
            mean = vY[:, 0] + ybar * (1.0 - vsum)
        else:
            mean = vY[:, self._group, np.arange(12)] + ybar * (1.0 - vsum[:, self._group])
        empty = n == 0
        mean[empty] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
        Z = np.zeros((k, 4, 4))
        Z[:, :3, :3] = _project_to_rotation_batch(mean[:, ROT_OUTPUTS].reshape(k, 3, 3))
        Z[:, :3, 3] = mean[:, TRANS_OUTPUTS]
        Z[:, 3, 3] = 1.0
        if not return_std:
            return Z
        var = _clamp_variance(1.0 - np.einsum("sn,sgn->sg", kb, v))
        std = summarise_std(self._signal_std * np.sqrt(var[:, self._group]))
        std[empty] = np.inf
        return Z, std

    def add_samples(self, slots, a, Z):
        """Append one sample ``(a, Z)`` to each slot.

        Parameters
        ----------
        slots : array-like of int, shape (k,)
            Distinct allocated slots, none of them full (filter with :meth:`size`).
        a : array-like, shape (m,)
            One action vector shared by all slots.
        Z : array-like, shape (k, 4, 4) or (4, 4)
            Observed ``parent2child`` per slot, or one transform for all.
        """
        slots = self._check_slots(slots, unique=True)
        a = self._check_a(a)
        Z = check_transform(Z, name="Z", tolerance=1e-4)
        if Z.shape == (4, 4):
            Z = np.broadcast_to(Z, (slots.size, 4, 4))
        if Z.shape != (slots.size, 4, 4):
            raise InvalidInputError(f"Z must have shape (4, 4) or ({slots.size}, 4, 4), got {Z.shape}")
        full = self._n[slots] >= self.capacity
        if np.any(full):
            raise InvalidInputError(f"slots already hold capacity={self.capacity} samples: {slots[full].tolist()}")
        if slots.size == 0:
            return
        idx = self._index(slots)
        self._append(slots, idx, self._inputs(idx, a), vector12_from_transform(Z), self._cached_solve(slots, a))

    def _cached_solve(self, slots, a):
        """Kernel vectors and solves of the last ``predict`` if it saw this state, this ``a`` and these slots."""
        cache = self._cache
        if cache is None or cache[0] != self._version or cache[2] != a.tobytes():
            return None
        cached_slots, kb, v = cache[1], cache[3], cache[4]
        if np.array_equal(cached_slots, slots):
            return kb, v
        # The usual caller predicts all candidates, then adds to those not yet full: reuse their rows.
        position = np.full(self._storage, -1)
        position[cached_slots] = np.arange(cached_slots.size)
        rows = position[slots]
        if np.any(rows < 0):
            return None
        ne = int(self._n[slots].max())
        # Entries of v beyond a slot's own size are exactly 0 (zero-padded inverse), so truncating is exact.
        return kb[rows, :ne], v[rows, :, :ne]

    def _append(self, slots, idx, x, y, cached=None):
        """Extend each slot's inverse by one sample: inputs ``x`` (k, max_dim), targets ``y`` (k, 12)."""
        n = self._n[idx]
        ne = int(n.max())
        kb, u = cached if cached is not None else self._kernel_solve(idx, x, ne)
        # Schur complement of the new diagonal entry: the predictive variance of the new noisy sample in unit
        # kernel scale, >= r^2 in exact arithmetic.
        schur = 1.0 + self._ratios2 - np.einsum("sn,sgn->sg", kb, u)
        if np.any(schur <= 1e-9 * self._ratios2):
            bad = slots[np.any(schur <= 1e-9 * self._ratios2, axis=1)]
            raise BodySchemeError(
                f"incremental GP update lost positive definiteness in slots {bad.tolist()} (Schur complement "
                f"{schur.min():.3g}); the noise-to-signal ratio {np.sqrt(self._ratios2).tolist()} is too small for "
                "double precision: increase the noise std relative to the signal std.")
        # The block inverse [[A^-1 + u u^T / s, -u / s], [-u^T / s, 1 / s]] is A^-1 (zero-padded) plus one rank-1
        # term (1 / s) [u; -1] [u; -1]^T, so a single broadcast update over contiguous rows covers all slots.
        k = n.shape[0]
        ne1 = ne + 1
        ext = np.zeros((k, self._n_groups, self.capacity))
        ext[..., :ne] = u
        ext[np.arange(k), :, n] = -1.0
        update = (ext[..., :ne1, None] / schur[:, :, None, None]) * ext[..., None, :]
        if isinstance(idx, slice):
            self._Kinv[idx, :, :ne1] += update
        else:
            self._Kinv[idx, :, :ne1] = self._Kinv[idx, :, :ne1] + update
        self._X[slots, :, n] = x
        self._Y[slots, n] = y
        self._Ysum[slots] += y
        self._n[slots] = n + 1
        self._version += 1
        self._cache = None

    # ------------------------------------------------------------ conversion

    def to_model(self, slot, parent, child):
        """A :class:`GPModel` fitted on exactly this slot's data (unfitted if the slot is empty)."""
        slot = int(self._check_slots([slot])[0])
        actions = tuple(int(a) for a in self._actions[slot, :self._dim[slot]])
        model = GPModel(parent, child, actions, **self.hyperparameters.to_dict())
        n = self._n[slot]
        if n:
            model._fit_components(self._X[slot, :len(actions), :n].T.copy(), self._Y[slot, :n].copy())
        return model

    def state_dict(self):
        """JSON-serialisable state: settings and, per storage slot, ``None`` (free) or its actions and data."""
        slots = []
        for slot in range(self._storage):
            if not self._allocated[slot]:
                slots.append(None)
                continue
            n, d = int(self._n[slot]), int(self._dim[slot])
            slots.append({"actions": self._actions[slot, :d].tolist(), "X": self._X[slot, :d, :n].T.tolist(),
                          "Y": self._Y[slot, :n].tolist()})
        return {"format": "GPBatch", "version": 1, "n_actions": self.n_actions, "capacity": self.capacity,
                "max_dim": self.max_dim, "hyperparameters": self.hyperparameters.to_dict(), "slots": slots}

    @classmethod
    def from_state_dict(cls, data):
        """Rebuild a batch from :meth:`state_dict` output, replaying the samples in order; same slot indices."""
        try:
            if data.get("format") != "GPBatch" or data.get("version") != 1:
                raise ModelFileError(f"not a GPBatch state (format {data.get('format')!r}, "
                                     f"version {data.get('version')!r})")
            batch = cls(data["n_actions"], data["capacity"], data["max_dim"], **data["hyperparameters"])
            entries = data["slots"]
            batch._grow(len(entries))
            X = np.zeros((len(entries), batch.capacity, batch.max_dim))
            Y = np.zeros((len(entries), batch.capacity, 12))
            sizes = np.zeros(len(entries), dtype=int)
            for slot, entry in enumerate(entries):
                if entry is None:
                    continue
                actions = tuple(entry["actions"])
                d = len(actions)
                if d > batch.max_dim:
                    raise ModelFileError(f"slot {slot}: {d} actions exceed max_dim {batch.max_dim}")
                Xs, Ys = _training_arrays(entry["X"], entry["Y"], d)
                n = Xs.shape[0]
                if Ys.shape != (n, 12) or n > batch.capacity:
                    raise ModelFileError(f"slot {slot}: X {Xs.shape} and Y {Ys.shape} do not match or exceed "
                                         f"capacity {batch.capacity}")
                if not (np.all(np.isfinite(Xs)) and np.all(np.isfinite(Ys))):
                    raise ModelFileError(f"slot {slot}: data contain NaN or inf")
                batch._assign(slot, batch._check_slot_actions(actions))
                X[slot, :n, :d] = Xs
                Y[slot, :n] = Ys
                sizes[slot] = n
            # Replaying sample by sample repeats the incremental updates that built the saved batch.
            for k in range(int(sizes.max()) if sizes.size else 0):
                slots = np.flatnonzero(sizes > k)
                batch._append(slots, slots, X[slots, k], Y[slots, k])
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ModelFileError(f"cannot read GPBatch state: {exc}") from exc
        return batch
