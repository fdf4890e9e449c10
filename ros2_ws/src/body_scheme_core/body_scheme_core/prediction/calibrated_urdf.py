"""The robot's own URDF, calibrated: a drop-in replacement with the learned joint axes.

:func:`~.learned_body.learned_urdf` describes the body scheme in links of its own (a link per part). A user who
calibrates wants the robot's file back, corrected: its links, names, meshes, limits and fixed joints as they are, and
each joint the body scheme learned moved onto the learned axis line. :func:`calibrated_urdf` edits the nominal URDF's
joint ``<origin>`` elements (the file is written again by ElementTree: its comments and declaration are not kept; no
``<calibration>`` tags, which most drivers ignore):

- every link frame is computed at zero actions in the robot's base frame. The learned body is placed there by its root
  marker (whose place on the base comes from the nominal marker file: the base is as well placed as that marker);
- a joint the body scheme learned gets its specified frame below its corrected parent link, turned by the least
  rotation that takes that axis onto the learned one, its origin moved to the point of the learned axis line nearest
  the specified origin (a revolute joint; a prismatic joint's line has no position, its origin stays); its axis in
  its own frame is unchanged;
- a revolute joint's zero offset (how far its link is turned about the axis at command 0): its frame is turned
  about its axis so that the next learned joint sits, seen from it, where the specification has it; the last joint's
  offset cannot be told from its marker's place and is kept;
- every other joint (fixed, or one the body scheme has no rigid joint for) keeps its origin relative to its parent, so
  it follows the corrected links above it. The joint's ``<origin>`` is the corrected parent link to the corrected
  joint frame.

With the markers' corrected places on their links (:attr:`CalibratedURDF.markers`), the file's forward kinematics is
the body scheme's prediction for every rigid joint. A tool-only calibration cannot tell where along its axis a joint
sits (the nominal place along the line is kept), nor a sliding joint's line, nor the last joint's zero offset from the
tool plate's placement (both go into the tool marker's place): :attr:`CalibratedURDF.notes` says so.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidInputError
from ..rotations import rotvec_matrix
from ..transforms import invert_transform, rotational_error, xyz_rpy_from_transform
from .learned_body import _aligned

__all__ = ["CalibratedURDF", "calibrated_urdf", "format_diff"]

#: A continuous joint is a revolute one without limits.
_KIND = {"continuous": "revolute"}


@dataclass
class CalibratedURDF:
    """:func:`calibrated_urdf`'s result.

    Attributes
    ----------
    text : str
        The corrected URDF.
    diff : list of dict
        Per joint moved: ``{joint, type, origin_mm, origin_deg, axis_deg}``: how far its ``<origin>`` moved (mm,
        deg, in its parent link's frame) and the angle between the nominal and the learned axis.
    markers : dict of int to (str, ndarray)
        Per marker: its link and its corrected place on that link (``link2marker``, (4, 4)).
    notes : list of str
    """

    text: str
    diff: list = field(default_factory=list)
    markers: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)


def calibrated_urdf(urdf_text, body, nominal, root):
    """The nominal URDF with the learned joint axes (see the module docstring).

    Parameters
    ----------
    urdf_text : str or bytes
        The robot's URDF (the one ``nominal`` was read from).
    body : LearnedBody
        :func:`~.learned_body.learned_tree`'s result (joint names: the robot's).
    nominal : KinematicTree
        The robot's specification with its markers.
    root : int
        The body scheme's root part (a marker on the base).

    Returns
    -------
    CalibratedURDF
    """
    try:
        robot = ET.fromstring(urdf_text)
    except ET.ParseError as error:
        raise InvalidInputError(f"the nominal URDF does not parse: {error}") from error
    zero = np.zeros(nominal.n_actions)
    nominal_links = nominal.link_poses(zero)
    learned_links = body.tree.link_poses(np.zeros(body.tree.n_actions))
    specified_markers = nominal.marker_poses(zero)
    if root not in specified_markers or set(body.marker_poses(np.zeros(body.n_actions))) - set(specified_markers):
        raise InvalidInputError(f"the nominal robot's markers {sorted(specified_markers)} lack the learned body's "
                                f"(root {root})")
    base2root = specified_markers[root]  # the learned body's root frame in the base frame
    learned_joints = {j.name: j for j in body.tree.joints if j.type in ("revolute", "prismatic")}
    # Each learned joint's axis line in the base frame, and the point of it nearest the specified joint origin.
    lines = {}
    for joint in nominal.joints:
        learned = learned_joints.get(joint.name)
        if learned is not None and learned.type == _KIND.get(joint.type, joint.type):
            frame = base2root @ learned_links[learned.parent] @ learned.origin
            axis = frame[:3, :3] @ learned.axis
            spec = (nominal_links[joint.parent] @ joint.origin)[:3, 3]
            lines[joint.name] = (frame[:3, 3] + axis * float(axis @ (spec - frame[:3, 3])), axis)
    frames = {nominal.root_link: np.eye(4)}
    origins, diff, notes = {}, [], []
    pending = list(nominal.joints)
    while pending:
        joint = next((j for j in pending if j.parent in frames), None)
        if joint is None:
            raise InvalidInputError(f"joints {[j.name for j in pending]} do not hang from the root link")
        pending.remove(joint)
        chained = frames[joint.parent] @ joint.origin  # as specified, below the corrected parent
        if joint.name not in lines:
            frames[joint.child] = chained
            continue
        point, axis = lines[joint.name]
        corrected = np.eye(4)
        corrected[:3, :3] = _aligned(chained[:3, :3], joint.axis, axis)
        corrected[:3, 3] = point if learned_joints[joint.name].type == "revolute" else chained[:3, 3]
        following = [j for j in nominal.joints if j.parent == joint.child and j.name in lines]
        if learned_joints[joint.name].type == "revolute" and following:
            corrected = _twisted(corrected, joint.axis, following[0].origin[:3, 3], lines[following[0].name][0])
        frames[joint.child] = corrected
        origins[joint.name] = invert_transform(frames[joint.parent]) @ corrected
        spec_axis = nominal_links[joint.parent][:3, :3] @ joint.origin[:3, :3] @ joint.axis
        diff.append({"joint": joint.name, "type": joint.type,
                     "origin_mm": 1e3 * float(np.linalg.norm(origins[joint.name][:3, 3] - joint.origin[:3, 3])),
                     "origin_deg": math.degrees(float(rotational_error(origins[joint.name], joint.origin))),
                     "axis_deg": math.degrees(math.acos(float(np.clip(axis @ spec_axis, -1, 1))))})
    for element in robot.findall("joint"):  # not the <joint> of a <transmission> or <ros2_control>
        if element.get("name") in origins:
            origin = element.find("origin")
            if origin is None:
                origin = ET.SubElement(element, "origin")
            xyz, rpy = xyz_rpy_from_transform(origins[element.get("name")])
            origin.set("xyz", " ".join(repr(float(v)) for v in xyz))
            origin.set("rpy", " ".join(repr(float(v)) for v in rpy))
    learned_markers = body.marker_poses(np.zeros(body.n_actions))
    markers = {part: (nominal.marker(part).link,
                      invert_transform(frames[nominal.marker(part).link]) @ base2root @ pose)
               for part, pose in learned_markers.items()}
    unlearned = [name for name in nominal.action_joint_names if name not in origins]
    if unlearned:
        notes.append(f"joints kept as specified (no rigid joint learned for them): {unlearned}")
    notes.append("a joint's place along its axis, a sliding joint's line and the last joint's zero offset are not "
                 "observable from the markers beyond it: the specification's are kept (the offset goes into the "
                 "marker's place)")
    comment = ET.Comment(" Calibrated by body_scheme: joint origins moved onto the learned axes "
                         f"({len(origins)} joints); links, names, meshes and limits as specified. ")
    robot.insert(0, comment)
    text = ET.tostring(robot, encoding="unicode")
    return CalibratedURDF(f'<?xml version="1.0"?>\n{text}\n', diff, markers, notes)


def _twisted(frame, axis, nominal_next, next_position, min_lever=0.01):
    """``frame`` turned about its own ``axis`` so that ``next_position`` (base frame) appears where the nominal
    ``nominal_next`` (in the frame) is, seen across the axis; unchanged with less than ``min_lever`` (m) of lever."""
    seen = (invert_transform(frame) @ np.append(next_position, 1.0))[:3]
    across = [v - axis * float(axis @ v) for v in (np.asarray(nominal_next, dtype=float), seen)]
    if min(np.linalg.norm(v) for v in across) < min_lever:
        return frame
    angle = math.atan2(float(axis @ np.cross(across[0], across[1])), float(across[0] @ across[1]))
    turned = frame.copy()
    turned[:3, :3] = frame[:3, :3] @ rotvec_matrix(axis * angle)
    return turned


def format_diff(result):
    """The per-joint diff against the nominal URDF as text, with the notes."""
    lines = [f"{'joint':24s} {'type':10s} {'origin mm':>10s} {'origin deg':>11s} {'axis deg':>9s}"]
    lines += [f"{row['joint']:24s} {row['type']:10s} {row['origin_mm']:10.2f} {row['origin_deg']:11.3f} "
              f"{row['axis_deg']:9.3f}" for row in result.diff]
    lines += [f"note: {note}" for note in result.notes]
    return "\n".join(lines) + "\n"
