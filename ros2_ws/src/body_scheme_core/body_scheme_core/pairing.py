"""Pairing action commands with the observations that show their result (one learning sample per command).

The learner needs samples (a_t, Y_t): the command a_t and marker poses Y_t observed after the arm executed it. Commands
and observations arrive on separate streams, possibly out of order with respect to each other. The rule:

- A command issued at stamp ``c`` is *shown* by the first observation stamped in ``[c + settle_time, c + max_delay]``
  and before the next command's stamp. That observation and the command form one sample.
- Further observations of the same command are not used (counted as ``duplicate``), so a slow command rate does
  not flood the test windows with copies of one configuration.
- An observation is decided only once it is certain which command it belongs to: when a command stamped after it
  has arrived, or when :meth:`flush` is called with a time ``>= stamp + grace``. Until then it waits in a buffer.

Rejections are counted by reason in :attr:`rejected`: ``out_of_order_command`` (command stamp not increasing),
``out_of_order_observation`` (observation older than one already decided), ``no_command`` (no command before it),
``stale`` (later than ``max_delay`` after its command), ``settling`` (earlier than ``settle_time`` after it), and
``duplicate``.

Recordings of other stacks have no command stream, only measured joint values at a high rate: :func:`still_periods`
finds where the arm stood still, and each still period becomes one command (the sample is taken once the arm has
settled, as with our own commands).
"""

from __future__ import annotations

import bisect
import math
from collections import Counter, deque

import numpy as np

from .errors import InvalidInputError

__all__ = ["CommandObservationPairer", "still_periods"]

_CHUNK = 256  # samples tested at once while a still period is extended


class CommandObservationPairer:
    """Turn two time-stamped streams into learning samples.

    Parameters
    ----------
    settle_time : float
        Seconds after a command before an observation may show its result.
    max_delay : float
        Seconds after a command after which observations no longer count as showing it.
    grace : float
        Seconds an observation waits for a possibly late command message before it is decided.
    max_commands : int
        Number of recent commands kept.
    """

    def __init__(self, settle_time=0.0, max_delay=2.0, grace=0.2, max_commands=256):
        if not (settle_time >= 0.0 and max_delay > settle_time and grace >= 0.0):
            raise InvalidInputError(
                f"need 0 <= settle_time < max_delay and grace >= 0, got {settle_time}, {max_delay}, {grace}")
        self.settle_time = float(settle_time)
        self.max_delay = float(max_delay)
        self.grace = float(grace)
        self._stamps = deque(maxlen=max_commands)
        self._actions = deque(maxlen=max_commands)
        self._used = deque(maxlen=max_commands)
        self._pending = []  # (stamp, observations), sorted by stamp
        self._decided_until = -math.inf
        self.rejected = Counter()

    def add_command(self, stamp, actions):
        """Record a command; returns the samples it resolves, as :meth:`flush` does."""
        stamp = float(stamp)
        if self._stamps and stamp <= self._stamps[-1]:
            self.rejected["out_of_order_command"] += 1
            return []
        self._stamps.append(stamp)
        self._actions.append(np.asarray(actions, dtype=float).copy())
        self._used.append(False)
        return self._decide(lambda obs_stamp: obs_stamp < stamp)

    def add_observation(self, stamp, observations):
        """Buffer an observation (any payload, e.g. ``{marker id: world2part}``) until it can be decided."""
        stamp = float(stamp)
        if stamp <= self._decided_until:
            self.rejected["out_of_order_observation"] += 1
            return
        bisect.insort(self._pending, (stamp, len(self.rejected), observations), key=lambda item: item[0])

    @property
    def waiting(self):
        """Number of observations buffered until it is certain which command they belong to."""
        return len(self._pending)

    def flush(self, now):
        """Decide buffered observations older than ``now - grace``; returns ``[(stamp, actions, observations)]``."""
        return self._decide(lambda obs_stamp: obs_stamp <= now - self.grace)

    def _decide(self, ready):
        samples = []
        while self._pending and ready(self._pending[0][0]):
            stamp, _, observations = self._pending.pop(0)
            self._decided_until = stamp
            sample = self._pair(stamp, observations)
            if sample is not None:
                samples.append(sample)
        return samples

    def _pair(self, stamp, observations):
        k = bisect.bisect_right(self._stamps, stamp) - 1
        if k < 0:
            self.rejected["no_command"] += 1
            return None
        age = stamp - self._stamps[k]
        if age < self.settle_time:
            self.rejected["settling"] += 1
            return None
        if age > self.max_delay:
            self.rejected["stale"] += 1
            return None
        if self._used[k]:
            self.rejected["duplicate"] += 1
            return None
        self._used[k] = True
        return stamp, self._actions[k], observations


def still_periods(stamps, values, tolerance, min_duration):
    """The periods in which the joint values stood still: one per pose of a recorded session.

    A period starts at a sample and holds every following sample whose values stay within ``tolerance`` of that
    first one (per joint); it counts if it lasts at least ``min_duration``. Periods do not overlap; motion between
    them is skipped.

    Parameters
    ----------
    stamps : array-like, shape (n,)
        Seconds, non-decreasing.
    values : array-like, shape (n, m)
        Joint values (rad or m).
    tolerance : float
        Largest change of any joint within a period (rad or m), > 0.
    min_duration : float
        Shortest period, s, >= 0.

    Returns
    -------
    periods : list of (float, float, ndarray of shape (m,))
        ``(start, end, mean values)`` per period, in time order.

    Raises
    ------
    InvalidInputError
        For shapes that do not match, stamps that decrease or values that are not finite.
    """
    stamps = np.asarray(stamps, dtype=float).reshape(-1)
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or len(values) != len(stamps):
        raise InvalidInputError(f"need stamps (n,) and values (n, m), got {stamps.shape} and {values.shape}")
    if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(values))):
        raise InvalidInputError("stamps and joint values must be finite")
    if np.any(np.diff(stamps) < 0):
        raise InvalidInputError("stamps must not decrease")
    if not (tolerance > 0 and min_duration >= 0):
        raise InvalidInputError(f"need tolerance > 0 and min_duration >= 0, got {tolerance}, {min_duration}")
    periods, i, n = [], 0, len(stamps)
    while i < n:
        # The samples up to min_duration after the start must all hold (one vectorised test per start) ...
        e = int(np.searchsorted(stamps, stamps[i] + min_duration, side="left"))
        if e >= n:
            break  # the recording ends before any later start could last min_duration
        if np.any(np.abs(values[i:e + 1] - values[i]) > tolerance):
            i += 1
            continue
        # ... and the period then runs until the first sample that moved (searched in chunks).
        j = e + 1
        while j < n:
            moved = np.flatnonzero(np.any(np.abs(values[j:j + _CHUNK] - values[i]) > tolerance, axis=1))
            if moved.size:
                j += int(moved[0])
                break
            j += _CHUNK
        j = min(j, n)
        periods.append((float(stamps[i]), float(stamps[j - 1]), values[i:j].mean(axis=0)))
        i = j
    return periods
