"""``other_stacks``: write a simulated babbling session as other ROS stacks record it, with its source map.

The recordings users already have (docs/your-data.md), made by our own simulator, so that the importer
(:mod:`body_scheme_nodes.sources`) is tested on those stacks' message layouts:

=============  ==============================================================================================
layout         what is written
=============  ==============================================================================================
aruco_ros      ``/tf`` (``tf2_msgs/TFMessage``): ``camera_color_optical_frame`` -> ``marker_<id>`` per detection
apriltag_ros   ``/tf``: ``camera`` -> ``tag36h11:<id>`` per detection
mocap          ``geometry_msgs/PoseStamped`` per rigid body on ``/mocap/body_<id>/pose``, frame ``world``
points         ``geometry_msgs/PointStamped`` per reflector, three per body (:data:`REFLECTORS`) on
               ``/tracker/body_<id>/<a|b|c>``, frame ``tracker`` (a laser tracker or single mocap markers)
trajectory     ``trajectory_msgs/JointTrajectory`` goals on ``/arm_controller/joint_trajectory`` (instead of
               measured joint states) and ``/tf`` as apriltag_ros
csv, jsonl     a table, one row per pose (the module docstring of body_scheme_nodes.sources has the format)
=============  ==============================================================================================

Bags hold ``/joint_states`` (``sensor_msgs/JointState``) at 50 Hz with one more joint than the robot's (a gripper,
which the map leaves out): each pose of the session is reached in ``MOVE`` s and held for ``HOLD`` s; detections
come at 15 Hz (30 Hz for motion capture) while the arm holds, and during a move they still show the pose the arm left
(a stale tracker), which the importer must not take as the new pose.

Example::

    python -m body_scheme_apps.other_stacks --layout apriltag_ros --out /tmp/tags
    python -m body_scheme_apps.replay_offline /tmp/tags --source-map /tmp/tags.map.yaml --params /tmp/tags.params.yaml
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
import yaml
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, PointStamped, PoseStamped, TransformStamped
from rosbags.rosbag2 import StoragePlugin, Writer
from sensor_msgs.msg import JointState
from tf2_msgs.msg import TFMessage
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.transforms import pose_from_transform
from body_scheme_core.world import arm_4dof, make_session, planar_2dof, powercube_6dof
from body_scheme_nodes import conversions
from body_scheme_nodes.bag_io import cdr_bytes, name_the_distro, typestore

from .entry import command

__all__ = ["LAYOUTS", "write_layout", "main"]

LAYOUTS = ("aruco_ros", "apriltag_ros", "mocap", "points", "trajectory", "csv", "jsonl")
#: ``points``: three reflectors per body, at these coordinates in the body's marker frame (m).
REFLECTORS = {"a": [0.0, 0.0, 0.0], "b": [0.06, 0.0, 0.0], "c": [0.0, 0.04, 0.02]}
MOVE, HOLD = 0.4, 0.6  # s per pose
JOINT_RATE, TAG_RATE, MOCAP_RATE = 50.0, 15.0, 30.0  # Hz
GRIPPER = "gripper_finger_joint"
ROBOTS = {"planar_2dof": planar_2dof, "arm_4dof": arm_4dof, "powercube_6dof": powercube_6dof}
_TF_FRAMES = {"aruco_ros": ("camera_color_optical_frame", "marker_{}"), "apriltag_ros": ("camera", "tag36h11:{}"),
              "trajectory": ("camera", "tag36h11:{}")}
_TYPES = {"/joint_states": "sensor_msgs/msg/JointState", "/tf": "tf2_msgs/msg/TFMessage",
          "/arm_controller/joint_trajectory": "trajectory_msgs/msg/JointTrajectory"}


def write_layout(session, path, layout):
    """Write ``session`` at ``path`` in ``layout``, its source map at ``<path>.map.yaml`` and scheme_node's
    parameters for it (the robot's joints, parts and limits, the map's frame) at ``<path>.params.yaml``.

    Returns
    -------
    recording, source_map, params : pathlib.Path
        The bag directory or table file, the map and the parameter file.
    """
    if layout not in LAYOUTS:
        raise BodySchemeError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    path = pathlib.Path(path)
    names = list(session.joint_names)
    source_map = {"joints": {"names": names, "topic": "/joint_states", "still_tolerance": 0.002,
                             "still_time": 0.3, "settle_time": 0.1}}
    if layout in ("csv", "jsonl"):
        path = path.with_suffix(f".{layout}")
        _write_table(session, path, layout)
        source_map = {"joints": {"names": names}, "frame": session.frame_id}  # pose columns need no bodies entry
    else:
        _write_bag(session, path, layout, source_map)
    map_path = path.parent / f"{path.name}.map.yaml"
    map_path.write_text(f"# source map of {path.name} ({layout} layout), python -m body_scheme_apps.other_stacks\n"
                        + yaml.safe_dump(source_map, sort_keys=False))
    tree = session.tree
    params = {"part_ids": [int(i) for i in session.marker_ids], "joint_names": names,
              "action_lower": [float(v) for v in tree.action_lower],
              "action_upper": [float(v) for v in tree.action_upper], "frame_id": source_map["frame"]}
    params_path = path.parent / f"{path.name}.params.yaml"
    params_path.write_text(f"# scheme_node parameters for {path.name}\n"
                           + yaml.safe_dump({"/**": {"ros__parameters": params}}, sort_keys=False))
    return path, map_path, params_path


def _write_table(session, path, layout):
    names, rows = list(session.joint_names), []
    for k in range(session.n_steps):
        poses = {str(i): [*map(float, p), *map(float, q)]
                 for i, (p, q) in ((i, pose_from_transform(T)) for i, T in session.observations[k].items())}
        joints = dict(zip(names, map(float, session.actions[k]), strict=True))
        rows.append({"stamp": float(k), "joints": joints, "poses": poses})
    if layout == "jsonl":
        path.write_text("".join(json.dumps(row) + "\n" for row in rows))
        return
    columns = [f"{i}.{axis}" for i in session.marker_ids for axis in ("x", "y", "z", "qx", "qy", "qz", "qw")]
    lines = [",".join(["stamp", *names, *columns])]
    for row in rows:
        cells = [str(row["stamp"]), *(repr(row["joints"][n]) for n in names)]
        for i in session.marker_ids:
            cells += [repr(v) for v in row["poses"][str(i)]] if str(i) in row["poses"] else [""] * 7
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def _write_bag(session, path, layout, source_map):
    store = typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        topics = dict(_TYPES)
        if layout == "mocap":
            topics.update({f"/mocap/body_{i}/pose": "geometry_msgs/msg/PoseStamped" for i in session.marker_ids})
            source_map["frame"] = "world"
            source_map["bodies"] = {int(i): {"topic": f"/mocap/body_{i}/pose"} for i in session.marker_ids}
        elif layout == "points":
            source_map["frame"] = "tracker"
            source_map["bodies"] = {int(i): {"points": {f"/tracker/body_{i}/{label}": xyz
                                                        for label, xyz in REFLECTORS.items()}}
                                    for i in session.marker_ids}
            topics.update({topic: "geometry_msgs/msg/PointStamped"
                           for body in source_map["bodies"].values() for topic in body["points"]})
        else:
            parent, child = _TF_FRAMES[layout]
            source_map["frame"] = parent
            source_map["bodies"] = {int(i): {"tf": child.format(i)} for i in session.marker_ids}
        if layout == "trajectory":
            source_map["joints"]["topic"] = "/arm_controller/joint_trajectory"
        connections = {topic: writer.add_connection(topic, msgtype, typestore=store)
                       for topic, msgtype in topics.items()}

        def write(topic, t, msg):
            writer.write(connections[topic], int(round(t * 1e9)), cdr_bytes(msg, topics[topic], store))

        for t, msg in _messages(session, layout, source_map):
            topic = msg.pop("topic")
            write(topic, t, msg["msg"])
    finally:
        writer.close()
    name_the_distro(path)


def _messages(session, layout, source_map):
    """``(t, {"topic", "msg"})`` in time order."""
    names, frame = list(session.joint_names), source_map["frame"]
    period = MOVE + HOLD
    out = []
    previous = session.actions[0]
    for k in range(session.n_steps):
        start = 1.0 + k * period
        target = session.actions[k]
        if layout == "trajectory":
            goal = JointTrajectory(joint_names=names, points=[JointTrajectoryPoint(
                positions=[float(v) for v in target], time_from_start=Duration(sec=0, nanosec=int(MOVE * 1e9)))])
            goal.header.stamp = conversions.stamp_from_seconds(start)
            out.append((start, {"topic": "/arm_controller/joint_trajectory", "msg": goal}))
        for t in np.arange(start, start + period, 1.0 / JOINT_RATE):
            s = min((t - start) / MOVE, 1.0)
            q = (1 - s) * previous + s * target
            msg = JointState(name=[*names, GRIPPER], position=[*map(float, q), 0.0])
            msg.header.stamp = conversions.stamp_from_seconds(t)
            out.append((t, {"topic": "/joint_states", "msg": msg}))
        rate = MOCAP_RATE if layout in ("mocap", "points") else TAG_RATE
        for t in np.arange(start + 0.5 / rate, start + period, 1.0 / rate):
            shown = session.observations[k] if t >= start + MOVE else session.observations[max(k - 1, 0)]
            out += [(t, item) for item in _detections(shown, layout, frame, t, source_map)]
        previous = target
    out.sort(key=lambda item: item[0])
    return out


def _detections(poses, layout, frame, t, source_map):
    stamp = conversions.stamp_from_seconds(t)
    if layout == "mocap":
        items = []
        for i, T in poses.items():
            msg = PoseStamped(pose=conversions.pose_msg_from_transform(T))
            msg.header.stamp, msg.header.frame_id = stamp, frame
            items.append({"topic": source_map["bodies"][int(i)]["topic"], "msg": msg})
        return items
    if layout == "points":
        items = []
        for i, T in poses.items():
            for topic, xyz in source_map["bodies"][int(i)]["points"].items():
                x, y, z = T[:3, :3] @ np.asarray(xyz) + T[:3, 3]
                msg = PointStamped(point=Point(x=float(x), y=float(y), z=float(z)))
                msg.header.stamp, msg.header.frame_id = stamp, frame
                items.append({"topic": topic, "msg": msg})
        return items
    transforms = []
    for i, T in poses.items():
        pose = conversions.pose_msg_from_transform(T)
        transform = TransformStamped(child_frame_id=source_map["bodies"][int(i)]["tf"])
        transform.header.stamp, transform.header.frame_id = stamp, frame
        transform.transform.translation.x, transform.transform.translation.y, transform.transform.translation.z = (
            pose.position.x, pose.position.y, pose.position.z)
        transform.transform.rotation = pose.orientation
        transforms.append(transform)
    return [{"topic": "/tf", "msg": TFMessage(transforms=transforms)}] if transforms else []


def parser():
    p = argparse.ArgumentParser(prog="other_stacks", description=__doc__.split("\n\n")[0])
    p.add_argument("--layout", choices=LAYOUTS, required=True)
    p.add_argument("--robot", default="planar_2dof", choices=sorted(ROBOTS))
    p.add_argument("--steps", type=int, default=80)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sigma-trans", type=float, default=0.01, help="m (3D RMS)")
    p.add_argument("--sigma-rot", type=float, default=3.0, help="deg")
    p.add_argument("--out", required=True, help="bag directory, or table path (suffix set by the layout)")
    return p


@command
def main(argv=None):
    args = parser().parse_args(argv)
    try:
        session = make_session(ROBOTS[args.robot](), args.steps, args.seed, sigma_trans=args.sigma_trans,
                               sigma_rot=np.radians(args.sigma_rot))
        recording, source_map, params = write_layout(session, args.out, args.layout)
    except (BodySchemeError, OSError) as error:
        print(f"other_stacks: {error}", file=sys.stderr)
        return 2
    print(f"wrote {recording}, its source map {source_map} and scheme_node's parameters {params}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
