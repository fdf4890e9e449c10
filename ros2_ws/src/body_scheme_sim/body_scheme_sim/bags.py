"""Babbling sessions as rosbag2 files (mcap storage, zstd chunks), written and read with ``rosbags`` (no ROS needed).

Topics of a session bag (log time = header stamp):

=============================  ====================================  =============================================
topic                          type                                  content, one message per step unless noted
=============================  ====================================  =============================================
``/session/info``              ``std_msgs/msg/String``               once, first: JSON metadata (robot, seed,
                                                                     perception, noise settings, fault timeline,
                                                                     camera pose and intrinsics)
``/joint_commands``            ``sensor_msgs/msg/JointState``        the babbling command, stamped at command time
``/observations``              ``body_scheme_msgs/msg/MarkerPoses``  what the learner sees, stamped at image time
``/ground_truth/marker_poses`` ``body_scheme_msgs/msg/MarkerPoses``  true pose of every marker (evaluation only)
``/ground_truth/joint_states`` ``sensor_msgs/msg/JointState``        joint positions actually reached
``/camera/image_raw``          ``sensor_msgs/msg/Image``             rgb8, only at steps with a stored image
``/camera/camera_info``        ``sensor_msgs/msg/CameraInfo``        with each image
=============================  ====================================  =============================================

Our message types are registered in the rosbags type store from the ``.msg`` files of ``body_scheme_msgs`` (the
installed share directory if ROS is sourced, else the source tree), on top of ROS 2 Jazzy's standard types.

This module maps rosbags' own message classes (plain dataclasses, not rclpy messages), so recording and reading
sessions needs neither rclpy nor a built workspace; the rclpy mapping stays in ``body_scheme_nodes.conversions``.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
import struct

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, ReaderError, StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from body_scheme_core.transforms import pose_from_transform, transform_from_pose
from body_scheme_nodes.session_format import SESSION_TOPICS

try:  # the zstd module rosbags decompresses mcap chunks with (Python >= 3.14 has it built in)
    from compression.zstd import ZstdError
except ImportError:
    from backports.zstd import ZstdError

from .camera import Camera
from .errors import BagError
from .sessions import Session

__all__ = [
    "BagError",
    "SESSION_FORMAT",
    "SESSION_FORMAT_VERSION",
    "TOPICS",
    "typestore",
    "write_bag",
    "read_bag",
    "read_messages",
]

SESSION_FORMAT = "body_scheme/session"
SESSION_FORMAT_VERSION = 1
#: Topic name -> message type of every topic a session bag may hold (the one table, shared with the readers).
TOPICS = SESSION_TOPICS
_REQUIRED_TOPICS = ("/session/info", "/joint_commands", "/observations", "/ground_truth/marker_poses")
_MSG_PACKAGE = "body_scheme_msgs"


# ---------------------------------------------------------------------- type store
def _msg_dir():
    """Directory of body_scheme_msgs' ``.msg`` files: installed share dir if ROS is sourced, else the source tree."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        candidate = pathlib.Path(prefix) / "share" / _MSG_PACKAGE / "msg"
        if prefix and candidate.is_dir():
            return candidate
    source = pathlib.Path(__file__).resolve().parents[2] / _MSG_PACKAGE / "msg"
    if source.is_dir():
        return source
    raise BagError(f"cannot find the .msg files of {_MSG_PACKAGE}: source the workspace (install/local_setup.bash)")


@functools.cache
def typestore():
    """The ROS 2 Jazzy type store with every message of body_scheme_msgs registered."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted(_msg_dir().glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(encoding="utf-8"), f"{_MSG_PACKAGE}/msg/{path.stem}"))
    store.register(types)
    return store


def _msg(msgtype, /, **fields):
    return typestore().types[msgtype](**fields)


# ---------------------------------------------------------------------- mapping to rosbags messages
def _header(stamp_ns, frame_id):
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _msg("std_msgs/msg/Header", stamp=_msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec),
                frame_id=frame_id)


def _stamp_ns(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _joint_state(stamp_ns, names, positions):
    return _msg("sensor_msgs/msg/JointState", header=_header(stamp_ns, ""), name=list(names),
                position=np.asarray(positions, dtype=np.float64), velocity=np.zeros(0), effort=np.zeros(0))


def _marker_poses(stamp_ns, frame_id, poses):
    ids, items = [], []
    for marker_id in sorted(poses):
        position, q = pose_from_transform(poses[marker_id])
        pose = _msg("geometry_msgs/msg/Pose",
                    position=_msg("geometry_msgs/msg/Point", x=position[0], y=position[1], z=position[2]),
                    orientation=_msg("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))
        items.append(_msg("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=np.zeros(36)))
        ids.append(int(marker_id))
    return _msg("body_scheme_msgs/msg/MarkerPoses", header=_header(stamp_ns, frame_id),
                marker_ids=np.array(ids, dtype=np.int64), poses=items)


def _poses_from_msg(msg):
    poses = {}
    for marker_id, item in zip(msg.marker_ids, msg.poses, strict=True):
        p, q = item.pose.position, item.pose.orientation
        poses[int(marker_id)] = transform_from_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
    return poses


def _image(stamp_ns, frame_id, image):
    image = np.ascontiguousarray(image, dtype=np.uint8)
    height, width = image.shape[:2]
    return _msg("sensor_msgs/msg/Image", header=_header(stamp_ns, frame_id), height=height, width=width,
                encoding="rgb8", is_bigendian=0, step=3 * width, data=image.reshape(-1))


def _camera_info(stamp_ns, frame_id, camera):
    K = camera.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = _msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _msg("sensor_msgs/msg/CameraInfo", header=_header(stamp_ns, frame_id), height=camera.height,
                width=camera.width, distortion_model="plumb_bob", d=np.zeros(5), k=K.reshape(-1),
                r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)


def _info(session):
    camera = session.camera
    return {
        "format": SESSION_FORMAT, "format_version": SESSION_FORMAT_VERSION,
        "robot": session.robot, "protocol": session.protocol, "seed": session.seed,
        "perception": session.perception, "sigma_trans": session.sigma_trans, "sigma_rot": session.sigma_rot,
        "visibility": session.visibility, "n_steps": session.n_steps, "frame_id": session.frame_id,
        "joint_names": list(session.joint_names), "marker_ids": [int(i) for i in session.marker_ids],
        "faults": [[int(step), str(description)] for step, description in session.faults],
        "camera": {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
                   "cx": camera.cx, "cy": camera.cy, "world2camera": camera.world2camera.tolist()},
        "tracker_rejected": dict(session.tracker_rejected),
    }


# ---------------------------------------------------------------------- writing
def write_bag(session, path):
    """Write a session as a rosbag2 directory (mcap storage, zstd-compressed chunks).

    Parameters
    ----------
    session : Session
    path : str or os.PathLike
        Bag directory to create; it must not exist yet.

    Returns
    -------
    path : pathlib.Path

    Raises
    ------
    BagError
        If the directory exists already or cannot be written.
    """
    path = pathlib.Path(path)
    store = typestore()
    try:
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        writer.open()
    except (WriterError, OSError) as error:
        raise BagError(f"cannot create bag {path}: {error}") from error
    try:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=store)
                       for topic, msgtype in TOPICS.items()
                       if session.images or topic not in ("/camera/image_raw", "/camera/camera_info")}

        def write(topic, stamp_ns, msg):
            writer.write(connections[topic], int(stamp_ns), store.serialize_cdr(msg, TOPICS[topic]))

        start = int(session.command_stamps[0]) if session.n_steps else 0
        write("/session/info", start, _msg("std_msgs/msg/String", data=json.dumps(_info(session))))
        ids, frame = session.marker_ids, session.frame_id
        for k in range(session.n_steps):
            t_cmd, t_obs = int(session.command_stamps[k]), int(session.observation_stamps[k])
            write("/joint_commands", t_cmd, _joint_state(t_cmd, session.joint_names, session.actions[k]))
            write("/observations", t_obs, _marker_poses(t_obs, frame, session.observations[k]))
            truth = {marker_id: session.true_poses[k, j] for j, marker_id in enumerate(ids)}
            write("/ground_truth/marker_poses", t_obs, _marker_poses(t_obs, frame, truth))
            write("/ground_truth/joint_states", t_obs, _joint_state(t_obs, session.joint_names, session.executed[k]))
            if k in session.images:
                write("/camera/image_raw", t_obs, _image(t_obs, frame, session.images[k]))
                write("/camera/camera_info", t_obs, _camera_info(t_obs, frame, session.camera))
    finally:
        writer.close()
    return path


# ---------------------------------------------------------------------- reading
def read_messages(path):
    """Every message of a bag, decoded: ``{topic: [(log time ns, message), ...]}`` in log-time order.

    Raises
    ------
    BagError
        If the bag is missing, truncated or corrupt, or holds a type the type store does not know.
    """
    path = pathlib.Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    store = typestore()
    messages = {}
    try:
        with Reader(path) as reader:
            for connection in reader.connections:
                messages.setdefault(connection.topic, [])
            for connection, timestamp, raw in reader.messages():
                msg = store.deserialize_cdr(raw, connection.msgtype)
                messages[connection.topic].append((timestamp, msg))
    except ReaderError as error:
        raise BagError(f"cannot read bag {path}: {error}") from error
    except (KeyError, ValueError, IndexError, AssertionError, EOFError, OSError, struct.error, ZstdError,
            SerdeError) as error:
        # Chunks that do not decompress or messages that do not decode: the file was damaged after writing.
        raise BagError(f"bag {path} is corrupt: {type(error).__name__}: {error}") from error
    return messages


def read_bag(path):
    """Read a session bag written by :func:`write_bag`.

    Returns
    -------
    session : Session
        With everything :func:`write_bag` stores (no ``visible_truth``: it is not in the bag).

    Raises
    ------
    BagError
        If the bag is missing, truncated, corrupt, not a session bag, of an unsupported version, or inconsistent
        (different numbers of commands and observations).
    """
    messages = read_messages(path)
    missing = [topic for topic in _REQUIRED_TOPICS if not messages.get(topic)]
    if missing:
        raise BagError(f"bag {path} is not a body scheme session: no messages on {missing}")
    try:
        info = json.loads(messages["/session/info"][0][1].data)
    except json.JSONDecodeError as error:
        raise BagError(f"bag {path}: /session/info is not JSON: {error}") from error
    if info.get("format") != SESSION_FORMAT or info.get("format_version") != SESSION_FORMAT_VERSION:
        raise BagError(f"bag {path} holds {info.get('format')!r} v{info.get('format_version')}; this code reads "
                       f"{SESSION_FORMAT!r} v{SESSION_FORMAT_VERSION}")
    commands = [msg for _, msg in messages["/joint_commands"]]
    observed = [msg for _, msg in messages["/observations"]]
    truth = [msg for _, msg in messages["/ground_truth/marker_poses"]]
    executed = [msg for _, msg in messages.get("/ground_truth/joint_states", [])]
    n = info["n_steps"]
    counts = {"/joint_commands": len(commands), "/observations": len(observed),
              "/ground_truth/marker_poses": len(truth), "/ground_truth/joint_states": len(executed)}
    if any(count != n for count in counts.values()):
        raise BagError(f"bag {path} should hold {n} messages per step topic, got {counts}")
    joint_names = tuple(info["joint_names"])
    marker_ids = tuple(info["marker_ids"])
    true_poses = np.zeros((n, len(marker_ids), 4, 4))
    for k, msg in enumerate(truth):
        poses = _poses_from_msg(msg)
        true_poses[k] = [poses[marker_id] for marker_id in marker_ids]
    images = {}
    observation_stamps = np.array([_stamp_ns(msg.header) for msg in observed], dtype=np.int64)
    for _, msg in messages.get("/camera/image_raw", []):
        k = int(np.searchsorted(observation_stamps, _stamp_ns(msg.header)))
        images[k] = np.array(msg.data, dtype=np.uint8).reshape(msg.height, msg.width, 3)
    camera = info["camera"]
    return Session(
        robot=info["robot"], joint_names=joint_names, marker_ids=marker_ids,
        command_stamps=np.array([_stamp_ns(msg.header) for msg in commands], dtype=np.int64),
        observation_stamps=observation_stamps,
        actions=np.array([msg.position for msg in commands], dtype=float).reshape(n, len(joint_names)),
        executed=np.array([msg.position for msg in executed], dtype=float).reshape(n, len(joint_names)),
        observations=[_poses_from_msg(msg) for msg in observed], true_poses=true_poses,
        faults=[(int(step), description) for step, description in info["faults"]],
        camera=Camera(width=camera["width"], height=camera["height"], fx=camera["fx"], fy=camera["fy"],
                      cx=camera["cx"], cy=camera["cy"], world2camera=np.array(camera["world2camera"])),
        images=images, perception=info["perception"], seed=info["seed"], protocol=info["protocol"],
        sigma_trans=info["sigma_trans"], sigma_rot=info["sigma_rot"], visibility=info["visibility"],
        frame_id=info["frame_id"], tracker_rejected=dict(info["tracker_rejected"]))
