"""control_node: moves a body part to a target with inverse kinematics on the learned body scheme.

Subscriptions
-------------
body_scheme/snapshot : body_scheme_msgs/ModelSnapshot  (transient local)
    The current body scheme from scheme_node; rebuilt into a :class:`~body_scheme_core.prediction.scheme.BodyScheme`.
ik_target : body_scheme_msgs/IKTarget
    Target position of a part (``part_id`` -1: the ``part_id`` parameter), in ``header.frame_id``.
ik_target/point : geometry_msgs/PointStamped
    Target position of the ``part_id`` parameter's part.
joint_commands : sensor_msgs/JointState
    The latest command (from anyone) is the IK start point.
body_scheme/explore_near/done : body_scheme_msgs/ExploreNear  (``explore_when_unsure``)
    scheme_node's answer to a request to explore near an unsure answer.
observations : body_scheme_msgs/MarkerPoses  (execute)
    Where the part is seen after an executed move.
/joint_states : sensor_msgs/JointState  (execute; ``joint_states_topic``)

Publishers
----------
joint_commands : sensor_msgs/JointState
    The solution, or ``trajectory_steps`` commands interpolated from the current command to it. With ``execute``:
    the solution once the arm settled at it (the action signal scheme_node learns from, as babble_node's).
<controller>/joint_trajectory : trajectory_msgs/JointTrajectory  (execute)
    The solution as a JointTrajectoryController goal, after babble_node's safety checks (joint limits less the
    margin, workspace box, collision screen).
ik_result : body_scheme_msgs/IKResult
    One per request taken, success or not, with the reason; with ``execute``, after the move: ``executed``, where the
    part went (``reached``: seen by the camera after the move, else predicted at the joint states) and its distance
    from the target. Beyond ``max_pending_requests`` waiting, a request is answered at once "busy" (``busy``). The
    targets are taken in batches from a queue of ``queue_depth``: a target DDS overwrote in a flood never reaches the
    node and is counted instead (``lost.ik_target_messages``), one over ``max_message_bytes`` is refused unread
    (``rejected.oversized_message``). So requests = answered + busy, and sent = requests + lost + refused.
body_scheme/explore_near : body_scheme_msgs/ExploreNear  (``explore_when_unsure``)
    An answer that reaches the target but is not sure enough: scheme_node explores ``explore_samples`` postures near
    it, runs the joint fit and answers; the request is then solved again on the new snapshot and answered a second
    time (``IKResult.explored_samples``), once. Refused or unanswered within ``explore_timeout``, it is answered a
    second time without exploring (reason "not explored (why): ...").
/diagnostics : diagnostic_msgs/DiagnosticArray
    ``body_scheme: control``: model age, requests, successes, explorations, last outcome (1 Hz).

Parameters
----------
part_id : int 7                      default part to move
tolerance : double 0.005 m           IK success: the predicted distance to the target plus the radius holding the
                                     true position at the ``confidence`` level below this
confidence : double 2.0              level in sigmas (95.4 % at 2; 0: the model's word alone, however unsure)
prefer_certain : bool false          use every restart and keep the least uncertain solution
max_iterations : int 100, restarts : int 3
max_snapshot_age : double 0.0 s      refuse to act on an older model (0: never stale)
trajectory_steps : int 1             commands per solution (1: jump to it)
trajectory_period : double 0.05 s    time between interpolated commands
stay_in_training_range : bool true   search only actions the learned local models were trained on
                                     (:func:`~body_scheme_core.control.ik.trained_bounds`); false: the full joint limits
execute : bool false                 move the arm through its JointTrajectoryController (arm_driver)
explore_when_unsure : bool false     ask scheme_node (with ``exploration`` true) to explore near an unsure answer,
                                     then solve again
explore_samples : int 5, explore_radius : double 0.1 (of each joint's range), explore_timeout : double 60.0 s
observe_timeout : double 1.0 s       execute: how long to wait for the camera to see the part after the move
queue_depth : int 100                depth of the two target subscriptions (taken every 10 ms)
max_pending_requests : int 100       requests waiting for a solve; more are answered "busy" at once
max_message_bytes : int 1048576      a larger message on any subscription is refused unread (16x for the snapshot)
robot, controller, joint_states_topic, max_velocity, max_acceleration, limit_margin, workspace, collision_check,
package_path, settle_*               execute: as babble_node's (config/babble_node.yaml)
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import JointState

from body_scheme_core.control import NearFocus, solve_ik, trained_bounds
from body_scheme_core.errors import BodySchemeError, InvalidInputError
from body_scheme_msgs.msg import ExploreNear, IKResult, IKTarget, MarkerPoses, ModelSnapshot

from . import conversions
from .arm_driver import declare_driver_parameters, driver_from_parameters
from .intake import BatchIntake, create_sized_subscription
from .qos import LATCHED
from .ros_parameters import refuse_parameter_changes
from .spin import run_node


class ExploreSettings:
    """``explore_when_unsure`` and its parameters, checked."""

    def __init__(self, enabled, samples, radius, timeout):
        if not isinstance(enabled, bool):
            raise InvalidInputError(f"explore_when_unsure must be true or false, got {enabled!r}")
        try:  # scheme_node checks each request so: refused here at start-up rather than per request
            NearFocus.check_settings(samples, radius)
        except InvalidInputError as exc:
            raise InvalidInputError(f"explore_samples, explore_radius: {exc}") from None
        if not (isinstance(timeout, float) and np.isfinite(timeout) and timeout > 0):
            raise InvalidInputError(f"explore_timeout must be a number > 0 (s), got {timeout!r}")
        self.enabled, self.samples, self.radius, self.timeout = enabled, samples, radius, timeout


class ControlNode(Node):
    """ROS wrapper of :func:`body_scheme_core.control.ik.solve_ik` (see the module docstring)."""

    def __init__(self):
        super().__init__("control_node")
        self.default_part = self.declare_parameter("part_id", 7).value
        self.tolerance = self.declare_parameter("tolerance", 0.005).value
        self.confidence = self.declare_parameter("confidence", 2.0).value
        self.prefer_certain = self.declare_parameter("prefer_certain", False).value
        if not (isinstance(self.confidence, float) and np.isfinite(self.confidence) and self.confidence >= 0):
            raise InvalidInputError(f"confidence must be a number >= 0 (sigmas), got {self.confidence!r}")
        self.max_iterations = self.declare_parameter("max_iterations", 100).value
        self.restarts = self.declare_parameter("restarts", 3).value
        self.max_age = self.declare_parameter("max_snapshot_age", 0.0).value
        self.trajectory_steps = max(1, self.declare_parameter("trajectory_steps", 1).value)
        trajectory_period = self.declare_parameter("trajectory_period", 0.05).value
        self.stay_in_training_range = self.declare_parameter("stay_in_training_range", True).value
        self.execute = self.declare_parameter("execute", False).value
        self.observe_timeout = self.declare_parameter("observe_timeout", 1.0).value
        queue_depth = self.declare_parameter("queue_depth", 100).value
        self.max_pending = self.declare_parameter("max_pending_requests", 100).value
        for name, value in (("queue_depth", queue_depth), ("max_pending_requests", self.max_pending)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 1 << 30:
                raise InvalidInputError(f"{name} must be an integer from 1 to {1 << 30}, got {value!r}")
        self.explore = ExploreSettings(self.declare_parameter("explore_when_unsure", False).value,
                                       self.declare_parameter("explore_samples", 5).value,
                                       self.declare_parameter("explore_radius", 0.1).value,
                                       self.declare_parameter("explore_timeout", 60.0).value)
        driver_values = declare_driver_parameters(self)
        max_bytes = driver_values["max_message_bytes"]
        self.driver = driver_from_parameters(self, driver_values) if self.execute else None
        self.moving = None  # execute: (IKResult, part, target, model) of the move under way
        self.settled_at = None  # execute: (time s, positions) the move settled at, until the part is seen
        self.seen = {}  # part -> (stamp s, camera2part) of its last observation

        self.model = None  # (scheme, world2root, lower, upper, joint names, frame_id, received_at, step)
        self.current = None  # latest commanded actions, in the model's joint order
        # (header, part, position, None | (samples explored, reason prefix) of a second solve) awaiting a solve
        self.requests = deque()
        self.exploring = None  # (request ExploreNear, header, part, target, asked at) awaiting scheme_node's answer
        self.resolve = None  # (header, part, target, step, answered at): solve again once the snapshot is of step
        self.trajectory = deque()  # action vectors still to command
        self.counts = {"received": 0, "requests": 0, "succeeded": 0, "failed": 0, "busy": 0, "executed": 0,
                       "explored": 0, "explore_refused": 0, "explore_timeouts": 0}
        self.oversized = 0  # messages refused unread for their size, under _lock (any callback's thread)
        self.last_outcome = "none yet"
        self.last_uncertainty = (float("nan"), float("nan"))  # position_std, error_bound (m) of the last answer
        self._lock = threading.Lock()

        work = MutuallyExclusiveCallbackGroup()

        def subscribe(msg_type, topic, callback, qos, limit=max_bytes):
            create_sized_subscription(self, msg_type, topic, callback, qos, limit, self._oversized)

        # The snapshot is taken with the targets, first: a target sent right after a snapshot is solved on it.
        self.snapshots = BatchIntake(self, ModelSnapshot, "body_scheme/snapshot", LATCHED, 16 * max_bytes)
        self.targets = {"ik_target": BatchIntake(self, IKTarget, "ik_target", queue_depth, max_bytes),
                        "ik_target/point": BatchIntake(self, PointStamped, "ik_target/point", queue_depth, max_bytes)}
        subscribe(JointState, "joint_commands", self._on_command, 10)
        if self.execute:
            subscribe(MarkerPoses, "observations", self._on_observations, 10)
        if self.explore.enabled:
            self.pub_explore = self.create_publisher(ExploreNear, "body_scheme/explore_near", 10)
            subscribe(ExploreNear, "body_scheme/explore_near/done", self._on_explored, 10)
        self.pub_command = self.create_publisher(JointState, "joint_commands", 10)
        # Every answer one batch may give (a "busy" for each target taken, a solve for each waiting) is kept until a
        # slow reader took it: with a depth of 10 a flood's answers overwrote each other unread (a CI run under load
        # received 1,051 of 1,465).
        self.pub_result = self.create_publisher(IKResult, "ik_result", min(2 * queue_depth + self.max_pending, 1 << 16))
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(0.01, self._solve_pending, callback_group=work)
        self.create_timer(trajectory_period, self._command_next, callback_group=work)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=work)
        refuse_parameter_changes(self)
        self.get_logger().info(f"control_node ready: default part {self.default_part}, tolerance {self.tolerance} m")

    # -- callbacks only store --------------------------------------------------------------------------------------
    def _on_snapshot(self, msg):
        try:
            scheme, world2root, lower, upper = conversions.scheme_from_snapshot(msg)
        except BodySchemeError as error:
            self.get_logger().error(f"ignoring unusable model snapshot: {error}")
            return
        with self._lock:
            self.model = (scheme, world2root, lower, upper, list(msg.action_names), msg.header.frame_id,
                          time.monotonic(), msg.step)

    def _on_command(self, msg):
        with self._lock:
            names = None if self.model is None else self.model[4]
        if names is None:
            return
        try:
            _, self.current = conversions.actions_from_joint_state(msg, names)
        except BodySchemeError:
            pass  # someone else's command for other joints: not a start point for us

    def _on_observations(self, msg):
        try:
            stamp, observed, _ = conversions.observations_from_msg(msg)
        except BodySchemeError:
            return
        with self._lock:
            self.seen.update({part: (stamp, pose) for part, pose in observed.items()})

    def _oversized(self, size):
        with self._lock:
            self.oversized += 1
        self.get_logger().warn(f"rejected input (oversized_message): {size} bytes", throttle_duration_sec=5.0)

    def _take_targets(self):
        """Take the newest snapshot, then the waiting targets (IKTarget and PointStamped) into the request queue;
        beyond ``max_pending_requests`` waiting, a request is answered "busy" at once."""
        for msg, _ in self.snapshots.take():
            self._on_snapshot(msg)
        for size in self.snapshots.take_refused():
            self._oversized(size)
        for topic, intake in self.targets.items():
            for msg, _ in intake.take():
                self.counts["received"] += 1
                if topic == "ik_target":
                    part, p = (self.default_part if msg.part_id < 0 else msg.part_id), msg.position
                else:
                    part, p = self.default_part, msg.point
                with self._lock:
                    full = len(self.requests) >= self.max_pending
                    if not full:
                        self.requests.append((msg.header, int(part), [p.x, p.y, p.z], None))
                if full:
                    self._answer_busy(msg.header, int(part), [p.x, p.y, p.z])
            for size in intake.take_refused():
                self._oversized(size)

    def _answer_busy(self, header, part, target):
        result = self._refusal(header, part, target)
        result.reason = f"busy: {self.max_pending} requests are waiting already (max_pending_requests); send again"
        self.counts["busy"] += 1
        self.pub_result.publish(result)

    def _on_explored(self, msg):
        """scheme_node served (or refused) our request to explore near an unsure answer."""
        with self._lock:
            if self.exploring is None or self.exploring[0].header.stamp != msg.header.stamp:
                return  # another control_node's request, or one we gave up on
            _, header, part, target, _ = self.exploring
            self.exploring = None
            if msg.outcome:
                self.counts["explore_refused"] += 1
                self.requests.appendleft((header, part, target, (0, f"not explored ({msg.outcome}): ")))
            else:
                self.resolve = (header, part, target, msg.step, time.monotonic())
        if msg.outcome:
            self.get_logger().warn(f"exploring near the answer for part {part}: {msg.outcome}")

    # -- work in timers --------------------------------------------------------------------------------------------
    def _solve_pending(self):
        self._take_targets()
        if self.moving is not None:
            self._watch_move()
            return
        self._follow_exploration()
        with self._lock:
            if not self.requests:
                return
            header, part, target, again = self.requests.popleft()
            model = self.model
        self.counts["requests"] += int(again is None)
        result = self._solve(header, part, target, model)
        if again is not None:  # the second answer of a request whose first was unsure
            result.explored_samples = again[0]
            result.reason = again[1] + result.reason
        elif self.explore.enabled and result.converged and not result.success:
            result.reason += self._ask_to_explore(header, part, target, result.actions, model)
        if self.execute and result.success:
            why = self._send(result, model)
            if why is None:
                self.moving = (result, part, target, model)
                return
            result.reason = f"converged, not executed: {why}"
        self._report(result, part, target)

    def _ask_to_explore(self, header, part, target, actions, model):
        """Ask scheme_node to explore near ``actions``; returns what to add to the answer's reason."""
        if self.exploring is not None or self.resolve is not None:
            return "; not exploring near it: exploring near an earlier answer"
        request = ExploreNear(joint_names=model[4], positions=list(actions), samples=self.explore.samples,
                              radius=self.explore.radius)
        request.header.stamp = self.get_clock().now().to_msg()
        with self._lock:
            self.exploring = (request, header, part, target, time.monotonic())
        self.counts["explored"] += 1
        self.pub_explore.publish(request)
        return f"; exploring {self.explore.samples} postures near it, then solving again"

    def _follow_exploration(self):
        """Solve an explored request again once the snapshot of scheme_node's joint fit arrived. Every request whose
        first answer asked for exploration is answered a second time: without exploring when scheme_node did not
        answer within ``explore_timeout``, on the newest snapshot when the joint fit's did not arrive within it."""
        now, timeout, samples = time.monotonic(), self.explore.timeout, self.explore.samples
        with self._lock:
            if self.exploring is not None and now - self.exploring[4] > timeout:
                _, header, part, target, _ = self.exploring
                self.exploring = None
                self.counts["explore_timeouts"] += 1
                self.requests.appendleft((header, part, target, (0, f"not explored (no answer from scheme_node "
                                                                    f"within {timeout} s): ")))
                self.get_logger().warn(f"no answer to exploring near the answer for part {part} within {timeout} s: "
                                       f"is scheme_node running with exploration true, and a babble_node in mode "
                                       f"active?")
            if self.resolve is None or self.model is None:
                return
            header, part, target, step, answered = self.resolve
            prefix = f"after exploring {samples} postures near the first answer"
            if self.model[7] >= step:
                self.requests.appendleft((header, part, target, (samples, prefix + ": ")))
            elif now - answered > timeout:
                self.counts["explore_timeouts"] += 1
                self.requests.appendleft((header, part, target, (samples, f"{prefix} (the body scheme of step {step} "
                                                                          f"did not arrive within {timeout} s; on "
                                                                          f"that of step {self.model[7]}): ")))
            else:
                return
            self.resolve = None

    def _report(self, result, part, target):
        self.counts["succeeded" if result.success else "failed"] += 1
        self.counts["executed"] += int(result.executed)
        self.last_outcome = f"part {part}: {result.reason}"
        self.last_uncertainty = (result.position_std, result.error_bound)
        self.pub_result.publish(result)
        text = (f"IK part {part} -> {np.round(target, 3).tolist()}: {result.reason} (residual {result.residual:.4f} m, "
                f"predicted std {result.position_std:.4f} m)")
        if result.executed:
            text += f"; went to {result.reached_error * 1000:.1f} mm from it ({result.reached_source})"
        if result.success:
            self.get_logger().info(text)
        else:
            self.get_logger().warn(text)

    # -- execute: true ---------------------------------------------------------------------------------------------
    def _send(self, result, model):
        """Send the solution to the controller (checked by the driver); returns None or why it was not sent."""
        names = model[4]
        if tuple(names) != self.driver.joint_names:
            return f"the body scheme's joints {names} are not the robot's {list(self.driver.joint_names)}"
        return self.driver.send(np.asarray(result.actions))

    def _watch_move(self):
        """Once the arm settled: publish the action signal, then report where the part went (seen by the camera
        within observe_timeout, else predicted at the joint states)."""
        result, part, target, model = self.moving
        now = self.get_clock().now().nanoseconds * 1e-9
        if self.settled_at is None:
            goal = self.driver.settled()
            if goal is None:
                return
            self.settled_at = (now, self.driver.positions)
            self.pub_command.publish(conversions.joint_state_msg(now, model[4], goal))
            self.current = goal
        settled, positions = self.settled_at
        with self._lock:
            seen = self.seen.get(part)
        if seen is not None and seen[0] >= settled:
            reached, result.reached_source = seen[1][:3, 3], "observed"
        elif now - settled >= self.observe_timeout:
            scheme, world2root = model[0], model[1]
            at = positions if positions is not None else np.asarray(result.actions)
            reached, result.reached_source = (world2root @ scheme.predict(at)[part])[:3, 3], "predicted"
        else:
            return
        result.executed = True
        result.reached.x, result.reached.y, result.reached.z = (float(v) for v in reached)
        result.reached_error = float(np.linalg.norm(reached - np.asarray(target)))
        self.moving, self.settled_at = None, None
        self._report(result, part, target)

    @staticmethod
    def _refusal(header, part, target):
        """An answer refused before any evaluation: residual NaN and no actions, whatever the reason."""
        result = IKResult(header=header, part_id=part, success=False, residual=float("nan"),
                          position_std=float("nan"), error_bound=float("nan"), reached_error=float("nan"))
        result.target.x, result.target.y, result.target.z = (float(v) for v in target)
        return result

    def _solve(self, header, part, target, model):
        result = self._refusal(header, part, target)
        if not np.all(np.isfinite(target)):
            result.reason = "target contains NaN or inf"
            return result
        if model is None or model[0] is None:
            result.reason = "no body scheme yet: waiting for a model snapshot from scheme_node"
            return result
        scheme, world2root, lower, upper, names, frame_id, received_at, _ = model
        age = time.monotonic() - received_at
        if self.max_age > 0 and age > self.max_age:
            result.reason = f"model snapshot is stale: {age:.1f} s old (max_snapshot_age {self.max_age} s)"
            return result
        if header.frame_id and frame_id and header.frame_id != frame_id:
            result.reason = f"target frame {header.frame_id!r} differs from the body scheme's frame {frame_id!r}"
            return result
        if self.stay_in_training_range:
            lower, upper = trained_bounds(scheme, lower, upper)
        # The start of the search and of the interpolated commands: the latest command (anyone's, so unchecked)
        # within the limits, so every command sent lies within them.
        a0 = self.current if self.current is not None else (lower + upper) / 2.0
        a0 = np.clip(np.where(np.isfinite(a0), a0, (lower + upper) / 2.0), lower, upper)
        outcome = solve_ik(scheme, part, target, a0, lower, upper, tol=self.tolerance,
                           max_iterations=self.max_iterations, n_restarts=self.restarts, world2root=world2root,
                           confidence=self.confidence, prefer_certain=self.prefer_certain)
        result.success = bool(outcome.success)
        result.converged = bool(outcome.converged)
        result.position_std = float(outcome.position_std)
        result.error_bound = float(outcome.error_bound)
        result.reason = outcome.reason
        result.iterations = int(outcome.iterations)
        result.residual = float(outcome.residual)
        # Not evaluated (e.g. the part is not in the body scheme): no actions, as IKResult.msg says.
        result.actions = [float(v) for v in outcome.actions] if np.isfinite(outcome.residual) else []
        if outcome.success and not self.execute:
            steps = np.linspace(0.0, 1.0, self.trajectory_steps + 1)[1:]
            with self._lock:
                self.trajectory = deque(a0 + s * (outcome.actions - a0) for s in steps)
        return result

    def _command_next(self):
        with self._lock:
            if not self.trajectory or self.model is None:
                return
            actions = self.trajectory.popleft()
            names = self.model[4]
        msg = JointState(name=names, position=[float(v) for v in actions])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.current = actions
        self.pub_command.publish(msg)

    def _publish_diagnostics(self):
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        model = self.model
        if model is None or model[0] is None:
            level, message, age = DiagnosticStatus.WARN, "no body scheme yet", float("nan")
        else:
            age = time.monotonic() - model[6]
            stale = self.max_age > 0 and age > self.max_age
            level = DiagnosticStatus.WARN if stale else DiagnosticStatus.OK
            message = "model snapshot stale" if stale else "ready"
        with self._lock:
            oversized = self.oversized
        values = dict(self.counts, model_age_s=age, last_outcome=self.last_outcome,
                      last_position_std_mm=1e3 * self.last_uncertainty[0],
                      last_error_bound_mm=1e3 * self.last_uncertainty[1])
        values["rejected.oversized_message"] = oversized
        for topic, intake in self.targets.items():
            values[f"lost.{topic.replace('/', '_')}_messages"] = intake.lost
        if self.driver is not None:
            values.update({f"driver.{k}": v for k, v in self.driver.counts.items()})
        name = self.get_fully_qualified_name()  # node and namespace: two robots in one domain do not collide
        array.status.append(conversions.diagnostic_status(f"{name}: control", level, message, values, name))
        self.pub_diagnostics.publish(array)


    def destroy_node(self):
        if self.driver is not None:
            self.driver.close()
        super().destroy_node()


def main(args=None):
    return run_node(ControlNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
