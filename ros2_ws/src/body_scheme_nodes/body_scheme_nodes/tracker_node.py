"""tracker_node: ArUco marker poses from camera images (the robot's self-observation).

Subscriptions
-------------
camera/image_raw : sensor_msgs/Image  (sensor data QoS; reliable with ``image_reliability: reliable``)
    mono8, rgb8, bgr8, rgba8 or bgra8. Only the latest image is kept; older unprocessed ones are counted as dropped.
camera/camera_info : sensor_msgs/CameraInfo  (same QoS as the images)
    Intrinsics ``k`` and distortion ``d`` (plumb_bob or rational_polynomial); images wait for the first one.

Publishers
----------
observations : body_scheme_msgs/MarkerPoses
    Id and ``camera2marker`` pose of every marker detected in an image, with the image's header (stamp, frame_id);
    published for every processed image, also when no marker is seen (empty arrays).
observations/poses : geometry_msgs/PoseArray
    The same poses without ids (for rviz), same header.
/diagnostics : diagnostic_msgs/DiagnosticArray
    1 Hz ``body_scheme: tracker``: images received / processed / dropped, detections, poses, rejections by reason.

Parameters
----------
marker_size : double 0.08              edge length (m) of every marker not sized otherwise; 0.0: reject those ids
marker_sizes.ids : int[] (unset)       ids with their own edge length ...
marker_sizes.sizes : double[] (unset)  ... and those lengths (m, written as floats), same order
markers_path : string ""               marker placement YAML of the robot (id, link, xyz, rpy, size, plate); its
                                       sizes are used, marker_sizes.* override them; markers with a ``plate``
                                       give one pose per plate, under the plate's id
dictionary : string "DICT_4X4_50"      OpenCV predefined ArUco dictionary
corner_refinement : string "apriltag"  apriltag | subpix | contour | none
min_side_px : double 6.0               smaller detections are rejected
max_reprojection_error : double 2.0    px; worse poses are rejected
max_ambiguity : double 0.8             reject poses whose mirrored IPPE solution reprojects nearly as well (1: off)
corner_sigma_px : double 0.5           px, corner noise behind each pose's covariance on observations (through the
                                       PnP Jacobian: large along the ray, growing with the distance squared)
image_reliability : string best_effort image QoS: best_effort (sensor data) or reliable
process_period : double 0.01 s         period of the detection timer
"""

from __future__ import annotations

import os
import pathlib
import threading
from collections import Counter

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import MarkerTracker, rejection_kind
from body_scheme_core.plates import plates_from_markers
from body_scheme_core.world import load_markers_yaml
from body_scheme_msgs.msg import MarkerPoses

from . import conversions
from .ros_parameters import refuse_parameter_changes
from .spin import run_node

#: Image subscription QoS. Sensor data (best effort) is the ROS convention for cameras; a large image over best
#: effort can be lost in transit (Fast DDS drops frames whose fragments do not all arrive), so with a publisher that
#: offers reliability (sim_node does) ``reliable`` gets every frame.
IMAGE_QOS = {"best_effort": qos_profile_sensor_data,
             "reliable": QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)}


def markers_from_parameters(markers_path, ids, sizes):
    """``({id: edge length}, {plate id: Plate})`` from a marker placement file (its sizes and its markers' ``plate``
    entries), the sizes overridden by the ``ids``/``sizes`` parameter arrays.

    Raises
    ------
    InvalidInputError
        If ``ids`` and ``sizes`` differ in length, or the marker file is missing or invalid.
    """
    if len(ids) != len(sizes):
        raise InvalidInputError(f"marker_sizes.ids has {len(ids)} entries but marker_sizes.sizes has {len(sizes)}")
    markers = []
    if markers_path:
        if not os.path.isfile(markers_path):
            raise InvalidInputError(f"markers_path {markers_path!r} is not a file")
        markers = load_markers_yaml(pathlib.Path(markers_path))
    by_id = {marker.id: marker.size for marker in markers}
    by_id.update({int(i): float(s) for i, s in zip(ids, sizes, strict=True)})
    return by_id, plates_from_markers(markers)


class TrackerNode(Node):
    """ROS wrapper of :class:`body_scheme_core.perception.MarkerTracker` (see the module docstring)."""

    def __init__(self, **node_options):
        super().__init__("tracker_node", **node_options)
        default_size = self.declare_parameter("marker_size", 0.08).value
        sizes, plates = markers_from_parameters(
            self.declare_parameter("markers_path", "").value,
            self.declare_parameter("marker_sizes.ids", Parameter.Type.INTEGER_ARRAY).value or [],
            self.declare_parameter("marker_sizes.sizes", Parameter.Type.DOUBLE_ARRAY).value or [])
        self.options = {
            "marker_sizes": sizes,
            "default_size": default_size if default_size > 0 else None,
            "dictionary": self.declare_parameter("dictionary", "DICT_4X4_50").value,
            "corner_refinement": self.declare_parameter("corner_refinement", "apriltag").value,
            "min_side_px": self.declare_parameter("min_side_px", 6.0).value,
            "max_reprojection_error": self.declare_parameter("max_reprojection_error", 2.0).value,
            "max_ambiguity": self.declare_parameter("max_ambiguity", 0.8).value,
            "corner_sigma_px": self.declare_parameter("corner_sigma_px", 0.5).value,
            "plates": plates,
        }
        process_period = self.declare_parameter("process_period", 0.01).value
        reliability = self.declare_parameter("image_reliability", "best_effort").value
        if reliability not in IMAGE_QOS:
            raise InvalidInputError(f"image_reliability must be one of {sorted(IMAGE_QOS)}, got {reliability!r}")
        # Fail at start-up on a bad dictionary or size, not at the first image.
        MarkerTracker(np.eye(3), **self.options)

        self.tracker = None
        self._camera_key = None
        self._image = None  # latest unprocessed sensor_msgs/Image
        self._info = None  # latest sensor_msgs/CameraInfo
        self._lock = threading.Lock()
        self.counts = Counter()
        self.rejected = Counter()

        work = MutuallyExclusiveCallbackGroup()
        self.create_subscription(Image, "camera/image_raw", self._on_image, IMAGE_QOS[reliability])
        self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, IMAGE_QOS[reliability])
        self.pub_observations = self.create_publisher(MarkerPoses, "observations", 10)
        self.pub_poses = self.create_publisher(PoseArray, "observations/poses", 10)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(process_period, self._process, callback_group=work)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=work)
        refuse_parameter_changes(self)
        others = "rejected" if self.options["default_size"] is None else f"{self.options['default_size']} m"
        self.get_logger().info(f"tracking {self.options['dictionary']} markers; sizes {sizes}, other ids {others}")

    # -- callbacks: buffer only ------------------------------------------------------------------------------------
    def _on_image(self, msg):
        with self._lock:
            if self._image is not None:
                self.counts["dropped"] += 1
            self._image = msg
            self.counts["received"] += 1

    def _on_camera_info(self, msg):
        with self._lock:
            self._info = msg

    # -- timer: detection ------------------------------------------------------------------------------------------
    def _process(self):
        with self._lock:
            msg, info, self._image = self._image, self._info, None
        if msg is None:
            return
        if info is None:
            self.counts["waiting_for_camera_info"] += 1
            self.get_logger().warn("image dropped: no camera_info received yet", throttle_duration_sec=5.0)
            return
        try:
            tracker = self._tracker_for(info)
            image = conversions.image_from_msg(msg)
            detections, rejected = tracker.detect_markers(image)
        except InvalidInputError as error:
            self.rejected["image"] += 1
            self.get_logger().warn(f"image rejected: {error}", throttle_duration_sec=5.0)
            return
        for _, reason in rejected:
            self.rejected[rejection_kind(reason)] += 1
        self.counts["processed"] += 1
        self.counts["poses"] += len(detections)
        self.counts["detections"] += len(detections) + len(rejected)
        markers, array = conversions.tracked_poses_msgs(msg.header, {i: d.pose for i, d in detections.items()},
                                                        {i: d.covariance for i, d in detections.items()})
        self.pub_observations.publish(markers)
        self.pub_poses.publish(array)

    def _tracker_for(self, info):
        """The tracker for this camera; rebuilt only when the intrinsics change."""
        key = (tuple(info.k), tuple(info.d), info.distortion_model)
        if key != self._camera_key:
            self.tracker = MarkerTracker(conversions.camera_from_info(info)[0],
                                         conversions.distortion_from_info(info), **self.options)
            self._camera_key = key
        return self.tracker

    def _publish_diagnostics(self):
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        with self._lock:
            counts = dict(self.counts)
        processed = counts.get("processed", 0)
        if processed == 0:
            level, message = DiagnosticStatus.WARN, "no image processed yet"
        else:
            level, message = DiagnosticStatus.OK, f"{processed} images processed"
        values = {key: counts.get(key, 0) for key in
                  ("received", "processed", "dropped", "waiting_for_camera_info", "detections", "poses")}
        values["rejected_total"] = sum(self.rejected.values())
        values.update({f"rejected.{reason}": count for reason, count in sorted(self.rejected.items())})
        name = self.get_fully_qualified_name()  # node and namespace: two robots in one domain do not collide
        array.status.append(conversions.diagnostic_status(f"{name}: tracker", level, message, values, name))
        self.pub_diagnostics.publish(array)


def main(args=None):
    return run_node(TrackerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
