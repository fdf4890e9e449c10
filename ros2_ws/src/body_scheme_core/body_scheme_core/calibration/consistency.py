"""Does the body scheme explain every marker? A lack-of-fit test on the joint fit's residuals.

Local models are judged one by one against thresholds of three noise sigmas (paper Eq. 5-6). A model that is wrong
by less than that, or whose error hides in a generous threshold (a wrongly static edge at a high noise), passes, and
every part below it is then predicted wrongly with nothing to show for it. After a joint fit
(:mod:`~body_scheme_core.calibration.joint_fit`) the question can be asked of the whole tree: are the residuals of each
marker what the noise makes, or do they still depend on the commands?

A residual that depends on the commands is the signature of a wrong model: a missing joint leaves residuals that
follow that joint's action; a wrong form (rigid where a gear bends the relation) leaves a curve. Noise is independent
of the commands. :func:`lack_of_fit` regresses a marker's whitened residuals (6 per observation) on features of each
action in turn (``sin a`` and ``cos a``: a revolute joint moves a marker along a circle, and over a prismatic joint's
range ``sin a`` is nearly ``a``) and tests the explained variance with an F test, Bonferroni-corrected over the
actions. The test does not depend on the noise level, so a noise estimate that
grew with a wrong model's errors (:mod:`~body_scheme_core.calibration.noise_model`) cannot hide them, and a marker whose
noise is larger than the others' (farther from the camera) does not fail it. Residuals are clipped at
:data:`CLIP` sigmas first, so a mirrored orientation is one outlier, not a structure.

:func:`part_consistency` applies it to every part of a fit and gives each a :class:`PartConsistency`; the learner
trusts its body scheme while every part passes at the level ``alpha`` (Bonferroni-corrected over the parts).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy import stats

__all__ = ["CLIP", "MIN_EXTRA_SAMPLES", "MIN_EXPLAINED", "PartConsistency", "action_features", "lack_of_fit",
           "part_consistency"]

#: Whitened residual components are clipped to +-CLIP before the test.
CLIP = 3.0
#: A part is tested once it has at least this many observations more than one action's regression has parameters.
MIN_EXTRA_SAMPLES = 10
#: A part lacks fit only when the commands explain at least this fraction of its residuals' variance: with a few
#: hundred observations the test finds structure far below the noise (a slightly biased calibration), which is no
#: reason to search the tree again. A missing joint or a wrong form explains half or more.
MIN_EXPLAINED = 0.25


class PartConsistency(NamedTuple):
    """The lack-of-fit test of one part.

    Attributes
    ----------
    n : int
        Observations tested.
    F : float
        Statistic of the action that explains most (explained over unexplained variance per degree of freedom); NaN
        when untested.
    p : float
        p-value under "the residuals are noise" (Bonferroni over the actions); NaN when untested.
    explained : float
        Fraction of the residuals' variance that action explains.
    rms : float
        RMS of the whitened residual components (about 1 when the noise estimate fits the part).
    """

    n: int
    F: float
    p: float
    explained: float
    rms: float

    @property
    def tested(self):
        """Whether the part had enough observations to be tested."""
        return math.isfinite(self.p)

    def lacks_fit(self, alpha):
        """Whether the commands explain the residuals at level ``alpha``, and by at least :data:`MIN_EXPLAINED`."""
        return self.tested and self.p < alpha and self.explained >= MIN_EXPLAINED


def action_features(a):
    """Regressors of one command: ``[sin a, cos a]`` minus their means, shape (n, 2); empty (n, 0) if constant.

    Parameters
    ----------
    a : ndarray, shape (n,)
    """
    a = np.asarray(a, dtype=float)
    features = np.stack([np.sin(a), np.cos(a)], axis=1)
    features = features[:, np.ptp(features, axis=0) > 1e-9] if len(a) else features[:, :0]
    return features - features.mean(axis=0)


def lack_of_fit(residuals, A):
    """F test of "the residuals do not depend on the commands" for one part.

    For each action in turn, the part's residual components (all of them together) are regressed on that action's
    features (:func:`action_features`), and the F statistic of the explained variance gives a p-value; the part's
    p-value is the smallest, times the number of actions tested (Bonferroni). A missing joint, a wrong action or a
    wrong form shows in one action's features, so testing them one at a time keeps the test's power; all actions at
    once would spread the same signal over as many degrees of freedom as there are actions.

    Parameters
    ----------
    residuals : ndarray, shape (n, c)
        Whitened residual components (units of their noise sigma) of the part's observations.
    A : ndarray, shape (n, m)
        The commands of those observations.

    Returns
    -------
    consistency : PartConsistency
        ``F`` and ``explained`` of the action that explains most.
    """
    r = np.clip(np.asarray(residuals, dtype=float), -CLIP, CLIP)
    A = np.asarray(A, dtype=float)
    n, c = r.shape
    rms = float(np.sqrt(np.mean(r * r))) if r.size else math.nan
    untested = PartConsistency(n, math.nan, math.nan, math.nan, rms)
    centred = r - r.mean(axis=0) if n else r
    total = float(np.sum(centred * centred))
    if n < 3 + MIN_EXTRA_SAMPLES or total <= 0.0:
        return untested
    best, tested = None, 0
    for j in range(A.shape[1]):
        X = action_features(A[:, j])
        k = X.shape[1]
        if k == 0:
            continue
        coef, _, rank, _ = np.linalg.lstsq(X, centred, rcond=None)
        explained = float(np.sum((X @ coef) ** 2))
        df1, df2 = c * rank, c * (n - 1 - rank)
        unexplained = total - explained
        if rank == 0 or df2 <= 0 or unexplained <= 0.0:
            continue
        tested += 1
        F = (explained / df1) / (unexplained / df2)
        p = float(stats.f.sf(F, df1, df2))
        if best is None or p < best[1]:
            best = (F, p, explained / total)
    if best is None:
        return untested
    F, p, share = best
    return PartConsistency(n, float(F), min(1.0, p * tested), share, rms)


def part_consistency(parts, residuals, A):
    """:func:`lack_of_fit` for every part.

    Parameters
    ----------
    parts : ndarray of int, shape (N,)
        The part of each observation.
    residuals : ndarray, shape (N, c)
        Whitened residual components per observation.
    A : ndarray, shape (N, m)
        The commands per observation.

    Returns
    -------
    consistency : dict of int to PartConsistency
    """
    parts = np.asarray(parts)
    return {int(p): lack_of_fit(residuals[parts == p], A[parts == p]) for p in np.unique(parts)}
