"""Kinematic trees: the robot's specification and its forward kinematics (URDF and marker files: robot_files).

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
- A mimic joint (URDF ``<mimic>``, e.g. a gripper's second finger) follows the joint it mimics: it shares that joint's
  action ``k`` and sits at ``multiplier * a[k] + offset``. It adds no action of its own.
- A marker is rigidly attached to one link at ``link2marker``; its id is the body-part id of the paper (``X_i``).
- Roll-pitch-yaw (``rpy``) is URDF's: fixed axes x, then y, then z (``Rotation.from_euler("xyz", rpy)``).
"""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np

from ..errors import InvalidInputError
from ..models import check_action_batch
from ..transforms import invert_transform
from .joints import Joint, Marker

__all__ = ["KinematicTree"]


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
        actions = sorted(j.action for j in joints if j.action is not None and j.mimic is None)
        if actions != list(range(len(actions))):
            raise InvalidInputError(f"action indices must be exactly 0..m-1 without repeats, got {actions}")
        by_name = {j.name: j for j in joints}
        for joint in joints:
            if joint.mimic is None:
                continue
            followed = by_name.get(joint.mimic)
            if followed is None or followed.mimic is not None or followed.action != joint.action:
                raise InvalidInputError(
                    f"mimic joint {joint.name!r} must follow a joint of the tree that is not a mimic joint itself, "
                    f"with its action; got {joint.mimic!r} (action {joint.action})")

        self.joints = joints
        self.markers = tuple(sorted(markers, key=lambda m: m.id))
        self.root_link = root_link
        self.links = tuple(link_order)
        self._order = tuple(order)
        self._parent_joint = parent_joint
        self._joint_by_name = {j.name: j for j in joints}
        self._marker_by_id = {m.id: m for m in self.markers}
        self._action_joint = {j.action: j for j in joints if j.action is not None and j.mimic is None}
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
                parent2child = joint.transform(joint.position(A))
            poses[joint.child] = poses[joint.parent] @ parent2child
        if single:
            return {link: T[0] for link, T in poses.items()}
        return poses

    def joint_positions(self, a):
        """Position of every movable joint for actions ``a`` (m,): ``{name: float}``, mimic joints included."""
        A = check_action_batch(np.asarray(a, dtype=float), self.n_actions, name="a")
        return {j.name: float(j.position(A)[0]) for j in self.joints if j.is_movable}

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
        return tuple(sorted({j.action for j in up + down if j.action is not None}))  # a mimic shares its action

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

    # ------------------------------------------------------------------ URDF (body_scheme_core.world.robot_files)
    @classmethod
    def from_urdf(cls, xml_string, markers=(), joint_actions=None):
        """Build a tree from URDF text; see :func:`body_scheme_core.world.robot_files.tree_from_urdf`."""
        from .robot_files import tree_from_urdf

        return tree_from_urdf(xml_string, markers, joint_actions)

    def to_urdf(self, name="robot"):
        """URDF text of the tree, loadable by pybullet; see :func:`body_scheme_core.world.robot_files.tree_to_urdf`."""
        from .robot_files import tree_to_urdf

        return tree_to_urdf(self, name)

    def __repr__(self):
        return (f"<KinematicTree root={self.root_link!r} links={len(self.links)} joints={len(self.joints)} "
                f"actions={self.n_actions} markers={list(self.marker_ids)}>")
