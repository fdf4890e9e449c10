"""The ``main`` of every node: initialise rclpy, spin, shut down cleanly (ros2/examples' pattern, written once)."""

from __future__ import annotations

import rclpy
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.threads import limit_math_threads

__all__ = ["run_node"]


def run_node(node_class, args=None, threads=2):
    """Create ``node_class()`` and spin it until Ctrl-C or shutdown, with one math-library thread
    (:func:`~body_scheme_core.threads.limit_math_threads`); returns the process exit code.

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
        0 after a normal shutdown, 1 if the node could not start: arguments rclpy cannot read (a broken parameter
        file), or parameters the node refused (a ``BodySchemeError`` at start-up). Either is one FATAL line with the
        reason, no traceback.
    """
    node = None
    try:
        limit_math_threads()  # one BLAS thread per process unless BODY_SCHEME_MATH_THREADS says otherwise
    except BodySchemeError as error:
        rclpy.logging.get_logger(node_class.__name__).fatal(f"cannot start: {error}")
        return 1
    try:
        rclpy.init(args=args)
    except rclpy_implementation.RCLError as error:  # e.g. a --params-file that is not YAML
        reason = " ".join(str(error).split())
        rclpy.logging.get_logger(node_class.__name__).fatal(f"cannot start: {reason}")
        return 1
    try:
        node = node_class()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BodySchemeError, ParameterException, NameValidationException) as error:  # one line, no traceback
        rclpy.logging.get_logger(node_class.__name__).fatal(f"{type(error).__name__}: {error}")
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
