"""ArUco marker tracker: camera image in, ``{marker id: camera2marker}`` out (no ROS).

Detection is OpenCV's :class:`cv2.aruco.ArucoDetector` (corner refinement configurable, AprilTag's edge fit by
default) and each marker's pose comes from its four corners by ``cv2.solvePnP(..., flags=cv2.SOLVEPNP_IPPE_SQUARE)``.
Poses are ``camera2marker``: the marker's pose in the OpenCV camera optical frame (x right, y down, z forward), the
marker frame being OpenCV ArUco's (origin at the marker centre, x right, y up, z out of the plate; units m).

Every detection that does not become a pose is reported as ``(marker id, reason)``: an id without a known size, an
id seen twice in one image, a marker smaller than ``min_side_px`` on the image, a failed or non-finite PnP solution,
a pose behind the camera, a reprojection error above ``max_reprojection_error`` pixels, or an ambiguous pose: IPPE
gives two solutions for a square, the true one and a mirrored one; when the best explains the corners barely
better than the other (ratio of their reprojection errors at or above ``max_ambiguity``), the marker's orientation
is a coin toss and the detection is rejected rather than reported with a possibly mirrored orientation.

Each pose comes with its covariance (:func:`pose_covariance`): the corners' noise (``corner_sigma_px``) through the
PnP Jacobian, first order, over ``(x, y, z, rot_x, rot_y, rot_z)`` as ``geometry_msgs/PoseWithCovariance`` has it.
It is large along the ray and grows with the distance squared: what a monocular camera can and cannot tell.
:meth:`MarkerTracker.detect_markers` also gives IPPE's other solution and both reprojection errors.

Measured accuracy
-----------------
On the simulator's rendered images: ``docs/sim.md``, "Tracker accuracy" (``python -m
body_scheme_apps.perception_bench``, figures in ``docs/results/sim.json``), with what limits it (depth along the ray,
IPPE's mirrored solution on small, nearly fronto-parallel markers, the aliased renderer's fixed error on the static
base marker). The corner refinement matters: OpenCV's ``subpix`` and ``contour`` methods place the corners of small
markers up to 0.7 px inside the square (distances biased by centimetres); ``apriltag`` fits lines to the edges, and
OpenCV returns its corners in AprilTag's pixel convention, half a pixel off (:data:`APRILTAG_PIXEL_OFFSET`,
subtracted). The ``DOCUMENTED_*`` constants below are the bounds the tests hold the tracker to.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.rotations import skew
from body_scheme_core.transforms import transform_from_rotvec

__all__ = [
    "MarkerTracker",
    "MarkerDetection",
    "pose_covariance",
    "check_image",
    "rejection_kind",
    "marker_object_points",
    "square_pnp",
    "APRILTAG_PIXEL_OFFSET",
    "DOCUMENTED_TRANS_ERROR_MEDIAN",
    "DOCUMENTED_TRANS_ERROR_P90",
    "DOCUMENTED_ROT_ERROR_MEDIAN",
    "DOCUMENTED_ROT_ERROR_P90",
    "DOCUMENTED_DETECTION_RATE",
]

#: Documented bounds of the tracker's error on the simulator's rendered images (measured: 3.3 mm, 19 mm, 0.49 deg,
#: 0.97 deg; docs/results/sim.json, docs/sim.md): median and 90th percentile, translation (m) and rotation (rad).
DOCUMENTED_TRANS_ERROR_MEDIAN = 0.012
DOCUMENTED_TRANS_ERROR_P90 = 0.030
DOCUMENTED_ROT_ERROR_MEDIAN = math.radians(1.5)
DOCUMENTED_ROT_ERROR_P90 = math.radians(5.0)
#: Documented lower bound of the fraction of geometrically visible markers the tracker detects (measured: 0.92).
DOCUMENTED_DETECTION_RATE = 0.75


@dataclass(frozen=True)
class MarkerDetection:
    """One marker's pose from its corners (:meth:`MarkerTracker.detect_markers`).

    Attributes
    ----------
    pose : ndarray, shape (4, 4)
        ``camera2marker``, IPPE's better solution.
    covariance : ndarray, shape (6, 6)
        Of ``pose`` over ``(x, y, z, rot_x, rot_y, rot_z)`` (:func:`pose_covariance`).
    alternative : ndarray, shape (4, 4), or None
        IPPE's other solution (the orientation mirrored about the ray, nearly), None when there is none.
    errors : tuple of float
        Reprojection errors (px, RMS over the corners) of ``pose`` and, if any, of ``alternative``.
    """

    pose: np.ndarray
    covariance: np.ndarray
    alternative: np.ndarray | None
    errors: tuple


def _left_jacobian(r):
    """The left Jacobian of SO(3) at rotation vector ``r`` (3,)."""
    theta = float(np.linalg.norm(r))
    K = skew(r)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K
    return (np.eye(3) + (1.0 - math.cos(theta)) / theta**2 * K
            + (theta - math.sin(theta)) / theta**3 * (K @ K))


def pose_covariance(object_points, rvec, tvec, camera_matrix, dist_coeffs=None, sigma_px=0.5):
    """Covariance (6, 6) of a PnP pose from independent corner noise of ``sigma_px`` pixels per coordinate.

    First order: ``sigma_px^2 (J^T J)^-1`` with ``J`` the Jacobian of the projected points by the rotation vector
    and the translation (``cv2.projectPoints``), then mapped to ``(x, y, z, rot_x, rot_y, rot_z)``: the position in
    the camera frame and small rotations about the camera frame's fixed axes (ROS's ``PoseWithCovariance``).

    Parameters
    ----------
    object_points : ndarray, shape (n, 3)
    rvec, tvec : array-like, shape (3,)
        The pose (OpenCV's rotation vector and translation, camera from object).
    camera_matrix : ndarray, shape (3, 3)
    dist_coeffs : ndarray or None
    sigma_px : float
    """
    rvec = np.asarray(rvec, dtype=float).reshape(3)
    tvec = np.asarray(tvec, dtype=float).reshape(3)
    _, jacobian = cv2.projectPoints(np.asarray(object_points, dtype=float), rvec, tvec, camera_matrix, dist_coeffs)
    J = jacobian[:, :6]  # d(u, v) / d(rvec, tvec)
    params = sigma_px**2 * np.linalg.pinv(J.T @ J)
    T = np.zeros((6, 6))
    T[:3, 3:] = np.eye(3)
    T[3:, :3] = _left_jacobian(rvec)  # d(fixed-axis rotation) / d(rvec): exp(J dr) R(r) = R(r + dr)
    cov = T @ params @ T.T
    return 0.5 * (cov + cov.T)


def marker_object_points(size):
    """Corners of a square marker of edge ``size`` in its own frame, in the order IPPE_SQUARE requires.

    The order (top-left, top-right, bottom-right, bottom-left as seen from the front, x right, y up) is also the
    order in which :class:`cv2.aruco.ArucoDetector` returns a marker's image corners.

    Parameters
    ----------
    size : float
        Edge length, m.

    Returns
    -------
    points : ndarray, shape (4, 3)
    """
    h = 0.5 * float(size)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def square_pnp(object_points, image_points, camera_matrix, dist_coeffs=None):
    """IPPE's two poses of a square marker from its corners: ``cv2.solvePnPGeneric``'s ``(n, rvecs, tvecs,
    errors)``. ``SOLVEPNP_IPPE_SQUARE``, or the general planar ``SOLVEPNP_IPPE`` where it gives no finite solution:
    its closed form is NaN for some symmetric views (a marker tilted about the image's horizontal axis and centred on
    the principal point's column; the simulator's planar arm's base marker, once its corners were in OpenCV's pixel
    convention), where the general one gives the same two poses."""
    image_points = np.ascontiguousarray(image_points, dtype=float).reshape(-1, 2)
    for flag in (cv2.SOLVEPNP_IPPE_SQUARE, cv2.SOLVEPNP_IPPE):
        n, rvecs, tvecs, errors = cv2.solvePnPGeneric(object_points, image_points, camera_matrix, dist_coeffs,
                                                      flags=flag)
        if n >= 1 and np.all(np.isfinite(rvecs[0])) and np.all(np.isfinite(tvecs[0])):
            break
    return n, rvecs, tvecs, errors


def check_image(image):
    """Validate a camera image and return it as a grayscale uint8 array.

    Parameters
    ----------
    image : ndarray, shape (H, W), (H, W, 1), (H, W, 3) RGB or (H, W, 4) RGBA, dtype uint8

    Returns
    -------
    gray : ndarray, shape (H, W), dtype uint8

    Raises
    ------
    InvalidInputError
        If ``image`` is not a numpy array, not uint8, empty, or of another shape.
    """
    if not isinstance(image, np.ndarray):
        raise InvalidInputError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InvalidInputError(f"image must have dtype uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (3, 4))):
        raise InvalidInputError(f"image must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise InvalidInputError(f"image is empty, shape {image.shape}")
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    code = cv2.COLOR_RGB2GRAY if image.shape[2] == 3 else cv2.COLOR_RGBA2GRAY
    return cv2.cvtColor(np.ascontiguousarray(image), code)


def _check_camera_matrix(camera_matrix):
    K = np.asarray(camera_matrix, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InvalidInputError(f"camera_matrix must be a finite (3, 3) array, got shape {K.shape}")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1.0 and K[2, 0] == 0.0 and K[2, 1] == 0.0):
        raise InvalidInputError(f"camera_matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got "
                                f"{K.tolist()}")
    return K


def _check_dist_coeffs(dist_coeffs):
    if dist_coeffs is None:
        return np.zeros(5)
    D = np.asarray(dist_coeffs, dtype=float).ravel()
    if D.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(D)):
        raise InvalidInputError(f"dist_coeffs must hold 4, 5, 8, 12 or 14 finite values, got {D.size}")
    return D


def _check_marker_sizes(marker_sizes, default_size):
    """``(sizes by id, default size or None)`` from a mapping id -> m or one float for every id."""
    default = None if default_size is None else _check_size(default_size, "default_size")
    if isinstance(marker_sizes, Mapping):
        sizes = {}
        for marker_id, size in marker_sizes.items():
            if isinstance(marker_id, bool) or not isinstance(marker_id, (int, np.integer)) or marker_id < 0:
                raise InvalidInputError(f"marker ids must be integers >= 0, got {marker_id!r}")
            sizes[int(marker_id)] = _check_size(size, f"marker {marker_id} size")
        return sizes, default
    if default is not None:
        raise InvalidInputError("default_size only applies when marker_sizes is a mapping id -> size")
    return {}, _check_size(marker_sizes, "marker_sizes")


def _check_size(size, name):
    try:
        size = float(size)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number (m) or a mapping id -> m, got {size!r}") from None
    if not (math.isfinite(size) and size > 0):
        raise InvalidInputError(f"{name} must be finite and > 0 (m), got {size}")
    return size


def _dictionary(name):
    if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise InvalidInputError(f"unknown ArUco dictionary {name!r}; OpenCV knows {known}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


_CORNER_REFINEMENTS = ("apriltag", "subpix", "contour", "none")
#: OpenCV's ``CORNER_REFINE_APRILTAG`` gives corners in AprilTag's pixel convention (a pixel's centre at +0.5,
#: AprilRobotics/apriltag#121), half a pixel right of and below OpenCV's (the centre at the integer), which the camera
#: matrix and the other refinements use: subtracted. Measured before: +0.43 / +0.43 px on the simulator's images
#: (no refinement +0.00 / +0.04), +0.44 / +0.41 px on an area-sampled marker, exactly +0.5 on an axis-aligned one; a
#: lateral bias of 0.8 mm at 1 m for a 600 px focal length.
APRILTAG_PIXEL_OFFSET = 0.5


def _corner_refinement(name):
    if name not in _CORNER_REFINEMENTS:
        raise InvalidInputError(f"corner_refinement must be one of {_CORNER_REFINEMENTS}, got {name!r}")
    return getattr(cv2.aruco, f"CORNER_REFINE_{name.upper()}")


class MarkerTracker:
    """Detect ArUco markers in an image and estimate their 6D poses in the camera frame.

    Parameters
    ----------
    camera_matrix : array-like, shape (3, 3)
        Intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` of the (rectified or raw) image.
    dist_coeffs : array-like, shape (k,), optional
        OpenCV distortion coefficients (k = 4, 5, 8, 12 or 14); ``None``: no distortion.
    marker_sizes : dict of int to float, or float
        Edge length (m) per marker id, or one edge length for every id. Detected ids without a size are rejected.
    default_size : float, optional
        With a mapping ``marker_sizes``: edge length of the ids it does not list (``None``: those are rejected).
    dictionary : str
        Name of an OpenCV predefined ArUco dictionary, e.g. ``"DICT_4X4_50"``.
    min_side_px : float
        Detections whose shortest side is shorter than this (pixels) are rejected as too small to give a pose.
    max_reprojection_error : float
        Detections whose pose reprojects the corners worse than this (RMS, pixels) are rejected.
    max_ambiguity : float
        Detections whose two IPPE solutions have reprojection errors in a ratio (best / second) at or above this are
        rejected as ambiguous; 1.0 (default) keeps every detection. On the simulator's images 0.8 keeps 92 % of the
        detections and cuts mirrored orientations from 5.4 % to 3.3 %; 0.5 keeps 58 % and leaves 1.5 %.
    corner_refinement : str
        ``"apriltag"``, ``"subpix"``, ``"contour"`` or ``"none"`` (OpenCV's ``CORNER_REFINE_*``). ``"apriltag"``
        fits lines to the marker's edges; on small, distant markers the other methods place the corners up to
        0.7 px inside the marker, which biases the distance by several centimetres.
    corner_sigma_px : float
        Standard deviation (px) of a detected corner's coordinates, for each pose's covariance
        (:func:`pose_covariance`; the learner may learn a scale on it).
    plates : dict of int to Plate, optional
        Plates of several tags (:mod:`body_scheme_core.plates`, e.g. from a marker file's ``plate`` entries): their
        tags give one pose under the plate's id from all their visible corners, not a pose each.

    Attributes
    ----------
    counts : dict of str to int
        Running totals: ``images``, ``detected`` (marker detections) and ``poses`` (detections that became poses).
    """

    def __init__(self, camera_matrix, dist_coeffs=None, marker_sizes=0.08, dictionary="DICT_4X4_50",
                 min_side_px=6.0, max_reprojection_error=2.0, corner_refinement="apriltag", default_size=None,
                 max_ambiguity=0.8, corner_sigma_px=0.5, plates=None):
        self.camera_matrix = _check_camera_matrix(camera_matrix)
        self.dist_coeffs = _check_dist_coeffs(dist_coeffs)
        self.marker_sizes, self.default_size = _check_marker_sizes(marker_sizes, default_size)
        self.dictionary = dictionary
        self.min_side_px = float(min_side_px)
        self.max_reprojection_error = float(max_reprojection_error)
        self.max_ambiguity = float(max_ambiguity)
        if not 0.0 < self.max_ambiguity <= 1.0:
            raise InvalidInputError(f"max_ambiguity must be in (0, 1], got {max_ambiguity}")
        self.corner_sigma_px = float(corner_sigma_px)
        if not (math.isfinite(self.corner_sigma_px) and self.corner_sigma_px > 0.0):
            raise InvalidInputError(f"corner_sigma_px must be a finite number > 0, got {corner_sigma_px}")
        self.plates = dict(plates or {})
        self._plate_of = {tag: plate_id for plate_id, plate in self.plates.items() for tag in plate.tags}
        parameters = cv2.aruco.DetectorParameters()
        parameters.cornerRefinementMethod = _corner_refinement(corner_refinement)
        self._corner_offset = APRILTAG_PIXEL_OFFSET if corner_refinement == "apriltag" else 0.0
        self._detector = cv2.aruco.ArucoDetector(_dictionary(dictionary), parameters)
        self.counts = {"images": 0, "detected": 0, "poses": 0}

    def size_of(self, marker_id):
        """Edge length (m) of marker ``marker_id``, or ``None`` if it is not known."""
        return self.marker_sizes.get(int(marker_id), self.default_size)

    def detect(self, image):
        """Detect markers and estimate their poses (:meth:`detect_markers` without the details).

        Parameters
        ----------
        image : ndarray, shape (H, W), (H, W, 1), (H, W, 3) RGB or (H, W, 4) RGBA, dtype uint8

        Returns
        -------
        poses : dict of int to ndarray, shape (4, 4)
            ``camera2marker`` of every marker that was detected once and whose pose is valid.
        rejected : list of (int, str)
            Marker id and reason for every detection that did not become a pose.

        Raises
        ------
        InvalidInputError
            If the image has the wrong type, dtype or shape.
        """
        detections, rejected = self.detect_markers(image)
        return {marker_id: d.pose for marker_id, d in detections.items()}, rejected

    def detect_markers(self, image):
        """Detect markers and estimate their poses, covariances and IPPE's other solutions.

        Returns
        -------
        detections : dict of int to MarkerDetection
            Every marker that was detected once and whose pose is valid.
        rejected : list of (int, str)
            Marker id and reason for every detection that did not become a pose.
        """
        gray = check_image(image)
        corners, ids, _ = self._detector.detectMarkers(gray)
        corners = [np.asarray(c, dtype=float) - self._corner_offset for c in corners]
        self.counts["images"] += 1
        if ids is None or len(ids) == 0:
            return {}, []
        ids = [int(i) for i in np.asarray(ids).ravel()]
        self.counts["detected"] += len(ids)
        repeated = {i for i in ids if ids.count(i) > 1}
        poses, rejected, on_plates = {}, [], {}
        for marker_id, image_points in zip(ids, corners, strict=True):
            image_points = np.asarray(image_points, dtype=float).reshape(4, 2)
            if marker_id in repeated:
                rejected.append((marker_id, "repeated marker id in one image"))
                continue
            if marker_id in self._plate_of:  # its plate's pose comes from all of them, below
                reason = self._side_problem(image_points)
                if reason is None:
                    on_plates.setdefault(self._plate_of[marker_id], {})[marker_id] = image_points
                    continue
            else:
                detection, reason = self._pose(marker_id, image_points)
                if detection is not None:
                    poses[marker_id] = detection
                    continue
            rejected.append((marker_id, reason))
        for plate_id, seen in on_plates.items():
            detection, reason = self._plate_pose(plate_id, seen)
            if detection is None:
                rejected.append((plate_id, reason))
            else:
                poses[plate_id] = detection
        self.counts["poses"] += len(poses)
        return poses, rejected

    def _side_problem(self, image_points):
        """None, or why a detection's corners (4, 2) are too small or not finite to give a pose."""
        sides = np.linalg.norm(image_points - np.roll(image_points, -1, axis=0), axis=1)
        if not np.all(np.isfinite(image_points)) or sides.min() < self.min_side_px:
            return f"degenerate detection: shortest side {sides.min():.1f} px < {self.min_side_px} px"
        return None

    def _checked(self, detection):
        """``(detection, None)``, or ``(None, reason)`` if ambiguous, behind the camera or reprojecting badly."""
        errors = detection.errors
        if len(errors) > 1 and self.max_ambiguity < 1.0 and errors[0] >= self.max_ambiguity * errors[1]:
            return None, (f"ambiguous pose: the mirrored solution reprojects almost as well ({errors[0]:.3f} vs "
                          f"{errors[1]:.3f} px, ratio >= {self.max_ambiguity})")
        if detection.pose[2, 3] <= 0:
            return None, "pose behind the camera"
        if errors[0] > self.max_reprojection_error:
            return None, f"reprojection error: {errors[0]:.2f} px > {self.max_reprojection_error} px"
        return detection, None

    def _plate_pose(self, plate_id, corners):
        """``(MarkerDetection, None)`` or ``(None, reason)`` for the corners of a plate's visible tags."""
        detection = self.plates[plate_id].pose(corners, self.camera_matrix, self.dist_coeffs, self.corner_sigma_px)
        return (None, "solvePnP found no pose") if detection is None else self._checked(detection)

    def _pose(self, marker_id, image_points):
        """``(MarkerDetection, None)`` or ``(None, reason)`` for one detection's corners, shape (4, 2)."""
        size = self.size_of(marker_id)
        if size is None:
            return None, "no size known for this marker id"
        if (problem := self._side_problem(image_points)) is not None:
            return None, problem
        object_points = marker_object_points(size)
        n, rvecs, tvecs, errors = square_pnp(object_points, image_points, self.camera_matrix, self.dist_coeffs)
        if n < 1 or not (np.all(np.isfinite(rvecs[0])) and np.all(np.isfinite(tvecs[0]))):
            return None, "solvePnP found no pose"
        errors = math.sqrt(2.0) * np.ravel(errors)[:2]  # OpenCV's is per coordinate; ours per corner
        covariance = pose_covariance(object_points, rvecs[0], tvecs[0], self.camera_matrix, self.dist_coeffs,
                                     self.corner_sigma_px)
        poses = [transform_from_rotvec(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs[:n], tvecs[:n], strict=True)]
        alternative = poses[1] if n > 1 and np.all(np.isfinite(poses[1])) else None
        return self._checked(MarkerDetection(poses[0], covariance, alternative, tuple(float(e) for e in errors)))


def rejection_kind(reason):
    """The counter key of a rejection reason: its words before the first colon (the numbers after it would make
    every rejection a key of its own)."""
    return str(reason).split(":", 1)[0].strip()
