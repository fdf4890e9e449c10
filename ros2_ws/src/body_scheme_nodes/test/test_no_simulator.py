"""A real robot's processes start no simulator: scheme_node, tracker_node, control_node and babble_node driving an arm
(``collision_check: false``; the collision screen is pybullet's), bag I/O and the replays import neither pybullet
nor the simulator's world, in a fresh interpreter with the real rclpy."""

import json
import os
import subprocess
import sys

SCRIPT = r"""
import json, sys
import rclpy

from body_scheme_nodes import bag_io, bag_replay, offline_replay  # noqa: F401
from body_scheme_nodes.babble_node import BabbleNode
from body_scheme_nodes.control_node import ControlNode
from body_scheme_nodes.scheme_node import SchemeNode
from body_scheme_nodes.tracker_node import TrackerNode

ARGS = ["scheme_node:part_ids:=[1, 2, 3]", "scheme_node:joint_names:=[j1, j2]",
        "control_node:robot:=powercube_6dof", "control_node:collision_check:=false", "control_node:execute:=true",
        "babble_node:robot:=powercube_6dof", "babble_node:collision_check:=false",
        "babble_node:preflight_skip:=[controller, camera, camera_info, markers]"]
rclpy.init(args=["--ros-args"] + [item for arg in ARGS for item in ("-p", arg)], domain_id=int(sys.argv[1]))
nodes = [SchemeNode(), TrackerNode(), ControlNode(), BabbleNode()]
loaded = sorted(name for name in sys.modules if name.split(".")[0] in ("pybullet", "pybullet_data")
                or name in ("body_scheme_sim.world", "body_scheme_sim.babbling"))
for node in nodes:
    node.destroy_node()
rclpy.shutdown()
print(json.dumps(loaded))
"""


def test_a_real_robots_nodes_load_no_simulator():
    done = subprocess.run([sys.executable, "-c", SCRIPT, "187"], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []
