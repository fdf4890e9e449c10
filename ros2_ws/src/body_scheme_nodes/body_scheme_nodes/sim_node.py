"""sim_node: a simulated arm with ArUco markers seen by a fixed camera; executes joint commands or babbles, or
stands in for a real arm's ``JointTrajectoryController``.

Subscriptions
-------------
joint_commands : sensor_msgs/JointState  (reliable, depth 10)
    Commanded joint positions by joint name. Only the newest pending command is executed (older ones are counted
    as superseded). Ignored while babbling (counted), executed once ``babbling_steps`` commands were babbled.
<controller>/joint_trajectory : trajectory_msgs/JointTrajectory  (reliable, depth 10)
    As a ros2_control ``JointTrajectoryController``: the arm moves from where it is through the points over their
    ``time_from_start``, by cubics where the points give velocities, else by straight lines; joints not named hold;
    an empty trajectory is rejected, as Jazzy's controller does. While it moves no picture is taken; at rest, one
    every ``camera_period``, from the moment a publisher of trajectories appears (a pre-flight sees the camera).
    From the first trajectory on, ``joint_commands`` is the action signal of whoever sends them and is no longer
    executed.

Publishers
----------
joint_commands : sensor_msgs/JointState  (reliable, depth 100; babbling mode only)
    The babbling commands, stamped at command time.
camera/image_raw : sensor_msgs/Image  (reliable, depth 5, volatile; perception_mode "rendered")
    ``image_encoding`` mono8 (default) or rgb8, after each executed command, stamped when it was taken (>= the
    command's stamp).
camera/camera_info : sensor_msgs/CameraInfo  (as the images; perception_mode "rendered")
    With each image, same header.
observations : body_scheme_msgs/MarkerPoses  (reliable, depth 100; perception_mode "noise")
    Visible markers' true poses with noise and random dropout, ``camera2marker``.
ground_truth/marker_poses : body_scheme_msgs/MarkerPoses  (reliable, depth 100)
    True pose of every marker after each command, same stamp as the image or observations. Evaluation only.
/joint_states : sensor_msgs/JointState  (depth 10)
    The joints' positions (as executed: clipped, blocked joints held) every ``joint_state_period``.

Subscriptions (babbling with ``max_in_flight`` > 0)
---------------------------------------------------
body_scheme/progress : std_msgs/UInt64  (reliable, transient local, depth 1)
    scheme_node's count of observation messages decided: babbling waits for its first value, then for it to keep up
    (as bag_replay's rate 0 does).

Services
--------
~/inject_fault : body_scheme_msgs/InjectFault
    Block a joint, deform a limb, displace a marker, or repair.

Parameters
----------
robot : string "powercube_6dof"      shipped robot name or URDF path
markers_path : string ""             marker placement file ("" = shipped / next to the URDF)
package_path : string[] []           directories searched first for package:// meshes
frame_id : string "camera"           frame of images, observations and ground truth (camera optical frame)
camera.width, camera.height : int 640, 480
camera.fx, camera.fy, camera.cx, camera.cy : double   default Camera() intrinsics (60 deg horizontal FOV)
camera.xyz, camera.rpy : double[3]   camera optical frame pose in the world (URDF rpy); default Camera() pose
perception_mode : string "rendered"  "rendered" (images) or "noise" (noisy ground truth on observations)
sigma_trans : double 0.044 m, sigma_rot : double 0.2618 rad, visibility : double 1.0   noise mode settings
seed : int 0                         seed of babbling and noise
babbling : bool false                publish and execute own random commands
babbling_period : double 0.2 s       time between babbling commands
babbling_steps : int 0               stop babbling after this many commands and execute joint_commands (0: never)
wait_for_subscribers : int 0         babble only once joint_commands has this many subscriptions and the image (or
                                     observations) and ground-truth topics one each, then 1 s more: messages sent
                                     before discovery matched them are lost (volatile QoS)
max_in_flight : int 0                babbling: the next command waits while this many of its pictures are not
                                     yet decided by scheme_node (body_scheme/progress); a simulator's way to have
                                     every command learnt on a busy machine (a real arm waits for no one). 0: never
in_flight_timeout : double 1.0 s     max_in_flight: after this long without progress the pictures in flight count as
                                     lost (a tracker drops those it has no time for) and babbling goes on
markers_of_interest : int[] []       markers that must be visible in babbled configurations
fault_schedule : string[] []         "step:kind:args" entries (core world.faults); steps count executed commands
update_period : double 0.01 s        period of the timer executing subscribed commands
controller : string "joint_trajectory_controller"   trajectories arrive on <controller>/joint_trajectory
joint_state_period : double 0.02 s   period of /joint_states
camera_period : double 0.2 s         trajectory mode: time between pictures while the arm is at rest
"""

from __future__ import annotations

import threading
import time
from collections import Counter

import cv2
import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.interpolate import CubicHermiteSpline, make_interp_spline
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import UInt64
from trajectory_msgs.msg import JointTrajectory

from body_scheme_core.errors import BodySchemeError, InvalidInputError
from body_scheme_core.world import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS, ObservationModel, babble, parse_fault_schedule
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_msgs.srv import InjectFault
from body_scheme_sim.babbling import babbling_screen
from body_scheme_sim.camera import CAMERA_KEYS, Camera, camera_from_values, camera_parameters
from body_scheme_sim.world import SimWorld

from . import conversions
from .in_flight import InFlight
from .qos import LATCHED
from .ros_parameters import declare_list_parameter, refuse_parameter_changes
from .spin import run_node

PERCEPTION_MODES = ("rendered", "noise")
#: Images are offered reliably: best-effort (sensor data QoS) subscribers still match, and reliable ones get every
#: frame. Frame size matters as much: Fast DDS moves messages up to its 512 KB shared-memory segment through shared
#: memory, larger ones as fragmented UDP, which on loopback loses frames (best effort) or, reliable, starves the
#: node's other topics. A 640x480 mono8 frame (300 KB) stays in shared memory; rgb8 (900 KB) does not.
IMAGE_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)


def camera_from_parameters(node, prefix="camera."):
    """Declare the camera parameters (defaults: :class:`Camera`'s) and build the camera from their values."""
    default = camera_parameters(Camera())["camera"]
    values = {name: node.declare_parameter(prefix + name, default[name]).value for name in CAMERA_KEYS}
    try:
        return camera_from_values(values)
    except (TypeError, ValueError) as error:
        raise InvalidInputError(f"{prefix}* parameters: {error}") from None


class SimNode(Node):
    """ROS wrapper of :class:`body_scheme_sim.world.SimWorld` (see the module docstring)."""

    def __init__(self, **node_options):
        super().__init__("sim_node", **node_options)
        robot = self.declare_parameter("robot", "powercube_6dof").value
        markers_path = self.declare_parameter("markers_path", "").value or None
        package_path = declare_list_parameter(self, "package_path", str)
        self.frame_id = self.declare_parameter("frame_id", "camera").value
        camera = camera_from_parameters(self)
        self.mode = self.declare_parameter("perception_mode", "rendered").value
        self.image_encoding = self.declare_parameter("image_encoding", "mono8").value
        self.sigma_trans = self.declare_parameter("sigma_trans", PAPER_SIGMA_TRANS).value
        self.sigma_rot = self.declare_parameter("sigma_rot", PAPER_SIGMA_ROT).value
        self.visibility = self.declare_parameter("visibility", 1.0).value
        seed = self.declare_parameter("seed", 0).value
        self.babbling = self.declare_parameter("babbling", False).value
        babbling_period = self.declare_parameter("babbling_period", 0.2).value
        self.babbling_steps = self.declare_parameter("babbling_steps", 0).value
        self.wait_for_subscribers = self.declare_parameter("wait_for_subscribers", 0).value
        self._ready_at = None  # monotonic time babbling may start, once the subscribers are there
        self.max_in_flight = self.declare_parameter("max_in_flight", 0).value
        self.in_flight_timeout = self.declare_parameter("in_flight_timeout", 1.0).value
        self.in_flight = InFlight()  # max_in_flight: the babbled pictures scheme_node has not decided yet
        self.markers_of_interest = declare_list_parameter(self, "markers_of_interest", int)
        fault_schedule = declare_list_parameter(self, "fault_schedule", str)
        update_period = self.declare_parameter("update_period", 0.01).value
        controller = self.declare_parameter("controller", "joint_trajectory_controller").value
        self.joint_state_period = self.declare_parameter("joint_state_period", 0.02).value
        self.camera_period = self.declare_parameter("camera_period", 0.2).value
        if self.image_encoding not in ("mono8", "rgb8"):
            raise InvalidInputError(f"image_encoding must be mono8 or rgb8, got {self.image_encoding!r}")
        if self.mode not in PERCEPTION_MODES:
            raise InvalidInputError(f"perception_mode must be one of {PERCEPTION_MODES}, got {self.mode!r}")
        if not (babbling_period > 0 and update_period > 0 and self.joint_state_period > 0 and self.camera_period > 0):
            raise InvalidInputError("babbling_period, update_period, joint_state_period and camera_period must be "
                                    "> 0 s")
        if self.babbling_steps < 0:
            raise InvalidInputError(f"babbling_steps must be >= 0, got {self.babbling_steps}")
        if self.max_in_flight < 0:
            raise InvalidInputError(f"max_in_flight must be >= 0, got {self.max_in_flight}")
        if not self.in_flight_timeout > 0:
            raise InvalidInputError(f"in_flight_timeout must be > 0 s, got {self.in_flight_timeout}")
        ObservationModel(self.sigma_trans, self.sigma_rot, self.visibility)  # validates the noise settings now

        self.schedule = parse_fault_schedule(fault_schedule)
        self.rng_babbling, self.rng_noise = np.random.default_rng(seed).spawn(2)
        self.world = SimWorld(robot, camera=camera, markers_path=markers_path, seed=seed,
                              marker_texture=self.mode == "rendered", package_path=package_path)
        for uri in self.world.missing_meshes[:1]:
            self.get_logger().warn(f"{len(self.world.missing_meshes)} mesh(es) of {robot} not found (first: {uri}): "
                                   f"drawn without them; add the package's directory to package_path")
        unknown = sorted(set(self.markers_of_interest) - set(self.world.marker_ids))
        if unknown:
            self.world.close()
            raise InvalidInputError(f"markers_of_interest {unknown} are not markers of {robot}: "
                                    f"{list(self.world.marker_ids)}")
        self.n_executed = 0
        self.n_babbled = 0
        self.last_babbled_stamp = -np.inf
        self.counts = Counter()
        self._pending = None
        self._pending_trajectory = None
        self._motion = None  # (start time s, duration s, path(t) -> positions) of the trajectory being executed
        self._next_frame = None  # trajectory mode: time of the next picture at rest
        self._controller = False  # a trajectory arrived: sim_node acts as a JointTrajectoryController from now on
        self._lock = threading.Lock()

        work = MutuallyExclusiveCallbackGroup()
        if self.babbling:
            self.pub_commands = self.create_publisher(JointState, "joint_commands", 100)
            self.babbling_timer = self.create_timer(babbling_period, self._on_babbling_timer, callback_group=work)
            if self.max_in_flight:  # in the babbling timer's group: one thread at a time updates the count
                self.create_subscription(UInt64, "body_scheme/progress", self._on_progress, LATCHED,
                                         callback_group=work)
        self.create_subscription(JointState, "joint_commands", self._on_command, 10)
        self.sub_trajectory = self.create_subscription(JointTrajectory, f"{controller}/joint_trajectory",
                                                       self._on_trajectory, 10)
        self.pub_joint_states = self.create_publisher(JointState, "/joint_states", 10)
        # Its own group, as a real arm's joint_state_broadcaster is its own process: rendering does not hold it up.
        self.create_timer(self.joint_state_period, self._publish_joint_states,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.create_timer(update_period, self._on_update_timer, callback_group=work)
        if self.mode == "rendered":
            self.pub_image = self.create_publisher(Image, "camera/image_raw", IMAGE_QOS)
            self.pub_info = self.create_publisher(CameraInfo, "camera/camera_info", IMAGE_QOS)
        else:
            self.pub_observations = self.create_publisher(MarkerPoses, "observations", 100)
        self.pub_truth = self.create_publisher(MarkerPoses, "ground_truth/marker_poses", 100)
        self.create_service(InjectFault, "~/inject_fault", self._on_inject_fault, callback_group=work)
        refuse_parameter_changes(self)
        self.get_logger().info(
            f"sim_node ready: {robot}, joints {list(self.world.action_joint_names)}, markers "
            f"{list(self.world.marker_ids)}, {self.mode} perception, "
            f"{'babbling' if self.babbling else 'executing joint_commands'}, {len(self.schedule)} scheduled fault(s)")

    # -- callbacks ------------------------------------------------------------------------------------------------
    def _on_command(self, msg):
        with self._lock:
            if self._controller:
                # Acting as a JointTrajectoryController: joint_commands is the action signal of whoever sends the
                # trajectories (babble_node), not a command.
                self.counts["ignored_as_controller"] += 1
                return
            if self.babbling or conversions.seconds_from_stamp(msg.header.stamp) <= self.last_babbled_stamp:
                self.counts["ignored_while_babbling"] += 1  # our own babbling commands come back here too
                return
            if self._pending is not None:
                self.counts["superseded"] += 1
            self._pending = msg

    def _on_trajectory(self, msg):
        with self._lock:
            self._controller = True
            if self._pending_trajectory is not None:
                self.counts["trajectories_superseded"] += 1
            self._pending_trajectory = msg

    def _on_update_timer(self):
        now = self._now()
        with self._lock:
            msg, self._pending = self._pending, None
            trajectory, self._pending_trajectory = self._pending_trajectory, None
        if trajectory is not None:
            self._start_trajectory(trajectory, now)
        self._move(now)
        if msg is None:
            return
        try:
            stamp, actions = conversions.actions_from_joint_state(msg, self.world.action_joint_names)
        except InvalidInputError as error:
            self.counts["rejected"] += 1
            self.get_logger().warn(f"rejected joint command: {error}", throttle_duration_sec=5.0)
            return
        self._step(actions, stamp)

    def _publish_joint_states(self):
        self.pub_joint_states.publish(conversions.joint_state_msg(self._now(), self.world.action_joint_names,
                                                                  self.world.joint_positions()))

    def _subscribers_ready(self):
        """Whether babbling may start (see ``wait_for_subscribers``; with ``max_in_flight``, once scheme_node's
        progress is known); logs while waiting."""
        if self.max_in_flight > 0 and self.in_flight.progress is None:
            self.get_logger().info("waiting for scheme_node's body_scheme/progress before babbling",
                                   throttle_duration_sec=2.0)
            return False
        if self.wait_for_subscribers <= 0:
            return True
        now = time.monotonic()
        if self._ready_at is None:
            perception = self.pub_image if self.mode == "rendered" else self.pub_observations
            if (self.pub_commands.get_subscription_count() >= self.wait_for_subscribers
                    and perception.get_subscription_count() >= 1 and self.pub_truth.get_subscription_count() >= 1):
                self._ready_at = now + 1.0  # the subscribers' side of the match may lag a little
            else:
                self.get_logger().info("waiting for subscribers before babbling", throttle_duration_sec=2.0)
        return self._ready_at is not None and now >= self._ready_at

    def _on_progress(self, msg):
        self.in_flight.on_progress(msg.data, time.monotonic())

    def _learner_behind(self):
        """``max_in_flight``: whether that many babbled pictures are not yet decided by scheme_node, and it made
        progress within ``in_flight_timeout`` (else those in flight count as lost and babbling goes on)."""
        if self.max_in_flight <= 0:
            return False
        now = time.monotonic()
        if not self.in_flight.started:
            self.in_flight.start(now)
        if self.in_flight.count() < self.max_in_flight:
            return False
        if self.in_flight.stalled_for(now) < self.in_flight_timeout:
            return True
        self.in_flight.count_as_lost(now)
        return False

    def _on_babbling_timer(self):
        if not self._subscribers_ready() or self._learner_behind():
            return
        self._apply_due_faults()
        try:
            screen = babbling_screen(self.world, self.markers_of_interest)
            actions = babble(self.world, 1, self.rng_babbling, screen=screen)[0]
        except BodySchemeError as error:
            self.get_logger().error(f"babbling failed: {error}", throttle_duration_sec=5.0)
            return
        stamp = self._now()
        self.pub_commands.publish(conversions.joint_state_msg(stamp, self.world.action_joint_names, actions))
        self._step(actions, stamp)
        self.n_babbled += 1
        self.in_flight.sent += 1
        if self.babbling_steps and self.n_babbled >= self.babbling_steps:
            with self._lock:
                self.babbling = False
                self.last_babbled_stamp = stamp
            self.babbling_timer.cancel()
            lost = self.in_flight.lost
            waited = f" ({lost} of their pictures never decided by scheme_node)" if self.max_in_flight else ""
            self.get_logger().info(f"babbled {self.n_babbled} commands{waited}: now executing joint_commands")

    def _start_trajectory(self, msg, now):
        """Begin executing a JointTrajectory from where the arm is, as a ``JointTrajectoryController`` does: joints
        it does not name hold; points with velocities are joined by cubics, points without by straight lines; an
        empty trajectory is rejected (a Jazzy controller rejects it too)."""
        names = list(self.world.action_joint_names)
        try:
            if not msg.points:
                raise InvalidInputError("an empty trajectory")
            given = list(msg.joint_names)
            if len(set(given)) != len(given) or not set(given) <= set(names) or not given:
                raise InvalidInputError(f"a trajectory names joints of {names}, each once, got {given}")
            index = [names.index(name) for name in given]
            times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
            if any(len(p.positions) != len(given) for p in msg.points):
                raise InvalidInputError("every trajectory point needs a position per joint")
            cubic = all(len(p.velocities) == len(given) for p in msg.points)
            goals = np.array([p.positions for p in msg.points], dtype=float)
            speeds = np.array([p.velocities for p in msg.points], dtype=float) if cubic else None
            if not (np.all(np.isfinite(goals)) and (speeds is None or np.all(np.isfinite(speeds)))):
                raise InvalidInputError("trajectory positions and velocities must be finite")
            if not (times[0] > 0 and np.all(np.diff(times) > 0)):
                raise InvalidInputError(f"time_from_start must be > 0 and increase, got {times.tolist()}")
        except InvalidInputError as error:
            self.counts["trajectories_rejected"] += 1
            self.get_logger().warn(f"rejected trajectory: {error}", throttle_duration_sec=5.0)
            return
        self._apply_due_faults()
        if self._motion is None:
            start, start_speed = self.world.joint_positions(), np.zeros(len(names))
        else:
            t0, duration, path = self._motion
            start = self._position(now)
            start_speed = path(now - t0, 1) if now - t0 < duration else np.zeros(len(names))
        positions = np.repeat(start[None], len(times) + 1, axis=0)
        positions[1:, index] = goals
        times = np.concatenate([[0.0], times])
        if cubic:
            velocities = np.zeros_like(positions)
            velocities[0] = start_speed
            velocities[1:, index] = speeds
            path = CubicHermiteSpline(times, positions, velocities, axis=0)
        else:
            path = make_interp_spline(times, positions, k=1, axis=0)
        self._motion = (now, times[-1], path)
        self._next_frame = None
        self.counts["trajectories"] += 1

    def _position(self, now):
        t0, duration, path = self._motion
        return path(min(now - t0, duration))

    def _move(self, now):
        """Trajectory mode: follow the trajectory being executed; at rest, take a picture every camera_period."""
        if self._motion is not None:
            self.world.execute(self._position(now))
            if now - self._motion[0] >= self._motion[1]:
                self._motion = None
                self.n_executed += 1
                self._next_frame = now
        elif self._next_frame is not None and now >= self._next_frame:  # at rest
            self._next_frame = now + self.camera_period
            self._publish_frame(now)
        elif self._next_frame is None and not self._controller and not self.babbling \
                and self.sub_trajectory.get_publisher_count() > 0:
            self._next_frame = now  # a trajectory client is there: the camera streams before its first goal too

    # -- the work -------------------------------------------------------------------------------------------------
    def _now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _apply_due_faults(self):
        while self.schedule and self.schedule[0][0] <= self.n_executed:
            step, fault = self.schedule.pop(0)
            try:
                self.world.apply(fault)
                self.get_logger().info(f"scheduled fault '{step}:{fault.entry}' applied before command "
                                       f"{self.n_executed}")
            except BodySchemeError as error:
                self.get_logger().error(f"scheduled fault '{step}:{fault.entry}' failed: {error}")

    def _step(self, actions, command_stamp):
        """Execute one command and publish what the camera sees and the ground truth."""
        self._apply_due_faults()
        self.world.execute(actions)
        self.n_executed += 1
        self._publish_frame(max(self._now(), command_stamp))  # the picture is taken after the command, never before

    def _publish_frame(self, stamp):
        """Publish what the camera sees now, and the ground truth."""
        if self.mode == "rendered":
            rendered = self.world.render()
            if self.image_encoding == "mono8":
                rendered = cv2.cvtColor(rendered, cv2.COLOR_RGB2GRAY)
            image = conversions.image_msg(stamp, self.frame_id, rendered)
            camera = self.world.camera
            info = conversions.camera_info_msg(stamp, self.frame_id, camera.width, camera.height, camera.K)
            info.header = image.header
            self.pub_image.publish(image)
            self.pub_info.publish(info)
        else:
            observed = self.world.observe_noisy(self.sigma_trans, self.sigma_rot, self.visibility, self.rng_noise)
            self.pub_observations.publish(conversions.marker_poses_msg(stamp, self.frame_id, observed))
        self.pub_truth.publish(conversions.marker_poses_msg(stamp, self.frame_id, self.world.true_marker_poses()))

    def _on_inject_fault(self, request, response):
        try:
            fault = conversions.fault_from_request(request)
            self.world.apply(fault)
        except BodySchemeError as error:
            response.success, response.message = False, f"{request.kind} refused: {error}"
        else:
            response.success = True
            response.message = f"{fault.kind} applied; active faults: {[f.kind for f in self.world.faults]}"
            self.get_logger().info(f"fault injected: {fault.entry}")
        return response

    def destroy_node(self):
        self.world.close()
        super().destroy_node()


def main(args=None):
    return run_node(SimNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
