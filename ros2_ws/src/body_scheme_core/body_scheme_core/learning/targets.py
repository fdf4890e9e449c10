"""What tracked models are tested against, and learn from, in one step (:class:`Targets`), and the translational
threshold of a relative observation (:func:`translation_threshold`).

The learner forms them two ways: the relative observations ``Y_i^-1 Y_j`` of every observed pair while bootstrapping
(:mod:`~body_scheme_core.learning.relative`), the chain-consistent observations of the calibrated body scheme
afterwards (:mod:`~body_scheme_core.learning.chain`); the pool judges and trains its models on them
(:meth:`~body_scheme_core.learning.pool.ModelPool.evaluate`, :meth:`~body_scheme_core.learning.pool.ModelPool.train`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .quality import prediction_errors

__all__ = ["Targets", "translation_threshold"]


class Targets(NamedTuple):
    """What tracked models are tested against (and candidates learn from) in one step.

    Attributes
    ----------
    Z : ndarray, shape (k, 4, 4)
        Observed ``parent2child`` per model, oriented as the model predicts.
    theta_trans : ndarray, shape (k,)
        Translational validity threshold of each sample (m).
    theta_rot : ndarray, shape (k,)
        Rotational validity threshold of each sample (rad).
    sigma : ndarray, shape (k, 2)
        Per-axis noise std of each sample (trans m, rot rad), for the rigid candidates' weighting.
    flip : ndarray of bool, shape (k,)
        Where ``Z`` is the *inverse* of what the model predicts: the prediction is inverted before the comparison,
        so the error is measured in the direction whose translation carries no parent-orientation lever arm.
    alternatives : ndarray, shape (k, 3, 4, 4), or None
        Other readings of each ``Z`` (its poses mirrored about the camera's ray,
        :attr:`~body_scheme_core.learning.relative.RelativeObservations.alternatives`); a model is judged against,
        and learns from, the reading nearest its prediction (:meth:`nearest`). None: ``Z`` only.
    """

    Z: np.ndarray
    theta_trans: np.ndarray
    theta_rot: np.ndarray
    sigma: np.ndarray
    flip: np.ndarray
    alternatives: np.ndarray | None = None

    def select(self, index):
        """The rows ``index``."""
        return Targets(self.Z[index], self.theta_trans[index], self.theta_rot[index], self.sigma[index],
                       self.flip[index], None if self.alternatives is None else self.alternatives[index])

    def nearest(self, Zp, index=slice(None)):
        """Of rows ``index``, the observed transform, or the alternative reading (poses mirrored about the ray) that
        explains the predictions ``Zp`` where it does not: off by more than a threshold while the alternative is
        within both and less than half as far (in threshold units, the larger of the two errors)."""
        Z = self.Z[index]
        if self.alternatives is None:
            return Z
        options = np.concatenate([Z[:, None], self.alternatives[index]], axis=1)
        e_t, e_r = prediction_errors(Zp[:, None], options)
        ratio = np.maximum(e_t / self.theta_trans[index][:, None], e_r / self.theta_rot[index][:, None])
        best = 1 + np.argmin(ratio[:, 1:], axis=1)
        k = np.arange(len(Z))
        use = (ratio[:, 0] > 1.0) & (ratio[k, best] <= 1.0) & (ratio[k, best] < 0.5 * ratio[:, 0])
        return np.where(use[:, None, None], options[k, best], Z)


def translation_threshold(theta_trans, theta_rot, distance):
    """Validity threshold of the translational error of a relative observation whose parts are ``distance`` apart.

    ``Z_ij = Y_i^-1 Y_j`` expresses the child's observed position in the parent's *observed* frame, so the parent's
    orientation noise (RMS angle ``sigma_rot``) moves it by the lever arm: RMS ``sqrt(2/3) sigma_rot d`` (only the
    rotation components perpendicular to the offset count). The threshold grows the same way::

        theta_t(d) = sqrt(theta_trans^2 + (2/3) theta_rot^2 d^2)

    It equals the paper's ``theta_trans`` for coincident parts. Without it a perfect model of two markers 0.5 m
    apart has a mean error near ``theta_trans`` at the paper's noise (15 deg), and validity becomes a coin toss.

    Parameters
    ----------
    theta_trans, theta_rot : float
        Validity thresholds (m, rad).
    distance : float or array-like
        Observed distance between the two parts (m).

    Returns
    -------
    theta : float or ndarray
    """
    d = np.asarray(distance, dtype=float)
    theta = np.sqrt(theta_trans**2 + (2.0 / 3.0) * theta_rot**2 * d * d)
    return float(theta) if theta.ndim == 0 else theta
