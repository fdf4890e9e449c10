r"""Synthetic robots: the paper's arms and random trees as :class:`~body_scheme_core.world.tree.KinematicTree`\ s.

Marker ids start at 1 like the paper's ``X_1 .. X_n``; action indices start at 0.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..transforms import transform_from_xyz_rpy
from .joints import Joint, Marker
from .tree import KinematicTree

__all__ = ["planar_2dof", "arm_4dof", "powercube_6dof", "arm_7dof", "upper_body", "branching_tree", "random_tree",
           "zoo_robot",
           "default_world2root"]


#: Rotation of a marker frame so that its normal (z) points along the link's +x axis, towards the default camera.
_FACING_CAMERA = (0.0, math.pi / 2.0, 0.0)


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


def arm_7dof():
    """A 7-joint arm like today's collaborative arms: yaw and pitch joints alternating from the base, 0.1-0.3 m
    links, one marker on the base and one on each of the seven links (8 markers, ids 1-8)."""
    return upper_body(arms=1, torso_joints=0, head_joints=0)


def upper_body(arms=2, arm_joints=7, torso_joints=0, head_joints=0):
    """A humanoid upper body: a base, a torso on ``torso_joints`` joints, a head on ``head_joints``, and ``arms``
    arms of ``arm_joints`` joints each (alternating yaw and pitch, 0.1-0.3 m links).

    Markers (ids from 1, facing the camera): one on the base and one on each arm link; with torso joints also a
    second on the base, one on each torso link and a second on the last; one on the head (on its last link only, so
    with two head joints its model needs both actions: complexity 2). Actions:
    torso, head, then each arm from the shoulder. ``upper_body()`` is a torso and two 7-joint arms with 15 markers
    (``dualarm``); ``upper_body(torso_joints=2, head_joints=2)`` has 18 joints and 20 markers (``upper18``).

    Returns
    -------
    tree : KinematicTree
    """
    z, y = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)
    joints, markers, action = [], [_marker(1, "base", (0.08, 0.0, 0.1))], 0
    if torso_joints:
        markers.append(_marker(2, "base", (0.08, 0.12, 0.05)))

    def chain(prefix, parent, n, xyz, rpy, lengths, marked):
        nonlocal action
        for k in range(n):
            link = f"{prefix}_link{k + 1}"
            origin = xyz if k == 0 else (0.0, 0.0, lengths[k - 1])
            joints.append(_revolute(f"{prefix}_joint{k + 1}", parent, link, origin, z if k % 2 == 0 else y,
                                    1.5 if k % 2 == 0 else 1.2, action, rpy=rpy if k == 0 else (0.0, 0.0, 0.0)))
            action += 1
            if marked(k):
                markers.append(_marker(len(markers) + 1, link, (0.07, 0.0, 0.5 * lengths[k])))
            parent = link
        return parent

    torso = chain("torso", "base", torso_joints, (0.0, 0.0, 0.3), (0.0, 0.0, 0.0), [0.15] * torso_joints,
                  lambda k: True) if torso_joints else "base"
    if torso_joints:
        markers.append(_marker(len(markers) + 1, torso, (0.08, -0.1, 0.1)))
    if head_joints:
        chain("head", torso, head_joints, (0.0, 0.0, 0.35), (0.0, 0.0, 0.0), [0.08] * head_joints,
              lambda k: k == head_joints - 1)
    lengths = [0.1, 0.3, 0.1, 0.25, 0.1, 0.2, 0.1, 0.15, 0.1][:arm_joints] + [0.1] * max(0, arm_joints - 9)
    for arm in range(arms):
        sign = 1.0 if arm == 0 else -1.0
        xyz = (0.0, 0.0, 0.2) if arms == 1 else (0.0, sign * 0.25, 0.3)
        rpy = (0.0, 0.0, 0.0) if arms == 1 else (-sign * math.pi / 2, 0.0, 0.0)
        chain(("left", "right")[arm] + "_arm" if arms > 1 else "arm", torso, arm_joints, xyz, rpy, lengths,
              lambda k: True)
    return KinematicTree(joints, markers)


def random_tree(n_joints, seed, branching=True, prismatic_fraction=0.0, *, link_length=(0.1, 0.4),
                marker_offset=0.05, second_marker_fraction=0.0, fixed_fraction=0.0, unmarked_fraction=0.0,
                dummy_actions=0,
                shuffle_ids=False, revolute_range=(0.5, math.pi), prismatic_range=(0.05, 0.3)):
    """A random kinematic tree with markers on its links.

    Link ``k`` (k = 1..n_joints) hangs off a uniformly chosen earlier link (``branching``) or off link ``k-1``
    (a chain) through joint ``k-1``: origin with a random rotation and a translation of ``link_length`` m in a random
    direction, random unit axis, limits ``+-U(revolute_range)`` rad (``+-U(prismatic_range)`` m for prismatic
    joints). A commanded joint gets the next action index. Marker ``k+1`` sits on link ``k`` at a random offset of up
    to ``marker_offset`` m with a random orientation. With the defaults every link carries one marker and every joint
    is commanded; the options make the bodies of the robot zoo (:func:`zoo_robot`), which the defaults do not draw
    (the same seed gives the same tree as before they existed):

    Parameters
    ----------
    n_joints : int
        Joints of the main tree (movable or fixed), ``dummy_actions`` not counted.
    seed : int
    branching : bool
    prismatic_fraction : float
        Probability that a movable joint is prismatic instead of revolute.
    link_length : (float, float)
        Range of the joint origins' distance from their parent link's origin, m.
    marker_offset : float
        Largest offset of a marker from its link's origin along each axis, m.
    second_marker_fraction : float
        Probability that a marked link carries a second marker (two markers on one link).
    fixed_fraction : float
        Probability that a joint is fixed (no action): a passive link, e.g. a tool, whose markers move with its
        parent. The last joint is movable when all others are fixed.
    unmarked_fraction : float
        Probability that a link carries no marker, as long as every marker stays within two commanded joints of the
        nearest marker above it (the learner's default ``max_complexity``) and a marked link lies below it (a leaf
        link keeps its marker).
    dummy_actions : int
        Extra revolute joints whose child links carry no marker and nothing else: actions that move nothing observed.
    shuffle_ids : bool
        Marker ids drawn at random from 1..99 instead of 1..n in link order.
    revolute_range, prismatic_range : (float, float)
        Ranges of the joints' symmetric limits (rad, m).

    Returns
    -------
    tree : KinematicTree
    """
    if not (isinstance(n_joints, (int, np.integer)) and n_joints >= 1):
        raise InvalidInputError(f"n_joints must be an integer >= 1, got {n_joints!r}")
    rng = np.random.default_rng(seed)
    options = np.random.default_rng([int(seed), 1]) if seed is not None else np.random.default_rng()
    joints, markers, actions = [], [], 0
    # Per link: commanded joints between it and the nearest marked link above it (0 when it is marked).
    unmarked_depth, skipped = {}, {}
    for k in range(n_joints + 1):
        link = f"link{k}"
        movable = True
        if k > 0:
            parent = f"link{int(rng.integers(0, k)) if branching else k - 1}"
            origin = np.eye(4)
            origin[:3, :3] = Rotation.random(random_state=rng).as_matrix()
            direction = rng.normal(size=3)
            origin[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(*link_length)
            axis = rng.normal(size=3)
            prismatic = rng.uniform() < prismatic_fraction
            limit = rng.uniform(*prismatic_range) if prismatic else rng.uniform(*revolute_range)
            movable = (not (fixed_fraction > 0 and options.uniform() < fixed_fraction)
                       or (k == n_joints and actions == 0))  # at least one joint moves
            kind = "fixed" if not movable else ("prismatic" if prismatic else "revolute")
            joints.append(Joint(f"joint{k - 1}", kind, parent, link, origin=origin, axis=axis / np.linalg.norm(axis),
                                lower=-limit, upper=limit, action=actions if movable else None))
            actions += int(movable)
            depth = unmarked_depth[parent] + int(movable)
        else:
            depth = 0
        unmarked = (k > 0 and depth < 2 and unmarked_fraction > 0 and options.uniform() < unmarked_fraction)
        unmarked_depth[link] = depth if unmarked else 0
        link2marker = np.eye(4)
        link2marker[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        link2marker[:3, 3] = rng.uniform(-marker_offset, marker_offset, size=3)
        if unmarked:
            skipped[link] = Marker(k + 1, link, link2marker, 0.05)
            continue
        markers.append(Marker(k + 1, link, link2marker, 0.05))
        if second_marker_fraction > 0 and options.uniform() < second_marker_fraction:
            extra = np.eye(4)
            extra[:3, :3] = Rotation.random(random_state=options).as_matrix()
            extra[:3, 3] = options.uniform(-marker_offset, marker_offset, size=3)
            markers.append(Marker(100 + len(markers), link, extra, 0.05))
    # A marked link ends every unmarked one's branch, or its joint would move nothing observed.
    marked = {m.link for m in markers}
    for link in reversed(list(skipped)):
        if not _marked_below(joints, link, marked):
            markers.append(skipped[link])
            marked.add(link)
    for d in range(dummy_actions):
        parent = f"link{int(options.integers(0, n_joints + 1))}"
        axis = options.normal(size=3)
        joints.append(Joint(f"dummy_joint{d}", "revolute", parent, f"dummy_link{d}",
                            origin=transform_from_xyz_rpy(options.uniform(-0.1, 0.1, size=3), (0.0, 0.0, 0.0)),
                            axis=axis / np.linalg.norm(axis), lower=-1.5, upper=1.5, action=actions))
        actions += 1
    ids = [m.id for m in markers]
    new_ids = (options.choice(np.arange(1, 100), size=len(ids), replace=False).tolist() if shuffle_ids
               else list(range(1, len(ids) + 1)) if second_marker_fraction > 0 or unmarked_fraction > 0 else ids)
    markers = [Marker(int(i), m.link, m.link2marker, m.size) for i, m in zip(new_ids, markers, strict=True)]
    return KinematicTree(joints, markers, root_link="link0")


def _marked_below(joints, link, marked):
    children = [j.child for j in joints if j.parent == link]
    return any(c in marked or _marked_below(joints, c, marked) for c in children)


def zoo_robot(seed, n_joints=None):
    """A body of the robot zoo: everything that makes body-scheme learning hard, drawn from ``seed``.

    Serial or branching (half each), 1-14 joints (``n_joints`` to fix it), a fifth of the movable joints prismatic,
    a tenth fixed (passive links, e.g. a tool), a tenth of the links without a marker (an edge then spans two
    joints), a fifth with a second marker, up to two dummy actions (joints moving nothing observed) and marker ids
    drawn at random (so the lowest id, the learner's default root, may sit anywhere). Links are 0.08-0.25 m long,
    markers up to 8 cm from their link's origin; revolute ranges +-(0.8 .. pi) rad, prismatic +-(0.15 .. 0.4) m, so
    every joint moves its markers clearly at the paper's noise. Every marker is within two commanded joints of the
    nearest marker above it (the learner's default ``max_complexity``).

    Parameters
    ----------
    seed : int
    n_joints : int, optional

    Returns
    -------
    tree : KinematicTree
    """
    rng = np.random.default_rng([int(seed), 2])
    n = int(rng.integers(1, 15)) if n_joints is None else int(n_joints)
    return random_tree(n, seed, branching=bool(rng.uniform() < 0.5), prismatic_fraction=0.2,
                       link_length=(0.08, 0.25), marker_offset=0.08, second_marker_fraction=0.2, fixed_fraction=0.1,
                       unmarked_fraction=0.1, dummy_actions=int(rng.integers(0, 3)), shuffle_ids=True,
                       revolute_range=(0.8, math.pi), prismatic_range=(0.15, 0.4))


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
