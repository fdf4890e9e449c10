"""The observation noise as the learner knows it: a prior at first, then estimated from the joint fit's residuals.

The paper's validity thresholds are ``theta = 3 sigma`` (Sec. IV), with ``sigma`` the camera's marker noise; a user
rarely knows it, and a real camera's is not isotropic: along the ray to a marker the position is several times worse
than across it, and planar markers are now and then seen mirrored (the planar ambiguity). :class:`NoiseModel` starts
from a prior (the configuration's ``sigma_trans``/``sigma_rot``, or a generous default for ``"auto"``) and, after
every joint fit of the body scheme (:mod:`~body_scheme_core.calibration.joint_fit`), estimates per marker, in the camera
frame:

- ``lateral``: the per-axis standard deviation of the position across the ray (two axes),
- ``depth``: the same along the ray,
- ``rotation``: the per-axis standard deviation of the orientation's rotation vector.

Each is a robust scale of the marker's residuals over the fit's window (:func:`robust_variance`: a median start, then
the mean of the squares below the 99 % quantile, corrected for the cut), so mirrored orientations and misdetections
are outliers, not noise. A residual of a fitted model is a little smaller than the noise (the fit used some of it):
the estimate is divided by ``1 - p / N`` (``p`` fitted parameters, ``N`` residual components).

A wrong local model makes its markers' residuals larger, and a noise estimate that followed them would hide the very
error the validity thresholds must reveal. So the *pooled* estimate, which sets every threshold and detector, is the
median over the markers (a minority of wrong markers cannot move it), leaving out markers seen from one viewpoint only
(:data:`STILL_SPREAD`: the root's errors repeat from image to image and would make every other marker look wrong),
and a marker's own estimate is only used to
weigh its observations in the joint fit, shrunk towards the pooled one and kept within a factor 2 of it. Whether the
body scheme explains each marker is a separate test that does not depend on the noise level
(:mod:`~body_scheme_core.calibration.consistency`).

A detection that comes with its own covariance ``C`` (a tag detector's) is weighed in the joint fit by
:meth:`NoiseModel.detection_covariance`: ``C`` times a scale the model learns (:attr:`NoiseModel.detection_scale`), plus
the floor every estimate has (:data:`MIN_SIGMA_TRANS`, :data:`MIN_SIGMA_ROT`). A detector's covariance is right in its
shape (far, tilted and small markers worse, mostly along the ray) but rests on an assumed corner noise. The scale is
the robust scale of the residuals whitened by their own covariances, of the markers that moved as for the pooled
estimate (1 until :data:`MIN_OBSERVATIONS` of them; within :data:`MIN_DETECTION_SCALE` and
:data:`MAX_DETECTION_SCALE`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from ..errors import InvalidInputError, ModelFileError
from ..limits import MAX_NOISE
from ..state_values import integer, listing, mapping, number, optional_number, part_id

__all__ = ["NoiseModel", "robust_variance", "ray_components"]

#: Observations (over all markers) before the estimate replaces an ``auto`` prior, and per marker before its own
#: estimate counts.
MIN_OBSERVATIONS = 20
MIN_PART_OBSERVATIONS = 10
#: Pseudo-observations of a prior the user gave (it still yields to data, but not to the first few residuals).
PRIOR_WEIGHT = 50
#: Shrinkage of a marker's own estimate towards the pooled one (pseudo-observations), and the largest factor between
#: the two (standard deviations).
PART_SHRINKAGE = 20
PART_FACTOR = 2.0
#: The thresholds use the estimate's upper confidence bound: sigma times ``1 + THRESHOLD_MARGIN / sqrt(2 N)`` for ``N``
#: residual components (the estimate's relative standard error is ``1 / sqrt(2 N)``), so that a CUSUM sensitive to a
#: shift of one sigma does not alarm because the first few hundred residuals happened to be small.
THRESHOLD_MARGIN = 3.0
#: A marker whose observed positions over a fit's window spread less than this (RMS distance from their mean, m) was
#: seen from one viewpoint: its residuals say little about the noise of the markers that move (a still marker's
#: errors repeat; a rendered one's not at all), so it is left out of the pooled estimate unless no marker moved.
STILL_SPREAD = 0.02
#: Smallest standard deviations (per axis) the thresholds may use: below this a simulator is noise-free, not a camera.
MIN_SIGMA_TRANS = 2e-4
MIN_SIGMA_ROT = 2e-4
#: Smallest scale on the detections' own covariances: a detector that claims ten times its true noise is already far
#: off, and a scale near 0 (residuals a fit absorbed) would weigh those detections without bound.
MIN_DETECTION_SCALE = 0.1
#: Largest scale: residuals beyond ten times what the detector claims say its covariances are no use (and the state
#: file holds variances up to ``MAX_NOISE**2``).
MAX_DETECTION_SCALE = 10.0
_QUANTILE = 0.99
_CHANNELS = ("lateral", "depth", "rotation")
#: Degrees of freedom of one residual's squared norm per channel: lateral 2 axes, depth 1, rotation 3.
_DOF = np.array([2, 1, 3])


def _truncation(dof):
    """``(cut, factor)``: the chi-square quantile at :data:`_QUANTILE` and the mean of ``chi2(dof)`` below it."""
    cut = stats.chi2.ppf(_QUANTILE, dof)
    # E[X | X < c] for X ~ chi2(k): k P(chi2(k + 2) < c) / P(chi2(k) < c)
    return cut, dof * stats.chi2.cdf(cut, dof + 2) / _QUANTILE


_CUTS = [_truncation(k) for k in _DOF]
_MEDIANS = stats.chi2.median(_DOF)


def robust_variance(q, dof):
    """Per-axis variance from squared residual norms ``q`` of ``dof`` axes each, robust to a minority of outliers.

    ``q = sum of dof squared N(0, s^2)`` values, so ``q / s^2 ~ chi2(dof)``. Start from the median, ``s^2 =
    median(q) / median(chi2)``, then average the ``q`` below the chi-square's 99 % quantile at that scale and correct
    for the cut: efficient on Gaussian residuals, unmoved by a few mirrored orientations.

    Parameters
    ----------
    q : array-like, shape (n,)
    dof : int
        1, 2 or 3.

    Returns
    -------
    variance : float
        NaN for an empty ``q``.
    """
    q = np.asarray(q, dtype=float)
    if q.size == 0:
        return math.nan
    k = int(np.flatnonzero(_DOF == dof)[0]) if dof in _DOF else None
    cut, factor = _CUTS[k] if k is not None else _truncation(dof)
    median = _MEDIANS[k] if k is not None else stats.chi2.median(dof)
    s2 = float(np.median(q)) / median
    if s2 <= 0.0:
        return float(np.mean(q)) / dof
    for _ in range(2):
        kept = q[q <= cut * s2]
        if kept.size == 0:
            break
        s2 = float(np.mean(kept)) / factor
    return s2


def ray_components(residual, position):
    """Squared lengths of a position residual across and along the ray to the observed marker.

    Parameters
    ----------
    residual : ndarray, shape (n, 3)
        ``t_pred - t_obs`` in the camera frame (m).
    position : ndarray, shape (n, 3)
        Observed positions in the camera frame (the camera at the origin).

    Returns
    -------
    lateral, depth : ndarray, shape (n,)
        Squared norms (m^2) of the components perpendicular to and along the ray.
    """
    ray = position / np.maximum(np.linalg.norm(position, axis=1, keepdims=True), 1e-12)
    along = np.einsum("ni,ni->n", residual, ray)
    depth = along * along
    return np.maximum(np.einsum("ni,ni->n", residual, residual) - depth, 0.0), depth


class NoiseModel:
    """The marker noise the learner works with (see the module docstring).

    Parameters
    ----------
    part_ids : tuple of int
    sigma_trans, sigma_rot : float
        Prior: the 3D RMS of one marker's position (m) and rotation-vector (rad) error.
    auto : (bool, bool)
        Per channel (position, orientation): the prior is only a start, replaced by the estimate once
        :data:`MIN_OBSERVATIONS` residuals exist (the configuration's ``"auto"``, whose prior is generous so that the
        first trees form even with a noisy camera); otherwise it weighs like :data:`PRIOR_WEIGHT` observations.
    validity_sigmas : float
        ``theta = validity_sigmas * sigma`` (the paper's 3).
    theta_trans, theta_rot : float or None
        Fixed validity thresholds (m, rad); ``None``: ``validity_sigmas`` times the current estimate.

    Attributes
    ----------
    n_observations : int
        Residuals behind the pooled estimate (0 while it is the prior).
    """

    def __init__(self, part_ids, sigma_trans, sigma_rot, auto=(False, False), validity_sigmas=3.0, theta_trans=None,
                 theta_rot=None):
        self.part_ids = tuple(part_ids)
        self._index = {p: k for k, p in enumerate(self.part_ids)}
        self.auto = (bool(auto[0]), bool(auto[1]))
        prior_t, prior_r = float(sigma_trans), float(sigma_rot)
        if not (prior_t > 0 and prior_r > 0 and math.isfinite(prior_t) and math.isfinite(prior_r)):
            raise InvalidInputError(f"noise priors must be finite and > 0, got {sigma_trans!r}, {sigma_rot!r}")
        # Per-axis variances [lateral, depth, rotation]: the prior, isotropic.
        self.prior = np.array([prior_t**2 / 3.0, prior_t**2 / 3.0, prior_r**2 / 3.0])
        self.validity_sigmas = float(validity_sigmas)
        self.fixed_theta = (theta_trans, theta_rot)
        self.parts = np.full((len(self.part_ids), 3), np.nan)  # per-axis variances per marker (NaN: unknown)
        self.part_n = np.zeros(len(self.part_ids), dtype=np.int64)
        self.pooled = self.prior.copy()
        self.n_observations = 0
        self.detection = np.ones(2)  # variance factors on detections' own covariances: position, rotation
        self.n_detected = 0

    @classmethod
    def from_config(cls, part_ids, config):
        """The noise model of a :class:`~body_scheme_core.learning.config.BodySchemeConfig`: its priors (``"auto"`` or a
        number), ``validity_sigmas`` and fixed thresholds."""
        return cls(part_ids, config.prior_sigma_trans, config.prior_sigma_rot,
                   (config.sigma_trans == "auto", config.sigma_rot == "auto"), config.validity_sigmas,
                   config.theta_trans, config.theta_rot)

    # ------------------------------------------------------------------ what the learner uses
    @property
    def sigma_trans(self):
        """Pooled 3D RMS position noise (m): ``sqrt(2 lateral^2 + depth^2)``."""
        lateral, depth, _ = self.axis_sigmas()
        return math.sqrt(2.0 * lateral**2 + depth**2)

    @property
    def sigma_rot(self):
        """Pooled 3D RMS orientation noise (rad)."""
        return math.sqrt(3.0) * self.axis_sigmas()[2]

    @property
    def theta_trans(self):
        """Translational validity threshold (m) of one marker: fixed, or ``validity_sigmas`` times the upper
        confidence bound of ``sigma_trans`` (:data:`THRESHOLD_MARGIN`)."""
        fixed = self.fixed_theta[0]
        return float(fixed) if fixed is not None else self.validity_sigmas * self.sigma_trans * self._margin(0)

    @property
    def theta_rot(self):
        """Rotational validity threshold (rad), likewise."""
        fixed = self.fixed_theta[1]
        return float(fixed) if fixed is not None else self.validity_sigmas * self.sigma_rot * self._margin(1)

    def _margin(self, channel):
        """``1 + THRESHOLD_MARGIN / sqrt(2 N)`` for the residual components behind a channel's estimate (1 for a
        prior the user gave and no data; the generous ``auto`` prior needs none)."""
        n = 3 * self.n_observations + (0 if self.auto[channel] else PRIOR_WEIGHT)
        return 1.0 + THRESHOLD_MARGIN / math.sqrt(2.0 * n) if self.n_observations else 1.0

    @property
    def pooled(self):
        """Pooled per-axis variances ``[lateral, depth, rotation]``, shape (3,)."""
        return self._pooled

    @pooled.setter
    def pooled(self, value):
        self._pooled = np.asarray(value, dtype=float)
        floored = np.maximum(self._pooled, [MIN_SIGMA_TRANS**2, MIN_SIGMA_TRANS**2, MIN_SIGMA_ROT**2])
        self._pooled_sigmas = tuple(float(v) for v in np.sqrt(floored))

    def axis_sigmas(self, part=None):
        """Per-axis standard deviations ``(lateral, depth, rotation)``: pooled, or of one marker for the joint fit
        (its own estimate shrunk towards the pooled one and kept within a factor :data:`PART_FACTOR` of it)."""
        if part is None or part not in self._index:
            return self._pooled_sigmas
        k = self._index[part]
        n = self.part_n[k]
        if n < MIN_PART_OBSERVATIONS:
            return self._pooled_sigmas
        pooled = np.square(self._pooled_sigmas)
        own = (n * self.parts[k] + PART_SHRINKAGE * pooled) / (n + PART_SHRINKAGE)
        own = np.clip(own, pooled / PART_FACTOR**2, pooled * PART_FACTOR**2)
        return tuple(np.sqrt(own))

    @property
    def detection_scale(self):
        """``(position, rotation)``: the standard deviation of a residual whitened by its detection's own
        covariance (1: the detector's covariance as it is)."""
        return tuple(float(v) for v in np.sqrt(self.detection))

    def detection_covariance(self, C):
        """The covariance (6, 6) the joint fit weighs a detection of covariance ``C`` (6, 6) by: its blocks times
        the learned :attr:`detection_scale`, plus the floor of every estimate (a detector can be far surer than the
        residuals of a model allow)."""
        s = np.sqrt(self.detection)
        factor = np.repeat(s, 3)
        floor = np.repeat([MIN_SIGMA_TRANS**2, MIN_SIGMA_ROT**2], 3)
        return C * np.outer(factor, factor) + np.diag(floor)

    def rms(self):
        """``(sigma_trans, sigma_rot)``: the pooled 3D RMS noise (m, rad)."""
        return self.sigma_trans, self.sigma_rot

    def per_part(self):
        """``{part: (lateral, depth, rotation, n)}``: each marker's own per-axis estimate and its residual count
        (NaN where it has none)."""
        return {p: (*np.sqrt(self.parts[k]).tolist(), int(self.part_n[k])) for p, k in self._index.items()}

    # ------------------------------------------------------------------ estimation
    def update(self, parts, residual_t, residual_r, positions, dof_fraction=1.0, cap=False, detected=None):
        """Estimate the noise from the residuals of a joint fit.

        Parameters
        ----------
        parts : array-like of int, shape (n,)
            The marker of each residual.
        residual_t : ndarray, shape (n, 3)
            Position residuals ``t_pred - t_obs`` in the camera frame (m).
        residual_r : ndarray, shape (n, 3)
            Orientation residuals as rotation vectors (rad).
        positions : ndarray, shape (n, 3)
            Observed positions (camera frame), for the rays.
        dof_fraction : float
            ``1 - p / N`` of the fit: the expected fraction of the noise variance left in its residuals.
        cap : bool
            The pooled estimate may not exceed the prior (a provisional body scheme's residuals can only lower a
            generous prior).
        detected : tuple of (ndarray of bool, shape (n,), ndarray, shape (n, 6)), optional
            ``(mask, whitened)``: which residuals came with a detection's own covariance, and those residuals
            whitened by it alone (position, rotation; other rows ignored); they teach :attr:`detection_scale`.

        Returns
        -------
        changed : float
            Largest relative change of a pooled per-axis standard deviation.
        """
        parts = np.asarray(parts)
        if parts.size == 0:
            return 0.0  # nothing explained yet: keep what is known
        lateral, depth = ray_components(np.asarray(residual_t, dtype=float), np.asarray(positions, dtype=float))
        q = np.stack([lateral, depth, np.einsum("ni,ni->n", residual_r, residual_r)], axis=1)
        fraction = min(max(float(dof_fraction), 0.5), 1.0)
        positions = np.asarray(positions, dtype=float)
        estimates, still_estimates, moving = [], [], np.zeros(parts.size, dtype=bool)
        self.parts[:] = np.nan
        self.part_n[:] = 0
        for part in np.unique(parts):
            k = self._index.get(int(part))
            if k is None:
                continue
            sel = parts == part
            self.parts[k] = [robust_variance(q[sel, c], _DOF[c]) / fraction for c in range(3)]
            self.part_n[k] = int(sel.sum())
            spread = math.sqrt(np.mean(np.sum((positions[sel] - positions[sel].mean(axis=0)) ** 2, axis=1)))
            moving[sel] = spread >= STILL_SPREAD
            if self.part_n[k] >= MIN_PART_OBSERVATIONS:
                (estimates if spread >= STILL_SPREAD else still_estimates).append(self.parts[k])
        if not moving.any():  # nothing moved: the still markers are all there is
            estimates, moving[:] = still_estimates, True
        before = np.sqrt(self.pooled)
        pooled = self.pooled.copy()
        n = int(moving.sum())
        if estimates:
            data = np.median(np.asarray(estimates), axis=0)
        else:  # every marker seen only a few times: pool the residuals themselves
            data = np.array([robust_variance(q[moving, c], _DOF[c]) / fraction for c in range(3)])
        for c, auto in ((0, self.auto[0]), (1, self.auto[0]), (2, self.auto[1])):
            if auto:
                pooled[c] = data[c] if n >= MIN_OBSERVATIONS else self.prior[c]
            else:
                pooled[c] = (PRIOR_WEIGHT * self.prior[c] + n * data[c]) / (PRIOR_WEIGHT + n)
        if cap:
            pooled = np.minimum(pooled, self.prior)
        self.pooled = pooled
        self.n_observations = n
        if detected is not None:
            self._update_detection(detected[0] & moving, detected[1], fraction)
        return float(np.max(np.abs(np.sqrt(self.pooled) / before - 1.0)))

    def _update_detection(self, mask, whitened, fraction):
        """The detection scale from residuals whitened by their own covariances (:meth:`update`)."""
        mask = np.asarray(mask, dtype=bool)
        self.n_detected = int(mask.sum())
        if self.n_detected < MIN_OBSERVATIONS:
            return
        w = np.asarray(whitened, dtype=float)[mask]
        for c, block in enumerate((w[:, :3], w[:, 3:])):
            variance = robust_variance(np.sum(block**2, axis=1), 3) / fraction
            self.detection[c] = min(max(variance, MIN_DETECTION_SCALE**2), MAX_DETECTION_SCALE**2)

    # ------------------------------------------------------------------ copies and state
    def copy(self):
        """An independent copy (for the learner's step snapshot)."""
        clone = NoiseModel.__new__(NoiseModel)
        vars(clone).update(vars(self))
        clone.parts, clone.part_n, clone.detection = self.parts.copy(), self.part_n.copy(), self.detection.copy()
        return clone

    def to_dict(self):
        """JSON-serialisable state: the per-marker and pooled per-axis variances and the residual count."""
        return {"parts": [[p, *(None if not math.isfinite(v) else float(v) for v in self.parts[k]),
                           int(self.part_n[k])] for p, k in self._index.items()],
                "pooled": self.pooled.tolist(), "n_observations": self.n_observations,
                "detection": self.detection.tolist(), "n_detected": self.n_detected}

    def load_dict(self, data):
        """Restore :meth:`to_dict` output into this model (its parts and priors come from the configuration).

        Raises
        ------
        ModelFileError
            On a missing key, an unknown part, or a variance that is not a finite number >= 0.
        """
        data = mapping(data, "noise state")
        missing = sorted({"pooled", "n_observations", "parts"} - set(data))
        if missing:
            raise ModelFileError(f"noise state is missing {missing}")
        high = MAX_NOISE**2
        pooled = np.array([number(v, "noise state pooled variance", maximum=high, above=0.0)
                           for v in listing(data["pooled"], "noise state pooled", 3)])
        n = integer(data["n_observations"], "noise state n_observations")
        parts = np.full((len(self.part_ids), 3), np.nan)
        part_n = np.zeros(len(self.part_ids), dtype=np.int64)
        for row in listing(data["parts"], "noise state parts"):
            p, *values, count = listing(row, "noise state part row [id, lateral, depth, rotation, n]", 5)
            k = self._index[part_id(p, self._index, "noise state")]
            parts[k] = [optional_number(v, f"noise state variance of part {p}", minimum=0.0, maximum=high)
                        for v in values]
            part_n[k] = integer(count, f"noise state count of part {p}")
        self.parts, self.part_n, self.pooled, self.n_observations = parts, part_n, pooled, n
        # (files written before detections' own covariances were used have neither)
        self.detection = np.array([number(v, "noise state detection scale", maximum=MAX_DETECTION_SCALE**2, above=0.0)
                                   for v in listing(data.get("detection", [1.0, 1.0]), "noise state detection", 2)])
        self.n_detected = integer(data.get("n_detected", 0), "noise state n_detected")
        return self
