"""Flipped orientations: a marker's pose mirrored about the camera's ray, found, used, and a learned mirror undone.

A planar marker seen from the camera has two poses that look alike, its orientation mirrored about the ray
(:func:`~body_scheme_core.transforms.mirror_about_ray`), and a tracker sometimes reports the wrong one. Once a joint
fit exists, :func:`mirrored_observations` compares each observation with the calibrated body scheme's prediction and
the learner takes a flipped one in mirrored (``corrected["flipped"]``).

That check trusts the prediction. A scheme fitted while a part's flips were still let through can hold the part's
*mirror image* (traced on the robot zoo's ``flips30`` level, seed 19): every true pose then looks flipped and is
"corrected" into agreement with the wrong scheme, every real flip agrees with it, and the fit never leaves. Flips are
the minority of a tracker's solutions (a few % to 30 % at 2 m), so :class:`MirrorWatch` counts, per part, the
observations the check judged in blocks of :data:`MIRROR_BLOCK`; a part that was taken in mirrored in more than half
of a block has its mirror image in the scheme. The learner then chooses every stored pose of that part again against
the mirror of the prediction (:func:`rechosen_poses`) and fits again.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..errors import ModelFileError
from ..state_values import integer, listing
from ..transforms import mirror_about_ray, rotational_error

__all__ = ["MIRROR_BLOCK", "EAGER_FLOOR", "mirrored_observations", "FlipDecisions", "decide_flips", "MirrorWatch",
           "rechosen_poses", "rechosen_history"]

#: Observations of a part per decision of :class:`MirrorWatch`. At a 30 % flip rate more than half of 60 are taken
#: in mirrored with probability about 1e-4 while the scheme is right; about 70 % are while it holds the mirror.
MIRROR_BLOCK = 60

#: The ``floor`` of :func:`mirrored_observations` for a tracker known to flip (``config.mirror_hypotheses``): a third
#: of the rotational threshold, about one noise RMS at the default 3-sigma validity. A flip of a marker seen nearly
#: face-on is off by less than the threshold, so the stricter default floor (1) lets it through, and the
#: rotational CUSUM of a rigid edge sums such flips into false alarms (robot zoo, 30 % flips).
EAGER_FLOOR = 1.0 / 3.0


def mirrored_observations(world2part, observations, theta_rot, theta_trans=math.inf, floor=1.0):
    """``[(part, detail, placed)]``: observations whose orientation is the mirror image about the camera's ray of what
    the calibrated body scheme predicts (``world2part``, per part, at this step's actions; the planar ambiguity a
    marker tracker falls into): off by more than ``floor`` times ``theta_rot`` while the mirror is within
    ``theta_rot`` and less than half as far off (``floor`` below 1: also a flip whose mirror image is only a few
    noise RMS away, as of a marker seen nearly face-on, :data:`EAGER_FLOOR`). ``placed``: the observed position is
    within ``theta_trans`` of the predicted one (a flip keeps the position, so the prediction is then trusted to
    tell which orientation is the true one). Every predicted part is
    judged, also one the scheme does not explain yet: a prediction that is wrong by a change or a poor fit makes a
    true observation look neither near nor mirrored, and a flip let through would look like a lack of fit itself."""
    parts = [p for p in observations if p in world2part]
    if not parts:
        return []
    predicted = np.stack([world2part[p] for p in parts])
    observed = np.stack([observations[p] for p in parts])
    error = rotational_error(predicted, observed)
    mirrored = rotational_error(predicted, mirror_about_ray(observed))
    flipped = (error > floor * theta_rot) & (mirrored <= theta_rot) & (mirrored < 0.5 * error)
    if not np.any(flipped):
        return []
    placed = np.linalg.norm(predicted[:, :3, 3] - observed[:, :3, 3], axis=1) <= theta_trans
    bound = f"threshold {math.degrees(theta_rot):.1f} deg" + (
        f", {math.degrees(floor * theta_rot):.1f} deg for a tracker known to flip" if floor < 1.0 else "")
    return [(p, f"the orientation of part {p} is {math.degrees(e):.0f} deg from the body scheme's prediction, "
                f"its mirror about the camera's ray {math.degrees(m):.0f} deg ({bound})", bool(c))
            for p, e, m, f, c in zip(parts, error, mirrored, flipped, placed, strict=True) if f]


class FlipDecisions(NamedTuple):
    """What the flip check made of one step's observations.

    Attributes
    ----------
    observations : dict
        ``{part: world2part}`` to learn from: flips taken in mirrored, refused ones left out, the rest as given.
    judged : list of int
        Parts the calibrated scheme predicts, all compared with their prediction.
    mirrored : list of int
        Parts taken in as their mirror image.
    refused : list of (int, str)
        Flipped parts whose position the scheme does not explain (a change?), with why: neither orientation trusted.
    """

    observations: dict
    judged: list
    mirrored: list
    refused: list


def decide_flips(predicted, observations, theta_rot, theta_trans, eager=False):
    """The flip check of one step (:func:`mirrored_observations`) applied: a flip whose position the scheme explains
    is taken in mirrored, one whose position it does not is refused. ``eager``: the tracker is known to flip, so a
    flip off by more than :data:`EAGER_FLOOR` times ``theta_rot`` counts. ``observations`` is not changed."""
    taken = dict(observations)
    mirrored, refused = [], []
    floor = EAGER_FLOOR if eager else 1.0
    for part, detail, placed in mirrored_observations(predicted, observations, theta_rot, theta_trans, floor):
        if placed:  # the scheme explains where the part is: its mirrored orientation is the true one
            taken[part] = mirror_about_ray(taken[part])
            mirrored.append(part)
        else:
            del taken[part]
            refused.append((part, detail))
    return FlipDecisions(taken, [p for p in observations if p in predicted], mirrored, refused)


class MirrorWatch:
    """Per part, ``[judged, mirrored]``: of the observations the flip check judged in the current block, how many it
    took in mirrored. A block ends after :data:`MIRROR_BLOCK` judged observations of the part."""

    def __init__(self, counts=None):
        self.counts = {} if counts is None else {p: list(c) for p, c in counts.items()}

    def record(self, judged, mirrored):
        """Count one step: ``judged`` parts were compared with the prediction, ``mirrored`` of them taken in
        mirrored. Returns the parts whose block ended with more than half taken in mirrored (their mirror image is
        in the body scheme)."""
        mirrored = set(mirrored)
        learned = []
        for part in judged:
            count = self.counts.setdefault(part, [0, 0])
            count[0] += 1
            count[1] += part in mirrored
            if count[0] >= MIRROR_BLOCK:
                if 2 * count[1] > count[0]:
                    learned.append(part)
                del self.counts[part]
        return learned

    def copy(self):
        return MirrorWatch(self.counts)

    def to_list(self):
        return [[p, n, m] for p, (n, m) in self.counts.items()]

    @classmethod
    def from_list(cls, items, parts):
        """From :meth:`to_list` output; parts must be in ``parts`` and counts within a block."""
        counts = {}
        for item in listing(items, "mirror_watch"):
            p, n, m = (integer(v, "mirror_watch item") for v in listing(item, "mirror_watch item", 3))
            if p not in parts or not 0 <= m <= n < MIRROR_BLOCK:
                raise ModelFileError(f"mirror_watch item {item!r}: unknown part or counts beyond a block")
            counts[p] = [n, m]
        return cls(counts)


def rechosen_poses(predicted, observed):
    """Each observed pose or its mirror about the camera's ray, whichever is nearer the *mirror* of the predicted
    pose: the stored poses of a part whose mirror image the body scheme learned, chosen again as if the scheme were
    its mirror. Returns ``(poses, changed)``.

    Parameters
    ----------
    predicted, observed : ndarray, shape (k, 4, 4)
        ``world2part`` the scheme predicts and the stored observations, at the same steps.

    Returns
    -------
    poses : ndarray, shape (k, 4, 4)
    changed : ndarray of bool, shape (k,)
    """
    observed = np.asarray(observed, dtype=float)
    target = mirror_about_ray(predicted)
    flipped = mirror_about_ray(observed)
    changed = rotational_error(target, flipped) < rotational_error(target, observed)
    return np.where(changed[:, None, None], flipped, observed), changed


def rechosen_history(records, covariances, part, predict):
    """The stored poses of ``part`` chosen again (:func:`rechosen_poses`): its scheme's mirror image is undone.

    Parameters
    ----------
    records : list of (int, ndarray, dict)
        The history, ``(step, actions, {part: world2part})`` oldest first; not changed (stored observations are never
        changed in place: a changed record is a new tuple and dict).
    covariances : dict
        ``{step: {part: (6, 6)}}``, the detections' own covariances; not changed.
    part : int
    predict : callable
        ``predict(A)``: ``world2part`` of ``part`` the scheme predicts at actions ``A`` (k, m), shape (k, 4, 4).

    Returns
    -------
    records, covariances
        New ones, a changed pose without its detection's covariance (it is the other solution's).
    changed, stored : int
        How many of the part's stored poses changed, of how many.
    """
    records, covariances = list(records), dict(covariances)
    at = [k for k, (_, _, obs) in enumerate(records) if part in obs]
    if not at:
        return records, covariances, 0, 0
    poses, changed = rechosen_poses(predict(np.stack([records[k][1] for k in at])),
                                    np.stack([records[k][2][part] for k in at]))
    for k in np.flatnonzero(changed):
        step, a, obs = records[at[k]]
        records[at[k]] = (step, a, {**obs, part: poses[k]})
        if part in covariances.get(step, {}):
            covariances[step] = {p: C for p, C in covariances[step].items() if p != part}
    return records, covariances, int(changed.sum()), len(at)
