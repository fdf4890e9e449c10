"""The pybullet arm seen by a fixed camera: a rendering and physics backend of :mod:`body_scheme_core.world`.

Robots are :class:`~body_scheme_core.world.KinematicTree`\\ s with markers, faults are the core's
:class:`~body_scheme_core.world.Fault` (``SimWorld.apply``), babbling is the core's loop with this world's screen
(:func:`babbling_screen`), and sessions record the core's protocols. No ROS dependency (sim_node lives in
body_scheme_nodes). See docs/sim.md.

The names below are imported when first used: the robot files (:mod:`.robots`) and the pinhole camera
(:mod:`.camera`) load without pybullet, so a real robot's nodes that read a robot description or a recorded
session's camera do not start a physics engine.
"""

import importlib

__all__ = ["SimWorld", "Camera", "look_at", "babbling_screen", "load_robot", "robot_names"]

_HOMES = {"SimWorld": ".world", "Camera": ".camera", "look_at": ".camera", "babbling_screen": ".babbling",
          "load_robot": ".robots", "robot_names": ".robots"}


def __getattr__(name):
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_HOMES[name], __name__), name)


def __dir__():
    return sorted(list(globals()) + __all__)
