"""Tests of pairing commands with the observations that show them."""

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.pairing import CommandObservationPairer, still_periods


def test_pairs_first_observation_after_each_command():
    """Each command pairs with its first later observation; later copies count as duplicates."""
    p = CommandObservationPairer(max_delay=1.0, grace=0.0)
    p.add_command(1.0, [0.1])
    p.add_observation(1.1, "A")
    p.add_observation(1.2, "B")
    samples = p.add_command(2.0, [0.2])
    assert [(s, a.tolist(), o) for s, a, o in samples] == [(1.1, [0.1], "A")]
    assert p.rejected["duplicate"] == 1


def test_observation_waits_for_late_command():
    """An observation that arrives before its (earlier-stamped) command is paired with that command."""
    p = CommandObservationPairer(max_delay=1.0, grace=0.5)
    p.add_command(1.0, [0.1])
    p.add_observation(2.1, "late")
    assert p.flush(now=2.2) == []  # still within grace: the command for 2.0 may be in flight
    assert p.add_command(2.0, [0.2]) == []  # 2.1 is not before 2.0: still undecided
    assert p.waiting == 1
    ((stamp, actions, obs),) = p.flush(now=3.0)
    assert p.waiting == 0
    assert (stamp, obs) == (2.1, "late")
    np.testing.assert_array_equal(actions, [0.2])


def test_rejections_are_counted_by_reason():
    """Out-of-order, stale, settling and command-less observations are counted, never silently dropped."""
    p = CommandObservationPairer(settle_time=0.05, max_delay=0.5, grace=0.0)
    p.add_observation(0.5, "before any command")
    p.flush(now=0.6)
    p.add_command(1.0, [0.0])
    p.add_command(0.9, [0.0])
    p.add_observation(1.01, "settling")
    p.add_observation(1.9, "stale")
    p.flush(now=2.0)
    p.add_observation(1.5, "out of order")
    assert p.rejected == {"no_command": 1, "out_of_order_command": 1, "settling": 1, "stale": 1,
                          "out_of_order_observation": 1}


def test_invalid_timing_parameters_rejected():
    """max_delay must exceed settle_time."""
    with pytest.raises(InvalidInputError):
        CommandObservationPairer(settle_time=1.0, max_delay=0.5)


# ---------------------------------------------------------------------- still periods
def test_still_periods_find_each_hold_and_skip_motion_and_short_stops():
    t = np.arange(0.0, 3.0, 0.02)
    q = np.where(t < 1.0, 0.0, np.where(t < 1.4, (t - 1.0) / 0.4, 1.0))  # hold, move, hold
    q[(t > 1.1) & (t < 1.2)] = q[(t > 1.1) & (t < 1.2)][0]  # a 0.1 s stop within the move: too short
    periods = still_periods(t, np.column_stack([q, -q]), tolerance=1e-3, min_duration=0.3)
    assert [(round(a, 2), round(b, 2)) for a, b, _ in periods] == [(0.0, 1.0), (1.4, 2.98)]
    np.testing.assert_allclose(periods[1][2], [1.0, -1.0])


@pytest.mark.parametrize("stamps, values, tolerance", [
    ([0.0, 1.0], [[0.0], [np.nan]], 1e-3),     # not finite
    ([1.0, 0.0], [[0.0], [0.0]], 1e-3),        # stamps decrease
    ([0.0, 1.0], [0.0, 0.0], 1e-3),            # values not (n, m)
    ([0.0, 1.0], [[0.0], [0.0]], 0.0),         # tolerance 0
])
def test_still_periods_refuse_bad_input(stamps, values, tolerance):
    with pytest.raises(InvalidInputError):
        still_periods(stamps, values, tolerance, 0.1)
