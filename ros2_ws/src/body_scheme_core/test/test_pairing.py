"""Tests of pairing commands with the observations that show them."""

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.pairing import CommandObservationPairer


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
