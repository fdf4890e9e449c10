"""The ArUco tracker (body_scheme_core.perception) on the simulator's rendered images: its documented accuracy."""

from __future__ import annotations

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import (
    DOCUMENTED_DETECTION_RATE,
    DOCUMENTED_ROT_ERROR_MEDIAN,
    DOCUMENTED_ROT_ERROR_P90,
    DOCUMENTED_TRANS_ERROR_MEDIAN,
    DOCUMENTED_TRANS_ERROR_P90,
    MarkerTracker,
    rejection_kind,
)
from body_scheme_core.transforms import rotational_error, translational_error
from body_scheme_core.world import babble
from body_scheme_sim.babbling import babbling_screen
from body_scheme_sim.world import SimWorld


def pose_errors(estimate, truth):
    """(translational m, rotational rad) error of one pose."""
    return translational_error(estimate, truth), rotational_error(estimate, truth)


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
        assert {rejection_kind(reason) for _, reason in rejected} <= {"ambiguous pose", "reprojection error"}, \
            rejected  # counter keys without the numbers, so similar rejections add up
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
