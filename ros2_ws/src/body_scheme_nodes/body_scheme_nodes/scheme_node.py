"""scheme_node: maintains the body scheme from joint commands and marker observations.

Subscriptions
-------------
joint_commands : sensor_msgs/JointState
    The action signals (commanded joint angles), in ``joint_names`` order.
observations : body_scheme_msgs/MarkerPoses
    Marker poses from the tracker, in the camera frame.
body_scheme/explore_near : body_scheme_msgs/ExploreNear
    A request (control_node's, when an IK answer is not sure enough) to explore near a posture: the next
    ``samples`` suggestions are drawn there, then the joint fit runs (body_scheme_nodes.explorer). Every request
    taken is answered; one over ``max_message_bytes`` is refused unread, one lost in DDS is counted.

Publishers
----------
predicted_poses : body_scheme_msgs/MarkerPoses
    Predicted pose of every part (also unobserved ones) for each paired command, with covariance.
body_scheme/structure : body_scheme_msgs/BodySchemeStructure  (transient local)
body_scheme/snapshot : body_scheme_msgs/ModelSnapshot  (transient local)
    The body scheme for control_node: with the structure, and within a second of a joint fit that changed it.
body_scheme/events : body_scheme_msgs/SchemeEvent  (transient local, the latest 100)
/diagnostics : diagnostic_msgs/DiagnosticArray
body_scheme/progress : std_msgs/UInt64  (transient local, the latest)
    Number of observation messages decided so far: learnt, refused or shed (bag_replay's backpressure signal).
body_scheme/markers : visualization_msgs/MarkerArray, body_scheme/poses : geometry_msgs/PoseArray, /tf
    The latest prediction for RViz, Foxglove and tf2 (at most every ``view_period``; see body_scheme_nodes.view).
body_scheme/robot_description : std_msgs/String  (transient local)
    The learned body scheme as URDF (body_scheme_core.prediction.learned_body), republished when it changes.
body_scheme/exploration_command : sensor_msgs/JointState  (``exploration`` true)
    After each learnt sample, the next command to babble (body_scheme_core.control.exploration: a uniform draw while
    bootstrapping, then the posture expected to make the body scheme surest); babble_node's ``mode: active``
    follows it.
body_scheme/explore_near/done : body_scheme_msgs/ExploreNear
    Each request echoed once it is served (``step``: the learner's step after the joint fit, whose snapshot is
    published first) or refused (``outcome``: why; e.g. ``exploration`` false).

Services
--------
~/save, ~/load : body_scheme_msgs/StatePath   (empty path: ``checkpoint_path``; else a file name inside ``state_dir``:
                no absolute paths elsewhere, no ``..``, no symlinks out, regular files of at most
                ``max_state_bytes`` only, and never over a file that is not a body scheme state file)
~/reset : std_srvs/Trigger
~/get_urdf : body_scheme_msgs/GetRobotDescription    the learned URDF now

Parameters
----------
part_ids : int[]  (required)          marker ids of the body parts
joint_names : string[]  (required)    joint names in action-vector order
action_lower, action_upper : double[] joint limits (default +-pi)
frame_id : string "camera"            frame of observations (others refused: wrong_frame; "" is it) and predictions
update_period : double 0.02 s         messages are taken in this often; the learning thread works at least this often
settle_time : 0.0, max_delay : 2.0, pairing_grace : 0.2 (s)   pairing rule, see body_scheme_core.pairing
checkpoint_path : string ""           state file; restored on start if it exists; "" disables checkpoints
checkpoint_period : double 30.0 s
urdf_path, markers_path : string ""   start from the engineered body scheme of this robot (paper Sec. IV-B/C)
                                      instead of bootstrapping; joints map to actions by ``joint_names``
urdf_tolerance_trans : 0.005 m, urdf_tolerance_rot : 0.01745 rad   how far each joint may be from its URDF: markers
                                      with unmarked links between them are joined by the URDF's chain, calibrated
                                      from there (0 for both: the URDF exact)
stamp_tolerance : double 1.0 s        messages stamped further ahead of the node clock are refused (future_stamp)
unstamped_policy : "receipt_time"     zero-stamped messages: stamped with their receipt time (counted as
                                      restamped.unstamped) or, with "reject", refused (unstamped)
stall_timeout : double 10.0 s         commands arriving but no learning step for this long: /diagnostics ERROR
hardware_id : string ""               diagnostics hardware_id ("" = the node's fully qualified name)
tf_prefix : string ""                 prefix of the TF frames and URDF links; joints keep the robot's names
view_period : double 0.1 s            markers, poses and /tf at most this often
exploration : bool false, exploration_candidates : int 64, exploration_travel_weight : double 0.0
                                      suggest the next command (see body_scheme/exploration_command)
exploration_excursions : bool false   while bootstrapping, first each joint alone, then pairs (chains from scratch)
exploration_camera_info : string ""   CameraInfo topic: suggest only postures whose markers are predicted inside
                                      the image, 10 % in from each border ("" = no view constraint)
state_dir : string ""                 directory of ~/save and ~/load names ("" = the checkpoint's directory, else
                                      $ROS_HOME/body_scheme)
max_state_bytes : int 67108864        largest state file ~/load reads
queue_depth : int 1000                depth of the two subscriptions; the executor's thread empties them every
                                      update_period (a message waiting longer than depth messages is lost in DDS)
max_inbox : int 2000, max_pending_samples : int 500, max_sample_age : double 5.0 s
                                      overload: messages and paired samples beyond the bounds are shed oldest
                                      first and counted (shed.*); a sample older than max_sample_age (since DDS
                                      received its message) when its turn comes is shed (shed.stale_samples), so
                                      predictions are at most about max_sample_age plus one learning step late
max_message_bytes : int 1048576, max_joint_names : int 1000, max_markers : int 1000
                                      larger input messages are refused whole (rejected.oversized_message)
service_queue_depth : int 100, max_waiting_requests : int 20
                                      requests are served in a thread of their own, one after the other; at most
                                      max_waiting_requests per service wait, the rest are answered "busy" at once
learner.<field> : one per BodySchemeConfig field (sigma_trans, test_window, ...); thresholds 0.0 = 3 sigma,
                  learner.root -1 = lowest part id
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String, UInt64
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from body_scheme_core.errors import BodySchemeError, ModelFileError
from body_scheme_core.learning import encode_state, load_state, write_state_text
from body_scheme_core.prediction import learned_tree, learned_urdf
from body_scheme_msgs.msg import BodySchemeStructure, MarkerPoses, ModelSnapshot, SchemeEvent
from body_scheme_msgs.srv import GetRobotDescription, StatePath

from . import conversions, scheme_diagnostics, state_files, view
from .checkpoint import Checkpoint, lock_holder
from .explorer import SchemeExplorer
from .intake import BatchIntake, RequestIntake, ServiceWorker
from .learning_loop import LearningLoop
from .message_feed import learn_sample
from .qos import LATCHED, RECENT_EVENTS
from .ros_parameters import refuse_parameter_changes
from .settings import SchemeSettings, parameter_defaults, specification_tree
from .spin import run_node


class SchemeNode(Node):
    """ROS wrapper of :class:`body_scheme_core.learning.learner.BodySchemeLearner` (see the module docstring)."""

    def __init__(self):
        super().__init__("scheme_node")
        # Joint count first: the joint-limit defaults depend on it.
        n_joints = len(self.declare_parameter("joint_names", parameter_defaults()["joint_names"]).value)
        values = {name: self.declare_parameter(name, default).value
                  for name, default in parameter_defaults(n_joints).items() if name != "joint_names"}
        values["joint_names"] = self.get_parameter("joint_names").value
        self.settings = SchemeSettings.from_parameters(values)
        self.joint_names = list(self.settings.joint_names)
        self.frame_id = self.settings.frame_id
        # Refuses a directory and a checkpoint another node holds (CheckpointError: one FATAL line, exit 1).
        self.checkpoint = Checkpoint(self.settings.checkpoint_path) if self.settings.checkpoint_path else None
        if self.checkpoint is not None and self.checkpoint.removed_orphans:
            self.get_logger().warn(f"removed temporary files a killed save left: {self.checkpoint.removed_orphans}")
        self.learner = self._restore_or_create()
        # The robot's specification, if given: the learned URDF keeps its unmarked links' frames and names.
        self._specification = specification_tree(self.settings.urdf_path, self.settings.markers_path,
                                                 self.joint_names, self.settings.part_ids) \
            if self.settings.urdf_path else None
        self.rejected = Counter()
        self.event_counts = Counter()
        self.latency = deque(maxlen=200)
        # Inbox, stamp policy, pairing, waiting samples and shedding (ROS-free). The learning thread works on it
        # under _learner_lock, which /diagnostics (the executor's thread) takes to read the learner and the counters.
        self.loop = LearningLoop(self.settings, self._now, self._learn, self._reject)
        self._learner_lock = threading.Lock()  # the learner between the learning thread and the executor's

        depth, max_bytes = self.settings.queue_depth, self.settings.max_message_bytes
        self._intake = {"command": BatchIntake(self, JointState, "joint_commands", depth, max_bytes),
                        "observations": BatchIntake(self, MarkerPoses, "observations", depth, max_bytes)}
        self.pub_predicted = self.create_publisher(MarkerPoses, "predicted_poses", 10)
        self.pub_structure = self.create_publisher(BodySchemeStructure, "body_scheme/structure", LATCHED)
        self.pub_snapshot = self.create_publisher(ModelSnapshot, "body_scheme/snapshot", LATCHED)
        self.pub_events = self.create_publisher(SchemeEvent, "body_scheme/events", RECENT_EVENTS)
        self.explorer = SchemeExplorer(self, self.settings, self.learner.config.prior_sigma_trans / math.sqrt(3.0),
                                       self._publish_snapshot)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.pub_progress = self.create_publisher(UInt64, "body_scheme/progress", LATCHED)  # a late joiner: the count
        self.pub_markers = self.create_publisher(MarkerArray, "body_scheme/markers", 10)
        self.pub_poses = self.create_publisher(PoseArray, "body_scheme/poses", 10)
        self.pub_tf = self.create_publisher(TFMessage, "/tf", 100)
        self.pub_description = self.create_publisher(String, "body_scheme/robot_description", LATCHED)
        self._last_view = -float("inf")
        self._last_description = None
        self._recent_events = {}  # child part -> (kind, node time) of the latest replacement or reinstatement
        self._last_progress = None
        depth = self.settings.service_queue_depth
        self._service_worker = ServiceWorker(
            {name: (RequestIntake(self, srv_type, f"~/{name}", depth), handler) for name, srv_type, handler in (
                ("save", StatePath, self._on_save), ("load", StatePath, self._on_load),
                ("reset", Trigger, self._on_reset), ("get_urdf", GetRobotDescription, self._on_get_urdf))},
            self.settings.max_waiting_requests,
            lambda name, limit: f"busy: {limit} ~/{name} requests are waiting already (max_waiting_requests); call "
                                f"again",
            self.get_logger().error)
        self.create_timer(self.settings.update_period, self._take_messages)
        self.create_timer(self.settings.update_period, self._service_worker.take)
        self.create_timer(1.0, self._publish_diagnostics)
        if self.checkpoint is not None:
            self.create_timer(self.settings.checkpoint_period, self._checkpoint)
        self._last_structure_key = None
        self._snapshot_fit = None  # the learner's fitted_at when the last snapshot was published
        refuse_parameter_changes(self)
        self._publish_structure(force=True)
        # Learning runs in a thread of its own, not in an executor callback: the executor's thread only takes
        # messages in, answers services and keeps diagnostics and checkpoints going, whatever a learning step costs.
        self._failure = None
        self._failed = self.create_guard_condition(self._raise_failure)
        self.loop.start(self._learner_lock, self._on_learning_failure, self._publish_progress)
        self.get_logger().info(
            f"scheme_node ready: parts {list(self.settings.part_ids)}, joints {self.joint_names}, "
            f"phase {self.learner.phase}")

    # -- set-up -------------------------------------------------------------------------------------------------
    def _restore_or_create(self):
        """The checkpoint's learner if it loads and is of this robot; otherwise the file is moved aside (never
        overwritten: a newer version's state survives a rollback) and learning starts afresh."""
        if self.checkpoint is None:
            return self.settings.new_learner()
        learner, problem = self.checkpoint.restore(self._load_own, self.settings.max_state_bytes)
        if learner is not None:
            self.get_logger().info(f"restored checkpoint {self.checkpoint.path} at step {learner.step}")
            return learner
        if problem is not None:
            self.get_logger().error(f"checkpoint {self.checkpoint.path} not used: {problem}")
            if self.checkpoint.exists():  # not moved aside: never overwrite it
                self.get_logger().error("checkpoints are off so that it is not overwritten")
                self.checkpoint.close()
                self.checkpoint = None
        return self.settings.new_learner()

    def _load_own(self, path):
        """The learner of a state file, if it is of this node's robot (else ModelFileError)."""
        learner = load_state(path)
        problem = self._foreign(learner)
        if problem is not None:
            raise ModelFileError(problem)
        return learner

    def _foreign(self, learner):
        """Why a loaded learner is not of this node's robot (other parts or joint count), or None."""
        if sorted(learner.part_ids) != sorted(self.settings.part_ids) or learner.n_actions != len(self.joint_names):
            return (f"it is another robot's state: parts {sorted(learner.part_ids)} and {learner.n_actions} "
                    f"actions, this node has parts {sorted(self.settings.part_ids)} and {len(self.joint_names)} joints")
        return None

    # -- intake: the executor's thread takes messages in every update_period --------------------------------------
    def _take_messages(self):
        """Move every waiting message into the inbox for the learning thread; beyond ``max_inbox`` the oldest are
        shed and counted."""
        now, wall = self._now(), time.time()
        # Both topics in the order DDS received them (as callbacks would have seen them), with receipt times on the
        # node clock: the wait in the queue counts towards a sample's age.
        self.explorer.take_requests()
        batch = [(now - max(0.0, wall - received), kind, msg) for received, kind, msg in sorted(
            ((received, kind, msg) for kind, intake in self._intake.items() for msg, received in intake.take()),
            key=lambda item: item[0])]
        # Larger than max_message_bytes: never deserialized. Counts of joints and markers are checked by
        # feed_message, on the path the offline replay shares, before any conversion.
        refused = []
        for kind, intake in self._intake.items():
            for size in intake.take_refused():
                refused.append(kind)
                self.get_logger().warn(f"rejected input (oversized_message): {size} byte message on {kind} "
                                       f"(max_message_bytes {self.settings.max_message_bytes})",
                                       throttle_duration_sec=5.0)
        self.loop.put(batch, refused)

    def _now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    # -- the learning thread (LearningLoop.start) -----------------------------------------------------------------
    def _on_learning_failure(self, error):
        self._failure = error
        self._failed.trigger()  # the executor raises it

    def _raise_failure(self):
        raise RuntimeError("the learning thread failed") from self._failure

    def destroy_node(self):
        self.loop.stop()
        self._service_worker.stop()
        if self.checkpoint is not None:
            self.checkpoint.close()
        super().destroy_node()

    def _publish_progress(self):
        """After each step of the learning thread: the replay's progress count, when it changed."""
        progress = self.loop.progress()
        if progress != self._last_progress:
            self._last_progress = progress
            self.pub_progress.publish(UInt64(data=progress))

    def _learn(self, stamp, actions, observed):
        """Learn one sample and publish what came of it; False if the learner refused it (LearningLoop's ``learn``)."""
        start = time.perf_counter()
        events, rejection = learn_sample(self.learner, stamp, actions, observed)
        if rejection is not None:
            self._reject(*rejection)
            return False
        self.latency.append(time.perf_counter() - start)
        events = events + self.explorer.after_learning(self.learner, stamp, actions)
        for event in events:
            self.event_counts[event.kind] += 1
            self.pub_events.publish(conversions.event_msg(stamp, event))
            if event.kind in ("model_replaced", "model_reinstated") and event.child is not None:
                self._recent_events[event.child] = (event.kind, self._now())
            if event.kind != "input_rejected":
                self.get_logger().info(f"[step {event.step}] {event.kind}: {event.reason}")
        edges = self.learner.edge_status()
        if self.learner.body_scheme is not None:
            poses, std = self.learner.predict(actions, return_std=True)
            self.pub_predicted.publish(conversions.marker_poses_msg(stamp, self.frame_id, poses, std))
            self._publish_view(stamp, poses, std, observed.poses, edges)
        self._publish_structure(edges=edges)
        return True

    def _publish_view(self, stamp, poses, std, observations, edges):
        """Markers, PoseArray and /tf of a prediction, at most every ``view_period`` (body_scheme_nodes.view)."""
        now = self._now()
        if now - self._last_view < self.settings.view_period:
            return
        self._last_view = now
        recent = {child: kind for child, (kind, when) in self._recent_events.items() if now - when < 5.0}
        self.pub_markers.publish(view.markers_msg(stamp, self.frame_id, poses, std, edges, observations, recent))
        self.pub_poses.publish(view.pose_array_msg(stamp, self.frame_id, poses))
        self.pub_tf.publish(view.tf_msg(stamp, self.frame_id, poses, self.settings.tf_prefix))

    def _learned_body(self):
        """The body scheme as a kinematic tree (body_scheme_core.prediction.learned_body), or None if there is none."""
        scheme = self.learner.body_scheme
        if scheme is None:
            return None
        lower, upper = self.learner.trained_range()
        return learned_tree(scheme, self.joint_names, lower, upper, prefix=self.settings.tf_prefix,
                            nominal=self._specification)

    def _publish_description(self):
        body = self._learned_body()
        if body is None:
            return
        text = learned_urdf(body)
        if text != self._last_description:
            self._last_description = text
            self.pub_description.publish(String(data=text))

    def _reject(self, code, detail):
        """Count a rejected input under a stable reason code (reported on /diagnostics) and log it, throttled."""
        self.rejected[code] += 1
        self.get_logger().warn(f"rejected input ({code}): {detail}", throttle_duration_sec=5.0)

    def _publish_structure(self, force=False, edges=None):
        learner = self.learner
        edges = learner.edge_status() if edges is None else edges
        key = tuple((e["parent"], e["child"], e["model"], e["valid"]) for e in edges) + (learner.phase,)
        if not force and key == self._last_structure_key:
            return
        self._last_structure_key = key
        stamp = self.get_clock().now().nanoseconds * 1e-9
        self.pub_structure.publish(conversions.structure_msg(
            stamp, learner.step, learner.phase, learner.root, learner.part_ids, edges))
        self._publish_snapshot()

    def _publish_snapshot(self):
        """The body scheme for control_node: with the structure, after the joint fit that ends an exploration near a
        posture, and once a second when a joint fit changed it (:meth:`_publish_refit`)."""
        learner = self.learner
        self._snapshot_fit = learner.fitted_at
        self.pub_snapshot.publish(conversions.snapshot_msg(
            self.get_clock().now().nanoseconds * 1e-9, self.frame_id, learner.step, learner.body_scheme,
            self.joint_names, self.settings.action_lower, self.settings.action_upper, learner.root_pose))

    def _publish_refit(self):
        """The snapshot again if a joint fit ran since the last one was published."""
        if self.learner.fitted_at != self._snapshot_fit:
            self._publish_snapshot()

    def _publish_diagnostics(self):
        with self._learner_lock:
            self._publish_diagnostics_locked()
            self._publish_description()
            self._publish_refit()

    def _publish_diagnostics_locked(self):
        learner = self.learner
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        edges = learner.edge_status()
        level, message = scheme_diagnostics.scheme_level(learner, edges, self._stalled_for())
        loop = self.loop
        explored_rejected, explored = self.explorer.diagnostics()
        rejected = (Counter(self.rejected) + Counter(loop.pairer.rejected) + Counter(learner.rejected)
                    + loop.intake_counts() + explored_rejected)
        values = scheme_diagnostics.learner_values(learner, edges, self.latency, loop.lag)
        values["rejected_total"] = sum(rejected.values())
        received, shed, inbox = loop.intake_snapshot()
        # Events are cumulative, so a mismatch that was repaired between two diagnostics messages still shows.
        values.update(scheme_diagnostics.counter_values({
            "rejected": rejected, "events": {k: n for k, n in self.event_counts.items() if k != "input_rejected"},
            "restamped": loop.restamped, "shed": shed, "received": received,
            "corrected": learner.corrected}))
        for kind, intake in self._intake.items():  # inside DDS, before the node saw them (body_scheme_nodes.intake)
            values[f"lost.{kind}_messages"] = intake.lost
            values[f"lost.{kind}_full_queue_takes"] = intake.full_queue_takes
        values.update(scheme_diagnostics.counter_values({"services": self._service_worker.counters()}))
        values["inbox"] = inbox  # received, not yet taken in by the learning thread
        values["pending_samples"] = len(loop.pending)
        values["pairing_waiting"] = loop.pairer.waiting  # observations waiting for their command
        values.update(explored)
        name = self.get_fully_qualified_name()
        hardware_id = self.settings.hardware_id or name
        array.status.append(conversions.diagnostic_status(scheme_diagnostics.status_name(name), level, message,
                                                          values, hardware_id))
        array.status.extend(scheme_diagnostics.edge_statuses(name, edges, hardware_id))
        self.pub_diagnostics.publish(array)

    def _stalled_for(self):
        """Seconds over which commands kept arriving with nothing learnt, if beyond ``stall_timeout``; else None
        (:meth:`LearningLoop.stalled_for`: observations alone, while the arm stands, are not a stall)."""
        since = self.loop.stalled_for()
        return since if since > self.settings.stall_timeout else None

    # -- services ------------------------------------------------------------------------------------------------
    def _on_save(self, request, response):
        """Save to ``checkpoint_path`` (empty request) or to a name inside the state directory (state_files)."""
        try:
            if request.path:
                path = state_files.resolve(self.settings.state_directory, request.path)
                own = self.checkpoint is not None and path == self.checkpoint.path
                holder = None if own else lock_holder(path)
                if holder is not None:
                    raise state_files.StateFileError(f"{path.name!r} is the checkpoint of a running node (pid "
                                                     f"{holder}); not overwritten")
                state_files.check_overwritable(path)
                path.parent.mkdir(parents=True, exist_ok=True)
            elif self.checkpoint is not None:
                path = self.checkpoint.path
            else:
                raise state_files.StateFileError("no file name given and checkpoint_path is empty")
            with self._learner_lock:  # the learner is read under the lock; the file is written after
                text, step = encode_state(self.learner, path), self.learner.step
            write_state_text(text, path)
            response.success, response.message = True, f"saved step {step} to {path}"
        except state_files.StateFileError as error:
            response.success, response.message = False, f"save refused: {error}"
        except (OSError, BodySchemeError) as error:
            response.success, response.message = False, f"save failed: {getattr(error, 'strerror', None) or error}"
        return response

    def _on_load(self, request, response):
        """Load from ``checkpoint_path`` (empty request) or a name inside the state directory (state_files)."""
        try:
            if request.path:
                path = state_files.resolve(self.settings.state_directory, request.path)
            elif self.checkpoint is not None:
                path = self.checkpoint.path
            else:
                raise state_files.StateFileError("no file name given and checkpoint_path is empty")
            state_files.check_loadable(path, self.settings.max_state_bytes)
            learner = self._load_own(path)
        except Exception as error:  # an untrusted file: refused in the reply, never a crash
            response.success, response.message = False, f"load failed: {error}"
            return response
        with self._learner_lock:
            self.learner = learner
            self.explorer.cancel(learner.step, f"the learner was loaded from {path}")
            self._publish_structure(force=True)
        response.success, response.message = True, f"loaded step {learner.step} from {path}"
        return response

    def _on_get_urdf(self, request, response):
        with self._learner_lock:
            body, phase, step = self._learned_body(), self.learner.phase, self.learner.step
        if body is None:
            response.success, response.message = False, f"no body scheme yet ({phase})"
            return response
        response.success, response.urdf = True, learned_urdf(body)
        response.message = f"learned body scheme at step {step}" + (
            f"; {len(body.notes)} note(s): " + " | ".join(body.notes) if body.notes else "")
        return response

    def _on_reset(self, request, response):
        with self._learner_lock:
            self.learner = self.settings.new_learner()
            self.explorer.cancel(0, "the learner was reset")
            self._publish_structure(force=True)
        response.success, response.message = True, "learner reset: bootstrapping from scratch"
        return response

    def _checkpoint(self):
        if self.checkpoint is None:
            return
        try:
            with self._learner_lock:  # learning waits for the encoding only, not for the disk
                text = encode_state(self.learner, self.checkpoint.path)
            self.checkpoint.write(text)
        except (OSError, BodySchemeError, ValueError) as error:
            self.get_logger().error(f"checkpoint to {self.checkpoint.path} failed: {error}")


def main(args=None):
    return run_node(SchemeNode, args, threads=1)  # the executor's thread; learning has a thread of its own


if __name__ == "__main__":
    raise SystemExit(main())
