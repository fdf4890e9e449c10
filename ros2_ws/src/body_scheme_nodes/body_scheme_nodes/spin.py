"""The ``main`` of every node: initialise rclpy, spin, shut down cleanly (ros2/examples' pattern, written once)."""

from __future__ import annotations

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor

from body_scheme_core.errors import BodySchemeError

__all__ = ["run_node"]


def run_node(node_class, args=None, threads=2):
    """Create ``node_class()`` and spin it until Ctrl-C or shutdown; returns the process exit code.

    Parameters
    ----------
    node_class : type
        A ``rclpy.node.Node`` subclass whose constructor takes no arguments.
    args : list of str, optional
        Command-line arguments for ``rclpy.init`` (``--ros-args ...``).
    threads : int
        Executor threads: 2 lets subscriptions buffer while a timer computes (callback groups); 1 for nodes
        that only publish.

    Returns
    -------
    code : int
        0 after a normal shutdown, 1 if the node refused its parameters (a ``BodySchemeError`` at start-up, logged
        with the reason).
    """
    rclpy.init(args=args)
    node = None
    try:
        node = node_class()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BodySchemeError, ParameterException) as error:  # a refused parameter: one line, no traceback
        rclpy.logging.get_logger(node_class.__name__).fatal(f"{type(error).__name__}: {error}")
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
