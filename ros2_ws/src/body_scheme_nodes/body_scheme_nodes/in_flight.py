"""Backpressure on scheme_node: how many of the messages sent to it it has not decided yet.

scheme_node counts the observation messages it has decided (learnt, refused or shed) on ``body_scheme/progress``
(transient local: a node that joins late gets the count at once). bag_replay's rate 0 publishes, and sim_node's
``max_in_flight`` babbles, only while fewer than a limit of their messages are in flight. :class:`InFlight` is that
count, without ROS: the node feeds it the progress messages and what it sent.
"""

from __future__ import annotations

__all__ = ["InFlight"]


class InFlight:
    """Messages sent and not yet decided by scheme_node, counted from :meth:`start`.

    Attributes
    ----------
    progress : int or None
        scheme_node's latest count (None until its first message).
    sent : int
        Messages sent since :meth:`start` (the node adds to it).
    lost : int
        Messages given up by :meth:`count_as_lost` and not decided since.
    """

    def __init__(self):
        self.progress, self.sent, self.lost = None, 0, 0
        self._start, self._changed_at = None, None

    @property
    def started(self):
        return self._start is not None

    def on_progress(self, value, now):
        """A ``body_scheme/progress`` message at monotonic time ``now``; a message given up and decided after all is
        taken back from :attr:`lost`."""
        if value != self.progress:
            self.progress, self._changed_at = int(value), now
            self.lost = min(self.lost, max(0, self.sent - self.decided))

    def start(self, now):
        """Count from here: what scheme_node decided before is not ours."""
        self._start, self._changed_at = self.progress or 0, now

    @property
    def decided(self):
        """Messages decided since :meth:`start`."""
        return 0 if self._start is None or self.progress is None else self.progress - self._start

    def count(self):
        """Messages in flight: sent, not decided, not given up."""
        return self.sent - self.lost - self.decided

    def stalled_for(self, now):
        """Seconds since the count last moved (or since :meth:`start`)."""
        return 0.0 if self._changed_at is None else now - self._changed_at

    def count_as_lost(self, now):
        """The messages in flight will not be decided (dropped on the way, e.g. a picture the tracker had no time
        for): give them up, and count the stall from ``now``."""
        self.lost += max(0, self.count())
        self._changed_at = now
