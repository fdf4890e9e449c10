"""The simulator's babbling screen (the paper's Sec. IV-B): commands the robot can safely execute and see; and the
collision screen of a real robot's moves (:class:`CollisionScreen`).

:func:`babbling_screen` gives :func:`body_scheme_core.world.babble` (the one babbling loop) a screen that executes
each candidate in the world (as it truly is, faults included) and rejects it if the robot collides with itself or the
ground, or if a marker of interest is not visible. Afterwards the world executes its last command again, so it is left
as it was::

    actions = babble(world, n, rng, screen=babbling_screen(world, markers_of_interest=[6, 7]))
"""

from __future__ import annotations

import numpy as np

from body_scheme_core.errors import InvalidInputError

__all__ = ["babbling_screen", "CollisionScreen"]


def babbling_screen(world, markers_of_interest=None):
    """A screen for :func:`body_scheme_core.world.babble` on a :class:`~body_scheme_sim.world.SimWorld`.

    Parameters
    ----------
    world : SimWorld
    markers_of_interest : iterable of int or None
        Markers that must all be visible in an accepted configuration; ``None`` or empty: no visibility check.

    Raises
    ------
    InvalidInputError
        If a marker of interest is not a marker of the robot.
    """
    required = set() if markers_of_interest is None else {int(i) for i in markers_of_interest}
    unknown = sorted(required - set(world.marker_ids))
    if unknown:
        raise InvalidInputError(f"markers_of_interest {unknown} are not markers of the robot {list(world.marker_ids)}")

    def screen(A):
        saved, reasons = world.last_command, []
        try:
            for candidate in A:
                world.execute(candidate)
                if world.in_collision():
                    reasons.append("in collision")
                elif required - world.visible_marker_ids():
                    reasons.append("with markers of interest hidden")
                else:
                    reasons.append(None)
        finally:
            world.execute(saved)
        return reasons

    return screen


class CollisionScreen:
    """Self-collision and ground checks of a real robot's postures, from its URDF, in a pybullet DIRECT world of
    their own (no rendering, no markers).

    Parameters
    ----------
    robot : str or os.PathLike
        Shipped robot name or URDF path.
    package_path : iterable of str
        See :class:`~body_scheme_sim.world.SimWorld`.

    Raises
    ------
    InvalidInputError
        If a mesh of the URDF is not found: without it the screen would pass postures in which that part collides.
    """

    def __init__(self, robot, package_path=()):
        from .world import SimWorld

        self.world = SimWorld(robot, markers=(), marker_texture=False, package_path=package_path)
        missing = self.world.missing_meshes
        if missing:
            self.world.close()
            raise InvalidInputError(
                f"the collision screen needs the robot's meshes: {len(missing)} not found (first: {missing[0]}); "
                "give their packages' parent directories in package_path, or switch the screen off "
                "(collision_check: false)")

    @property
    def ignored_pairs(self):
        """Link pairs not checked: they touch at the reference posture or in almost every posture
        (:attr:`~body_scheme_sim.world.SimWorld.ignored_collision_pairs`)."""
        return self.world.ignored_collision_pairs

    def collides(self, postures):
        """Whether the robot hits itself or the ground in any of ``postures`` (shape (k, m) or (m,): joint positions,
        e.g. :func:`~body_scheme_core.control.motion.path_samples` of a move)."""
        for posture in np.atleast_2d(np.asarray(postures, dtype=float)):
            self.world.execute(posture)
            if self.world.in_collision():
                return True
        return False

    def close(self):
        self.world.close()
