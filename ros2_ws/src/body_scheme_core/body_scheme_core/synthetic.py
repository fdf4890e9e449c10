"""Synthetic robots, observation noise, faults and motor-babbling sessions (no ROS, no pybullet).

Ground truth and observations come from one place: a :class:`Body` (a true :class:`KinematicTree` plus the
joints that ignore their commands) maps commanded actions to executed joint positions and true marker poses; an
:class:`ObservationModel` turns true poses into noisy, partially missing camera observations. Faults never modify
a tree or body in place: each returns a changed copy, and the learner only ever sees them through observations.

Marker ids start at 1 like the paper's ``X_1 .. X_n``; action indices start at 0. Every random quantity is drawn
from a ``numpy.random.Generator``, so ``make_session(..., seed=s)`` is reproducible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import BodySchemeError, InvalidInputError
from .kinematics import Joint, KinematicTree, Marker, transform_from_xyz_rpy
from .models.base import check_action_batch
from .transforms import check_transform, concat, relative_transform

__all__ = [
    "planar_2dof",
    "arm_4dof",
    "powercube_6dof",
    "branching_tree",
    "random_tree",
    "default_world2root",
    "ObservationModel",
    "Body",
    "block_joint",
    "deform_limb",
    "displace_marker",
    "Fault",
    "REPAIR",
    "babble",
    "Session",
    "make_session",
    "PROTOCOL_FAULTS",
    "protocol_schedule",
    "joint_blocked_protocol",
    "limb_deformed_protocol",
]

#: Rotation of a marker frame so that its normal (z) points along the link's +x axis, towards the default camera.
_FACING_CAMERA = (0.0, math.pi / 2.0, 0.0)
#: The paper's measured marker noise (m) and its rotational threshold / 3 (rad).
PAPER_SIGMA_TRANS = 0.044
PAPER_SIGMA_ROT = math.radians(15.0)


def _revolute(name, parent, child, xyz, axis, limit, action, rpy=(0.0, 0.0, 0.0)):
    lower, upper = (-limit, limit) if np.isscalar(limit) else limit
    return Joint(name, "revolute", parent, child, origin=transform_from_xyz_rpy(xyz, rpy), axis=axis,
                 lower=lower, upper=upper, action=action)


def _marker(marker_id, link, xyz, rpy=_FACING_CAMERA, size=0.08):
    return Marker(marker_id, link, transform_from_xyz_rpy(xyz, rpy), size)


# ---------------------------------------------------------------------- robots
def planar_2dof(l1=0.5, l2=0.4, limit=math.pi / 2):
    """The paper's 2-DOF robot (Sec. IV-A, Fig. 7): two revolute joints with parallel z axes.

    Joint 1 sits 0.1 m above the base frame; link 1 has length ``l1`` along its x axis, where joint 2 sits; link 2
    has length ``l2``. Markers (all with identity orientation relative to their link): 1 at the base origin,
    2 on link 1 on top of joint 2, 3 at the end of link 2 (end effector). So at actions ``(q1, q2)`` marker 3 is at
    ``(l1 cos q1 + l2 cos(q1 + q2), l1 sin q1 + l2 sin(q1 + q2), 0.1)`` with yaw ``q1 + q2``.

    Parameters
    ----------
    l1, l2 : float
        Link lengths, m.
    limit : float
        Joint limits are ``[-limit, limit]``, rad.

    Returns
    -------
    tree : KinematicTree
    """
    joints = [
        _revolute("joint1", "base", "link1", (0.0, 0.0, 0.1), (0.0, 0.0, 1.0), limit, 0),
        _revolute("joint2", "link1", "link2", (l1, 0.0, 0.0), (0.0, 0.0, 1.0), limit, 1),
    ]
    markers = [
        _marker(1, "base", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.05),
        _marker(2, "link1", (l1, 0.0, 0.0), (0.0, 0.0, 0.0), 0.05),
        _marker(3, "link2", (l2, 0.0, 0.0), (0.0, 0.0, 0.0), 0.05),
    ]
    return KinematicTree(joints, markers)


def arm_4dof():
    """A 4-DOF 3D arm like the paper's control experiment (Sec. IV-D): yaw, then three pitch joints.

    Base height 0.2 m, shoulder module 0.1 m, upper arm ("middle limb", link 2) 0.4 m, forearm 0.35 m, hand
    0.15 m; about 1.2 m stretched. Five markers (ids 1-5) on base, shoulder, upper arm, forearm and hand tip,
    offset 6 cm along +x and facing +x (towards the default camera). Bend the middle limb with
    ``deform_limb(body, "link2", delta_rotvec=(0.0, math.pi / 4, 0.0))``.

    Returns
    -------
    tree : KinematicTree
    """
    joints = [
        _revolute("joint1", "base", "link1", (0.0, 0.0, 0.2), (0.0, 0.0, 1.0), 2.0, 0),
        _revolute("joint2", "link1", "link2", (0.0, 0.0, 0.1), (0.0, 1.0, 0.0), 1.2, 1),
        _revolute("joint3", "link2", "link3", (0.0, 0.0, 0.4), (0.0, 1.0, 0.0), 1.5, 2),
        _revolute("joint4", "link3", "link4", (0.0, 0.0, 0.35), (0.0, 1.0, 0.0), 1.5, 3),
    ]
    markers = [
        _marker(1, "base", (0.06, 0.0, 0.1)),
        _marker(2, "link1", (0.06, 0.0, 0.05)),
        _marker(3, "link2", (0.06, 0.0, 0.35)),
        _marker(4, "link3", (0.06, 0.0, 0.3)),
        _marker(5, "link4", (0.06, 0.0, 0.15)),
    ]
    return KinematicTree(joints, markers)


def powercube_6dof():
    """A ~1.2 m 6-DOF arm like the paper's Schunk PowerCube manipulator (Sec. IV), with a tool and 7 markers.

    Joints alternate yaw/roll (z) and pitch (y): base pedestal 0.2 m, joint 1 yaw, joint 2 shoulder pitch 0.1 m
    higher, upper arm 0.3 m to joint 3 roll, joint 4 elbow pitch 0.1 m higher, forearm 0.25 m to joint 5 roll,
    joint 6 wrist pitch (the end-effector joint, action 5) 0.1 m higher, then a 0.15 m tool on a fixed joint
    ``tool_joint`` (link ``tool``). Markers 1-7 sit on the modules next to the joints, 7 cm out along +x facing the
    camera (marker 2 tilted 25 deg up), like the ARToolkit markers of the paper: 1 base, 2 link1, 3 link2, 4 link3,
    5 link4, 6 link5, 7 tool.
    Link 6 carries no marker, so the end-effector model ``6 -> 7`` depends on the end-effector joint (action 5)
    and contains the tool, as ``Delta_6->7`` in the paper's Figs. 1, 2 and 5.

    Returns
    -------
    tree : KinematicTree
    """
    z, y = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)
    joints = [
        _revolute("joint1", "base", "link1", (0.0, 0.0, 0.2), z, 1.5, 0),
        _revolute("joint2", "link1", "link2", (0.0, 0.0, 0.1), y, 1.2, 1),
        _revolute("joint3", "link2", "link3", (0.0, 0.0, 0.3), z, 1.5, 2),
        _revolute("joint4", "link3", "link4", (0.0, 0.0, 0.1), y, 1.5, 3),
        _revolute("joint5", "link4", "link5", (0.0, 0.0, 0.25), z, 1.5, 4),
        _revolute("joint6", "link5", "link6", (0.0, 0.0, 0.1), y, 1.5, 5),
        Joint("tool_joint", "fixed", "link6", "tool", origin=transform_from_xyz_rpy((0.0, 0.0, 0.15), (0, 0, 0))),
    ]
    markers = [
        _marker(1, "base", (0.08, 0.0, 0.1)),
        # link1 only yaws, so its plate is tilted 25 deg up towards the camera: upright, it is seen at 45-65 deg
        # and small, and IPPE mirrored its orientation in over 10 % of rendered frames (docs/sim.md).
        _marker(2, "link1", (0.07, 0.0, 0.05), rpy=(0.0, math.pi / 2 - math.radians(25.0), 0.0)),
        _marker(3, "link2", (0.07, 0.0, 0.25)),
        _marker(4, "link3", (0.07, 0.0, 0.05)),
        _marker(5, "link4", (0.07, 0.0, 0.2)),
        _marker(6, "link5", (0.07, 0.0, 0.05)),
        _marker(7, "tool", (0.05, 0.0, 0.0)),
    ]
    return KinematicTree(joints, markers)


def branching_tree(seed=None, second_torso_marker=False, dummy_action=False):
    """A torso on a yaw joint with two 2-DOF arms: a kinematic tree with a fork.

    Actions: 0 torso yaw, 1-2 left shoulder and elbow, 3-4 right shoulder and elbow. Markers: 1 base, 2 torso,
    3 left upper arm, 4 left forearm, 5 right upper arm, 6 right forearm; the true marker tree forks at 2.

    Parameters
    ----------
    seed : int or None
        ``None``: nominal lengths (0.3 m). Otherwise arm segment lengths are drawn uniformly from [0.2, 0.4] m.
    second_torso_marker : bool
        Add marker 7 on the torso's back (two markers on one link: trees that connect either are equivalent).
    dummy_action : bool
        Add action 5, a joint turning a link that carries no marker: an action that moves nothing observed.

    Returns
    -------
    tree : KinematicTree
    """
    lengths = np.full(4, 0.3) if seed is None else np.random.default_rng(seed).uniform(0.2, 0.4, size=4)
    y = (0.0, 1.0, 0.0)
    joints = [_revolute("torso_joint", "base", "torso", (0.0, 0.0, 0.3), (0.0, 0.0, 1.0), 1.5, 0)]
    markers = [_marker(1, "base", (0.08, 0.0, 0.1)), _marker(2, "torso", (0.08, 0.0, 0.2))]
    # The arms' z axes point sideways (left +y, right -y); shoulder and elbow pitch about the link y axis.
    for side, sign, first_action, first_marker, (upper, fore) in (
            ("left", 1.0, 1, 3, lengths[:2]), ("right", -1.0, 3, 5, lengths[2:])):
        joints.append(_revolute(f"{side}_shoulder", "torso", f"{side}_upper_arm", (0.0, sign * 0.2, 0.3), y, 1.2,
                                first_action, rpy=(-sign * math.pi / 2, 0.0, 0.0)))
        joints.append(_revolute(f"{side}_elbow", f"{side}_upper_arm", f"{side}_forearm", (0.0, 0.0, upper), y, 1.5,
                                first_action + 1))
        markers.append(_marker(first_marker, f"{side}_upper_arm", (0.06, 0.0, 0.5 * upper)))
        markers.append(_marker(first_marker + 1, f"{side}_forearm", (0.06, 0.0, fore)))
    if second_torso_marker:
        markers.append(_marker(7, "torso", (-0.08, 0.0, 0.15), rpy=(0.0, -math.pi / 2.0, 0.0)))
    if dummy_action:
        joints.append(_revolute("antenna_joint", "torso", "antenna", (0.0, 0.0, 0.35), (0.0, 0.0, 1.0), 1.5, 5))
    return KinematicTree(joints, markers)


def random_tree(n_joints, seed, branching=True, prismatic_fraction=0.0):
    """A random kinematic tree with one marker per link.

    Link ``k`` (k = 1..n_joints) hangs off a uniformly chosen earlier link (``branching``) or off link ``k-1``
    (a chain) through joint ``k-1`` commanded by action ``k-1``: origin with a random rotation and a translation of
    0.1-0.4 m in a random direction, random unit axis, limits ``+-U(0.5, pi)`` rad (``+-U(0.05, 0.3)`` m for
    prismatic joints). Marker ``k+1`` sits on link ``k`` at a random offset of up to 5 cm with a random orientation.

    Parameters
    ----------
    n_joints : int
    seed : int
    branching : bool
    prismatic_fraction : float
        Probability that a joint is prismatic instead of revolute.

    Returns
    -------
    tree : KinematicTree
    """
    if not (isinstance(n_joints, (int, np.integer)) and n_joints >= 1):
        raise InvalidInputError(f"n_joints must be an integer >= 1, got {n_joints!r}")
    rng = np.random.default_rng(seed)
    joints, markers = [], []
    for k in range(n_joints + 1):
        link = f"link{k}"
        if k > 0:
            parent = f"link{int(rng.integers(0, k)) if branching else k - 1}"
            origin = np.eye(4)
            origin[:3, :3] = Rotation.random(random_state=rng).as_matrix()
            direction = rng.normal(size=3)
            origin[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(0.1, 0.4)
            axis = rng.normal(size=3)
            prismatic = rng.uniform() < prismatic_fraction
            limit = rng.uniform(0.05, 0.3) if prismatic else rng.uniform(0.5, math.pi)
            joints.append(Joint(f"joint{k - 1}", "prismatic" if prismatic else "revolute", parent, link,
                                origin=origin, axis=axis / np.linalg.norm(axis), lower=-limit, upper=limit,
                                action=k - 1))
        link2marker = np.eye(4)
        link2marker[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        link2marker[:3, 3] = rng.uniform(-0.05, 0.05, size=3)
        markers.append(Marker(k + 1, link, link2marker, 0.05))
    return KinematicTree(joints, markers, root_link="link0")


# ---------------------------------------------------------------------- observations
def default_world2root(distance=2.0, drop=0.5):
    """Pose of the robot's root link in a camera's optical frame (x right, y down, z forward).

    The robot stands ``distance`` m in front of the camera with its base ``drop`` m below the optical axis, its
    z axis up and its x axis pointing at the camera (so markers facing +x face the camera at the home pose).

    Returns
    -------
    world2root : ndarray, shape (4, 4)
    """
    world2root = np.eye(4)
    world2root[:3, :3] = [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]
    world2root[:3, 3] = [0.0, drop, distance]
    return world2root


class ObservationModel:
    """Noisy, partially missing marker observations from a fixed camera (the paper's ``Y_i`` given ``X_i``).

    Noise model: the position gets isotropic Gaussian noise with per-axis standard deviation
    ``sigma_trans / sqrt(3)``, so the RMS 3D position error is ``sigma_trans`` (the paper reports one 3D
    standard deviation, 44 mm). The orientation is perturbed by a random rotation ``exp(w)``, ``w ~ N(0,
    (sigma_rot / sqrt(3))^2 I)`` applied in the marker frame, so the RMS rotation angle is ``sigma_rot``. Each
    marker is dropped independently with probability ``1 - visibility``, except those in ``always_visible``.
    Real ARToolkit noise is larger along the viewing ray; this isotropic model is a deliberate simplification.

    Parameters
    ----------
    sigma_trans : float
        RMS position error, m.
    sigma_rot : float
        RMS rotation error, rad.
    visibility : float
        Probability in [0, 1] that a marker is observed at a step.
    rng : numpy.random.Generator or int or None
    world2root : array-like, shape (4, 4) or None
        Pose of the robot root in the camera (world) frame; ``None``: :func:`default_world2root`.
    always_visible : iterable of int
        Marker ids never dropped (e.g. the root marker).
    """

    def __init__(self, sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT, visibility=1.0, rng=None,
                 world2root=None, always_visible=()):
        for name, value in (("sigma_trans", sigma_trans), ("sigma_rot", sigma_rot)):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be a finite number >= 0, got {value!r}")
        if not (0.0 <= visibility <= 1.0):
            raise InvalidInputError(f"visibility must be in [0, 1], got {visibility!r}")
        self.sigma_trans = float(sigma_trans)
        self.sigma_rot = float(sigma_rot)
        self.visibility = float(visibility)
        self.rng = np.random.default_rng(rng)
        world2root = default_world2root() if world2root is None else world2root
        self.world2root = check_transform(np.array(world2root, dtype=float), name="world2root")
        self.always_visible = frozenset(int(i) for i in always_visible)

    def observe_array(self, root2marker, marker_ids):
        """Observe a sequence of true poses.

        Parameters
        ----------
        root2marker : array-like, shape (n, k, 4, 4)
            True marker poses in the root frame.
        marker_ids : sequence of int, length k

        Returns
        -------
        observations : list of dict of int to ndarray, shape (4, 4)
            Per step, ``{marker id: noisy world2marker}`` of the visible markers.
        """
        root2marker = check_transform(root2marker, name="root2marker", tolerance=1e-6)
        marker_ids = [int(i) for i in marker_ids]
        if root2marker.ndim != 4 or root2marker.shape[1] != len(marker_ids):
            raise InvalidInputError(
                f"root2marker must have shape (n, {len(marker_ids)}, 4, 4), got {root2marker.shape}")
        n, k = root2marker.shape[:2]
        world2marker = concat(self.world2root, root2marker)
        # Draw every random number for every marker, so the noise of one marker does not depend on the others'
        # visibility settings.
        d_position = self.rng.normal(scale=self.sigma_trans / math.sqrt(3.0), size=(n, k, 3))
        d_rotvec = self.rng.normal(scale=self.sigma_rot / math.sqrt(3.0), size=(n, k, 3))
        visible = self.rng.uniform(size=(n, k)) < self.visibility
        visible[:, [c for c, i in enumerate(marker_ids) if i in self.always_visible]] = True
        noisy = world2marker.copy()
        noisy[..., :3, 3] += d_position
        noisy[..., :3, :3] = world2marker[..., :3, :3] @ Rotation.from_rotvec(
            d_rotvec.reshape(-1, 3)).as_matrix().reshape(n, k, 3, 3)
        return [{marker_ids[c]: noisy[t, c] for c in range(k) if visible[t, c]} for t in range(n)]

    def observe(self, root2marker):
        """Observe one configuration: ``{id: root2marker (4, 4)}`` -> ``{id: noisy world2marker}`` (visible only)."""
        ids = sorted(root2marker)
        stack = np.stack([np.asarray(root2marker[i], dtype=float) for i in ids])[None] if ids else np.zeros(
            (1, 0, 4, 4))
        return self.observe_array(stack, ids)[0]


# ---------------------------------------------------------------------- the true body and its faults
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


class Fault:
    """A change of the robot's physiology at a time step of a session.

    Parameters
    ----------
    kind : str
        ``"block_joint"``, ``"deform_limb"``, ``"displace_marker"`` (the functions of the same names, applied to
        the current body, so faults accumulate) or ``"repair"`` (back to the original body).
    **params
        Keyword arguments of that function (besides ``body``).
    """

    KINDS = ("block_joint", "deform_limb", "displace_marker", "repair")

    def __init__(self, kind, **params):
        if kind not in self.KINDS:
            raise InvalidInputError(f"fault kind must be one of {self.KINDS}, got {kind!r}")
        self.kind = kind
        self.params = params

    def apply(self, current, original):
        """The body after the fault, from the ``current`` and the ``original`` body."""
        if self.kind == "repair":
            return original
        function = {"block_joint": block_joint, "deform_limb": deform_limb, "displace_marker": displace_marker}
        return function[self.kind](current, **self.params)

    @property
    def entry(self):
        """The fault as a simulator schedule entry without its step (``"block_joint:5:0.8"``, ``"repair"``; see
        :mod:`body_scheme_sim.faults`).

        Raises
        ------
        InvalidInputError
            For a fault the schedule syntax cannot express (a marker displacement given as a matrix).
        """
        p = self.params
        if self.kind == "repair":
            return "repair"
        if self.kind == "block_joint":
            return f"block_joint:{p['action_index']}:{p['angle']}"
        if self.kind == "deform_limb":
            numbers = (p.get("delta_length", 0.0), *p.get("delta_rotvec", (0.0, 0.0, 0.0)))
            return f"deform_limb:{p['joint_or_link']}:" + ":".join(repr(float(v)) for v in numbers)
        raise InvalidInputError(f"{self.describe()} has no schedule entry form")

    def describe(self):
        """Short text like ``block_joint(action_index=5, angle=0.8)``."""
        args = ", ".join(f"{k}={np.asarray(v).round(4).tolist() if not np.isscalar(v) else v}"
                         for k, v in self.params.items())
        return f"{self.kind}({args})"

    def __repr__(self):
        return f"<Fault {self.describe()}>"


#: Restores the original body.
REPAIR = Fault("repair")


# ---------------------------------------------------------------------- babbling and sessions
def babble(tree, n, rng, above_ground=None, ground_z=0.0, max_draws=100_000):
    """Random motor babbling: actions uniform within the joint limits.

    Parameters
    ----------
    tree : KinematicTree or Body
        Nominal robot used to screen the commands (the body's tree, blocking ignored).
    n : int
        Number of action vectors.
    rng : numpy.random.Generator or int
    above_ground : iterable of int, bool or None
        Marker ids (``True``: all markers) that must stay above ``z = ground_z`` in the root frame, a cheap
        stand-in for the paper's collision check; ``None`` or ``False`` accepts everything.
    ground_z : float
    max_draws : int
        Give up (``BodySchemeError``) after drawing this many candidates.

    Returns
    -------
    A : ndarray, shape (n, m)
    """
    tree = tree.tree if isinstance(tree, Body) else tree
    rng = np.random.default_rng(rng)
    if not (isinstance(n, (int, np.integer)) and n >= 0):
        raise InvalidInputError(f"n must be an integer >= 0, got {n!r}")
    lower, upper = tree.action_lower, tree.action_upper
    if above_ground is True:
        above_ground = tree.marker_ids
    elif above_ground is False:
        above_ground = None
    ids = [tree.marker(i).id for i in above_ground] if above_ground is not None else []
    accepted, n_accepted, drawn = [], 0, 0
    while n_accepted < n:
        batch = max(2 * (n - n_accepted), 16)
        if drawn + batch > max_draws:
            raise BodySchemeError(
                f"babbling accepted only {n_accepted} of {n} configurations in {drawn} draws; markers {ids} are "
                f"rarely above z = {ground_z}")
        A = rng.uniform(lower, upper, size=(batch, tree.n_actions))
        drawn += batch
        if ids:
            poses = tree.marker_poses(A)
            ok = np.all([poses[i][:, 2, 3] > ground_z for i in ids], axis=0)
            A = A[ok]
        accepted.append(A)
        n_accepted += A.shape[0]
    return np.concatenate(accepted, axis=0)[:n] if accepted else np.zeros((0, tree.n_actions))


@dataclass
class Session:
    """A babbling session: commands, noisy observations, ground truth and the fault timeline.

    Attributes
    ----------
    tree : KinematicTree
        The robot's nominal specification (what an engineered model is built from).
    actions : ndarray, shape (n, m)
        Commanded actions.
    executed : ndarray, shape (n, m)
        Joint positions actually reached (differs from ``actions`` where a joint is blocked).
    observations : list of dict of int to ndarray, shape (4, 4)
        Per step ``{marker id: noisy world2marker}`` of the visible markers.
    true_poses : ndarray, shape (n, n_markers, 4, 4)
        True ``world2marker``, markers in ``marker_ids`` order.
    marker_ids : tuple of int
    world2root : ndarray, shape (4, 4)
        Camera (world) to robot root transform.
    faults : list of (int, Fault)
        Step at which each fault takes effect (it affects that step and later ones).
    phase : ndarray, shape (n,)
        Number of faults in effect so far at each step (0 before the first).
    sigma_trans, sigma_rot, visibility : float
        Observation model settings.
    seed : int or None
    """

    tree: KinematicTree
    actions: np.ndarray
    executed: np.ndarray
    observations: list
    true_poses: np.ndarray
    marker_ids: tuple
    world2root: np.ndarray
    faults: list = field(default_factory=list)
    phase: np.ndarray = None
    sigma_trans: float = PAPER_SIGMA_TRANS
    sigma_rot: float = PAPER_SIGMA_ROT
    visibility: float = 1.0
    seed: int | None = None

    @property
    def n_steps(self):
        """Number of time steps."""
        return self.actions.shape[0]

    @property
    def timeline(self):
        """``[(step, description), ...]`` of the faults."""
        return [(step, fault.describe()) for step, fault in self.faults]

    @property
    def visible(self):
        """Boolean mask (n, n_markers) of the observed markers."""
        return np.array([[i in obs for i in self.marker_ids] for obs in self.observations], dtype=bool)

    def _column(self, marker_id):
        try:
            return self.marker_ids.index(int(marker_id))
        except ValueError:
            raise InvalidInputError(f"unknown marker id {marker_id!r}; markers: {list(self.marker_ids)}") from None

    def true_relative(self, id_i, id_j):
        """True ``marker_i2marker_j`` at every step, shape (n, 4, 4)."""
        return relative_transform(self.true_poses[:, self._column(id_i)], self.true_poses[:, self._column(id_j)])

    def relative_observations(self, id_i, id_j):
        """Observed ``Z_ij = Y_i^-1 Y_j`` at the steps where both markers are visible.

        Returns
        -------
        steps : ndarray of int, shape (k,)
        Z : ndarray, shape (k, 4, 4)
        """
        for marker_id in (id_i, id_j):
            self._column(marker_id)
        steps = [t for t, obs in enumerate(self.observations) if id_i in obs and id_j in obs]
        if not steps:
            return np.zeros(0, dtype=int), np.zeros((0, 4, 4))
        Z = relative_transform(np.stack([self.observations[t][id_i] for t in steps]),
                               np.stack([self.observations[t][id_j] for t in steps]))
        return np.array(steps), Z


def make_session(robot, n_steps, seed, faults=(), sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT,
                 visibility=1.0, world2root=None, always_visible=(), above_ground=None, ground_z=0.0):
    """Simulate motor babbling with noisy observations and faults.

    The commands are babbled on the nominal robot and the noise comes from a separate random stream, so sessions
    with the same seed and different faults share actions and noise draws: only the ground truth differs.

    Parameters
    ----------
    robot : KinematicTree or Body
        The robot before any fault.
    n_steps : int
    seed : int or None
        Seed of ``np.random.default_rng``; equal seeds give identical sessions.
    faults : iterable of (int, Fault)
        Fault taking effect at each step, applied in step order to the body of the previous phase.
    sigma_trans, sigma_rot, visibility, world2root, always_visible
        See :class:`ObservationModel`.
    above_ground, ground_z
        See :func:`babble`.

    Returns
    -------
    session : Session
    """
    original = Body.wrap(robot)
    tree = original.tree
    faults = sorted(((int(step), fault) for step, fault in faults), key=lambda item: item[0])
    for step, fault in faults:
        if not isinstance(fault, Fault):
            raise InvalidInputError(f"faults must be (step, Fault) pairs, got {fault!r}")
        if not (0 <= step < n_steps):
            raise InvalidInputError(f"fault step {step} is outside the session's 0..{n_steps - 1}")
    rng_actions, rng_noise = np.random.default_rng(seed).spawn(2)
    A = babble(tree, n_steps, rng_actions, above_ground=above_ground, ground_z=ground_z)
    executed = np.zeros_like(A)
    root2marker = np.zeros((n_steps, len(tree.marker_ids), 4, 4))
    phase = np.zeros(n_steps, dtype=int)
    body, start = original, 0
    boundaries = [step for step, _ in faults] + [n_steps]
    for index, end in enumerate(boundaries):
        if end > start:
            executed[start:end] = body.execute(A[start:end])
            root2marker[start:end] = body.true_marker_array(A[start:end])
            phase[start:end] = index
        if index < len(faults):
            body = faults[index][1].apply(body, original)
            start = end
    observer = ObservationModel(sigma_trans, sigma_rot, visibility, rng_noise, world2root, always_visible)
    observations = observer.observe_array(root2marker, tree.marker_ids)
    return Session(tree=tree, actions=A, executed=executed, observations=observations,
                   true_poses=concat(observer.world2root, root2marker), marker_ids=tree.marker_ids,
                   world2root=observer.world2root, faults=faults, phase=phase, sigma_trans=sigma_trans,
                   sigma_rot=sigma_rot, visibility=visibility, seed=seed)


#: The paper's adaptation protocols (Sec. IV-B/C) on :func:`powercube_6dof`: name -> the fault of blocks 2 and 4.
#: Block 1 is normal, block 3 repaired. Defined once here; the simulator records the same schedule
#: (:func:`body_scheme_sim.sessions.record_protocol`) from :meth:`Fault.entry`.
PROTOCOL_FAULTS = {
    "joint_blocked": lambda: Fault("block_joint", action_index=5, angle=0.8),
    "limb_deformed": lambda: Fault("deform_limb", joint_or_link="tool_joint", delta_length=0.1,
                                   delta_rotvec=(math.pi / 4, 0.0, 0.0)),
}


def protocol_schedule(protocol, n_per_block=100, fault=None):
    """The fault schedule of a protocol: ``[(n, fault), (2n, REPAIR), (3n, fault)]``.

    Parameters
    ----------
    protocol : str
        A key of :data:`PROTOCOL_FAULTS`.
    n_per_block : int
    fault : Fault or None
        Replaces the protocol's own fault (e.g. another blocked angle).
    """
    if protocol not in PROTOCOL_FAULTS:
        raise InvalidInputError(f"protocol must be one of {list(PROTOCOL_FAULTS)}, got {protocol!r}")
    fault = PROTOCOL_FAULTS[protocol]() if fault is None else fault
    n = n_per_block
    return [(n, fault), (2 * n, REPAIR), (3 * n, fault)]


def joint_blocked_protocol(seed, n_per_block=100, blocked_angle=0.8, sigma_trans=PAPER_SIGMA_TRANS,
                           sigma_rot=PAPER_SIGMA_ROT, visibility=0.919):
    """The paper's "joint stuck" scenario (Sec. IV-B) on :func:`powercube_6dof`.

    Four blocks of ``n_per_block`` steps: normal, end-effector joint (action 5) blocked at ``blocked_angle``,
    repaired, blocked again at the same angle. Commands keep all markers above the table.

    Returns
    -------
    session : Session
    """
    fault = Fault("block_joint", action_index=5, angle=blocked_angle)
    return make_session(powercube_6dof(), 4 * n_per_block, seed,
                        faults=protocol_schedule("joint_blocked", n_per_block, fault), sigma_trans=sigma_trans,
                        sigma_rot=sigma_rot, visibility=visibility, above_ground=True)


def limb_deformed_protocol(seed, n_per_block=100, delta_length=0.1, delta_rotvec=(math.pi / 4, 0.0, 0.0),
                           sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT, visibility=0.79):
    """The paper's "deformed limb" scenario (Sec. IV-C) on :func:`powercube_6dof`.

    Four blocks of ``n_per_block`` steps: normal, tool displaced (``tool_joint`` lengthened by ``delta_length``
    and bent by ``delta_rotvec`` about the wrist), restored, displaced again the same way.

    Returns
    -------
    session : Session
    """
    fault = Fault("deform_limb", joint_or_link="tool_joint", delta_length=delta_length,
                  delta_rotvec=tuple(float(v) for v in delta_rotvec))
    return make_session(powercube_6dof(), 4 * n_per_block, seed,
                        faults=protocol_schedule("limb_deformed", n_per_block, fault), sigma_trans=sigma_trans,
                        sigma_rot=sigma_rot, visibility=visibility, above_ground=True)
