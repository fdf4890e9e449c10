"""The pinhole camera: intrinsics, pose, and agreement between K and pybullet's rendering."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pybullet
import pytest
from pybullet_utils.bullet_client import BulletClient

from body_scheme_core.errors import InvalidInputError
from body_scheme_sim.camera import DEFAULT_EYE, DEFAULT_TARGET, Camera, look_at
from body_scheme_sim.scene import render


def rendered_centroids(camera, points, radius=0.015):
    """Render red spheres at ``points`` (n, 3) and return the pixel centroid of each, matched by nearest ``K``."""
    scene = BulletClient(connection_mode=pybullet.DIRECT)
    try:
        for point in points:
            visual = scene.createVisualShape(pybullet.GEOM_SPHERE, radius=radius, rgbaColor=(1.0, 0.0, 0.0, 1.0))
            scene.createMultiBody(baseMass=0.0, baseVisualShapeIndex=visual, basePosition=point)
        rgb, _ = render(scene, camera)
    finally:
        scene.disconnect()
    red = ((rgb[..., 0] > 120) & (rgb[..., 1] < 60)).astype(np.uint8)
    n, labels = cv2.connectedComponents(red)
    centroids = []
    for label in range(1, n):
        rows, cols = np.nonzero(labels == label)
        centroids.append([cols.mean(), rows.mean()])
    return np.array(centroids)


def test_default_camera_is_about_one_and_a_half_metres_from_the_robot_and_looks_at_it():
    """The default optical axis points from DEFAULT_EYE at DEFAULT_TARGET, 1.5 m away, with a 60 deg FOV."""
    camera = Camera()
    distance = np.linalg.norm(np.subtract(DEFAULT_TARGET, DEFAULT_EYE))
    assert 1.4 < distance < 1.6
    uv, depth = camera.project(np.array([DEFAULT_TARGET]))
    np.testing.assert_allclose(uv[0], [camera.cx, camera.cy], atol=1e-9)
    np.testing.assert_allclose(depth, [distance])
    assert math.degrees(2 * math.atan(0.5 * camera.width / camera.fx)) == pytest.approx(60.0)
    np.testing.assert_allclose(camera.K, [[camera.fx, 0, 319.5], [0, camera.fy, 239.5], [0, 0, 1]])


def test_look_at_gives_an_opencv_optical_frame():
    """z points at the target, x is horizontal (image right), y points down in the world."""
    world2camera = look_at((2.0, 1.0, 1.5), (0.0, 0.0, 0.5))
    R = world2camera[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    direction = np.array([-2.0, -1.0, -1.0]) / np.sqrt(6.0)
    np.testing.assert_allclose(R[:, 2], direction, atol=1e-12)
    assert abs(R[2, 0]) < 1e-12 and R[2, 1] < 0
    with pytest.raises(InvalidInputError, match="parallel"):
        look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))


def test_k_and_pybullet_rendering_agree_within_half_a_pixel():
    """Spheres rendered by pybullet land where K projects them (< 0.5 px; a half-pixel convention slip fails)."""
    rng = np.random.default_rng(0)
    for camera in (Camera(), Camera(width=320, height=200, fx=300.0, fy=280.0, cx=150.3, cy=90.8),
                   Camera(fx=700.0, fy=720.0, cx=340.2, cy=222.7, world2camera=look_at((1.0, -1.5, 1.2),
                                                                                       (0.0, 0.0, 0.4)))):
        points = rng.uniform([-0.5, -0.5, 0.1], [0.5, 0.5, 1.0], size=(8, 3))
        uv, _ = camera.project(points)
        keep = camera.in_image(uv, margin=15)
        # points whose images overlap would merge into one blob
        gaps = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(len(uv)) * 1e9
        keep &= gaps.min(axis=1) > 30
        centroids = rendered_centroids(camera, points[keep])
        assert len(centroids) == keep.sum()
        for centroid in centroids:
            assert np.min(np.linalg.norm(uv[keep] - centroid, axis=1)) < 0.5


def test_pybullet_matrices_match_opencv_conventions():
    """The view matrix maps the camera centre to the origin and the optical axis to OpenGL's -z."""
    camera = Camera()
    view = np.array(camera.view_matrix).reshape(4, 4, order="F")
    np.testing.assert_allclose(view @ np.append(camera.position, 1.0), [0, 0, 0, 1], atol=1e-12)
    ahead = camera.position + camera.world2camera[:3, 2]
    np.testing.assert_allclose(view @ np.append(ahead, 1.0), [0, 0, -1, 1], atol=1e-12)
    projection = np.array(camera.projection_matrix).reshape(4, 4, order="F")
    assert projection[3, 2] == -1.0 and projection[0, 0] == pytest.approx(2 * camera.fx / camera.width)


def test_in_image_and_points_behind_the_camera():
    """Points behind the camera have negative depth; in_image honours the margin."""
    camera = Camera()
    behind = camera.position - 0.5 * camera.world2camera[:3, 2]
    _, depth = camera.project(behind[None])
    assert depth[0] < 0
    uv = np.array([[0.0, 0.0], [639.0, 479.0], [-1.0, 10.0], [5.0, 5.0]])
    np.testing.assert_array_equal(camera.in_image(uv), [True, True, False, True])
    np.testing.assert_array_equal(camera.in_image(uv, margin=10), [False, False, False, False])


@pytest.mark.parametrize("changes, message", [
    ({"width": 0}, "width"), ({"fx": -1.0}, "fx"), ({"near": 2.0, "far": 1.0}, "near"),
    ({"cy": float("nan")}, "cy"), ({"world2camera": np.zeros((4, 4))}, "world2camera")])
def test_invalid_camera_settings_raise(changes, message):
    """Non-positive sizes and focal lengths, bad clipping planes, NaN and non-rigid poses are refused."""
    with pytest.raises(InvalidInputError, match=message):
        Camera(**changes)
