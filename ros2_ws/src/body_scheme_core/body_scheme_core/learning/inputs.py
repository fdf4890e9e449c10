"""Validation of the learner's inputs: constructor arguments, action vectors, time stamps and marker observations.

Two kinds of bad input are told apart (``docs/core/learning-and-adaptation.md``, Sec. 1). An argument the caller got
wrong (actions of the wrong length or not finite, observations that are not a mapping, a non-finite stamp, a bad
constructor argument) raises :class:`~body_scheme_core.errors.InvalidInputError` before anything changes. A single
bad marker pose among good ones is only dropped: :func:`filter_observations` keeps the good ones and returns a
:class:`Rejection` per bad one, which the learner counts and reports.

:func:`~body_scheme_core.transforms.check_transform` is not used for observations: it raises on the first bad pose,
while the learner must keep the others and name the reason for each bad one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from ..errors import ActionOutOfRangeError, InvalidInputError, StampOrderError
from ..limits import MAX_ACTION, MAX_ACTIONS, MAX_PARTS
from ..prediction import BodyScheme
from .config import BodySchemeConfig
from .structure import n_candidates

__all__ = [
    "OBSERVATION_TOLERANCE",
    "MAX_ACTION",
    "MAX_PARTS",
    "MAX_ACTIONS",
    "MAX_CANDIDATES",
    "check_body_size",
    "Rejection",
    "check_config",
    "check_part_ids",
    "check_n_actions",
    "root_part",
    "check_action_bounds",
    "check_action_range",
    "check_initial_models",
    "check_action_vector",
    "check_stamp",
    "check_observation_mapping",
    "filter_observations",
    "filter_covariances",
    "rigidity_problem",
]

#: Largest deviation of an observed rotation block from orthonormality (and of the last row from [0 0 0 1]).
OBSERVATION_TOLERANCE = 1e-4
#: Most candidate local models bootstrapping may start with (about 16 kB each: 60,000 is about 1 GB).
MAX_CANDIDATES = 60_000


class Rejection(NamedTuple):
    """One dropped observation.

    Attributes
    ----------
    part : int or None
        The key as given when it is an integer (known or not), else ``None``.
    reason : str
        ``unknown_id``, ``bad_shape``, ``not_finite``, ``not_rigid``, ``out_of_workspace``, or ``bad_covariance``
        (:func:`filter_covariances`: the covariance is dropped, not the pose).
    detail : str
        What was wrong, for the ``input_rejected`` event.
    """

    part: int | None
    reason: str
    detail: str


def _is_id(key):
    """Whether ``key`` can be a part id: an integer, but not a bool."""
    return isinstance(key, (int, np.integer)) and not isinstance(key, bool)


# ---------------------------------------------------------------------- constructor arguments
def check_config(config):
    """Raise unless ``config`` is a :class:`BodySchemeConfig`."""
    if not isinstance(config, BodySchemeConfig):
        raise InvalidInputError(f"config must be a BodySchemeConfig, got {type(config).__name__}")
    return config


def check_part_ids(part_ids):
    """Part ids as a non-empty tuple of unique ints.

    Parameters
    ----------
    part_ids : iterable of int

    Returns
    -------
    parts : tuple of int
    """
    try:
        parts = tuple(part_ids)
    except TypeError as exc:
        raise InvalidInputError(f"part_ids must be integer ids, got {part_ids!r}") from exc
    if not all(_is_id(p) for p in parts):  # a float id would be truncated, a bool taken for 0 or 1
        raise InvalidInputError(f"part_ids must be integer ids, got {parts!r}")
    parts = tuple(int(p) for p in parts)
    if not parts or len(set(parts)) != len(parts):
        raise InvalidInputError(f"part_ids must be non-empty and unique, got {parts}")
    if len(parts) > MAX_PARTS:
        raise InvalidInputError(f"{len(parts)} parts: a learner takes at most {MAX_PARTS} (split the robot into "
                                f"learners of one limb each)")
    return parts


def check_n_actions(n_actions):
    """The number of actions m as an int >= 0 (bools refused)."""
    if isinstance(n_actions, bool) or not isinstance(n_actions, (int, np.integer)) or n_actions < 0:
        raise InvalidInputError(f"n_actions must be an integer >= 0, got {n_actions!r}")
    if n_actions > MAX_ACTIONS:
        raise InvalidInputError(f"{n_actions} actions: a learner takes at most {MAX_ACTIONS} (split the robot into "
                                f"learners of one limb each)")
    return int(n_actions)


def check_body_size(n_parts, n_actions, config):
    """Refuse a body whose bootstrapping would start with more than :data:`MAX_CANDIDATES` candidate models.

    The candidates are every pair of parts times every action subset of at most ``config.max_complexity`` actions and
    model class (:func:`~body_scheme_core.learning.structure.n_candidates`): quadratic in the parts, polynomial in the
    actions.
    """
    count = n_candidates(n_parts, n_actions, config.max_complexity, config.candidate_kinds)
    if count > MAX_CANDIDATES:
        raise InvalidInputError(
            f"{n_parts} parts and {n_actions} actions at max_complexity {config.max_complexity} make {count:,} "
            f"candidate models to bootstrap; at most {MAX_CANDIDATES:,} fit in memory: lower max_complexity, or "
            f"start from the robot's specification (urdf_path)")


def root_part(parts, root=None):
    """The root part: ``root`` (``config.root``) if given, else the lowest id; it must be one of ``parts``."""
    root = min(parts) if root is None else int(root)
    if root not in parts:
        raise InvalidInputError(f"config.root {root} is not one of the parts {parts}")
    return root


def check_action_bounds(lower, upper, n_actions):
    """Action limits as float arrays of shape (m,) (or ``None``), without NaN and with ``lower <= upper``.

    Parameters
    ----------
    lower, upper : array-like, shape (m,), or None
        Infinite limits (continuous joints) are allowed.
    n_actions : int

    Returns
    -------
    lower, upper : ndarray, shape (m,), or None
    """
    def check(bounds, name):
        if bounds is None:
            return None
        bounds = np.array(bounds, dtype=float)
        if bounds.shape != (n_actions,):
            raise InvalidInputError(f"{name} must have shape ({n_actions},), got {bounds.shape}")
        if np.any(np.isnan(bounds)):
            raise InvalidInputError(f"{name} contains NaN: {bounds.tolist()}")
        return bounds

    lower, upper = check(lower, "action_lower"), check(upper, "action_upper")
    if lower is not None and upper is not None and np.any(lower > upper):
        raise InvalidInputError(f"action_lower {lower.tolist()} exceeds action_upper {upper.tolist()}")
    return lower, upper


def check_initial_models(models, parts, root, n_actions):
    """A given body scheme: fitted models forming a spanning tree over ``parts``, using actions below ``n_actions``.

    Returns
    -------
    models : list of LocalModel
    """
    models = list(models)
    BodyScheme(parts, root, models)  # validates the tree and that every model is fitted
    for model in models:
        if model.actions and max(model.actions) >= n_actions:
            raise InvalidInputError(f"{model.describe()} uses action {max(model.actions)} but n_actions is "
                                    f"{n_actions}")
    return models


# ---------------------------------------------------------------------- one time step
def check_action_vector(actions, n_actions):
    """The one action vector of a time step as a float array of shape exactly ``(n_actions,)``, finite and within
    :data:`MAX_ACTION`.

    The models validate their stacked inputs with :func:`~body_scheme_core.models.base.check_action_batch` instead.

    Returns
    -------
    a : ndarray, shape (m,)
        Not necessarily a copy.
    """
    a = _real_array(actions, "actions")
    if a.shape != (n_actions,):
        raise InvalidInputError(f"actions must have shape ({n_actions},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InvalidInputError(f"actions contain NaN or inf: {a.tolist()}")
    if np.any(np.abs(a) > MAX_ACTION):
        raise ActionOutOfRangeError(f"actions {np.flatnonzero(np.abs(a) > MAX_ACTION).tolist()} exceed "
                                    f"+-{MAX_ACTION:g} (rad or m): no joint position is that large; check the "
                                    f"command's units")
    return a


def _real_array(values, name):
    """``values`` as a float array; strings, objects and complex numbers are refused (numpy would raise a bare
    ``ValueError`` or drop the imaginary part with only a warning)."""
    try:
        array = np.asarray(values)
    except (TypeError, ValueError) as exc:  # ragged nesting
        raise InvalidInputError(f"{name} must be real numbers, got {values!r}") from exc
    if array.dtype.kind not in "biuf":
        raise InvalidInputError(f"{name} must be real numbers, got {array.dtype} values: {values!r}")
    return array.astype(float, copy=False)


def check_stamp(stamp, previous=None):
    """A time stamp as a finite float, or ``None``; not before ``previous`` (the last step's stamp) if both are
    given."""
    if stamp is None:
        return None
    if isinstance(stamp, (bool, complex, np.complexfloating)) or not isinstance(stamp, (int, float, np.number)):
        raise InvalidInputError(f"stamp must be a real number or None, got {stamp!r}")
    stamp = float(stamp)
    if not math.isfinite(stamp):
        raise InvalidInputError(f"stamp must be finite, got {stamp!r}")
    if previous is not None and stamp < previous:
        raise StampOrderError(f"stamp {stamp!r} is before the last step's stamp {previous!r}: steps must come in "
                                f"time order")
    return stamp


def check_observation_mapping(observations):
    """Raise unless ``observations`` is a mapping (part id -> pose); the entries are checked one by one later."""
    if not isinstance(observations, Mapping):
        raise InvalidInputError(f"observations must be a mapping part id -> (4, 4) pose, got "
                                f"{type(observations).__name__}")
    return observations


def check_action_range(a, lower, upper, margin):
    """Refuse actions beyond the joint limits ``[lower, upper]`` (None: no limits) by more than ``margin`` of each
    joint's range (``ActionOutOfRangeError``)."""
    if lower is None or upper is None:
        return
    span = np.where(np.isfinite(upper - lower), upper - lower, 0.0)
    outside = (a < lower - margin * span) | (a > upper + margin * span)
    if np.any(outside):
        raise ActionOutOfRangeError(f"actions {np.flatnonzero(outside).tolist()} are beyond the joint limits "
                                    f"[{lower.tolist()}, {upper.tolist()}]: {a.tolist()}")


def filter_observations(observations, part_ids, max_distance=math.inf, reach=None):
    """Split observations into valid poses and rejections.

    Parameters
    ----------
    observations : mapping of int to array-like, shape (4, 4)
        ``world2part`` per observed part.
    part_ids : tuple of int
        The known parts.
    max_distance : float
        Poses whose position is farther than this from the camera (m) are rejected as ``out_of_workspace``.
    reach : tuple of (ndarray, shape (3,), float), optional
        ``(centre, radius)``: poses whose position is farther than ``radius`` from ``centre`` (the root part's
        position and the robot's reach plus a margin) are rejected as ``out_of_workspace`` too.

    Returns
    -------
    valid : dict of int to ndarray, shape (4, 4)
        Copies of the valid poses (the caller may reuse its arrays), in the given order.
    rejections : list of Rejection
        In the order: unknown ids, bad shapes and non-finite values as met, then non-rigid poses.
    """
    valid, rejected = {}, []
    for key, value in observations.items():
        if not _is_id(key) or int(key) not in part_ids:
            what = f"id {key!r} is not an integer" if not isinstance(key, (int, np.integer)) else f"id {key}"
            rejected.append(Rejection(key if _is_id(key) else None, "unknown_id",
                                      f"{what} is not one of the parts {part_ids}"))
            continue
        part = int(key)
        try:
            Y = np.array(value, dtype=float)  # a copy: the history must not change with the caller's arrays
        except (TypeError, ValueError):
            Y = None
        if Y is None or Y.shape != (4, 4):
            shape = None if Y is None else Y.shape
            rejected.append(Rejection(part, "bad_shape", f"pose of part {part} must have shape (4, 4), got {shape}"))
        elif not np.all(np.isfinite(Y)):
            rejected.append(Rejection(part, "not_finite", f"pose of part {part} contains NaN or inf"))
        elif not (distance := math.hypot(*Y[:3, 3])) <= max_distance:  # hypot: no overflow for 1e300
            rejected.append(Rejection(part, "out_of_workspace", f"pose of part {part} is {distance:.3g} m from the "
                                      f"camera (max_distance {max_distance} m)"))
        elif reach is not None and not (distance := math.hypot(*(Y[:3, 3] - reach[0]))) <= reach[1]:
            rejected.append(Rejection(part, "out_of_workspace", f"pose of part {part} is {distance:.3g} m from the "
                                      f"root part, beyond the robot's reach ({reach[1]:.3g} m with the margin)"))
        else:
            valid[part] = Y
    if valid:
        # Rigidity of all remaining poses in one vectorised check.
        dev, bad = _rigidity(np.stack(list(valid.values())))
        for part, is_bad, d in zip(list(valid), bad, dev, strict=True):
            if is_bad:
                del valid[part]
                rejected.append(Rejection(part, "not_rigid", f"pose of part {part} is not a rigid transform "
                                                             f"(deviation {d:.3g} > {OBSERVATION_TOLERANCE:g} or "
                                                             f"det < 0)"))
    return valid, rejected


def filter_covariances(covariances, poses):
    """Split the covariances of accepted ``poses`` into usable ones and rejections.

    Parameters
    ----------
    covariances : mapping of int to array-like, shape (6, 6) or (36,), or None
        Per observed part: its pose's covariance over ``(x, y, z, rot_x, rot_y, rot_z)`` (position in the camera
        frame, rotation about its axes, as ``geometry_msgs/PoseWithCovariance``). All zeros means "not estimated"
        (that message's convention): the pose is weighed by the learned noise. A covariance of a part without an
        accepted pose is dropped with it (the pose's rejection is the one reported).
    poses : mapping of int to ndarray
        The accepted poses (:func:`filter_observations`).

    Returns
    -------
    usable : dict of int to ndarray, shape (6, 6)
        Symmetric copies.
    rejections : list of Rejection
        ``bad_covariance``: not (6, 6), not finite, not symmetric or not positive definite; the pose is kept and
        weighed by the learned noise.

    Raises
    ------
    InvalidInputError
        If ``covariances`` is neither None nor a mapping.
    """
    if covariances is None:
        return {}, []
    if not isinstance(covariances, Mapping):
        raise InvalidInputError(f"covariances must be a mapping part id -> (6, 6) covariance, got "
                                f"{type(covariances).__name__}")
    usable, rejected = {}, []
    for key, value in covariances.items():
        if not _is_id(key) or int(key) not in poses:
            continue
        part = int(key)
        try:
            C = np.array(value, dtype=float)
        except (TypeError, ValueError):
            C = None
        if C is not None and C.size == 36:
            C = C.reshape(6, 6)
        problem = None
        if C is None or C.shape != (6, 6):
            problem = f"must have shape (6, 6) or (36,), got {None if C is None else C.shape}"
        elif not np.all(np.isfinite(C)):
            problem = "contains NaN or inf"
        elif not np.any(C):
            continue  # not estimated
        elif np.max(np.abs(C - C.T)) > 1e-6 * max(np.max(np.abs(C)), 1e-300):  # float32 drivers pass
            problem = "is not symmetric"
        elif min(np.linalg.eigvalsh(C[:3, :3])[0], np.linalg.eigvalsh(C[3:, 3:])[0]) <= 0.0:
            problem = "is not positive definite (position and rotation blocks)"
        if problem is None:
            usable[part] = 0.5 * (C + C.T)
        else:
            rejected.append(Rejection(part, "bad_covariance", f"covariance of part {part} {problem}; the pose is "
                                                              f"weighed by the learned noise"))
    return usable, rejected


def _rigidity(Y):
    """``(deviation, bad)`` per pose of a stack (k, 4, 4): the largest deviation of ``R^T R`` from I and of the last
    row from [0 0 0 1], and whether it exceeds :data:`OBSERVATION_TOLERANCE` or the rotation is a reflection."""
    R = Y[:, :3, :3]
    dev = np.maximum(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2)),
                     np.abs(Y[:, 3] - (0.0, 0.0, 0.0, 1.0)).max(axis=1))
    return dev, (dev > OBSERVATION_TOLERANCE) | (np.linalg.det(R) < 0.0)


def rigidity_problem(pose):
    """None for a rigid (4, 4) pose (within :data:`OBSERVATION_TOLERANCE`), else what is wrong with it."""
    dev, bad = _rigidity(np.asarray(pose, dtype=float)[None])
    return f"deviation {dev[0]:.3g} or det < 0" if bad[0] else None
