"""body_scheme_nodes.graph: while a monitor node is open, the first SIGINT or SIGTERM is an interrupt the program's
finally blocks unwind (stopping its nodes), later ones do not cut that short, and the handlers are put back after."""

import os
import signal

import pytest

from body_scheme_nodes.graph import _interrupted_by_signals


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

