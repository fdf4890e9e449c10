"""Active exploration: the next command chosen to teach the learner the most (the paper's future work).

Random babbling spends many commands where the body scheme is already sure. :class:`ExplorationPolicy` draws
candidate commands within the joint limits, keeps those a feasibility callback accepts (a collision screen, markers
predicted in the camera's view), and picks the one with the highest score, less a cost for the distance from the
arm's posture:

- with a body scheme that carries the joint fit's covariance ``S``: the expected fall of the parts' positional
  variance, averaged over reference postures, if the candidate were observed (a Kalman update of ``S`` through the
  candidate's position Jacobian, :func:`~body_scheme_core.prediction.uncertainty.parameter_jacobian`). That is the
  A-optimal design of Martinez-Cantin, Lopes and Montesano ("Body schema acquisition through active learning"), weighted
  by where the body scheme is used (I-optimal), on every rigid-joint model of a learned tree rather than a known chain;
- with a body scheme without it (GP or engineered edges only): the predicted positional variance summed over the
  parts (:meth:`BodyScheme.predict_batch <body_scheme_core.prediction.scheme.BodyScheme.predict_batch>`);
- without one (pass None while the learner is bootstrapping): a uniform draw, random babbling; with ``excursions``
  first the postures of :func:`excursion_plan` (each joint moved alone from a reference posture, then pairs): what
  identifies a chain through unmarked links from scratch (a tool observed past six joints). Measured, both the
  candidate farthest from every command seen so far and the most uncertain posture of the provisional body scheme
  made bootstrapping slower than random babbling (7-joint arm, 6 seeds: 180 and 97 commands until the end effector
  was predicted within the noise, against 75; ``docs/RESULTS.md``, explore): they pick the corners of the joint
  space, where the candidate models all fail alike.

Measured (``docs/RESULTS.md``, explore): with every marker seen, one observation teaches every parameter almost
equally wherever the arm is (``explore_information_spread_*``: the 90th over the 10th percentile of the candidates'
expected falls at the end of bootstrapping is 1.2-1.5), so active exploration gains little over random babbling
there. A suggestion costs about P + 1 predictions of the candidates (P: the joint fit's parameters; 256 candidates
on the 6-DOF arm: tens of ms).

Scores are scaled by their mean over the candidates, so ``travel_weight`` trades a unit of relative information
against moving across the whole joint range. :func:`explore_near` teaches the learner around one posture (an IK
answer it is unsure of); :class:`NearFocus` does it one suggestion at a time, for scheme_node.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..errors import InvalidInputError
from ..prediction import parameter_jacobian

__all__ = ["ExplorationPolicy", "NearFocus", "PAPER_NOISE", "excursion_plan", "explore_near", "in_camera_view"]

#: The camera's positional noise per axis (m) the policy assumes by default: the paper's 44 mm 3D RMS.
PAPER_NOISE = 0.044 / np.sqrt(3.0)


def _positive(value):
    """Whether ``value`` is a finite real number > 0 (not a bool)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
        and bool(np.isfinite(value)) and value > 0


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
    noise : float
        The camera's positional noise per axis (m) in the expected fall of the variance.
    n_reference : int
        Postures drawn uniformly within the limits (once, first from ``rng``) over which the variance should fall.
    excursions : bool
        Without a body scheme, first suggest the middle of the limits and the feasible postures of
        :func:`excursion_plan` about it (4 excursions of each joint over 40 % of its range, then one posture per pair
        of joints).

    Raises
    ------
    InvalidInputError
        On limits that are not finite vectors with ``lower <= upper``, or bad settings.
    """

    def __init__(self, lower, upper, n_candidates=256, feasible=None, travel_weight=0.0, rng=None,
                 noise=PAPER_NOISE, n_reference=64, excursions=False):
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
        if not _positive(noise):
            raise InvalidInputError(f"noise must be a number > 0 (m per axis), got {noise!r}")
        if isinstance(n_reference, bool) or not isinstance(n_reference, (int, np.integer)) or n_reference < 1:
            raise InvalidInputError(f"n_reference must be an integer >= 1, got {n_reference!r}")
        self.noise = float(noise)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self._weights = None  # (scheme, reference, M): the reference postures' weights, per body scheme
        #: Postures over which the body scheme should become sure (uniform within the limits).
        self.reference = self.rng.uniform(self.lower, self.upper, size=(int(n_reference), self.lower.size))
        self._scale = np.where(self.upper > self.lower, self.upper - self.lower, 1.0)
        #: Suggestions that found no feasible candidate (None was returned).
        self.n_infeasible = 0
        #: The excursions still to suggest while there is no body scheme (``excursions``).
        middle = 0.5 * (self.lower + self.upper)
        self.plan = [middle, *excursion_plan(middle, self.lower, self.upper, range(self.lower.size), values=3,
                                             span=0.4, rng=self.rng)] if excursions else []

    def suggest(self, scheme=None, current=None, near=None, radius=0.1, feasible=None):
        """The next command (m,), or None when no candidate is feasible (counted in :attr:`n_infeasible`).

        Parameters
        ----------
        scheme : BodyScheme or None
            The learner's body scheme once it has finished bootstrapping; None before (a uniform draw).
        current : array-like, shape (m,) or None
            The arm's posture, for the travel cost.
        near : array-like, shape (m,) or None
            A posture whose prediction should become sure (an IK answer the body scheme is not sure of): the
            candidates are drawn within ``radius`` of each joint's range around it, and scored by how much they
            reduce the variance at ``near`` alone (without the joint fit's covariance: by their own variance).
        radius : float
            Fraction of each joint's range (with ``near``).
        feasible : callable or None
            A constraint of this call only, on top of the policy's own (e.g. :func:`in_camera_view` of the current
            body scheme).
        """
        if scheme is None and near is None and self.plan:
            command = self._next_excursion(feasible)
            if command is not None:
                return command
        lower, upper, reference = self.lower, self.upper, self.reference
        if near is not None:
            near = np.asarray(near, dtype=float)
            if near.shape != self.lower.shape or not np.all(np.isfinite(near)):
                raise InvalidInputError(f"near must be a finite vector of {self.lower.size} actions, got {near!r}")
            if not _positive(radius):
                raise InvalidInputError(f"radius must be a number > 0, got {radius!r}")
            near = np.clip(near, self.lower, self.upper)
            lower = np.maximum(self.lower, near - radius * self._scale)
            upper = np.minimum(self.upper, near + radius * self._scale)
            reference = near[None]
        C = self.rng.uniform(lower, upper, size=(self.n_candidates, self.lower.size))
        for constraint in (self.feasible, feasible):
            if constraint is not None and C.shape[0]:
                C = C[np.asarray(constraint(C), dtype=bool).reshape(-1)]
        if C.shape[0] == 0:
            self.n_infeasible += 1
            return None
        score = self.information(C, scheme, reference)
        if scheme is not None and current is not None and self.travel_weight > 0:
            travel = np.linalg.norm((C - np.asarray(current, dtype=float)) / self._scale, axis=1)
            score = score - self.travel_weight * travel
        return C[int(np.argmax(score))]

    def _next_excursion(self, feasible):
        """The next posture of the plan that the constraints accept (infeasible ones are skipped), or None."""
        while self.plan:
            command = self.plan.pop(0)
            ok = all(constraint is None or bool(np.asarray(constraint(command[None]), dtype=bool).reshape(-1)[0])
                     for constraint in (self.feasible, feasible))
            if ok:
                return command
        return None

    def information(self, C, scheme=None, reference=None):
        """Each candidate's score (k,), scaled to mean 1 (see the module docstring); all 1 without a scheme.
        ``reference``: the postures (r, m) whose variance should fall (default :attr:`reference`)."""
        if scheme is None:
            return np.ones(C.shape[0])
        score = self._variance_reduction(C, scheme, self.reference if reference is None else reference)
        if score is None:  # no joint covariance: the predicted positional variance
            _, std = scheme.predict_batch(C, return_std=True)
            score = np.sum(std[:, :, 0] ** 2, axis=1)
        mean = float(np.mean(score))
        return score / mean if mean > 0 else np.ones(C.shape[0])

    def _variance_reduction(self, C, scheme, reference):
        """The expected reduction of the parts' positional variance averaged over the reference postures if each
        candidate were observed (k,), or None without the joint fit's covariance.

        With the parameters' covariance ``S``, the candidate's position Jacobian ``J`` (all parts stacked) and the
        camera's noise ``R``, one observation leaves ``S - S J' (J S J' + R)^-1 J S``; averaged over the reference
        postures' Jacobians ``Jr`` the variance falls by ``tr((J S J' + R)^-1 J S M S J')``, ``M = mean Jr' Jr``.
        """
        if scheme.param_covariance is None:
            return None
        S = scheme.param_covariance[1]
        cached = self._weights
        if cached is None or cached[0] is not scheme or cached[1] is not reference:
            Jr = parameter_jacobian(scheme, reference).reshape(-1, S.shape[0])
            cached = self._weights = (scheme, reference, Jr.T @ Jr / reference.shape[0])
        M = cached[2]
        k = C.shape[0]
        Jc = parameter_jacobian(scheme, C).reshape(k, -1, S.shape[0])
        JS = Jc @ S
        innovation = JS @ Jc.transpose(0, 2, 1) + self.noise**2 * np.eye(Jc.shape[1])
        gain = JS @ M @ JS.transpose(0, 2, 1)
        return np.trace(np.linalg.solve(innovation, gain), axis1=1, axis2=2)


def in_camera_view(scheme, world2root, K, width, height, parts=None, margin=0.05):
    """A feasibility callback ``(C) -> bool (k,)``: every part of ``parts`` (default: all) predicted by ``scheme`` in
    front of the camera and inside the image, ``margin`` of its size in from each border.

    Parameters
    ----------
    scheme : BodyScheme
    world2root : array-like, shape (4, 4)
        The root part's pose in the camera's frame (the observations are ``camera2marker`` poses, so the learner's
        :attr:`~body_scheme_core.learning.learner.BodySchemeLearner.root_pose`).
    K : array-like, shape (3, 3)
        The camera's intrinsic matrix (undistorted pinhole).
    width, height : int
        Image size in pixels.
    parts : iterable of int or None
    margin : float
        Fraction of the image's width and height kept clear at each border, in [0, 0.5).
    """
    K, world2root = np.asarray(K, dtype=float), np.asarray(world2root, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InvalidInputError(f"K must be a finite 3 x 3 intrinsic matrix, got {K.tolist()}")
    if world2root.shape != (4, 4) or not np.all(np.isfinite(world2root)):
        raise InvalidInputError("world2root must be a finite 4 x 4 transform")
    if not (width > 0 and height > 0 and 0.0 <= margin < 0.5):
        raise InvalidInputError(f"need width, height > 0 and 0 <= margin < 0.5, got {width}, {height}, {margin}")
    columns = [scheme.parts.index(p) for p in (scheme.parts if parts is None else parts)]
    low, high = margin * np.array([width, height]), (1.0 - margin) * np.array([width, height])

    def feasible(C):
        root2part = scheme.predict_batch(C)[:, columns][..., :3, 3]
        camera = root2part @ world2root[:3, :3].T + world2root[:3, 3]
        z = camera[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = (camera @ K.T)[..., :2] / z[..., None]
        inside = (z > 0) & np.all((pixels >= low) & (pixels <= high), axis=-1)
        return np.all(inside, axis=1)

    return feasible


class NearFocus:
    """Exploration near one posture, one suggestion at a time: the streaming form of :func:`explore_near`, for a
    learner fed by a camera (scheme_node) rather than by a callback.

    Draw the next ``n_samples`` suggestions with :meth:`suggest`; once the sample of the last of them is learnt,
    run the joint fit (:meth:`BodySchemeLearner.recalibrate`) and solve again.

    Parameters
    ----------
    actions : array-like, shape (m,)
        The posture to explore near (an IK answer whose predicted error is too large).
    n_samples : int
        Suggestions near it, 1 to :attr:`MAX_SAMPLES`.
    radius : float
        Fraction of each joint's range around it (> 0, at most 1).

    Raises
    ------
    InvalidInputError
        On a posture that is not a finite vector, or bad settings.
    """

    #: The most suggestions one focus may ask for.
    MAX_SAMPLES = 1000

    def __init__(self, actions, n_samples=5, radius=0.1):
        self.actions = np.asarray(actions, dtype=float)
        if self.actions.ndim != 1 or not np.all(np.isfinite(self.actions)):
            raise InvalidInputError(f"the posture to explore near must be a finite vector, got {actions!r}")
        self.check_settings(n_samples, radius)
        self.radius = float(radius)
        #: Suggestions still to draw near :attr:`actions`.
        self.left = int(n_samples)

    @classmethod
    def check_settings(cls, n_samples, radius):
        """Raise :class:`InvalidInputError` unless ``n_samples`` and ``radius`` are valid (e.g. to check a node's
        parameters at start-up rather than per request)."""
        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) \
                or not 1 <= n_samples <= cls.MAX_SAMPLES:
            raise InvalidInputError(f"n_samples must be an integer from 1 to {cls.MAX_SAMPLES}, got {n_samples!r}")
        if not (_positive(radius) and radius <= 1.0):
            raise InvalidInputError(f"radius must be a number in (0, 1], got {radius!r}")

    @property
    def done(self):
        """Whether every suggestion was drawn."""
        return self.left == 0

    def suggest(self, policy, scheme=None, current=None, feasible=None):
        """The next command near :attr:`actions` (:meth:`ExplorationPolicy.suggest` with ``near``), or None when
        every suggestion was drawn or none near it is feasible (then :attr:`done` stays False)."""
        if self.done:
            return None
        if self.actions.shape != policy.lower.shape:
            raise InvalidInputError(f"the posture to explore near has {self.actions.size} actions, the policy "
                                    f"{policy.lower.size}")
        command = policy.suggest(scheme, current, near=self.actions, radius=self.radius, feasible=feasible)
        if command is not None:
            self.left -= 1
        return command


def explore_near(learner, policy, actions, observe, n_samples=5, radius=0.1):
    """Teach ``learner`` where it is unsure: ``n_samples`` commands chosen by ``policy`` near ``actions`` (an IK
    answer whose predicted error is too large), each executed and observed through ``observe(a) -> {part:
    world2part}``, then a joint fit now (:meth:`BodySchemeLearner.recalibrate`); solve again after.

    Returns
    -------
    list of Event
        The learner's events of those steps.
    """
    focus, events, current = NearFocus(actions, n_samples, radius), [], np.asarray(actions, dtype=float)
    while not focus.done:
        a = focus.suggest(policy, learner.body_scheme, current)
        if a is None:
            break
        events += learner.update(a, observe(a))
        current = a
    return events + learner.recalibrate()


def excursion_plan(reference, lower, upper, actions, values=3, span=0.5, rng=None):
    """Postures that identify a chain through unmarked links from scratch
    (:func:`~body_scheme_core.learning.chain_search.identify_chain`): excursions of each action from ``reference``
    (spread over ``span`` of its range, within the limits), then one posture per pair of actions in a random order:
    ``values + 1`` evenly spread excursions of each action (one fewer where one falls on the reference).

    Returns
    -------
    postures : ndarray, shape (k, m)
    """
    rng = np.random.default_rng(rng)
    reference = np.asarray(reference, dtype=float)
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    if reference.shape != lower.shape or not np.all((lower <= reference) & (reference <= upper)):
        raise InvalidInputError("the reference posture must lie within the limits")
    out = []
    for j in actions:
        half = 0.5 * span * (upper[j] - lower[j])
        for v in np.linspace(-half, half, values + 1):
            if abs(v) < 1e-12:
                continue
            a = reference.copy()
            a[j] = np.clip(reference[j] + v, lower[j], upper[j])
            out.append(a)
    pairs = list(itertools.combinations(actions, 2))
    rng.shuffle(pairs)
    for j1, j2 in pairs:
        a = reference.copy()
        for j in (j1, j2):
            a[j] = rng.uniform(lower[j], upper[j])
        out.append(a)
    return np.array(out).reshape(-1, reference.size)
