"""Driving an arm the way ros2_control expects: a ``JointTrajectory`` to a ``JointTrajectoryController``, checked
first, and watched on ``/joint_states`` until it settles. Shared by babble_node and control_node (``execute``).

The arm may be a real one or sim_node (which accepts the same topic). What is checked before a goal is sent
(:meth:`ArmDriver.refusal`): the joint limits shrunk by a margin and the workspace box
(:class:`~body_scheme_core.motion.SafetyLimits`), and self-collision and ground contact along the straight joint-space
path from the arm's position (:class:`~body_scheme_sim.babbling.CollisionScreen`, pybullet from the URDF). Refused
goals are counted by reason and never sent.
"""

from __future__ import annotations

import threading
from collections import Counter

import numpy as np
from builtin_interfaces.msg import Duration
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from body_scheme_core.errors import BodySchemeError, InvalidInputError
from body_scheme_core.motion import SafetyLimits, SettleDetector, trajectory_duration

from . import conversions

__all__ = ["ArmDriver", "declare_driver_parameters", "driver_from_parameters"]


def declare_driver_parameters(node):
    """Declare the driver's parameters on ``node`` (see config/babble_node.yaml for their meaning); returns their
    values, for :func:`driver_from_parameters`."""
    from .sim_node import declare_list_parameter

    p = node.declare_parameter
    values = {name: p(name, default).value for name, default in (
        ("robot", "powercube_6dof"), ("controller", "joint_trajectory_controller"),
        ("joint_states_topic", "/joint_states"), ("max_velocity", 1.0), ("max_acceleration", 2.0),
        ("limit_margin", 0.05), ("collision_check", True), ("settle_tolerance", 0.01), ("settle_still", 0.002),
        ("settle_window", 0.1), ("settle_timeout", 2.0))}
    values["package_path"] = declare_list_parameter(node, "package_path", str)
    values["workspace"] = declare_list_parameter(node, "workspace", float)
    return values


def driver_from_parameters(node, values):
    """An :class:`ArmDriver` for ``node`` from :func:`declare_driver_parameters`' values."""
    from body_scheme_sim.babbling import CollisionScreen
    from body_scheme_sim.robots import load_robot

    workspace = values["workspace"]
    if workspace and len(workspace) != 6:
        raise InvalidInputError(f"workspace takes [x_min, y_min, z_min, x_max, y_max, z_max] (m, root frame), got "
                                f"{workspace}")
    settle = SettleDetector(values["settle_tolerance"], values["settle_still"], values["settle_window"],
                            values["settle_timeout"])
    tree = load_robot(values["robot"], markers=())

    def points(a):  # every link origin, in the root link's frame
        return np.array([T[:3, 3] for T in tree.link_poses(a).values()])

    safety = SafetyLimits(tree.action_lower, tree.action_upper, values["limit_margin"],
                          np.reshape(workspace, (2, 3)) if workspace else None, points if workspace else None)
    screen = CollisionScreen(values["robot"], package_path=values["package_path"]) \
        if values["collision_check"] else None
    return ArmDriver(node, tree.action_joint_names, safety, screen, values["max_velocity"],
                     values["max_acceleration"], settle, values["controller"], values["joint_states_topic"])


class ArmDriver:
    """Sends checked goals as ``JointTrajectory`` messages and tells when the arm has settled.

    Parameters
    ----------
    node : rclpy.node.Node
    joint_names : sequence of str
        Joint per action, in action order.
    safety : SafetyLimits
    screen : CollisionScreen or None
    max_velocity, max_acceleration : float
        Per-joint limits of the moves (rad/s, rad/s^2; :func:`~body_scheme_core.motion.trajectory_duration`).
    settle : SettleDetector
    controller : str
        The ``JointTrajectoryController``'s name: goals go to ``<controller>/joint_trajectory``.
    joint_states_topic : str

    Attributes
    ----------
    counts : Counter
        ``sent``, ``settled``, ``settle_timeouts``, ``halted``, ``refused.<reason>`` (joint limit, workspace,
        collision), ``joint_states`` received and ``joint_states_rejected``.
    """

    def __init__(self, node, joint_names, safety, screen, max_velocity, max_acceleration, settle, controller,
                 joint_states_topic):
        self.node = node
        self.joint_names = tuple(joint_names)
        self.safety, self.screen, self.settle = safety, screen, settle
        self.max_velocity, self.max_acceleration = max_velocity, max_acceleration
        trajectory_duration(np.zeros(1), np.ones(1), max_velocity, max_acceleration)  # validates the limits now
        self.counts = Counter()
        self.goal = None  # the goal being moved to, until it settled
        self._positions = None  # (time s, positions) of the last joint state
        self._lock = threading.Lock()
        self.pub_trajectory = node.create_publisher(JointTrajectory, f"{controller}/joint_trajectory", 10)
        node.create_subscription(JointState, joint_states_topic, self._on_joint_states, 50)

    def _now(self):
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _on_joint_states(self, msg):
        try:
            _, positions = conversions.actions_from_joint_state(msg, self.joint_names)
        except BodySchemeError:
            self.counts["joint_states_rejected"] += 1
            return
        with self._lock:
            self._positions = (self._now(), positions)
            self.counts["joint_states"] += 1

    @property
    def positions(self):
        """The arm's last reported joint positions (action order), or None before the first joint state."""
        with self._lock:
            return None if self._positions is None else self._positions[1].copy()

    def refusal(self, goal, start=None):
        """Why ``goal`` may not be sent from ``start`` (default: the arm's position), or None."""
        why = self.safety.violation(goal)
        if why is None and self.screen is not None:
            start = self.positions if start is None else start
            if self.screen.collides(start, goal):
                why = "collision"
        return why

    def send(self, goal):
        """Check ``goal`` and send it as a one-point trajectory; returns None, or the refusal (counted)."""
        goal = np.asarray(goal, dtype=float)
        start = self.positions
        if start is None:
            return "no joint state yet"
        why = self.refusal(goal, start)
        if why is not None:
            self.counts[f"refused.{why}"] += 1
            return why
        duration = trajectory_duration(start, goal, self.max_velocity, self.max_acceleration)
        seconds = int(duration)
        point = JointTrajectoryPoint(positions=[float(v) for v in goal], velocities=[0.0] * len(goal),
                                     time_from_start=Duration(sec=seconds, nanosec=int((duration - seconds) * 1e9)))
        msg = JointTrajectory(joint_names=list(self.joint_names), points=[point])  # stamp 0: start at once
        self.goal = goal
        self.settle.start(goal, self._now() + duration)
        self.pub_trajectory.publish(msg)
        self.counts["sent"] += 1
        return None

    def settled(self):
        """The goal being moved to once the arm has come to rest at it (or timed out: counted), else None; a
        settled goal is done."""
        if self.goal is None:
            return None
        with self._lock:
            reading = self._positions
        now = self._now()
        done = self.settle.update(reading[1] if reading is not None else np.full(len(self.joint_names), np.nan),
                                  now)
        if not done:
            return None
        self.counts["settle_timeouts" if self.settle.timed_out else "settled"] += 1
        goal, self.goal = self.goal, None
        return goal

    def halt(self):
        """Stop the arm where it is: an empty trajectory (a ``JointTrajectoryController`` then holds its position)."""
        self.pub_trajectory.publish(JointTrajectory(joint_names=list(self.joint_names)))
        self.goal = None
        self.counts["halted"] += 1

    def close(self):
        if self.screen is not None:
            self.screen.close()
