"""The true body: actions to executed joint positions and true marker poses, and the faults that change it.

Faults never modify a tree or body in place: each returns a changed copy, and the learner only ever sees them
through observations.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..models import check_action_batch
from ..transforms import check_transform
from .tree import KinematicTree

__all__ = ["Body", "block_joint", "deform_limb", "displace_marker"]


class Body:
    """The physical robot: its true geometry and the mapping from commanded actions to executed joint positions.

    Parameters
    ----------
    tree : KinematicTree
        True geometry (possibly deformed).
    blocked : dict of int to float or None
        ``{action index: angle}`` of joints that ignore their command and stay at ``angle``.
    gears : dict of int to (float, float) or None
        ``{action index: (amplitude, frequency)}`` of joints driven through a nonlinear transmission: the joint moves
        to ``amplitude sin(frequency a)`` for the (clipped) command ``a``, a relation no rigid joint model explains.
    """

    def __init__(self, tree, blocked=None, gears=None):
        if not isinstance(tree, KinematicTree):
            raise InvalidInputError(f"tree must be a KinematicTree, got {type(tree).__name__}")
        self.tree = tree
        self.blocked = {}
        for action, angle in (blocked or {}).items():
            joint = tree.action_joint(action)
            angle = float(angle)
            if not (joint.lower <= angle <= joint.upper):
                raise InvalidInputError(
                    f"blocked angle {angle} of action {action} is outside [{joint.lower}, {joint.upper}]")
            self.blocked[int(action)] = angle
        self.gears = {}
        for action, (amplitude, frequency) in (gears or {}).items():
            joint = tree.action_joint(action)
            if not (math.isfinite(amplitude) and math.isfinite(frequency)) or not (
                    joint.lower <= -abs(amplitude) and abs(amplitude) <= joint.upper):
                raise InvalidInputError(f"gear ({amplitude}, {frequency}) of action {action} must be finite and "
                                        f"keep the joint in [{joint.lower}, {joint.upper}]")
            self.gears[int(action)] = (float(amplitude), float(frequency))

    @classmethod
    def wrap(cls, body_or_tree):
        """``body_or_tree`` as a :class:`Body` (a tree becomes an unblocked body)."""
        if isinstance(body_or_tree, Body):
            return body_or_tree
        return cls(body_or_tree)

    def copy(self):
        """An independent copy."""
        return Body(self.tree.copy(), dict(self.blocked), dict(self.gears))

    def execute(self, a):
        """Executed joint positions for commanded actions: clipped to the joint limits, through the gears, blocked
        joints held.

        Parameters
        ----------
        a : array-like, shape (m,) or (n, m)

        Returns
        -------
        q : ndarray, same shape as ``a``
        """
        a = np.asarray(a, dtype=float)
        q = np.clip(check_action_batch(a, self.tree.n_actions), self.tree.action_lower, self.tree.action_upper)
        for action, (amplitude, frequency) in self.gears.items():
            q[:, action] = amplitude * np.sin(frequency * q[:, action])
        for action, angle in self.blocked.items():
            q[:, action] = angle
        return q[0] if a.ndim == 1 else q

    def true_marker_poses(self, a):
        """True ``root2marker`` per marker id for commanded actions ``a`` (m,) or (n, m): (4, 4) or (n, 4, 4)."""
        return self.tree.marker_poses(self.execute(a))

    def true_marker_array(self, A):
        """True ``root2marker`` for commanded actions ``A`` (n, m), shape (n, n_markers, 4, 4) in id order."""
        poses = self.true_marker_poses(check_action_batch(A, self.tree.n_actions))
        return np.stack([poses[i] for i in self.tree.marker_ids], axis=1)

    def __repr__(self):
        return f"<Body {self.tree!r} blocked={self.blocked} gears={self.gears}>"


def block_joint(body, action_index, angle):
    """A copy of ``body`` whose joint commanded by ``action_index`` is stuck at ``angle`` (rad or m)."""
    body = Body.wrap(body)
    blocked = dict(body.blocked)
    blocked[int(action_index)] = angle
    return Body(body.tree, blocked, body.gears)


def deform_limb(body, joint_or_link, delta_length=0.0, delta_rotvec=(0.0, 0.0, 0.0)):
    """A copy of ``body`` with a bent and/or stretched limb.

    The limb of joint ``J`` is the segment from the origin of ``J``'s parent link to ``J``'s frame. Deforming it
    lengthens the segment by ``delta_length`` along its direction and then rotates it (and everything beyond
    ``J``) by ``delta_rotvec`` about the parent link's origin, in the parent link frame:
    ``origin' = rot(delta_rotvec) @ stretch(origin)``. A link name ``L`` deforms link ``L`` itself: every joint
    whose parent is ``L``. Markers on the parent link do not move (use :func:`displace_marker` for that).

    Parameters
    ----------
    body : Body or KinematicTree
    joint_or_link : str
    delta_length : float
        Change of the segment length, m.
    delta_rotvec : array-like, shape (3,)
        Bending rotation vector, rad, in the parent link frame.

    Returns
    -------
    body : Body
    """
    body = Body.wrap(body)
    tree = body.tree
    if joint_or_link in {j.name for j in tree.joints}:
        names = [joint_or_link]
    elif joint_or_link in tree.links:
        names = [j.name for j in tree.joints if j.parent == joint_or_link]
        if not names:
            raise InvalidInputError(f"link {joint_or_link!r} has no child joints, so there is no limb to deform")
    else:
        raise InvalidInputError(f"{joint_or_link!r} is neither a joint nor a link of the tree")
    delta_rotvec = np.asarray(delta_rotvec, dtype=float)
    if delta_rotvec.shape != (3,) or not np.all(np.isfinite(delta_rotvec)) or not math.isfinite(delta_length):
        raise InvalidInputError(f"delta_rotvec must be a finite (3,) vector, got {delta_rotvec}")
    bend = np.eye(4)
    bend[:3, :3] = Rotation.from_rotvec(delta_rotvec).as_matrix()
    for name in names:
        origin = tree.joint(name).origin.copy()
        length = np.linalg.norm(origin[:3, 3])
        if delta_length != 0.0:
            if length < 1e-9:
                raise InvalidInputError(f"joint {name!r} has a zero-length limb; cannot change its length")
            if length + delta_length <= 0.0:
                raise InvalidInputError(f"delta_length {delta_length} would make limb {name!r} ({length} m) vanish")
            origin[:3, 3] *= (length + delta_length) / length
        tree = tree.replace_joint(name, origin=bend @ origin)
    return Body(tree, body.blocked, body.gears)


def displace_marker(body, marker_id, delta):
    """A copy of ``body`` whose marker moved on its link: ``link2marker' = link2marker @ delta``.

    Parameters
    ----------
    body : Body or KinematicTree
    marker_id : int
    delta : array-like, shape (4, 4)
        Displacement expressed in the marker's own frame (``old_marker2new_marker``).

    Returns
    -------
    body : Body
    """
    body = Body.wrap(body)
    delta = check_transform(delta, name="delta")
    if delta.shape != (4, 4):
        raise InvalidInputError(f"delta must have shape (4, 4), got {delta.shape}")
    marker = body.tree.marker(marker_id)
    return Body(body.tree.replace_marker(marker_id, link2marker=marker.link2marker @ delta), body.blocked,
                body.gears)
