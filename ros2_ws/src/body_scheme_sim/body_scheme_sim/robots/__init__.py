"""The shipped robots (URDF + marker placement file) and loading any robot from a URDF and a marker file.

The shipped files are generated from the core's synthetic builders, so the simulator and the core's engineered
models describe exactly the same geometry. Regenerate them with ``python -m body_scheme_sim.robots --write``; a test
keeps the shipped files equal to a fresh generation.

A robot is a pair of files: ``<name>.urdf`` and ``<name>.markers.yaml`` (format:
:func:`body_scheme_core.world.load_markers_yaml`). Any other URDF works with a marker file next to it
(``<stem>.markers.yaml``) or given explicitly.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np

from body_scheme_core import world as synthetic_world
from body_scheme_core.errors import InvalidInputError
from body_scheme_core.world import KinematicTree, load_markers_yaml, markers_to_yaml

from ..errors import RobotFileError

__all__ = ["ROBOTS_DIR", "ROBOT_BUILDERS", "robot_names", "robot_files", "load_robot", "generate_robot_files",
           "write_robot_files"]

#: Directory of the shipped robot files (inside the Python package, so found from source tree and install alike).
ROBOTS_DIR = pathlib.Path(__file__).resolve().parent
#: Shipped robot name -> core builder of its :class:`KinematicTree`.
ROBOT_BUILDERS = {
    "planar_2dof": synthetic_world.planar_2dof,
    "arm_4dof": synthetic_world.arm_4dof,
    "powercube_6dof": synthetic_world.powercube_6dof,
}
#: Changes to the core builders' markers in the shipped files: ``{robot: {"size": {id: m}, "lift": {id: m}}}``,
#: lift along the marker's link z axis. Kinematics stay the core's; the changes only let a 640x480 camera 2 m away
#: detect the markers reliably:
#:
#: - the base markers of the 3D arms are 10 cm instead of 8 cm: they are the farthest from the camera and seen most
#:   obliquely (the root of the body scheme must be seen);
#: - the core's planar arm has 5 cm markers on the link axes, inside the link geometry where no camera sees them; the
#:   shipped one has 8 cm markers raised to 1 cm above the joint housings (all at z = 0.13 m). Both joints turn about
#:   z, so the lifts only add constant z offsets between markers; the in-plane kinematics of Fig. 7 are unchanged.
MARKER_CHANGES = {
    "planar_2dof": {"size": {1: 0.08, 2: 0.08, 3: 0.08}, "lift": {1: 0.13, 2: 0.03, 3: 0.03}},
    "arm_4dof": {"size": {1: 0.1}},
    "powercube_6dof": {"size": {1: 0.1}},
}
MARKERS_SUFFIX = ".markers.yaml"
# No "--" in it: XML comments cannot hold one.
_GENERATED_NOTE = "Generated from body_scheme_core.world.{name}() by body_scheme_sim.robots (docs/sim.md); " \
                  "do not edit."


def robot_names():
    """Names of the shipped robots."""
    return tuple(ROBOT_BUILDERS)


def robot_files(name_or_urdf_path, markers_path=None, require_markers=True):
    """URDF and marker file paths of a shipped robot name or a URDF path.

    Parameters
    ----------
    name_or_urdf_path : str or os.PathLike
        A name from :func:`robot_names` or the path of a URDF file.
    markers_path : str or os.PathLike or None
        Marker placement file; ``None``: the shipped one, or ``<urdf stem>.markers.yaml`` next to the URDF.
    require_markers : bool
        ``False``: a URDF without a marker file is fine (``markers_path`` is then None).

    Returns
    -------
    urdf_path, markers_path : pathlib.Path

    Raises
    ------
    RobotFileError
        If the name is unknown or a file does not exist.
    """
    text = os.fspath(name_or_urdf_path)
    if text in ROBOT_BUILDERS:
        urdf_path = ROBOTS_DIR / f"{text}.urdf"
    elif text.endswith(".urdf") or os.sep in text:
        urdf_path = pathlib.Path(text)
    else:
        raise RobotFileError(f"unknown robot {text!r}: give one of {list(ROBOT_BUILDERS)} or a .urdf path")
    if markers_path is None:
        markers_path = urdf_path.with_name(urdf_path.name[:-len(".urdf")] + MARKERS_SUFFIX) \
            if urdf_path.name.endswith(".urdf") else urdf_path.with_name(urdf_path.name + MARKERS_SUFFIX)
        if not markers_path.is_file():
            if not require_markers:
                markers_path = None
            else:
                raise RobotFileError(
                    f"no marker file for {urdf_path}: expected {markers_path}, or give one (--markers); without "
                    f"one, calibrate --simulate plans them (docs/your-robot.md)")
    markers_path = None if markers_path is None else pathlib.Path(markers_path)
    for path in (urdf_path, markers_path):
        if path is not None and not path.is_file():
            raise RobotFileError(f"robot file {path} does not exist")
    return urdf_path, markers_path


def load_robot(name_or_urdf_path, markers_path=None, markers=None):
    """The :class:`KinematicTree` of a shipped robot or of a URDF with a marker placement file.

    Movable joints get action indices in URDF order (``KinematicTree.from_urdf``).

    Parameters
    ----------
    name_or_urdf_path : str or os.PathLike
    markers_path : str or os.PathLike or None
        See :func:`robot_files`.
    markers : iterable of Marker or None
        The markers, instead of a marker file.

    Returns
    -------
    tree : KinematicTree

    Raises
    ------
    RobotFileError
        If a file is missing, or the URDF or marker file is invalid (the message names the file).
    """
    urdf_path, markers_path = robot_files(name_or_urdf_path, markers_path, require_markers=markers is None)
    try:
        markers = load_markers_yaml(markers_path) if markers is None else list(markers)
        return KinematicTree.from_urdf(urdf_path.read_text(encoding="utf-8", errors="replace"), markers=markers)
    except InvalidInputError as error:
        raise RobotFileError(f"robot {urdf_path}" + (f" with markers {markers_path}" if markers_path else "")
                             + f": {error}") from error
    except OSError as error:
        raise RobotFileError(f"cannot read robot {urdf_path}: {error.strerror or error}") from error


def generate_robot_files(name):
    """Fresh contents of a shipped robot's files from its core builder (with :data:`MARKER_CHANGES`).

    Returns
    -------
    urdf_text, markers_text : str
    """
    if name not in ROBOT_BUILDERS:
        raise RobotFileError(f"unknown robot {name!r}: give one of {list(ROBOT_BUILDERS)}")
    tree = ROBOT_BUILDERS[name]()
    changes = MARKER_CHANGES.get(name, {})
    for marker in tree.markers:
        lift = np.eye(4)
        lift[2, 3] = changes.get("lift", {}).get(marker.id, 0.0)
        tree = tree.replace_marker(marker.id, link2marker=lift @ marker.link2marker,
                                   size=changes.get("size", {}).get(marker.id, marker.size))
    note = _GENERATED_NOTE.format(name=name)
    declaration, rest = tree.to_urdf(name).split("\n", 1)
    urdf_text = f"{declaration}\n<!-- {note} -->\n{rest}"
    markers_text = f"# {note}\n" + markers_to_yaml(tree.markers)
    return urdf_text, markers_text


def write_robot_files(directory=ROBOTS_DIR):
    """Write every shipped robot's files into ``directory``; returns the paths written."""
    directory = pathlib.Path(directory)
    written = []
    for name in ROBOT_BUILDERS:
        urdf_text, markers_text = generate_robot_files(name)
        for path, text in ((directory / f"{name}.urdf", urdf_text), (directory / f"{name}{MARKERS_SUFFIX}",
                                                                     markers_text)):
            path.write_text(text, encoding="utf-8")
            written.append(path)
    return written
