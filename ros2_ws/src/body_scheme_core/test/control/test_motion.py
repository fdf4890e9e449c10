"""Trajectory durations, safety limits and settling for driving a real arm."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from body_scheme_core.control.motion import SafetyLimits, SettleDetector, path_samples, trajectory_duration
from body_scheme_core.errors import InvalidInputError


def test_duration_keeps_the_controllers_cubic_within_both_limits():
    """A one-point trajectory is a cubic from rest to rest: peak speed 1.5 d / T, peak acceleration 6 d / T^2. 1 rad
    at 1 rad/s and 10 rad/s^2 is speed-bound (1.5 s); 0.1 rad at 1 rad/s and 2 rad/s^2 is acceleration-bound
    (sqrt(0.3)); the slowest joint sets the time; a zero move takes the minimum."""
    assert trajectory_duration([0, 0], [1.0, 0.1], 1.0, 10.0) == pytest.approx(1.5)
    assert trajectory_duration([0], [0.1], 1.0, 2.0) == pytest.approx(np.sqrt(0.3))
    assert trajectory_duration([0, 0], [0.5, 0.5], [1.0, 0.25], [10.0, 10.0]) == pytest.approx(1.5 * 0.5 / 0.25)
    assert trajectory_duration([1, 2], [1, 2], 1.0, 1.0, min_duration=0.2) == 0.2
    with pytest.raises(InvalidInputError):
        trajectory_duration([0], [1], 0.0, 1.0)
    with pytest.raises(InvalidInputError):
        trajectory_duration([0], [np.nan], 1.0, 1.0)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.1, 5), st.floats(0.1, 20)),
                min_size=1, max_size=7))
def test_the_cubic_of_the_duration_never_exceeds_a_limit(joints):
    """Sampled densely, the controller's cubic over the returned duration stays within every joint's speed and
    acceleration limit (to 1 %)."""
    start, goal, v, a = (np.array(column) for column in zip(*joints, strict=True))
    T = trajectory_duration(start, goal, v, a, min_duration=1e-3)
    s = np.linspace(0.0, 1.0, 2001)[:, None]
    speed = np.abs(goal - start) * 6 * s * (1 - s) / T
    acceleration = np.abs(goal - start) * np.abs(6 - 12 * s) / T**2
    assert np.all(speed <= 1.01 * v) and np.all(acceleration <= 1.01 * a)


def test_path_samples_step_at_most_max_step_and_end_at_the_goal():
    """No joint moves more than max_step between samples, the start is left out and the goal is the last."""
    samples = path_samples([0.0, 0.0], [1.0, -0.2], max_step=0.05)
    assert samples.shape == (20, 2)
    assert np.allclose(samples[-1], [1.0, -0.2])
    assert np.max(np.abs(np.diff(np.vstack([[0.0, 0.0], samples]), axis=0))) <= 0.05 + 1e-12
    assert path_samples([1.0], [1.0]).shape == (1, 1)
    with pytest.raises(InvalidInputError):
        path_samples([0.0], [1.0], max_step=0.0)


@pytest.mark.parametrize("start", [1e308, 1e6, float("nan")])
def test_a_path_from_an_implausible_posture_is_refused_not_enumerated(start):
    """A start 1e308 away overflowed and 1e6 away asked for 2x10^7 postures (1.8 GB): both are refused at once."""
    with pytest.raises(InvalidInputError):
        path_samples([start, 0.0], [0.0, 0.0], max_step=0.05)
    assert path_samples([0.0], [400.0], max_step=0.05).shape == (8000, 1)  # long, within MAX_PATH_SAMPLES


def test_safety_limits_keep_a_margin_and_the_workspace_box():
    """Commands within the margin of a limit, or putting a point outside the box, are refused and say why."""
    limits = SafetyLimits([-1.0, -1.0], [1.0, 1.0], margin=0.1, workspace=[[-1, -1, 0], [1, 1, 1]],
                          points=lambda a: np.array([[a[0], a[1], 0.5], [0.0, 0.0, a[0]]]))
    assert limits.violation([0.5, 0.5]) is None
    assert limits.violation([0.95, 0.0]) == "joint limit"
    assert limits.violation([-0.5, 0.0]) == "workspace"  # the second point's z < 0
    assert limits.violation([0.0, np.inf]) == "malformed"
    assert limits.outside([[0.0, 0.0, 0.5], [0.0, 0.0, -0.1], [2.0, 0.0, 0.5]]).tolist() == [False, True, True]
    narrow = SafetyLimits([0.0], [0.1], margin=1.0)  # the margin is at most half the range
    assert narrow.violation([0.05]) is None and narrow.outside([[9.0, 9.0, 9.0]]).tolist() == [False]  # no box
    with pytest.raises(InvalidInputError, match="points"):
        SafetyLimits([0.0], [1.0], workspace=[[0, 0, 0], [1, 1, 1]])


def test_settling_needs_the_goal_and_stillness_or_the_timeout():
    """At the goal but still moving is not settled; at the goal and still over the window is; far from the goal
    only the timeout after the planned end settles."""
    settle = SettleDetector(tolerance=0.01, still=0.002, window=0.1, timeout=1.0)
    settle.start([1.0], planned_end=0.5)
    assert not settle.reading([0.995], 0.4)
    assert not settle.reading([1.004], 0.5)  # moved 9 mrad in 0.1 s
    assert settle.reading([1.005], 0.6)
    settle.start([2.0], planned_end=1.0)
    assert not settle.reading([1.5], 1.2) and not settle.reading([1.5], 1.5)
    assert not settle.expired(1.9) and settle.expired(2.0)


def test_a_reading_that_stopped_arriving_never_looks_still():
    """The same reading fed again (joint states went quiet) is ignored: it cannot settle the move; only a new one
    taken a window later can."""
    settle = SettleDetector(tolerance=0.01, still=0.002, window=0.1, timeout=1.0)
    settle.start([1.0], planned_end=0.0)
    assert not settle.reading([1.0], 0.3)
    assert not settle.reading([1.0], 0.3) and not settle.reading([1.0], 0.3)
    assert settle.reading([1.0], 0.4)
