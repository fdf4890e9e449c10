"""tracker_node's message side: image and camera-info conversions, marker sizes and its parameter file (no DDS)."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
import rclpy
import yaml
from sensor_msgs.msg import CameraInfo

from body_scheme_core.errors import InvalidInputError
from body_scheme_nodes import conversions
from body_scheme_nodes.tracker_node import TrackerNode, markers_from_parameters

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
SIZE = 0.08
#: The marker frame facing the camera: marker x = camera x, marker y = camera -y, marker z = camera -z.
FACING_CAMERA = np.diag([1.0, -1.0, -1.0])


@pytest.mark.parametrize("shape", [(6, 5), (6, 5, 3), (6, 5, 4)])
def test_image_message_round_trip(shape):
    """image_msg then image_from_msg gives back the same pixels, stamp and frame."""
    image = np.random.default_rng(0).integers(0, 256, size=shape, dtype=np.uint8)
    msg = conversions.image_msg(12.5, "camera_optical", image)
    assert msg.header.frame_id == "camera_optical" and conversions.seconds_from_stamp(msg.header.stamp) == 12.5
    np.testing.assert_array_equal(conversions.image_from_msg(msg), image)


def test_bgr_and_padded_images_are_read_as_rgb():
    """bgr8 images come back in RGB order, and row padding (step > width * channels) is skipped."""
    rgb = np.random.default_rng(1).integers(0, 256, size=(4, 3, 3), dtype=np.uint8)
    msg = conversions.image_msg(0.0, "camera", rgb[:, :, ::-1])
    msg.encoding = "bgr8"
    np.testing.assert_array_equal(conversions.image_from_msg(msg), rgb)
    padded = np.zeros((4, 16), dtype=np.uint8)
    padded[:, :9] = rgb.reshape(4, 9)
    msg.encoding, msg.step, msg.data = "rgb8", 16, padded.tobytes()
    np.testing.assert_array_equal(conversions.image_from_msg(msg), rgb)


def test_inconsistent_image_messages_are_rejected():
    """Unknown encodings and data lengths that do not match height * step raise InvalidInputError."""
    msg = conversions.image_msg(0.0, "camera", np.zeros((4, 3), dtype=np.uint8))
    msg.encoding = "16UC1"
    with pytest.raises(InvalidInputError, match="encoding"):
        conversions.image_from_msg(msg)
    msg.encoding, msg.data = "mono8", bytes(11)
    with pytest.raises(InvalidInputError, match="bytes"):
        conversions.image_from_msg(msg)


def test_camera_info_gives_intrinsics_and_rejects_uncalibrated():
    """camera_from_info reads K and the image size; an all-zero K (uncalibrated camera) raises."""
    info = CameraInfo(k=K.ravel().tolist(), d=[0.0] * 5, distortion_model="plumb_bob", width=640, height=480)
    camera = conversions.camera_from_info(info)
    np.testing.assert_array_equal(camera[0], K)
    assert camera[1:] == (640, 480) and conversions.distortion_from_info(info) is None
    info.d = [0.1, 0.0, 0.0, 0.0, 0.0]
    np.testing.assert_array_equal(conversions.distortion_from_info(info), info.d)
    with pytest.raises(InvalidInputError, match="calibrated"):
        conversions.camera_from_info(CameraInfo())


@pytest.mark.parametrize("width, height, k, match", [
    (1, 1, [500.0, 0, 0.5, 0, 500.0, 0.5, 0, 0, 1], "image of 1 x 1"),
    (640, 480, [1e300, 0, 320, 0, 1e300, 240, 0, 0, 1], "focal lengths"),
    (640, 480, [2.0, 0, 320, 0, 2.0, 240, 0, 0, 1], "focal lengths"),
    (640, 480, [500.0, 0, -1e6, 0, 500.0, 240, 0, 0, 1], "principal point"),
    (640, 480, [500.0, 0, 320, 0, 5000.0, 240, 0, 0, 1], "focal lengths"),
    (0, 480, [500.0, 0, 320, 0, 500.0, 240, 0, 0, 1], "image of 0 x 480")])
def test_a_camera_that_cannot_exist_is_refused(width, height, k, match):
    """A 1 x 1 image, a focal length of 1e300 or 2 px, a principal point far outside the image, 10:1 pixels."""
    with pytest.raises(InvalidInputError, match=match):
        conversions.camera_from_info(CameraInfo(k=k, width=width, height=height))


# ---------------------------------------------------------------------- tracker_node configuration
def test_marker_sizes_and_plates_come_from_the_marker_file_and_overrides(tmp_path):
    """Sizes are read from the robot's marker file; the ids/sizes parameters override single ids; markers that name
    a plate make one."""
    markers_path = tmp_path / "arm.markers.yaml"
    markers_path.write_text("markers:\n- {id: 1, link: base, size: 0.1}\n- {id: 7, link: tool, size: 0.08}\n"
                            "- {id: 8, link: tool}\n- {id: 10, link: tool, plate: 10}\n"
                            "- {id: 11, link: tool, xyz: [0.06, 0, 0], plate: 10}\n")
    sizes, plates = markers_from_parameters(str(markers_path), [7, 9], [0.05, 0.12])
    assert sizes == {1: 0.1, 7: 0.05, 8: 0.05, 9: 0.12, 10: 0.05, 11: 0.05}  # the file format's default, 0.05 m
    assert list(plates) == [10] and sorted(plates[10].tags) == [10, 11]
    assert np.allclose(plates[10].tags[11][1][:3, 3], [0.06, 0.0, 0.0])
    with pytest.raises(InvalidInputError, match="2 entries"):
        markers_from_parameters("", [1, 2], [0.05])
    with pytest.raises(InvalidInputError, match="not a file"):
        markers_from_parameters(str(tmp_path / "missing.yaml"), [], [])


def test_config_yaml_holds_the_node_defaults():
    """config/tracker_node.yaml lists every parameter tracker_node declares, at its default value."""
    config = pathlib.Path(__file__).resolve().parents[1] / "config" / "tracker_node.yaml"
    documented = yaml.safe_load(config.read_text())["/**"]["ros__parameters"]
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = TrackerNode(context=context)
        built_in = {"use_sim_time", "start_type_description_service"}
        declared = {name: parameter.value for name, parameter in node._parameters.items()
                    if name not in built_in and parameter.value is not None}  # unset: marker_sizes.*
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert documented == declared


