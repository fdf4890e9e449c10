"""Subscriptions read in batches: high message rates without one executor round trip per message.

rclpy's executor dispatches a subscription's messages one callback at a time, and each dispatch (a wait set, a task,
the callback) costs a few hundred microseconds of Python. At 2,000 messages/s that is the whole core, holding the
GIL the learner needs. A :class:`BatchIntake` subscription is never waited on by the executor; a timer calls
:meth:`BatchIntake.take` and gets every message waiting in the DDS queue in one go (rclpy's own
``wait_for_message`` takes messages the same way).

Messages beyond the subscription's depth are overwritten in DDS before anyone sees them: the depth must cover the
longest time between two ``take`` calls at the highest message rate (1 s of 1 kHz for the default 1000).
"""

from __future__ import annotations

import time

from rclpy.callback_groups import CallbackGroup

__all__ = ["BatchIntake"]


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
    depth : int
        Queue depth (reliable, keep last).
    """

    def __init__(self, node, msg_type, topic, depth):
        self.subscription = node.create_subscription(msg_type, topic, self._not_dispatched, depth,
                                                     callback_group=_NeverDispatched())

    @staticmethod
    def _not_dispatched(msg):
        raise AssertionError("a BatchIntake subscription is read by take(), never by the executor")

    def take(self):
        """Every message waiting in the queue, oldest first: a list of ``(message, received)``, where ``received`` is
        when DDS received it (system clock, s), so a message's wait in the queue counts towards its age."""
        subscription, messages = self.subscription, []
        with subscription.handle:
            while (taken := subscription.handle.take_message(subscription.msg_type, subscription.raw)) is not None:
                msg, info = taken
                messages.append((msg, info["received_timestamp"] * 1e-9 if info.get("received_timestamp") else
                                 time.time()))
        return messages
