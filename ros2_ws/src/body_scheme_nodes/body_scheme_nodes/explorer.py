"""scheme_node's active exploration (body_scheme_core.control.exploration) over topics.

After each learnt sample, :meth:`SchemeExplorer.after_learning` publishes the next command to babble on
``body_scheme/exploration_command``, within the camera's view once a CameraInfo arrived. A request on
``body_scheme/explore_near`` (control_node, when an IK answer is not sure enough) turns the next ``samples``
suggestions towards its posture (:class:`~body_scheme_core.control.exploration.NearFocus`); once the last of them is
learnt, the joint fit runs, the body scheme snapshot is published and the request is answered on
``body_scheme/explore_near/done``. A request that cannot be served is answered at once with the reason: with
exploration off, or with joints or values it cannot take (those are counted, ``rejected.bad_explore_near``); an answer
echoes the request's header, and its joints and positions only when it was served. Requests are taken in batches by
scheme_node's intake timer (:meth:`SchemeExplorer.take_requests`): every request taken is answered, one larger than
``max_message_bytes`` is refused unread (``rejected.oversized_message``) and one DDS overwrote in a flood is counted
(``lost.explore_near_messages``). A CameraInfo must describe a camera that can exist
(:func:`~body_scheme_nodes.conversions.camera_from_info`; else ``rejected.bad_camera_info``).

The ``samples`` are the next samples learnt after the suggestions near the posture; a command babble_node drew at
random when a suggestion came late (or anyone else's command) counts among them. A reset or a load of the learner
cancels an exploration under way (answered "cancelled: ...").
"""

from __future__ import annotations

import math
import threading
from collections import Counter

from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, JointState

from body_scheme_core.control import ExplorationPolicy, NearFocus, in_camera_view
from body_scheme_core.errors import BodySchemeError
from body_scheme_msgs.msg import ExploreNear

from . import conversions
from .intake import BatchIntake, create_sized_subscription

#: Fraction of the image's width and height kept clear at each border by the exploration's view constraint.
VIEW_MARGIN = 0.1
#: Draws in a row near a posture that find no feasible candidate before its request is refused.
MAX_MISSES = 3


class SchemeExplorer:
    """The exploration topics of scheme_node ``node``: its ``settings`` (SchemeSettings), the camera's positional noise
    per axis (m) to assume until the learner has its own estimate, and ``publish_snapshot()``, called after the joint
    fit that ends an exploration near a posture."""

    def __init__(self, node, settings, noise, publish_snapshot):
        self.node, self.joint_names, self.publish_snapshot = node, list(settings.joint_names), publish_snapshot
        self.policy = None
        self.camera = None  # (K, width, height) of the last valid CameraInfo
        self.rejected = Counter()  # bad_camera_info, bad_explore_near: by the executor's thread under _lock
        self.counts = Counter()  # near_requests, near_answered: by either thread under _lock
        self._lock = threading.Lock()
        self._requested = None  # (request, NearFocus) not taken up by the learning thread yet
        self._focus = None  # (request, NearFocus) being explored
        self._to_finish = None  # (request, NearFocus) whose last sample is the next one learnt
        self._misses = 0  # draws in a row near the focus that found no feasible candidate
        if settings.exploration:
            self.policy = ExplorationPolicy(settings.action_lower, settings.action_upper,
                                            settings.exploration_candidates,
                                            travel_weight=settings.exploration_travel_weight,
                                            noise=noise, excursions=settings.exploration_excursions)
            self.pub_command = node.create_publisher(JointState, "body_scheme/exploration_command", 10)
            if settings.exploration_camera_info:
                create_sized_subscription(  # best effort: matches either publisher
                    node, CameraInfo, settings.exploration_camera_info, self._on_camera_info, qos_profile_sensor_data,
                    settings.max_message_bytes, lambda size: self._refuse("oversized_message", f"{size} byte "
                                                                                              f"CameraInfo"))
        elif settings.exploration_camera_info:
            node.get_logger().warn("exploration_camera_info is set but exploration is false: it is ignored")
        self.pub_done = node.create_publisher(ExploreNear, "body_scheme/explore_near/done", 10)
        self.requests = BatchIntake(node, ExploreNear, "body_scheme/explore_near", settings.service_queue_depth,
                                    settings.max_message_bytes)

    # -- the executor's thread ---------------------------------------------------------------------------------------
    def _on_camera_info(self, msg):
        """Keep the camera's intrinsics and image size for the view constraint; a camera that cannot exist
        (uncalibrated, an empty or 1 x 1 image, a focal length of 1e300) is counted (``rejected.bad_camera_info``) and
        ignored: the last good one stays."""
        try:
            self.camera = conversions.camera_from_info(msg)
        except BodySchemeError as exc:
            self._refuse("bad_camera_info", exc)

    def take_requests(self):
        """Take the waiting ExploreNear requests (the executor's thread, every ``update_period``); see the module
        docstring."""
        for msg, _ in self.requests.take():
            self._on_explore_near(msg)
        for size in self.requests.take_refused():
            self._refuse("oversized_message", f"{size} byte ExploreNear request")

    def _on_explore_near(self, msg):
        """Take a request up (a newer one replaces it until the learning thread takes it), or answer why not."""
        with self._lock:
            self.counts["near_requests"] += 1
        if self.policy is None:
            self._answer(msg, 0, "refused: exploration is false on this scheme_node (set exploration: true)")
            return
        try:
            _, actions = conversions.actions_from_joint_state(
                JointState(name=list(msg.joint_names), position=list(msg.positions)), self.joint_names)
            focus = NearFocus(actions, int(msg.samples), msg.radius)
        except BodySchemeError as exc:
            self._refuse("bad_explore_near", exc)
            self._answer(msg, 0, f"refused: {conversions.brief(str(exc))}")
            return
        with self._lock:
            replaced, self._requested = self._requested, (msg, focus)
        if replaced is not None:
            self._answer(replaced[0], 0, "replaced by a newer request before it started")

    def _refuse(self, code, why):
        with self._lock:
            self.rejected[code] += 1
        self.node.get_logger().warn(f"rejected input ({code}): {conversions.brief(str(why))}",
                                    throttle_duration_sec=5.0)

    def _answer(self, request, step, outcome):
        """Publish the answer to ``request``: its header (by which the caller knows it) and the outcome; the
        request's joints and positions only when it was served (``outcome`` ""): a refusal never echoes a request."""
        answer = ExploreNear(header=request.header, samples=request.samples, radius=request.radius, step=int(step),
                             outcome=outcome)
        if not outcome:
            answer.joint_names, answer.positions = list(request.joint_names), list(request.positions)
        with self._lock:
            self.counts["near_answered"] += 1
        self.pub_done.publish(answer)

    # -- the learning thread -----------------------------------------------------------------------------------------
    def after_learning(self, learner, stamp, actions):
        """After the sample at ``actions`` (stamp ``stamp``) was learnt: end an exploration near a posture whose
        last sample this was, then publish the next command (if exploration is on). Returns the learner's events of
        the joint fit that ends it."""
        events = self._finish(learner)
        if self.policy is None:
            return events
        with self._lock:
            requested, self._requested = self._requested, None
        if requested is not None:
            if self._focus is not None:
                self._answer(self._focus[0], learner.step, "replaced by a newer request")
            self._focus, self._misses = requested, 0
        body = learner.body_scheme  # provisional while bootstrapping: good enough for the view, not for the score
        scheme = body if learner.phase != "bootstrapping" else None
        self.policy.noise = learner.noise.sigma_trans / math.sqrt(3.0)  # the camera as the learner knows it now
        in_view = None
        camera = self.camera
        if camera is not None and body is not None:
            in_view = in_camera_view(body, learner.root_pose, *camera, margin=VIEW_MARGIN)
        if self._focus is None:
            command = self.policy.suggest(scheme, current=actions, feasible=in_view)
        else:
            request, focus = self._focus
            command = focus.suggest(self.policy, scheme, current=actions, feasible=in_view)
            self._misses = 0 if command is not None else self._misses + 1
            if command is None:  # this time a suggestion from anywhere; after MAX_MISSES in a row, refused
                if self._misses >= MAX_MISSES:
                    self._focus = None
                    self._answer(request, learner.step, f"refused: no feasible posture near it in {MAX_MISSES} "
                                                        "draws (limits, camera view, feasibility callback)")
                command = self.policy.suggest(scheme, current=actions, feasible=in_view)
            elif focus.done:
                self._focus, self._to_finish = None, self._focus
        if command is not None:
            self.pub_command.publish(conversions.joint_state_msg(stamp, self.joint_names, command))
        return events

    def _finish(self, learner):
        """The joint fit after the last sample near a posture, the snapshot, and the answer."""
        if self._to_finish is None:
            return []
        request, self._to_finish = self._to_finish[0], None
        if learner.body_scheme is None:
            self._answer(request, learner.step, "no joint fit: the learner has no body scheme")
            return []
        try:
            events, outcome = learner.recalibrate(), ""
        except BodySchemeError as exc:  # undone by the learner: the body scheme stays as it was
            events, outcome = [], f"the joint fit failed and was undone: {exc}"
        self.publish_snapshot()
        self._answer(request, learner.step, outcome)
        return events

    def cancel(self, step, why):
        """Answer every request taken up or under way with ``"cancelled: " + why`` (the learner was replaced)."""
        with self._lock:
            requested, self._requested = self._requested, None
        for entry in (requested, self._focus, self._to_finish):
            if entry is not None:
                self._answer(entry[0], step, f"cancelled: {why}")
        self._focus = self._to_finish = None

    def diagnostics(self):
        """(rejected counts, values) for /diagnostics."""
        with self._lock:
            values = {f"exploration.{k}": n for k, n in self.counts.items()}
            rejected = Counter(self.rejected)
        values["lost.explore_near_messages"] = self.requests.lost
        values["lost.explore_near_full_queue_takes"] = self.requests.full_queue_takes
        if self._focus is not None:
            values["exploration.near_samples_left"] = self._focus[1].left
        return rejected, values
