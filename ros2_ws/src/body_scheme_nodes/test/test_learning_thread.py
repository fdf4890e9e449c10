"""scheme_node's learning thread with the real rclpy, in-process: it stops with the node, and an unexpected error in
it is raised by the executor (the node fails loudly) instead of leaving a node that no longer learns."""

import os
import random
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor

from body_scheme_nodes.scheme_node import SchemeNode

ARGS = ["--ros-args", "-p", "part_ids:=[1, 2, 3]", "-p", "joint_names:=[j1, j2]"]


@pytest.fixture
def node(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    rclpy.init(args=ARGS, domain_id=random.Random(os.getpid() + time.monotonic_ns()).randint(101, 200))
    node = SchemeNode()
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def test_the_learning_thread_runs_until_the_node_is_destroyed(node):
    assert node.loop.thread.is_alive()
    node.destroy_node()
    assert not node.loop.thread.is_alive()


def test_an_error_in_the_learning_thread_is_raised_by_the_executor(node, monkeypatch):
    def broken(inbox):
        raise ZeroDivisionError("a bug in learning")

    monkeypatch.setattr(node.loop, "work", broken)  # the thread calls it at the latest after update_period
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    with pytest.raises(RuntimeError, match="the learning thread failed") as raised:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    assert isinstance(raised.value.__cause__, ZeroDivisionError)
    executor.shutdown()
