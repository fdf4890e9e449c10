"""Motor babbling (the paper's Sec. IV-B): random commands within the joint limits, screened cheaply.
"""

from __future__ import annotations

import numpy as np

from ..errors import BodySchemeError, InvalidInputError
from .body import Body

__all__ = ["babble"]


def babble(tree, n, rng, above_ground=None, ground_z=0.0, max_draws=100_000):
    """Random motor babbling: actions uniform within the joint limits.

    Parameters
    ----------
    tree : KinematicTree or Body
        Nominal robot used to screen the commands (the body's tree, blocking ignored).
    n : int
        Number of action vectors.
    rng : numpy.random.Generator or int
    above_ground : iterable of int, bool or None
        Marker ids (``True``: all markers) that must stay above ``z = ground_z`` in the root frame, a cheap
        stand-in for the paper's collision check; ``None`` or ``False`` accepts everything.
    ground_z : float
    max_draws : int
        Give up (``BodySchemeError``) after drawing this many candidates.

    Returns
    -------
    A : ndarray, shape (n, m)
    """
    tree = tree.tree if isinstance(tree, Body) else tree
    rng = np.random.default_rng(rng)
    if not (isinstance(n, (int, np.integer)) and n >= 0):
        raise InvalidInputError(f"n must be an integer >= 0, got {n!r}")
    lower, upper = tree.action_lower, tree.action_upper
    if above_ground is True:
        above_ground = tree.marker_ids
    elif above_ground is False:
        above_ground = None
    ids = [tree.marker(i).id for i in above_ground] if above_ground is not None else []
    accepted, n_accepted, drawn = [], 0, 0
    while n_accepted < n:
        batch = max(2 * (n - n_accepted), 16)
        if drawn + batch > max_draws:
            raise BodySchemeError(
                f"babbling accepted only {n_accepted} of {n} configurations in {drawn} draws; markers {ids} are "
                f"rarely above z = {ground_z}")
        A = rng.uniform(lower, upper, size=(batch, tree.n_actions))
        drawn += batch
        if ids:
            poses = tree.marker_poses(A)
            ok = np.all([poses[i][:, 2, 3] > ground_z for i in ids], axis=0)
            A = A[ok]
        accepted.append(A)
        n_accepted += A.shape[0]
    return np.concatenate(accepted, axis=0)[:n] if accepted else np.zeros((0, tree.n_actions))
