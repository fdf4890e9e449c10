"""The body-scheme nodes for a real robot and camera (ROS 2 Jazzy from apt): tracker_node, scheme_node, control_node.

    ros2 launch body_scheme_nodes body_scheme.launch.py \\
        scheme_params:=my_robot_scheme.yaml tracker_params:=my_camera_tracker.yaml

Your driver publishes ``camera/image_raw`` + ``camera/camera_info`` and executes ``joint_commands``
(sensor_msgs/JointState). Start from copies of the shipped parameter files (``share/body_scheme_nodes/config/``):
``scheme_node.yaml`` names your parts (marker ids), joints and their limits; ``tracker_node.yaml`` your marker sizes
(or ``markers_path``). docs/nodes.md lists every topic, service and parameter.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory("body_scheme_nodes"), "config")
    return LaunchDescription([
        DeclareLaunchArgument("tracker_params", default_value=os.path.join(config, "tracker_node.yaml")),
        DeclareLaunchArgument("scheme_params", default_value=os.path.join(config, "scheme_node.yaml")),
        DeclareLaunchArgument("control_params", default_value=os.path.join(config, "control_node.yaml")),
        Node(package="body_scheme_nodes", executable="tracker_node", output="screen",
             parameters=[LaunchConfiguration("tracker_params")]),
        Node(package="body_scheme_nodes", executable="scheme_node", output="screen",
             parameters=[LaunchConfiguration("scheme_params")]),
        Node(package="body_scheme_nodes", executable="control_node", output="screen",
             parameters=[LaunchConfiguration("control_params")]),
    ])
