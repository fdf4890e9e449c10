"""body_scheme_nodes.graph: while a monitor node is open, the first SIGINT or SIGTERM is an interrupt the program's
finally blocks unwind (stopping its nodes), later ones do not cut that short, and the handlers are put back after."""

import os
import signal

import pytest

from body_scheme_nodes.graph import _interrupted_by_signals, spin_until


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_first_signal_interrupts_later_ones_wait_and_the_handlers_are_restored(sig):
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    stopped = []
    with pytest.raises(KeyboardInterrupt, match=sig.name):
        with _interrupted_by_signals():
            try:
                os.kill(os.getpid(), sig)  # Python runs the handler before the next line
                stopped.append("not interrupted")
            finally:
                os.kill(os.getpid(), signal.SIGINT)  # a second Ctrl-C, and a kill, while the nodes are being stopped
                os.kill(os.getpid(), signal.SIGTERM)
                stopped.append(True)
    assert stopped == [True]
    assert {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)} == before


@pytest.fixture
def executor():
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    node = rclpy.create_node("spin_until_test", context=context)
    executor.add_node(node)
    try:
        yield executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_spin_until_returns_once_the_predicate_holds_and_calls_during_before_each_spin(executor):
    calls = []
    assert spin_until(executor, lambda: len(calls) >= 3, timeout=60, during=lambda: calls.append(1), step=0.001)
    assert len(calls) == 3


def test_spin_until_gives_up_after_the_timeout_unless_progress_moves(executor):
    assert not spin_until(executor, lambda: False, timeout=0.05, step=0.001)
    ticks = []
    # Each spin moves the progress: 1,000 spins of at least 1 ms wait out a 0.2 s timeout five times; the predicate
    # decides.
    assert spin_until(executor, lambda: len(ticks) >= 1000, timeout=0.2, during=lambda: ticks.append(1),
                      progress=lambda: len(ticks), step=0.001)
