"""The simulated robot's collision screen: which link pairs penetrate, and which pairs it ignores because they touch
by design.

Like a MoveIt configuration's disabled pairs, three kinds are not checked: adjacent links (they share a joint),
pairs already touching in the reference posture (a base standing on the ground, overlapping neighbours) and pairs
touching in (almost) every random posture within the limits ("always in collision", e.g. a shoulder's cover and the
elbow two joints on: checking those would refuse every command).
"""

from __future__ import annotations

import numpy as np

__all__ = ["COLLISION_TOLERANCE", "ALWAYS_SAMPLES", "ALWAYS_FRACTION", "pairs_in_contact", "pairs_always_in_contact"]

#: Penetrations shallower than this (m) are not collisions (contact-margin noise).
COLLISION_TOLERANCE = 1e-3
#: Random postures sampled at start-up to find link pairs that touch in (almost) every posture, and the fraction of
#: them in which a pair must touch to be left unchecked (MoveIt's "always in collision").
ALWAYS_SAMPLES = 200
ALWAYS_FRACTION = 0.95
_ALWAYS_IN_CONTACT = {}  # (robot key, samples, fraction) -> pairs: the sampling is 0.5 s per start


def _deeper_than(points, tolerance=COLLISION_TOLERANCE):
    """Whether pybullet closest points contain a penetration deeper than ``tolerance``."""
    return any(point[8] < -tolerance for point in points)


def pairs_in_contact(pb, robot_id, ground_id, links, parent_index):
    """Link pairs (``(a, b)`` by pybullet link index, ``a < b``, or ``(a, "ground")``) penetrating each other now.

    Parameters
    ----------
    pb : pybullet client
    robot_id, ground_id : int
        The robot's and the ground's bodies.
    links : iterable of int
        The robot's links (pybullet indices, the base -1).
    parent_index : dict of int to int
        Each link's parent link; adjacent links are never checked.
    """
    pairs = set()
    links = sorted(links)
    for a_index, link_a in enumerate(links):
        if _deeper_than(pb.getClosestPoints(robot_id, ground_id, 0.0, linkIndexA=link_a)):
            pairs.add((link_a, "ground"))
        for link_b in links[a_index + 1:]:
            if parent_index.get(link_b) == link_a or parent_index.get(link_a) == link_b:
                continue  # adjacent links share a joint and always touch
            if _deeper_than(pb.getClosestPoints(robot_id, robot_id, 0.0, linkIndexA=link_a, linkIndexB=link_b)):
                pairs.add((link_a, link_b))
    return pairs


def pairs_always_in_contact(key, contacts_at, lower, upper, samples=ALWAYS_SAMPLES, fraction=ALWAYS_FRACTION):
    """Link pairs in contact in at least ``fraction`` of ``samples`` random postures within ``[lower, upper]``.

    Parameters
    ----------
    key : hashable
        What identifies the robot (its URDF's digest and limits): the result is kept per process for that key, so a
        second world of the same robot starts 0.5 s sooner.
    contacts_at : callable
        ``contacts_at(a)``: the pairs in contact (:func:`pairs_in_contact`) after commanding ``a``; the caller
        restores its own posture afterwards.
    lower, upper : array-like, shape (m,)
    samples : int
    fraction : float

    Returns
    -------
    pairs : frozenset
        The postures come from a fixed seed (a world's own random stream is not used).
    """
    cache_key = (key, samples, fraction)
    if cache_key not in _ALWAYS_IN_CONTACT:
        rng, counts = np.random.default_rng(0), {}
        for _ in range(samples):
            for pair in contacts_at(rng.uniform(lower, upper)):
                counts[pair] = counts.get(pair, 0) + 1
        _ALWAYS_IN_CONTACT[cache_key] = frozenset(pair for pair, count in counts.items()
                                                  if count >= fraction * samples)
    return _ALWAYS_IN_CONTACT[cache_key]
