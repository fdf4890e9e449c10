"""Tests of the ArUco marker tracker and the image conversions it is fed through (no DDS)."""

from __future__ import annotations

import math
import pathlib

import cv2
import numpy as np
import pytest
import rclpy
import yaml
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import rotational_error
from body_scheme_nodes import conversions
from body_scheme_nodes.tracker import (
    DOCUMENTED_DETECTION_RATE,
    DOCUMENTED_ROT_ERROR_MEDIAN,
    DOCUMENTED_ROT_ERROR_P90,
    DOCUMENTED_TRANS_ERROR_MEDIAN,
    DOCUMENTED_TRANS_ERROR_P90,
    MarkerTracker,
    marker_object_points,
)
from body_scheme_nodes.tracker_node import TrackerNode, marker_sizes_from_parameters
from body_scheme_sim.babbling import babble
from body_scheme_sim.world import SimWorld

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
SIZE = 0.08
#: The marker frame facing the camera: marker x = camera x, marker y = camera -y, marker z = camera -z.
FACING_CAMERA = np.diag([1.0, -1.0, -1.0])


def marker_pose(x, y, z, rotvec=(0.0, 0.0, 0.0)):
    """``camera2marker`` at ``(x, y, z)``, tilted by ``rotvec`` away from facing the camera."""
    camera2marker = np.eye(4)
    camera2marker[:3, :3] = FACING_CAMERA @ Rotation.from_rotvec(rotvec).as_matrix()
    camera2marker[:3, 3] = (x, y, z)
    return camera2marker


def draw_marker(image, camera2marker, marker_id, size=SIZE, quiet_zone=0.25):
    """Warp ArUco marker ``marker_id`` (with a white quiet zone) into the grayscale ``image`` at its true pose."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    pixels = 240
    texture = cv2.aruco.generateImageMarker(dictionary, marker_id, pixels)
    border = int(round(quiet_zone * pixels))
    texture = cv2.copyMakeBorder(texture, border, border, border, border, cv2.BORDER_CONSTANT, value=255)
    n = texture.shape[0]
    corners = marker_object_points(size * (1.0 + 2.0 * quiet_zone))
    projected, _ = cv2.projectPoints(corners, cv2.Rodrigues(camera2marker[:3, :3])[0], camera2marker[:3, 3], K, None)
    # Texture pixel centres are integers, so its outer edges lie half a pixel outside them.
    source = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]], dtype=np.float32)
    H = cv2.getPerspectiveTransform(source, projected.reshape(4, 2).astype(np.float32))
    size_wh = (image.shape[1], image.shape[0])
    warped = cv2.warpPerspective(texture, H, size_wh, flags=cv2.INTER_LINEAR).astype(float)
    alpha = cv2.warpPerspective(np.ones_like(texture, dtype=np.float32), H, size_wh, flags=cv2.INTER_LINEAR)
    image[:] = np.clip(alpha * warped + (1.0 - alpha) * image, 0, 255).astype(np.uint8)
    return image


def scene(rng, n_markers=4):
    """A gray 640x480 image with ``n_markers`` non-overlapping markers 1.6-2.4 m away; returns (image, truth)."""
    image = np.full((480, 640), 110, dtype=np.uint8)
    truth = {}
    columns = rng.permutation(6)[:n_markers]
    for marker_id, column in zip(range(1, n_markers + 1), columns, strict=True):
        z = rng.uniform(1.6, 2.4)
        x = (column - 2.5) * 0.2 * z / 2.0
        truth[marker_id] = marker_pose(x, rng.uniform(-0.3, 0.3), z, rng.normal(0.0, 0.35, 3))
        draw_marker(image, truth[marker_id], marker_id)
    return image, truth


def pose_errors(estimate, truth):
    """Translational (m) and rotational (rad) error of one pose."""
    trans = np.linalg.norm(estimate[:3, 3] - truth[:3, 3])
    rot = Rotation.from_matrix(estimate[:3, :3].T @ truth[:3, :3]).magnitude()
    return trans, rot


def test_object_points_follow_the_detector_corner_order():
    """The corners IPPE_SQUARE needs are in the order in which ArucoDetector reports a marker's image corners."""
    image = np.full((480, 640), 110, dtype=np.uint8)
    camera2marker = marker_pose(0.05, -0.02, 1.0, (0.2, -0.3, 0.4))
    draw_marker(image, camera2marker, 3)
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = detector.detectMarkers(image)
    assert ids.ravel().tolist() == [3]
    expected, _ = cv2.projectPoints(marker_object_points(SIZE), cv2.Rodrigues(camera2marker[:3, :3])[0],
                                    camera2marker[:3, 3], K, None)
    np.testing.assert_allclose(corners[0].reshape(4, 2), expected.reshape(4, 2), atol=1.5)


def test_detects_every_visible_marker_with_its_pose():
    """Every marker drawn into the image is found with its id, and its pose is close to the true one."""
    rng = np.random.default_rng(0)
    tracker = MarkerTracker(K, marker_sizes=SIZE)
    image, truth = scene(rng)
    poses, rejected = tracker.detect(image)
    assert rejected == []
    assert sorted(poses) == sorted(truth)
    for marker_id, camera2marker in poses.items():
        trans, rot = pose_errors(camera2marker, truth[marker_id])
        assert trans < 0.03 and rot < math.radians(10.0), (marker_id, trans, rot)


def test_pose_error_on_warped_markers_is_small():
    """On markers warped into images at known poses, translation p90 < 3 cm and rotation median < 2 deg."""
    rng = np.random.default_rng(1)
    tracker = MarkerTracker(K, marker_sizes=SIZE, max_ambiguity=1.0)  # every detection, ambiguous or not
    errors = []
    for _ in range(15):
        image, truth = scene(rng)
        poses, _ = tracker.detect(image)
        errors += [pose_errors(poses[i], truth[i]) for i in poses]
    errors = np.array(errors)
    assert len(errors) >= 0.95 * 15 * 4
    assert np.percentile(errors[:, 0], 90) <= 0.03
    assert np.median(errors[:, 1]) <= math.radians(2.0)


def test_rgb_gray_and_rgba_images_give_the_same_poses():
    """The tracker accepts grayscale, (H, W, 1), RGB and RGBA images and finds the same poses in each."""
    rng = np.random.default_rng(2)
    tracker = MarkerTracker(K, marker_sizes=SIZE)
    gray, _ = scene(rng, n_markers=2)
    variants = [gray[:, :, None], np.repeat(gray[:, :, None], 3, axis=2),
                np.dstack([gray, gray, gray, np.full_like(gray, 255)])]
    reference, _ = tracker.detect(gray)
    for image in variants:
        poses, _ = tracker.detect(image)
        assert sorted(poses) == sorted(reference)
        for marker_id in poses:
            np.testing.assert_allclose(poses[marker_id], reference[marker_id], atol=1e-9)


@pytest.mark.parametrize("image, message", [
    (np.zeros((48, 64), dtype=np.float32), "dtype uint8"),
    (np.zeros((48, 64, 2), dtype=np.uint8), "shape"),
    (np.zeros((2, 48, 64, 3), dtype=np.uint8), "shape"),
    (np.zeros((0, 64), dtype=np.uint8), "empty"),
    ([[0, 1], [2, 3]], "numpy array"),
])
def test_bad_images_raise_a_clear_error(image, message):
    """Images of the wrong type, dtype or shape raise InvalidInputError naming the problem."""
    tracker = MarkerTracker(K, marker_sizes=SIZE)
    with pytest.raises(InvalidInputError, match=message):
        tracker.detect(image)


def test_markers_without_a_known_size_are_rejected_with_a_reason():
    """Ids missing from the size mapping are reported as rejected; sized ids and the default size still work."""
    rng = np.random.default_rng(3)
    image, truth = scene(rng, n_markers=3)
    poses, rejected = MarkerTracker(K, marker_sizes={1: SIZE, 3: SIZE}, max_ambiguity=1.0).detect(image)
    assert sorted(poses) == [1, 3]
    assert rejected == [(2, "no size known for this marker id")]
    poses, rejected = MarkerTracker(K, marker_sizes={1: SIZE}, default_size=SIZE, max_ambiguity=1.0).detect(image)
    assert sorted(poses) == [1, 2, 3] and rejected == []


def test_marker_size_scales_the_estimated_distance():
    """A wrongly configured size scales the estimated translation by the same factor (the size is used)."""
    rng = np.random.default_rng(4)
    image, truth = scene(rng, n_markers=1)
    right, _ = MarkerTracker(K, marker_sizes=SIZE).detect(image)
    double, _ = MarkerTracker(K, marker_sizes={1: 2 * SIZE}).detect(image)
    np.testing.assert_allclose(double[1][:3, 3], 2 * right[1][:3, 3], rtol=1e-6)


def test_repeated_id_in_one_image_is_rejected():
    """The same id seen twice in one image is ambiguous: both detections are rejected, others are kept."""
    image = np.full((480, 640), 110, dtype=np.uint8)
    draw_marker(image, marker_pose(-0.3, 0.0, 2.0), 5)
    draw_marker(image, marker_pose(0.3, 0.0, 2.0), 5)
    draw_marker(image, marker_pose(0.0, 0.2, 2.0), 6)
    poses, rejected = MarkerTracker(K, marker_sizes=SIZE).detect(image)
    assert sorted(poses) == [6]
    assert rejected == [(5, "repeated marker id in one image")] * 2


def test_tiny_markers_are_rejected_as_degenerate():
    """A marker only a few pixels wide is detected but rejected instead of giving a wild pose."""
    image = np.full((480, 640), 110, dtype=np.uint8)
    draw_marker(image, marker_pose(0.0, 0.0, 2.0), 4, size=0.08)
    poses, rejected = MarkerTracker(K, marker_sizes=SIZE, min_side_px=40.0).detect(image)
    assert poses == {}
    assert len(rejected) == 1 and rejected[0][0] == 4 and rejected[0][1].startswith("degenerate detection")


def test_empty_image_gives_no_poses():
    """An image without markers gives no poses and no rejections."""
    poses, rejected = MarkerTracker(K).detect(np.full((480, 640, 3), 200, dtype=np.uint8))
    assert poses == {} and rejected == []


@pytest.mark.parametrize("kwargs, message", [
    ({"camera_matrix": np.zeros((3, 3))}, "camera_matrix"),
    ({"camera_matrix": np.eye(4)}, "camera_matrix"),
    ({"marker_sizes": -0.1}, "> 0"),
    ({"marker_sizes": {1: math.nan}}, "> 0"),
    ({"marker_sizes": {-1: 0.08}}, "integers >= 0"),
    ({"dictionary": "DICT_NOPE"}, "unknown ArUco dictionary"),
    ({"corner_refinement": "magic"}, "corner_refinement"),
    ({"dist_coeffs": [0.1, 0.2]}, "dist_coeffs"),
])
def test_bad_configuration_raises(kwargs, message):
    """Invalid intrinsics, sizes, dictionary or refinement raise InvalidInputError at construction."""
    arguments = {"camera_matrix": K, **kwargs}
    with pytest.raises(InvalidInputError, match=message):
        MarkerTracker(**arguments)


# ---------------------------------------------------------------------- on the simulator's rendered images
@pytest.fixture(scope="module")
def rendered():
    """40 rendered babbling frames of powercube_6dof: (images, true poses, geometrically visible ids, tracker)."""
    with SimWorld("powercube_6dof", seed=0) as world:
        actions = babble(world, np.random.default_rng(0), 40, markers_of_interest=(6, 7))
        frames = []
        for a in actions:
            world.execute(a)
            frames.append((world.render(), world.true_marker_poses(), world.visible_marker_ids()))
        sizes = {i: world.robot.marker(i).size for i in world.marker_ids}
        tracker = MarkerTracker(world.camera.K, marker_sizes=sizes)
    return frames, tracker


def test_finds_the_visible_markers_in_rendered_images(rendered):
    """In the simulator's images the tracker finds at least the documented share of the visible markers, no others.

    Detections it drops are ambiguous (mirror-prone) or badly reprojected ones, never an unknown or duplicate id.
    """
    frames, tracker = rendered
    n_visible = n_found = 0
    for image, truth, visible in frames:
        poses, rejected = tracker.detect(image)
        assert set(poses) <= set(truth)
        assert all(reason.startswith(("ambiguous pose", "reprojection error")) for _, reason in rejected), rejected
        n_visible += len(visible)
        n_found += len(set(poses) & visible)
    assert n_visible > 100
    assert n_found / n_visible >= DOCUMENTED_DETECTION_RATE


def test_pose_error_on_rendered_images_is_within_documented_figure(rendered):
    """Median and 90th percentile pose errors on rendered babbling frames are within the documented bounds."""
    frames, tracker = rendered
    errors = np.array([pose_errors(camera2marker, truth[marker_id])
                       for image, truth, _ in frames for marker_id, camera2marker in tracker.detect(image)[0].items()])
    assert np.median(errors[:, 0]) <= DOCUMENTED_TRANS_ERROR_MEDIAN
    assert np.percentile(errors[:, 0], 90) <= DOCUMENTED_TRANS_ERROR_P90
    assert np.median(errors[:, 1]) <= DOCUMENTED_ROT_ERROR_MEDIAN
    assert np.percentile(errors[:, 1], 90) <= DOCUMENTED_ROT_ERROR_P90


# ---------------------------------------------------------------------- image conversions
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
    """camera_matrix_from_info reads K; an all-zero K (uncalibrated camera) raises."""
    info = CameraInfo(k=K.ravel().tolist(), d=[0.0] * 5, distortion_model="plumb_bob")
    np.testing.assert_array_equal(conversions.camera_matrix_from_info(info), K)
    assert conversions.distortion_from_info(info) is None
    info.d = [0.1, 0.0, 0.0, 0.0, 0.0]
    np.testing.assert_array_equal(conversions.distortion_from_info(info), info.d)
    with pytest.raises(InvalidInputError, match="calibrated"):
        conversions.camera_matrix_from_info(CameraInfo())


# ---------------------------------------------------------------------- tracker_node configuration
def test_marker_sizes_come_from_the_marker_file_and_overrides(tmp_path):
    """Sizes are read from the robot's marker file; the ids/sizes parameters override single ids."""
    markers_path = tmp_path / "arm.markers.yaml"
    markers_path.write_text("markers:\n- {id: 1, link: base, size: 0.1}\n- {id: 7, link: tool, size: 0.08}\n"
                            "- {id: 8, link: tool}\n")
    sizes = marker_sizes_from_parameters(str(markers_path), [7, 9], [0.05, 0.12])
    assert sizes == {1: 0.1, 7: 0.05, 8: 0.05, 9: 0.12}  # id 8: the file format's default size, 0.05 m
    with pytest.raises(InvalidInputError, match="2 entries"):
        marker_sizes_from_parameters("", [1, 2], [0.05])
    with pytest.raises(InvalidInputError, match="not a file"):
        marker_sizes_from_parameters(str(tmp_path / "missing.yaml"), [], [])


def test_config_yaml_holds_the_node_defaults():
    """config/tracker_node.yaml lists every parameter tracker_node declares, at its default value."""
    config = pathlib.Path(__file__).resolve().parents[1] / "config" / "tracker_node.yaml"
    documented = yaml.safe_load(config.read_text())["tracker_node"]["ros__parameters"]
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


def test_ambiguity_filter_rejects_mirror_prone_poses(rendered):
    """max_ambiguity < 1 rejects detections whose mirrored IPPE solution fits almost as well, with that reason."""
    frames, tracker = rendered
    keep_all = MarkerTracker(tracker.camera_matrix, marker_sizes=tracker.marker_sizes, max_ambiguity=1.0)
    strict = MarkerTracker(tracker.camera_matrix, marker_sizes=tracker.marker_sizes, max_ambiguity=0.8)
    mirrored = {"all": 0, "strict": 0}
    n_ambiguous = 0
    for image, truth, _ in frames:
        for name, t in (("all", keep_all), ("strict", strict)):
            poses, rejected = t.detect(image)
            mirrored[name] += sum(np.degrees(rotational_error(poses[i], truth[i])) > 20 for i in poses)
            if name == "strict":
                n_ambiguous += sum("ambiguous pose" in reason for _, reason in rejected)
    assert n_ambiguous > 0 and mirrored["strict"] < mirrored["all"]
    with pytest.raises(InvalidInputError, match="max_ambiguity"):
        MarkerTracker(tracker.camera_matrix, max_ambiguity=0.0)
