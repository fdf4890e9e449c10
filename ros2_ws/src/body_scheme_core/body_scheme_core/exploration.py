"""Active exploration: the next command chosen to teach the learner the most (the paper's future work).

Random babbling spends many commands where the body scheme is already sure. :class:`ExplorationPolicy` draws
candidate commands within the joint limits, keeps those a feasibility callback accepts (a collision screen, markers
predicted in the camera's view), and picks the one with the highest score, less a cost for the distance from the
arm's posture:

- with a body scheme: the predicted positional variance summed over the parts (:meth:`BodyScheme.predict_batch
  <body_scheme_core.scheme.BodyScheme.predict_batch>`: the models' parameter covariances and the GPs' variances
  along the chain). Where that variance is largest an observation constrains the parameters most: the A-optimal
  choice of Martinez-Cantin, Lopes and Montesano ("Body schema acquisition through active learning") for one
  candidate at a time, on every model of the tree rather than a known chain;
- without one (pass None while the learner is bootstrapping): a uniform draw, random babbling. Measured, both the
  candidate farthest from every command seen so far and the most uncertain posture of the provisional body scheme
  made bootstrapping slower than random babbling (7-joint arm, 6 seeds: 180 and 97 commands until the end effector
  was predicted within the noise, against 75; ``docs/RESULTS.md``, explore): they pick the corners of the joint
  space, where the candidate models all fail alike.

Scores are scaled by their mean over the candidates, so ``travel_weight`` trades a unit of relative information
against moving across the whole joint range.
"""

from __future__ import annotations

import numpy as np

from .errors import InvalidInputError

__all__ = ["ExplorationPolicy"]


class ExplorationPolicy:
    """Picks the next babbling command.

    Parameters
    ----------
    lower, upper : array-like, shape (m,)
        Joint limits (finite).
    n_candidates : int
        Random candidates drawn per suggestion.
    feasible : callable or None
        ``feasible(C) -> bool array (k,)`` for candidates ``C`` (k, m): which may be commanded (e.g. no collision,
        markers of interest in view). ``None``: all.
    travel_weight : float
        Cost per unit of joint-space distance from the current posture, ranges scaled to one (0: none); only with a
        body scheme (without one the draw stays uniform).
    rng : numpy.random.Generator, int or None

    Raises
    ------
    InvalidInputError
        On limits that are not finite vectors with ``lower <= upper``, or bad settings.
    """

    def __init__(self, lower, upper, n_candidates=256, feasible=None, travel_weight=0.0, rng=None):
        self.lower, self.upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        if (self.lower.shape != self.upper.shape or self.lower.ndim != 1 or not np.all(np.isfinite(self.lower))
                or not np.all(np.isfinite(self.upper)) or np.any(self.lower > self.upper)):
            raise InvalidInputError(f"limits must be finite vectors with lower <= upper, got {lower}, {upper}")
        if isinstance(n_candidates, bool) or not isinstance(n_candidates, (int, np.integer)) or n_candidates < 1:
            raise InvalidInputError(f"n_candidates must be an integer >= 1, got {n_candidates!r}")
        if not (np.isfinite(travel_weight) and travel_weight >= 0):
            raise InvalidInputError(f"travel_weight must be a number >= 0, got {travel_weight!r}")
        if feasible is not None and not callable(feasible):
            raise InvalidInputError("feasible must be callable (candidates (k, m) -> bool (k,)) or None")
        self.n_candidates, self.feasible, self.travel_weight = int(n_candidates), feasible, float(travel_weight)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self._scale = np.where(self.upper > self.lower, self.upper - self.lower, 1.0)
        #: Suggestions that found no feasible candidate (None was returned).
        self.n_infeasible = 0

    def suggest(self, scheme=None, current=None):
        """The next command (m,), or None when no candidate is feasible (counted in :attr:`n_infeasible`).

        Parameters
        ----------
        scheme : BodyScheme or None
            The learner's body scheme once it has finished bootstrapping; None before (a uniform draw).
        current : array-like, shape (m,) or None
            The arm's posture, for the travel cost.
        """
        C = self.rng.uniform(self.lower, self.upper, size=(self.n_candidates, self.lower.size))
        if self.feasible is not None:
            C = C[np.asarray(self.feasible(C), dtype=bool).reshape(-1)]
            if C.shape[0] == 0:
                self.n_infeasible += 1
                return None
        score = self.information(C, scheme)
        if scheme is not None and current is not None and self.travel_weight > 0:
            travel = np.linalg.norm((C - np.asarray(current, dtype=float)) / self._scale, axis=1)
            score = score - self.travel_weight * travel
        return C[int(np.argmax(score))]

    def information(self, C, scheme=None):
        """Each candidate's score (k,), scaled to mean 1 (see the module docstring); all 1 without a scheme."""
        if scheme is None:
            return np.ones(C.shape[0])
        _, std = scheme.predict_batch(C, return_std=True)
        score = np.sum(std[:, :, 0] ** 2, axis=1)
        mean = float(np.mean(score))
        return score / mean if mean > 0 else np.ones(C.shape[0])
