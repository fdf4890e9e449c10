"""The learned body scheme as a robot description, and how it differs from the robot's specification.

:func:`learned_tree` turns a :class:`~body_scheme_core.prediction.scheme.BodyScheme` into a
:class:`~body_scheme_core.world.tree.KinematicTree` (and :func:`learned_urdf` that into URDF text for
robot_state_publisher, MoveIt or pybullet):

- a link ``<prefix>part_<id>`` per body part and a link ``<prefix>marker_<id>`` on a fixed joint ``marker_<id>_joint``
  for its marker (the prefix goes on links only: joints keep the robot's names); the
  root part's link is its marker's frame;
- a ``revolute`` or ``prismatic`` joint per one-action rigid-joint edge, named after the action's joint (so the
  commands drive it), its axis through the learned axis line, its limits the trained range; the joint frame has the
  parent marker's orientation, and for a revolute joint its origin is the axis point nearest to the child marker;
- a ``fixed`` joint per static edge;
- a joint per joint of a chain edge (:class:`~body_scheme_core.models.chain.ChainModel`), through links of their own
  for the unmarked links between: given the robot's specification (``nominal``), each joint's frame is the
  specification's, moved onto the learned axis (its origin to the nearest point of the learned axis line, its
  orientation turned by the least rotation that aligns the axes), and the links keep the specification's names;
  without one, a joint's frame has the parent marker's orientation and its origin is the axis point nearest the
  previous joint's. A tool's observations cannot tell where along its axis a joint sits, nor a sliding joint's line
  (:mod:`~body_scheme_core.models.chain`): the specification's places are kept for those. A coupled joint gets a
  ``mimic`` joint on its axis that follows the coupled action;
- an edge no URDF joint can express (a GP, or a model of several actions) becomes a fixed joint at its prediction for
  mid-range actions, and is named in the notes (:attr:`LearnedBody.notes`, a comment at the top of the URDF).

:func:`calibration_report` compares a learned body with a nominal one (a URDF and its marker file, as a
``KinematicTree``): per learned joint (a chain's joints each), the axis deviation (deg), the origin offset (mm: the
distance of the nominal joint origin from the learned axis line, for revolute joints; a prismatic joint's line has no
position) at zero actions in the edge's parent marker frame, and the edge's child marker's placement (its pose
relative to the parent marker at zero actions: mm and deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidInputError
from ..models import ChainModel
from ..rotations import cross3, rotation_log, rotvec_matrix
from ..transforms import invert_transform, rotational_error, translational_error
from ..world import Joint, KinematicTree, Marker, tree_to_urdf
from .scheme import BodyScheme

__all__ = ["LearnedJoint", "LearnedBody", "marker_link", "learned_tree", "learned_urdf", "calibration_report",
           "format_report"]

#: Below this |s - 1| a joint's learned scale is 1 (the command is the joint position).
_UNIT_SCALE = 1e-6


@dataclass(frozen=True)
class LearnedJoint:
    """One tree edge as exported: ``parent -> child`` parts, URDF joint type, name, action and scale."""

    parent: int
    child: int
    type: str  # "revolute", "prismatic" or "fixed"
    name: str
    action: int | None
    model: str  # the local model's kind: static, prismatic, revolute, chain, gp
    scale: float = 1.0  # joint position per action unit
    axis: tuple = ()  # unit axis in the parent marker frame (a chain's joint: at the chain's reference posture)
    point: tuple = ()  # a point of the axis line in the parent marker frame (revolute; likewise)


@dataclass
class LearnedBody:
    """:func:`learned_tree`'s result: the tree, the exported joints, the action of each tree action, the notes."""

    tree: KinematicTree
    joints: list
    actions: tuple  # tree action index -> body scheme action index
    n_actions: int
    notes: list = field(default_factory=list)

    def marker_poses(self, a):
        """``root_marker2marker`` per part for body-scheme action vector(s) ``a`` (forward kinematics of the
        tree; equals the body scheme's prediction for every rigid edge)."""
        a = np.asarray(a, dtype=float)
        scale = np.array([j.scale for j in self.joints if j.action is not None])  # in tree action order
        return self.tree.marker_poses(a[..., list(self.actions)] * scale)


def _edge_transforms(edge, n_actions, values):
    """The edge's parent2child (n, 4, 4) with its model's actions at ``values`` (n, k) and the others zero."""
    _, _, model, inverted = edge
    A = np.zeros((len(values), n_actions))
    A[:, list(model.actions)] = values
    return BodyScheme.edge_transform(model, inverted, A)


def _screw(Z0, Z1, kind):
    """Axis, scale and (revolute) axis point of ``Z(a) = J(a) Z0`` from ``Z0 = Z(0)`` and ``Z1 = Z(1)``."""
    J = Z1 @ invert_transform(Z0)
    if kind == "prismatic":
        v = J[:3, 3]
        scale = float(np.linalg.norm(v))
        return v / scale, scale, None
    rotvec = rotation_log(J[None, :3, :3])[0]
    scale = float(np.linalg.norm(rotvec))
    u = rotvec / scale
    # The axis line: (I - R) c = t, solved in the least-squares sense; then the point nearest to the child at a = 0.
    c = np.linalg.lstsq(np.eye(3) - J[:3, :3], J[:3, 3], rcond=None)[0]
    c = c + u * float(np.dot(Z0[:3, 3] - c, u))
    return u, scale, c


def _chain_joints(model, inverted):
    """A chain's joints in the tree's direction: ``[(action, kind, w or d, p or None, reference)]`` in the parent
    marker frame at the reference posture, its couplings ``[(i, j, c)]`` (chain positions) and ``M``. An inverted
    edge reverses the chain: ``M^-1 exp(-Ad_{M^-1} S_k q_k) ... exp(-Ad_{M^-1} S_1 q_1)``."""
    screws, M = model.screws()
    at = model.form.COUPLING_STORED_AT
    couplings = [(i, j, float(model.params_[at + c])) for c, (i, j) in enumerate(model.couplings)]
    joints = []
    for k, (kind, screw) in enumerate(zip(model.types, screws, strict=True)):
        w, p = screw if kind == "revolute" else (screw, None)
        joints.append((model.actions[k], kind, w, p, float(model.reference[k])))
    if not inverted:
        return joints, couplings, M
    Minv = invert_transform(M)
    R, t = Minv[:3, :3], Minv[:3, 3]
    flipped = [(a, kind, -R @ w, None if p is None else R @ p + t, r) for a, kind, w, p, r in reversed(joints)]
    k = len(joints) - 1
    return flipped, [(k - i, k - j, c) for i, j, c in couplings], Minv


def _aligned(R, u, w):
    """``R`` turned by the least rotation that takes ``R u`` to ``w`` (unit vectors)."""
    v = R @ u
    axis = cross3(v, w)
    s, c = float(np.linalg.norm(axis)), float(np.clip(v @ w, -1.0, 1.0))
    if s < 1e-12:
        if c > 0:
            return R
        axis = np.cross(v, np.eye(3)[int(np.argmin(np.abs(v)))])
        s = float(np.linalg.norm(axis))
    return rotvec_matrix(axis / s * math.atan2(s, c)) @ R


def _chain_frames(joints, nominal_frames):
    """The joints' frames (4, 4) in the parent marker frame at the reference posture (module docstring), and each
    axis in its own frame."""
    frames, axes = [], []
    previous = np.eye(4)
    for k, (_, _, w, p, _) in enumerate(joints):
        F = np.eye(4)
        if nominal_frames is not None:
            nominal, nominal_axis = nominal_frames[k]
            sign = 1.0 if (nominal[:3, :3] @ nominal_axis) @ w >= 0 else -1.0  # a chain traversed child to parent
            F[:3, :3] = _aligned(nominal[:3, :3], nominal_axis, sign * w)
            near = nominal[:3, 3]
        else:
            F[:3, :3] = previous[:3, :3]
            near = previous[:3, 3]
        F[:3, 3] = near if p is None else p + w * float(w @ (near - p))
        frames.append(F)
        axes.append(F[:3, :3].T @ w)
        previous = F
    return frames, axes


def _nominal_chain_frames(nominal, parent, joints):
    """Per chain joint, the specification's joint frame in the parent marker frame at the chain's reference posture
    and its axis; None when the specification lacks a marker or a joint of the chain."""
    if nominal is None or parent not in nominal.marker_ids:
        return None
    a = np.zeros(nominal.n_actions)
    try:
        specs = [nominal.action_joint(action) for action, *_ in joints]
    except InvalidInputError:
        return None
    for (action, *_, reference) in joints:
        a[action] = reference
    links = nominal.link_poses(a)
    to_parent = invert_transform(nominal.marker_poses(a)[parent])
    return [(to_parent @ links[spec.parent] @ spec.origin, np.asarray(spec.axis, dtype=float)) for spec in specs]


def _export_chain(edge, joint_names, part, link2marker, lower, upper, used, nominal, prefix):
    """The URDF joints of a chain edge (module docstring): ``(joints, exported, child link2marker, notes)``; the
    tree actions of its joints are appended to ``used``."""
    parent, child, model, inverted = edge
    joints, couplings, M = _chain_joints(model, inverted)
    nominal_frames = _nominal_chain_frames(nominal, parent, joints)
    frames, axes = _chain_frames(joints, nominal_frames)
    tree_action = {action: len(used) + k for k, (action, *_) in enumerate(joints)}
    out, exported, notes = [], [], []
    previous, link = link2marker[parent], part[parent]
    for k, ((action, kind, w, p, reference), F, u) in enumerate(zip(joints, frames, axes, strict=True)):
        name = joint_names[action]
        last = k == len(joints) - 1
        if last:
            next_link = part[child]
        elif nominal_frames is not None:
            spec = nominal.action_joint(action)
            next_link = prefix + (spec.parent if inverted else spec.child)
        else:
            next_link = f"{part[parent]}_to_{child}_link_{k + 1}"
        zero = np.eye(4)  # the joint at its zero position: the reference turned or slid back
        zero[:3, :3] = rotvec_matrix(-u * reference) if kind == "revolute" else np.eye(3)
        zero[:3, 3] = 0.0 if kind == "revolute" else -u * reference
        coupled = [(j, c) for i, j, c in couplings if i == k]
        mid_link = f"{next_link}_coupling" if coupled else next_link
        out.append(Joint(name, kind, link, mid_link, origin=previous @ F @ zero, axis=u, lower=float(lower[action]),
                         upper=float(upper[action]), action=tree_action[action]))
        for j, c in coupled:
            source, source_reference = joints[j][0], joints[j][4]
            limits = sorted(c * (np.array([lower[source], upper[source]]) - source_reference))
            out.append(Joint(f"{name}_coupling", kind, mid_link, next_link, axis=u, lower=float(limits[0]),
                             upper=float(limits[1]), action=tree_action[source], mimic=joint_names[source],
                             multiplier=c, offset=-c * source_reference))
            notes.append(f"{parent}->{child}: joint {name} moves {c:.6g} x joint {joint_names[source]} too (a "
                         f"coupling): mimic joint {name}_coupling")
        exported.append(LearnedJoint(parent, child, kind, name, action, "chain", 1.0, tuple(w),
                                     () if p is None else tuple(F[:3, 3])))
        previous, link = invert_transform(F), next_link
    used += [action for action, *_ in joints]
    return out, exported, invert_transform(frames[-1]) @ M, notes


def marker_link(prefix, part):
    """The learned URDF's link of a part's marker, ``<prefix>marker_<id>`` (also its TF frame)."""
    return f"{prefix}marker_{int(part)}"


def learned_tree(scheme, joint_names, lower, upper, prefix="", nominal=None):
    """The body scheme as a kinematic tree (see the module docstring).

    Parameters
    ----------
    scheme : BodyScheme
    joint_names : sequence of str
        The action's joint names, in action order.
    lower, upper : array-like, shape (m,)
        The trained range of each action (the joints' limits; mid-range actions fix GP edges).
    prefix : str
        Prefix of every link name (two robots in one TF tree). Joint names keep the robot's joint names, so its
        JointState drives them, as robot_state_publisher's ``frame_prefix`` expects.
    nominal : KinematicTree, optional
        The robot's specification with its markers: a chain's unmarked links take its frames and names.

    Returns
    -------
    LearnedBody
    """
    n_actions = len(joint_names)
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    if lower.shape != (n_actions,) or upper.shape != (n_actions,) or np.any(lower > upper):
        raise InvalidInputError(f"need {n_actions} lower <= upper limits, got {lower.tolist()}, {upper.tolist()}")
    if scheme.min_n_actions > n_actions:
        raise InvalidInputError(f"the body scheme uses {scheme.min_n_actions} actions, got {n_actions} joint names")
    mid = np.where(np.isfinite(lower + upper), (lower + upper) / 2.0, 0.0)
    part = {p: f"{prefix}part_{p}" for p in scheme.parts}
    link2marker = {scheme.root: np.eye(4)}  # part link -> marker, filled parent before child
    joints, exported, used, notes = [], [], [], []
    for edge in scheme.edges:
        parent, child, model, _ = edge
        if isinstance(model, ChainModel) and not set(model.actions) & set(used):
            chain, rows, link2marker[child], why = _export_chain(edge, joint_names, part, link2marker, lower, upper,
                                                                 used, nominal, prefix)
            joints += chain
            exported += rows
            notes += why
            continue
        kind = model.kind if len(model.actions) <= 1 else "multi"
        action = model.actions[0] if len(model.actions) == 1 else None
        rigid_joint = kind in ("revolute", "prismatic") and action not in used
        if rigid_joint:
            Z0, Z1 = _edge_transforms(edge, n_actions, [[0.0], [1.0]])
            u, scale, c = _screw(Z0, Z1, kind)
            scale = 1.0 if abs(scale - 1.0) < _UNIT_SCALE else scale
            joint_frame = np.eye(4)
            if c is not None:
                joint_frame[:3, 3] = c
            limits = sorted((scale * lower[action], scale * upper[action]))
            joints.append(Joint(joint_names[action], kind, part[parent], part[child],
                                origin=link2marker[parent] @ joint_frame, axis=u, lower=limits[0], upper=limits[1],
                                action=len(used)))
            used.append(action)
            link2marker[child] = invert_transform(joint_frame) @ Z0
            exported.append(LearnedJoint(parent, child, kind, joint_names[action], action, model.kind,
                                         scale, tuple(u), () if c is None else tuple(c)))
            if scale != 1.0:
                notes.append(f"{parent}->{child}: joint {joint_names[action]} turns {scale:.6g} per action unit; "
                             f"its position is {scale:.6g} x the command")
            continue
        Z = _edge_transforms(edge, n_actions, [mid[list(model.actions)]])[0]  # fixed at mid-range
        name = f"part_{parent}_to_part_{child}"
        joints.append(Joint(name, "fixed", part[parent], part[child], origin=link2marker[parent] @ Z))
        link2marker[child] = np.eye(4)
        exported.append(LearnedJoint(parent, child, "fixed", name, None, model.kind))
        if kind != "static":
            why = "a second joint of the same action" if action in used else f"a {model.kind} model"
            notes.append(f"{parent}->{child}: {why} over actions {list(model.actions)} is no URDF joint; fixed at "
                         f"its prediction for mid-range actions {mid[list(model.actions)].round(4).tolist()}")
    markers = []
    for p in scheme.parts:
        joints.append(Joint(f"marker_{p}_joint", "fixed", part[p], marker_link(prefix, p),
                            origin=link2marker[p]))
        markers.append(Marker(p, marker_link(prefix, p)))
    tree = KinematicTree(joints, markers, root_link=part[scheme.root])
    return LearnedBody(tree, exported, tuple(used), n_actions, notes)


def learned_urdf(body, name="learned_body_scheme"):
    """URDF text of a :class:`LearnedBody` (:func:`learned_tree`), with its notes (GP edges, scaled joints) in a
    comment at the top."""
    xml = tree_to_urdf(body.tree, name=name)
    lines = ["Learned by body_scheme from camera observations: a link per part, a fixed marker link per part,",
             "a joint per rigid one-action local model (named after its action), limits = the trained range."]
    lines += [f"NOTE {note}" for note in body.notes] or ["Every edge is a rigid joint or fixed."]
    comment = "<!--\n  " + "\n  ".join(line.replace("--", "- -") for line in lines) + "\n-->\n"
    head, _, rest = xml.partition("\n")
    return f"{head}\n{comment}{rest}"


# ---------------------------------------------------------------------- the calibration report
def _angle_deg(u, v):
    return math.degrees(math.acos(float(np.clip(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)), -1, 1))))


def calibration_report(body, nominal):
    """Compare a :class:`LearnedBody` with the nominal robot (a ``KinematicTree`` with its markers).

    The nominal joint of a learned joint is the nominal joint commanded by the same action; frames are compared in
    the parent marker's frame at zero actions.

    Returns
    -------
    report : dict
        ``joints``: per learned joint ``{parent, child, joint, type, axis_deg, origin_mm, marker_mm, marker_deg}``
        (``origin_mm`` None for prismatic joints); ``fixed``: per fixed edge ``{parent, child, model, marker_mm,
        marker_deg}``; ``max_axis_deg``, ``max_origin_mm``, ``max_marker_mm``; ``notes``.
    """
    zero_nominal = np.zeros(nominal.n_actions)
    nominal_markers = nominal.marker_poses(zero_nominal)
    nominal_links = nominal.link_poses(zero_nominal)
    learned_markers = body.marker_poses(np.zeros(body.n_actions))
    learned_links = body.tree.link_poses(np.zeros(body.tree.n_actions))
    tree_joints = {j.name: j for j in body.tree.joints}
    rows, fixed = [], []
    for joint in body.joints:
        for part in (joint.parent, joint.child):
            if part not in nominal_markers:
                raise InvalidInputError(f"marker {part} of the learned body is not in the nominal robot")
        nominal2parent = invert_transform(nominal_markers[joint.parent])
        nominal_rel = nominal2parent @ nominal_markers[joint.child]
        learned_rel = invert_transform(learned_markers[joint.parent]) @ learned_markers[joint.child]
        placement = {"marker_mm": 1e3 * float(translational_error(nominal_rel, learned_rel)),
                     "marker_deg": math.degrees(float(rotational_error(nominal_rel, learned_rel)))}
        if joint.type == "fixed":
            fixed.append({"parent": joint.parent, "child": joint.child, "model": joint.model, **placement})
            continue
        if joint.action >= nominal.n_actions:
            raise InvalidInputError(f"the nominal robot has no joint for action {joint.action}")
        spec = nominal.action_joint(joint.action)
        parent2frame = nominal2parent @ nominal_links[spec.parent] @ spec.origin
        axis = parent2frame[:3, :3] @ spec.axis
        learned = tree_joints[joint.name]  # its frame at zero actions, in the parent marker's frame
        frame = invert_transform(learned_markers[joint.parent]) @ learned_links[learned.parent] @ learned.origin
        u = frame[:3, :3] @ learned.axis
        origin_mm = None
        if joint.type == "revolute":
            d = parent2frame[:3, 3] - frame[:3, 3]
            origin_mm = 1e3 * float(np.linalg.norm(d - u * np.dot(d, u)))
        rows.append({"parent": joint.parent, "child": joint.child, "joint": joint.name, "nominal_joint": spec.name,
                     "type": joint.type, "axis_deg": _angle_deg(u, axis), "origin_mm": origin_mm, **placement})

    def biggest(key, items):
        values = [r[key] for r in items if r[key] is not None]
        return max(values) if values else None

    return {"joints": rows, "fixed": fixed, "max_axis_deg": biggest("axis_deg", rows),
            "max_origin_mm": biggest("origin_mm", rows), "max_marker_mm": biggest("marker_mm", rows + fixed),
            "notes": list(body.notes)}


def format_report(report):
    """The report as a text table."""
    lines = ["learned vs nominal, in the parent marker's frame at zero actions",
             f"{'edge':>8s}  {'joint':<22s} {'type':<10s} {'axis deg':>9s} {'origin mm':>10s} {'marker mm':>10s} "
             f"{'marker deg':>10s}"]
    for r in report["joints"]:
        origin = "-" if r["origin_mm"] is None else f"{r['origin_mm']:.2f}"
        lines.append(f"{r['parent']:>3d}->{r['child']:<3d}  {r['joint']:<22s} {r['type']:<10s} {r['axis_deg']:>9.3f} "
                     f"{origin:>10s} {r['marker_mm']:>10.2f} {r['marker_deg']:>10.3f}")
    for r in report["fixed"]:
        lines.append(f"{r['parent']:>3d}->{r['child']:<3d}  {'(fixed: ' + r['model'] + ')':<22s} {'fixed':<10s} "
                     f"{'-':>9s} {'-':>10s} {r['marker_mm']:>10.2f} {r['marker_deg']:>10.3f}")
    lines += [f"note: {note}" for note in report["notes"]]
    return "\n".join(lines)
