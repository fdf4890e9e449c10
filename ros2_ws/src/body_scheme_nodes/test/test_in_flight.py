"""The backpressure count of bag_replay's rate 0 and sim_node's max_in_flight (body_scheme_nodes.in_flight)."""

from body_scheme_nodes.in_flight import InFlight


def test_counts_from_the_start_what_scheme_node_has_not_decided():
    count = InFlight()
    assert count.progress is None and not count.started
    count.on_progress(7, now=0.0)  # decided before we started: not ours
    count.start(now=1.0)
    count.sent += 3
    assert count.count() == 3 and count.decided == 0
    count.on_progress(9, now=2.0)
    assert count.count() == 1 and count.decided == 2 and count.stalled_for(2.5) == 0.5


def test_messages_given_up_are_taken_back_when_decided_after_all():
    count = InFlight()
    count.on_progress(0, now=0.0)
    count.start(now=0.0)
    count.sent += 4
    count.on_progress(1, now=1.0)
    count.count_as_lost(now=3.0)  # the three in flight will not come: given up, the stall counts anew
    assert count.lost == 3 and count.count() == 0 and count.stalled_for(3.0) == 0.0
    count.sent += 1
    count.on_progress(4, now=4.0)  # two of them were decided after all
    assert count.lost == 1 and count.count() == 0
    count.on_progress(5, now=5.0)
    assert count.lost == 0 and count.count() == 0
