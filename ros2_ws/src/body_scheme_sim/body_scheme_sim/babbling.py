"""Motor babbling in the simulator (the paper's Sec. IV-B): random commands the robot can safely execute and see.

Each candidate is drawn uniformly within the joint limits and executed in the world (as it truly is, faults
included), then rejected if the robot collides with itself or the ground, or if a marker of interest is not
visible. Afterwards the world executes its last command again, so it is left as it was.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from body_scheme_core.errors import InvalidInputError

from .errors import BabblingError

__all__ = ["babble", "DEFAULT_MAX_TRIES"]

#: Default budget of candidates per requested action.
DEFAULT_MAX_TRIES = 200


def babble(world, n, rng, markers_of_interest=None, max_tries=None):
    """Draw ``n`` valid babbling commands (the argument order of :func:`body_scheme_core.world.babble`).

    Parameters
    ----------
    world : SimWorld
    n : int
        Number of actions.
    rng : numpy.random.Generator or int or None
    markers_of_interest : iterable of int or None
        Markers that must all be visible in an accepted configuration; ``None`` or empty: no visibility check.
    max_tries : int or None
        Candidates to draw in total before giving up; ``None``: ``DEFAULT_MAX_TRIES * max(n, 1)``.

    Returns
    -------
    actions : ndarray, shape (n, m)

    Raises
    ------
    BabblingError
        If fewer than ``n`` candidates were valid within ``max_tries``; the message counts the rejections by reason.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise InvalidInputError(f"n must be an integer >= 0, got {n!r}")
    required = set() if markers_of_interest is None else {int(i) for i in markers_of_interest}
    unknown = sorted(required - set(world.marker_ids))
    if unknown:
        raise InvalidInputError(f"markers_of_interest {unknown} are not markers of the robot {list(world.marker_ids)}")
    max_tries = DEFAULT_MAX_TRIES * max(int(n), 1) if max_tries is None else int(max_tries)
    rng = np.random.default_rng(rng)
    lower, upper = world.action_lower, world.action_upper
    accepted, rejected, tries = [], Counter(), 0
    saved = world.last_command
    try:
        while len(accepted) < n:
            if tries >= max_tries:
                reasons = ", ".join(f"{count} {reason}" for reason, count in rejected.most_common())
                raise BabblingError(
                    f"babbling found {len(accepted)} of {n} valid configurations in {tries} tries "
                    f"(rejected: {reasons or 'none'}); relax markers_of_interest {sorted(required)}, move the camera "
                    f"or raise max_tries")
            candidate = rng.uniform(lower, upper)
            tries += 1
            world.execute(candidate)
            if world.in_collision():
                rejected["in collision"] += 1
            elif required - world.visible_marker_ids():
                rejected["with markers of interest hidden"] += 1
            else:
                accepted.append(candidate)
    finally:
        world.execute(saved)
    return np.array(accepted).reshape(n, world.n_actions)
