"""How accurate is a calibration: k-fold cross-validated prediction errors, never on training data.

The poses are split into ``folds`` groups (a fixed random permutation); each group in turn is held out, the model is
fitted on the others, and its predictions at the held-out commands are compared with what was observed there. Every
observation is predicted exactly once, by a fit that never saw it. The fit is a callback, so the same protocol
measures a learner from scratch, the learned body scheme refitted with its structure fixed (:func:`refit_scheme`:
the joint fit, as a calibration tool refits its parameters) and the nominal specification (its root pose fitted
only).

The spread of the fold fits also estimates how well each parameter is determined: the delete-d jackknife over the
folds, ``std = sqrt((k - 1) / k * sum_i (theta_i - theta_mean)^2)`` (Shao and Wu 1989), which
:func:`jackknife_std` applies to any per-fold figures (e.g. each joint's axis and origin from
:func:`~body_scheme_core.prediction.calibration_report`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidInputError
from ..models import EngineeredModel
from ..prediction import BodyScheme, calibration_report, learned_tree
from ..transforms import rotational_error, translational_error
from .joint_fit import calibrate

__all__ = ["CrossValidation", "cross_validate", "fold_indices", "refit_scheme", "jackknife_std", "accuracy_report"]


@dataclass
class CrossValidation:
    """Held-out errors of every observation, by part.

    Attributes
    ----------
    trans, rot : dict of int to ndarray
        Per part: the distance (m) and angle (rad) between the held-out observation and its prediction.
    fits : list
        What ``fit`` returned per fold (e.g. for :func:`jackknife_std`).
    failed_folds : int
        Folds whose fit gave no predictor (``None``); their observations have no error.
    """

    trans: dict = field(default_factory=dict)
    rot: dict = field(default_factory=dict)
    fits: list = field(default_factory=list)
    failed_folds: int = 0

    def summary(self):
        """Per part ``{n, mean_mm, rms_mm, p95_mm, mean_deg}``, and ``all`` over every part."""
        out = {}
        groups = {part: (self.trans[part], self.rot[part]) for part in sorted(self.trans)}
        if groups:
            groups["all"] = (np.concatenate([t for t, _ in groups.values()]),
                             np.concatenate([r for _, r in groups.values()]))
        for key, (t, r) in groups.items():
            out[key] = {"n": len(t),
                        "mean_mm": 1e3 * float(np.mean(t)) if len(t) else math.nan,
                        "rms_mm": 1e3 * float(np.sqrt(np.mean(t ** 2))) if len(t) else math.nan,
                        "p95_mm": 1e3 * float(np.percentile(t, 95)) if len(t) else math.nan,
                        "mean_deg": math.degrees(float(np.mean(r))) if len(r) else math.nan}
        return out

    @property
    def mean_mm(self):
        """Mean held-out position error over every part's observations (mm); NaN without any."""
        return self.summary().get("all", {}).get("mean_mm", math.nan)


def fold_indices(n, folds=5, seed=0):
    """The held-out indices of each fold: a permutation of ``range(n)`` (``seed``) cut into ``folds`` groups."""
    if isinstance(folds, bool) or not isinstance(folds, (int, np.integer)) or not 2 <= folds <= n:
        raise InvalidInputError(f"need 2 <= folds <= number of poses ({n}), got {folds!r}")
    return [np.sort(part) for part in np.array_split(np.random.default_rng(seed).permutation(n), folds)]


def cross_validate(fit, actions, observations, folds=5, seed=0, parts=None):
    """k-fold cross-validated prediction errors (see the module docstring).

    Parameters
    ----------
    fit : callable
        ``fit(train) -> predictor or None``: fit on the poses ``train`` (indices); ``predictor(a)`` returns
        ``{part: world2part}`` in the observations' frame. A fold whose fit returns None is counted as failed.
    actions : array-like, shape (n, m)
    observations : sequence of dict of int to ndarray, shape (4, 4)
        ``world2part`` per pose.
    folds, seed : int
        See :func:`fold_indices`.
    parts : iterable of int, optional
        Parts to score (default: every observed part the predictor predicts).

    Returns
    -------
    CrossValidation
    """
    A = np.asarray(actions, dtype=float)
    if A.ndim != 2 or len(A) != len(observations):
        raise InvalidInputError(f"actions must be (n, m) with n = len(observations) = {len(observations)}, got "
                                f"{A.shape}")
    wanted = None if parts is None else set(parts)
    result = CrossValidation()
    trans, rot = {}, {}
    for test in fold_indices(len(A), folds, seed):
        train = np.setdiff1d(np.arange(len(A)), test)
        predictor = fit(train)
        result.fits.append(predictor)
        if predictor is None:
            result.failed_folds += 1
            continue
        for k in test:
            predicted = predictor(A[k])
            for part, observed in observations[k].items():
                if part in predicted and (wanted is None or part in wanted):
                    trans.setdefault(part, []).append(float(translational_error(predicted[part], observed)))
                    rot.setdefault(part, []).append(float(rotational_error(predicted[part], observed)))
    result.trans = {part: np.array(v) for part, v in trans.items()}
    result.rot = {part: np.array(v) for part, v in rot.items()}
    return result


def refit_scheme(scheme, world2root, actions, observations, sigma_trans, sigma_rot, axis_sigmas=None):
    """A ``fit`` for :func:`cross_validate`: the body scheme's parameters refitted by the joint fit on the training
    poses, its structure fixed (engineered models keep theirs: only their root pose is fitted).

    The returned predictor carries the refitted scheme as ``predictor.scheme`` and root pose as
    ``predictor.world2root``.
    """
    A = np.asarray(actions, dtype=float)

    def fit(train):
        calibration = calibrate(scheme, world2root, A[train], [observations[k] for k in train], sigma_trans,
                                sigma_rot, axis_sigmas=axis_sigmas)

        def predictor(a):
            return {part: calibration.world2root @ pose for part, pose in calibration.scheme.predict(a).items()}

        predictor.scheme, predictor.world2root = calibration.scheme, calibration.world2root
        return predictor

    return fit


def jackknife_std(values, about=None):
    """Delete-d jackknife standard deviation over the folds: ``values`` (k, ...) per fold -> std (...).

    ``about``: the centre (default the folds' mean), e.g. 0 for each fold's deviation from the fit on every pose.
    """
    v = np.asarray(values, dtype=float)
    k = len(v)
    if k < 2:
        raise InvalidInputError(f"need the values of at least two folds, got {k}")
    centre = v.mean(axis=0) if about is None else about
    return np.sqrt((k - 1) / k * np.sum((v - centre) ** 2, axis=0))


def accuracy_report(scheme, world2root, actions, observations, sigma_trans, sigma_rot, joint_names, lower, upper,
                    nominal=None, folds=5, seed=0, axis_sigmas=None, curve_points=6):
    """How accurate a learned body scheme is, on poses no fit saw (what ``calibrate`` reports).

    Parameters
    ----------
    scheme, world2root
        The learned body scheme and its root pose (the starting point of every fold's refit).
    actions, observations
        The poses to cross-validate on (e.g. :meth:`~body_scheme_core.learning.BodySchemeLearner.samples`).
    sigma_trans, sigma_rot, axis_sigmas
        The observation noise, as for :func:`~body_scheme_core.calibration.calibrate`.
    joint_names, lower, upper
        As for :func:`~body_scheme_core.prediction.learned_tree` (the joints' names and trained range).
    nominal : KinematicTree, optional
        The robot's specification with its markers: its cross-validated error too (its root pose fitted per fold).
    folds, seed : int
    curve_points : int
        Sizes of the held-out error curve (geometric from ``2 * folds`` poses to all of them); 0: no curve.

    Returns
    -------
    report : dict
        ``cv`` (:meth:`CrossValidation.summary` of the learned scheme, parts as strings), ``cv_mm`` (its mean over
        every observation), ``nominal_cv`` and ``nominal_cv_mm`` (or None), ``joint_std`` (per learned joint: the
        jackknife std of its axis, deg, and origin, mm, over the folds' refits), ``curve`` (``[{poses, cv_mm}]``),
        ``folds``, ``n_poses``.
    """
    A = np.asarray(actions, dtype=float)
    learned = cross_validate(refit_scheme(scheme, world2root, A, observations, sigma_trans, sigma_rot, axis_sigmas),
                             A, observations, folds, seed)
    report = {"folds": int(folds), "n_poses": len(A), "cv": _keyed(learned.summary()), "cv_mm": learned.mean_mm,
              "nominal_cv": None, "nominal_cv_mm": None}
    if nominal is not None:
        engineered = BodyScheme(scheme.parts, scheme.root,
                                [EngineeredModel.from_tree(nominal, parent, child)
                                 for parent, child, _, _ in scheme.edges])
        specified = cross_validate(refit_scheme(engineered, world2root, A, observations, sigma_trans, sigma_rot,
                                                axis_sigmas), A, observations, folds, seed)
        report["nominal_cv"], report["nominal_cv_mm"] = _keyed(specified.summary()), specified.mean_mm
    # Each fold's joints against the whole fit's: the jackknife spread of every joint's axis and origin.
    reference = learned_tree(scheme, joint_names, lower, upper).tree
    deviations = [calibration_report(learned_tree(fit.scheme, joint_names, lower, upper), reference)["joints"]
                  for fit in learned.fits]
    report["joint_std"] = [
        {"joint": rows[0]["joint"], "parent": rows[0]["parent"], "child": rows[0]["child"],
         "axis_deg": float(jackknife_std([r["axis_deg"] for r in rows], about=0.0)),
         "origin_mm": None if rows[0]["origin_mm"] is None else
         float(jackknife_std([r["origin_mm"] for r in rows], about=0.0))}
        for rows in zip(*deviations, strict=True)] if deviations else []
    sizes = np.unique(np.round(np.geomspace(2 * folds, len(A), curve_points)).astype(int)) if len(A) >= 2 * folds \
        else np.array([], dtype=int)
    report["curve"] = []
    for n in sizes:
        part = cross_validate(refit_scheme(scheme, world2root, A[:n], observations[:n], sigma_trans, sigma_rot,
                                           axis_sigmas), A[:n], observations[:n], folds, seed)
        report["curve"].append({"poses": int(n), "cv_mm": part.mean_mm})
    return report


def _keyed(summary):
    return {str(part): figures for part, figures in summary.items()}
