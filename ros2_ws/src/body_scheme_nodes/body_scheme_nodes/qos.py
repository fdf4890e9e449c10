"""The QoS profiles the nodes share: one place for what "latched" and "recent events" mean."""

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""The latest message, kept for late joiners (structure, snapshot, robot_description, bag_replay/done)."""

RECENT_EVENTS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""scheme_node's events: the latest 100 kept, so a follower that joins late (or whose publisher matched it a moment
after the graph showed it) still sees the decisions it came for. A volatile subscriber is served too."""
