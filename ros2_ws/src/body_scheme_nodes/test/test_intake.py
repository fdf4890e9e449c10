"""BatchIntake with the real rclpy: the executor never dispatches it; take() returns every waiting message at once."""

import os
import random
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from body_scheme_nodes.intake import BatchIntake


@pytest.fixture
def node(monkeypatch):
    """A node in an rclpy context on a domain of this test alone (localhost only)."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=random.Random(os.getpid() + time.monotonic_ns()).randint(101, 200))
    node = rclpy.create_node("intake_test", context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def _publish(node, intake, n):
    publisher = node.create_publisher(JointState, "commands", 100)
    deadline = time.monotonic() + 10
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    for k in range(n):
        publisher.publish(JointState(name=["j"], position=[float(k)]))
    return publisher


def test_take_returns_every_waiting_message_oldest_first_with_its_reception_time(node):
    intake = BatchIntake(node, JointState, "commands", 100)
    before = time.time()
    _publish(node, intake, 30)
    messages, deadline = [], time.monotonic() + 10
    while len(messages) < 30 and time.monotonic() < deadline:
        messages += intake.take()
        time.sleep(0.01)
    after = time.time()
    assert [msg.position[0] for msg, _ in messages] == [float(k) for k in range(30)]
    received = [t for _, t in messages]
    assert received == sorted(received) and before <= received[0] and received[-1] <= after
    assert intake.take() == []


def test_the_executor_never_dispatches_a_batch_intake(node):
    """Spinning with messages waiting calls no callback (its callback would raise) and leaves them for take()."""
    intake = BatchIntake(node, JointState, "commands", 100)
    _publish(node, intake, 5)
    time.sleep(0.3)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    for _ in range(20):
        executor.spin_once(timeout_sec=0.01)
    executor.shutdown()
    assert len(intake.take()) == 5


def test_messages_beyond_the_depth_are_lost_oldest_first(node):
    """The depth is the bound documented for queue_depth: a longer backlog keeps the newest messages."""
    intake = BatchIntake(node, JointState, "commands", 10)
    _publish(node, intake, 25)
    time.sleep(0.5)
    assert [msg.position[0] for msg, _ in intake.take()] == [float(k) for k in range(15, 25)]
