"""``body_scheme_nodes.graph.spin_until``: what live_demo and the tests wait with."""

from body_scheme_nodes.graph import spin_until


def test_spin_until_returns_once_the_predicate_holds_and_calls_during_before_each_spin(ros_node):
    calls = []
    assert spin_until(ros_node.executor_for_test, lambda: len(calls) >= 3, timeout=60,
                      during=lambda: calls.append(1), step=0.001)
    assert len(calls) == 3


def test_spin_until_gives_up_after_the_timeout_unless_progress_moves(ros_node):
    executor = ros_node.executor_for_test
    assert not spin_until(executor, lambda: False, timeout=0.05, step=0.001)
    ticks = []
    # Each spin moves the progress: 300 spins of at least 5 ms outlast the 1 s timeout; the predicate decides (a
    # 1 s window between two lines: no busy machine stalls a thread that long).
    assert spin_until(executor, lambda: len(ticks) >= 300, timeout=1.0, during=lambda: ticks.append(1),
                      progress=lambda: len(ticks), step=0.005)
