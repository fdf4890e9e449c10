"""scheme_node's loop from messages to learning steps, without ROS (no node, no DDS): an injected clock, messages
built in memory, the learning step and the rejections recorded."""

import threading
import time

import numpy as np
import pytest

from body_scheme_nodes import conversions
from body_scheme_nodes.learning_loop import LearningLoop
from body_scheme_nodes.settings import SchemeSettings


class Loop:
    """A LearningLoop on a 1-joint, 2-part robot with a clock the test sets; ``learnt`` and ``rejected`` record."""

    def __init__(self, **settings):
        self.now, self.learnt, self.rejected = 10.0, [], []
        values = {"part_ids": [1, 2], "joint_names": ["j"], "pairing_grace": 0.0, **settings}
        self.loop = LearningLoop(SchemeSettings.from_parameters(values), lambda: self.now, self._learn,
                                 lambda *why: self.rejected.append(why))

    def _learn(self, *sample):
        self.learnt.append(sample)
        return True  # the learner took it

    def put(self, *messages):
        """Put ``(receipt time, message)`` pairs, received in that order."""
        self.loop.put([(t, "command" if hasattr(msg, "position") else "observations", msg) for t, msg in messages])

    def work(self):
        self.loop.work(self.loop.take_inbox())


def command(stamp, q):
    return conversions.joint_state_msg(stamp, ["j"], [q])


def observations(stamp):
    return conversions.marker_poses_msg(stamp, "camera", {1: np.eye(4), 2: np.eye(4)})


def _pairs(start, n):
    """``n`` command/observation pairs 0.5 s apart from ``start``, each received at its stamp."""
    return [item for k in range(n) for item in ((start + 0.5 * k, command(start + 0.5 * k, 0.1 * k)),
                                                (start + 0.5 * k + 0.1, observations(start + 0.5 * k + 0.1)))]


def test_one_sample_is_learnt_per_step_oldest_first_and_progress_counts_the_decided_messages():
    loop = Loop()
    loop.put(*_pairs(9.0, 2))
    loop.work()
    assert [stamp for stamp, _, _ in loop.learnt] == [pytest.approx(9.1)]
    assert loop.loop.received == {"command": 2, "observations": 2}
    assert loop.loop.progress() == 1 and len(loop.loop.pending) == 1  # the second waits its turn
    loop.work()
    assert [stamp for stamp, _, _ in loop.learnt] == [pytest.approx(9.1), pytest.approx(9.6)]
    assert loop.loop.progress() == 2


def test_a_sample_older_than_max_sample_age_when_its_turn_comes_is_shed_and_the_next_is_learnt():
    loop = Loop(max_sample_age=1.0)
    loop.put(*_pairs(9.0, 2))
    loop.now = 10.05  # a sample is as old as what completed its pair: the first, the command received at 9.5
    loop.work()
    loop.put(*_pairs(11.0, 1))
    loop.now = 12.0  # the second (completed by the pairer's flush at 10.05) is 1.95 s old: shed; the third learnt
    loop.work()
    assert [stamp for stamp, _, _ in loop.learnt] == [pytest.approx(9.1), pytest.approx(11.1)]
    assert loop.loop.shed == {"stale_samples": 1}
    assert list(loop.loop.lag) == [pytest.approx(0.55), pytest.approx(0.0)]


def test_the_intake_snapshot_accounts_for_every_message_received():
    """Received = in the inbox + shed from it + taken in (decided, waiting in the pairer or pending), at one instant."""
    loop = Loop(max_inbox=3)
    loop.put(*_pairs(9.0, 3))
    received, shed, inbox = loop.loop.intake_snapshot()
    assert received == {"command": 3, "observations": 3} and inbox == 3
    assert sum(shed.values()) + inbox == 6
    loop.work()
    received, shed, inbox = loop.loop.intake_snapshot()
    # decided (progress: learnt, refused, or shed from the inbox) + waiting for a command + waiting to be learnt
    assert inbox == 0 and shed["observations_messages"] == 1
    assert received["observations"] == loop.loop.progress() + loop.loop.pairer.waiting + len(loop.loop.pending)


def test_beyond_max_inbox_the_oldest_messages_are_shed_and_counted_by_kind():
    loop = Loop(max_inbox=3)
    loop.put(*_pairs(9.0, 3))
    assert loop.loop.shed == {"command_messages": 2, "observations_messages": 1}
    assert loop.loop.received == {"command": 3, "observations": 3}
    assert [kind for kind, _, _ in loop.loop.take_inbox()] == ["observations", "command", "observations"]


def test_beyond_max_pending_samples_the_oldest_samples_are_shed():
    loop = Loop(max_pending_samples=2)
    loop.now = 12.0
    loop.put(*_pairs(9.0, 5))
    loop.work()  # five paired, three shed, the oldest of the two left learnt
    assert loop.loop.shed == {"samples": 3} and len(loop.learnt) == 1 and len(loop.loop.pending) == 1


def test_a_zero_stamp_is_its_receipt_time_or_refused_and_a_future_stamp_is_refused():
    loop = Loop(stamp_tolerance=1.0)
    loop.put((9.0, command(0.0, 0.1)), (9.1, observations(0.0)), (9.5, command(20.0, 0.2)))
    loop.work()
    assert [stamp for stamp, _, _ in loop.learnt] == [pytest.approx(9.1)]
    assert loop.loop.restamped == {"unstamped": 2} and [code for code, _ in loop.rejected] == ["future_stamp"]
    strict = Loop(unstamped_policy="reject")
    strict.put((9.0, command(0.0, 0.1)))
    strict.work()
    assert strict.rejected == [("unstamped", "zero stamp (unstamped_policy: reject)")] and not strict.learnt


def test_messages_too_large_to_read_are_counted_as_received_and_decided():
    loop = Loop()
    loop.loop.put([], refused=["observations", "command"])
    assert loop.loop.received == {"observations": 1, "command": 1}
    assert loop.loop.intake_counts() == {"oversized_message": 2} and loop.loop.progress() == 1


def test_the_stall_is_how_long_commands_keep_arriving_unlearnt_not_observations_nor_one_late_command():
    """The arm standing (babble_node in its pre-flight, a pause) sends observations only: no stall. The first command
    after a quiet spell is no stall either; commands that keep arriving with nothing learnt (a dead camera) are,
    until a sample is learnt."""
    loop = Loop()
    loop.put((9.1, observations(9.1)), (9.6, observations(9.6)))
    loop.work()
    assert loop.loop.stalled_for() == 0.0 and not loop.learnt
    for now in (40.0, 45.0, 52.0):  # 30 s after the start, then every few seconds, never an observation after them
        loop.now = now
        loop.put((now, command(now, 0.3)))
        loop.work()
    assert loop.loop.stalled_for() == 12.0
    loop.now = 52.1
    loop.put((52.1, observations(52.1)))  # the last command's observation: a sample, learnt
    loop.work()
    assert loop.learnt and loop.loop.stalled_for() == 0.0


def test_the_learning_thread_learns_what_is_put_under_the_given_lock_and_stops():
    loop, lock, steps, failures = Loop(), threading.Lock(), [], []
    learn = loop.loop._learn

    def learn_under_the_lock(*sample):
        assert lock.locked()  # readers of the learner hold it too
        return learn(*sample)

    loop.loop._learn = learn_under_the_lock
    loop.loop.start(lock, on_failure=failures.append, after_step=lambda: steps.append(1))
    try:
        loop.put(*_pairs(9.0, 2))
        deadline = time.monotonic() + 60  # a condition, waited for however busy the machine
        while len(loop.learnt) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(loop.learnt) == 2 and steps and not failures, failures
    finally:
        loop.loop.stop()
    assert not loop.loop.thread.is_alive()


def test_an_error_in_the_learning_thread_is_handed_over_and_ends_it():
    loop, failures = Loop(), []

    def broken(inbox):
        raise ZeroDivisionError("a bug in learning")

    loop.loop.work = broken
    loop.loop.start(threading.Lock(), on_failure=failures.append)
    loop.loop.thread.join(timeout=60)
    assert not loop.loop.thread.is_alive() and isinstance(failures[0], ZeroDivisionError)
    loop.loop.stop()  # after the thread ended: nothing to wait for
