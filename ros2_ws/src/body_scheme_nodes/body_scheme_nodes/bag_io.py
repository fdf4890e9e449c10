"""Bag I/O: babbling sessions as rosbag2 files (mcap, zstd chunks), written and read as rclpy messages.

``rosbags`` reads and writes the files and hands over each message as raw CDR bytes; rclpy's own
``serialize_message`` / ``deserialize_message`` turn the generated message classes (``sensor_msgs.msg.JointState``,
``body_scheme_msgs.msg.MarkerPoses``, ...) into those bytes and back, and :mod:`body_scheme_nodes.conversions` builds
and reads them. So a bag fed to the nodes' code offline takes exactly the path live messages take, and a message is
built in one place whether it is published or recorded.

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

Readers: :func:`read_messages` (any bag, lazily, in log-time order), :func:`bag_topics`, :func:`session_info` and
:func:`read_session` (a whole session bag back into a :class:`~body_scheme_core.world.Session`). Writer:
:func:`write_session`. See ``bags/README.md``.
"""


from __future__ import annotations

import functools
import json
import os
import pathlib
import struct
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, PoseArray, PoseStamped, PoseWithCovarianceStamped, TransformStamped
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, ReaderError, StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from trajectory_msgs.msg import JointTrajectory

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.world import Session
from body_scheme_msgs.msg import MarkerPoses

from . import conversions

try:  # the zstd module rosbags decompresses mcap chunks with (Python >= 3.14 has it built in)
    from compression.zstd import ZstdError
except ImportError:
    from backports.zstd import ZstdError

__all__ = ["BagError", "BagMessage", "MESSAGE_CLASSES", "SESSION_TOPICS", "SESSION_FORMAT", "SESSION_FORMAT_VERSION",
           "bag_topics", "read_messages", "session_info", "read_session", "write_session", "typestore",
           "name_the_distro", "cdr_bytes"]

#: Topic -> message type of every topic a session bag may hold.
SESSION_TOPICS = {
    "/session/info": "std_msgs/msg/String",
    "/joint_commands": "sensor_msgs/msg/JointState",
    "/observations": "body_scheme_msgs/msg/MarkerPoses",
    "/ground_truth/marker_poses": "body_scheme_msgs/msg/MarkerPoses",
    "/ground_truth/joint_states": "sensor_msgs/msg/JointState",
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
}
SESSION_FORMAT = "body_scheme/session"
SESSION_FORMAT_VERSION = 1
_REQUIRED_TOPICS = ("/session/info", "/joint_commands", "/observations", "/ground_truth/marker_poses")
_IMAGE_TOPICS = ("/camera/image_raw", "/camera/camera_info")
_MSG_PACKAGE = "body_scheme_msgs"

#: Message type name (as stored in the bag) -> rclpy message class: every type a session bag holds, and those of
#: other stacks' recordings that a source map reads (:mod:`.sources`).
MESSAGE_CLASSES = {
    "std_msgs/msg/String": String,
    "sensor_msgs/msg/JointState": JointState,
    "sensor_msgs/msg/Image": Image,
    "sensor_msgs/msg/CameraInfo": CameraInfo,
    "body_scheme_msgs/msg/MarkerPoses": MarkerPoses,
    "trajectory_msgs/msg/JointTrajectory": JointTrajectory,
    "tf2_msgs/msg/TFMessage": TFMessage,
    "geometry_msgs/msg/PoseStamped": PoseStamped,
    "geometry_msgs/msg/PoseWithCovarianceStamped": PoseWithCovarianceStamped,
    "geometry_msgs/msg/TransformStamped": TransformStamped,
    "geometry_msgs/msg/PoseArray": PoseArray,
    "geometry_msgs/msg/PointStamped": PointStamped,
}

# What a damaged file raises inside rosbags while reading (chunks that do not decompress, records cut short, message
# bytes that are not CDR, a record size garbled into a number no seek takes).
_CORRUPT = (KeyError, ValueError, IndexError, AssertionError, EOFError, OSError, OverflowError, struct.error,
            ZstdError, SerdeError)


class BagError(BodySchemeError):
    """A bag is missing, truncated or corrupt, or holds a topic of an unexpected or unknown type."""


@dataclass(frozen=True)
class BagMessage:
    """One decoded message of a bag.

    Attributes
    ----------
    topic : str
        Topic name as recorded (absolute, e.g. ``/observations``).
    log_time : int
        Time the message was recorded, ns.
    msg : object
        The rclpy message (an instance of ``MESSAGE_CLASSES[type]``).
    """

    topic: str
    log_time: int
    msg: object


def _open(path):
    path = pathlib.Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    try:
        reader = Reader(path)
        reader.open()
    except ReaderError as error:
        raise BagError(f"cannot read bag {path}: {error}") from error
    except _CORRUPT as error:
        raise BagError(f"bag {path} is corrupt: {type(error).__name__}: {error}") from error
    return reader


def bag_topics(path):
    """Topics of a bag with their message type and count: ``{topic: (type, count)}``.

    Raises
    ------
    BagError
        If the bag is missing or its metadata or index cannot be read.
    """
    reader = _open(path)
    try:
        topics = {}
        for connection in reader.connections:
            _, count = topics.get(connection.topic, (connection.msgtype, 0))
            topics[connection.topic] = (connection.msgtype, count + connection.msgcount)
        return topics
    finally:
        reader.close()


def _message_class(path, topic, msgtype):
    expected = SESSION_TOPICS.get(topic)
    if expected is not None and msgtype != expected:
        raise BagError(f"bag {path}: topic {topic} has type {msgtype}, expected {expected}")
    if msgtype not in MESSAGE_CLASSES:
        raise BagError(f"bag {path}: topic {topic} has type {msgtype}, which this reader does not decode "
                           f"(known: {sorted(MESSAGE_CLASSES)})")
    return MESSAGE_CLASSES[msgtype]


def read_messages(path, topics=None):
    """Decoded messages of a bag, in log-time order (ties in recording order).

    The bag is opened and its topics are checked at once; messages are read and decoded lazily while iterating.

    Parameters
    ----------
    path : str or os.PathLike
        rosbag2 directory.
    topics : iterable of str, optional
        Topics to read; topics the bag does not have are skipped (see :func:`bag_topics`). Default: every topic.

    Returns
    -------
    messages : iterator of BagMessage

    Raises
    ------
    BagError
        At once if the bag is missing or unreadable or a selected topic has an unexpected or unknown type; while
        iterating if the file turns out truncated or corrupt or a message does not decode.
    """
    reader = _open(path)
    try:
        wanted = None if topics is None else set(topics)
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        classes = {c.id: _message_class(path, c.topic, c.msgtype) for c in connections}
    except BagError:
        reader.close()
        raise
    return _decoded(reader, pathlib.Path(path), connections, classes)


def _decoded(reader, path, connections, classes) -> Iterator[BagMessage]:
    count = 0
    counts = dict.fromkeys(classes, 0)
    try:
        if connections:
            for connection, log_time, raw in reader.messages(connections=connections):
                try:
                    msg = deserialize_message(raw, classes[connection.id])
                except _rclpy.RMWError as error:
                    raise BagError(f"bag {path}: message {count} (on {connection.topic}) does not decode as "
                                       f"{connection.msgtype}: {error}") from error
                count += 1
                counts[connection.id] += 1
                yield BagMessage(connection.topic, int(log_time), msg)
        # Chunks carry no checksum here, so damaged data can decompress "fine" and lose messages: compare with
        # the counts of the bag's metadata.
        short = {c.topic: f"{counts[c.id]} of {c.msgcount}" for c in connections if counts[c.id] != c.msgcount}
        if short:
            raise BagError(f"bag {path} is truncated or corrupt: read {short} messages (per topic)")
    except ReaderError as error:
        raise BagError(f"bag {path} is corrupt after {count} messages: {error}") from error
    except _CORRUPT as error:
        raise BagError(f"bag {path} is corrupt after {count} messages: {type(error).__name__}: "
                           f"{error}") from error
    finally:
        reader.close()


def session_info(path):
    """The session metadata of ``/session/info`` (robot, seed, protocol, fault timeline, ...), or None.

    Returns
    -------
    info : dict or None
        The parsed JSON; None if the bag has no ``/session/info`` message.

    Raises
    ------
    BagError
        If the bag cannot be read, or the message is not a JSON object.
    """
    messages = read_messages(path, ["/session/info"])
    try:
        first = next(messages, None)
    finally:
        messages.close()
    if first is None:
        return None
    return _parsed_info(path, first.msg)


# ---------------------------------------------------------------------- sessions
def read_session(path):
    """Read a session bag written by :func:`write_session`.

    Returns
    -------
    session : body_scheme_core.world.Session
        With everything :func:`write_session` stores (no ``visible_truth``: it is not in the bag).

    Raises
    ------
    BagError
        If the bag is missing, truncated, corrupt, not a session bag, of an unsupported version, or inconsistent
        (different numbers of commands and observations).
    """
    messages = {}
    for item in read_messages(path):
        messages.setdefault(item.topic, []).append(item.msg)
    missing = [topic for topic in _REQUIRED_TOPICS if not messages.get(topic)]
    if missing:
        raise BagError(f"bag {path} is not a body scheme session: no messages on {missing}")
    info = _parsed_info(path, messages["/session/info"][0])
    if info.get("format") != SESSION_FORMAT or info.get("format_version") != SESSION_FORMAT_VERSION:
        raise BagError(f"bag {path} holds {info.get('format')!r} v{info.get('format_version')}; this code reads "
                           f"{SESSION_FORMAT!r} v{SESSION_FORMAT_VERSION}")
    commands, observed = messages["/joint_commands"], messages["/observations"]
    truth, executed = messages["/ground_truth/marker_poses"], messages.get("/ground_truth/joint_states", [])
    n = info["n_steps"]
    counts = {"/joint_commands": len(commands), "/observations": len(observed),
              "/ground_truth/marker_poses": len(truth), "/ground_truth/joint_states": len(executed)}
    if any(count != n for count in counts.values()):
        raise BagError(f"bag {path} should hold {n} messages per step topic, got {counts}")
    joint_names, marker_ids = tuple(info["joint_names"]), tuple(info["marker_ids"])
    true_poses = np.zeros((n, len(marker_ids), 4, 4))
    for k, msg in enumerate(truth):
        poses = _poses(msg)
        true_poses[k] = [poses[marker_id] for marker_id in marker_ids]
    observation_stamps = np.array([_stamp_ns(msg.header.stamp) for msg in observed], dtype=np.int64)
    images = {int(np.searchsorted(observation_stamps, _stamp_ns(msg.header.stamp))): conversions.image_from_msg(msg)
              for msg in messages.get("/camera/image_raw", [])}
    from body_scheme_sim.camera import Camera  # a simulator's session: only then the simulator's camera model

    camera = info["camera"]
    return Session(
        robot=info["robot"], joint_names=joint_names, marker_ids=marker_ids,
        command_stamps=np.array([_stamp_ns(msg.header.stamp) for msg in commands], dtype=np.int64),
        observation_stamps=observation_stamps,
        actions=np.array([msg.position for msg in commands], dtype=float).reshape(n, len(joint_names)),
        executed=np.array([msg.position for msg in executed], dtype=float).reshape(n, len(joint_names)),
        observations=[_poses(msg) for msg in observed], true_poses=true_poses,
        faults=[(int(step), description) for step, description in info["faults"]],
        camera=Camera(width=camera["width"], height=camera["height"], fx=camera["fx"], fy=camera["fy"],
                      cx=camera["cx"], cy=camera["cy"], world2camera=np.array(camera["world2camera"])),
        images=images, perception=info["perception"], seed=info["seed"], protocol=info["protocol"],
        sigma_trans=info["sigma_trans"], sigma_rot=info["sigma_rot"], visibility=info["visibility"],
        frame_id=info["frame_id"], tracker_rejected=dict(info["tracker_rejected"]))


def write_session(session, path):
    """Write a session as a rosbag2 directory (mcap storage, zstd-compressed chunks).

    Parameters
    ----------
    session : body_scheme_core.world.Session
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
    try:
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        writer.open()
    except (WriterError, OSError) as error:
        raise BagError(f"cannot create bag {path}: {error}") from error
    try:
        store = typestore()
        connections = {topic: writer.add_connection(topic, msgtype, typestore=store)
                       for topic, msgtype in SESSION_TOPICS.items() if session.images or topic not in _IMAGE_TOPICS}

        def write(topic, stamp_ns, msg):
            if hasattr(msg, "header"):
                msg.header.stamp = _time(stamp_ns)
            writer.write(connections[topic], int(stamp_ns), cdr_bytes(msg, SESSION_TOPICS[topic], store))

        start = int(session.command_stamps[0]) if session.n_steps else 0
        write("/session/info", start, String(data=json.dumps(_info(session))))
        ids, frame, names = session.marker_ids, session.frame_id, session.joint_names
        for k in range(session.n_steps):
            t_cmd, t_obs = int(session.command_stamps[k]), int(session.observation_stamps[k])
            write("/joint_commands", t_cmd, conversions.joint_state_msg(0.0, names, session.actions[k]))
            write("/observations", t_obs, conversions.marker_poses_msg(0.0, frame, session.observations[k]))
            truth = {marker_id: session.true_poses[k, j] for j, marker_id in enumerate(ids)}
            write("/ground_truth/marker_poses", t_obs, conversions.marker_poses_msg(0.0, frame, truth))
            write("/ground_truth/joint_states", t_obs, conversions.joint_state_msg(0.0, names, session.executed[k]))
            if k in session.images:
                camera = session.camera
                write("/camera/image_raw", t_obs, conversions.image_msg(0.0, frame, session.images[k]))
                write("/camera/camera_info", t_obs,
                      conversions.camera_info_msg(0.0, frame, camera.width, camera.height, camera.K))
    finally:
        writer.close()
    name_the_distro(path)
    return path


def cdr_bytes(msg, msgtype, store):
    """The CDR bytes of rclpy message ``msg`` of type ``msgtype`` (``sensor_msgs/msg/JointState``), as every bag
    reader takes them.

    rclpy's ``serialize_message`` of the PyPI wheels returns bytes past the end of the CDR stream (164 for a 6-joint
    JointState of 156, the extra ones uninitialised), which rosbags' reader and the mcap ROS 2 decoder refuse ("CDR
    message size mismatch"). The stream is read back with rosbags' deserializer, which says where it ends, and cut
    there.
    """
    raw = serialize_message(msg)
    msgdef = store.get_msgdef(msgtype)
    deserialize = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
    _, end = deserialize(memoryview(raw)[4:], 0, msgdef.cls, store)
    return raw[:4 + end]


#: The ROS distribution our bags are written for (rosbags writes its own name into ``metadata.yaml``).
ROS_DISTRO = "jazzy"


def name_the_distro(path):
    """Put ``ros_distro: jazzy`` into the bag's ``metadata.yaml`` (rosbags writes ``rosbags`` there)."""
    metadata = pathlib.Path(path) / "metadata.yaml"
    text = metadata.read_text()
    metadata.write_text(text.replace("ros_distro: rosbags", f"ros_distro: {ROS_DISTRO}"))


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


def _parsed_info(path, msg):
    try:
        info = json.loads(msg.data)
    except json.JSONDecodeError as error:
        raise BagError(f"bag {path}: /session/info is not JSON: {error}") from error
    if not isinstance(info, dict):
        raise BagError(f"bag {path}: /session/info is not a JSON object")
    return info


def _poses(msg):
    return conversions.observations_from_msg(msg)[1]


def _time(stamp_ns):
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def _stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


# ---------------------------------------------------------------------- type store (message definitions for the writer)
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
    """The rosbags ROS 2 Jazzy type store with body_scheme_msgs registered: the definitions a bag's schema records."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted(_msg_dir().glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(encoding="utf-8"), f"{_MSG_PACKAGE}/msg/{path.stem}"))
    store.register(types)
    return store
