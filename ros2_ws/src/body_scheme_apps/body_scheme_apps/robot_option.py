"""Bring your own robot: the ``--robot``, ``--markers``, ``--camera`` and ``--package-path`` options every command
shares (``calibrate --simulate``, ``record``, ``live_demo``, ``core_demo``, ``plan_markers``), resolved in one place.

``--robot`` is a shipped robot's name or a URDF path. Its markers are ``--markers``, else the shipped file or
``<stem>.markers.yaml`` beside the URDF, else they are planned for the camera
(:func:`body_scheme_sim.planning.plan_markers`) and written next to the command's output. The camera is
``--camera "x y z roll pitch yaw"`` (its optical frame in the world, m and rad, URDF rpy; a 1280 x 960 camera),
``auto`` (framing every marker), or by default the camera the markers were planned for (``camera.yaml`` beside a
``markers.yaml``, ``<stem>.camera.yaml`` beside ``<stem>.markers.yaml``:
:func:`body_scheme_sim.markers.beside_markers`), else the simulator's camera for a shipped robot and ``auto`` for a
URDF.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

__all__ = ["RobotChoice", "add_robot_arguments", "add_camera_arguments", "resolve_robot", "scheme_parameters_path",
           "write_scheme_parameters"]


@dataclass
class RobotChoice:
    """What the options resolved to.

    Attributes
    ----------
    robot : str
        Shipped name or URDF path.
    markers_path : pathlib.Path or None
        None for a shipped robot's own file.
    camera : Camera or None
        None: the simulator's default camera.
    package_path : list of str
    tree : KinematicTree
        The robot with its markers.
    """

    robot: str
    markers_path: object
    camera: object
    package_path: list
    tree: object


def add_robot_arguments(parser, default="powercube_6dof", camera=True):
    """Add ``--robot``, ``--markers``, ``--camera`` (unless ``camera`` is false: a command without one) and
    ``--package-path`` to an argparse parser."""
    parser.add_argument("--robot", default=default, help="a shipped robot's name or a URDF path (default: "
                                                         "%(default)s)")
    parser.add_argument("--markers", help="marker placement YAML (default: the shipped one, <stem>.markers.yaml "
                                          "beside the URDF, else planned and written to the output directory)")
    if camera:
        add_camera_arguments(parser, package_path=False)
    add_camera_arguments(parser, camera=False)


def add_camera_arguments(parser, camera=True, package_path=True, prefix=""):
    """Add ``--camera`` and ``--package-path`` (their help texts start with ``prefix``, e.g. ``"--simulate: "``)."""
    if camera:
        parser.add_argument("--camera", default="default",
                            help=f'{prefix}"x y z roll pitch yaw" of the camera\'s optical frame in the world (m, '
                                 "rad), or auto (default: the camera the markers were planned for, camera.yaml "
                                 "beside them; else the simulator's camera for a shipped robot, auto for a URDF)")
    if package_path:
        parser.add_argument("--package-path", action="append", default=[], metavar="DIR",
                            help=f"{prefix}a directory searched first for package:// meshes (repeatable; then "
                                 "ROS_PACKAGE_PATH, the ament index and the URDF's directory)")


def resolve_robot(robot, markers=None, camera="default", package_path=(), plan_to=None, seed=0, log=print):
    """Resolve the options (see the module docstring); plans markers into the file ``plan_to`` when none exist
    (the caller's output directory: ``plan_to`` None with no markers to read is a ``ValueError``).

    Raises
    ------
    BodySchemeError
        One line: an unknown robot, an unreadable URDF, marker file or camera file (``camera.yaml`` beside the
        markers), no marker could be planned.
    """
    from body_scheme_core.errors import InvalidInputError
    from body_scheme_sim.camera import read_camera, write_camera
    from body_scheme_sim.errors import RobotFileError
    from body_scheme_sim.markers import beside_markers
    from body_scheme_sim.planning import auto_camera, parse_camera, plan_markers, write_markers
    from body_scheme_sim.robots import ROBOT_BUILDERS, load_robot, robot_files
    from body_scheme_sim.sheet import write_sheet

    shipped = robot in ROBOT_BUILDERS
    markers_path = None if markers is None else pathlib.Path(markers)
    if markers_path is None and not shipped:
        markers_path = robot_files(robot, require_markers=False)[1]
    planned_camera = None if markers_path is None else beside_markers(markers_path, "camera.yaml")
    if camera == "default" and planned_camera is not None and planned_camera.is_file():
        try:
            chosen = read_camera(planned_camera)  # the camera the markers were planned for (plan_markers wrote it)
        except InvalidInputError as error:
            raise InvalidInputError(f"{error}; read as the camera {markers_path} was planned for (it is beside it): "
                                    f"--camera auto or --camera \"x y z roll pitch yaw\" does without it") from None
        log(f"camera of {planned_camera} (the one the markers were planned for; --camera overrides it)")
    else:
        if camera == "default":
            camera = None if shipped else "auto"
        chosen = None if camera is None else parse_camera(camera)
        if markers_path is None and not shipped:
            if plan_to is None:
                raise ValueError("resolve_robot: plan_to (where planned markers go) is needed for a URDF without "
                                 "markers")
            planned, skipped, chosen = plan_markers(robot, camera=chosen, package_path=package_path, seed=seed)
            if not planned:
                raise RobotFileError(f"no marker could be planned on {robot}: no link's collision geometry is in "
                                     f"view (are its meshes found? see --package-path)")
            plan_to = pathlib.Path(plan_to)
            plan_to.parent.mkdir(parents=True, exist_ok=True)
            markers_path = write_markers(planned, plan_to)
            sheet = write_sheet([p.marker for p in planned], plan_to.with_suffix(""))
            params = write_scheme_parameters(robot, markers_path, scheme_parameters_path(markers_path))
            camera_file = write_camera(chosen, beside_markers(markers_path, "camera.yaml"))
            log(f"planned {len(planned)} markers ({', '.join(p.marker.link for p in planned)}), wrote {markers_path}, "
                f"its camera {camera_file}, scheme_node's parameters {params} and the sheet to print "
                f"({', '.join(str(path) for path in sheet)})"
                + "".join(f"; no marker on {link}: {why}" for link, why in skipped.items()))
    tree = load_robot(robot, markers_path)
    if camera is not None and chosen is None:
        chosen = auto_camera(tree)
    if camera == "auto":
        log(f"camera at {[round(float(v), 3) for v in chosen.position]} looking at the robot (--camera auto)")
    return RobotChoice(str(robot), markers_path, chosen, list(package_path), tree)


def scheme_parameters_path(markers_path):
    """Where scheme_node's parameter file for the markers of ``markers_path`` goes: ``dir/markers.yaml`` ->
    ``dir/scheme_node.yaml``, ``bags/run.markers.yaml`` -> ``bags/run.scheme_node.yaml``."""
    from body_scheme_sim.markers import beside_markers

    return beside_markers(markers_path, "scheme_node.yaml")


def write_scheme_parameters(robot, markers_path, path):
    """Write scheme_node's parameter file for ``robot`` with the markers of ``markers_path`` to ``path``
    (:func:`body_scheme_nodes.settings.robot_parameter_file`); returns ``path``."""
    from body_scheme_nodes.offline_replay import default_params_file
    from body_scheme_nodes.settings import robot_parameter_file
    from body_scheme_sim.robots import load_robot

    tree = load_robot(robot, markers_path)
    path = pathlib.Path(path)
    path.write_text(robot_parameter_file(default_params_file().read_text(), tree, robot), encoding="utf-8")
    return path
