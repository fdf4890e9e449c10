"""The simulated world: a robot arm in pybullet with ArUco marker plates, a ground plane and a fixed camera.

Execution is kinematic (no dynamics): a command is clipped to the joint limits, blocked joints keep their angle, and
the joints are set directly. The true geometry lives in a core :class:`~body_scheme_core.world.Body` (a
:class:`KinematicTree` plus blocked joints); faults are the core's fault functions applied to it, so the simulator
and the synthetic sessions of the core share one definition of "block", "deform" and "displace". pybullet draws
the robot and answers collision and line-of-sight queries; ground-truth marker poses come from the tree's forward
kinematics (a test checks that pybullet's link poses agree).

Frames: the robot's root link sits at the world origin (``world2root`` is the identity), the ground is the plane
``z = 0``, and the camera's optical frame is at ``camera.world2camera``. Observations and ground truth are
``camera2marker``: marker poses in the camera optical frame.
"""

from __future__ import annotations

import hashlib
import math
import os
import pathlib
import tempfile

import cv2
import numpy as np
import pybullet
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import check_transform, invert_transform
from body_scheme_core.world import (
    FAULT_KINDS,
    PAPER_SIGMA_ROT,
    PAPER_SIGMA_TRANS,
    Body,
    Fault,
    KinematicTree,
    ObservationModel,
)

from .camera import Camera
from .collisions import pairs_always_in_contact, pairs_in_contact
from .markers import marker_corners
from .robots import ROBOT_BUILDERS, load_robot, robot_files
from .scene import create_ground, create_marker_plates, direct_client, link_poses, patched_urdf, render, render_ground

__all__ = ["SimWorld", "MAX_VIEW_ANGLE", "MIN_MARKER_PIXELS"]

#: A marker counts as visible only if its normal is within this angle of the direction to the camera, rad.
MAX_VIEW_ANGLE = math.radians(70.0)
#: A marker counts as visible only if each edge of its square spans at least this many pixels in the image (2 pixels
#: per cell of the 6-cell ArUco square; below that cv2.aruco rarely decodes a marker).
MIN_MARKER_PIXELS = 12.0
#: Visible marker corners must lie this many pixels inside the image border.
IMAGE_MARGIN = 2.0
# Rays stop this far (m) in front of a marker point, so they never hit the marker's own plate.
_RAY_STANDOFF = 2e-3


class SimWorld:
    """A robot with ArUco markers seen by a fixed camera, with runtime faults and ground truth.

    Parameters
    ----------
    robot : str or os.PathLike or KinematicTree
        A shipped robot name (:func:`~body_scheme_sim.robots.robot_names`), a URDF path (markers from
        ``markers_path`` or ``<stem>.markers.yaml`` next to it) or a tree (drawn from ``KinematicTree.to_urdf``).
    camera : Camera or None
        ``None``: :class:`Camera` defaults (640x480, 60 deg, about 2 m in front of the robot).
    markers_path : str or os.PathLike or None
        Marker placement file (see :func:`~body_scheme_sim.robots.load_robot`).
    seed : int or None
        Seed of :attr:`rng`, the default random stream of :meth:`observe_noisy` and babbling.
    marker_texture : bool
        Draw the ArUco patterns; ``False`` draws plain plates (same occlusion, no texture loading).
    max_view_angle : float
        See :data:`MAX_VIEW_ANGLE`.
    min_marker_pixels : float
        See :data:`MIN_MARKER_PIXELS`.
    markers : iterable of Marker or None
        The markers, instead of a marker file (e.g. none: a robot for collision checks only).
    package_path : iterable of str or os.PathLike
        Directories searched first for ``package://`` meshes
        (:func:`~body_scheme_core.world.robot_files.resolve_resource`). Meshes that are not found are left out of
        the drawing and listed in :attr:`missing_meshes`; the kinematics do not need them.

    Notes
    -----
    Each world owns a pybullet DIRECT client, so several worlds live in one process. Call :meth:`close` (or use
    ``with SimWorld(...) as world:``) to free it.
    """

    def __init__(self, robot="powercube_6dof", camera=None, markers_path=None, seed=0, marker_texture=True,
                 max_view_angle=MAX_VIEW_ANGLE, min_marker_pixels=MIN_MARKER_PIXELS, package_path=(), markers=None):
        self.camera = Camera() if camera is None else camera
        if not isinstance(self.camera, Camera):
            raise InvalidInputError(f"camera must be a Camera, got {type(self.camera).__name__}")
        self.rng = np.random.default_rng(seed)
        self.max_view_angle = float(max_view_angle)
        self.min_marker_pixels = float(min_marker_pixels)
        self._package_path = tuple(package_path)
        #: Mesh URIs of the robot's URDF that were not found (drawn without them).
        self.missing_meshes = []
        self._tmp = tempfile.TemporaryDirectory(prefix="body_scheme_sim_")
        self._dir = pathlib.Path(self._tmp.name)
        self._pb = None
        self._backdrop_cache = None
        if isinstance(robot, KinematicTree):
            tree, self._urdf_path = robot, None
        elif markers is not None:
            self._urdf_path = robot_files(robot, require_markers=False)[0]
            tree = load_robot(self._urdf_path, markers=markers)
        else:
            self._urdf_path, markers_path = robot_files(robot, markers_path)
            tree = load_robot(self._urdf_path, markers_path)
        # Shipped robots are to_urdf() output: a deformed one is drawn the same way. Other URDFs keep their own
        # meshes and get only the joint origins patched.
        self._redraw_from_tree = self._urdf_path is None or os.fspath(robot) in ROBOT_BUILDERS
        self._n_loads = 0
        self._nominal = Body(tree)
        self._body = self._nominal
        self._faults = []
        try:
            self._pb = direct_client()
            self._robot_id = self._load_robot(tree)
            self._index_links(tree)
            self._ground_id = create_ground(self._pb)
            self._marker_bodies = create_marker_plates(self._pb, self._dir, tree.markers, marker_texture)
            self._command = np.clip(np.zeros(tree.n_actions), tree.action_lower, tree.action_upper)
            self._set_configuration(self._body.execute(self._command))
            self._ignored_pairs = self._pairs_in_contact() | self._pairs_always_in_contact()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ set-up
    def _load_robot(self, tree):
        """Load the robot into pybullet: its own URDF file, or one drawn for a deformed or in-memory tree."""
        self._n_loads += 1
        if self._urdf_path is not None and tree is self._nominal.tree and self._redraw_from_tree:
            path = self._urdf_path  # a shipped robot: its own file
        else:
            path = self._dir / f"robot_{self._n_loads}.urdf"
            if self._redraw_from_tree:
                text = tree.to_urdf("body_scheme_sim_robot")
            else:
                urdf = self._urdf_path.read_text(encoding="utf-8", errors="replace")
                text, self.missing_meshes = patched_urdf(urdf, self._urdf_path.resolve().parent, tree,
                                                         self._package_path)
            path.write_text(text, encoding="utf-8")
        if self._n_loads == 1:
            self._nominal_urdf = pathlib.Path(path).read_bytes()  # the key of the "always in contact" cache
        try:
            return self._pb.loadURDF(str(path), basePosition=(0.0, 0.0, 0.0), useFixedBase=True)
        except pybullet.error as error:
            raise InvalidInputError(f"pybullet cannot load the robot's URDF {self._urdf_path or path}: {error}") \
                from None

    def _index_links(self, tree):
        pb = self._pb
        joint_index, link_index = {}, {tree.root_link: -1}
        for index in range(pb.getNumJoints(self._robot_id)):
            info = pb.getJointInfo(self._robot_id, index)
            joint_index[info[1].decode()] = index
            link_index[info[12].decode()] = index
        movable = [j.name for j in tree.joints if j.is_movable]
        missing = [name for name in movable if name not in joint_index]
        if missing:
            raise InvalidInputError(f"pybullet did not load joints {missing} of the robot")
        self._movable_joint_index = {name: joint_index[name] for name in movable}
        self._link_index = link_index
        self._parent_index = {link_index[j.child]: link_index[j.parent] for j in tree.joints}

    def _pairs_in_contact(self):
        return pairs_in_contact(self._pb, self._robot_id, self._ground_id, self._link_index.values(),
                                self._parent_index)

    def _pairs_always_in_contact(self):
        """The pairs that touch in (almost) every posture (:func:`.collisions.pairs_always_in_contact`), for this
        robot's URDF and limits; the reference posture is restored."""
        tree = self._nominal.tree
        key = (hashlib.sha256(self._nominal_urdf).hexdigest(), tuple(tree.action_lower), tuple(tree.action_upper))

        def contacts_at(a):
            self._set_configuration(self._body.execute(a))
            return self._pairs_in_contact()

        try:
            return pairs_always_in_contact(key, contacts_at, tree.action_lower, tree.action_upper)
        finally:
            self._set_configuration(self._body.execute(self._command))

    @property
    def ignored_collision_pairs(self):
        """``[(link, link or "ground")]`` by name: the pairs :meth:`in_collision` does not check, because they touch
        in the reference posture or in (almost) every posture (:mod:`.collisions`). Adjacent links are never checked
        and not listed."""
        names = {index: name for name, index in self._link_index.items()}
        return sorted((names[a], b if b == "ground" else names[b]) for a, b in self._ignored_pairs)

    # ------------------------------------------------------------------ the robot
    @property
    def robot(self):
        """The robot's true :class:`KinematicTree` now (deformed limbs and displaced markers included)."""
        return self._body.tree

    @property
    def nominal_robot(self):
        """The robot's :class:`KinematicTree` before any fault (its specification)."""
        return self._nominal.tree

    @property
    def marker_ids(self):
        """Marker ids, ascending."""
        return self._nominal.tree.marker_ids

    @property
    def n_actions(self):
        """Length m of the action vector."""
        return self._nominal.tree.n_actions

    @property
    def action_lower(self):
        """Lower joint limits, shape (m,)."""
        return self._nominal.tree.action_lower

    @property
    def action_upper(self):
        """Upper joint limits, shape (m,)."""
        return self._nominal.tree.action_upper

    @property
    def action_joint_names(self):
        """Joint name of each action, tuple of length m."""
        return self._nominal.tree.action_joint_names

    @property
    def camera2root(self):
        """Pose of the robot's root link in the camera optical frame, shape (4, 4) (the core's ``world2root``)."""
        return invert_transform(self.camera.world2camera)

    def execute(self, a):
        """Execute a command: clip to the joint limits, hold blocked joints, set the joints.

        Parameters
        ----------
        a : array-like, shape (m,)
            Commanded joint positions (rad or m) in action order.

        Returns
        -------
        q : ndarray, shape (m,)
            Joint positions reached.
        """
        a = np.array(a, dtype=float)
        if a.shape != (self.n_actions,):
            raise InvalidInputError(f"command must have shape ({self.n_actions},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InvalidInputError(f"command must be finite, got {a.tolist()}")
        self._command = a
        self._set_configuration(self._body.execute(a))
        return self._q.copy()

    @property
    def last_command(self):
        """The last command executed (before clipping and blocking), shape (m,); initially zeros within limits."""
        return self._command.copy()

    def joint_positions(self):
        """Joint positions reached by the last command, shape (m,)."""
        return self._q.copy()

    def _set_configuration(self, q):
        pb = self._pb
        for name, value in self._body.tree.joint_positions(q).items():  # mimic and passive joints too
            pb.resetJointState(self._robot_id, self._movable_joint_index[name], value)
        self._q = np.array(q, dtype=float)
        root2marker = self._body.tree.marker_poses(self._q)
        self._world2marker = root2marker
        for marker_id, (body, marker2body) in self._marker_bodies.items():
            pose = root2marker[marker_id] @ marker2body
            pb.resetBasePositionAndOrientation(body, pose[:3, 3], Rotation.from_matrix(pose[:3, :3]).as_quat())

    def drawn_link_poses(self):
        """Link poses as pybullet holds them, ``{link: world2link (4, 4)}`` (a check against ``robot.link_poses``)."""
        return link_poses(self._pb, self._robot_id, self._link_index)

    # ------------------------------------------------------------------ perception
    def render(self):
        """Camera image of the scene (pybullet TinyRenderer, headless).

        The static ground is rendered once per camera setting into a backdrop (colour and depth); each frame renders
        only the robot and the markers and lets the closer of the two win per pixel, the same z-test the renderer
        would do, at a third of the cost (TinyRenderer's cost grows with the pixels a surface covers).

        Returns
        -------
        image : ndarray, shape (height, width, 3), dtype uint8
            RGB, top row first.
        """
        backdrop_rgb, backdrop_depth = self._backdrop()
        rgb, depth = render(self._pb, self.camera)
        image = backdrop_rgb.copy()
        cv2.copyTo(rgb, (depth < backdrop_depth).view(np.uint8), image)  # in place, 30x faster than np.where
        return image

    def _backdrop(self):
        key = (self.camera.width, self.camera.height, self.camera.view_matrix, self.camera.projection_matrix)
        if self._backdrop_cache is None or self._backdrop_cache[0] != key:
            self._backdrop_cache = (key, render_ground(self.camera))
        return self._backdrop_cache[1]

    def true_marker_poses(self):
        """Ground truth (for evaluation only): ``{marker id: camera2marker (4, 4)}`` of every marker."""
        camera2world = invert_transform(self.camera.world2camera)
        return {marker_id: camera2world @ pose for marker_id, pose in self._world2marker.items()}

    def world_marker_poses(self):
        """Ground truth in the world frame: ``{marker id: world2marker (4, 4)}``."""
        return {marker_id: pose.copy() for marker_id, pose in self._world2marker.items()}

    def visible_marker_ids(self):
        """Markers the camera can see now: in the image, facing the camera, not occluded.

        A marker is visible if its four corners project inside the image (``IMAGE_MARGIN`` pixels from the border)
        in front of the camera, each edge spans at least ``min_marker_pixels``, its normal is within
        ``max_view_angle`` of the direction to the camera, and rays
        from the camera to its corners and centre hit nothing (robot, ground, other plates). No rendering needed.

        Returns
        -------
        ids : set of int
        """
        camera = self.camera
        eye = camera.position
        cos_limit = math.cos(self.max_view_angle)
        candidates, targets = [], []
        for marker in self._body.tree.markers:
            world2marker = self._world2marker[marker.id]
            to_camera = eye - world2marker[:3, 3]
            distance = np.linalg.norm(to_camera)
            if not (distance > 0 and world2marker[:3, 2] @ to_camera / distance > cos_limit):
                continue
            points = np.vstack([marker_corners(marker.size), np.zeros(3)]) @ world2marker[:3, :3].T \
                + world2marker[:3, 3]
            uv, depth = camera.project(points[:4])
            if not (np.all(depth > camera.near) and np.all(camera.in_image(uv, IMAGE_MARGIN))):
                continue
            if np.min(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)) < self.min_marker_pixels:
                continue
            rays = points - eye
            lengths = np.linalg.norm(rays, axis=1, keepdims=True)
            candidates.append(marker.id)
            targets.append(eye + rays * (1.0 - _RAY_STANDOFF / lengths))
        if not candidates:
            return set()
        targets = np.concatenate(targets)
        hits = self._pb.rayTestBatch(np.tile(eye, (len(targets), 1)).tolist(), targets.tolist())
        clear = np.array([hit[0] < 0 for hit in hits]).reshape(len(candidates), -1).all(axis=1)
        return {marker_id for marker_id, ok in zip(candidates, clear, strict=True) if ok}

    def observe_noisy(self, sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT, visibility=1.0, rng=None):
        """Fast noise-model perception: the visible markers' true poses, perturbed and randomly dropped.

        Noise follows :class:`body_scheme_core.world.ObservationModel` (``sigma_trans``, ``sigma_rot`` are 3D
        RMS errors); each visible marker is kept with probability ``visibility``.

        Parameters
        ----------
        sigma_trans : float
            m.
        sigma_rot : float
            rad.
        visibility : float
            In [0, 1].
        rng : numpy.random.Generator or int or None
            ``None``: :attr:`rng`.

        Returns
        -------
        observations : dict of int to ndarray, shape (4, 4)
            ``camera2marker`` of the observed markers.
        """
        model = ObservationModel(sigma_trans, sigma_rot, visibility, rng=self.rng if rng is None else rng,
                                 world2root=np.eye(4))
        truth = self.true_marker_poses()
        return model.observe({marker_id: truth[marker_id] for marker_id in sorted(self.visible_marker_ids())})

    def in_collision(self):
        """Whether the robot now collides with itself (non-adjacent links) or with the ground.

        Pairs already touching in the reference configuration (all actions 0), e.g. the base on the ground, or in
        almost every posture are ignored (:attr:`ignored_collision_pairs`).
        """
        return bool(self._pairs_in_contact() - self._ignored_pairs)

    # ------------------------------------------------------------------ faults
    @property
    def faults(self):
        """Active faults in the order applied (:class:`body_scheme_core.world.Fault`, blocks with their angle)."""
        return list(self._faults)

    def apply(self, fault):
        """Apply a :class:`body_scheme_core.world.Fault` (e.g. a parsed schedule entry) by its kind."""
        p = fault.params
        if fault.kind == "repair":
            self.repair(p.get("repair_kind"))
        elif fault.kind == "block_joint":
            self.block_joint(p["action_index"], p.get("angle"))
        elif fault.kind == "deform_limb":
            self.deform_limb(p["joint_or_link"], p.get("delta_length", 0.0), p.get("delta_rotvec", (0.0, 0.0, 0.0)))
        else:
            self.displace_marker(p["marker_id"], p["delta"])

    def block_joint(self, action_index, angle=None):
        """Block the joint of ``action_index``: it ignores commands and stays at ``angle`` (``None``: where it is).

        The fault takes effect at once (the last command is executed again on the changed body).
        """
        action_index = int(action_index)
        if not 0 <= action_index < self.n_actions:
            raise InvalidInputError(f"action_index must be in 0..{self.n_actions - 1}, got {action_index}")
        angle = float(self._q[action_index] if angle is None else angle)
        self._add_fault(Fault("block_joint", action_index=action_index, angle=angle))

    def deform_limb(self, joint_name, delta_length=0.0, delta_rotvec=(0.0, 0.0, 0.0)):
        """Stretch and/or bend the limb ending at ``joint_name`` (see ``body_scheme_core.world.deform_limb``).

        Parameters
        ----------
        joint_name : str
            Joint (or link: all its child joints) whose origin changes.
        delta_length : float
            m.
        delta_rotvec : array-like, shape (3,)
            Bend, rad, in the parent link frame.
        """
        delta_rotvec = [float(v) for v in np.asarray(delta_rotvec, dtype=float).reshape(-1)]
        self._add_fault(Fault("deform_limb", joint_or_link=str(joint_name), delta_length=float(delta_length),
                              delta_rotvec=delta_rotvec))

    def displace_marker(self, marker_id, delta):
        """Move a marker on its link (a shifted marker, or a tool displaced in the gripper).

        Parameters
        ----------
        marker_id : int
        delta : array-like, shape (4, 4)
            ``old_marker2new_marker``: the displacement in the marker's own frame.
        """
        delta = check_transform(np.array(delta, dtype=float), name="delta")
        if delta.shape != (4, 4):
            raise InvalidInputError(f"delta must have shape (4, 4), got {delta.shape}")
        self._add_fault(Fault("displace_marker", marker_id=int(marker_id), delta=delta))

    def repair(self, kind=None):
        """Undo all faults (``kind=None``) or all faults of one kind; the rest stay in effect."""
        if kind is not None and kind not in FAULT_KINDS:
            raise InvalidInputError(f"repair kind must be None or one of {FAULT_KINDS}, got {kind!r}")
        self._rebuild([f for f in self._faults if kind is not None and f.kind != kind])

    def _add_fault(self, fault):
        self._rebuild(self._faults + [fault])

    def _rebuild(self, faults):
        body = self._nominal
        for fault in faults:
            body = fault.apply(body, self._nominal)  # raises before anything changes if a fault is invalid
        old_joints = self._body.tree.joints
        self._body, self._faults = body, faults
        if any(a.origin.tobytes() != b.origin.tobytes() for a, b in zip(old_joints, body.tree.joints, strict=True)):
            self._pb.removeBody(self._robot_id)
            self._robot_id = self._load_robot(body.tree)
            self._index_links(body.tree)
        self._set_configuration(body.execute(self._command))

    # ------------------------------------------------------------------ lifetime
    def close(self):
        """Disconnect the pybullet client and delete the temporary files (idempotent)."""
        if self._pb is not None:
            self._pb.disconnect()
            self._pb = None
        self._tmp.cleanup()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.close()

    def __repr__(self):
        return f"<SimWorld {self._nominal.tree!r} faults={self._faults}>"

