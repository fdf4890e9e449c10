"""The one place where ROS messages become core types and back.

Nothing here keeps state or decides anything: functions take messages or core objects and return the other.
Validation errors are raised as :class:`body_scheme_core.errors.InvalidInputError` so nodes count and report them.
"""

from __future__ import annotations

import json
import math
from collections import Counter

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseArray, PoseWithCovariance
from sensor_msgs.msg import CameraInfo, Image, JointState

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import pose_from_transform, transform_from_pose, transform_from_rotvec
from body_scheme_core.world import Fault
from body_scheme_msgs.msg import BodySchemeStructure, LocalModelInfo, MarkerPoses, ModelSnapshot, SchemeEvent

__all__ = [
    "brief",
    "seconds_from_stamp",
    "stamp_from_seconds",
    "transform_from_pose_msg",
    "pose_msg_from_transform",
    "observations_from_msg",
    "covariances_from_msg",
    "marker_poses_msg",
    "actions_from_joint_state",
    "structure_msg",
    "event_msg",
    "snapshot_msg",
    "scheme_from_snapshot",
    "diagnostic_status",
    "IMAGE_ENCODINGS",
    "image_from_msg",
    "image_msg",
    "camera_from_info",
    "distortion_from_info",
    "tracked_poses_msgs",
    "camera_info_msg",
    "joint_state_msg",
    "fault_from_request",
]

SNAPSHOT_FORMAT = "body_scheme/scheme"
SNAPSHOT_FORMAT_VERSION = 1


def brief(text, limit=300):
    """``text`` cut to ``limit`` characters (with the length it had): what a log line or a reply may carry of a
    message's content, so a hostile request is named, never echoed whole."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


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
    rejected : list of (int, str, str)
        Marker id, reason code (``repeated_id`` or ``invalid_pose``) and detail for every marker that was dropped.

    Raises
    ------
    InvalidInputError
        If ``marker_ids`` and ``poses`` differ in length (the message as a whole is unusable).
    """
    if len(msg.marker_ids) != len(msg.poses):
        raise InvalidInputError(
            f"MarkerPoses has {len(msg.marker_ids)} marker_ids but {len(msg.poses)} poses")
    poses = [item.pose for item in msg.poses]
    # All poses in one vectorised call (the node converts every marker of every message); a message with an invalid
    # pose is redone marker by marker for the per-marker reasons.
    try:
        transforms = transform_from_pose(
            np.array([[p.position.x, p.position.y, p.position.z] for p in poses], dtype=float).reshape(-1, 3),
            np.array([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w] for p in poses],
                     dtype=float).reshape(-1, 4))
    except InvalidInputError:
        transforms = None
    observations, rejected = {}, []
    for index, marker_id in enumerate(msg.marker_ids):
        marker_id = int(marker_id)
        if marker_id in observations:
            rejected.append((marker_id, "repeated_id", "repeated marker id in one message"))
            continue
        try:
            observations[marker_id] = (transforms[index] if transforms is not None
                                       else transform_from_pose_msg(poses[index]))
        except InvalidInputError as error:
            rejected.append((marker_id, "invalid_pose", str(error)))
    return seconds_from_stamp(msg.header.stamp), observations, rejected


def covariances_from_msg(msg, observations):
    """The covariances a ``MarkerPoses`` message gives the markers of ``observations`` (:func:`observations_from_msg`),
    ``{id: (6, 6)}``: each pose's ``covariance`` where it is not all zeros ("not estimated") and its id is not repeated
    (which entry's pose was kept is then not certain). The learner checks them (an unusable one is counted as
    ``bad_covariance`` and its pose weighed by the learned noise)."""
    counts = Counter(int(i) for i in msg.marker_ids)
    return {int(marker_id): np.asarray(item.covariance, dtype=float).reshape(6, 6)
            for marker_id, item in zip(msg.marker_ids, msg.poses, strict=True)
            if int(marker_id) in observations and counts[int(marker_id)] == 1 and any(item.covariance)}


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
        If a joint is missing or named twice, names and positions differ in length, or a value is not finite.
    """
    if len(msg.name) != len(msg.position):
        raise InvalidInputError(f"JointState has {len(msg.name)} names but {len(msg.position)} positions")
    repeated = sorted(name for name, count in Counter(msg.name).items() if count > 1)  # linear in the names
    if repeated:
        raise InvalidInputError(f"JointState names joint(s) {repeated} more than once")
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
    """``ModelSnapshot`` carrying a :class:`~body_scheme_core.prediction.BodyScheme` as JSON (empty if ``None``)."""
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
    from body_scheme_core.prediction import BodyScheme

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


# ---------------------------------------------------------------------- images and cameras (no cv_bridge)
#: Image encodings read and written here: channels per pixel (all 8 bit).
IMAGE_ENCODINGS = {"mono8": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


def image_from_msg(msg):
    """``sensor_msgs/Image`` to a numpy array in RGB channel order (BGR and BGRA are reordered).

    Returns
    -------
    image : ndarray, shape (H, W) for mono8, (H, W, 3) for rgb8/bgr8, (H, W, 4) for rgba8/bgra8, dtype uint8

    Raises
    ------
    InvalidInputError
        If the encoding is not in :data:`IMAGE_ENCODINGS`, or height, width, step and data length disagree.
    """
    channels = IMAGE_ENCODINGS.get(msg.encoding)
    if channels is None:
        raise InvalidInputError(f"image encoding {msg.encoding!r} not supported; use one of {sorted(IMAGE_ENCODINGS)}")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height < 1 or width < 1 or step < width * channels:
        raise InvalidInputError(
            f"image of {height}x{width} {msg.encoding} needs step >= {width * channels}, got {step}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if data.size != height * step:
        raise InvalidInputError(f"image data has {data.size} bytes, expected height * step = {height * step}")
    image = data.reshape(height, step)[:, :width * channels].reshape(height, width, channels)
    if msg.encoding in ("bgr8", "bgra8"):
        image = image[:, :, [2, 1, 0, 3][:channels]]
    return image[:, :, 0] if channels == 1 else image


def image_msg(stamp, frame_id, image):
    """numpy image to ``sensor_msgs/Image``: (H, W) uint8 as mono8, (H, W, 3) as rgb8, (H, W, 4) as rgba8."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3, 4))):
        raise InvalidInputError(f"image must be uint8 of shape (H, W), (H, W, 3) or (H, W, 4), got "
                                f"{image.dtype} {image.shape}")
    channels = 1 if image.ndim == 2 else image.shape[2]
    msg = Image()
    msg.header.stamp = stamp_from_seconds(stamp)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(image.shape[0]), int(image.shape[1])
    msg.encoding = {1: "mono8", 3: "rgb8", 4: "rgba8"}[channels]
    msg.is_bigendian = 0
    msg.step = msg.width * channels
    msg.data = np.ascontiguousarray(image).tobytes()
    return msg


#: Image sides (px) and focal lengths (in image sides: 0.1 is a 157 deg field of view, 100 a 0.6 deg one) a real
#: camera can have; a CameraInfo outside them is a broken driver or a hostile publisher.
IMAGE_SIDE = (8, 65536)
FOCAL_IN_SIDES = (0.1, 100.0)


def camera_from_info(msg):
    """``(K, width, height)`` of a ``sensor_msgs/CameraInfo``, checked for a camera that can exist.

    Raises
    ------
    InvalidInputError
        For an uncalibrated (zero) or non-finite ``K``, an image side outside :data:`IMAGE_SIDE`, a focal length
        outside :data:`FOCAL_IN_SIDES` of the image's larger side or pixels more than 5:1 from square, a principal
        point outside the image, or a skew larger than the focal length.
    """
    K = np.asarray(msg.k, dtype=float).reshape(3, 3)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1.0
            and not np.any(K[2, :2]) and K[1, 0] == 0.0):
        raise InvalidInputError(f"CameraInfo.k is not a calibrated camera matrix: {np.round(K.ravel(), 6).tolist()}")
    width, height = int(msg.width), int(msg.height)
    if not (IMAGE_SIDE[0] <= width <= IMAGE_SIDE[1] and IMAGE_SIDE[0] <= height <= IMAGE_SIDE[1]):
        raise InvalidInputError(f"CameraInfo has an image of {width} x {height} px (each side from {IMAGE_SIDE[0]} "
                                f"to {IMAGE_SIDE[1]})")
    fx, fy, cx, cy, side = K[0, 0], K[1, 1], K[0, 2], K[1, 2], max(width, height)
    if not (FOCAL_IN_SIDES[0] * side <= min(fx, fy) and max(fx, fy) <= FOCAL_IN_SIDES[1] * side
            and 0.2 <= fy / fx <= 5.0):
        raise InvalidInputError(f"CameraInfo focal lengths {fx:.4g}, {fy:.4g} px are implausible for a {width} x "
                                f"{height} image ({FOCAL_IN_SIDES[0]} to {FOCAL_IN_SIDES[1]} times its larger side)")
    if not (0.0 < cx < width and 0.0 < cy < height) or abs(K[0, 1]) > fx:
        raise InvalidInputError(f"CameraInfo principal point ({cx:.4g}, {cy:.4g}) or skew {K[0, 1]:.4g} is "
                                f"implausible for a {width} x {height} image")
    return K, width, height


def distortion_from_info(msg):
    """OpenCV distortion coefficients of a ``sensor_msgs/CameraInfo`` (plumb_bob / rational_polynomial), or None.

    Raises
    ------
    InvalidInputError
        For a distortion model OpenCV's pinhole functions do not implement.
    """
    d = np.asarray(msg.d, dtype=float)
    if d.size == 0 or not np.any(d):
        return None
    if msg.distortion_model not in ("plumb_bob", "rational_polynomial"):
        raise InvalidInputError(f"distortion model {msg.distortion_model!r} not supported (plumb_bob, "
                                "rational_polynomial)")
    return d


def tracked_poses_msgs(header, poses, covariances=None):
    """``(MarkerPoses, PoseArray)`` of tracked ``{id: camera2marker}``, both carrying ``header`` unchanged;
    ``covariances``: ``{id: (6, 6)}`` over (x, y, z, rot_x, rot_y, rot_z) into each pose's covariance.

    The image's header is copied as is (not through float seconds) so that consumers can match stamps exactly.
    """
    markers = marker_poses_msg(0.0, header.frame_id, poses)
    markers.header = header
    for marker_id, item in zip(markers.marker_ids, markers.poses, strict=True):
        if covariances is not None and marker_id in covariances:
            item.covariance = np.asarray(covariances[marker_id], dtype=float).ravel().tolist()
    array = PoseArray(header=header)
    array.poses = [item.pose for item in markers.poses]
    return markers, array


# ---------------------------------------------------------------------- simulator (sim_node)
def camera_info_msg(stamp, frame_id, width, height, K):
    """``sensor_msgs/CameraInfo`` of an undistorted pinhole camera with intrinsic matrix ``K`` (3, 3)."""
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InvalidInputError(f"K must be a finite (3, 3) matrix, got {K.tolist()}")
    msg = CameraInfo()
    msg.header.stamp = stamp_from_seconds(stamp)
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(width), int(height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = K.ravel().tolist()
    msg.r = np.eye(3).ravel().tolist()
    msg.p = np.hstack([K, np.zeros((3, 1))]).ravel().tolist()
    return msg


def joint_state_msg(stamp, joint_names, positions):
    """``sensor_msgs/JointState`` command: ``positions`` (m,) by ``joint_names`` (the inverse of
    :func:`actions_from_joint_state`)."""
    positions = np.asarray(positions, dtype=float)
    if positions.shape != (len(joint_names),):
        raise InvalidInputError(f"{len(joint_names)} joint names but positions of shape {positions.shape}")
    msg = JointState(name=list(joint_names), position=[float(v) for v in positions])
    msg.header.stamp = stamp_from_seconds(stamp)
    return msg


def fault_from_request(request):
    """A ``body_scheme_msgs/InjectFault`` request as a :class:`body_scheme_core.world.Fault` (for ``SimWorld.apply``).

    Raises
    ------
    InvalidInputError
        For an unknown kind, a non-finite ``delta``, or a deform_limb request with a translation in ``delta``.
    """
    kind = request.kind
    delta = np.asarray(request.delta, dtype=float)
    if delta.shape != (6,) or not np.all(np.isfinite(delta)):
        raise InvalidInputError(f"delta must be 6 finite numbers, got {delta.tolist()}")
    if kind == "block_joint":
        angle = float(request.angle)
        return Fault(kind, action_index=int(request.action_index), angle=None if math.isnan(angle) else angle)
    if kind == "deform_limb":
        if np.any(delta[:3]):
            raise InvalidInputError("deform_limb takes the length change from delta_length and the bend from "
                                    f"delta[3:6]; delta[0:3] must be zero, got {delta[:3].tolist()}")
        return Fault(kind, joint_or_link=request.joint_name, delta_length=float(request.delta_length),
                     delta_rotvec=delta[3:].tolist())
    if kind == "displace_marker":
        return Fault(kind, marker_id=int(request.marker_id), delta=transform_from_rotvec(delta[3:], delta[:3]))
    if kind == "repair":
        return Fault(kind, repair_kind=request.repair_kind or None)
    raise InvalidInputError(
        f"unknown fault kind {kind!r}; kinds: block_joint, deform_limb, displace_marker, repair")
