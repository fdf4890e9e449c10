"""The simulator's babbling screen (the paper's Sec. IV-B): commands the robot can safely execute and see.

:func:`babbling_screen` gives :func:`body_scheme_core.world.babble` (the one babbling loop) a screen that executes
each candidate in the world (as it truly is, faults included) and rejects it if the robot collides with itself or the
ground, or if a marker of interest is not visible. Afterwards the world executes its last command again, so it is left
as it was::

    actions = babble(world, n, rng, screen=babbling_screen(world, markers_of_interest=[6, 7]))
"""

from __future__ import annotations

from body_scheme_core.errors import InvalidInputError

__all__ = ["babbling_screen"]


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
