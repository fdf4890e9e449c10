"""Tests of the ArUco marker tracker (body_scheme_core.perception) on synthetic images."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import (
    MarkerTracker,
    marker_object_points,
    pose_covariance,
    square_pnp,
)

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
    ({"corner_sigma_px": 0.0}, "corner_sigma_px"),
])
def test_bad_configuration_raises(kwargs, message):
    """Invalid intrinsics, sizes, dictionary or refinement raise InvalidInputError at construction."""
    arguments = {"camera_matrix": K, **kwargs}
    with pytest.raises(InvalidInputError, match=message):
        MarkerTracker(**arguments)



def _ippe(corners, size=SIZE):
    n, rvecs, tvecs, errors = cv2.solvePnPGeneric(marker_object_points(size), corners, K, None,
                                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return rvecs[0].ravel(), tvecs[0].ravel()


@pytest.mark.parametrize("distance", [1.0, 2.0])
def test_the_covariance_of_a_pose_matches_the_scatter_of_noisy_corners(distance):
    """Monte Carlo: 0.5 px of corner noise on an 8 cm tag tilted 30 deg; the predicted position covariance matches the
    scatter of IPPE's poses (std per axis of the ray frame within 25 %), the depth std is several times the lateral
    one, and it grows with the distance squared (checked between the two cases by the fixed ratio of their stds)."""
    rng = np.random.default_rng(3)
    truth = marker_pose(0.1, -0.05, distance, (math.radians(30.0), 0.0, 0.0))
    rvec = cv2.Rodrigues(truth[:3, :3])[0]
    clean, _ = cv2.projectPoints(marker_object_points(SIZE), rvec, truth[:3, 3], K, None)
    covariance = pose_covariance(marker_object_points(SIZE), rvec, truth[:3, 3], K, None, sigma_px=0.5)
    assert covariance.shape == (6, 6) and np.allclose(covariance, covariance.T)
    ray = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    lateral = np.linalg.svd(np.eye(3) - np.outer(ray, ray))[0][:, :2]
    frame = np.column_stack([lateral, ray])  # two lateral axes, then the ray
    positions, rotations = [], []
    for _ in range(2000):
        corners = clean.reshape(4, 2) + rng.normal(0.0, 0.5, (4, 2))
        r, t = _ippe(corners)
        error = Rotation.from_matrix(cv2.Rodrigues(r)[0] @ truth[:3, :3].T).as_rotvec()  # about the camera's axes
        if np.linalg.norm(error) < math.radians(15.0):  # IPPE's mirrored solutions are the learner's business
            positions.append(t)
            rotations.append(error)
    scatter = np.std((np.array(positions) - truth[:3, 3]) @ frame, axis=0)
    predicted = np.sqrt(np.diag(frame.T @ covariance[:3, :3] @ frame))
    assert np.allclose(predicted, scatter, rtol=0.25), (predicted, scatter)
    assert predicted[2] > 5.0 * predicted[:2].max()
    # The rotation block: the scatter's largest and smallest principal stds within 25 % (the two tilt axes are
    # poorly and the axis about the ray well determined).
    scatter_rot = np.sqrt(np.linalg.eigvalsh(np.cov(np.array(rotations).T)))
    predicted_rot = np.sqrt(np.linalg.eigvalsh(covariance[3:, 3:]))
    assert np.allclose(predicted_rot[[0, 2]], scatter_rot[[0, 2]], rtol=0.25), (predicted_rot, scatter_rot)


def test_the_covariance_grows_with_the_distance_squared():
    covariances = [pose_covariance(marker_object_points(SIZE), cv2.Rodrigues(marker_pose(0, 0, z)[:3, :3])[0],
                                   (0.0, 0.0, z), K, None) for z in (1.0, 2.0)]
    depth_std = [math.sqrt(c[2, 2]) for c in covariances]
    assert 3.5 < depth_std[1] / depth_std[0] < 4.5


def test_detections_carry_a_covariance_and_ippes_other_solution():
    """detect_markers: each pose with its covariance (positive definite), the other IPPE solution about as far away
    with its orientation mirrored about the ray, and both reprojection errors, the reported one the smaller."""
    from body_scheme_core.transforms import mirror_about_ray, rotational_error

    image, truth = scene(np.random.default_rng(0))
    detections, rejected = MarkerTracker(K, marker_sizes=SIZE, max_ambiguity=1.0).detect_markers(image)
    assert sorted(detections) == sorted(truth) and rejected == []
    for marker_id, d in detections.items():
        assert np.all(np.linalg.eigvalsh(d.covariance) > 0.0) and d.errors[0] <= d.errors[1]
        assert d.alternative is not None
        assert np.linalg.norm(d.alternative[:3, 3] - d.pose[:3, 3]) < 0.05
        assert rotational_error(mirror_about_ray(d.pose), d.alternative) < math.radians(10.0), marker_id


def test_a_plate_of_tags_is_one_pose_under_its_id_and_other_markers_stay_their_own():
    """Four tags of a 2 x 2 plate drawn at a known pose and one loose marker: the tracker reports the plate once,
    under its reference id, close to the truth, and the loose marker as before; a plate of which one tag is seen is
    still a pose."""
    from body_scheme_core.plates import grid_plate

    plate = grid_plate([5, 6, 7, 8], 0.06, 0.015)
    camera2plate = marker_pose(-0.15, 0.05, 1.3, (0.5, 0.2, 0.0))
    image = np.full((480, 640), 110, dtype=np.uint8)
    for tag_id, (size, plate2tag) in plate.tags.items():
        draw_marker(image, camera2plate @ plate2tag, tag_id, size=size, quiet_zone=0.1)
    loose = marker_pose(0.25, 0.0, 1.6, (0.2, 0.0, 0.0))
    draw_marker(image, loose, 2)
    tracker = MarkerTracker(K, marker_sizes=SIZE, plates={5: plate})
    detections, rejected = tracker.detect_markers(image)
    assert sorted(detections) == [2, 5] and rejected == []
    trans, rot = pose_errors(detections[5].pose, camera2plate)
    assert trans < 0.01 and rot < math.radians(2.0), (trans, rot)
    assert pose_errors(detections[2].pose, loose)[0] < 0.03
    assert detections[5].errors[0] < 1.0 and np.all(np.linalg.eigvalsh(detections[5].covariance) > 0.0)
    only_one = np.full((480, 640), 110, dtype=np.uint8)
    draw_marker(only_one, camera2plate @ plate.tags[7][1], 7, size=0.06, quiet_zone=0.1)
    detections, _ = tracker.detect_markers(only_one)
    assert list(detections) == [5] and pose_errors(detections[5].pose, camera2plate)[0] < 0.05


@pytest.mark.parametrize("refinement", ["apriltag", "subpix"])
def test_poses_are_not_shifted_by_a_pixel_convention(refinement):
    """OpenCV's AprilTag refinement gives corners half a pixel right of and below OpenCV's convention (a lateral bias
    of 0.8 mm at 1 m here, before the tracker subtracted it); the mean lateral error over markers drawn at known
    poses is a small fraction of that, as with OpenCV's subpixel refinement."""
    rng = np.random.default_rng(5)
    tracker = MarkerTracker(K, marker_sizes=SIZE, max_ambiguity=1.0, corner_refinement=refinement)
    lateral = []
    for _ in range(20):
        image = np.full((480, 640), 110, dtype=np.uint8)
        truth = marker_pose(rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 1.0, rng.normal(0.0, 0.3, 3))
        draw_marker(image, truth, 2)
        poses, _ = tracker.detect(image)
        lateral.append(poses[2][:2, 3] - truth[:2, 3])
    bias = np.abs(np.mean(lateral, axis=0))
    assert np.all(bias < 0.25e-3), bias


def test_a_marker_centred_on_the_principal_points_column_has_a_pose():
    """The simulator's planar arm's base marker, as its corners came once in OpenCV's pixel convention: an upright
    rectangle centred on the principal point's column, seen by the 640 x 480, 60 deg camera. IPPE_SQUARE's closed form
    is NaN there ('solvePnP found no pose' in every picture); square_pnp falls back to the general planar IPPE."""
    f = 320.0 / math.tan(math.radians(30.0))
    camera_matrix = np.array([[f, 0.0, 319.5], [0.0, f, 239.5], [0.0, 0.0, 1.0]])
    image_points = np.array([[330.5, 174.5], [330.5, 191.5], [308.5, 191.5], [308.5, 174.5]])
    object_points = marker_object_points(0.08)
    _, _, tvecs, _ = cv2.solvePnPGeneric(object_points, image_points, camera_matrix, None,
                                         flags=cv2.SOLVEPNP_IPPE_SQUARE)
    assert not np.all(np.isfinite(tvecs[0]))  # OpenCV's degenerate case; if it ever solves it, drop the fallback
    n, _, tvecs, errors = square_pnp(object_points, image_points, camera_matrix)
    assert n == 2 and np.all(np.isfinite(tvecs[0])) and math.sqrt(2.0) * np.ravel(errors)[0] < 0.2
    assert abs(float(np.ravel(tvecs[0])[2]) - 2.016) < 0.01  # what IPPE, SQPNP and the iterative solver give
