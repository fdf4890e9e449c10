"""Moving a real arm safely: trajectory durations from joint limits, the limits' safety margin, and settling.

What a node that drives an arm through ros2_control's ``JointTrajectoryController`` needs, without ROS: how long a
point-to-point move takes under per-joint velocity and acceleration limits (:func:`trajectory_duration`), which
postures the move passes through (:func:`path_samples`), which are allowed (:class:`SafetyLimits`: joint limits
shrunk by a margin and a workspace box around the root), and when the arm has come to rest at its goal
(:class:`SettleDetector`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError

__all__ = ["trajectory_duration", "path_samples", "MAX_PATH_SAMPLES", "SafetyLimits", "SettleDetector"]


def trajectory_duration(start, goal, max_velocity, max_acceleration, min_duration=0.1):
    """Time of a one-point trajectory that a ``JointTrajectoryController`` executes within per-joint limits.

    Given one point with positions and zero velocities, the controller moves each joint from rest along the cubic
    ``p(s) = p0 + d (3 s^2 - 2 s^3)``, ``s = t / T``: its peak speed is ``1.5 d / T`` (at ``s = 1/2``) and its peak
    acceleration ``6 d / T^2`` (at the start and the end). The duration is the smallest ``T`` that keeps every joint
    within both limits.

    Parameters
    ----------
    start, goal : array-like, shape (m,)
        Joint positions.
    max_velocity, max_acceleration : array-like, shape (m,) or float
        Per-joint limits (> 0), rad/s (m/s) and rad/s^2 (m/s^2).
    min_duration : float
        Lower bound, s (a controller needs a non-zero ``time_from_start``).

    Returns
    -------
    duration : float
        Seconds: ``max over joints of max(1.5 d / v, sqrt(6 d / a))``, at least ``min_duration``.
    """
    start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
    if start.shape != goal.shape or start.ndim != 1:
        raise InvalidInputError(f"start and goal must be vectors of one length, got {start.shape}, {goal.shape}")
    v = np.broadcast_to(np.asarray(max_velocity, dtype=float), start.shape)
    a = np.broadcast_to(np.asarray(max_acceleration, dtype=float), start.shape)
    if not (np.all(np.isfinite(v)) and np.all(v > 0) and np.all(np.isfinite(a)) and np.all(a > 0)):
        raise InvalidInputError("velocity and acceleration limits must be finite and > 0")
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal))):
        raise InvalidInputError("start and goal must be finite")
    d = np.abs(goal - start)
    t = np.maximum(1.5 * d / v, np.sqrt(6.0 * d / a))
    return max(float(t.max(initial=0.0)), float(min_duration))


#: Most postures :func:`path_samples` returns: a path that needs more (1e6 rad between start and goal) is refused,
#: so no input makes a move's checks unbounded.
MAX_PATH_SAMPLES = 10_000


def path_samples(start, goal, max_step=0.05, max_samples=MAX_PATH_SAMPLES):
    """Postures along the straight joint-space path from ``start`` to ``goal`` (what a controller's interpolation
    passes through), no joint moving more than ``max_step`` (rad, m) between two; ``start`` excluded, ``goal``
    included. Shape (k, m), 1 <= k <= ``max_samples``.

    Raises
    ------
    InvalidInputError
        For non-finite or mismatched postures, or a path that needs more than ``max_samples`` postures.
    """
    start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
    if not (max_step > 0):
        raise InvalidInputError(f"max_step must be > 0, got {max_step!r}")
    if start.shape != goal.shape or not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal))):
        raise InvalidInputError(f"start and goal must be finite postures of one shape, got {start.shape}, "
                                f"{goal.shape}")
    with np.errstate(over="ignore"):
        steps = np.max(np.abs(goal - start), initial=0.0) / max_step
    if not steps <= max_samples:
        raise InvalidInputError(f"a path of {steps:.3g} steps of {max_step} is longer than {max_samples} postures")
    n = max(1, int(np.ceil(steps)))
    return start + np.linspace(0.0, 1.0, n + 1)[1:, None] * (goal - start)


@dataclass
class SafetyLimits:
    """Which commands an arm may be sent.

    Parameters
    ----------
    lower, upper : array-like, shape (m,)
        Joint limits (the robot's specification).
    margin : float or array-like
        Kept away from each limit, in the joint's unit (rad or m); at most half the range.
    workspace : array-like, shape (2, 3) or None
        ``[[x_min, y_min, z_min], [x_max, y_max, z_max]]`` in the root link's frame, m: every point that
        ``points(a)`` returns must lie inside. ``None``: no box.
    points : callable or None
        ``points(a) -> (k, 3)``: the points to keep in the box for command ``a`` (e.g. every link origin from the
        URDF's forward kinematics).
    """

    lower: np.ndarray
    upper: np.ndarray
    margin: float = 0.05
    workspace: np.ndarray | None = None
    points: object = None

    def __post_init__(self):
        lower, upper = np.asarray(self.lower, dtype=float), np.asarray(self.upper, dtype=float)
        if lower.shape != upper.shape or lower.ndim != 1 or not np.all(lower <= upper):
            raise InvalidInputError(f"joint limits must be vectors with lower <= upper, got {lower}, {upper}")
        margin = np.broadcast_to(np.asarray(self.margin, dtype=float), lower.shape)
        if not (np.all(np.isfinite(margin)) and np.all(margin >= 0)):
            raise InvalidInputError(f"margin must be >= 0, got {self.margin}")
        margin = np.minimum(margin, 0.5 * (upper - lower))
        self.lower, self.upper = lower + margin, upper - margin
        if self.workspace is not None:
            box = np.asarray(self.workspace, dtype=float)
            if box.shape != (2, 3) or not np.all(box[0] < box[1]):
                raise InvalidInputError(f"workspace must be [[x,y,z min], [x,y,z max]] with min < max, got {box}")
            if self.points is None:
                raise InvalidInputError("a workspace box needs the points to keep inside it")
            self.workspace = box

    def outside(self, points):
        """Per point of ``points`` (k, 3), whether it lies outside the workspace box (all False without a box)."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        if self.workspace is None:
            return np.zeros(len(points), dtype=bool)
        return np.any((points < self.workspace[0]) | (points > self.workspace[1]), axis=1)

    def outside_box(self, a):
        """Whether command ``a`` puts a point outside the workspace box (False without a box)."""
        if self.workspace is None:
            return False
        return bool(np.any(self.outside(self.points(np.asarray(a, dtype=float)))))

    def violation(self, a):
        """Why command ``a`` may not be sent, or None: ``"joint limit"`` or ``"workspace"``."""
        a = np.asarray(a, dtype=float)
        if a.shape != self.lower.shape or not np.all(np.isfinite(a)):
            return "malformed"
        if np.any(a < self.lower - 1e-12) or np.any(a > self.upper + 1e-12):
            return "joint limit"
        return "workspace" if self.outside_box(a) else None


class SettleDetector:
    """Whether an arm has come to rest at its goal: every joint within ``tolerance`` of the goal and moving less
    than ``still`` between readings taken at least ``window`` s apart; or ``timeout`` s after the move should have
    ended (:meth:`expired`).

    Readings are judged by the time they were taken, so a joint state that stopped arriving never looks still: the
    same reading fed twice is ignored.

    Parameters
    ----------
    tolerance : float
        rad (m) from the goal.
    still : float
        Largest change (rad, m) between two readings at least ``window`` s apart that counts as at rest.
    window : float
        s.
    timeout : float
        s after the planned end of the move at which it counts as settled anyway.
    """

    def __init__(self, tolerance=0.01, still=0.002, window=0.1, timeout=2.0):
        for name, value in (("tolerance", tolerance), ("still", still), ("window", window), ("timeout", timeout)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be a finite number >= 0, got {value!r}")
        self.tolerance, self.still, self.window, self.timeout = tolerance, still, window, timeout
        self._goal = None

    def start(self, goal, planned_end):
        """A new move towards ``goal`` (m,) that should end at time ``planned_end`` (s)."""
        self._goal = np.asarray(goal, dtype=float)
        self._end = float(planned_end)
        self._previous = None
        self._last_stamp = -math.inf

    def reading(self, positions, stamp):
        """Feed a joint reading (m,) taken at ``stamp`` (s); returns whether the arm has settled at the goal."""
        if self._goal is None or stamp <= self._last_stamp:
            return False
        self._last_stamp = stamp
        positions = np.asarray(positions, dtype=float)
        if positions.shape != self._goal.shape or not np.all(np.isfinite(positions)):
            return False
        at_goal = bool(np.all(np.abs(positions - self._goal) <= self.tolerance))
        if self._previous is None or stamp - self._previous[0] >= self.window - 1e-9:
            still = self._previous is not None and bool(np.all(np.abs(positions - self._previous[1]) <= self.still))
            self._previous = (stamp, positions)
            return at_goal and still
        return False

    def expired(self, now):
        """Whether ``timeout`` s have passed since the planned end of the move at time ``now`` (s)."""
        return self._goal is not None and now >= self._end + self.timeout
