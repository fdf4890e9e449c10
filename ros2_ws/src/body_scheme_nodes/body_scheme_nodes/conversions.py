"""The one place where ROS messages become core types and back.

Nothing here keeps state or decides anything: functions take messages or core objects and return the other.
Validation errors are raised as :class:`body_scheme_core.errors.InvalidInputError` so nodes count and report them.
"""

from __future__ import annotations

import json
import math

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseWithCovariance

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import pose_from_transform, transform_from_pose
from body_scheme_msgs.msg import BodySchemeStructure, LocalModelInfo, MarkerPoses, ModelSnapshot, SchemeEvent

__all__ = [
    "seconds_from_stamp",
    "stamp_from_seconds",
    "transform_from_pose_msg",
    "pose_msg_from_transform",
    "observations_from_msg",
    "marker_poses_msg",
    "actions_from_joint_state",
    "structure_msg",
    "event_msg",
    "snapshot_msg",
    "scheme_from_snapshot",
    "diagnostic_status",
]

SNAPSHOT_FORMAT = "body_scheme/scheme"
SNAPSHOT_FORMAT_VERSION = 1


def seconds_from_stamp(stamp):
    """``builtin_interfaces/Time`` to float seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def stamp_from_seconds(seconds):
    """Float seconds to ``builtin_interfaces/Time``."""
    sec = math.floor(seconds)
    return Time(sec=int(sec), nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))


def transform_from_pose_msg(pose):
    """``geometry_msgs/Pose`` to a (4, 4) transform; zero or non-unit quaternions raise InvalidInputError."""
    p, q = pose.position, pose.orientation
    return transform_from_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])


def pose_msg_from_transform(A2B):
    """(4, 4) transform to ``geometry_msgs/Pose``."""
    position, q = pose_from_transform(A2B)
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in position)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def observations_from_msg(msg):
    """Split a ``MarkerPoses`` message into usable observations and per-marker rejections.

    Returns
    -------
    stamp : float
    observations : dict of int to ndarray, shape (4, 4)
        ``frame2marker`` for every marker whose pose is valid.
    rejected : list of (int, str)
        Marker id and reason for every marker that was dropped (NaN, zero quaternion, repeated id, ...).

    Raises
    ------
    InvalidInputError
        If ``marker_ids`` and ``poses`` differ in length (the message as a whole is unusable).
    """
    if len(msg.marker_ids) != len(msg.poses):
        raise InvalidInputError(
            f"MarkerPoses has {len(msg.marker_ids)} marker_ids but {len(msg.poses)} poses")
    observations, rejected = {}, []
    for marker_id, pose in zip(msg.marker_ids, msg.poses, strict=True):
        marker_id = int(marker_id)
        if marker_id in observations:
            rejected.append((marker_id, "repeated marker id in one message"))
            continue
        try:
            observations[marker_id] = transform_from_pose_msg(pose.pose)
        except InvalidInputError as error:
            rejected.append((marker_id, str(error)))
    return seconds_from_stamp(msg.header.stamp), observations, rejected


def marker_poses_msg(stamp, frame_id, poses, std=None):
    """Build a ``MarkerPoses`` message from ``{id: frame2marker}``, with isotropic covariance from ``std``.

    Parameters
    ----------
    stamp : float
    frame_id : str
    poses : dict of int to ndarray, shape (4, 4)
    std : dict of int to array-like, shape (2,), optional
        Translational (m) and rotational (rad) standard deviation per marker; omitted: covariance all zeros.
    """
    msg = MarkerPoses()
    msg.header.stamp = stamp_from_seconds(stamp)
    msg.header.frame_id = frame_id
    for marker_id in sorted(poses):
        item = PoseWithCovariance()
        item.pose = pose_msg_from_transform(poses[marker_id])
        if std is not None and marker_id in std:
            s_t, s_r = (float(v) for v in std[marker_id])
            cov = np.diag([s_t**2 / 3] * 3 + [s_r**2 / 3] * 3)
            item.covariance = cov.ravel().tolist()
        msg.marker_ids.append(int(marker_id))
        msg.poses.append(item)
    return msg


def actions_from_joint_state(msg, joint_names):
    """Action vector in ``joint_names`` order from a ``sensor_msgs/JointState`` command.

    Raises
    ------
    InvalidInputError
        If a joint is missing, names and positions differ in length, or a value is not finite.
    """
    if len(msg.name) != len(msg.position):
        raise InvalidInputError(f"JointState has {len(msg.name)} names but {len(msg.position)} positions")
    by_name = dict(zip(msg.name, msg.position, strict=True))
    missing = [name for name in joint_names if name not in by_name]
    if missing:
        raise InvalidInputError(f"JointState lacks joint(s) {missing}; expected {list(joint_names)}")
    actions = np.array([by_name[name] for name in joint_names], dtype=float)
    if not np.all(np.isfinite(actions)):
        raise InvalidInputError(f"JointState positions must be finite, got {actions.tolist()}")
    return seconds_from_stamp(msg.header.stamp), actions


def _model_info(status):
    info = LocalModelInfo()
    info.parent_id = int(status["parent"])
    info.child_id = int(status["child"])
    info.action_indices = [int(a) for a in status["actions"]]
    info.kind = str(status["kind"])
    info.description = str(status["model"])
    info.n_test = int(status["n_test"])
    info.trans_error = float(status["trans_error"])
    info.rot_error = float(status["rot_error"])
    info.theta_trans = float(status["theta_trans"])
    info.theta_rot = float(status["theta_rot"])
    info.valid = bool(status["valid"])
    info.in_mismatch = bool(status["in_mismatch"])
    return info


def structure_msg(stamp, step, phase, root, part_ids, edge_status):
    """``BodySchemeStructure`` from the learner's ``edge_status()`` list of dicts."""
    msg = BodySchemeStructure()
    msg.header.stamp = stamp_from_seconds(stamp)
    msg.step = int(step)
    msg.phase = str(phase)
    msg.root_id = int(root)
    msg.part_ids = [int(p) for p in part_ids]
    msg.edges = [_model_info(status) for status in edge_status]
    return msg


def event_msg(stamp, event):
    """``SchemeEvent`` from a core :class:`~body_scheme_core.events.Event`."""
    msg = SchemeEvent()
    msg.header.stamp = stamp_from_seconds(stamp)
    msg.step = int(event.step)
    msg.kind = event.kind
    msg.reason = event.reason
    msg.parent_id = -1 if event.parent is None else int(event.parent)
    msg.child_id = -1 if event.child is None else int(event.child)
    msg.model = event.model or ""
    msg.trans_error = math.nan if event.trans_error is None else float(event.trans_error)
    msg.rot_error = math.nan if event.rot_error is None else float(event.rot_error)
    return msg


def snapshot_msg(stamp, frame_id, step, scheme, action_names, lower, upper, world2root):
    """``ModelSnapshot`` carrying a :class:`~body_scheme_core.scheme.BodyScheme` as JSON (empty if ``None``)."""
    msg = ModelSnapshot()
    msg.header.stamp = stamp_from_seconds(stamp)
    msg.header.frame_id = frame_id
    msg.step = int(step)
    msg.format = SNAPSHOT_FORMAT
    msg.format_version = SNAPSHOT_FORMAT_VERSION
    msg.scheme_json = "" if scheme is None else json.dumps(scheme.to_dict())
    msg.action_names = list(action_names)
    msg.action_lower = [float(v) for v in lower]
    msg.action_upper = [float(v) for v in upper]
    msg.world_to_root = pose_msg_from_transform(np.eye(4) if world2root is None else world2root)
    return msg


def scheme_from_snapshot(msg):
    """Rebuild ``(scheme or None, world2root, lower, upper)`` from a ``ModelSnapshot``.

    Raises
    ------
    InvalidInputError
        If the format tag or version is not one this code reads, or the JSON is corrupt.
    """
    from body_scheme_core.models import model_from_dict
    from body_scheme_core.scheme import BodyScheme

    if msg.format != SNAPSHOT_FORMAT or msg.format_version != SNAPSHOT_FORMAT_VERSION:
        raise InvalidInputError(
            f"unsupported snapshot {msg.format!r} v{msg.format_version}; "
            f"this node reads {SNAPSHOT_FORMAT!r} v{SNAPSHOT_FORMAT_VERSION}")
    scheme = None
    if msg.scheme_json:
        try:
            scheme = BodyScheme.from_dict(json.loads(msg.scheme_json), model_from_dict)
        except (ValueError, KeyError, TypeError) as error:
            raise InvalidInputError(f"corrupt snapshot scheme: {error}") from error
    world2root = transform_from_pose_msg(msg.world_to_root)
    return scheme, world2root, np.asarray(msg.action_lower), np.asarray(msg.action_upper)


def diagnostic_status(name, level, message, values, hardware_id=""):
    """``diagnostic_msgs/DiagnosticStatus`` with ``values`` (dict) as key-value strings."""
    status = DiagnosticStatus()
    status.name = name
    status.level = level
    status.message = message
    status.hardware_id = hardware_id
    status.values = [KeyValue(key=str(k), value=_format_value(v)) for k, v in values.items()]
    return status


def _format_value(value):
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
