"""A fixed pinhole camera: OpenCV intrinsics, its pose in the world, and the matching pybullet matrices.

Conventions: ``world2camera`` is the pose of the camera *optical* frame in the world (OpenCV: z forward, x right,
y down). Pixel coordinates are OpenCV's: ``(u, v) = (column, row)`` with pixel centres at integers, so a point
projects to ``u = fx x / z + cx``, ``v = fy y / z + cy``. The pybullet (OpenGL) view and projection matrices are
derived from these numbers alone, so what pybullet renders and what ``K`` predicts agree (tested to < 1 px).
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, field

import numpy as np
import yaml

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import (
    check_transform,
    invert_transform,
    transform_from_xyz_rpy,
    xyz_rpy_from_transform,
)

__all__ = ["Camera", "look_at", "DEFAULT_EYE", "DEFAULT_TARGET", "DEFAULT_HFOV", "CAMERA_KEYS", "camera_parameters",
           "camera_from_values", "write_camera", "read_camera"]

#: Default camera position (m, world frame): in front of the robot (+x), 1.5 m from its middle, 40 deg above it.
#: Chosen so that markers facing the camera (3D arms) and facing up (planar arm) are both seen at <= 50 deg and large
#: enough at 640x480 for cv2.aruco to decode them and for IPPE to tell a marker's tilt from its mirror image (from 2 m,
#: 20 px markers came out mirrored 6 % of the time, one marker 27 %; see docs/sim.md).
DEFAULT_EYE = (1.1625, 0.0, 1.375)
#: Default point the camera looks at: the middle of a ~1.2 m arm standing at the world origin.
DEFAULT_TARGET = (0.0, 0.0, 0.4)
#: Default horizontal field of view, rad.
DEFAULT_HFOV = math.radians(60.0)
_DEFAULT_WIDTH, _DEFAULT_HEIGHT = 640, 480
_DEFAULT_F = 0.5 * _DEFAULT_WIDTH / math.tan(0.5 * DEFAULT_HFOV)
# OpenCV optical frame -> OpenGL camera frame (x right, y up, z backwards).
_CV2GL = np.diag([1.0, -1.0, -1.0, 1.0])


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """Pose of a camera optical frame at ``eye`` looking at ``target`` with image "up" along ``up``.

    Parameters
    ----------
    eye, target, up : array-like, shape (3,)

    Returns
    -------
    world2camera : ndarray, shape (4, 4)
    """
    eye, target, up = (np.asarray(v, dtype=float) for v in (eye, target, up))
    z = target - eye
    if not np.linalg.norm(z) > 1e-9:
        raise InvalidInputError(f"eye {eye.tolist()} and target {target.tolist()} coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if not np.linalg.norm(x) > 1e-9:
        raise InvalidInputError(f"viewing direction {z.tolist()} is parallel to up {up.tolist()}")
    x /= np.linalg.norm(x)
    world2camera = np.eye(4)
    world2camera[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    world2camera[:3, 3] = eye
    return world2camera


@dataclass
class Camera:
    """A fixed pinhole camera without distortion.

    Attributes
    ----------
    width, height : int
        Image size, pixels.
    fx, fy, cx, cy : float
        OpenCV intrinsics, pixels (default: 60 deg horizontal field of view, principal point at the image centre).
    world2camera : ndarray, shape (4, 4)
        Pose of the optical frame in the world (default: :func:`look_at` from :data:`DEFAULT_EYE` to
        :data:`DEFAULT_TARGET`, about 2 m from the robot).
    near, far : float
        Clipping distances of the renderer, m.
    """

    width: int = _DEFAULT_WIDTH
    height: int = _DEFAULT_HEIGHT
    fx: float = _DEFAULT_F
    fy: float = _DEFAULT_F
    cx: float = 0.5 * (_DEFAULT_WIDTH - 1)
    cy: float = 0.5 * (_DEFAULT_HEIGHT - 1)
    world2camera: np.ndarray = field(default_factory=lambda: look_at(DEFAULT_EYE, DEFAULT_TARGET))
    near: float = 0.05
    far: float = 10.0

    def __post_init__(self):
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or int(value) < 1:
                raise InvalidInputError(f"camera {name} must be a positive integer, got {value!r}")
            setattr(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy", "near", "far"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise InvalidInputError(f"camera {name} must be finite, got {value!r}")
            setattr(self, name, value)
        if not (self.fx > 0 and self.fy > 0):
            raise InvalidInputError(f"camera fx, fy must be > 0, got {self.fx}, {self.fy}")
        if not (0 < self.near < self.far):
            raise InvalidInputError(f"camera needs 0 < near < far, got {self.near}, {self.far}")
        self.world2camera = check_transform(np.array(self.world2camera, dtype=float), name="world2camera")
        if self.world2camera.shape != (4, 4):
            raise InvalidInputError(f"world2camera must have shape (4, 4), got {self.world2camera.shape}")

    @property
    def K(self):
        """Intrinsic matrix, shape (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def position(self):
        """Optical centre in the world, shape (3,)."""
        return self.world2camera[:3, 3].copy()

    def project(self, points):
        """Pixel coordinates and depth of world points.

        Parameters
        ----------
        points : array-like, shape (n, 3)
            Points in the world frame.

        Returns
        -------
        uv : ndarray, shape (n, 2)
            ``(u, v)`` = (column, row), OpenCV convention; meaningless where ``depth <= 0``.
        depth : ndarray, shape (n,)
            ``z`` in the optical frame, m (> 0 in front of the camera).
        """
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        camera2world = invert_transform(self.world2camera)
        in_camera = points @ camera2world[:3, :3].T + camera2world[:3, 3]
        depth = in_camera[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = in_camera[:, :2] / depth[:, None] * [self.fx, self.fy] + [self.cx, self.cy]
        return uv, depth

    def in_image(self, uv, margin=0.0):
        """Whether pixel coordinates ``uv`` (n, 2) lie inside the image, ``margin`` pixels from its border."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return ((uv[:, 0] >= margin - 0.5) & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= margin - 0.5) & (uv[:, 1] <= self.height - 0.5 - margin))

    @property
    def view_matrix(self):
        """pybullet view matrix: world to OpenGL camera coordinates, 16 floats column-major."""
        world2gl_camera = self.world2camera @ _CV2GL
        return tuple(invert_transform(world2gl_camera).flatten(order="F"))

    @property
    def projection_matrix(self):
        """pybullet (OpenGL) projection matrix equivalent to ``K``, 16 floats column-major.

        TinyRenderer samples pixel column ``i`` at window x = ``i`` (not ``i + 0.5``) and row ``r`` (top row first)
        at window y = ``height - 1 - r``; the ``cx`` and ``cy + 1`` terms make OpenCV's pixel-centre convention come
        out exactly (measured: rendered and ``K``-projected points agree to < 0.2 px).
        """
        w, h, n, f = self.width, self.height, self.near, self.far
        P = np.zeros((4, 4))
        P[0, 0] = 2.0 * self.fx / w
        P[0, 2] = 1.0 - 2.0 * self.cx / w
        P[1, 1] = 2.0 * self.fy / h
        P[1, 2] = 2.0 * (self.cy + 1.0) / h - 1.0
        P[2, 2] = -(f + n) / (f - n)
        P[2, 3] = -2.0 * f * n / (f - n)
        P[3, 2] = -1.0
        return tuple(P.flatten(order="F"))


#: The keys of a camera's values (sim_node's ``camera.*`` parameters, a ``camera.yaml``'s ``camera:`` mapping).
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "xyz", "rpy")


def camera_parameters(camera):
    """``{camera: {width, height, fx, fy, cx, cy, xyz, rpy}}``: sim_node's ``camera.*`` parameters of a
    :class:`Camera` (``xyz`` / ``rpy``: the optical frame in the world, m and rad); the content of ``camera.yaml``."""
    xyz, rpy = xyz_rpy_from_transform(camera.world2camera)
    return {"camera": {"width": int(camera.width), "height": int(camera.height), "fx": float(camera.fx),
                       "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
                       "xyz": [float(v) for v in xyz], "rpy": [float(v) for v in rpy]}}


def camera_from_values(values):
    """The :class:`Camera` of a mapping with :data:`CAMERA_KEYS` (the inverse of :func:`camera_parameters`).

    Raises
    ------
    KeyError, TypeError, ValueError
        A key missing, a value not a number, ``xyz`` or ``rpy`` not three numbers; InvalidInputError from
        :class:`Camera` for impossible intrinsics.
    """
    missing = [key for key in CAMERA_KEYS if key not in values]
    if missing:
        raise KeyError(", ".join(missing))
    xyz, rpy = ([float(v) for v in values[key]] for key in ("xyz", "rpy"))
    if len(xyz) != 3 or len(rpy) != 3:
        raise ValueError("xyz and rpy take three numbers each")
    return Camera(width=values["width"], height=values["height"], fx=float(values["fx"]), fy=float(values["fy"]),
                  cx=float(values["cx"]), cy=float(values["cy"]), world2camera=transform_from_xyz_rpy(xyz, rpy))


def write_camera(camera, path):
    """Write :func:`camera_parameters` of ``camera`` to ``path`` as YAML; returns ``path``."""
    path = pathlib.Path(path)
    path.write_text(yaml.safe_dump(camera_parameters(camera), sort_keys=False), encoding="utf-8")
    return path


def read_camera(path):
    """The :class:`Camera` of a file :func:`write_camera` wrote (plan_markers' ``camera.yaml``).

    Raises
    ------
    InvalidInputError
        One line naming the file: unreadable, not YAML, or a key missing or not a number.
    """
    try:
        return camera_from_values(yaml.safe_load(pathlib.Path(path).read_text(encoding="utf-8"))["camera"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError, InvalidInputError) as error:
        why = " ".join(str(error).split())  # one line, whatever YAML's message spans
        raise InvalidInputError(f"camera file {path}: {type(error).__name__}: {why} (plan_markers writes it: "
                                f"{{camera: {{{', '.join(CAMERA_KEYS)}}}}})") from None
