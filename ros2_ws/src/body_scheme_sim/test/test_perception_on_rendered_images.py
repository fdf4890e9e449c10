"""The ArUco tracker (body_scheme_core.perception) on the simulator's rendered images: its documented accuracy."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import (
    DOCUMENTED_DETECTION_RATE,
    DOCUMENTED_ROT_ERROR_MEDIAN,
    DOCUMENTED_ROT_ERROR_P90,
    DOCUMENTED_TRANS_ERROR_MEDIAN,
    DOCUMENTED_TRANS_ERROR_P90,
    MarkerTracker,
    marker_object_points,
)
from body_scheme_core.transforms import rotational_error
from body_scheme_core.world import babble
from body_scheme_sim.babbling import babbling_screen
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



# ---------------------------------------------------------------------- on the simulator's rendered images
@pytest.fixture(scope="module")
def rendered():
    """40 rendered babbling frames of powercube_6dof: (images, true poses, geometrically visible ids, tracker)."""
    with SimWorld("powercube_6dof", seed=0) as world:
        actions = babble(world, 40, np.random.default_rng(0), screen=babbling_screen(world, (6, 7)))
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
