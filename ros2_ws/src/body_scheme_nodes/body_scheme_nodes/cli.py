"""body-scheme: what a user would do with ros2 topic, ros2 service and ros2 param, with rclpy only.

The set-up from PyPI has no ros2cli (docs/ros-from-pypi.md); this command is installed with the workspace
(``ros2 run body_scheme_nodes body-scheme ...``, ``body-scheme ...`` in the activated venv, or
``python -m body_scheme_nodes.cli ...``)::

    body-scheme status                     # /diagnostics, readable: one line per status, the values indented
    body-scheme events                     # scheme_node's latest decisions, then follow (Ctrl-C ends; --count N, --new)
    body-scheme save [NAME]                # scheme_node's ~/save, ~/load (a name inside its state_directory;
    body-scheme load [NAME]                #   none: its checkpoint_path) and ~/reset
    body-scheme reset
    body-scheme get-urdf [--out FILE]      # the learned body scheme as URDF
    body-scheme pause | resume | stop      # babble_node's services
    body-scheme params NODE [NAME [VALUE]] # list, get or set (VALUE is YAML, as for ros2 param set)

Exit codes: 0 done; 1 the node answered and refused (its reason on stderr); 2 the node could not be reached, or did
not answer, in ``--timeout`` seconds (or the command line was wrong); 130 cut short by Ctrl-C (``events``, once it
follows, ends so: 0).
Node names may be given with or without the leading slash. Message formatting is in pure functions, tested without DDS.
"""

from __future__ import annotations

import argparse
import array
import math
import pathlib
import signal
import sys

import yaml

__all__ = ["main", "format_status", "format_event", "parse_value"]

LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
DONE, REFUSED, UNREACHABLE, INTERRUPTED = 0, 1, 2, 130  # 130: cut short by Ctrl-C, as a shell reports it
BAD_COMMAND_LINE = UNREACHABLE


# -- formatting (no DDS) -------------------------------------------------------------------------------------------
def format_status(status, values=True):
    """Lines for one ``diagnostic_msgs/DiagnosticStatus``: ``LEVEL name: message`` and, with ``values``, one
    indented ``key: value`` line per value."""
    level = LEVELS.get(status.level if isinstance(status.level, int) else ord(status.level), str(status.level))
    lines = [f"{level:5s} {status.name}: {status.message}"]
    if values:
        lines += [f"      {kv.key}: {kv.value}" for kv in status.values]
    return lines


def format_event(event):
    """One line for a ``body_scheme_msgs/SchemeEvent``: step, kind, the edge and its model, errors, the reason."""
    parts = [f"step {event.step}", event.kind]
    if event.parent_id >= 0 and event.child_id >= 0:
        parts.append(f"{event.parent_id}->{event.child_id}" + (f" ({event.model})" if event.model else ""))
    if math.isfinite(event.trans_error):
        parts.append(f"error {1e3 * event.trans_error:.1f} mm")
    if math.isfinite(event.rot_error):
        parts.append(f"{math.degrees(event.rot_error):.1f} deg")
    return " ".join(parts) + (f": {event.reason}" if event.reason else "")


def parse_value(text):
    """A parameter value from the command line, as ``ros2 param set`` reads it: YAML (``0.5``, ``true``, ``[1, 2]``,
    ``abc``), and the text itself as a string when no ROS parameter type holds the YAML (``""``, ``null``, ``{a:
    1}``, ``[1, 2.5]``: write ``[1.0, 2.5]`` for a list of doubles)."""
    from rclpy.parameter import Parameter

    try:
        value = yaml.safe_load(text)
        Parameter("value", value=value)
    except (yaml.YAMLError, TypeError):
        return text
    return text if value is None else value


def format_parameter_value(value):
    """A parameter value for printing (``rclpy.parameter.parameter_value_to_python``'s result)."""
    if isinstance(value, (list, tuple, array.array)):
        return "[" + ", ".join(str(v) for v in value) + "]"
    return str(value)


def full_name(name):
    """A node's full name as the graph spells it: ``scheme_node`` is ``/scheme_node``."""
    return name if name.startswith("/") else "/" + name


def events_topic(node_name):
    """scheme_node's events topic: ``body_scheme/events`` in the namespace of the node (its full name)."""
    return node_name.rpartition("/")[0] + "/body_scheme/events"


class Unreachable(Exception):
    """The node could not be reached, or did not answer, within ``--timeout`` (exit code 2)."""


# -- over DDS ------------------------------------------------------------------------------------------------------
class Session:
    """An rclpy context and node for one command; ``wait(future)`` spins until the future is done or the timeout."""

    def __init__(self, timeout):
        import rclpy  # imported here so that ``--help`` and the formatting need no ROS
        from rclpy.signals import SignalHandlerOptions

        self.rclpy, self.timeout = rclpy, timeout
        # Ctrl-C is Python's KeyboardInterrupt (main's exit code), not rclpy's shutdown of the context under a wait;
        # also when started with SIGINT ignored (a job of a non-interactive shell, as CI runs the tests), as rclpy's
        # own handler would have taken it.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("body_scheme_cli", use_global_arguments=False, start_parameter_services=False,
                                      enable_rosout=False)

    def close(self):
        self.node.destroy_node()
        self.rclpy.try_shutdown()

    def wait(self, future, name):
        """The future's result; Unreachable if ``name`` did not answer within the timeout."""
        if not self.spin_until(future.done, self.timeout):
            raise Unreachable(f"{name} found, but it did not answer within {self.timeout:g} s (is the node busy?)")
        return future.result()

    def call(self, srv_type, name, request=None):
        """The response of service ``name``; Unreachable if it is not there or does not answer in time."""
        client = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=self.timeout):
            raise Unreachable(f"no {name} service within {self.timeout:g} s: is the node running, in this "
                              "ROS_DOMAIN_ID?")
        return self.wait(client.call_async(request if request is not None else srv_type.Request()), name)

    def spin_until(self, predicate, timeout):
        from time import monotonic

        deadline = monotonic() + timeout if timeout is not None else math.inf
        while not predicate() and monotonic() < deadline:
            self.rclpy.spin_once(self.node, timeout_sec=0.05)
        return predicate()


def _answer(response, out):
    """Print a service's answer; the exit code."""
    if response.success:
        print(response.message, file=out)
        return DONE
    print(response.message, file=sys.stderr)
    return REFUSED


def cmd_status(session, args):
    """Wait for /diagnostics; print the latest status of each name (of ``--node`` only, when given)."""
    from diagnostic_msgs.msg import DiagnosticArray

    statuses, first = {}, []

    def on_message(msg):
        for status in msg.status:
            if args.node is None or status.name.startswith(f"{args.node}:"):
                statuses[status.name] = status
        if statuses and not first:
            first.append(True)

    session.node.create_subscription(DiagnosticArray, "/diagnostics", on_message, 10)
    if not session.spin_until(lambda: bool(first), args.timeout):
        whose = f" from {args.node}" if args.node else ""
        raise Unreachable(f"no diagnostics{whose} within {args.timeout:g} s: is the node running, in this "
                          "ROS_DOMAIN_ID?")
    # Our nodes publish once a second: one more period collects the other nodes' (and the other statuses') arrays.
    session.spin_until(lambda: False, args.settle)
    for name in sorted(statuses):
        print("\n".join(format_status(statuses[name], values=not args.brief)))
    return DONE


def cmd_events(session, args):
    """Print scheme_node's latest events (up to 100 kept), then each as it comes, until ``--count`` events or Ctrl-C;
    with ``--new`` only those that come."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from body_scheme_msgs.msg import SchemeEvent

    from .qos import RECENT_EVENTS

    seen = []

    def on_event(msg):
        seen.append(msg)
        print(format_event(msg), flush=True)

    topic = events_topic(args.node)
    if not session.spin_until(lambda: session.node.count_publishers(topic) > 0, args.timeout):
        raise Unreachable(f"no publisher of {topic} within {args.timeout:g} s: is scheme_node running, in this "
                          "ROS_DOMAIN_ID?")
    offered = [info.qos_profile.durability for info in session.node.get_publishers_info_by_topic(topic)]
    if args.new or any(d != DurabilityPolicy.TRANSIENT_LOCAL for d in offered):
        # Only what comes: asked for, or a publisher keeps no history (a bag played back, an older scheme_node),
        # which a transient local subscription would not be matched with.
        qos = QoSProfile(depth=RECENT_EVENTS.depth, reliability=ReliabilityPolicy.RELIABLE)
    else:
        qos = RECENT_EVENTS  # the latest events first
    session.node.create_subscription(SchemeEvent, topic, on_event, qos)
    print(f"following {topic} (Ctrl-C ends)", file=sys.stderr, flush=True)
    args.following = True  # from here Ctrl-C ends it as intended (exit 0)
    session.spin_until(lambda: args.count is not None and len(seen) >= args.count, None)
    return DONE


def cmd_state(session, args):
    """save / load (StatePath) and reset (Trigger) of scheme_node."""
    from std_srvs.srv import Trigger

    from body_scheme_msgs.srv import StatePath

    name = f"{args.node}/{args.command}"
    if args.command == "reset":
        return _answer(session.call(Trigger, name), sys.stdout)
    return _answer(session.call(StatePath, name, StatePath.Request(path=args.name or "")), sys.stdout)


def cmd_get_urdf(session, args):
    """The learned URDF to stdout or ``--out``."""
    from body_scheme_msgs.srv import GetRobotDescription

    response = session.call(GetRobotDescription, f"{args.node}/get_urdf")
    if not response.success:
        return _answer(response, sys.stdout)
    if args.out is None:
        print(response.urdf)
    else:
        pathlib.Path(args.out).write_text(response.urdf, encoding="utf-8")
    print(response.message + (f"; written to {args.out}" if args.out else ""), file=sys.stderr)
    return DONE


def cmd_babble(session, args):
    """pause / resume / stop of babble_node (Trigger)."""
    from std_srvs.srv import Trigger

    return _answer(session.call(Trigger, f"{args.node}/{args.command}"), sys.stdout)


def cmd_params(session, args):
    """List a node's parameters with their values, get one, or set one."""
    from rclpy.parameter import Parameter, parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    target = args.target
    client = AsyncParameterClient(session.node, target)
    if not client.wait_for_services(timeout_sec=args.timeout):
        raise Unreachable(f"no parameter services of {target} within {args.timeout:g} s: is the node running, in "
                          "this ROS_DOMAIN_ID?")
    if args.value is not None:
        parameter = Parameter(args.name, value=args.value)
        result = session.wait(client.set_parameters([parameter]), f"{target}/set_parameters").results[0]
        if result.successful:
            print(f"set {args.name}")
            return DONE
        print(f"{args.name} not set: {result.reason}", file=sys.stderr)
        return REFUSED
    if args.name is not None:
        names = [args.name]
    else:
        names = sorted(session.wait(client.list_parameters(), f"{target}/list_parameters").result.names)
    response = session.wait(client.get_parameters(names), f"{target}/get_parameters")
    if args.name is not None and (not response.values or response.values[0].type == 0):  # PARAMETER_NOT_SET
        print(f"{target} has no parameter {args.name}", file=sys.stderr)
        return REFUSED
    for name, value in zip(names, response.values, strict=True):
        print(f"{name}: {format_parameter_value(parameter_value_to_python(value))}")
    return DONE


def parser():
    p = argparse.ArgumentParser(prog="body-scheme", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for a node (default 10)")

    def add(name, function, help_text, node="/scheme_node"):
        command = sub.add_parser(name, help=help_text, description=help_text, parents=[common])
        command.set_defaults(function=function)
        if node is not None:
            command.add_argument("--node", default=node, type=full_name,
                                 help=f"the node's full name (default {node})")
        return command

    status = add("status", cmd_status, "print /diagnostics readably (all nodes unless --node)", node=None)
    status.add_argument("--node", default=None, type=full_name, help="only this node's statuses, e.g. /scheme_node")
    status.add_argument("--brief", action="store_true", help="one line per status, no values")
    status.add_argument("--settle", type=float, default=1.5, help="seconds to collect after the first array")
    events = add("events", cmd_events, "scheme_node's latest events (up to 100 kept), then follow them")
    events.add_argument("--count", type=int, default=None, help="exit after this many events (the kept ones count)")
    events.add_argument("--new", action="store_true", help="only events from now on, not the kept ones")
    for name, help_text in (("save", "save the learner's state (scheme_node ~/save)"),
                            ("load", "load a saved state (scheme_node ~/load)")):
        add(name, cmd_state, help_text).add_argument(
            "name", nargs="?", default="", help="a file name inside state_directory; none: checkpoint_path")
    add("reset", cmd_state, "learn from scratch (scheme_node ~/reset)")
    add("get-urdf", cmd_get_urdf, "the learned body scheme as URDF").add_argument(
        "--out", default=None, help="write it to this file (default: stdout)")
    for name in ("pause", "resume", "stop"):
        add(name, cmd_babble, f"{name} the babbling (babble_node ~/{name})", node="/babble_node")
    params = add("params", cmd_params, "list, get or set a node's parameters", node=None)
    params.add_argument("target", metavar="NODE", type=full_name, help="the node's full name, e.g. /scheme_node")
    params.add_argument("name", nargs="?", default=None, help="a parameter (none: list all with their values)")
    params.add_argument("value", nargs="?", default=None, type=parse_value, help="set it to this value (YAML)")
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.timeout <= 0:
        print("--timeout must be positive", file=sys.stderr)
        return BAD_COMMAND_LINE
    from rclpy.executors import ExternalShutdownException

    session = None
    try:
        session = Session(args.timeout)
        return args.function(session, args)
    except Unreachable as error:
        print(error, file=sys.stderr)
        return UNREACHABLE
    except (KeyboardInterrupt, ExternalShutdownException):  # Ctrl-C is how ``events`` ends; others were cut short
        return DONE if getattr(args, "following", False) else INTERRUPTED
    finally:
        if session is not None:
            session.close()


if __name__ == "__main__":
    raise SystemExit(main())
