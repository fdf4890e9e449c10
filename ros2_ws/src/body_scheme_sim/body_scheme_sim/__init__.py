"""pybullet arm simulator seen by a fixed camera (issue 4): robots, rendering, babbling, faults, ground truth.

The library (everything but :mod:`body_scheme_nodes.sim_node`) has no ROS dependency. See docs/sim.md.
"""

from .babbling import babbling_screen
from .camera import Camera, look_at
from .faults import ScheduledFault, apply_fault, parse_fault_schedule
from .robots import load_robot, robot_names
from .world import SimWorld

__all__ = ["SimWorld", "Camera", "look_at", "babbling_screen", "load_robot", "robot_names", "parse_fault_schedule",
           "ScheduledFault", "apply_fault"]
