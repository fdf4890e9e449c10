"""babble_node: babbles a real arm through ros2_control and publishes the action signal once each move has settled.

Each step: draw a random command within the joint limits (shrunk by ``limit_margin``) or, with ``mode: active``, take
scheme_node's latest suggestion (``body_scheme/exploration_command``, published after it learnt the last action; a
random draw instead, counted as ``fallbacks``, when none arrives within ``suggestion_timeout`` s or the suggestion is
refused); refuse it if it leaves the
workspace box or if the robot would hit itself or the ground on the way (pybullet from the URDF), send it as a
``trajectory_msgs/JointTrajectory`` to ``<controller>/joint_trajectory`` with a duration from the velocity and
acceleration limits, wait until ``/joint_states`` settles at it (or ``settle_timeout`` after the planned end), then
publish the commanded positions on ``joint_commands`` stamped at the settle time: the action signal scheme_node
learns from. The next step starts once the camera has sent a frame taken after the settle time (``wait_for_frame``)
and ``dwell`` seconds have passed. ``joint_names`` limits the commanded joints to a subset of the robot's (e.g. an
arm without its gripper; give scheme_node the same list). The ``control_msgs``
``FollowJointTrajectory`` action is not used: control_msgs is not on the PyPI route (docs/your-robot.md).

**Pre-flight.** Nothing is sent until every check passes (:mod:`.preflight`; each failing one is logged as one line
every 5 s and named on /diagnostics): joint states fresh and naming the configured joints, a subscriber on the
controller's trajectory topic, fresh observations on ``camera_topic``, a ``sensor_msgs/CameraInfo`` on
``camera_info_topic``, and a marker of ``part_ids`` (any marker if empty) seen while the arm stands at its start
posture (the others are named when it passes: a planned marker faces the camera in some postures only).
``preflight_skip`` lists checks skipped on purpose.

It stops by itself (a trajectory to where the arm is, clamped within the limits: the controller holds it there) when
scheme_node's /diagnostics status stays ERROR for ``error_hold`` s (a model invalid after bootstrapping, or learning
stalled), when the camera goes quiet (no message on ``camera_topic`` for ``camera_timeout`` s with the arm at rest,
summed over the rests between moves),
or when the joint states do (none usable for ``joint_state_timeout`` s: a joint state beyond the limits is refused,
and the stop names it). ``watch_diagnostics`` names that scheme_node (relative to babble_node's namespace, like a
topic): its status ``<node>: body scheme`` is matched exactly, so another robot's scheme_node in the same domain never
masks an ERROR.
After a pause of babble_node itself (a busy machine) the loop waits one tick (no watchdog verdict, no command), so the
messages that arrived during the pause are read first.

Subscriptions
-------------
/joint_states : sensor_msgs/JointState              (``joint_states_topic``)
/diagnostics : diagnostic_msgs/DiagnosticArray      the status ``<watch_diagnostics, resolved>: body scheme``
observations : body_scheme_msgs/MarkerPoses         (``camera_topic``) the camera watchdog and pre-flight
camera/camera_info : sensor_msgs/CameraInfo         (``camera_info_topic``) pre-flight
body_scheme/exploration_command : sensor_msgs/JointState   ``mode: active``: scheme_node's suggestions

Publishers
----------
<controller>/joint_trajectory : trajectory_msgs/JointTrajectory
joint_commands : sensor_msgs/JointState             the action signal (``action_topic``)
/diagnostics : diagnostic_msgs/DiagnosticArray      ``<node>: babbling``, 1 Hz: state, counters, stop reason

Services
--------
~/pause, ~/resume, ~/stop : std_srvs/Trigger
    Pause finishes the current move and waits; stop halts the arm at once. Resume continues after either.

Parameters: config/babble_node.yaml.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, JointState
from std_srvs.srv import Trigger

from body_scheme_core.errors import InvalidInputError
from body_scheme_msgs.msg import MarkerPoses

from . import conversions
from .arm_driver import declare_driver_parameters, driver_from_parameters
from .intake import create_sized_subscription
from .preflight import CHECKS, PreflightFacts, preflight_failures, unseen_markers
from .ros_parameters import declare_list_parameter, refuse_parameter_changes
from .scheme_diagnostics import status_name
from .spin import run_node

#: Random draws per step before the step is skipped (counted) because every draw was refused.
MAX_DRAWS = 100
#: s between two logs of the failing pre-flight checks.
PREFLIGHT_LOG_PERIOD = 5.0
#: s to wait for a camera frame stamped after the action when the camera watchdog is off (camera_timeout 0).
FRAME_WAIT = 3.0
#: s between two ticks of the loop past which this process was paused (a busy machine): the executor runs the tick
#: before the messages that queued meanwhile, so such a tick does nothing and the next one, after those are read,
#: judges the watchdogs and sends.
LATE_TICK = 0.5


def watched_status(node_name, namespace):
    """The exact /diagnostics status name babble_node watches for scheme_node ``node_name`` (relative names resolve
    in ``namespace``, as topics do); "" for "" (never)."""
    if not node_name:
        return ""
    if not all(part.isidentifier() for part in node_name.lstrip("/").split("/")):
        raise InvalidInputError(f"watch_diagnostics must be a node name (e.g. scheme_node, /robot2/scheme_node) or "
                                f"\"\", got {node_name!r}")
    full = node_name if node_name.startswith("/") else f"{namespace.rstrip('/')}/{node_name}"
    return status_name(full)


class BabbleNode(Node):
    """See the module docstring."""

    def __init__(self, **node_options):
        super().__init__("babble_node", **node_options)
        self.monotonic = time.monotonic  # the watchdogs' clock (s); tests inject their own
        p = self.declare_parameter
        self.action_topic = p("action_topic", "joint_commands").value
        self.dwell = p("dwell", 0.3).value
        self.steps = p("steps", 0).value
        seed = p("seed", 0).value
        self.watch = watched_status(p("watch_diagnostics", "scheme_node").value, self.get_namespace())
        self.error_hold = p("error_hold", 2.0).value
        camera_topic = p("camera_topic", "observations").value
        self.camera_timeout = p("camera_timeout", 10.0).value
        self.wait_for_frame = p("wait_for_frame", True).value
        self.joint_state_timeout = p("joint_state_timeout", 3.0).value
        camera_info_topic = p("camera_info_topic", "camera/camera_info").value
        self.part_ids = tuple(declare_list_parameter(self, "part_ids", int))
        self.preflight_skip = tuple(declare_list_parameter(self, "preflight_skip", str))
        unknown = sorted(set(self.preflight_skip) - set(CHECKS))
        if unknown:
            raise InvalidInputError(f"preflight_skip names unknown checks {unknown}; the checks are {list(CHECKS)}")
        self.mode = p("mode", "random").value
        self.suggestion_timeout = p("suggestion_timeout", 1.0).value
        if self.mode not in ("random", "active"):
            raise InvalidInputError(f"mode must be random or active, got {self.mode!r}")
        if not self.suggestion_timeout >= 0:
            raise InvalidInputError(f"suggestion_timeout must be >= 0 s, got {self.suggestion_timeout!r}")
        self.state = "paused" if p("start_paused", False).value else "waiting"
        update_period = p("update_period", 0.02).value
        if not (self.dwell >= 0 and self.camera_timeout >= 0 and self.error_hold >= 0 and update_period > 0
                and self.steps >= 0 and self.joint_state_timeout >= 0):
            raise InvalidInputError("dwell, camera_timeout, joint_state_timeout, error_hold and steps must be >= 0 "
                                    "and update_period > 0")
        self.driver = driver_from_parameters(self, declare_driver_parameters(self))
        self.rng = np.random.default_rng(seed)
        self.counts = Counter()
        self.stop_reason = ""
        self.next_at = 0.0  # monotonic time the next step may start (after the dwell)
        self.started = None  # monotonic time the first joint state was seen
        self.moved_since_camera = 0.0  # s the arm moved since the last camera message: not silence at rest
        self.judged_at = None  # monotonic time of the watchdogs' last verdict
        self.last_camera = None  # monotonic time of the last camera message
        self.last_frame_stamp = -np.inf  # header stamp (s) of the last camera message
        self.settled_stamp = -np.inf  # stamp (s) of the last action signal
        self.suggestion = None  # (stamp s, command in the driver's joint order) of scheme_node's latest suggestion
        self.idle_since = None  # monotonic time the loop became ready for the next step
        self.last_tick = None  # monotonic time of the loop's last tick
        self.error_since = None  # monotonic time the watched status turned ERROR (None: it is not)
        self.camera_info = False  # a CameraInfo arrived
        self.seen_markers = set()  # markers observed since the first joint state (the start posture)
        self.preflight = []  # the failing pre-flight checks' lines (empty once passed)
        self._preflight_logged = None  # monotonic time they were last logged

        work = MutuallyExclusiveCallbackGroup()
        self.pub_action = self.create_publisher(JointState, self.action_topic, 100)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        max_bytes = self.driver.max_message_bytes

        def subscribe(msg_type, topic, callback):  # larger messages are refused unread (counted: oversized)
            create_sized_subscription(self, msg_type, topic, callback, 10, max_bytes, self._oversized, work)

        subscribe(DiagnosticArray, "/diagnostics", self._on_diagnostics)
        subscribe(MarkerPoses, camera_topic, self._on_camera)
        # Camera drivers publish CameraInfo best effort (sensor data QoS): a best-effort subscription matches both.
        create_sized_subscription(self, CameraInfo, camera_info_topic, self._on_camera_info, qos_profile_sensor_data,
                                  max_bytes, self._oversized, work)
        self._facts = PreflightFacts(joint_states_topic=self.driver.joint_states_topic,
                                     controller_topic=self.driver.pub_trajectory.topic_name,
                                     camera_topic=self.resolve_topic_name(camera_topic),
                                     camera_info_topic=self.resolve_topic_name(camera_info_topic),
                                     expected_markers=self.part_ids)
        if self.mode == "active":
            subscribe(JointState, "body_scheme/exploration_command", self._on_suggestion)
        for name, handler in (("pause", self._on_pause), ("resume", self._on_resume), ("stop", self._on_stop)):
            self.create_service(Trigger, f"~/{name}", handler, callback_group=work)
        self.create_timer(update_period, self._on_timer, callback_group=work)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=work)
        refuse_parameter_changes(self)
        self.get_logger().info(f"babble_node ready: joints {list(self.driver.joint_names)}, {self.state}")

    # -- inputs -----------------------------------------------------------------------------------------------------
    def _oversized(self, size):
        self.counts["rejected.oversized_message"] += 1
        self.get_logger().warn(f"rejected input (oversized_message): {size} bytes", throttle_duration_sec=5.0)

    def _on_camera(self, msg):
        self.last_camera = self.monotonic()
        self.moved_since_camera = 0.0
        self.last_frame_stamp = max(self.last_frame_stamp, conversions.seconds_from_stamp(msg.header.stamp))
        if self.state == "waiting" and self.driver.positions is not None:
            self.seen_markers.update(int(i) for i in msg.marker_ids)

    def _on_camera_info(self, _msg):
        self.camera_info = True

    def _on_suggestion(self, msg):
        try:
            stamp, command = conversions.actions_from_joint_state(msg, self.driver.joint_names)
        except InvalidInputError:
            self.counts["suggestions_rejected"] += 1
            return
        self.suggestion = (stamp, command)

    def _on_diagnostics(self, msg):
        if not self.watch:
            return
        for status in msg.status:
            if status.name != self.watch:
                continue
            if status.level != DiagnosticStatus.ERROR:
                self.error_since = None
                continue
            now = self.monotonic()
            self.error_since = now if self.error_since is None else self.error_since
            if now - self.error_since >= self.error_hold and self.state not in ("stopped", "done"):
                self._stop(f"{status.name} reported ERROR for {now - self.error_since:.1f} s: {status.message}")

    def _on_pause(self, _request, response):
        if self.state == "stopped":
            response.success, response.message = False, f"stopped ({self.stop_reason}): resume first"
            return response
        self.state = "paused"
        response.success, response.message = True, "paused after the current move"
        return response

    def _on_resume(self, _request, response):
        previous = self.state
        if previous not in ("paused", "stopped"):
            response.success, response.message = False, f"not paused or stopped ({previous})"
            return response
        self.state, self.stop_reason = ("idle" if self.started is not None else "waiting"), ""
        self.error_since = None  # the watched status must stay ERROR for error_hold again
        now = self.monotonic()
        self.last_camera = now if self.last_camera is not None else None  # a fresh watchdog period
        self.moved_since_camera, self.judged_at = 0.0, None
        self.started = now if self.started is not None else None
        response.success, response.message = True, f"resumed (was {previous})"
        return response

    def _on_stop(self, _request, response):
        self._stop("stop requested")
        response.success, response.message = True, "stopped: the arm holds its position"
        return response

    # -- the loop -------------------------------------------------------------------------------------------------
    def _stop(self, reason):
        self.driver.halt()
        self.state, self.stop_reason = "stopped", reason
        self.counts["stops"] += 1
        self.get_logger().warn(f"babbling stopped: {reason}")

    def _on_timer(self):
        now = self.monotonic()
        late = self.last_tick is not None and now - self.last_tick > LATE_TICK
        self.last_tick = now
        if late:
            return  # after a pause: read what queued meanwhile before judging the watchdogs or sending anything
        if self.state in ("stopped", "paused", "done") and self.driver.goal is None:
            return
        if self.state == "waiting":
            if not self._preflight_passed(now):
                return
            self.state, self.started = "idle", now
        if self.state != "stopped":
            why = self._quiet(now)
            if why:
                self._stop(why)
                return
        if self.driver.goal is not None:
            goal = self.driver.settled()
            if goal is not None:
                self.settled_stamp = self.get_clock().now().nanoseconds * 1e-9
                self.pub_action.publish(conversions.joint_state_msg(self.settled_stamp, self.driver.joint_names, goal))
                self.counts["actions"] += 1
                self.next_at = now + self.dwell
            return
        if self.state != "idle" or now < self.next_at:
            return
        if self.wait_for_frame and self.last_frame_stamp < self.settled_stamp:
            if now - self.next_at < (self.camera_timeout or FRAME_WAIT):
                return  # the camera has not yet seen the arm at the last action
            self.counts["frames_missed"] += 1  # frames keep coming but none after it (stamps of another clock?)
            self.settled_stamp = -np.inf
        if self.steps and self.counts["actions"] >= self.steps:
            self.state = "done"
            self.get_logger().info(f"babbled {self.counts['actions']} commands: done")
            return
        if self.mode == "active" and self._follow_suggestion(now):
            return
        safety = self.driver.safety
        reasons = Counter()
        for _ in range(MAX_DRAWS):
            goal = self.rng.uniform(safety.lower, safety.upper)
            why = self.driver.send(goal)
            if why is None:
                return
            reasons[why] += 1
        self.counts["steps_without_a_safe_command"] += 1
        if set(reasons) == {"no joint state yet"}:
            return  # nothing is refused: the arm has not reported yet (the joint-state watchdog tells)
        where = self.driver.workspace_problem(goal) if reasons["workspace"] else ""
        self.get_logger().warning(
            f"no safe command in {MAX_DRAWS} random draws (refused: {dict(reasons)})"
            + (f"; the last draw put outside the workspace box: {where}" if where else ""),
            throttle_duration_sec=10.0)

    def _follow_suggestion(self, now):
        """Active mode: send scheme_node's suggestion made after the last action. True: sent, or still waiting for
        one (at most ``suggestion_timeout``); False: draw at random instead (none came, counted as a fallback, or it
        was refused)."""
        if self.counts["actions"] == 0:
            return False  # nothing learnt yet, so nothing to suggest: the first command is random
        fresh = self.suggestion is not None and self.suggestion[0] >= self.settled_stamp
        if not fresh:
            self.idle_since = now if self.idle_since is None else self.idle_since
            if now - self.idle_since < self.suggestion_timeout:
                return True  # keep waiting
            self.counts["fallbacks"] += 1
            self.idle_since = None
            return False
        self.idle_since = None
        command, self.suggestion = self.suggestion[1], None
        if self.driver.send(command) is None:
            self.counts["suggestions_followed"] += 1
            return True
        self.counts["suggestions_refused"] += 1
        return False

    def _preflight_passed(self, now):
        """Run the pre-flight checks (module docstring); log each failing one, once every 5 s."""
        facts = self._facts
        facts.joint_state_age, facts.joint_state_problem = self.driver.joint_state_age(), \
            self.driver.joint_state_problem
        facts.controller_subscribers = self.driver.pub_trajectory.get_subscription_count()
        facts.camera_age = None if self.last_camera is None else now - self.last_camera
        facts.camera_info, facts.seen_markers = self.camera_info, self.seen_markers
        fresh = self.joint_state_timeout or self.camera_timeout or 3.0
        self.preflight = [line for _, line in preflight_failures(facts, fresh, self.preflight_skip)]
        if self.preflight:
            self.counts["preflight_waits"] += 1
            if self._preflight_logged is None or now - self._preflight_logged >= PREFLIGHT_LOG_PERIOD:
                self._preflight_logged = now
                for line in self.preflight:
                    self.get_logger().warn(f"pre-flight: {line}")
            return False
        skipped = f" (skipped: {list(self.preflight_skip)})" if self.preflight_skip else ""
        self.get_logger().info(f"pre-flight passed: {', '.join(c for c in CHECKS if c not in self.preflight_skip)}"
                               f"{skipped}; babbling starts")
        unseen = unseen_markers(facts) if "markers" not in self.preflight_skip else []
        if unseen:
            self.get_logger().warn(f"pre-flight: markers {unseen} not seen at the start posture; each must face the "
                                   f"camera in other postures (scheme_node's /diagnostics shows what it learns)")
        return True

    def _quiet(self, now):
        """Why babbling must stop because the camera or the joint states went quiet, or "".

        The camera's silence counts at rest only, summed over the rests since its last message: a simulated camera
        takes no picture while the arm moves, and a move at a low ``max_velocity`` outlasts ``camera_timeout`` (the
        collision screen and the joint-state watchdog guard the move itself); a dead camera still stops babbling
        with rests shorter than ``camera_timeout`` (``wait_for_frame`` off, a short ``dwell``)."""
        if self.judged_at is not None and self.driver.goal is not None:  # moving since then (or the last message)
            since = self.judged_at if self.last_camera is None else max(self.judged_at, self.last_camera)
            self.moved_since_camera += max(0.0, now - since)
        self.judged_at = now
        if self.camera_timeout > 0:
            quiet_since = self.last_camera if self.last_camera is not None else self.started
            silence = now - quiet_since - self.moved_since_camera
            if silence > self.camera_timeout:
                return f"the camera is quiet: nothing on the camera topic for {silence:.1f} s at rest"
        age = self.driver.joint_state_age()
        if self.joint_state_timeout > 0 and age is not None and age > self.joint_state_timeout:
            refused = self.driver.joint_state_problem
            return f"the joint states are quiet: none usable for {age:.1f} s" + (
                f" (the last refused: {refused})" if refused else "")
        return ""

    def _publish_diagnostics(self):
        level = {"stopped": DiagnosticStatus.ERROR if self.stop_reason != "stop requested" else DiagnosticStatus.WARN,
                 "paused": DiagnosticStatus.WARN, "waiting": DiagnosticStatus.WARN}.get(self.state,
                                                                                      DiagnosticStatus.OK)
        message = self.state + (f": {self.stop_reason}" if self.stop_reason else "")
        if self.state == "waiting" and self.preflight:
            message += " (pre-flight: " + "; ".join(self.preflight) + ")"
        values = dict(state=self.state, **self.counts, **{f"driver.{k}": v for k, v in self.driver.counts.items()})
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        name = self.get_fully_qualified_name()
        array.status.append(conversions.diagnostic_status(f"{name}: babbling", level, message, values, name))
        self.pub_diagnostics.publish(array)

    def destroy_node(self):
        self.driver.close()
        super().destroy_node()


def main(args=None):
    return run_node(BabbleNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
