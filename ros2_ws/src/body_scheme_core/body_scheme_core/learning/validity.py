"""The validity monitor: test windows, validity and CUSUM change detection of tracked models (paper Eq. 5-6).

A local model is judged by how well it predicts observations it has *not* been trained on. The learner evaluates
prequentially (test-then-train): each new observation ``Z`` is first predicted, the error
(:func:`~body_scheme_core.learning.quality.prediction_errors`) enters the model's test window, and only then may the
sample be added to the model's training set.

Errors are split into a translational part (m) and a rotational part (rad), because the two have different units
and noise levels; the paper's single norm ``||Z - Z'||`` (Eq. 6) mixes them. A model is *valid* (Eq. 5-6 with
``theta = 3 sigma``) when its mean errors over the test window are below both thresholds.

Thresholds. ``theta_trans`` and ``theta_rot`` are ``validity_sigmas`` times the marker noise, which the learner
estimates as it goes (:mod:`~body_scheme_core.calibration.noise_model`): :meth:`ValidityMonitor.set_thresholds` gives
the monitor the current ones, and every stored error is judged against them, old samples too. The rotational threshold
is ``theta_rot`` for every sample. The translational threshold of a sample grows with the lever arm between its two
parts, so it is computed per sample where the sample is formed and recorded with its errors:
:func:`~body_scheme_core.learning.targets.translation_threshold` for the relative observations of
:mod:`~body_scheme_core.learning.relative`, :meth:`~body_scheme_core.learning.chain.ChainTargets.threshold` for
chain-consistent targets; it travels to :meth:`ValidityMonitor.record` in
:class:`~body_scheme_core.learning.targets.Targets`, and the monitor keeps it as a multiple of the ``theta_trans`` of
that moment (the lever-arm factor, at least 1), so it follows the noise estimate too.

The monitor is *batched*: one object holds the windows of hundreds of candidate models in ``(rows, W)`` arrays, with
``allocate``/``release`` row management like :class:`~body_scheme_core.models.gp_batch.GPBatch`, so one learner step
costs a handful of numpy calls instead of one Python loop iteration per candidate.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import InvalidInputError

__all__ = ["RATIO_CLIP", "WindowStats", "ValidityMonitor"]

#: Per-sample errors enter window means (validity, quality, paired comparisons) in threshold units clipped to this:
#: one outlier (a misdetection) moves a window mean by at most ``RATIO_CLIP / window`` thresholds, while a model whose
#: errors all exceed the threshold still averages above 1.
RATIO_CLIP = 2.0


class WindowStats(NamedTuple):
    """Test-window statistics of k models (arrays of shape (k,)); means are ``inf`` where ``n == 0``.

    Attributes
    ----------
    n : ndarray of int
        Number of counted samples.
    trans_error, rot_error : ndarray
        Mean errors (m, rad).
    trans_ratio, rot_ratio : ndarray
        Mean of the per-sample errors divided by their thresholds; the model is valid when both are below 1.
    theta_trans, theta_rot : ndarray
        Mean effective thresholds (m, rad) over the counted samples.
    """

    n: np.ndarray
    trans_error: np.ndarray
    rot_error: np.ndarray
    trans_ratio: np.ndarray
    rot_ratio: np.ndarray
    theta_trans: np.ndarray
    theta_rot: np.ndarray


class ValidityMonitor:
    """The validity monitor: test windows, validity and CUSUM change detectors of many models at once, one row each.

    Each row holds a ring buffer of the last ``window`` per-sample errors (translational, rotational) with their
    translational threshold (see :func:`~body_scheme_core.learning.targets.translation_threshold`), the step index at
    which they were observed and the number of training samples the model had when it predicted them, plus a
    one-sided CUSUM per error channel.

    Parameters
    ----------
    window : int
        ``|D_test|``, the ring buffer length (>= 1).
    capacity : int
        Initial number of rows; grows on demand.
    theta_trans, theta_rot : float
        Validity thresholds (m, rad); ``theta_trans`` is the default per-sample translational threshold.
    cusum_drift : float
        Reference value ``k`` of the CUSUM: a sample raises the statistic by the amount its squared error in noise
        units exceeds ``k`` (1 on average for a right model).
    cusum_threshold : float
        Alarm level ``h``, same units.
    cusum_clip : float
        Squared errors are clipped to this value before entering the CUSUM, so that one outlier (a misdetected marker)
        raises it by at most ``cusum_clip - cusum_drift``; an alarm then needs at least ``ceil(h / (cusum_clip - k))``
        bad samples.
    sigmas : float
        Thresholds in noise sigmas (``validity_sigmas``, the paper's 3): a threshold over this is the sample's noise.

    Notes
    -----
    The CUSUM of a channel is ``S <- max(0, S + min(x, clip) - k)`` with ``x = (sigmas e / theta)^2``, the squared
    error in units of the sample's noise (the marker's, plus the predicted parent's for chain-consistent targets): a
    chi-square statistic with mean 1 while the model is right and ``1 + (d / sigma)^2`` after a change that moves the
    part by ``d``, so a shift of one noise sigma is found within about ten samples and a shift of three within three
    (docs/core/learning-and-adaptation.md). Its change-point estimate is the step of the first sample of the current
    excursion above zero (where ``S`` last left zero): for an abrupt change this is about the first sample after the
    change, so data from there on is post-change data.
    """

    ARRAYS = ("errors", "thresholds", "steps", "n_train", "head", "count", "cusum", "cusum_start", "in_use")

    def __init__(self, window, capacity=0, theta_trans=0.15, theta_rot=0.7853981633974483, cusum_drift=1.5,
                 cusum_threshold=12.0, cusum_clip=6.0, sigmas=3.0):
        if isinstance(window, bool) or not (isinstance(window, (int, np.integer)) and window >= 1):
            raise InvalidInputError(f"window must be an integer >= 1, got {window!r}")
        if not (theta_trans > 0 and theta_rot > 0):
            raise InvalidInputError(f"thresholds must be > 0, got {theta_trans!r}, {theta_rot!r}")
        if not (cusum_clip > cusum_drift > 0 and cusum_threshold > 0):
            raise InvalidInputError(
                f"need cusum_clip > cusum_drift > 0 and cusum_threshold > 0, got clip {cusum_clip}, "
                f"drift {cusum_drift}, threshold {cusum_threshold}")
        self.window = int(window)
        self.theta = np.array([theta_trans, theta_rot], dtype=float)
        if not sigmas > 0:
            raise InvalidInputError(f"sigmas must be > 0, got {sigmas!r}")
        self.cusum_drift = float(cusum_drift)
        self.cusum_threshold = float(cusum_threshold)
        self.cusum_clip = float(cusum_clip)
        self.sigmas = float(sigmas)
        self._resize(int(capacity))

    @classmethod
    def from_config(cls, config, capacity=0):
        """An empty monitor with the test window and the CUSUM settings of ``config``, and the thresholds of its noise
        prior (or its fixed thresholds) until :meth:`set_thresholds`."""
        c = config
        theta_t = c.theta_trans if c.theta_trans is not None else c.validity_sigmas * c.prior_sigma_trans
        theta_r = c.theta_rot if c.theta_rot is not None else c.validity_sigmas * c.prior_sigma_rot
        return cls(c.test_window, capacity, theta_t, theta_r, c.cusum_drift, c.cusum_threshold, c.cusum_clip,
                   c.validity_sigmas)

    def set_thresholds(self, theta_trans, theta_rot):
        """The current validity thresholds (m, rad) of one marker: every stored error is judged against them."""
        if not (theta_trans > 0 and theta_rot > 0 and np.isfinite(theta_trans) and np.isfinite(theta_rot)):
            raise InvalidInputError(f"thresholds must be finite and > 0, got {theta_trans!r}, {theta_rot!r}")
        self.theta = np.array([theta_trans, theta_rot], dtype=float)

    # ------------------------------------------------------------------ rows
    def empty_rows(self, capacity):
        W = self.window
        return {
            "errors": np.zeros((capacity, W, 2)),
            "thresholds": np.ones((capacity, W, 2)),
            "steps": np.full((capacity, W), -1, dtype=np.int64),
            "n_train": np.zeros((capacity, W), dtype=np.int64),
            "head": np.zeros(capacity, dtype=np.int64),
            "count": np.zeros(capacity, dtype=np.int64),
            "cusum": np.zeros((capacity, 2)),
            "cusum_start": np.full((capacity, 2), -1, dtype=np.int64),
            "in_use": np.zeros(capacity, dtype=bool),
        }

    def _resize(self, capacity):
        arrays = self.empty_rows(capacity)
        if hasattr(self, "errors"):
            k = min(self.capacity, capacity)
            for name in self.ARRAYS:
                arrays[name][:k] = getattr(self, name)[:k]
        for name, value in arrays.items():
            setattr(self, name, value)

    @property
    def capacity(self):
        """Number of rows currently allocated in memory (used or free)."""
        return self.errors.shape[0]

    def allocate(self, k):
        """Reserve ``k`` empty rows; returns their indices (ndarray of int, shape (k,)), lowest free first."""
        free = np.flatnonzero(~self.in_use)
        if free.size < k:
            self._resize(max(2 * self.capacity, self.capacity + k - free.size))
            free = np.flatnonzero(~self.in_use)
        rows = free[:k]
        self.clear(rows)
        self.in_use[rows] = True
        return rows

    def release(self, rows):
        """Free rows for reuse."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        self.clear(rows)
        self.in_use[rows] = False

    def clear(self, rows):
        """Empty the windows and reset the CUSUMs of ``rows``."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        empty = self.empty_rows(1)
        for name in self.ARRAYS:
            if name != "in_use":
                getattr(self, name)[rows] = empty[name][0]

    def copy_rows(self, other, src_rows, dst_rows):
        """Copy windows and CUSUMs of ``src_rows`` of monitor ``other`` into ``dst_rows`` of this one."""
        if other.window != self.window:
            raise InvalidInputError(f"window lengths differ: {other.window} != {self.window}")
        s = np.asarray(src_rows, dtype=np.int64)
        d = np.asarray(dst_rows, dtype=np.int64)
        for name in self.ARRAYS:
            if name != "in_use":
                getattr(self, name)[d] = getattr(other, name)[s]

    # ------------------------------------------------------------------ recording
    def record(self, rows, trans_error, rot_error, step, n_train=0, cusum=True, theta_trans=None, theta_rot=None):
        """Append one error sample to each row and update its CUSUMs.

        Parameters
        ----------
        rows : array-like of int, shape (k,)
            Distinct rows.
        trans_error, rot_error : array-like, shape (k,)
            Per-sample errors (m, rad).
        step : int
            Time step of the observation.
        n_train : int or array-like of int, shape (k,)
            Training samples each model had when it made the prediction (for :meth:`stats`' staleness rule).
        cusum : bool or array-like of bool, shape (k,)
            Whether to update the CUSUMs too (per row, or for all).
        theta_trans : float or array-like, shape (k,), optional
            Translational threshold of each sample
            (:func:`~body_scheme_core.learning.targets.translation_threshold`); default ``theta[0]``.
        theta_rot : float or array-like, shape (k,), optional
            Rotational threshold of each sample (larger than ``theta[1]`` where the target's own orientation is
            uncertain); default ``theta[1]``.

        Returns
        -------
        alarm : ndarray of bool, shape (k,)
            CUSUM at or above the threshold in either channel after this sample.
        """
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if rows.size == 0:
            return np.zeros(0, dtype=bool)
        e = np.stack([np.asarray(trans_error, dtype=float).reshape(-1),
                      np.asarray(rot_error, dtype=float).reshape(-1)], axis=1)
        theta = np.stack([np.broadcast_to(self.theta[c] if value is None else np.asarray(value, dtype=float),
                                          rows.shape) for c, value in enumerate((theta_trans, theta_rot))], axis=1)
        pos = self.head[rows]
        self.errors[rows, pos] = e
        self.thresholds[rows, pos] = theta / self.theta  # factors over the thresholds of the moment: follow them
        self.steps[rows, pos] = step
        self.n_train[rows, pos] = n_train
        self.head[rows] = (pos + 1) % self.window
        self.count[rows] += 1
        use = np.broadcast_to(np.asarray(cusum, dtype=bool), rows.shape)
        if not np.any(use):
            return np.zeros(rows.size, dtype=bool)
        x = (self.sigmas * e / theta) ** 2
        if not np.all(use):
            alarm = np.zeros(rows.size, dtype=bool)
            alarm[use] = self._update_cusum(rows[use], x[use], step)
            return alarm
        return self._update_cusum(rows, x, step)

    def _update_cusum(self, rows, x, step):
        x = np.minimum(x, self.cusum_clip)
        S_old = self.cusum[rows]
        S = np.maximum(0.0, S_old + x - self.cusum_drift)
        start = self.cusum_start[rows]
        start[(S_old <= 0.0) & (S > 0.0)] = step
        start[S <= 0.0] = -1
        self.cusum[rows] = S
        self.cusum_start[rows] = start
        return np.any(S >= self.cusum_threshold, axis=1)

    def forget_before(self, rows, step):
        """Drop window samples observed before ``step`` (e.g. from before a change point); the CUSUMs are kept."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        steps = self.steps[rows]
        steps[steps < step] = -1
        self.steps[rows] = steps

    def forget_since(self, rows, step):
        """Drop window samples observed at or after ``step`` (errors that followed from a change elsewhere)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        steps = self.steps[rows]
        steps[steps >= step] = -1
        self.steps[rows] = steps

    def reset_cusum(self, rows):
        """Set the CUSUMs of ``rows`` back to zero (after a model was (re)installed)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        self.cusum[rows] = 0.0
        self.cusum_start[rows] = -1

    # ------------------------------------------------------------------ statistics
    def _mask(self, rows, n_train, stale_fraction):
        mask = self.steps[rows] >= 0
        if n_train is not None and stale_fraction > 0.0:
            floor = np.floor(stale_fraction * np.asarray(n_train, dtype=float)).astype(np.int64).reshape(-1, 1)
            mask &= self.n_train[rows] >= floor
        return mask

    def _ratios(self, rows):
        """Per-sample errors in threshold units, clipped at :data:`RATIO_CLIP`, shape (k, W, 2).

        Validity, quality and the paired comparisons all use these clipped ratios.
        """
        return np.minimum(self.errors[rows] / (self.theta * self.thresholds[rows]), RATIO_CLIP)

    def stats(self, rows, since=None, n_train=None, stale_fraction=0.0):
        """Test-window statistics of ``rows``.

        Parameters
        ----------
        rows : array-like of int, shape (k,)
        since : int or array-like of int, shape (k,), optional
            Count only samples observed at or after this step (errors since a change point).
        n_train : int or array-like of int, shape (k,), optional
            Current number of training samples of each model.
        stale_fraction : float
            With ``n_train``: ignore errors of predictions the model made while it had fewer than
            ``floor(stale_fraction * n_train)`` training samples. While a model is still learning, its early
            predictions say little about the current model, so they would keep it invalid for a whole window.

        Returns
        -------
        stats : WindowStats
        """
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        mask = self._mask(rows, n_train, stale_fraction)
        if since is not None:
            mask &= self.steps[rows] >= np.asarray(since, dtype=np.int64).reshape(-1, 1)
        n = mask.sum(axis=1)
        w = mask.astype(float)
        values = np.concatenate([self.errors[rows], self._ratios(rows), self.theta * self.thresholds[rows]], axis=-1)
        total = np.einsum("kw,kwc->kc", w, values)
        mean = np.where(n[:, None] > 0, total / np.maximum(n, 1)[:, None], np.inf)
        return WindowStats(n, mean[:, 0], mean[:, 1], mean[:, 2], mean[:, 3], mean[:, 4], mean[:, 5])

    def hopeless(self, rows, n_samples, ratio, min_train):
        """Rows whose last ``n_samples`` errors all exceed ``ratio`` times the threshold (in either channel), each
        predicted by a model trained on at least ``min_train`` samples: invalid with high confidence (racing).

        For a right model every such error is beyond ``3 ratio`` noise sigmas (``ratio`` 2: a chance below 1e-6 per
        sample), so ``n_samples`` in a row do not happen; a model trained on that many samples is past its first
        guesses. Returns a bool array, shape (k,)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if n_samples < 1 or n_samples > self.window or rows.size == 0:
            return np.zeros(rows.size, dtype=bool)
        last = (self.head[rows][:, None] - 1 - np.arange(n_samples)[None, :]) % self.window
        pick = (rows[:, None], last)
        far = np.any(self.errors[pick] > ratio * self.theta * self.thresholds[pick], axis=-1)
        return np.all(far & (self.steps[pick] >= 0) & (self.n_train[pick] >= min_train), axis=1)

    def valid(self, stats, min_samples):
        """Validity (paper Eq. 5-6): at least ``min_samples`` samples and both mean error ratios below 1.

        With a constant translational threshold this is exactly "mean error below the threshold".
        """
        return (stats.n >= min_samples) & (stats.trans_ratio < 1.0) & (stats.rot_ratio < 1.0)

    def paired_difference(self, rows_a, rows_b, n_train_a=None, n_train_b=None, stale_fraction=0.0, since=None):
        """Mean of ``(e_a - e_b) / theta`` per channel over the samples both rows observed at the same step.

        Two models of one pair of parts see the same observations, so this is a paired comparison on identical
        samples: the observation noise largely cancels and a small mean difference is already significant. Both
        errors of a sample are measured against the same threshold, the smaller of the two rows' (each clipped at
        :data:`RATIO_CLIP`): a model whose own uncertainty widens its threshold (a GP far from its data) is judged
        on how close it comes, not on what it claims.

        Parameters
        ----------
        rows_a, rows_b : array-like of int, shape (k,)
        n_train_a, n_train_b : array-like of int, shape (k,), optional
            Current training-set sizes, for the staleness rule of :meth:`stats`.
        stale_fraction : float
        since : int or array-like of int, shape (k,), optional
            Only samples observed at or after this step.

        Returns
        -------
        n : ndarray of int, shape (k,)
            Number of common samples.
        diff : ndarray, shape (k, 2)
            Mean normalised difference (translational, rotational); 0 where ``n == 0``.
        """
        rows_a = np.asarray(rows_a, dtype=np.int64).reshape(-1)
        rows_b = np.asarray(rows_b, dtype=np.int64).reshape(-1)
        mask_a = self._mask(rows_a, n_train_a, stale_fraction)
        mask_b = self._mask(rows_b, n_train_b, stale_fraction)
        if since is not None:
            mask_a &= self.steps[rows_a] >= np.asarray(since, dtype=np.int64).reshape(-1, 1)
        steps_a, steps_b = self.steps[rows_a], self.steps[rows_b]
        errors_b, thresholds_b = self.errors[rows_b], self.thresholds[rows_b]
        # Rows that recorded the same steps from the same start (models created together) are aligned slot by
        # slot; the others are matched by step with a (W, W) comparison.
        aligned = np.all(steps_a == steps_b, axis=1)
        other = np.flatnonzero(~aligned)
        if other.size:
            match = ((steps_a[other][:, :, None] == steps_b[other][:, None, :])
                     & mask_a[other][:, :, None] & mask_b[other][:, None, :]).astype(float)
            # Each step occurs at most once per row, so the matched sample of b is the masked row sum.
            errors_b[other] = np.einsum("kij,kjc->kic", match, errors_b[other])
            thresholds_b[other] = np.einsum("kij,kjc->kic", match, thresholds_b[other])
            mask_b[other] = match.any(axis=2)
            mask_a[other] = mask_b[other]
        both = mask_a & mask_b
        n = both.sum(axis=1)
        theta = self.theta * np.maximum(np.minimum(self.thresholds[rows_a], thresholds_b), 1e-12)
        ratios_a = np.minimum(self.errors[rows_a] / theta, RATIO_CLIP)
        ratios_b = np.minimum(errors_b / theta, RATIO_CLIP)
        d = np.where(both[..., None], ratios_a - ratios_b, 0.0)
        return n, d.sum(axis=1) / np.maximum(n, 1)[:, None]

    def change_point(self, rows):
        """CUSUM change-point estimate per row, over the alarmed channels (else every channel above zero).

        The excursion of a channel started where its statistic last left zero; with a drift near the noise's own
        mean, a noise excursion may already be under way when the body changes, so the start alone can come several
        samples early. Within the excursion's samples still in the window, the estimate is the step that maximises
        ``sum(x_t - k')`` over the samples from it on, with ``k'`` halfway between the noise's mean (1) and the
        excursion's: the maximum-likelihood change point of a shift in the mean. Over several channels, the latest.

        Returns
        -------
        tau : ndarray of int, shape (k,)
            Step index, or -1 where no CUSUM is above zero.
        """
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        S = self.cusum[rows]
        start = self.cusum_start[rows]
        alarmed = S >= self.cusum_threshold
        use = np.where(np.any(alarmed, axis=1, keepdims=True), alarmed, S > 0.0) & (start >= 0)
        tau = np.full(rows.size, -1, dtype=np.int64)
        for k, row in enumerate(rows):
            for c in np.flatnonzero(use[k]):
                tau[k] = max(tau[k], self._refined_start(row, c, int(start[k, c])))
        return tau

    def _refined_start(self, row, channel, start):
        """The change point of one channel's excursion that started at ``start`` (see :meth:`change_point`)."""
        steps = self.steps[row]
        keep = steps >= start
        if np.count_nonzero(keep) < 2:
            return start
        order = np.argsort(steps[keep])
        theta = self.theta[channel] * self.thresholds[row, keep, channel]
        x = np.minimum((self.sigmas * self.errors[row, keep, channel] / theta) ** 2, self.cusum_clip)[order]
        shift = float(x.mean())
        if shift <= 1.0:
            return start
        gain = np.cumsum((x - 0.5 * (1.0 + shift))[::-1])[::-1]  # sum from each sample on
        return int(steps[keep][order][int(np.argmax(gain))])

    def first_step(self, rows):
        """Oldest step in each row's window, -1 if empty."""
        steps = self.steps[np.asarray(rows, dtype=np.int64).reshape(-1)]
        big = np.iinfo(np.int64).max
        first = np.where(steps >= 0, steps, big).min(axis=1)
        return np.where(first == big, -1, first)

    # ------------------------------------------------------------------ persistence
    def copy(self):
        """An independent copy: its arrays copied, its settings shared (immutable)."""
        clone = ValidityMonitor.__new__(ValidityMonitor)
        vars(clone).update({name: value.copy() if isinstance(value, np.ndarray) else value
                            for name, value in vars(self).items()})
        return clone
