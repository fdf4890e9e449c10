"""Trajectory durations, safety limits and settling for driving a real arm."""

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.motion import SafetyLimits, SettleDetector, trajectory_duration


def test_duration_is_the_slowest_joints_trapezoid_or_triangle():
    """1 rad at 1 rad/s and 2 rad/s^2 takes 1/1 + 1/2 = 1.5 s (trapezoid); 0.1 rad takes 2 sqrt(0.1/2) (triangle);
    the slowest joint sets the time, and a zero move takes the minimum."""
    assert trajectory_duration([0, 0], [1.0, 0.1], 1.0, 2.0) == pytest.approx(1.5)
    assert trajectory_duration([0], [0.1], 1.0, 2.0) == pytest.approx(2 * np.sqrt(0.05))
    assert trajectory_duration([0, 0], [0.5, 0.5], [1.0, 0.25], [10.0, 10.0]) == pytest.approx(0.5 / 0.25 + 0.025)
    assert trajectory_duration([1, 2], [1, 2], 1.0, 1.0, min_duration=0.2) == 0.2
    with pytest.raises(InvalidInputError):
        trajectory_duration([0], [1], 0.0, 1.0)
    with pytest.raises(InvalidInputError):
        trajectory_duration([0], [np.nan], 1.0, 1.0)


def test_safety_limits_keep_a_margin_and_the_workspace_box():
    """Commands within the margin of a limit, or putting a point outside the box, are refused and say why."""
    limits = SafetyLimits([-1.0, -1.0], [1.0, 1.0], margin=0.1, workspace=[[-1, -1, 0], [1, 1, 1]],
                          points=lambda a: np.array([[a[0], a[1], 0.5], [0.0, 0.0, a[0]]]))
    assert limits.violation([0.5, 0.5]) is None
    assert limits.violation([0.95, 0.0]) == "joint limit"
    assert limits.violation([-0.5, 0.0]) == "workspace"  # the second point's z < 0
    assert limits.violation([0.0, np.inf]) == "malformed"
    narrow = SafetyLimits([0.0], [0.1], margin=1.0)  # the margin is at most half the range
    assert narrow.violation([0.05]) is None
    with pytest.raises(InvalidInputError, match="points"):
        SafetyLimits([0.0], [1.0], workspace=[[0, 0, 0], [1, 1, 1]])


def test_settling_needs_the_goal_and_stillness_or_the_timeout():
    """At the goal but still moving is not settled; at the goal and still over the window is; far from the goal
    only the timeout after the planned end settles (and says so)."""
    settle = SettleDetector(tolerance=0.01, still=0.002, window=0.1, timeout=1.0)
    settle.start([1.0], planned_end=0.5)
    assert not settle.update([0.995], 0.4)
    assert not settle.update([1.004], 0.5)  # moved 9 mrad in 0.1 s
    assert settle.update([1.005], 0.6) and not settle.timed_out
    settle.start([2.0], planned_end=1.0)
    assert not settle.update([1.5], 1.2) and not settle.update([1.5], 1.5)
    assert settle.update([1.5], 2.0) and settle.timed_out
