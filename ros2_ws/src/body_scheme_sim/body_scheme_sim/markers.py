"""ArUco marker plates: the markers' patterns and corners, and the plate mesh the simulator renders.

A marker of ``size`` s is the black ArUco square of side s (OpenCV's marker length, the one ``solvePnP`` uses),
printed on a white plate one marker cell wider on every side (the quiet zone detectors need). The marker frame is
OpenCV ArUco's: origin at the centre of the square, x to the right and y up in the marker image, z out of the plate
towards the viewer. So the image's top-left corner is at ``(-s/2, s/2, 0)``, the first corner
``cv2.aruco.ArucoDetector.detectMarkers`` reports.
"""

from __future__ import annotations

import pathlib

import cv2
import numpy as np

from body_scheme_core.errors import InvalidInputError

__all__ = ["ARUCO_DICTIONARY", "MARKER_CELLS", "PLATE_THICKNESS", "aruco_dictionary", "marker_image",
           "plate_side", "marker_corners", "write_plate_obj", "beside_markers"]

#: OpenCV predefined dictionary of the markers; a marker's id is its ArUco id.
ARUCO_DICTIONARY = cv2.aruco.DICT_4X4_50
#: Cells across a marker of that dictionary: 4 data bits plus a black border cell on each side.
MARKER_CELLS = 6
#: Thickness of a marker plate, m.
PLATE_THICKNESS = 0.002

# A unit plate: front face z = 0 spanning [-0.5, 0.5]^2 and mapped onto the whole texture, back face at z = -1.
# pybullet scales it by (plate side, plate side, thickness). Back and sides sample the texture's white border.
# OBJ texture coordinates have v = 0 at the bottom of the image, so the image's top-left corner (v = 1) goes to
# the plate's (-0.5, +0.5) corner: x right, y up, as in OpenCV's marker frame.
_PLATE_OBJ = """\
# body_scheme_sim marker plate (unit size, front face z = 0 textured with the marker image)
v -0.5 -0.5 0
v 0.5 -0.5 0
v 0.5 0.5 0
v -0.5 0.5 0
v -0.5 -0.5 -1
v 0.5 -0.5 -1
v 0.5 0.5 -1
v -0.5 0.5 -1
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.02 0.02
vn 0 0 1
vn 0 0 -1
vn 1 0 0
vn -1 0 0
vn 0 1 0
vn 0 -1 0
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
f 5/5/2 8/5/2 7/5/2
f 5/5/2 7/5/2 6/5/2
f 2/5/3 6/5/3 7/5/3
f 2/5/3 7/5/3 3/5/3
f 1/5/4 4/5/4 8/5/4
f 1/5/4 8/5/4 5/5/4
f 4/5/5 3/5/5 7/5/5
f 4/5/5 7/5/5 8/5/5
f 1/5/6 5/5/6 6/5/6
f 1/5/6 6/5/6 2/5/6
"""


def aruco_dictionary():
    """The OpenCV ArUco dictionary of the simulated markers."""
    return cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY)


def marker_image(marker_id, pixels):
    """The black ArUco square of ``marker_id``, ``pixels`` wide (grey levels, 0 black and 255 white, top row first).

    Raises
    ------
    InvalidInputError
        If :data:`ARUCO_DICTIONARY` holds no such id.
    """
    dictionary = aruco_dictionary()
    n_ids = dictionary.bytesList.shape[0]
    if isinstance(marker_id, bool) or int(marker_id) != marker_id or not (0 <= int(marker_id) < n_ids):
        raise InvalidInputError(
            f"marker id {marker_id!r} has no ArUco marker: DICT_4X4_50 holds ids 0..{n_ids - 1}")
    return cv2.aruco.generateImageMarker(dictionary, int(marker_id), int(pixels))


def plate_side(size):
    """Side of the white plate of a marker of side ``size`` (m): one cell of border on each side."""
    return size * (MARKER_CELLS + 2) / MARKER_CELLS


def marker_corners(size):
    """Corners of a marker's black square in its own frame, in OpenCV ArUco order (TL, TR, BR, BL).

    Returns
    -------
    corners : ndarray, shape (4, 3)
    """
    h = 0.5 * size
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def write_plate_obj(directory):
    """Write the unit plate mesh (Wavefront OBJ with texture coordinates) into ``directory``; returns its path."""
    path = pathlib.Path(directory) / "marker_plate.obj"
    path.write_text(_PLATE_OBJ, encoding="utf-8")
    return path


def beside_markers(markers_path, name):
    """A file that goes with a marker file, beside it and named after it: ``beside_markers("dir/markers.yaml",
    "camera.yaml")`` is ``dir/camera.yaml``; ``bags/run.markers.yaml`` gives ``bags/run.camera.yaml`` (so two
    recordings in one directory never overwrite each other's); ``plates.yaml`` gives ``plates.camera.yaml``."""
    markers_path = pathlib.Path(markers_path)
    stem = markers_path.name
    if stem == "markers.yaml" or stem.endswith(".markers.yaml"):
        return markers_path.with_name(stem[:-len("markers.yaml")] + name)
    return markers_path.with_name(f"{markers_path.stem}.{name}")
