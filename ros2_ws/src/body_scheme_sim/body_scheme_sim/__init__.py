"""The pybullet arm seen by a fixed camera: a rendering and physics backend of :mod:`body_scheme_core.world`.

Robots are :class:`~body_scheme_core.world.KinematicTree`\\ s with markers, faults are the core's
:class:`~body_scheme_core.world.Fault` (``SimWorld.apply``), babbling is the core's loop with this world's screen
(:func:`babbling_screen`), and sessions record the core's protocols. No ROS dependency (sim_node lives in
body_scheme_nodes). See docs/sim.md.
"""

from .babbling import babbling_screen
from .camera import Camera, look_at
from .robots import load_robot, robot_names
from .world import SimWorld

__all__ = ["SimWorld", "Camera", "look_at", "babbling_screen", "load_robot", "robot_names"]
