"""Motor babbling (the paper's Sec. IV-B): random commands within the joint limits that a screen accepts.

:func:`babble` is the one babbling loop. What makes a command acceptable depends on the backend, so it is a *screen*:
a function of a batch of candidate commands that gives, per candidate, the reason it is rejected (or ``None``). The
synthetic world screens kinematically (:func:`above_ground_screen`, a cheap stand-in for the paper's collision
check); the pybullet simulator executes each candidate and rejects collisions and hidden markers
(:func:`body_scheme_sim.babbling.babbling_screen`). Candidates are drawn in batches from one stream, so the accepted
commands do not depend on the batch size, and no candidate is drawn after the last one needed.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..errors import BabblingError, InvalidInputError
from .body import Body

__all__ = ["babble", "above_ground_screen", "DEFAULT_DRAWS_PER_ACTION"]

#: Default budget of candidates per requested command.
DEFAULT_DRAWS_PER_ACTION = 200


def babble(robot, n, rng, screen=None, max_draws=None, above_ground=None, ground_z=0.0):
    """Draw ``n`` babbling commands uniformly within the joint limits, keeping those the screen accepts.

    Parameters
    ----------
    robot : KinematicTree, Body or body_scheme_sim.world.SimWorld
        Anything with ``action_lower``, ``action_upper`` and ``n_actions`` (a body's nominal tree is used).
    n : int
        Number of commands.
    rng : numpy.random.Generator or int or None
    screen : callable or None
        ``screen(A)`` for candidates ``A`` (k, m) returns k rejection reasons (str), ``None`` where a candidate is
        accepted; ``None`` accepts everything.
    max_draws : int or None
        Candidates to draw in total before giving up; ``None``: ``DEFAULT_DRAWS_PER_ACTION * max(n, 1)``.
    above_ground, ground_z
        Shorthand for ``screen=above_ground_screen(robot, above_ground, ground_z)`` (``None`` or ``False``: no
        screen).

    Returns
    -------
    A : ndarray, shape (n, m)

    Raises
    ------
    BabblingError
        If fewer than ``n`` candidates were accepted within ``max_draws``; the message counts the rejections by reason.
    """
    robot = robot.tree if isinstance(robot, Body) else robot
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise InvalidInputError(f"n must be an integer >= 0, got {n!r}")
    if above_ground is not None and above_ground is not False:
        if screen is not None:
            raise InvalidInputError("give either screen or above_ground, not both")
        screen = above_ground_screen(robot, above_ground, ground_z)
    max_draws = DEFAULT_DRAWS_PER_ACTION * max(int(n), 1) if max_draws is None else int(max_draws)
    rng = np.random.default_rng(rng)
    lower, upper = robot.action_lower, robot.action_upper
    accepted, n_accepted, drawn, rejected = [], 0, 0, Counter()
    while n_accepted < n:
        if drawn >= max_draws:
            reasons = ", ".join(f"{count} {reason}" for reason, count in rejected.most_common())
            raise BabblingError(f"babbling found {n_accepted} of {n} valid configurations in {drawn} tries "
                                f"(rejected: {reasons or 'none'})")
        # Exactly as many candidates as are still needed: the stream is never drawn beyond the last accepted one
        # (a world that babbles one command at a time keeps its stream), and a costly screen sees no extras.
        batch = min(n - n_accepted, max_draws - drawn)
        A = rng.uniform(lower, upper, size=(batch, robot.n_actions))
        drawn += batch
        if screen is not None:
            reasons = list(screen(A))
            rejected.update(reason for reason in reasons if reason is not None)
            A = A[[reason is None for reason in reasons]]
        accepted.append(A)
        n_accepted += A.shape[0]
    return np.concatenate(accepted, axis=0)[:n] if accepted else np.zeros((0, robot.n_actions))


def above_ground_screen(tree, marker_ids=True, ground_z=0.0):
    """A screen rejecting commands that put a marker at or below ``z = ground_z`` in the root frame.

    Parameters
    ----------
    tree : KinematicTree or Body
    marker_ids : iterable of int or True
        The markers to keep up (``True``: all).
    ground_z : float
    """
    tree = tree.tree if isinstance(tree, Body) else tree
    ids = [tree.marker(i).id for i in (tree.marker_ids if marker_ids is True else marker_ids)]
    reason = f"a marker of {ids} at or below z = {ground_z}"

    def screen(A):
        poses = tree.marker_poses(A)
        ok = np.all([poses[i][:, 2, 3] > ground_z for i in ids], axis=0) if ids else np.ones(len(A), dtype=bool)
        return [None if good else reason for good in ok]

    return screen
