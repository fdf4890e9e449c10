"""Gaussian-process local models (paper Sec. III-B).

A :class:`GPModel` regresses the 12 free components of ``Z = parent2child``, ``[R (row-major, 9), t (3)]``, on the
actions it depends on, each component independently (the paper's simplification). The prediction is mapped back
onto SE(3) by the nearest rotation in the Frobenius norm (the paper's "normalisation step").

The kernel, the hyperparameters and the marginal likelihood are in :mod:`~body_scheme_core.models.gp_kernel` (with
the parametrisation); the batched incremental engine in which GP candidates learn is
:class:`~body_scheme_core.models.gp_batch.GPBatch`.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from ..errors import BodySchemeError, InvalidInputError, ModelFileError
from ..limits import MAX_ACTION, MAX_COORDINATE
from ..rotations import polar_derivative
from ..transforms import transform_from_vector12, vector12_from_transform
from .base import LocalModel, check_action_batch, check_observations
from .gp_kernel import (
    ROT_OUTPUTS,
    TRANS_OUTPUTS,
    GPHyperparameters,
    _clamp_variance,
    marginal_likelihood_hyperparameters,
    squared_exponential,
    squared_exponential_gradient,
    summarise_std,
)

__all__ = ["GPModel"]


def _training_arrays(X, Y, d):
    """Saved training inputs and targets as float arrays (n, d) and (n, 12) within :data:`MAX_ACTION` and
    :data:`MAX_COORDINATE`; empty lists give n = 0."""
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    if Y.size == 0:
        Y = Y.reshape(0, 12)
    if X.size == 0:  # also the n rows of a 0-dim GP, saved as [[], [], ...]
        X = X.reshape(Y.shape[0] if X.ndim == 2 else 0, d)
    if X.ndim != 2 or X.shape[1] != d:
        raise ModelFileError(f"training inputs must have shape (n, {d}), got {X.shape}")
    if not (np.all(np.abs(X) <= MAX_ACTION) and np.all(np.abs(Y) <= MAX_COORDINATE)):
        raise ModelFileError(f"GP training data contains NaN, inf, actions beyond {MAX_ACTION:g} or outputs beyond "
                             f"{MAX_COORDINATE:g}")
    return X, Y


class GPModel(LocalModel):
    """GP regression from the model's actions to the 12 components of ``parent2child``.

    Parameters
    ----------
    parent, child : int
        Part ids; the model predicts ``parent2child``.
    actions : tuple of int
        Indices of the actions the model depends on; ``()`` gives a GP that predicts the training mean.
    length_scale, signal_std_trans, signal_std_rot, noise_std_trans, noise_std_rot : float or None
        See :class:`GPHyperparameters`; ``None`` takes the default, :meth:`GPHyperparameters.from_marker_noise`
        without arguments (the value derived from the default ``BodySchemeConfig``).

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
            defaults = GPHyperparameters.from_marker_noise().to_dict()
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
        a = check_action_batch(a)
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
            model = cls._unfitted_from_dict(data)
            if "X" in data:
                d = len(model.actions)
                X, Y = _training_arrays(data["X"], data["Y"], d)
                if Y.ndim != 2 or Y.shape[1] != 12 or Y.shape[0] != X.shape[0] or X.shape[0] == 0:
                    raise ModelFileError(f"GP training data must be X (n, {d}) and Y (n, 12), n >= 1, got "
                                         f"X {X.shape} and Y {Y.shape}")
                model._fit_components(X, Y)
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, BodySchemeError, np.linalg.LinAlgError) as exc:
            keys = sorted(data) if isinstance(data, dict) else data
            raise ModelFileError(f"cannot read GP model from {keys!r}: {exc}") from exc
        return model
