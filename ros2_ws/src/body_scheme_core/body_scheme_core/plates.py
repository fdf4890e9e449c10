"""Plates: several tags on one rigid body (an ArUco board on a tool, a cube with a tag per face), one pose from all
their visible corners (no ROS).

A single small tag gives a poor pose: its four corners span a few pixels, so the distance along the camera's ray is
uncertain and its orientation is often IPPE's mirrored solution. A plate's corners span the whole plate: the depth is
better determined and the mirrored solution no longer explains the corners (``python -m
body_scheme_apps.perception_bench``, ``perception_*`` figures). A :class:`Plate` lists each tag's pose on it;
:func:`plate_pose` starts from both IPPE solutions of every visible tag, refines each over all visible corners
(Levenberg-Marquardt, :func:`cv2.solvePnPRefineLM`) and keeps the one that reprojects best; the best of the other
orientations is the alternative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import MarkerDetection, marker_object_points, pose_covariance, square_pnp
from body_scheme_core.transforms import invert_transform, rotational_error, transform_from_rotvec

__all__ = ["Plate", "plate_pose", "grid_plate", "plates_from_markers"]

#: Two refined solutions whose orientations differ by less than this (rad) are the same solution.
_SAME_ORIENTATION = math.radians(5.0)


@dataclass(frozen=True)
class Plate:
    """A rigid plate of tags.

    Attributes
    ----------
    tags : dict of int to (float, ndarray (4, 4))
        Per tag id: its edge length (m) and ``plate2tag``, its pose on the plate.
    """

    tags: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.tags:
            raise InvalidInputError("a plate needs at least one tag")
        for tag_id, (size, plate2tag) in self.tags.items():
            plate2tag = np.asarray(plate2tag, dtype=float)
            if not (math.isfinite(size) and size > 0) or plate2tag.shape != (4, 4) \
                    or not np.all(np.isfinite(plate2tag)):
                raise InvalidInputError(f"tag {tag_id}: size must be > 0 and its pose a finite (4, 4) transform")

    def pose(self, corners, camera_matrix, dist_coeffs=None, sigma_px=0.5):
        """:func:`plate_pose` of this plate."""
        return plate_pose(self, corners, camera_matrix, dist_coeffs, sigma_px)

    def corners(self, tag_id):
        """The tag's four corners in the plate's frame, shape (4, 3), in the detector's order."""
        size, plate2tag = self.tags[tag_id]
        points = marker_object_points(size)
        return points @ np.asarray(plate2tag)[:3, :3].T + np.asarray(plate2tag)[:3, 3]


def grid_plate(ids, size, gap, columns=2):
    """A flat plate of ``len(ids)`` tags of edge ``size`` in rows of ``columns``, ``gap`` m apart, centred on the
    plate's origin (tag frames parallel to the plate's: x right, y up, z out of the plate); row-major from the top
    left, as an ArUco grid board."""
    rows = math.ceil(len(ids) / columns)
    pitch = size + gap
    tags = {}
    for k, tag_id in enumerate(ids):
        r, c = divmod(k, columns)
        plate2tag = np.eye(4)
        plate2tag[:3, 3] = ((c - 0.5 * (columns - 1)) * pitch, (0.5 * (rows - 1) - r) * pitch, 0.0)
        tags[int(tag_id)] = (float(size), plate2tag)
    return Plate(tags)


def plates_from_markers(markers):
    """``{plate id: Plate}`` of the markers that name a ``plate`` (a marker file's entries, ``Marker`` objects).

    A plate's id is the id of its reference marker, one of its own; its frame is that marker's, so the plate is
    observed as the body part that marker stands for, better seen. Its markers must sit on one link.

    Raises
    ------
    InvalidInputError
        If a plate's id is none of its markers', or its markers sit on several links.
    """
    groups = {}
    for marker in markers:
        if marker.plate is not None:
            groups.setdefault(marker.plate, []).append(marker)
    plates = {}
    for plate_id, members in sorted(groups.items()):
        reference = next((m for m in members if m.id == plate_id), None)
        if reference is None:
            raise InvalidInputError(f"plate {plate_id} must be the id of one of its markers "
                                    f"{sorted(m.id for m in members)}")
        links = sorted({m.link for m in members})
        if len(links) > 1:
            raise InvalidInputError(f"the markers of plate {plate_id} sit on several links {links}: a plate is rigid")
        to_reference = invert_transform(np.asarray(reference.link2marker, dtype=float))
        plates[plate_id] = Plate({m.id: (m.size, to_reference @ np.asarray(m.link2marker, dtype=float))
                                  for m in members})
    return plates


def _pose(rvec, tvec):
    return transform_from_rotvec(np.ravel(rvec), np.ravel(tvec))


def _rms(object_points, image_points, rvec, tvec, camera_matrix, dist_coeffs):
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, camera_matrix, dist_coeffs)
    return math.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points) ** 2, axis=1)))


def plate_pose(plate, corners, camera_matrix, dist_coeffs=None, sigma_px=0.5):
    """The plate's pose from the image corners of its visible tags.

    Parameters
    ----------
    plate : Plate
    corners : dict of int to ndarray, shape (4, 2)
        Image corners (px) of the plate's tags that were detected, in the detector's order; other ids are ignored.
    camera_matrix : ndarray, shape (3, 3)
    dist_coeffs : ndarray or None
    sigma_px : float
        Corner noise (px) for the covariance (:func:`~body_scheme_core.perception.pose_covariance`).

    Returns
    -------
    MarkerDetection or None
        ``camera2plate`` with its covariance, the best other orientation and both RMS reprojection errors (px);
        None when no tag of the plate is among ``corners`` or no pose lies in front of the camera.
    """
    seen = sorted(i for i in corners if i in plate.tags)
    if not seen:
        return None
    object_points = np.concatenate([plate.corners(i) for i in seen])
    image_points = np.concatenate([np.asarray(corners[i], dtype=float).reshape(4, 2) for i in seen])
    solutions = []
    for tag_id in seen:
        size, plate2tag = plate.tags[tag_id]
        n, rvecs, tvecs, _ = square_pnp(marker_object_points(size), corners[tag_id], camera_matrix, dist_coeffs)
        for rvec, tvec in zip(rvecs[:n], tvecs[:n], strict=True):
            camera2plate = _pose(rvec, tvec) @ invert_transform(np.asarray(plate2tag, dtype=float))
            rvec = cv2.Rodrigues(camera2plate[:3, :3])[0]
            tvec = camera2plate[:3, 3].reshape(3, 1).copy()
            if len(seen) > 1:
                rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, camera_matrix, dist_coeffs, rvec, tvec)
            if tvec[2, 0] > 0 and np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
                solutions.append((_rms(object_points, image_points, rvec, tvec, camera_matrix, dist_coeffs),
                                  rvec, tvec))
    if not solutions:
        return None
    solutions.sort(key=lambda s: s[0])
    error, rvec, tvec = solutions[0]
    pose = _pose(rvec, tvec)
    other = next((s for s in solutions[1:]
                  if rotational_error(_pose(s[1], s[2]), pose) > _SAME_ORIENTATION), None)
    covariance = pose_covariance(object_points, rvec, tvec, camera_matrix, dist_coeffs, sigma_px)
    return MarkerDetection(pose, covariance, None if other is None else _pose(other[1], other[2]),
                           (error,) if other is None else (error, other[0]))

