"""Robot description files: URDF in and out for a :class:`~body_scheme_core.world.tree.KinematicTree`, and marker
placement YAML.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..transforms import transform_from_xyz_rpy, xyz_rpy_from_transform
from .joints import CONTINUOUS_RANGE, JOINT_TYPES, MOVABLE_JOINT_TYPES, Joint, Marker
from .tree import KinematicTree

__all__ = ["tree_from_urdf", "tree_to_urdf", "load_markers_yaml", "markers_to_yaml", "resolve_resource",
           "resolve_meshes"]


def tree_from_urdf(xml_string, markers=(), joint_actions=None):
    """Build a tree from URDF text.

    Parameters
    ----------
    xml_string : str or bytes
        URDF document.
    markers : iterable of Marker
    joint_actions : dict of str to int or None
        Action index per joint name. ``None``: movable joints that do not mimic another get indices 0, 1, ... in
        URDF order. Movable joints missing from a given mapping are passive (held at 0).

    Returns
    -------
    tree : KinematicTree

    Raises
    ------
    InvalidInputError
        With one line naming the element, for anything the tree cannot hold (floating and planar joints, a mimic
        of a mimic, a joint without parent or child, numbers that do not parse).

    Notes
    -----
    Only ``<link>`` and ``<joint>`` elements are read: transmissions, ``<gazebo>``, ``<ros2_control>`` and other
    extensions are ignored (so are their own ``<joint>`` children). Continuous joints, and revolute joints whose URDF
    ``lower > upper`` (pybullet's "unlimited"), get the range :data:`CONTINUOUS_RANGE` unless a limit with
    ``lower < upper`` is given. A mimic joint (``<mimic joint= multiplier= offset=>``) shares the action of the joint
    it follows.
    """
    if isinstance(xml_string, bytes):
        xml_string = xml_string.decode("utf-8", errors="replace")
    try:
        robot = ET.fromstring(xml_string)
    except ET.ParseError as exc:
        raise InvalidInputError(f"cannot parse URDF: {exc}") from exc
    if robot.tag != "robot":
        raise InvalidInputError(f"a URDF's root element is <robot>, got <{robot.tag}>")
    raw = [_urdf_joint(element) for element in robot.findall("joint")]
    mimics = {j["name"]: j["mimic"] for j in raw if j["mimic"] is not None}
    movable = [j["name"] for j in raw if j["type"] in MOVABLE_JOINT_TYPES and j["name"] not in mimics]
    if joint_actions is None:
        joint_actions = {name: k for k, name in enumerate(movable)}
    else:
        joint_actions = dict(joint_actions)
        unknown = sorted(set(joint_actions) - set(movable))
        if unknown:
            raise InvalidInputError(
                f"joint_actions names {unknown} are not movable joints of the URDF; movable: {movable}")
    names = {j["name"] for j in raw}
    for name, followed in mimics.items():
        if followed not in names:
            raise InvalidInputError(f"URDF joint {name!r} mimics {followed!r}, which the URDF does not have")
        if followed in mimics:
            raise InvalidInputError(f"URDF joint {name!r} mimics {followed!r}, itself a mimic joint")
    joints = []
    for j in raw:
        followed = j["mimic"]
        action = joint_actions.get(followed if followed is not None else j["name"])
        mimic = {} if followed is None else {"mimic": followed, "multiplier": j["multiplier"], "offset": j["offset"]}
        joints.append(Joint(name=j["name"], type=j["type"], parent=j["parent"], child=j["child"], origin=j["origin"],
                            axis=j["axis"], lower=j["lower"], upper=j["upper"],
                            action=action if j["type"] != "fixed" else None, **mimic))
    link_names = sorted(link.get("name") for link in robot.findall("link") if link.get("name"))
    return KinematicTree(joints, markers, root_link=None if joints else (link_names[0] if link_names else None))


def _urdf_numbers(element, attribute, count, default, where):
    """``count`` floats of an attribute (whitespace-separated), or ``default`` if the element or attribute is
    missing."""
    text = None if element is None else element.get(attribute)
    if text is None:
        return default
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        raise InvalidInputError(f"URDF {where}: {attribute}={text!r} is not {count} numbers") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise InvalidInputError(f"URDF {where}: {attribute}={text!r} is not {count} finite numbers")
    return values[0] if count == 1 else values


def _urdf_joint(element):
    """One ``<joint>`` element as a dict of checked values (one-line errors that name the joint)."""
    name = element.get("name")
    if not name:
        raise InvalidInputError("URDF <joint> without a name")
    where = f"joint {name!r}"
    kind = element.get("type")
    if kind not in JOINT_TYPES:
        raise InvalidInputError(f"URDF {where} has type {kind!r}; supported types are {JOINT_TYPES}")
    links = {}
    for tag in ("parent", "child"):
        link = element.find(tag)
        links[tag] = None if link is None else link.get("link")
        if not links[tag]:
            raise InvalidInputError(f"URDF {where} needs <{tag} link=...>")
    origin = element.find("origin")
    xyz = _urdf_numbers(origin, "xyz", 3, [0.0, 0.0, 0.0], where)
    rpy = _urdf_numbers(origin, "rpy", 3, [0.0, 0.0, 0.0], where)
    axis = np.array(_urdf_numbers(element.find("axis"), "xyz", 3, [1.0, 0.0, 0.0], where), dtype=float)
    norm = np.linalg.norm(axis)
    if kind != "fixed" and not norm > 1e-9:
        raise InvalidInputError(f"URDF {where} has a zero axis")
    axis = axis / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
    lower, upper = CONTINUOUS_RANGE
    limit = element.find("limit")
    if limit is not None and kind in MOVABLE_JOINT_TYPES:
        lo = _urdf_numbers(limit, "lower", 1, 0.0, where)
        hi = _urdf_numbers(limit, "upper", 1, 0.0, where)
        if lo < hi or (lo == hi and kind != "continuous"):
            lower, upper = lo, hi
        elif kind == "prismatic":
            raise InvalidInputError(f"URDF prismatic {where} has limits lower {lo} > upper {hi}")
    elif kind == "prismatic":
        raise InvalidInputError(f"URDF prismatic {where} needs a <limit>")
    mimic = element.find("mimic")
    followed = None if mimic is None or kind == "fixed" else mimic.get("joint")
    if mimic is not None and kind != "fixed" and not followed:
        raise InvalidInputError(f"URDF {where}: <mimic> needs joint=...")
    return {"name": name, "type": kind, "parent": links["parent"], "child": links["child"],
            "origin": transform_from_xyz_rpy(xyz, rpy), "axis": axis, "lower": lower, "upper": upper,
            "mimic": followed, "multiplier": _urdf_numbers(mimic, "multiplier", 1, 1.0, where),
            "offset": _urdf_numbers(mimic, "offset", 1, 0.0, where)}


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
    commanded = sorted((j for j in tree.joints if j.action is not None and j.mimic is None), key=lambda j: j.action)
    for joint in commanded + [j for j in tree.joints if j not in commanded]:
        element = ET.SubElement(robot, "joint", name=joint.name, type=joint.type)
        ET.SubElement(element, "parent", link=joint.parent)
        ET.SubElement(element, "child", link=joint.child)
        ET.SubElement(element, "origin", **_xyz_rpy_attributes(joint.origin))
        if joint.is_movable:
            ET.SubElement(element, "axis", xyz=_format_floats(joint.axis))
            ET.SubElement(element, "limit", lower=repr(joint.lower), upper=repr(joint.upper), effort="100",
                          velocity="2")
        if joint.mimic is not None:
            ET.SubElement(element, "mimic", joint=joint.mimic, multiplier=repr(joint.multiplier),
                          offset=repr(joint.offset))
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


# ---------------------------------------------------------------------- resources (meshes)
def _package_roots(package_path):
    """Directories that may hold packages, in search order: ``package_path``, then ``ROS_PACKAGE_PATH``."""
    roots = [os.fspath(d) for d in package_path]
    roots += [d for d in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if d]
    return roots


def resolve_resource(uri, urdf_dir=None, package_path=()):
    """The file a URDF resource names, or None if it cannot be found.

    Parameters
    ----------
    uri : str
        ``package://<package>/<path>``, ``file://<absolute path>``, an absolute path, or a path relative to the
        URDF's directory.
    urdf_dir : str or os.PathLike or None
        Directory of the URDF file.
    package_path : iterable of str or os.PathLike
        Directories to search first (``--package-path``): each is a package named by its last component, or holds
        packages as subdirectories.

    Returns
    -------
    path : str or None
        An existing file.

    Notes
    -----
    ``package://<package>/<path>`` is searched in ``package_path``, then ``ROS_PACKAGE_PATH`` (same rule), then the
    ament index of every prefix in ``AMENT_PREFIX_PATH`` (``<prefix>/share/<package>``), and last in the URDF's
    directory and its ancestors (``<dir>/<package>``, as pybullet does: robot descriptions are often shipped beside
    their meshes).
    """
    if uri.startswith("file://"):
        candidates = [uri[len("file://"):]]
    elif uri.startswith("package://"):
        package, _, rest = uri[len("package://"):].partition("/")
        candidates = []
        for root in _package_roots(package_path):
            candidates += [os.path.join(root, rest) if os.path.basename(os.path.normpath(root)) == package
                           else os.path.join(root, package, rest)]
        for prefix in (d for d in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if d):
            marker = os.path.join(prefix, "share", "ament_index", "resource_index", "packages", package)
            if os.path.exists(marker):
                candidates.append(os.path.join(prefix, "share", package, rest))
        if urdf_dir is not None:
            here = os.path.abspath(os.fspath(urdf_dir))
            while True:
                candidates.append(os.path.join(here, package, rest))
                if os.path.dirname(here) == here:
                    break
                here = os.path.dirname(here)
    elif "://" in uri:
        return None  # http:// and other schemes are not fetched
    elif os.path.isabs(uri) or urdf_dir is None:
        candidates = [uri]
    else:
        candidates = [os.path.join(os.fspath(urdf_dir), uri)]
    return next((os.path.abspath(c) for c in candidates if os.path.isfile(c)), None)


def resolve_meshes(urdf_text, urdf_dir=None, package_path=()):
    """URDF text with every ``<mesh filename>`` resolved to an absolute path (:func:`resolve_resource`), and the
    ``<visual>`` and ``<collision>`` elements whose mesh cannot be found removed.

    Returns
    -------
    text : str
    missing : list of str
        The mesh URIs that were not found, each once, in document order.
    """
    try:
        root = ET.fromstring(urdf_text)
    except ET.ParseError as exc:
        raise InvalidInputError(f"cannot parse URDF: {exc}") from exc
    missing = []
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for shape in link.findall(tag):
                mesh = shape.find("geometry/mesh")
                if mesh is None:
                    continue
                uri = mesh.get("filename", "")
                path = resolve_resource(uri, urdf_dir, package_path)
                if path is None:
                    if uri not in missing:
                        missing.append(uri)
                    link.remove(shape)
                else:
                    mesh.set("filename", path)
    return ET.tostring(root, encoding="unicode"), missing


# ---------------------------------------------------------------------- marker placement files
def load_markers_yaml(text_or_path):
    """Read markers from a placement file.

    The file is YAML: either a list of entries or a mapping with key ``markers`` holding that list. Each entry is
    ``{id: int, link: str, xyz: [x, y, z], rpy: [roll, pitch, yaw], size: float, plate: int}`` with ``xyz`` in m,
    ``rpy`` in rad (URDF convention), ``size`` the marker's edge length in m; ``xyz``, ``rpy``, ``size`` and
    ``plate`` are optional (zero pose, 0.05 m, none). Markers with the same ``plate`` are one rigid plate whose pose
    is that of the marker with that id (:func:`body_scheme_core.plates.plates_from_markers`).

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
