"""The body scheme for the ROS toolbox (RViz, Foxglove, tf2): message builders, no node state.

scheme_node publishes, for its latest prediction:

- ``body_scheme/markers`` (visualization_msgs/MarkerArray): namespaces ``axes`` (every predicted part as RGB axes),
  ``edges`` (each local model of the tree as a line from parent to child, coloured by :data:`EDGE_COLOURS`),
  ``uncertainty`` (a sphere of radius 2 sigma of the predicted position: the learner's position uncertainty is
  isotropic, so its ellipsoid is a sphere), ``labels`` (part id, model kind and actions), ``observed`` (the marker
  poses observed in that step, as grey cubes beside the predicted axes);
- ``body_scheme/poses`` (geometry_msgs/PoseArray): the predicted poses in part-id order;
- ``/tf`` (tf2_msgs/TFMessage): ``<frame_id>`` -> ``<tf_prefix>marker_<id>`` for every predicted part;
- ``body_scheme/robot_description`` (std_msgs/String, transient local): the learned URDF
  (:func:`body_scheme_core.prediction.learned_body.learned_urdf`).
"""

from __future__ import annotations

import math

from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, PoseArray, TransformStamped
from std_msgs.msg import ColorRGBA, Header
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from body_scheme_core.prediction import marker_link

from . import conversions

__all__ = ["EDGE_COLOURS", "edge_state", "markers_msg", "pose_array_msg", "tf_msg"]

#: Colour (r, g, b) of a tree edge by state.
EDGE_COLOURS = {"valid": (0.1, 0.8, 0.1), "mismatch": (0.9, 0.1, 0.1), "invalid": (1.0, 0.55, 0.0),
                "replaced": (0.1, 0.4, 1.0), "reinstated": (0.7, 0.2, 0.9)}
_AXIS_COLOURS = ((1.0, 0.0, 0.0), (0.0, 0.8, 0.0), (0.0, 0.3, 1.0))
_AXIS_LENGTH = 0.08
_LIFETIME = Duration(sec=0)  # until replaced


def edge_state(edge, recent_event=None):
    """An edge's display state: a recent ``model_replaced`` / ``model_reinstated`` event wins, then mismatch,
    invalid, valid."""
    if recent_event == "model_replaced":
        return "replaced"
    if recent_event == "model_reinstated":
        return "reinstated"
    if edge["in_mismatch"]:
        return "mismatch"
    return "valid" if edge["valid"] else "invalid"


def _header(stamp, frame_id):
    return Header(stamp=conversions.stamp_from_seconds(stamp), frame_id=frame_id)


def _colour(rgb, alpha=1.0):
    return ColorRGBA(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(alpha))


def _point(p):
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _marker(header, ns, marker_id, kind):
    marker = Marker(header=header, ns=ns, id=int(marker_id), type=kind, action=Marker.ADD, lifetime=_LIFETIME)
    marker.pose.orientation.w = 1.0
    return marker


def markers_msg(stamp, frame_id, poses, std, edges, observed=None, recent_events=None):
    """The MarkerArray of one prediction (see the module docstring).

    Parameters
    ----------
    stamp : float
    frame_id : str
    poses : dict of int to ndarray, shape (4, 4)
        Predicted ``frame2part``.
    std : dict of int to array-like, shape (2,), or None
        Translational (m) and rotational (rad) std per part.
    edges : list of dict
        ``BodySchemeLearner.edge_status()``.
    observed : dict of int to ndarray, shape (4, 4), optional
        The poses observed in the same step.
    recent_events : dict of int to str, optional
        Child part -> kind of a recent replacement or reinstatement of its edge.
    """
    header = _header(stamp, frame_id)
    array = MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])
    axes = _marker(header, "axes", 0, Marker.LINE_LIST)
    axes.scale.x = 0.006
    for part in sorted(poses):
        T = poses[part]
        for k, rgb in enumerate(_AXIS_COLOURS):
            axes.points += [_point(T[:3, 3]), _point(T[:3, 3] + _AXIS_LENGTH * T[:3, k])]
            axes.colors += [_colour(rgb), _colour(rgb)]
    array.markers.append(axes)
    into = {e["child"]: e for e in edges}
    for k, e in enumerate(edges):
        if e["parent"] not in poses or e["child"] not in poses:
            continue
        line = _marker(header, "edges", k, Marker.LINE_STRIP)
        line.scale.x = 0.012
        line.color = _colour(EDGE_COLOURS[edge_state(e, (recent_events or {}).get(e["child"]))])
        line.points = [_point(poses[e["parent"]][:3, 3]), _point(poses[e["child"]][:3, 3])]
        array.markers.append(line)
    for part in sorted(poses):
        position = poses[part][:3, 3]
        if std is not None and part in std:
            sphere = _marker(header, "uncertainty", part, Marker.SPHERE)
            sphere.pose.position = _point(position)
            # 2 sigma per axis, as predicted_poses' covariance says (diag std**2 / 3: std is the 3D RMS)
            diameter = 4.0 * float(std[part][0]) / math.sqrt(3.0) if math.isfinite(float(std[part][0])) else 0.0
            sphere.scale.x = sphere.scale.y = sphere.scale.z = max(diameter, 1e-4)
            sphere.color = _colour((0.3, 0.6, 1.0), 0.25)
            array.markers.append(sphere)
        label = _marker(header, "labels", part, Marker.TEXT_VIEW_FACING)
        label.pose.position = _point(position + [0.0, 0.0, 0.05])
        label.scale.z = 0.035
        label.color = _colour((1.0, 1.0, 1.0))
        edge = into.get(part)
        label.text = f"{part}" if edge is None else f"{part}: {edge['kind']} a{','.join(map(str, edge['actions']))}"
        array.markers.append(label)
    for part, T in sorted((observed or {}).items()):
        cube = _marker(header, "observed", part, Marker.CUBE)
        cube.pose = conversions.pose_msg_from_transform(T)
        cube.scale.x = cube.scale.y = 0.05
        cube.scale.z = 0.005
        cube.color = _colour((0.7, 0.7, 0.7), 0.8)
        array.markers.append(cube)
    return array


def pose_array_msg(stamp, frame_id, poses):
    """PoseArray of the predicted poses, in part-id order."""
    header = _header(stamp, frame_id)
    return PoseArray(header=header, poses=[conversions.pose_msg_from_transform(poses[p]) for p in sorted(poses)])


def tf_msg(stamp, frame_id, poses, prefix=""):
    """TFMessage ``frame_id -> <prefix>marker_<id>`` for every predicted part."""
    out = TFMessage()
    for part in sorted(poses):
        pose = conversions.pose_msg_from_transform(poses[part])
        transform = TransformStamped()
        transform.header = _header(stamp, frame_id)
        transform.child_frame_id = marker_link(prefix, part)  # the learned URDF's marker link
        transform.transform.translation.x = pose.position.x
        transform.transform.translation.y = pose.position.y
        transform.transform.translation.z = pose.position.z
        transform.transform.rotation = pose.orientation
        out.transforms.append(transform)
    return out
