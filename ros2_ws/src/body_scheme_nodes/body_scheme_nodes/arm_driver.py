"""Driving an arm the way ros2_control expects: a ``JointTrajectory`` to a ``JointTrajectoryController``, checked
first, and watched on ``/joint_states`` until it settles. Shared by babble_node and control_node (``execute``).

The arm may be a real one or sim_node (which accepts the same topic). What is checked before a goal is sent
(:meth:`ArmDriver.refusal`): the joint limits shrunk by a margin and the workspace box
(:class:`~body_scheme_core.control.motion.SafetyLimits`), and self-collision and ground contact along the straight
joint-space path from the arm's position (:class:`~body_scheme_sim.babbling.CollisionScreen`, pybullet from the URDF).
Refused goals are counted by reason and never sent. The one goal sent without those checks, :meth:`ArmDriver.halt`'s,
stays where the arm is, clamped within the limits less the margin.

Every joint state is checked before it is used: a commanded joint's position beyond its limits by more than
:data:`JOINT_STATE_SLACK` of its range (a broken encoder, a hostile publisher: 50 rad, 1e308) is refused whole and
counted (``joint_states_out_of_range``), so no reading can make a halt leave the limits or a move's path check
unbounded.
"""

from __future__ import annotations

import threading
from collections import Counter

import numpy as np
from builtin_interfaces.msg import Duration
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from body_scheme_core.control import SafetyLimits, SettleDetector, path_samples, trajectory_duration
from body_scheme_core.errors import BodySchemeError, InvalidInputError

from . import conversions
from .intake import BatchIntake
from .ros_parameters import declare_list_parameter

__all__ = ["ArmDriver", "declare_driver_parameters", "driver_from_parameters"]

#: Largest joint step (rad, m) between two postures checked along a move's path.
PATH_STEP = 0.05
#: s between two takes of the joint states, and the depth of their queue (a second of joint states at 100 Hz).
JOINT_STATE_PERIOD = 0.01
JOINT_STATE_DEPTH = 100
#: Fraction of a joint's range a reported position may lie beyond its limits (encoders overshoot a little; more is a
#: broken reading).
JOINT_STATE_SLACK = 0.1


def declare_driver_parameters(node):
    """Declare the driver's parameters on ``node`` (see config/babble_node.yaml for their meaning); returns their
    values, for :func:`driver_from_parameters`."""
    p = node.declare_parameter
    values = {name: p(name, default).value for name, default in (
        ("robot", "powercube_6dof"), ("controller", "joint_trajectory_controller"),
        ("joint_states_topic", "/joint_states"), ("max_velocity", 1.0), ("max_acceleration", 2.0),
        ("limit_margin", 0.05), ("collision_check", True), ("settle_tolerance", 0.01), ("settle_still", 0.002),
        ("settle_window", 0.1), ("settle_timeout", 2.0), ("max_message_bytes", 1 << 20))}
    if isinstance(values["max_message_bytes"], bool) or not isinstance(values["max_message_bytes"], int) or \
            not 1 <= values["max_message_bytes"] <= 1 << 30:
        raise InvalidInputError(f"max_message_bytes must be an integer from 1 to {1 << 30}, got "
                                f"{values['max_message_bytes']!r}")
    values["package_path"] = declare_list_parameter(node, "package_path", str)
    values["workspace"] = declare_list_parameter(node, "workspace", float)
    values["joint_names"] = declare_list_parameter(node, "joint_names", str)
    return values


def driver_from_parameters(node, values):
    """An :class:`ArmDriver` for ``node`` from :func:`declare_driver_parameters`' values."""
    from body_scheme_sim.robots import load_robot  # robot files only: no physics engine

    workspace = values["workspace"]
    if workspace and len(workspace) != 6:
        raise InvalidInputError(f"workspace takes [x_min, y_min, z_min, x_max, y_max, z_max] (m, root frame), got "
                                f"{workspace}")
    settle = SettleDetector(values["settle_tolerance"], values["settle_still"], values["settle_window"],
                            values["settle_timeout"])
    tree = load_robot(values["robot"], markers=())
    screen = None
    if values["collision_check"]:  # pybullet's collision geometry: the one place a real arm's driver loads it
        from body_scheme_sim.babbling import CollisionScreen

        screen = CollisionScreen(values["robot"], package_path=values["package_path"])
        pairs = ", ".join(f"{a}-{b}" for a, b in screen.ignored_pairs)
        node.get_logger().info(f"collision screen: every link pair is checked but {pairs or 'none'} (touching at the "
                               f"zero posture or in almost every posture; adjacent links are never checked)")
    return ArmDriver(node, tree, values["joint_names"] or tree.action_joint_names, values["limit_margin"],
                     np.reshape(workspace, (2, 3)) if workspace else None, screen, values["max_velocity"],
                     values["max_acceleration"], settle, values["controller"], values["joint_states_topic"],
                     values["max_message_bytes"])


class ArmDriver:
    """Sends checked goals as ``JointTrajectory`` messages and tells when the arm has settled.

    Parameters
    ----------
    node : rclpy.node.Node
    tree : KinematicTree
        The robot (limits, forward kinematics for the workspace box); its action joints are the robot's joints.
    joint_names : sequence of str
        The joints this driver commands, a subset of the robot's (e.g. an arm's without its gripper's). The others
        are read from the joint states when they are there (else held at 0) and are never sent.
    limit_margin : float
        rad (m) kept from every joint limit (:class:`~body_scheme_core.control.motion.SafetyLimits`).
    workspace : array-like, shape (2, 3) or None
        Box in the root link's frame that every link origin stays in, at every checked posture of a move.
    screen : CollisionScreen or None
    max_velocity, max_acceleration : float
        Per-joint limits of the moves (rad/s, rad/s^2; :func:`~body_scheme_core.control.motion.trajectory_duration`).
    settle : SettleDetector
    controller : str
        The ``JointTrajectoryController``'s name: goals go to ``<controller>/joint_trajectory``.
    joint_states_topic : str
    max_message_bytes : int
        A larger joint state is refused unread (``joint_states_oversized``).
    """

    def __init__(self, node, tree, joint_names, limit_margin, workspace, screen, max_velocity, max_acceleration,
                 settle, controller, joint_states_topic, max_message_bytes=1 << 20):
        self.node = node
        self.clock = None  # the node's clock (s) unless a test injects its own
        self.robot_joints = tuple(tree.action_joint_names)
        self.joint_names = tuple(joint_names)
        unknown = sorted(set(self.joint_names) - set(self.robot_joints))
        if unknown or len(set(self.joint_names)) != len(self.joint_names) or not self.joint_names:
            raise InvalidInputError(f"joint_names must name joints of the robot, each once, got "
                                    f"{list(self.joint_names)}; the robot's are {list(self.robot_joints)}")
        self._index = np.array([self.robot_joints.index(name) for name in self.joint_names])
        self._others = [name for name in self.robot_joints if name not in self.joint_names]

        self.tree = tree

        def link_origins(a):  # in the root link's frame, at command a with the other joints where they are
            return np.array([T[:3, 3] for T in tree.link_poses(self.posture(a)).values()])

        self.safety = SafetyLimits(tree.action_lower[self._index], tree.action_upper[self._index], limit_margin,
                                   workspace, link_origins if workspace is not None else None)
        slack = JOINT_STATE_SLACK * (tree.action_upper - tree.action_lower)
        #: Plausible reported positions of every joint of the robot (action order): the limits widened by the slack.
        self.plausible = (tree.action_lower - slack, tree.action_upper + slack)
        self.joint_state_problem = ""  # why the last refused joint state was refused
        self.screen, self.settle, self.max_message_bytes = screen, settle, max_message_bytes
        self.max_velocity, self.max_acceleration = max_velocity, max_acceleration
        trajectory_duration(np.zeros(1), np.ones(1), max_velocity, max_acceleration)  # validates the limits now
        self._counts = Counter()
        self.goal = None  # the goal being moved to, until it settled
        self._reading = None  # (receipt time s, positions of joint_names) of the last joint state
        self._held = np.zeros(len(self.robot_joints))  # the robot's last known posture (action order)
        self._lock = threading.Lock()
        if workspace is not None:
            self._check_fixed_links_inside(workspace)
        self.pub_trajectory = node.create_publisher(JointTrajectory, f"{controller}/joint_trajectory", 10)
        self.joint_states_topic = node.resolve_topic_name(joint_states_topic)
        # Taken in batches every JOINT_STATE_PERIOD: a joint state DDS overwrote in a flood is counted, not lost
        # unseen (body_scheme_nodes.intake).
        self._joint_states = BatchIntake(node, JointState, joint_states_topic, JOINT_STATE_DEPTH, max_message_bytes)
        node.create_timer(JOINT_STATE_PERIOD, self.take_joint_states)

    def _now(self):
        return self.clock() if self.clock is not None else self.node.get_clock().now().nanoseconds * 1e-9

    def _count(self, key):
        with self._lock:
            self._counts[key] += 1

    @property
    def counts(self):
        """A copy of the counters: ``sent``, ``settled``, ``settle_timeouts``, ``halted`` (with a goal: where the arm
        is), ``halted_without_goal`` (no joint state yet), ``refused.<reason>`` (joint limit, workspace, collision,
        malformed), ``joint_states`` taken, ``joint_states_rejected`` (malformed), ``joint_states_out_of_range``,
        ``joint_states_oversized`` (over ``max_message_bytes``, refused unread) and ``joint_states_lost`` (overwritten
        in DDS before they were taken)."""
        with self._lock:
            return dict(self._counts)

    def take_joint_states(self):
        """Take the joint states waiting in DDS (a timer every :data:`JOINT_STATE_PERIOD`)."""
        for msg, _ in self._joint_states.take():
            self._on_joint_states(msg)
        refused = len(self._joint_states.take_refused())
        with self._lock:
            self._counts["joint_states_oversized"] += refused
            self._counts["joint_states_lost"] = self._joint_states.lost

    def _on_joint_states(self, msg):
        try:
            _, positions = conversions.actions_from_joint_state(msg, self.joint_names)
        except BodySchemeError as error:
            with self._lock:
                self._counts["joint_states_rejected"] += 1
                self.joint_state_problem = str(error)
            return
        lower, upper = (bound[self._index] for bound in self.plausible)
        outside = np.flatnonzero((positions < lower) | (positions > upper))
        if outside.size:
            k = outside[0]
            with self._lock:
                self._counts["joint_states_out_of_range"] += 1
                self.joint_state_problem = (f"{self.joint_names[k]} reported at {positions[k]:.4g}, beyond its limits "
                                            f"[{lower[k]:.4g}, {upper[k]:.4g}] (with {JOINT_STATE_SLACK:.0%} slack)")
            return
        by_name = dict(zip(msg.name, msg.position, strict=False))
        with self._lock:
            self._reading = (self._now(), positions)
            self._held[self._index] = positions
            for name in self._others:
                j = self.robot_joints.index(name)
                if name in by_name and self.plausible[0][j] <= by_name[name] <= self.plausible[1][j]:
                    self._held[j] = by_name[name]
            self._counts["joint_states"] += 1

    @property
    def positions(self):
        """The commanded joints' last reported positions, or None before the first joint state."""
        with self._lock:
            return None if self._reading is None else self._reading[1].copy()

    def joint_state_age(self):
        """Seconds since the last joint state, or None before the first."""
        with self._lock:
            return None if self._reading is None else self._now() - self._reading[0]

    def posture(self, a):
        """The robot's whole posture (its action order) with the commanded joints at ``a``."""
        with self._lock:
            full = self._held.copy()
        full[self._index] = a
        return full

    def _check_fixed_links_inside(self, workspace):
        """A link origin that no joint moves (the base's) outside the workspace box makes every command a refusal:
        say which, at start-up, instead of refusing every move."""
        low, high = self.tree.action_lower, self.tree.action_upper  # every joint of the robot, commanded or not
        poses = [self.tree.link_poses(low + f * (high - low)) for f in (0.0, 0.3, 0.55, 0.8)]
        for link, T in poses[0].items():
            p = T[:3, 3]
            fixed = all(np.allclose(other[link][:3, 3], p, atol=1e-9) for other in poses[1:])
            if fixed and self.safety.outside(p)[0]:
                raise InvalidInputError(
                    f"workspace {np.ravel(workspace).tolist()} does not hold link {link!r} at "
                    f"{np.round(p, 3).tolist()} m, whose origin no joint moves: every command would be refused "
                    f"(the box is [x_min, y_min, z_min, x_max, y_max, z_max] in the root link's frame and holds "
                    f"every link origin)")

    def workspace_problem(self, a):
        """Which link origins command ``a`` puts outside the workspace box, as text ("" when none, or no box)."""
        poses = self.tree.link_poses(self.posture(np.asarray(a, dtype=float)))
        outside = self.safety.outside([T[:3, 3] for T in poses.values()])
        return "; ".join(f"{link} at {np.round(T[:3, 3], 3).tolist()}"
                         for (link, T), out in zip(poses.items(), outside, strict=True) if out)

    def refusal(self, goal, start=None):
        """Why ``goal`` may not be sent from ``start`` (default: the arm's position), or None. The joint limits are
        checked at the goal; the workspace box and collisions at every :data:`PATH_STEP` along the way (only at the
        goal for the box when the arm starts outside it: the way back in is allowed)."""
        goal = np.asarray(goal, dtype=float)
        why = self.safety.violation(goal)
        if why is not None:
            return why
        start = self.positions if start is None else np.asarray(start, dtype=float)
        try:
            path = path_samples(goal if start is None else start, goal, PATH_STEP)
        except InvalidInputError:  # a start beyond any plausible posture: nothing is sent from there
            return "malformed"
        if start is not None and not self.safety.outside_box(start):
            if any(self.safety.outside_box(a) for a in path[:-1]):
                return "workspace"
        if self.screen is not None and self.screen.collides([self.posture(a) for a in path]):
            return "collision"
        return None

    def send(self, goal):
        """Check ``goal`` and send it as a one-point trajectory; returns None, or the refusal (counted)."""
        goal = np.asarray(goal, dtype=float)
        start = self.positions
        if start is None:
            return "no joint state yet"
        why = self.refusal(goal, start)
        if why is not None:
            self._count(f"refused.{why}")
            return why
        duration = trajectory_duration(start, goal, self.max_velocity, self.max_acceleration)
        self.goal = goal
        self.settle.start(goal, self._now() + duration)
        self.pub_trajectory.publish(self._trajectory(goal, duration))
        self._count("sent")
        return None

    def _trajectory(self, positions, duration):
        """A one-point trajectory to ``positions`` at rest after ``duration`` s, stamped 0 (start at once)."""
        seconds = int(duration)
        point = JointTrajectoryPoint(positions=[float(v) for v in positions], velocities=[0.0] * len(positions),
                                     time_from_start=Duration(sec=seconds, nanosec=int((duration - seconds) * 1e9)))
        return JointTrajectory(joint_names=list(self.joint_names), points=[point])

    def settled(self):
        """The goal being moved to once the arm has come to rest at it (or ``settle.timeout`` after the planned
        end: counted as a settle timeout), else None; a settled goal is done."""
        if self.goal is None:
            return None
        with self._lock:
            reading = self._reading
        at_rest = reading is not None and self.settle.reading(reading[1], reading[0])
        if not at_rest and not self.settle.expired(self._now()):
            return None
        self._count("settled" if at_rest else "settle_timeouts")
        goal, self.goal = self.goal, None
        return goal

    def halt(self):
        """Stop the arm where it is: a one-point trajectory to its last reported position clamped within the joint
        limits less the margin (a ``JointTrajectoryController`` rejects an empty trajectory), over ``4 v / a``: the
        controller's cubic from full speed back to rest there starts with a deceleration of ``4 v / T``, within the
        acceleration limit. Before the first joint state nothing is sent (``halted_without_goal``). Returns the goal
        sent, or None."""
        positions = self.positions
        self.goal = None
        if positions is None:
            self._count("halted_without_goal")
            return None
        self._count("halted")
        hold = np.clip(positions, self.safety.lower, self.safety.upper)
        self.pub_trajectory.publish(self._trajectory(hold, max(0.1, 4.0 * self.max_velocity / self.max_acceleration)))
        return hold

    def close(self):
        if self.screen is not None:
            self.screen.close()
