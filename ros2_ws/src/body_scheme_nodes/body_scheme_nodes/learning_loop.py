"""scheme_node's way from messages to learning steps, without ROS: the inbox, the stamp policy, pairing, the waiting
samples, and what is shed under overload.

The executor's thread :meth:`~LearningLoop.put` s every message it took from DDS, with its receipt time on the node
clock (beyond ``max_inbox`` the oldest are shed, counted by kind). The learning thread takes the inbox
(:meth:`~LearningLoop.take_inbox`) and :meth:`~LearningLoop.work` s on it: the stamp policy (a zero stamp is
restamped at receipt or refused, a stamp beyond ``stamp_tolerance`` ahead of the clock is refused), pairing through
:func:`~body_scheme_nodes.message_feed.feed_message` (the function the offline replay calls), the bound on waiting
samples (``max_pending_samples``, oldest shed), and one learning step on the oldest sample not older than
``max_sample_age`` (older ones are shed: under overload the learner keeps to the freshest data). The learning thread
(:meth:`~LearningLoop.start`, :meth:`~LearningLoop.stop`) repeats that, waking when messages are put. scheme_node wraps
it in ROS: subscriptions, publishers, services and /diagnostics.
"""

from __future__ import annotations

import threading
from collections import Counter, deque

from . import conversions
from .message_feed import feed_message

__all__ = ["LearningLoop"]


class LearningLoop:
    """The loop for one learner's settings (:class:`~body_scheme_nodes.settings.SchemeSettings`).

    ``clock()`` is the node's time in seconds; ``learn(stamp, actions, observed)`` learns one sample and says
    whether the learner took it (scheme_node publishes what came of it); ``reject(code, detail)`` counts and reports
    a refused input. Counters: ``received`` (messages put, by kind), ``refused_at_intake`` (too large to read),
    ``restamped``, ``shed`` (``<kind>_messages`` from the inbox, ``samples`` beyond ``max_pending_samples``,
    ``stale_samples`` beyond ``max_sample_age``), ``lag`` (the age of the last 200 samples when learnt, s).

    Threads: :meth:`put` and :meth:`intake_counts` take the loop's own lock (the executor's thread puts while the
    learning thread takes the inbox). :meth:`work` writes ``pending``, the pairer, ``restamped``, ``lag``, the
    learning thread's ``shed`` counts and the stall's command times: the learning thread holds the lock given to
    :meth:`start` around it, and every reader of those (and of the learner) holds it too (scheme_node's
    ``_learner_lock``, which its /diagnostics takes)."""

    def __init__(self, settings, clock, learn, reject):
        self.settings, self.clock, self._learn, self._reject = settings, clock, learn, reject
        self.pairer = settings.new_pairer()
        self.pending = deque()  # (receipt time, paired sample) not learnt yet: the learning thread's
        self._inbox = deque()  # (kind, message, receipt time): put by one thread, taken by the other
        self._lock = threading.Lock()
        self.received, self.refused_at_intake, self.restamped, self.shed = Counter(), Counter(), Counter(), Counter()
        self.lag = deque(maxlen=200)
        self.n_observation_messages = 0  # taken in by the learning thread
        self.oversized_observations = 0  # observation messages refused unread
        self._unlearnt = None  # (first, last) node times of the commands taken in since a sample was last learnt
        self.thread = None  # the learning thread, once started
        self._wake, self._stopping = threading.Event(), threading.Event()

    # -- the executor's thread ----------------------------------------------------------------------------------
    def put(self, batch, refused=()):
        """Take ``batch``, ``[(receipt time, kind, message)]`` in receipt order, into the inbox, and count
        ``refused``, ``[kind]`` of messages too large to read; beyond ``max_inbox`` the oldest are shed."""
        with self._lock:
            for kind in refused:
                self.received[kind] += 1
                self.refused_at_intake["oversized_message"] += 1
                self.oversized_observations += kind == "observations"
            for received, kind, msg in batch:
                self.received[kind] += 1
                self._inbox.append((kind, msg, received))
            while len(self._inbox) > self.settings.max_inbox:
                self.shed[f"{self._inbox.popleft()[0]}_messages"] += 1
        if batch:
            self._wake.set()

    def intake_counts(self):
        """A copy of ``refused_at_intake`` (the executor's thread writes it)."""
        with self._lock:
            return Counter(self.refused_at_intake)

    def intake_snapshot(self):
        """``(received, shed, inbox)``: copies of the counts and the number of messages in the inbox, read at one
        instant (the executor's thread puts meanwhile). Under the lock the learning thread works under, every
        message received is then in the inbox, shed, or taken in (decided, waiting in the pairer, or pending)."""
        with self._lock:
            return Counter(self.received), Counter(self.shed), len(self._inbox)

    # -- the learning thread ------------------------------------------------------------------------------------
    def start(self, lock, on_failure, after_step=lambda: None):
        """Start the learning thread: take the inbox in and :meth:`work` on it under ``lock``, then ``after_step()``
        (outside the lock), again and again; with no sample waiting, first wait for :meth:`put` or ``update_period``
        (the pairer's grace runs out by the clock). An unexpected error ends the thread and is handed to
        ``on_failure(error)``: scheme_node raises it in its executor, failing loudly rather than living on without
        learning."""
        self._stopping.clear()
        self.thread = threading.Thread(target=self._learn_forever, args=(lock, on_failure, after_step),
                                       name="learning", daemon=True)
        self.thread.start()

    def stop(self):
        """Stop the learning thread after its current step and wait for it (nothing to do if it never started)."""
        self._stopping.set()
        self._wake.set()
        if self.thread is not None:
            self.thread.join()

    def _learn_forever(self, lock, on_failure, after_step):
        try:
            while not self._stopping.is_set():
                if not self.pending:
                    self._wake.wait(self.settings.update_period)
                    self._wake.clear()
                with lock:  # taken under it: a diagnostics message (under it too) sees each message once
                    self.work(self.take_inbox())
                after_step()
        except Exception as error:  # any error: handed over, never lost with the thread
            on_failure(error)

    def stalled_for(self):
        """Seconds over which commands kept arriving with no sample learnt: from the first command taken in since the
        last learnt sample to the latest (0.0 when none waits). One command after a quiet spell is not a stall; a
        dead camera, or commands that cannot be learnt, are."""
        return 0.0 if self._unlearnt is None else self._unlearnt[1] - self._unlearnt[0]

    def take_inbox(self):
        """Every message put since the last call, oldest first."""
        with self._lock:
            inbox, self._inbox = self._inbox, deque()
        return inbox

    def work(self, inbox):
        """Stamp policy and pairing for ``inbox``, then learn the oldest waiting sample that is not too old."""
        self._take_in(inbox, self.clock())
        while self.pending:
            received, sample = self.pending.popleft()
            age = self.clock() - received
            if age <= self.settings.max_sample_age:
                self.lag.append(age)  # how far learning is behind its input (camera rate: it must not grow)
                if self._learn(*sample):
                    self._unlearnt = None  # no stall: a sample was learnt
                return
            self.shed["stale_samples"] += 1

    def progress(self):
        """Observation messages decided so far: taken in, shed from the inbox or refused unread, less those the
        pairer holds and those whose samples wait (one sample per observation message). bag_replay's rate 0 keeps
        its messages in flight within this, so a replay waits for learning, not only for intake."""
        with self._lock:
            oversized, shed = self.oversized_observations, self.shed["observations_messages"]
        return self.n_observation_messages + shed + oversized - self.pairer.waiting - len(self.pending)

    def _take_in(self, inbox, now):
        if any(kind == "command" for kind, _, _ in inbox):  # observations alone (the arm standing): nothing to learn
            self._unlearnt = (now if self._unlearnt is None else self._unlearnt[0], now)
        for kind, msg, received in inbox:
            if not self._stamp_acceptable(msg, received, now):
                continue
            samples, rejections = feed_message(self.pairer, kind, msg, self.settings.joint_names,
                                               self.settings.frame_id, self.settings.message_limits)
            self.pending.extend((received, sample) for sample in samples)  # a sample is as old as its message
            for code, detail in rejections:
                self._reject(code, detail)
        self.n_observation_messages += sum(item[0] == "observations" for item in inbox)
        self.pending.extend((now, sample) for sample in self.pairer.flush(now))
        while len(self.pending) > self.settings.max_pending_samples:
            self.pending.popleft()
            self.shed["samples"] += 1

    def _stamp_acceptable(self, msg, received, now):
        """Zero stamps per ``unstamped_policy``; stamps beyond ``stamp_tolerance`` ahead of the clock refused (one
        such stamp would otherwise put every later message out of order)."""
        stamp = msg.header.stamp
        if stamp.sec == 0 and stamp.nanosec == 0:
            if self.settings.unstamped_policy == "reject":
                self._reject("unstamped", "zero stamp (unstamped_policy: reject)")
                return False
            msg.header.stamp = conversions.stamp_from_seconds(received)
            self.restamped["unstamped"] += 1
            return True
        ahead = conversions.seconds_from_stamp(stamp) - now
        if ahead > self.settings.stamp_tolerance:
            self._reject("future_stamp", f"stamped {ahead:.3g} s ahead of the node clock (stamp_tolerance "
                                         f"{self.settings.stamp_tolerance} s)")
            return False
        return True
