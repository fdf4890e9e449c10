"""Recordings of other stacks as body scheme samples: a source map (YAML), rosbag2 sessions and tables.

A user's session recorded with aruco_ros, apriltag_ros, a motion-capture driver or a calibration tool has measured
joint values at a high rate and marker poses on topics of their own. A **source map** says where each observed body's
pose comes from; :func:`translate` turns the recording into the two streams scheme_node learns from
(``/joint_commands`` as ``sensor_msgs/JointState``, ``/observations`` as ``body_scheme_msgs/MarkerPoses``), so the
offline replay and ``bag_replay`` take a foreign recording exactly as they take our own bags.

Source map (docs/your-data.md has one per driver)::

    joints:
      names: [joint1, joint2]        # required: the joints, in the action order
      topic: /joint_states           # sensor_msgs/JointState (measured) or trajectory_msgs/JointTrajectory
      still_tolerance: 0.002         # rad or m: the arm stands still while no joint moves more than this
      still_time: 0.3                # s: a still period this long is one pose
      settle_time: 0.1               # s into a still period before an observation counts
    frame: camera_optical_frame      # the frame every pose is expressed in (tf parent, header.frame_id)
    bodies:                          # marker id -> where its pose comes from
      1: {tf: tag36h11:0}            # a /tf or /tf_static child frame (aruco_ros, apriltag_ros)
      2: {topic: /mocap/tool/pose}   # PoseStamped, PoseWithCovarianceStamped or TransformStamped (mocap drivers)
      3: {topic: /markers, index: 0} # one element of a PoseArray
      4: {points: {/tracker/a: [0, 0, 0], /tracker/b: [0.1, 0, 0], /tracker/c: [0, 0.1, 0]}}
                                     # PointStamped topics and each point's coordinates on the body (>= 3)

**Samples.** Each still period of the joint values (:func:`body_scheme_core.pairing.still_periods`) is one pose:
its mean joint values are the command, and each body's first pose stamped at least ``settle_time`` into the period
(and before it ends) is the observation. A ``JointTrajectory`` gives one period per message: from the time its last
point is reached until the next message. Points of a body are registered into its pose (least squares) when at least
three are seen. The observation message is stamped with its latest pose; the command at the period's start, or one
second before the observation if the period is longer (inside scheme_node's default pairing window of 2 s).

**Tables** (``.csv``, ``.jsonl``, one pose per row): :mod:`.source_tables`.

Everything that is dropped is counted by reason in :attr:`Translation.counts` (never silently).
"""

from __future__ import annotations

import bisect
import math
import pathlib
from collections import Counter, defaultdict
from dataclasses import dataclass, field

import numpy as np
import yaml
from sensor_msgs.msg import JointState

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning import MIN_SPREAD, point_spread, register_points
from body_scheme_core.pairing import still_periods
from body_scheme_core.transforms import transform_from_pose

from . import conversions
from .bag_io import BagMessage, bag_topics, read_messages
from .source_tables import TABLE_SUFFIXES, append_sample, table_samples

__all__ = ["BodySource", "SourceMap", "Translation", "translate", "TABLE_SUFFIXES", "POSE_TYPES", "JOINT_TYPES"]

#: Joint value message types a source map's ``joints.topic`` may carry.
JOINT_TYPES = ("sensor_msgs/msg/JointState", "trajectory_msgs/msg/JointTrajectory")
#: Pose message types a body's ``topic`` may carry.
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped", "geometry_msgs/msg/PoseArray")
TF_TOPICS = ("/tf", "/tf_static")
#: Longest time between a command and its observation in the translated streams, s (scheme_node's default
#: ``max_delay`` is 2 s).
MAX_OBSERVATION_DELAY = 1.0


@dataclass(frozen=True)
class BodySource:
    """Where one observed body's pose comes from (exactly one of ``tf``, ``topic`` or ``points``)."""

    marker_id: int
    tf: str = ""
    topic: str = ""
    index: int | None = None
    points: dict = field(default_factory=dict)  # topic or table label -> (3,) coordinates on the body


@dataclass(frozen=True)
class SourceMap:
    """How a recording of another stack becomes samples (the module docstring shows the YAML)."""

    joint_names: tuple
    bodies: tuple
    joint_topic: str = "/joint_states"
    frame: str = ""
    still_tolerance: float = 0.002
    still_time: float = 0.3
    settle_time: float = 0.1

    @classmethod
    def from_yaml(cls, path):
        """Read and check a source map file; every mistake is an :class:`InvalidInputError` naming the entry."""
        path = pathlib.Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as error:
            raise InvalidInputError(f"cannot read the source map {path}: {error}") from error
        if not isinstance(data, dict):
            raise InvalidInputError(f"source map {path}: expected a mapping with joints, frame and bodies")
        unknown = sorted(set(data) - {"joints", "frame", "bodies"})
        joints = data.get("joints")
        if unknown or not isinstance(joints, dict):
            raise InvalidInputError(f"source map {path}: needs 'joints' (a mapping), 'bodies' and optionally 'frame'"
                                    f"{'; unknown keys ' + str(unknown) if unknown else ''}")
        names = joints.get("names")
        if not (isinstance(names, list) and names and all(isinstance(n, str) and n for n in names)
                and len(set(names)) == len(names)):
            raise InvalidInputError(f"source map {path}: joints.names must be a list of distinct joint names")
        unknown = sorted(set(joints) - {"names", "topic", "still_tolerance", "still_time", "settle_time"})
        if unknown:
            raise InvalidInputError(f"source map {path}: unknown keys under joints: {unknown}")
        numbers = {}
        for key in ("still_tolerance", "still_time", "settle_time"):
            value = joints.get(key, getattr(cls, key))
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < 0 or (key == "still_tolerance" and value == 0):
                raise InvalidInputError(f"source map {path}: joints.{key} must be a number >= 0 (tolerance > 0), "
                                        f"got {value!r}")
            numbers[key] = float(value)
        bodies = data.get("bodies") or {}
        if not isinstance(bodies, dict):
            raise InvalidInputError(f"source map {path}: bodies must map marker ids to their source")
        return cls(joint_names=tuple(names), joint_topic=str(joints.get("topic", "/joint_states")),
                   frame=str(data.get("frame") or "").lstrip("/"),
                   bodies=tuple(_body(path, key, value) for key, value in bodies.items()), **numbers)

    def bag_topics(self):
        """The bag topics this map reads."""
        topics = {self.joint_topic}
        for body in self.bodies:
            topics |= set(TF_TOPICS) if body.tf else {body.topic} if body.topic else set(body.points)
        return topics


def _body(path, key, value):
    where = f"source map {path}: bodies.{key}"
    if isinstance(key, bool) or not isinstance(key, int) or key < 0:
        raise InvalidInputError(f"{where}: marker ids are integers >= 0")
    if not isinstance(value, dict) or sum(k in value for k in ("tf", "topic", "points")) != 1 \
            or set(value) - {"tf", "topic", "index", "points"}:
        raise InvalidInputError(f"{where}: give exactly one of tf (a frame), topic (+ index for a PoseArray) or "
                                f"points (label -> [x, y, z]), got {value!r}")
    index = value.get("index")
    if index is not None and (isinstance(index, bool) or not isinstance(index, int) or index < 0):
        raise InvalidInputError(f"{where}: index must be an integer >= 0, got {index!r}")
    points = {}
    for label, xyz in (value.get("points") or {}).items():
        coordinates = np.asarray(xyz, dtype=float) if isinstance(xyz, list) else np.zeros(0)
        if coordinates.shape != (3,) or not np.all(np.isfinite(coordinates)):
            raise InvalidInputError(f"{where}: point {label!r} needs coordinates [x, y, z], got {xyz!r}")
        points[str(label)] = coordinates
    if "points" in value and (len(points) < 3 or point_spread(list(points.values())) < MIN_SPREAD):
        raise InvalidInputError(f"{where}: needs at least three points not on one line")
    return BodySource(marker_id=key, tf=str(value.get("tf") or "").lstrip("/"), topic=str(value.get("topic") or ""),
                      index=index, points=points)


@dataclass
class Translation:
    """A recording as our two streams.

    Attributes
    ----------
    messages : list of BagMessage
        ``/joint_commands`` (JointState) and ``/observations`` (MarkerPoses), in log-time order.
    counts : collections.Counter
        ``poses`` (still periods or rows), ``samples`` (with at least one body observed), and what was dropped by
        reason: ``unseen`` (a pose in which no body was observed), ``wrong_frame``, ``invalid_pose``,
        ``too_few_points``, ``joints_missing`` (a joint message without the map's joints or with a value that is not
        finite), ``invalid_row`` (no valid joint values, or a stamp not after the row before), ``ignored_columns``.
    """

    messages: list = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)

    def summary(self):
        return ", ".join(f"{key} {value}" for key, value in sorted(self.counts.items()))


def translate(path, source_map):
    """A rosbag2 directory or a table (``.csv``, ``.jsonl``) as samples (see the module docstring).

    Raises
    ------
    BagError
        If the bag cannot be read or a mapped topic has a type the map cannot take.
    InvalidInputError
        If the recording has no joint values, or a table's header lacks a joint.
    """
    path = pathlib.Path(path)
    counts = Counter()
    rows = table_samples(path, source_map, counts) if path.suffix in TABLE_SUFFIXES else _bag(path, source_map, counts)
    return _messages(rows, counts, source_map)


# ---------------------------------------------------------------------- bags
def _bag(path, source_map, counts):
    """The bag's samples: ``[(start of the still period, values, {id: (stamp, pose or point) per key})]``."""
    if not source_map.bodies:
        raise InvalidInputError(f"bag {path}: the source map names no bodies (marker id -> tf, topic or points)")
    available = bag_topics(path)
    joint_type = available.get(source_map.joint_topic, (None, 0))[0]
    if joint_type not in JOINT_TYPES:
        raise InvalidInputError(f"bag {path}: the joints' topic {source_map.joint_topic} is "
                                f"{'missing' if joint_type is None else 'of type ' + joint_type}; it must carry "
                                f"one of {list(JOINT_TYPES)} (joints.topic in the source map)")
    for body in source_map.bodies:
        for topic in [body.topic] if body.topic else list(body.points):
            kind = available.get(topic, (None, 0))[0]
            wanted = POSE_TYPES if body.topic else ("geometry_msgs/msg/PointStamped",)
            if kind is not None and kind not in wanted:
                raise InvalidInputError(f"bag {path}: body {body.marker_id}'s topic {topic} is of type {kind}, "
                                        f"not one of {list(wanted)}")
    joint_stamps, joint_values, trajectory = [], [], []
    seen = defaultdict(list)  # (marker id, point label or "") -> [(stamp, pose or point)]
    by_frame = {body.tf: body for body in source_map.bodies if body.tf}
    by_topic = defaultdict(list)
    for body in source_map.bodies:
        if body.topic:
            by_topic[body.topic].append(body)
        for topic in body.points:
            by_topic[topic].append(body)
    for item in read_messages(path, sorted(source_map.bag_topics() & set(available))):
        msg = item.msg
        if item.topic == source_map.joint_topic:
            try:
                if joint_type == JOINT_TYPES[0]:
                    joint_values.append(conversions.actions_from_joint_state(msg, source_map.joint_names)[1])
                    joint_stamps.append(_stamp(msg.header.stamp, item.log_time))
                else:
                    trajectory.append(_trajectory_target(msg, item.log_time, source_map.joint_names))
            except InvalidInputError:
                counts["joints_missing"] += 1
        elif item.topic in TF_TOPICS:
            for transform in msg.transforms:
                body = by_frame.get(transform.child_frame_id.lstrip("/"))
                if body is not None:
                    _keep(seen, counts, source_map, (body.marker_id, ""), transform.header, item.log_time,
                          lambda t=transform.transform: _transform(t))
        for body in by_topic.get(item.topic, ()):
            if body.points:
                _keep(seen, counts, source_map, (body.marker_id, item.topic), msg.header, item.log_time,
                      lambda p=msg.point: np.array([p.x, p.y, p.z], dtype=float))
            else:
                _keep(seen, counts, source_map, (body.marker_id, ""), msg.header, item.log_time,
                      lambda m=msg, b=body: _pose_of(m, b))
    if trajectory:
        periods = _trajectory_periods(sorted(trajectory, key=lambda goal: goal[0]), source_map.still_time)
    elif joint_values:
        order = np.argsort(joint_stamps, kind="stable")  # header stamps may jitter out of the log order
        periods = still_periods(np.asarray(joint_stamps)[order], np.array(joint_values)[order],
                                source_map.still_tolerance, source_map.still_time)
    else:
        raise InvalidInputError(f"bag {path}: no message on {source_map.joint_topic} names the joints "
                                f"{list(source_map.joint_names)}")
    return _in_periods(periods, seen, source_map)


def _stamp(stamp, log_time):
    """A header stamp in seconds; the log time when the header is not stamped."""
    seconds = conversions.seconds_from_stamp(stamp)
    return seconds if seconds > 0 else log_time * 1e-9


def _trajectory_target(msg, log_time, joint_names):
    """``(sent, reached, values)`` of a JointTrajectory: its last point, at header stamp + time_from_start."""
    if not msg.points:
        raise InvalidInputError("trajectory without points")
    last = msg.points[-1]
    _, values = conversions.actions_from_joint_state(
        JointState(name=list(msg.joint_names), position=list(last.positions)), joint_names)
    sent = _stamp(msg.header.stamp, log_time)
    return sent, sent + last.time_from_start.sec + last.time_from_start.nanosec * 1e-9, values


def _trajectory_periods(targets, min_duration):
    """A goal holds from the time it is reached until the next goal is sent (its header stamp)."""
    periods = []
    for k, (_, reached, values) in enumerate(targets):
        end = targets[k + 1][0] if k + 1 < len(targets) else math.inf
        if end - reached >= min_duration:
            periods.append((reached, end, values))
    return periods


def _keep(seen, counts, source_map, key, header, log_time, value):
    """Keep ``value()`` (a pose or a point) of ``key`` (marker id, point label) if its frame is the map's."""
    if source_map.frame and header.frame_id.lstrip("/") != source_map.frame:
        counts["wrong_frame"] += 1
        return
    append_sample(seen, counts, key, _stamp(header.stamp, log_time), value)


def _transform(transform):
    t, q = transform.translation, transform.rotation
    return transform_from_pose([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])


def _pose_of(msg, body):
    if hasattr(msg, "transform"):
        return _transform(msg.transform)
    if hasattr(msg, "poses"):
        return conversions.transform_from_pose_msg(msg.poses[body.index or 0])
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    return conversions.transform_from_pose_msg(pose)


# ---------------------------------------------------------------------- periods and observations -> messages
def _in_periods(periods, seen, source_map):
    """Per still period: its start, values and each key's first sample at least ``settle_time`` into it."""
    for key in seen:
        seen[key].sort(key=lambda item: item[0])
    stamps = {key: [stamp for stamp, _ in values] for key, values in seen.items()}
    samples = []
    for start, end, values in periods:
        found = {}
        for key, key_stamps in stamps.items():
            k = bisect.bisect_left(key_stamps, start + source_map.settle_time)
            if k < len(key_stamps) and key_stamps[k] <= end:
                found[key] = seen[key][k]
        samples.append((start, values, found))
    return samples


def _messages(samples, counts, source_map):
    """One command and one observation message per sample in which a body was observed."""
    translation = Translation(counts=counts)
    points_of = {body.marker_id: body for body in source_map.bodies if body.points}
    for start, values, found in samples:
        counts["poses"] += 1
        poses, latest = {}, -math.inf
        for marker_id in sorted({marker_id for marker_id, _ in found} | set(points_of)):
            body = points_of.get(marker_id)
            mine = {label: item for (part, label), item in found.items() if part == marker_id}
            if not mine:
                continue
            pose = mine[""][1] if body is None else _registered(body, mine)
            if pose is None:
                counts["too_few_points"] += 1
                continue
            poses[marker_id] = pose
            latest = max(latest, *(stamp for stamp, _ in mine.values()))
        if not poses:
            counts["unseen"] += 1
            continue
        command_stamp = max(start, latest - MAX_OBSERVATION_DELAY)
        command = conversions.joint_state_msg(command_stamp, source_map.joint_names, values)
        observation = conversions.marker_poses_msg(latest, source_map.frame, poses)
        translation.messages += [BagMessage("/joint_commands", round(command_stamp * 1e9), command),
                                 BagMessage("/observations", round(latest * 1e9), observation)]
        counts["samples"] += 1
    translation.messages.sort(key=lambda item: item.log_time)
    return translation


def _registered(body, found):
    """The body's pose from its points seen (>= 3, not on one line), or None."""
    labels = [label for label in body.points if label in found and np.all(np.isfinite(found[label][1]))]
    if len(labels) < 3:
        return None
    local = np.array([body.points[label] for label in labels])
    if point_spread(local) < MIN_SPREAD:
        return None
    return register_points(local, np.array([found[label][1] for label in labels]))
