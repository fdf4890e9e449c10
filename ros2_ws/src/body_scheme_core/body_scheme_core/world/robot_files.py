"""Robot description files: URDF in and out for a :class:`~body_scheme_core.world.tree.KinematicTree`, and marker
placement YAML.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..transforms import transform_from_xyz_rpy, xyz_rpy_from_transform
from .tree import CONTINUOUS_RANGE, JOINT_TYPES, MOVABLE_JOINT_TYPES, Joint, KinematicTree, Marker

__all__ = ["tree_from_urdf", "tree_to_urdf", "load_markers_yaml", "markers_to_yaml"]


def tree_from_urdf(xml_string, markers=(), joint_actions=None):
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
    tree = KinematicTree(joints, markers, root_link=None if joints else (sorted(link_names)[0] if link_names else None))
    return tree

def tree_to_urdf(tree, name="robot"):
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
    children = {link: [] for link in tree.links}
    for joint in tree.joints:
        children[joint.parent].append(joint)
    for link in tree.links:
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
    commanded = sorted((j for j in tree.joints if j.action is not None), key=lambda j: j.action)
    for joint in commanded + [j for j in tree.joints if j.action is None]:
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
