"""Fixtures of the nodes' in-process tests with the real rclpy."""

import os
import random
import time

import pytest
import rclpy


@pytest.fixture
def context(monkeypatch):
    """An rclpy context on a domain of this test alone (localhost only), shut down after the test."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=random.Random(os.getpid() + time.monotonic_ns()).randint(101, 200))
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)
