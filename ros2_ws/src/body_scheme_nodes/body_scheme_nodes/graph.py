"""Running installed node executables as processes: what ``ros2 run`` and launch files do on a full ROS install.

The PyPI route has no ``ros2cli`` and no ``launch``, so the live demo and the system tests start the very files
``ros2 run <package> <executable>`` would execute (``<install>/<package>/lib/<package>/<executable>``) with a
generated parameter file, and stop them with SIGINT (SIGKILL if they hang). The nodes run in sessions of their own
(a Ctrl-C at the terminal reaches only the program that started them); while a :func:`monitor_node` is open, SIGINT
and SIGTERM raise ``KeyboardInterrupt`` in that program, so its ``finally`` blocks stop them: no node outlives it to
babble on in the domain.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pathlib
import signal
import subprocess
import threading
import time

import rclpy
import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_prefix
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

__all__ = ["NodeProcess", "executable", "monitor_node", "spin_until"]


def executable(package, name):
    """Path of an installed node executable, as ``ros2 run <package> <name>`` would find it."""
    try:
        prefix = pathlib.Path(get_package_prefix(package))
    except PackageNotFoundError as error:
        raise FileNotFoundError(f"package {package!r} is not installed or not sourced (make build; source "
                                f"ros2_ws/install/local_setup.bash)") from error
    path = prefix / "lib" / package / name
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist: is {name!r} a console script of {package!r}?")
    return path


class NodeProcess:
    """One node started as its own OS process, its output captured to ``<log_dir>/<name>.log``.

    Parameters
    ----------
    package, name : str
        Package and executable.
    parameters : dict
        ROS parameters, written to ``<log_dir>/<name>.params.yaml`` (nested dicts become dotted names).
    log_dir : path-like
    env : dict, optional
        Environment of the process (default: this one's).
    ros_args : sequence of str
        More ``--ros-args`` arguments after the parameter file (remappings, more parameter files).
    """

    def __init__(self, package, name, parameters, log_dir, env=None, ros_args=()):
        log_dir = pathlib.Path(log_dir)
        log_dir.mkdir(parents=True, exist_ok=True)
        self.name = name
        tag = "".join(c if c.isalnum() else "_" for c in " ".join(ros_args)).strip("_")
        if len(tag) > 64:  # a file name has at most 255 bytes: long arguments are named by their digest
            tag = f"{tag[:40]}_{hashlib.sha1(tag.encode()).hexdigest()[:12]}"
        self.log_path = log_dir / f"{name}{'.' + tag if tag else ''}.log"
        params_path = log_dir / f"{name}{'.' + tag if tag else ''}.params.yaml"
        params_path.write_text(yaml.safe_dump({"/**": {"ros__parameters": parameters}}))
        self._log = open(self.log_path, "w")
        self.process = subprocess.Popen(
            [str(executable(package, name)), "--ros-args", "--params-file", str(params_path), *ros_args],
            stdout=self._log, stderr=subprocess.STDOUT, env=dict(os.environ if env is None else env,
                                                                  PYTHONUNBUFFERED="1"),
            start_new_session=True)

    def running(self):
        """Whether the process is still alive."""
        return self.process.poll() is None

    def output(self):
        """Everything the process printed so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def kill(self, sig=signal.SIGKILL):
        """Send a signal to the node's process group (``kill -9`` by default) and wait for it."""
        if self.running():
            os.killpg(self.process.pid, sig)
        self.process.wait(timeout=10)

    def stop(self):
        """SIGINT (a clean shutdown), then SIGKILL after 10 s; returns the exit code."""
        if self.running():
            os.killpg(self.process.pid, signal.SIGINT)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill()
        if not self._log.closed:
            self._log.close()
        return self.process.returncode


@contextlib.contextmanager
def monitor_node(name, domain):
    """``(node, executor)``: an rclpy node of this process in a context of its own on ROS domain ``domain``, with a
    single-threaded executor; both are shut down on exit. The demo, the benchmarks and the fuzz watch the graph
    through one.

    While it is open, the first SIGINT or SIGTERM raises ``KeyboardInterrupt`` (in the main thread; rclpy's own
    handler would shut the context down under a wait, and the program would go on, or SIGTERM would end it at once
    with its nodes still running)."""
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        with _interrupted_by_signals():
            yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@contextlib.contextmanager
def _interrupted_by_signals():
    """The first SIGINT or SIGTERM inside the block raises ``KeyboardInterrupt`` (named after the signal); later
    ones are ignored, so that the ``finally`` blocks it unwinds stop every node (a second Ctrl-C would cut them
    short). Also when the signal was ignored (a job of a non-interactive shell). The previous Python handlers after
    the block (the default where none was set from Python); nothing outside the main thread, where Python cannot set
    handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []

    def interrupt(signum, frame):
        if not received:
            received.append(signum)
            raise KeyboardInterrupt(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)


def spin_until(executor, predicate, timeout, during=None, progress=None, step=0.02):
    """Spin ``executor`` until ``predicate()`` holds, at most ``timeout`` s; returns the predicate's last value.

    ``during()`` is called before each spin (to publish the next sample, or check the nodes still run). With
    ``progress``, ``timeout`` is how long ``progress()`` may keep one value: work that advances is waited for however
    slow the machine is."""
    deadline = time.monotonic() + timeout
    last = progress() if progress is not None else None
    while time.monotonic() < deadline:
        if during is not None:
            during()
        executor.spin_once(timeout_sec=step)
        if predicate():
            return True
        if progress is not None and (now := progress()) != last:
            last, deadline = now, time.monotonic() + timeout
    return bool(predicate())
