"""Recorded sessions as rclpy messages: read rosbag2 files with ``rosbags`` and decode them with rclpy.

``rosbags`` reads the bag (mcap or sqlite3 storage) and hands over each message as raw CDR bytes; rclpy's own
``deserialize_message`` turns them into the generated message classes (``sensor_msgs.msg.JointState``,
``body_scheme_msgs.msg.MarkerPoses``, ...), the same objects a subscription callback receives. So a bag fed to
:mod:`body_scheme_nodes.conversions` offline takes exactly the path live messages take in the nodes.

The session layout (topics and types) is the one ``body_scheme_sim`` records; see ``bags/README.md``.
"""

from __future__ import annotations

import json
import pathlib
import struct
from collections.abc import Iterator
from dataclasses import dataclass

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.serde import SerdeError
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import String

from body_scheme_core.errors import BodySchemeError
from body_scheme_msgs.msg import MarkerPoses

from .session_format import SESSION_TOPICS

try:  # the zstd module rosbags decompresses mcap chunks with (Python >= 3.14 has it built in)
    from compression.zstd import ZstdError
except ImportError:
    from backports.zstd import ZstdError

__all__ = ["BagReadError", "BagMessage", "MESSAGE_CLASSES", "SESSION_TOPICS", "bag_topics", "read_messages",
           "session_info"]

#: Message type name (as stored in the bag) -> rclpy message class, for every type a session bag holds.
MESSAGE_CLASSES = {
    "std_msgs/msg/String": String,
    "sensor_msgs/msg/JointState": JointState,
    "sensor_msgs/msg/Image": Image,
    "sensor_msgs/msg/CameraInfo": CameraInfo,
    "body_scheme_msgs/msg/MarkerPoses": MarkerPoses,
}

# What a damaged file raises inside rosbags while reading (chunks that do not decompress, records cut short, message
# bytes that are not CDR).
_CORRUPT = (KeyError, ValueError, IndexError, AssertionError, EOFError, OSError, struct.error, ZstdError, SerdeError)


class BagReadError(BodySchemeError):
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
        raise BagReadError(f"bag {path} does not exist")
    try:
        reader = Reader(path)
        reader.open()
    except ReaderError as error:
        raise BagReadError(f"cannot read bag {path}: {error}") from error
    except _CORRUPT as error:
        raise BagReadError(f"bag {path} is corrupt: {type(error).__name__}: {error}") from error
    return reader


def bag_topics(path):
    """Topics of a bag with their message type and count: ``{topic: (type, count)}``.

    Raises
    ------
    BagReadError
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
        raise BagReadError(f"bag {path}: topic {topic} has type {msgtype}, expected {expected}")
    if msgtype not in MESSAGE_CLASSES:
        raise BagReadError(f"bag {path}: topic {topic} has type {msgtype}, which this reader does not decode "
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
    BagReadError
        At once if the bag is missing or unreadable or a selected topic has an unexpected or unknown type; while
        iterating if the file turns out truncated or corrupt or a message does not decode.
    """
    reader = _open(path)
    try:
        wanted = None if topics is None else set(topics)
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        classes = {c.id: _message_class(path, c.topic, c.msgtype) for c in connections}
    except BagReadError:
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
                    raise BagReadError(f"bag {path}: message {count} (on {connection.topic}) does not decode as "
                                       f"{connection.msgtype}: {error}") from error
                count += 1
                counts[connection.id] += 1
                yield BagMessage(connection.topic, int(log_time), msg)
        # Chunks carry no checksum here, so damaged data can decompress "fine" and lose messages: compare with
        # the counts of the bag's metadata.
        short = {c.topic: f"{counts[c.id]} of {c.msgcount}" for c in connections if counts[c.id] != c.msgcount}
        if short:
            raise BagReadError(f"bag {path} is truncated or corrupt: read {short} messages (per topic)")
    except ReaderError as error:
        raise BagReadError(f"bag {path} is corrupt after {count} messages: {error}") from error
    except _CORRUPT as error:
        raise BagReadError(f"bag {path} is corrupt after {count} messages: {type(error).__name__}: "
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
    BagReadError
        If the bag cannot be read, or the message is not a JSON object.
    """
    messages = read_messages(path, ["/session/info"])
    try:
        first = next(messages, None)
    finally:
        messages.close()
    if first is None:
        return None
    try:
        info = json.loads(first.msg.data)
    except json.JSONDecodeError as error:
        raise BagReadError(f"bag {path}: /session/info is not JSON: {error}") from error
    if not isinstance(info, dict):
        raise BagReadError(f"bag {path}: /session/info is not a JSON object")
    return info
