"""The fuzz's plan: a babbling session interleaved with hostile messages of every kind (:data:`CASES`), the other
nodes' hostile inputs (:data:`OTHER_INPUTS`), and what each node must then count (:class:`Plan`); the run is
:mod:`body_scheme_apps.fuzz`'s."""

from __future__ import annotations

import functools
import math
import struct
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovariance
from sensor_msgs.msg import CameraInfo, JointState
from std_msgs.msg import Header

from body_scheme_msgs.msg import ExploreNear, IKTarget, MarkerPoses
from body_scheme_nodes import conversions

__all__ = ["PERIOD", "CASES", "OTHER_INPUTS", "OTHER_TOPICS", "OTHER_MAX_BYTES", "Plan", "make_plan",
           "marker_poses_bytes"]

#: Seconds between two valid samples; hostile messages go in between.
PERIOD = 0.05
#: Valid samples before backwards-stamped messages start (they are stamped 1 s back, behind every decided sample).
BACKWARDS_FROM = 2 * int(1.0 / PERIOD)
BURST = 40


def _pose(x=0.1, y=0.0, z=1.0, q=(0.0, 0.0, 0.0, 1.0)):
    """A ``PoseWithCovariance`` with arbitrary (possibly invalid) numbers, unlike ``marker_poses_msg``."""
    item = PoseWithCovariance()
    item.pose.position.x, item.pose.position.y, item.pose.position.z = float(x), float(y), float(z)
    item.pose.orientation.x, item.pose.orientation.y, item.pose.orientation.z, item.pose.orientation.w = \
        (float(v) for v in q)
    return item


def _header(stamp):
    return Header(stamp=conversions.stamp_from_seconds(stamp), frame_id="camera")


def _observations(stamp, markers=(), ids=None):
    """``MarkerPoses`` stamped ``stamp`` from ``[(id, PoseWithCovariance)]`` as given (no checks); ``ids`` replaces
    the ids (arrays of different lengths)."""
    markers = list(markers)
    return MarkerPoses(header=_header(stamp), marker_ids=[int(i) for i, _ in markers] if ids is None else ids,
                       poses=[item for _, item in markers])


def _command(stamp, names, positions):
    return JointState(header=_header(stamp), name=list(names), position=[float(v) for v in positions])


# ---------------------------------------------------------------------- the hostile messages
# Each case: (kind, build(stamp, names, valid actions) -> message, what the node counts). ``stamp`` is the slot's time.
NAN, INF, HUGE = float("nan"), float("inf"), 1e300

#: Refused before pairing, whatever else happens: safe anywhere, in any number (bursts).
REFUSED_ANYWHERE = {
    "command_nan": ("command", lambda t, n, a: _command(t, n, [NAN, a[1]]), {"rejected.bad_command_message": 1}),
    "command_inf": ("command", lambda t, n, a: _command(t, n, [a[0], -INF]), {"rejected.bad_command_message": 1}),
    "command_more_names_than_positions": ("command", lambda t, n, a: _command(t, n, [a[0]]),
                                          {"rejected.bad_command_message": 1}),
    "command_empty": ("command", lambda t, n, a: _command(t, [], []), {"rejected.bad_command_message": 1}),
    "command_unknown_joint": ("command", lambda t, n, a: _command(t, [n[0], "elbow_of_another_robot"], a),
                              {"rejected.bad_command_message": 1}),
    "command_joint_named_twice": ("command", lambda t, n, a: _command(t, [n[0], n[0], n[1]], [a[0], 0.3, a[1]]),
                                  {"rejected.bad_command_message": 1}),
    "command_future_stamp": ("command", lambda t, n, a: _command(t + 5.0, n, a), {"rejected.future_stamp": 1}),
    "command_far_future_stamp": ("command", lambda t, n, a: _command(t + 1e8, n, a), {"rejected.future_stamp": 1}),
    "observations_ids_without_poses": ("observations", lambda t, n, a: _observations(t, ids=[1, 2]),
                                       {"rejected.bad_observations_message": 1}),
    "observations_poses_without_ids": ("observations", lambda t, n, a: _observations(t, [(1, _pose()), (2, _pose())],
                                                                                     ids=[]),
                                       {"rejected.bad_observations_message": 1}),
    "observations_future_stamp": ("observations", lambda t, n, a: _observations(t + 30.0, [(1, _pose())]),
                                  {"rejected.future_stamp": 1}),
    "observations_wrong_frame": ("observations", lambda t, n, a: MarkerPoses(
        header=Header(stamp=conversions.stamp_from_seconds(t), frame_id="world"), marker_ids=[1], poses=[_pose()]),
        {"rejected.wrong_frame": 1}),
}
#: Larger than scheme_node's limits (defaults: 1 MiB, 1,000 joint names, 1,000 markers): refused whole, by their size
#: in bytes before they are deserialized, or by their count before any work. Published :data:`OVERSIZED_ROUNDS` times
#: each at the very end (sending 352 MB delays this process's later messages, which would change their pairing),
#: and the node must stay responsive meanwhile (/diagnostics keeps its period, by the node's own stamps).
OVERSIZED = {
    "command_100000_names": ("command", lambda t, n, a: _command(t, [f"joint_{k}" for k in range(100_000)],
                                                                 [0.0] * 100_000), {"rejected.oversized_message": 1}),
    "command_2000_names": ("command", lambda t, n, a: _command(t, [f"joint_{k}" for k in range(2000)], [0.0] * 2000),
                           {"rejected.oversized_message": 1}),
    "observations_2000_markers": ("observations", lambda t, n, a: _observations(
        t, [(k, _pose()) for k in range(2000)]), {"rejected.oversized_message": 1}),
    "observations_1000000_markers": ("observations", lambda t, n, a: marker_poses_bytes(t, "camera", 1_000_000),
                                     {"rejected.oversized_message": 1}),
}
OVERSIZED_ROUNDS = 2
#: Stamped 1 s back: behind the last command and every decided observation (only after ``BACKWARDS_FROM`` samples).
BACKWARDS = {
    "command_backwards_stamp": ("command", lambda t, n, a: _command(t - 1.0, n, a),
                                {"rejected.out_of_order_command": 1}),
    "command_negative_stamp": ("command", lambda t, n, a: JointState(
        header=Header(stamp=Time(sec=-5, nanosec=0)), name=list(n), position=[float(v) for v in a]),
        {"rejected.out_of_order_command": 1}),
    "observations_backwards_stamp": ("observations", lambda t, n, a: _observations(t - 1.0, [(1, _pose())]),
                                     {"rejected.out_of_order_observation": 1}),
}
#: An observation in the slot after a valid sample: its command is used, so it is a ``duplicate`` besides its markers.
IN_SLOT = {
    "observations_bad_markers": ("observations", lambda t, n, a: _observations(t, [
        (1, _pose(x=NAN)), (2, _pose(y=INF)), (3, _pose(q=(0, 0, 0, 0))), (4, _pose(q=(0, 0, 0, 2))),
        (5, _pose(q=(NAN, 0, 0, 1)))]), {"rejected.invalid_pose": 5, "rejected.duplicate": 1}),
    "observations_repeated_ids": ("observations", lambda t, n, a: _observations(t, [
        (1, _pose()), (1, _pose()), (2, _pose()), (2, _pose()), (2, _pose())]),
        {"rejected.repeated_id": 3, "rejected.duplicate": 1}),
    "observations_empty": ("observations", lambda t, n, a: _observations(t, []), {"rejected.duplicate": 1}),
}
#: A command and its observation in the slot: a learning sample the learner refuses (whole or marker by marker).
PAIRS = {
    "pair_command_beyond_limits": (lambda t, n, a: _command(t, n, [50.0, a[1]]),
                                   lambda t: _observations(t, [(1, _pose())]),
                                   {"rejected.command_out_of_range": 1}, 0),
    "pair_command_1e300": (lambda t, n, a: _command(t, n, [a[0], HUGE]),
                           lambda t: _observations(t, [(1, _pose())]), {"rejected.command_out_of_range": 1}, 0),
    "pair_markers_out_of_workspace": (lambda t, n, a: _command(t, n, a), lambda t: _observations(t, [
        (1, _pose(x=HUGE)), (2, _pose(y=1e150)), (3, _pose(z=20.0))]), {"rejected.out_of_workspace": 3}, 1),
    "pair_unknown_and_negative_ids": (lambda t, n, a: _command(t, n, a), lambda t: _observations(t, [
        (99, _pose()), (-5, _pose()), (2**40, _pose())]), {"rejected.unknown_id": 3}, 1),
}


# ---------------------------------------------------------------------- the other nodes' inputs
def _explore_near(t, names, positions, samples=3, radius=0.05):
    return ExploreNear(header=_header(t), joint_names=list(names), positions=[float(v) for v in positions],
                       samples=samples, radius=radius)


def _camera_info(width, height, fx, cx, cy, frame="camera"):
    return CameraInfo(header=_header(0.0), width=width, height=height, k=[fx, 0.0, cx, 0.0, fx, cy, 0.0, 0.0, 1.0])


def _target(t, part, position, frame="camera"):
    msg = IKTarget(header=_header(t), part_id=part)
    msg.header.frame_id = frame
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in position)
    return msg


#: Topics of the other nodes' inputs: topic key -> (message type, topic, the node that counts it).
OTHER_TOPICS = {"explore_near": (ExploreNear, "body_scheme/explore_near", "scheme_node"),
                "camera_info": (CameraInfo, "camera/camera_info", "scheme_node"),
                "ik_target": (IKTarget, "ik_target", "control_node"),
                "joint_states": (JointState, "/joint_states", "babble_node")}
#: ``max_message_bytes`` of the three nodes in the run: a message larger than this is refused unread.
OTHER_MAX_BYTES = 1 << 16
_LARGE = "x" * (OTHER_MAX_BYTES + 1)
#: Case -> (topic key, build(t, joint names, valid actions) -> message, {node: {counter: n}}). Each is refused: none
#: changes what scheme_node learns (control_node answers without a command, babble_node is paused).
OTHER_INPUTS = {
    "explore_near_unknown_joint": ("explore_near", lambda t, n, a: _explore_near(t, [n[0], "wrist_of_another"], a),
                                   {"scheme_node": {"rejected.bad_explore_near": 1}}),
    "explore_near_nan": ("explore_near", lambda t, n, a: _explore_near(t, n, [NAN, a[1]]),
                         {"scheme_node": {"rejected.bad_explore_near": 1}}),
    "explore_near_zero_samples": ("explore_near", lambda t, n, a: _explore_near(t, n, a, samples=0),
                                  {"scheme_node": {"rejected.bad_explore_near": 1}}),
    "explore_near_radius_5": ("explore_near", lambda t, n, a: _explore_near(t, n, a, radius=5.0),
                              {"scheme_node": {"rejected.bad_explore_near": 1}}),
    "explore_near_too_large": ("explore_near", lambda t, n, a: _explore_near(t, [_LARGE], [0.0]),
                               {"scheme_node": {"rejected.oversized_message": 1}}),
    "camera_info_1x1_f1e300": ("camera_info", lambda t, n, a: _camera_info(1, 1, 1e300, 0.5, 0.5),
                               {"scheme_node": {"rejected.bad_camera_info": 1}}),
    "camera_info_uncalibrated": ("camera_info", lambda t, n, a: _camera_info(640, 480, 0.0, 320.0, 240.0),
                                 {"scheme_node": {"rejected.bad_camera_info": 1}}),
    "camera_info_principal_point_off": ("camera_info", lambda t, n, a: _camera_info(640, 480, 500.0, -1e6, 240.0),
                                        {"scheme_node": {"rejected.bad_camera_info": 1}}),
    "camera_info_too_large": ("camera_info", lambda t, n, a: CameraInfo(header=Header(frame_id=_LARGE)),
                              {"scheme_node": {"rejected.oversized_message": 1}}),
    "ik_target_nan": ("ik_target", lambda t, n, a: _target(t, -1, [NAN, 0.0, 1.0]), {"control_node": {"received": 1}}),
    "ik_target_unknown_part": ("ik_target", lambda t, n, a: _target(t, 99, [0.0, 0.0, 1.0]),
                               {"control_node": {"received": 1}}),
    "ik_target_other_frame": ("ik_target", lambda t, n, a: _target(t, -1, [0.0, 0.0, 1.0], frame="world"),
                              {"control_node": {"received": 1}}),
    "ik_target_too_large": ("ik_target", lambda t, n, a: _target(t, -1, [0.0, 0.0, 1.0], frame=_LARGE),
                            {"control_node": {"rejected.oversized_message": 1}}),
    "joint_states_50_rad": ("joint_states", lambda t, n, a: _command(t, n, [50.0, a[1]]),
                            {"babble_node": {"driver.joint_states_out_of_range": 1}}),
    "joint_states_1e308": ("joint_states", lambda t, n, a: _command(t, n, [a[0], -1e308]),
                           {"babble_node": {"driver.joint_states_out_of_range": 1}}),
    "joint_states_nan": ("joint_states", lambda t, n, a: _command(t, n, [NAN, a[1]]),
                         {"babble_node": {"driver.joint_states_rejected": 1}}),
    "joint_states_unknown_joint": ("joint_states", lambda t, n, a: _command(t, ["shoulder_of_another"], [0.0]),
                                   {"babble_node": {"driver.joint_states_rejected": 1}}),
    "joint_states_too_large": ("joint_states", lambda t, n, a: _command(t, [_LARGE], [0.0]),
                               {"babble_node": {"driver.joint_states_oversized": 1}}),
    "joint_states_valid": ("joint_states", lambda t, n, a: _command(t, n, a),
                           {"babble_node": {"driver.joint_states": 1}}),
}
#: One of the other inputs every this many slots, the cases in turn.
OTHER_EVERY = 2
#: Every case name (for the report).
CASES = sorted([*REFUSED_ANYWHERE, *BACKWARDS, *IN_SLOT, *PAIRS, *OVERSIZED, *OTHER_INPUTS, "zero_stamp_command",
                "zero_stamp_observations"])


def marker_poses_bytes(stamp, frame_id, n):
    """A serialized ``MarkerPoses`` (CDR, little endian) of ``n`` identical markers, built with numpy: a million
    markers as Python message objects would take gigabytes, as bytes they take 352 MB."""
    sec, nanosec = divmod(round(stamp * 1e9), 10**9)
    frame = frame_id.encode() + b"\0"
    head = struct.pack("<iII", sec, nanosec, len(frame)) + frame
    head += b"\0" * (-len(head) % 4) + struct.pack("<I", n)  # marker_ids: count, then int64s aligned to 8
    head += b"\0" * (-len(head) % 8)
    return b"\x00\x01\x00\x00" + head + _markers_body(n)


@functools.lru_cache(maxsize=1)
def _markers_body(n):
    """The ids and poses of :func:`marker_poses_bytes` (built once: a second, identical, message costs a copy)."""
    pose = np.zeros(43, dtype="<f8")  # PoseWithCovariance: position, orientation, 36 covariance entries
    pose[2], pose[6] = 1.0, 1.0
    return np.arange(n, dtype="<i8").tobytes() + struct.pack("<I", n) + b"\0" * 4 + np.tile(pose, n).tobytes()


@dataclass
class Plan:
    """What to publish when (offsets from the start, s) and what the node must then count."""

    messages: list = field(default_factory=list)  # (offset s, kind, build(t0) -> message), in publishing order
    expected: Counter = field(default_factory=Counter)  # scheme_node's counters
    other_expected: dict = field(default_factory=lambda: {"control_node": Counter(), "babble_node": Counter()})
    cases: Counter = field(default_factory=Counter)  # hostile messages by case
    learning_steps: int = 0
    valid_samples: list = field(default_factory=list)  # (actions, observations) the learner must see
    huge_from: float = math.inf  # offset of the first message of hundreds of MB

    def add(self, offset, kind, build, case=None):
        self.messages.append((offset, kind, build))
        if case is not None:
            self.cases[case] += 1


def make_plan(session, n_messages, seed=0):
    """Interleave ``session`` (one valid command and observation per ``PERIOD``) with hostile messages, about
    ``n_messages`` in all, and add up the node's expected counts."""
    rng = np.random.default_rng(seed)
    names = list(session.tree.action_joint_names)
    n = session.n_steps
    plan = Plan()
    # Refusals per slot so that the total comes near n_messages (a slot holds 1.2 pair or slot messages on average).
    per_slot = max(0.0, (n_messages - 2 * n - 7) / n - 1.2 - BURST * 0.03)
    for k in range(n):
        t, a, obs = k * PERIOD, session.actions[k], session.observations[k]
        ignored = k % 7 == 3  # NaN, inf and 1e300 in fields the node does not use
        plan.add(t, "command", lambda t0, t=t, a=a, ignored=ignored: _valid_command(t0 + t, names, a, ignored))
        plan.add(t + 0.005, "observations", lambda t0, t=t, obs=obs, ignored=ignored: _valid_observations(
            t0 + t + 0.005, obs, ignored))
        plan.valid_samples.append((a, obs))
        plan.learning_steps += 1
        mid = t + PERIOD / 2
        cases = dict(REFUSED_ANYWHERE, **(BACKWARDS if k >= BACKWARDS_FROM else {}))
        count = int(rng.poisson(per_slot)) + (BURST if rng.random() < 0.03 else 0)
        for j, name in enumerate(rng.choice(sorted(cases), size=count)):
            kind, build, counts = cases[name]
            plan.add(mid - 0.01 + 1e-5 * j, kind, lambda t0, t=mid, b=build, a=a: b(t0 + t, names, a), name)
            plan.expected.update(counts)
        if k % OTHER_EVERY == 0:  # in turn: every case in a short run, a CameraInfo (best effort) now and then
            name = sorted(OTHER_INPUTS)[(k // OTHER_EVERY) % len(OTHER_INPUTS)]
            topic, build, counts = OTHER_INPUTS[name]
            plan.add(mid + 0.01, topic, lambda t0, t=mid, b=build, a=a: b(t0 + t, names, a), name)
            for node_name, node_counts in counts.items():
                (plan.expected if node_name == "scheme_node" else plan.other_expected[node_name]).update(node_counts)
        slot = rng.choice(["none", "observations", "pair"], p=[0.2, 0.4, 0.4])
        if slot == "observations":
            name = str(rng.choice(sorted(IN_SLOT)))
            kind, build, counts = IN_SLOT[name]
            plan.add(mid, kind, lambda t0, t=mid, b=build, a=a: b(t0 + t, names, a), name)
            plan.expected.update(counts)
        elif slot == "pair":
            name = str(rng.choice(sorted(PAIRS)))
            command, observations, counts, steps = PAIRS[name]
            plan.add(mid, "command", lambda t0, t=mid, b=command, a=a: b(t0 + t, names, a), name)
            plan.add(mid + 0.005, "observations", lambda t0, t=mid, b=observations: b(t0 + t + 0.005), name)
            plan.expected.update(counts)
            plan.learning_steps += steps
    # Zero stamps, after the session: commands take their receipt time (no observation follows them), then
    # observations of an unknown marker take theirs: the first pairs with the last command (a learning step whose only
    # marker is unknown), the others are duplicates of it.
    end = n * PERIOD + 1.0
    for j in range(3):
        plan.add(end + 0.05 * j, "command", lambda t0, a=session.actions[-1]: JointState(
            name=names, position=[float(v) for v in a]), "zero_stamp_command")
    for j in range(4):
        plan.add(end + 0.2 + 0.05 * j, "observations", lambda t0: MarkerPoses(marker_ids=[77], poses=[_pose()]),
                 "zero_stamp_observations")
    plan.expected.update({"restamped.unstamped": 7, "rejected.unknown_id": 1, "rejected.duplicate": 3})
    plan.learning_steps += 1
    # Last: a 352 MB publish holds this process up for seconds, which would shift the receipt times of what follows.
    plan.huge_from = end + 1.0
    for r in range(OVERSIZED_ROUNDS):
        t = end + 1.0 + 0.5 * r
        for j, name in enumerate(sorted(OVERSIZED)):
            kind, build, counts = OVERSIZED[name]
            plan.add(t + 0.1 * j, kind, lambda t0, t=t, b=build, a=session.actions[-1]: b(t0 + t, names, a), name)
            plan.expected.update(counts)
    plan.messages.sort(key=lambda item: item[0])
    return plan


def _valid_command(stamp, names, actions, ignored):
    msg = _command(stamp, names, actions)
    if ignored:
        msg.velocity, msg.effort = [NAN, INF], [HUGE, -HUGE]
    return msg


def _valid_observations(stamp, observations, ignored):
    msg = conversions.marker_poses_msg(stamp, "camera", observations)
    if ignored:
        for item in msg.poses:
            item.covariance = [NAN] * 36
    return msg
