"""Tests of plates: several tags on one rigid body, one pose from all their visible corners."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.plates import Plate, grid_plate, plate_pose
from body_scheme_core.transforms import rotational_error, transform_from_rotvec

K = np.array([[554.0, 0.0, 319.5], [0.0, 554.0, 239.5], [0.0, 0.0, 1.0]])
ORIGIN = [0.0, 0.0, 0.0]
#: A plate facing the camera 1.8 m away, tilted 35 deg.
CAMERA2PLATE = transform_from_rotvec([math.pi, 0, 0], [0.1, -0.05, 1.8]) @ transform_from_rotvec([0.6, 0, 0], ORIGIN)


def corners_of(plate, camera2plate, ids=None, noise=0.0, rng=None):
    rvec = cv2.Rodrigues(camera2plate[:3, :3])[0]
    result = {}
    for tag_id in plate.tags if ids is None else ids:
        projected, _ = cv2.projectPoints(plate.corners(tag_id), rvec, camera2plate[:3, 3], K, None)
        result[tag_id] = projected.reshape(4, 2) + (0.0 if rng is None else rng.normal(0.0, noise, (4, 2)))
    return result


def cube(size=0.06, edge=0.1):
    """A cube of edge ``edge`` with a tag on five faces (not the bottom): not planar."""
    faces = {1: [0.0, 0.0, 0.0], 2: [0.0, math.pi / 2, 0.0], 3: [0.0, -math.pi / 2, 0.0], 4: [math.pi / 2, 0.0, 0.0],
             5: [-math.pi / 2, 0.0, 0.0]}
    tags = {}
    for tag_id, rotvec in faces.items():
        plate2face = transform_from_rotvec(rotvec, ORIGIN)
        plate2face[:3, 3] = plate2face[:3, :3] @ [0.0, 0.0, edge / 2]
        tags[tag_id] = (size, plate2face)
    return Plate(tags)


@pytest.mark.parametrize("plate", [grid_plate([1], 0.08, 0.02), grid_plate([3, 4, 5, 6], 0.08, 0.02), cube()],
                         ids=["one tag", "grid of four", "cube"])
def test_exact_corners_give_the_plates_pose(plate):
    """From noiseless corners of the visible tags the plate's pose is exact, whatever its layout."""
    turned = CAMERA2PLATE @ transform_from_rotvec([0.0, 0.3, 0.0], ORIGIN)  # the cube shows three faces
    camera2plate = turned if len(plate.tags) == 5 else CAMERA2PLATE
    visible = [i for i in plate.tags if (camera2plate @ plate.tags[i][1])[2, 2] < 0.0]  # facing the camera
    detection = plate_pose(plate, corners_of(plate, camera2plate, visible), K)
    assert np.allclose(detection.pose, camera2plate, atol=1e-6)
    assert detection.errors[0] < 1e-6 and np.all(np.linalg.eigvalsh(detection.covariance) > 0.0)


def test_a_plate_of_four_tags_is_far_better_along_the_ray_and_never_mirrored():
    """0.5 px of corner noise, 200 poses: the plate's depth error is under half the single tag's (the same tag among
    them) and its orientation is never mirrored, while the tag's is now and then."""
    rng = np.random.default_rng(0)
    plate = grid_plate([1, 2, 3, 4], 0.08, 0.02)
    depth = {"tag": [], "plate": []}
    mirrored = {"tag": 0, "plate": 0}
    for _ in range(200):
        corners = corners_of(plate, CAMERA2PLATE, noise=0.5, rng=rng)
        for name, seen in (("tag", {1: corners[1]}), ("plate", corners)):
            pose = plate_pose(plate, seen, K).pose
            depth[name].append(abs(pose[2, 3] - CAMERA2PLATE[2, 3]))
            mirrored[name] += rotational_error(pose, CAMERA2PLATE) > math.radians(20.0)
    assert np.median(depth["plate"]) < 0.5 * np.median(depth["tag"])
    assert mirrored["plate"] == 0 and mirrored["tag"] > 0


def test_other_ids_are_ignored_and_a_plate_unseen_gives_none():
    plate = grid_plate([1, 2], 0.08, 0.02)
    corners = corners_of(plate, CAMERA2PLATE)
    assert plate_pose(plate, {7: corners[1]}, K) is None
    assert np.allclose(plate_pose(plate, {**corners, 7: corners[1] + 40.0}, K).pose, CAMERA2PLATE, atol=1e-6)


@pytest.mark.parametrize("tags", [{}, {1: (0.0, np.eye(4))}, {1: (0.05, np.eye(3))},
                                  {1: (0.05, np.full((4, 4), np.nan))}])
def test_a_bad_plate_is_refused(tags):
    with pytest.raises(InvalidInputError):
        Plate(tags)


def test_markers_that_name_a_plate_make_one_in_the_frame_of_its_reference():
    from body_scheme_core.plates import plates_from_markers
    from body_scheme_core.world import Marker

    offset = transform_from_rotvec([0.0, 0.0, 0.0], [0.07, 0.0, 0.0])
    reference = transform_from_rotvec([0.0, 0.4, 0.0], [0.1, 0.0, 0.2])
    markers = [Marker(3, "tool", reference, 0.05, plate=3), Marker(4, "tool", reference @ offset, 0.05, plate=3),
               Marker(1, "base")]
    plates = plates_from_markers(markers)
    assert list(plates) == [3] and np.allclose(plates[3].tags[4][1], offset) and np.allclose(plates[3].tags[3][1],
                                                                                              np.eye(4))
    with pytest.raises(InvalidInputError, match="one of its markers"):
        plates_from_markers([Marker(3, "tool", plate=9), Marker(4, "tool", plate=9)])
    with pytest.raises(InvalidInputError, match="several links"):
        plates_from_markers([Marker(3, "tool", plate=3), Marker(4, "wrist", plate=3)])
    with pytest.raises(InvalidInputError, match="plate must be"):
        Marker(3, "tool", plate=-1)
    assert Marker.from_dict(markers[1].to_dict()).plate == 3 and "plate" not in markers[2].to_dict()
