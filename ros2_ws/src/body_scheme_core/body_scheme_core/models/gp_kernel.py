"""Kernel, hyperparameters and output layout of the Gaussian-process local models (paper Sec. III-B).

Shared by :class:`~body_scheme_core.models.gp.GPModel` (one GP) and :class:`~body_scheme_core.models.gp_batch.GPBatch`
(hundreds of GP candidates learning at once). Both regress the 12 free components of ``Z = parent2child``,
``[R (row-major, 9), t (3)]`` (:data:`ROT_OUTPUTS`, :data:`TRANS_OUTPUTS`), each component independently.

Parametrisation:

- kernel ``k(a, a') = s_o^2 exp(-|a - a'|^2 / (2 l^2))`` over the model's actions, one length scale ``l`` (rad);
- prior mean per output = the mean of that output over the training set (constant mean, recomputed as data
  arrive), so a GP far from its data predicts the training mean;
- signal std ``s_o``: ``signal_std_rot`` for the nine rotation-matrix entries, ``signal_std_trans`` (m) for the
  three translations;
- white observation noise ``n_o``: ``noise_std_rot`` (matrix entries), ``noise_std_trans`` (m).

Only the ratio ``r_o = n_o / s_o`` enters the posterior mean: ``mu = ybar + k*^T (K + r^2 I)^-1 (y - ybar)`` with the
unit-amplitude kernel ``K``. When the translational and rotational ratios are equal, ONE factorisation per model
serves all 12 outputs; :meth:`GPHyperparameters.from_marker_noise` makes them equal (see its docstring). Unequal
ratios are supported, at twice the cost.

The candidates keep fixed hyperparameters (no marginal-likelihood optimisation), so that they stay comparable and
cheap to update online. A :class:`~body_scheme_core.models.gp.GPModel` fitted with ``optimize=True`` (the GP edges
of the body scheme in the joint fit, config ``gp_optimize``) first chooses its length scale and noise-to-signal ratio
by maximum marginal likelihood (:func:`marginal_likelihood_hyperparameters`).

Uncertainty: predictions with ``return_std=True`` give the latent (noise-free) predictive std, summarised per
sample as a per-axis translational std (m) and a per-axis rotational std (rad); see :func:`summarise_std`.

The defaults (``DEFAULT_*``) live here, not in the learner's configuration: models do not depend on
:mod:`~body_scheme_core.learning.config`, whose ``BodySchemeConfig`` takes its defaults of these values from this
module.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass

import numpy as np
from scipy.linalg import cho_solve

from ..errors import InvalidInputError

__all__ = [
    "ROT_OUTPUTS",
    "TRANS_OUTPUTS",
    "DEFAULT_LENGTH_SCALE",
    "DEFAULT_SIGNAL_STD_TRANS",
    "DEFAULT_SIGNAL_STD_ROT",
    "DEFAULT_SIGMA_TRANS",
    "DEFAULT_SIGMA_ROT",
    "squared_exponential",
    "squared_exponential_gradient",
    "summarise_std",
    "GPHyperparameters",
    "log_marginal_likelihood",
    "marginal_likelihood_hyperparameters",
]

#: Index of the rotation-matrix outputs and of the translation outputs in the 12-vector.
ROT_OUTPUTS = slice(0, 9)
TRANS_OUTPUTS = slice(9, 12)
#: Per-axis rotation std (rad) of a small random rotation whose matrix entries have std 1: E|[w]x R|_F^2 = 6 s^2
#: spread over 9 entries gives an entry variance of (2/3) s^2.
ROT_STD_PER_ENTRY_STD = math.sqrt(1.5)
#: Default length scale of the kernel (rad) and signal stds (m; rotation-matrix entries). ``BodySchemeConfig``
#: takes its ``gp_length_scale``, ``gp_signal_std_trans`` and ``gp_signal_std_rot`` defaults from here.
DEFAULT_LENGTH_SCALE = 1.0
DEFAULT_SIGNAL_STD_TRANS = 0.3
DEFAULT_SIGNAL_STD_ROT = 0.7
#: Default noise of one marker, the RMS 3D error of its position (m) and of its rotation vector (rad), from which the
#: default noise stds are derived (:meth:`GPHyperparameters.from_marker_noise`). ``BodySchemeConfig`` takes its
#: ``sigma_trans`` and ``sigma_rot`` defaults from here.
DEFAULT_SIGMA_TRANS = 0.05
DEFAULT_SIGMA_ROT = math.radians(15.0)


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
    """Hyperparameters of the GP local models (see the module docstring for the parametrisation).

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
        """Derive the hyperparameters from a :class:`~body_scheme_core.learning.config.BodySchemeConfig`: its marker
        noise prior (``prior_sigma_trans``, ``prior_sigma_rot``) and its ``gp_length_scale``, ``gp_signal_std_trans``,
        ``gp_signal_std_rot`` (see :meth:`from_marker_noise`)."""
        return cls.from_marker_noise(config.prior_sigma_trans, config.prior_sigma_rot, config.gp_length_scale,
                                     config.gp_signal_std_trans, config.gp_signal_std_rot)

    @classmethod
    def from_marker_noise(cls, sigma_trans=DEFAULT_SIGMA_TRANS, sigma_rot=DEFAULT_SIGMA_ROT,
                          length_scale=DEFAULT_LENGTH_SCALE, signal_std_trans=DEFAULT_SIGNAL_STD_TRANS,
                          signal_std_rot=DEFAULT_SIGNAL_STD_ROT):
        """Derive the noise stds from the noise of one marker; with no arguments, the default hyperparameters.

        Physical noise: ``sigma_trans`` and ``sigma_rot`` are the RMS 3D errors of one marker's position (m) and
        rotation vector (rad), so per axis ``s_t = sigma_trans / sqrt(3)`` and ``s_r = sigma_rot / sqrt(3)``. A
        relative observation ``Z = Y_i^-1 Y_j`` combines two markers, so per axis its translation has std
        ``sqrt(2) s_t`` and its rotation vector ``sqrt(2) s_r``; a rotation vector with per-axis std ``s`` perturbs
        each matrix entry with std ``sqrt(2/3) s`` on average, giving a per-entry noise ``(2 / sqrt(3)) s_r``.
        ``length_scale``, ``signal_std_trans`` and ``signal_std_rot`` are taken as given.

        One ratio: the posterior mean only depends on noise/signal, so both output groups get the LARGER of the
        two physical ratios and the noise of the other group is raised to match; one factorisation then serves all
        12 outputs. For translation this is also physically right: the orientation noise of ``Y_i`` moves the
        origin of ``Y_j`` by ``|t_ij| s_r``, a lever-arm term the ``sqrt(2) s_t`` estimate leaves out (with the
        defaults the raised translational noise, 0.075 m, is about that per axis at ``|t_ij|`` = 0.5 m). On simulated
        chains this choice predicted better than two separate ratios and than the translational ratio for all
        outputs (docs/core/local-models.md).
        """
        noise_trans = math.sqrt(2.0) * sigma_trans / math.sqrt(3.0)
        noise_rot = 2.0 / math.sqrt(3.0) * sigma_rot / math.sqrt(3.0)
        ratio = max(noise_trans / signal_std_trans, noise_rot / signal_std_rot)
        return cls(length_scale=length_scale, signal_std_trans=signal_std_trans,
                   signal_std_rot=signal_std_rot, noise_std_trans=ratio * signal_std_trans,
                   noise_std_rot=ratio * signal_std_rot)

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
