"""The topics of a recorded babbling session (rosbag2), in one place without ROS imports.

Written by ``body_scheme_sim.bags`` (no rclpy needed to record) and read by ``body_scheme_nodes.bag_reader``.
"""

__all__ = ["SESSION_TOPICS"]

#: Topic -> message type of every topic a session bag may hold.
SESSION_TOPICS = {
    "/session/info": "std_msgs/msg/String",
    "/joint_commands": "sensor_msgs/msg/JointState",
    "/observations": "body_scheme_msgs/msg/MarkerPoses",
    "/ground_truth/marker_poses": "body_scheme_msgs/msg/MarkerPoses",
    "/ground_truth/joint_states": "sensor_msgs/msg/JointState",
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
}
