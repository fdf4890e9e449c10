"""Recording a live ROS graph into a rosbag2 (mcap) file, the way ``ros2 bag record`` would (it is not on PyPI).

:class:`GraphRecorder` subscribes to each topic with ``raw=True`` (the CDR bytes as they came over DDS, not decoded
and re-encoded) and writes them with ``rosbags`` into a zstd-compressed mcap, each channel with its message definition
embedded, so Foxglove, ``ros2 bag play`` and the ``mcap`` library's ROS 2 decoder read it from the file alone.
Latched topics are subscribed transient local, so their last message is recorded even if it was sent before. Each
channel carries its QoS in the bag's metadata (``offered_qos_profiles``, as ``ros2 bag record`` writes it), so a replay
offers latched topics latched again.
"""

from __future__ import annotations

import pathlib
import threading

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

from .bag_io import name_the_distro, typestore
from .qos import LATCHED

__all__ = ["GraphRecorder", "bag_qos"]

_VOLATILE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def bag_qos(profile):
    """The rosbags ``Qos`` of an rclpy ``QoSProfile`` (reliable or best effort, volatile or transient local, keep
    last with its depth); durations are left at the middleware's default (0)."""
    default = QosTime(0, 0)
    return Qos(history=QosHistory.KEEP_LAST, depth=profile.depth,
               reliability=QosReliability.RELIABLE if profile.reliability == ReliabilityPolicy.RELIABLE
               else QosReliability.BEST_EFFORT,
               durability=QosDurability.TRANSIENT_LOCAL if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
               else QosDurability.VOLATILE,
               deadline=default, lifespan=default, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=default, avoid_ros_namespace_conventions=False)


def _type_name(msg_class):
    """``sensor_msgs/msg/JointState`` of an rclpy message class."""
    module = msg_class.__module__.split(".")
    return f"{module[0]}/{module[1]}/{msg_class.__name__}"


class GraphRecorder:
    """Record topics of a running graph into ``path`` (a new rosbag2 directory).

    Parameters
    ----------
    node : rclpy.node.Node
        The node to subscribe with (its executor must spin).
    path : path-like
    topics : iterable of (str, type, bool or QoSProfile)
        Topic name, rclpy message class, and whether it is latched (transient local, the latest message), or the
        publisher's QoS profile (e.g. :data:`~body_scheme_nodes.qos.RECENT_EVENTS`), recorded as offered.
    """

    def __init__(self, node, path, topics):
        self.path = pathlib.Path(path)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._node = node
        self._lock = threading.Lock()
        self.counts = {}
        store = typestore()
        for topic, msg_class, latched in topics:
            name = topic if topic.startswith("/") else f"/{topic}"
            qos = latched if isinstance(latched, QoSProfile) else LATCHED if latched else _VOLATILE
            connection = self._writer.add_connection(name, _type_name(msg_class), typestore=store,
                                                     offered_qos_profiles=[bag_qos(qos)])
            self.counts[name] = 0
            node.create_subscription(msg_class, topic, lambda data, c=connection, n=name: self._write(c, n, data),
                                     qos, raw=True)

    def _write(self, connection, name, data):
        with self._lock:
            if self._writer is None:
                return
            self._writer.write(connection, self._node.get_clock().now().nanoseconds, data)
            self.counts[name] += 1

    def close(self):
        """Finish the file (index, metadata); later messages are ignored."""
        with self._lock:
            if self._writer is not None:
                self._writer.close()
                self._writer = None
                name_the_distro(self.path)
