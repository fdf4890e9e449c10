"""Kinematic trees: the robot's specification, its forward kinematics, URDF and marker placement files.

This module is the one place that knows a robot's true geometry. Everything that needs "the engineered model"
(the engineered local models, the synthetic robots and faults, the simulator, the benchmarks) computes forward
kinematics here.

Conventions
-----------
- Frames follow :mod:`body_scheme_core.transforms`: ``A2B`` is the pose of ``B`` in ``A``, composed left to right.
- A joint follows URDF: ``parent_link2child_link = origin @ motion(q)`` where ``origin`` is the pose of the joint
  frame in the parent link and ``motion(q)`` is a rotation by ``q`` (rad) about ``axis`` (revolute, continuous) or a
  translation by ``q`` (m) along ``axis`` (prismatic), both in the joint frame. The child link's frame *is* the
  joint frame.
- Each movable joint is commanded by at most one action: ``joint.action = k`` means ``a[k]`` is its target position.
  Action indices of a tree are exactly ``0 .. m-1``. A movable joint without an action is passive and stays at 0.
- A marker is rigidly attached to one link at ``link2marker``; its id is the body-part id of the paper (``X_i``).
- Roll-pitch-yaw (``rpy``) is URDF's: fixed axes x, then y, then z (``Rotation.from_euler("xyz", rpy)``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
import xml.etree.ElementTree as ET
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import InvalidInputError
from .models.base import check_action_batch
from .transforms import check_transform, invert_transform

__all__ = [
    "JOINT_TYPES",
    "MOVABLE_JOINT_TYPES",
    "Joint",
    "Marker",
    "KinematicTree",
    "transform_from_xyz_rpy",
    "xyz_rpy_from_transform",
    "load_markers_yaml",
    "markers_to_yaml",
]

#: Joint types a :class:`KinematicTree` supports (URDF names).
JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")
#: Joint types that move with their action.
MOVABLE_JOINT_TYPES = ("revolute", "continuous", "prismatic")
#: Position range given to continuous joints (and revolute joints whose URDF limits are unset), rad.
CONTINUOUS_RANGE = (-math.pi, math.pi)
#: Largest accepted deviation of a joint axis norm from 1.
AXIS_NORM_TOLERANCE = 1e-6


def transform_from_xyz_rpy(xyz, rpy):
    """Transform from a translation and URDF roll-pitch-yaw (fixed axes x, y, z).

    Parameters
    ----------
    xyz : array-like, shape (3,)
    rpy : array-like, shape (3,)

    Returns
    -------
    A2B : ndarray, shape (4, 4)
    """
    xyz = np.asarray(xyz, dtype=float)
    rpy = np.asarray(rpy, dtype=float)
    if xyz.shape != (3,) or rpy.shape != (3,):
        raise InvalidInputError(f"xyz and rpy must have shape (3,), got {xyz.shape} and {rpy.shape}")
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(rpy))):
        raise InvalidInputError("xyz or rpy contains NaN or inf")
    A2B = np.eye(4)
    A2B[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    A2B[:3, 3] = xyz
    return A2B


def xyz_rpy_from_transform(A2B):
    """Translation and URDF roll-pitch-yaw of a transform (inverse of :func:`transform_from_xyz_rpy`).

    Parameters
    ----------
    A2B : array-like, shape (4, 4)

    Returns
    -------
    xyz, rpy : ndarray, shape (3,)
    """
    A2B = check_transform(A2B)
    with warnings.catch_warnings():
        # At pitch = +-pi/2 scipy warns and sets one angle to zero; the angles still represent the same rotation.
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(A2B[:3, :3]).as_euler("xyz")
    return A2B[:3, 3].copy(), rpy


def _frozen_array(value, shape, name):
    array = np.array(value, dtype=float)
    if array.shape != shape:
        raise InvalidInputError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class Joint:
    """One joint of a kinematic tree (URDF semantics).

    Attributes
    ----------
    name : str
    type : str
        One of :data:`JOINT_TYPES`.
    parent, child : str
        Link names.
    origin : ndarray, shape (4, 4)
        ``parent_link2joint_frame`` at zero position (read-only).
    axis : ndarray, shape (3,)
        Unit axis of rotation or translation in the joint frame (read-only).
    lower, upper : float
        Position limits (rad or m); actions are drawn and clipped within them.
    action : int or None
        Index into the action vector that commands the joint; ``None`` for fixed and passive joints.
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    axis: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    lower: float = CONTINUOUS_RANGE[0]
    upper: float = CONTINUOUS_RANGE[1]
    action: int | None = None

    def __post_init__(self):
        if self.type not in JOINT_TYPES:
            raise InvalidInputError(f"joint {self.name!r}: type must be one of {JOINT_TYPES}, got {self.type!r}")
        for field in ("name", "parent", "child"):
            if not isinstance(getattr(self, field), str) or not getattr(self, field):
                raise InvalidInputError(f"joint {field} must be a non-empty string, got {getattr(self, field)!r}")
        if self.parent == self.child:
            raise InvalidInputError(f"joint {self.name!r} connects link {self.parent!r} to itself")
        origin = _frozen_array(self.origin, (4, 4), f"joint {self.name!r} origin")
        check_transform(origin, name=f"joint {self.name!r} origin")
        axis = _frozen_array(self.axis, (3,), f"joint {self.name!r} axis")
        if abs(np.linalg.norm(axis) - 1.0) > AXIS_NORM_TOLERANCE:
            raise InvalidInputError(f"joint {self.name!r} axis must be a unit vector, got {axis.tolist()}")
        lower, upper = float(self.lower), float(self.upper)
        if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
            raise InvalidInputError(f"joint {self.name!r} needs finite limits lower <= upper, got {lower}, {upper}")
        action = self.action
        if action is not None:
            if isinstance(action, bool) or int(action) != action or int(action) < 0:
                raise InvalidInputError(f"joint {self.name!r} action must be an integer >= 0, got {action!r}")
            action = int(action)
            if self.type == "fixed":
                raise InvalidInputError(f"fixed joint {self.name!r} cannot be commanded by action {action}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "axis", axis)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "action", action)

    @property
    def is_movable(self):
        """Whether the joint has a degree of freedom (it may still be passive, ``action is None``)."""
        return self.type in MOVABLE_JOINT_TYPES

    def motion(self, q):
        """``joint_frame2child_link`` for joint position(s) ``q``.

        Parameters
        ----------
        q : float or array-like, shape (n,)

        Returns
        -------
        T : ndarray, shape (4, 4) or (n, 4, 4)
        """
        q = np.asarray(q, dtype=float)
        flat = np.atleast_1d(q)
        T = np.tile(np.eye(4), (flat.shape[0], 1, 1))
        if self.type in ("revolute", "continuous"):
            T[:, :3, :3] = Rotation.from_rotvec(flat[:, None] * self.axis[None, :]).as_matrix()
        elif self.type == "prismatic":
            T[:, :3, 3] = flat[:, None] * self.axis[None, :]
        return T[0] if q.ndim == 0 else T

    def transform(self, q):
        """``parent_link2child_link = origin @ motion(q)``, shape (4, 4) or (n, 4, 4)."""
        return self.origin @ self.motion(q)

    def to_dict(self):
        """JSON-serialisable dict."""
        return {"name": self.name, "type": self.type, "parent": self.parent, "child": self.child,
                "origin": self.origin.tolist(), "axis": self.axis.tolist(), "lower": self.lower,
                "upper": self.upper, "action": self.action}

    @classmethod
    def from_dict(cls, data):
        """Inverse of :meth:`to_dict`."""
        return cls(**data)


@dataclass(frozen=True, eq=False)
class Marker:
    """A visual marker rigidly attached to a link: one observable body part.

    Attributes
    ----------
    id : int
        Marker id = body-part id.
    link : str
        Link it is attached to.
    link2marker : ndarray, shape (4, 4)
        Pose of the marker in the link frame (read-only). The marker's z axis is its outward normal.
    size : float
        Edge length of the square marker, m.
    """

    id: int
    link: str
    link2marker: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    size: float = 0.05

    def __post_init__(self):
        if isinstance(self.id, bool) or not isinstance(self.id, (int, np.integer)) or int(self.id) < 0:
            raise InvalidInputError(f"marker id must be an integer >= 0, got {self.id!r}")
        if not isinstance(self.link, str) or not self.link:
            raise InvalidInputError(f"marker {self.id} link must be a non-empty string, got {self.link!r}")
        link2marker = np.array(check_transform(self.link2marker, name=f"marker {self.id} link2marker"))
        link2marker.flags.writeable = False
        size = float(self.size)
        if not (math.isfinite(size) and size > 0):
            raise InvalidInputError(f"marker {self.id} size must be a finite number > 0, got {self.size!r}")
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "link2marker", link2marker)
        object.__setattr__(self, "size", size)

    def to_dict(self):
        """Marker file entry ``{id, link, xyz, rpy, size}`` (plain floats)."""
        xyz, rpy = xyz_rpy_from_transform(self.link2marker)
        return {"id": self.id, "link": self.link, "xyz": [float(v) for v in xyz], "rpy": [float(v) for v in rpy],
                "size": self.size}

    @classmethod
    def from_dict(cls, data):
        """Build from a marker file entry ``{id, link, xyz, rpy, size}`` (``xyz``, ``rpy``, ``size`` optional)."""
        if not isinstance(data, dict):
            raise InvalidInputError(f"a marker entry must be a mapping, got {data!r}")
        unknown = sorted(set(data) - {"id", "link", "xyz", "rpy", "size"})
        if unknown or "id" not in data or "link" not in data:
            raise InvalidInputError(f"a marker entry needs keys id, link and may have xyz, rpy, size; got {data!r}")
        link2marker = transform_from_xyz_rpy(data.get("xyz", [0.0, 0.0, 0.0]), data.get("rpy", [0.0, 0.0, 0.0]))
        return cls(id=data["id"], link=data["link"], link2marker=link2marker, size=data.get("size", 0.05))


class KinematicTree:
    """A robot's specification: a tree of links connected by joints, with markers on the links.

    Parameters
    ----------
    joints : iterable of Joint
    markers : iterable of Marker
    root_link : str or None
        Name of the root link (the robot's trunk). ``None``: the unique link that is no joint's child. Required
        when there are no joints.

    Raises
    ------
    InvalidInputError
        If the joints do not form one tree (a link with two parents, a cycle, several roots), joint names or
        marker ids repeat, a marker sits on an unknown link, or the action indices are not exactly ``0 .. m-1``.
    """

    def __init__(self, joints, markers=(), root_link=None):
        joints = tuple(joints)
        markers = tuple(markers)
        for joint in joints:
            if not isinstance(joint, Joint):
                raise InvalidInputError(f"joints must be Joint instances, got {type(joint).__name__}")
        for marker in markers:
            if not isinstance(marker, Marker):
                raise InvalidInputError(f"markers must be Marker instances, got {type(marker).__name__}")
        names = [j.name for j in joints]
        if len(set(names)) != len(names):
            raise InvalidInputError(f"joint names must be unique, got {names}")
        parent_joint = {}
        for joint in joints:
            if joint.child in parent_joint:
                raise InvalidInputError(
                    f"link {joint.child!r} has two parents (joints {parent_joint[joint.child].name!r} and "
                    f"{joint.name!r}); a kinematic tree allows one")
            parent_joint[joint.child] = joint
        links = {j.parent for j in joints} | {j.child for j in joints}
        roots = sorted(links - set(parent_joint))
        if joints:
            if len(roots) != 1:
                raise InvalidInputError(
                    f"the joints must form one tree with one root link, found roots {roots} (cycle or forest)")
            if root_link is not None and root_link != roots[0]:
                raise InvalidInputError(f"root_link {root_link!r} is not the tree's root {roots[0]!r}")
            root_link = roots[0]
        else:
            marker_links = sorted({m.link for m in markers})
            if root_link is None:
                if len(marker_links) != 1:
                    raise InvalidInputError("a tree without joints needs root_link (or markers on exactly one link)")
                root_link = marker_links[0]
            links = {root_link}
        children = {link: [] for link in links}
        for joint in joints:
            children[joint.parent].append(joint)
        # Breadth-first order from the root: every joint comes after the joint of its parent link, so forward
        # kinematics is one pass. Links unreachable from the root would mean a cycle.
        order, link_order, queue = [], [root_link], deque([root_link])
        while queue:
            link = queue.popleft()
            for joint in children[link]:
                order.append(joint)
                link_order.append(joint.child)
                queue.append(joint.child)
        if len(link_order) != len(links):
            unreachable = sorted(links - set(link_order))
            raise InvalidInputError(f"links {unreachable} are not reachable from root {root_link!r} (cycle)")
        ids = [m.id for m in markers]
        if len(set(ids)) != len(ids):
            raise InvalidInputError(f"marker ids must be unique, got {ids}")
        for marker in markers:
            if marker.link not in links:
                raise InvalidInputError(
                    f"marker {marker.id} is on unknown link {marker.link!r}; links: {sorted(links)}")
        actions = sorted(j.action for j in joints if j.action is not None)
        if actions != list(range(len(actions))):
            raise InvalidInputError(f"action indices must be exactly 0..m-1 without repeats, got {actions}")

        self.joints = joints
        self.markers = tuple(sorted(markers, key=lambda m: m.id))
        self.root_link = root_link
        self.links = tuple(link_order)
        self._order = tuple(order)
        self._parent_joint = parent_joint
        self._joint_by_name = {j.name: j for j in joints}
        self._marker_by_id = {m.id: m for m in self.markers}
        self._action_joint = {j.action: j for j in joints if j.action is not None}
        depth = {root_link: 0}
        for joint in order:
            depth[joint.child] = depth[joint.parent] + 1
        self._depth = depth

    # ------------------------------------------------------------------ accessors
    @property
    def n_actions(self):
        """m: length of the action vector."""
        return len(self._action_joint)

    @property
    def action_lower(self):
        """Lower limits of the actions, shape (m,)."""
        return np.array([self._action_joint[k].lower for k in range(self.n_actions)])

    @property
    def action_upper(self):
        """Upper limits of the actions, shape (m,)."""
        return np.array([self._action_joint[k].upper for k in range(self.n_actions)])

    @property
    def action_joint_names(self):
        """Name of the joint each action commands, tuple of length m."""
        return tuple(self._action_joint[k].name for k in range(self.n_actions))

    @property
    def marker_ids(self):
        """Marker ids in ascending order."""
        return tuple(m.id for m in self.markers)

    def joint(self, name):
        """The joint called ``name``."""
        try:
            return self._joint_by_name[name]
        except KeyError:
            raise InvalidInputError(f"unknown joint {name!r}; joints: {sorted(self._joint_by_name)}") from None

    def marker(self, marker_id):
        """The marker with id ``marker_id``."""
        try:
            return self._marker_by_id[int(marker_id)]
        except (KeyError, TypeError, ValueError):
            raise InvalidInputError(f"unknown marker id {marker_id!r}; markers: {list(self.marker_ids)}") from None

    def parent_joint(self, link):
        """The joint whose child is ``link`` (``None`` for the root link)."""
        if link not in self._depth:
            raise InvalidInputError(f"unknown link {link!r}; links: {list(self.links)}")
        return self._parent_joint.get(link)

    def action_joint(self, action_index):
        """The joint commanded by action ``action_index``."""
        try:
            return self._action_joint[int(action_index)]
        except (KeyError, TypeError, ValueError):
            raise InvalidInputError(
                f"unknown action index {action_index!r}; the tree has actions 0..{self.n_actions - 1}") from None

    def copy(self):
        """An independent copy (joints and markers are immutable, so they are shared)."""
        return KinematicTree(self.joints, self.markers, self.root_link)

    def replace_joint(self, name, **changes):
        """A new tree with joint ``name`` changed (``dataclasses.replace`` fields, e.g. ``origin=...``)."""
        joint = self.joint(name)
        joints = [dataclasses.replace(joint, **changes) if j is joint else j for j in self.joints]
        return KinematicTree(joints, self.markers, self.root_link)

    def replace_marker(self, marker_id, **changes):
        """A new tree with marker ``marker_id`` changed (e.g. ``link2marker=...``)."""
        marker = self.marker(marker_id)
        markers = [dataclasses.replace(marker, **changes) if m is marker else m for m in self.markers]
        return KinematicTree(self.joints, markers, self.root_link)

    # ------------------------------------------------------------------ forward kinematics
    def link_poses(self, a):
        """Poses of all links in the root link frame.

        Parameters
        ----------
        a : array-like, shape (m,) or (n, m)
            Joint positions, indexed like the actions.

        Returns
        -------
        poses : dict of str to ndarray, shape (4, 4) or (n, 4, 4)
            ``root2link`` per link name.
        """
        a = np.asarray(a, dtype=float)
        single = a.ndim == 1
        A = check_action_batch(a, self.n_actions, name="a")
        n = A.shape[0]
        poses = {self.root_link: np.tile(np.eye(4), (n, 1, 1))}
        for joint in self._order:
            if joint.action is None:
                parent2child = joint.origin  # fixed or passive joint: zero position
            else:
                parent2child = joint.transform(A[:, joint.action])
            poses[joint.child] = poses[joint.parent] @ parent2child
        if single:
            return {link: T[0] for link, T in poses.items()}
        return poses

    def marker_poses(self, a):
        """Poses of all markers in the root link frame.

        Parameters
        ----------
        a : array-like, shape (m,) or (n, m)

        Returns
        -------
        poses : dict of int to ndarray, shape (4, 4) or (n, 4, 4)
            ``root2marker`` per marker id.
        """
        links = self.link_poses(a)
        return {m.id: links[m.link] @ m.link2marker for m in self.markers}

    def relative_transform(self, id_i, id_j, a):
        """``marker_i2marker_j`` (the paper's noise-free ``Delta_ij``), shape (4, 4) or (n, 4, 4)."""
        marker_i, marker_j = self.marker(id_i), self.marker(id_j)
        links = self.link_poses(a)
        root2i = links[marker_i.link] @ marker_i.link2marker
        root2j = links[marker_j.link] @ marker_j.link2marker
        return invert_transform(root2i) @ root2j

    # ------------------------------------------------------------------ structure
    def link_path(self, link_i, link_j):
        """Joints on the tree path between two links.

        Returns
        -------
        up : list of Joint
            Joints traversed from ``link_i`` up to the lowest common ancestor, child to parent.
        down : list of Joint
            Joints traversed from the lowest common ancestor down to ``link_j``, parent to child.
        """
        for link in (link_i, link_j):
            if link not in self._depth:
                raise InvalidInputError(f"unknown link {link!r}; links: {list(self.links)}")
        up, down = [], []
        while link_i != link_j:
            if self._depth[link_i] >= self._depth[link_j]:
                joint = self._parent_joint[link_i]
                up.append(joint)
                link_i = joint.parent
            else:
                joint = self._parent_joint[link_j]
                down.append(joint)
                link_j = joint.parent
        return up, down[::-1]

    def path_actions(self, id_i, id_j):
        """Sorted action indices of the commanded joints between the links of markers ``id_i`` and ``id_j``."""
        up, down = self.link_path(self.marker(id_i).link, self.marker(id_j).link)
        return tuple(sorted(j.action for j in up + down if j.action is not None))

    @property
    def root_marker(self):
        """Root of :meth:`marker_tree_edges`: the marker closest to the root link (lowest id on ties)."""
        if not self.markers:
            raise InvalidInputError("the tree has no markers")
        return min(self.markers, key=lambda m: (self._depth[m.link], m.id)).id

    def marker_tree_edges(self):
        """The true body-scheme structure: the link tree contracted onto the markers.

        Definition: on each link, the marker with the lowest id represents the link; the link's other markers
        are its children. A link's representative is the child of the representative of the nearest ancestor link
        that carries markers. Representatives without such an ancestor (no marker on the path to the root) become
        children of :attr:`root_marker`. The result is a spanning tree over all markers, each edge oriented away
        from the root.

        Returns
        -------
        edges : list of (int, int)
            ``(parent marker, child marker)``, ordered by the child's link depth, then child id, so every parent
            appears as a child (or is the root marker) before its own children; ``n - 1`` edges.
        """
        if not self.markers:
            return []
        by_link = {}
        for marker in self.markers:  # sorted by id
            by_link.setdefault(marker.link, []).append(marker.id)
        root = self.root_marker
        edges = []
        for marker in sorted(self.markers, key=lambda m: (self._depth[m.link], m.id)):
            if marker.id == root:
                continue
            on_link = by_link[marker.link]
            if marker.id != on_link[0]:
                edges.append((on_link[0], marker.id))
                continue
            link, parent = marker.link, root
            while link != self.root_link:
                link = self._parent_joint[link].parent
                if link in by_link:
                    parent = by_link[link][0]
                    break
            edges.append((parent, marker.id))
        return edges

    # ------------------------------------------------------------------ URDF
    @classmethod
    def from_urdf(cls, xml_string, markers=(), joint_actions=None):
        """Build a tree from URDF text.

        Parameters
        ----------
        xml_string : str or bytes
            URDF document.
        markers : iterable of Marker
        joint_actions : dict of str to int or None
            Action index per joint name. ``None``: movable joints get indices 0, 1, ... in URDF order. Movable
            joints missing from a given mapping are passive (held at 0).

        Returns
        -------
        tree : KinematicTree

        Notes
        -----
        Continuous joints, and revolute joints whose URDF ``lower > upper`` (pybullet's "unlimited"), get the range
        :data:`CONTINUOUS_RANGE` unless a limit with ``lower < upper`` is given.
        """
        from urdf_parser_py.urdf import URDF

        if isinstance(xml_string, bytes):
            xml_string = xml_string.decode("utf-8")
        try:
            robot = URDF.from_xml_string(xml_string)
        except Exception as exc:  # urdf_parser_py raises assorted types (AssertionError, ValueError, ...)
            raise InvalidInputError(f"cannot parse URDF: {type(exc).__name__}: {exc}") from exc
        movable = [j for j in robot.joints if j.type in MOVABLE_JOINT_TYPES]
        if joint_actions is None:
            joint_actions = {j.name: k for k, j in enumerate(movable)}
        else:
            joint_actions = dict(joint_actions)
            unknown = sorted(set(joint_actions) - {j.name for j in movable})
            if unknown:
                raise InvalidInputError(
                    f"joint_actions names {unknown} are not movable joints of the URDF; movable: "
                    f"{[j.name for j in movable]}")
        joints = []
        for j in robot.joints:
            if j.type not in JOINT_TYPES:
                raise InvalidInputError(
                    f"URDF joint {j.name!r} has type {j.type!r}; supported types are {JOINT_TYPES}")
            if j.mimic is not None:
                raise InvalidInputError(f"URDF joint {j.name!r} is a mimic joint; mimic joints are not supported")
            origin = np.eye(4)
            if j.origin is not None:
                origin = transform_from_xyz_rpy(j.origin.xyz or [0.0, 0.0, 0.0], j.origin.rpy or [0.0, 0.0, 0.0])
            axis = np.array(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=float)
            norm = np.linalg.norm(axis)
            if j.type != "fixed" and not norm > 1e-9:
                raise InvalidInputError(f"URDF joint {j.name!r} has a zero axis")
            axis = axis / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
            lower, upper = CONTINUOUS_RANGE
            if j.limit is not None and j.type in MOVABLE_JOINT_TYPES:
                lo = j.limit.lower if j.limit.lower is not None else 0.0
                hi = j.limit.upper if j.limit.upper is not None else 0.0
                if lo < hi or (lo == hi and j.type != "continuous"):
                    lower, upper = lo, hi
                elif j.type == "prismatic":
                    raise InvalidInputError(f"URDF prismatic joint {j.name!r} has limits lower {lo} > upper {hi}")
            elif j.type == "prismatic":
                raise InvalidInputError(f"URDF prismatic joint {j.name!r} needs a <limit>")
            joints.append(Joint(name=j.name, type=j.type, parent=j.parent, child=j.child, origin=origin, axis=axis,
                                lower=lower, upper=upper,
                                action=joint_actions.get(j.name) if j.type != "fixed" else None))
        link_names = {link.name for link in robot.links}
        tree = cls(joints, markers, root_link=None if joints else (sorted(link_names)[0] if link_names else None))
        return tree

    def to_urdf(self, name="robot"):
        """URDF text of the tree, loadable by pybullet.

        Each link gets a small box at its origin and a cylinder "bone" to each child joint, as both visual and
        collision geometry, and a unit-ish inertial. Markers are not part of the URDF (see
        :func:`markers_to_yaml`). Joints are written with the commanded ones first, in action order, so that
        ``from_urdf(to_urdf())`` reproduces the action indices when every movable joint has an action.

        Parameters
        ----------
        name : str
            Robot name.

        Returns
        -------
        xml : str
        """
        robot = ET.Element("robot", name=name)
        material = ET.SubElement(robot, "material", name="body_scheme_grey")
        ET.SubElement(material, "color", rgba="0.6 0.6 0.6 1")
        children = {link: [] for link in self.links}
        for joint in self.joints:
            children[joint.parent].append(joint)
        for link in self.links:
            element = ET.SubElement(robot, "link", name=link)
            inertial = ET.SubElement(element, "inertial")
            ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
            ET.SubElement(inertial, "mass", value="0.5")
            ET.SubElement(inertial, "inertia", ixx="0.001", ixy="0", ixz="0", iyy="0.001", iyz="0", izz="0.001")
            shapes = [(np.eye(4), ("box", {"size": "0.04 0.04 0.04"}))]
            for joint in children[link]:
                bone = _bone_geometry(joint.origin[:3, 3])
                if bone is not None:
                    shapes.append(bone)
            for tag in ("visual", "collision"):
                for pose, (kind, attributes) in shapes:
                    shape = ET.SubElement(element, tag)
                    ET.SubElement(shape, "origin", **_xyz_rpy_attributes(pose))
                    geometry = ET.SubElement(shape, "geometry")
                    ET.SubElement(geometry, kind, **attributes)
                    if tag == "visual":
                        ET.SubElement(shape, "material", name="body_scheme_grey")
        commanded = sorted((j for j in self.joints if j.action is not None), key=lambda j: j.action)
        for joint in commanded + [j for j in self.joints if j.action is None]:
            element = ET.SubElement(robot, "joint", name=joint.name, type=joint.type)
            ET.SubElement(element, "parent", link=joint.parent)
            ET.SubElement(element, "child", link=joint.child)
            ET.SubElement(element, "origin", **_xyz_rpy_attributes(joint.origin))
            if joint.is_movable:
                ET.SubElement(element, "axis", xyz=_format_floats(joint.axis))
                ET.SubElement(element, "limit", lower=repr(joint.lower), upper=repr(joint.upper), effort="100",
                              velocity="2")
        ET.indent(robot)
        return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"

    def __repr__(self):
        return (f"<KinematicTree root={self.root_link!r} links={len(self.links)} joints={len(self.joints)} "
                f"actions={self.n_actions} markers={list(self.marker_ids)}>")


def _format_floats(values):
    # repr gives the shortest string that parses back to the same float, so URDF round trips are exact.
    return " ".join(repr(float(v)) for v in values)


def _xyz_rpy_attributes(A2B):
    xyz, rpy = xyz_rpy_from_transform(A2B)
    return {"xyz": _format_floats(xyz), "rpy": _format_floats(rpy)}


def _bone_geometry(offset, radius=0.015):
    """Cylinder from a link origin to ``offset``: (link2cylinder, (tag, attributes)) or None if too short."""
    length = float(np.linalg.norm(offset))
    if length < 1e-3:
        return None
    pose = np.eye(4)
    # The cylinder's axis is its z axis; rotate z onto the bone direction.
    rotation, _ = Rotation.align_vectors([offset / length], [[0.0, 0.0, 1.0]])
    pose[:3, :3] = rotation.as_matrix()
    pose[:3, 3] = 0.5 * np.asarray(offset, dtype=float)
    return pose, ("cylinder", {"radius": repr(radius), "length": repr(length)})


# ---------------------------------------------------------------------- marker placement files
def load_markers_yaml(text_or_path):
    """Read markers from a placement file.

    The file is YAML: either a list of entries or a mapping with key ``markers`` holding that list. Each entry is
    ``{id: int, link: str, xyz: [x, y, z], rpy: [roll, pitch, yaw], size: float}`` with ``xyz`` in m, ``rpy`` in rad
    (URDF convention), ``size`` the marker's edge length in m; ``xyz``, ``rpy`` and ``size`` are optional (zero
    pose, 0.05 m).

    Parameters
    ----------
    text_or_path : str or os.PathLike
        YAML text, or the path of a file holding it.

    Returns
    -------
    markers : list of Marker
    """
    import yaml

    if isinstance(text_or_path, os.PathLike) or (
            isinstance(text_or_path, str) and "\n" not in text_or_path and os.path.isfile(text_or_path)):
        with open(text_or_path, encoding="utf-8") as stream:
            text = stream.read()
    else:
        text = text_or_path
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InvalidInputError(f"marker file is not valid YAML: {exc}") from exc
    if isinstance(data, dict):
        if set(data) != {"markers"}:
            raise InvalidInputError(f"marker file mapping must have the single key 'markers', got {sorted(data)}")
        data = data["markers"]
    if data is None:
        data = []
    if not isinstance(data, list):
        raise InvalidInputError(f"marker file must hold a list of marker entries, got {type(data).__name__}")
    markers = [Marker.from_dict(entry) for entry in data]
    ids = [m.id for m in markers]
    if len(set(ids)) != len(ids):
        raise InvalidInputError(f"marker ids in the file must be unique, got {ids}")
    return markers


def markers_to_yaml(markers):
    """YAML text of a marker placement file (see :func:`load_markers_yaml`), entries sorted by id."""
    import yaml

    entries = [m.to_dict() for m in sorted(markers, key=lambda m: m.id)]
    return yaml.safe_dump({"markers": entries}, sort_keys=False, default_flow_style=None)
