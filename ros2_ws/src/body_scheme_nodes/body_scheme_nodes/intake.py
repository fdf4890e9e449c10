"""Subscriptions read in batches: high message rates without one executor round trip per message.

rclpy's executor dispatches a subscription's messages one callback at a time, and each dispatch (a wait set, a task,
the callback) costs a few hundred microseconds of Python. At 2,000 messages/s that is the whole core, holding the
GIL the learner needs. A :class:`BatchIntake` subscription is never waited on by the executor; a timer calls
:meth:`BatchIntake.take` and gets every message waiting in the DDS queue in one go (rclpy's own
``wait_for_message`` takes messages the same way).

Messages beyond the subscription's depth are overwritten in DDS before anyone sees them: the depth must cover the
longest time between two ``take`` calls at the highest message rate (1 s of 1 kHz for the default 1000). Fast DDS
reports no such loss (its message-lost event stays silent for keep-last overwrites, measured), so they are counted
from the publishers' sequence numbers: a gap in one publisher's numbers is that many messages lost (:attr:`lost`).
With several publishers on the topic their numbers interleave and cannot be told apart; then every take that found
the queue full is counted instead (:attr:`full_queue_takes`: something may have been overwritten).

Messages are taken serialized: one larger than ``max_bytes`` is refused before it is deserialized (:attr:`oversized`),
so a 300 MB message costs the node a copy, not a minute of Python objects. :func:`create_sized_subscription` does the
same for a subscription the executor dispatches (a callback per message).

Service requests are taken in batches too (:class:`RequestIntake`) and served in a thread of their own
(:class:`ServiceWorker`): a batch of slow requests (50 ``~/load`` of large files) never holds the executor's thread,
which keeps taking messages in and publishing /diagnostics.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import Counter

from rclpy.callback_groups import CallbackGroup
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

__all__ = ["BatchIntake", "RequestIntake", "ServiceWorker", "create_sized_subscription"]


class _NeverDispatched(CallbackGroup):
    """A callback group whose entities the executor never waits on or calls."""

    def can_execute(self, entity):
        return False

    def beginning_execution(self, entity):
        return False

    def ending_execution(self, entity):
        pass


class BatchIntake:
    """One subscription of ``node`` whose messages are taken in batches by :meth:`take`.

    Parameters
    ----------
    node : rclpy.node.Node
    msg_type : type
    topic : str
    depth : int or QoSProfile
        Queue depth (reliable, keep last), or the whole profile (e.g. transient local for a latched topic).
    max_bytes : int or None
        Largest serialized message taken; a larger one is refused whole (counted in :attr:`oversized`).

    Attributes
    ----------
    lost : int
        Messages DDS overwrote before they were taken (gaps in the publisher's sequence numbers; one publisher).
    full_queue_takes : int
        Takes that found the queue full while several publishers were matched (losses possible, not countable).
    oversized : list of int
        Sizes (bytes) of the refused messages not yet collected by :meth:`take_refused`.
    """

    def __init__(self, node, msg_type, topic, depth, max_bytes=None):
        self.subscription = node.create_subscription(msg_type, topic, self._not_dispatched, depth,
                                                     callback_group=_NeverDispatched())
        self.depth, self.max_bytes = getattr(depth, "depth", depth), max_bytes
        self.lost = self.full_queue_takes = 0
        self.oversized = []
        self._last_sequence = None

    @staticmethod
    def _not_dispatched(msg):
        raise AssertionError("a BatchIntake subscription is read by take(), never by the executor")

    def take(self):
        """Every message waiting in the queue, oldest first: a list of ``(message, received)``, where ``received`` is
        when DDS received it (system clock, s), so a message's wait in the queue counts towards its age."""
        subscription, taken_all = self.subscription, []
        with subscription.handle:
            while (taken := subscription.handle.take_message(subscription.msg_type, True)) is not None:
                taken_all.append(taken)
        if not taken_all:
            return []
        self._count_losses([info.get("publication_sequence_number") for _, info in taken_all])
        messages = []
        for raw, info in taken_all:
            if self.max_bytes is not None and len(raw) > self.max_bytes:
                self.oversized.append(len(raw))
                continue
            messages.append((deserialize_message(raw, subscription.msg_type),
                             info["received_timestamp"] * 1e-9 if info.get("received_timestamp") else time.time()))
        return messages

    def take_refused(self):
        """Sizes of the messages refused as larger than ``max_bytes`` since the last call."""
        refused, self.oversized = self.oversized, []
        return refused

    def _count_losses(self, sequences):
        """Add the gaps in the publisher's sequence numbers to :attr:`lost` (see the module docstring)."""
        if self.subscription.get_publisher_count() > 1:
            self._last_sequence = None
            self.full_queue_takes += len(sequences) >= self.depth
            return
        for sequence in sequences:
            if sequence is None:  # a middleware without sequence numbers
                continue
            if self._last_sequence is not None and sequence > self._last_sequence + 1:
                self.lost += sequence - self._last_sequence - 1
            self._last_sequence = sequence  # lower: a new publisher, numbering from 1 again


class RequestIntake:
    """One service of ``node`` whose requests are taken in batches by :meth:`take` and answered by :meth:`answer`.

    The executor never dispatches them: a timer takes every waiting request at once, so the node decides how many it
    serves and answers the rest at once ("busy") instead of leaving them in a DDS queue that overwrites the oldest
    (rclpy's default service depth is 10: an eleventh concurrent caller would wait forever).

    Parameters
    ----------
    node : rclpy.node.Node
    srv_type : type
    name : str
    depth : int
        Request queue depth (reliable, keep last).
    """

    def __init__(self, node, srv_type, name, depth):
        self.service = node.create_service(srv_type, name, self._not_dispatched,
                                           qos_profile=QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE),
                                           callback_group=_NeverDispatched())

    @staticmethod
    def _not_dispatched(request, response):
        raise AssertionError("a RequestIntake service is read by take(), never by the executor")

    def take(self):
        """Every waiting request, oldest first: a list of ``(request, header)``."""
        service, requests = self.service, []
        with service.handle:
            while True:
                request, header = service.handle.service_take_request(service.srv_type.Request)
                if header is None:
                    return requests
                requests.append((request, header))

    def answer(self, header, response):
        """Send ``response`` to the caller of the request with ``header``."""
        self.service.send_response(response, header)


def create_sized_subscription(node, msg_type, topic, callback, qos, max_bytes, refused, callback_group=None):
    """A subscription of ``node`` whose messages larger than ``max_bytes`` (serialized) are never deserialized:
    ``refused(size)`` is called for each of them, ``callback(msg)`` for the others."""

    def on_serialized(raw):
        if len(raw) > max_bytes:
            refused(len(raw))
            return
        callback(deserialize_message(raw, msg_type))

    return node.create_subscription(msg_type, topic, on_serialized, qos, callback_group=callback_group, raw=True)


class ServiceWorker:
    """Serves the requests of several :class:`RequestIntake` services in a thread of its own.

    :meth:`take` (the executor's thread, every ``update_period``) takes every waiting request; at most
    ``max_waiting`` per service wait for the thread, the others are answered at once with ``busy(name, waiting)``'s
    response. The thread calls ``handler(request, response)`` for each in turn and sends its answer; an exception is
    answered as a failure (``success`` false, the error in ``message``) and logged, never raised.

    Parameters
    ----------
    services : dict of str to (RequestIntake, callable)
    max_waiting : int
    busy : callable
        ``busy(name, waiting) -> str``: the message of a request answered busy.
    log_error : callable
        ``log_error(text)``.

    """

    def __init__(self, services, max_waiting, busy, log_error):
        self.services, self.max_waiting, self.busy, self.log_error = services, max_waiting, busy, log_error
        self._queue = queue.Queue()
        self._lock = threading.Lock()
        self._counts = Counter()
        self._waiting = Counter()
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._serve_forever, name="services", daemon=True)
        self._thread.start()

    def counters(self):
        """``<name>.answered``, ``.failed`` and ``.busy`` so far, and ``<name>.waiting`` now (when any wait)."""
        with self._lock:
            return Counter(self._counts) + Counter({f"{name}.waiting": n for name, n in self._waiting.items()})

    def take(self):
        """Take every waiting request of every service (see the class docstring); the executor's thread."""
        for name, (intake, _) in self.services.items():
            for request, header in intake.take():
                with self._lock:
                    full = self._waiting[name] >= self.max_waiting
                    if not full:
                        self._waiting[name] += 1
                    else:
                        self._counts[f"{name}.busy"] += 1
                if full:
                    response = intake.service.srv_type.Response(success=False,
                                                                message=self.busy(name, self.max_waiting))
                    intake.answer(header, response)
                else:
                    self._queue.put((name, request, header))

    def _serve_forever(self):
        while (item := self._queue.get()) is not None and not self._stopping.is_set():
            name, request, header = item
            intake, handler = self.services[name]
            response, outcome = intake.service.srv_type.Response(), "answered"
            try:
                response = handler(request, response)
            except Exception as error:  # a request never takes the node down; said in the reply
                response.success, response.message = False, f"{name} failed: {type(error).__name__}: {error}"
                self.log_error(f"~/{name} failed: {type(error).__name__}: {error}")
                outcome = "failed"
            try:
                intake.answer(header, response)
            except Exception as error:  # the node is shutting down: nothing to answer to
                self.log_error(f"~/{name}: the answer could not be sent: {error}")
            with self._lock:
                self._waiting[name] -= 1
                self._counts[f"{name}.{outcome}"] += 1

    def stop(self, timeout=5.0):
        """Let the thread finish the request it serves (at most ``timeout`` s) and end; waiting requests are
        dropped (the node is going away)."""
        self._stopping.set()
        self._queue.put(None)
        self._thread.join(timeout)
