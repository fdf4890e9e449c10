"""The live graph for ROS 2 Jazzy from apt: sim_node -> tracker_node -> scheme_node -> control_node.

    ros2 launch body_scheme_apps live_graph.launch.py

The same graph as ``make demo`` (``body_scheme_apps.live_demo``, which starts these nodes as processes because the
``launch`` package is not on PyPI): the simulated ``powercube_6dof`` babbles 300 commands from rendered camera
images, its end-effector joint is blocked at command 120 and repaired at 220, then the sim executes whatever arrives
on ``joint_commands``, e.g. control_node's answers to ``ik_target``. Each node reads its shipped parameter YAML; the
overrides below are the demo's. Watch ``body_scheme/events`` and ``/diagnostics``; send targets with
``ros2 topic pub --once /ik_target/point geometry_msgs/msg/PointStamped "{header: {frame_id: camera}, point: {x: 0.2,
y: -0.2, z: 0.9}}"``.
"""

import math
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node


def generate_launch_description():
    sim_share = get_package_share_directory("body_scheme_sim")
    nodes_share = get_package_share_directory("body_scheme_nodes")
    markers = os.path.join(sim_share, "robots", "powercube_6dof.markers.yaml")

    def config(share, node):
        return os.path.join(share, "config", node + ".yaml")

    return LaunchDescription([
        # The learner's noise sigmas match the tracker's accuracy on the sim's images (live_demo.RENDERED_SIGMA_*).
        Node(package="body_scheme_nodes", executable="scheme_node", output="screen",
             parameters=[config(nodes_share, "scheme_node"),
                         {"learner.sigma_trans": 0.01, "learner.sigma_rot": math.radians(5.0)}]),
        Node(package="body_scheme_nodes", executable="tracker_node", output="screen",
             parameters=[config(nodes_share, "tracker_node"),
                         {"markers_path": markers, "image_reliability": "reliable"}]),
        Node(package="body_scheme_nodes", executable="control_node", output="screen",
             parameters=[config(nodes_share, "control_node")]),
        Node(package="body_scheme_nodes", executable="sim_node", output="screen",
             parameters=[config(nodes_share, "sim_node"),
                         {"babbling": True, "babbling_period": 0.05, "babbling_steps": 300,
                          "wait_for_subscribers": 2, "max_in_flight": 10, "markers_of_interest": [6, 7],
                          "fault_schedule": ["120:block_joint:5:0.8", "220:repair"]}]),
    ])
