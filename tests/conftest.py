"""Fixtures for system tests: real node processes from the colcon install space, real rclpy, real DDS.

Every test gets its own ROS domain id and localhost-only discovery, so concurrent runs on one machine never see each
other's topics. Node processes are the files ``ros2 run`` would execute: ``install/<pkg>/lib/<pkg>/<executable>``.

And one guard for the whole suite: a run that leaves files in the repository that were not there before (a test that
wrote into the working directory, say) fails, naming them (``git status``; ``out/`` and the build are ignored).
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from workspace import REPO

from body_scheme_nodes import graph
from body_scheme_nodes.graph import NodeProcess


def _repository_status():
    """``git status --porcelain`` of the repository as a set of lines, or None without git or outside a clone."""
    try:
        done = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=all"],
                              capture_output=True, text=True, timeout=120, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return set(done.stdout.splitlines()) if done.returncode == 0 else None


def pytest_sessionstart(session):
    if not hasattr(session.config, "workerinput"):  # the controller of an xdist run, or a plain run
        session.config.stash[_STATUS] = _repository_status()


def pytest_sessionfinish(session, exitstatus):
    before = session.config.stash.get(_STATUS, None)
    after = None if before is None else _repository_status()
    left = sorted((after or set()) - (before or set()))
    if left:
        print("\nthe tests left these changes in the repository (write under tmp_path or out/ instead):\n  "
              + "\n  ".join(left), file=sys.stderr)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


_STATUS = pytest.StashKey()


@pytest.fixture
def domain_id():
    """A ROS domain id of this test alone (localhost-only discovery): random within this pytest-xdist worker's share of
    1-100, so that tests running at once (``pytest -m system -n 2``) never meet."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    share = 100 // max(workers, 1)
    return random.Random(os.getpid() + time.monotonic_ns()).randint(1 + index * share, (index + 1) * share)


@pytest.fixture
def ros_env(domain_id):
    """Environment for node processes: the current one plus this test's domain."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return env


@pytest.fixture
def start_node(ros_env, tmp_path):
    """Start installed node executables; all are stopped (and their logs shown on failure) at teardown."""
    started = []

    def start(package, name, parameters, env_overrides=None, ros_args=()):
        env = dict(ros_env, **(env_overrides or {}))
        process = NodeProcess(package, name, parameters, tmp_path, env=env, ros_args=ros_args)
        started.append(process)
        return process

    yield start
    for process in started:
        process.stop()
        print(f"----- {process.name} output -----\n{process.output()}")


@pytest.fixture
def ros_node(domain_id, monkeypatch):
    """An rclpy node of the test process in this test's domain; rclpy is initialised and shut down around it."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node("system_test", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.executor_for_test = executor
    try:
        yield node
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture
def spin_until(ros_node):
    """``spin_until(predicate, timeout, during=None, step=0.01, progress=None)``: spin the test node until
    ``predicate()`` holds (:func:`body_scheme_nodes.graph.spin_until`, which live_demo waits with too)."""

    def spin(predicate, timeout, during=None, step=0.01, progress=None):
        return graph.spin_until(ros_node.executor_for_test, predicate, timeout, during, progress, step)

    return spin
