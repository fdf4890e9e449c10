"""Relative observations ``Z_ij = Y_i^-1 Y_j`` of one time step, for every pair of observed parts (paper Sec. III-A).

Local models describe pairs of parts. :class:`PartPairs` numbers the unordered pairs once, in the part order (the
*canonical* direction of pair ``(p_i, p_j)`` is ``i < j``), and turns the marker poses of one step into a
:class:`RelativeObservations`: all relative transforms of observed pairs, formed in one vectorised pass, with the
translational validity threshold of each (it grows with the parts' distance, see
:func:`~body_scheme_core.learning.targets.translation_threshold`). A model whose parent comes later in the part order
predicts the inverse of the canonical transform (:meth:`PartPairs.flip`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..transforms import invert_transform, mirror_about_ray
from .targets import Targets, translation_threshold

__all__ = ["PartPairs", "RelativeObservations"]


class RelativeObservations(NamedTuple):
    """The relative observations of one time step.

    Attributes
    ----------
    Z : ndarray, shape (k, 4, 4)
        ``part_i2part_j`` of every observed pair, in the canonical direction.
    row : ndarray of int, shape (n_pairs,)
        Row of each pair in ``Z``; -1 where the pair is not observed.
    theta_trans : ndarray, shape (k,)
        Translational validity threshold of each row of ``Z`` (m).
    theta_rot : float
        Rotational validity threshold (rad) of every row.
    sigma : ndarray, shape (k, 2)
        Per-axis noise std of each row (trans m, rot rad): two markers' noise, and the parent's orientation noise
        times the distance (the lever arm) in translation.
    alternatives : ndarray, shape (k, 3, 4, 4), or None
        Each row's other readings: the first pose mirrored about the camera's ray, the second, both (None: the
        poses are taken as given; :class:`PartPairs` ``mirrors``).
    """

    Z: np.ndarray
    row: np.ndarray
    theta_trans: np.ndarray
    theta_rot: float
    sigma: np.ndarray
    alternatives: np.ndarray | None = None

    def targets(self, pair):
        """:class:`~body_scheme_core.learning.targets.Targets` of models in canonical direction with pair indices
        ``pair``."""
        rows = self.row[pair]
        return Targets(self.Z[rows], self.theta_trans[rows], np.full(len(rows), self.theta_rot), self.sigma[rows],
                       np.zeros(len(rows), dtype=bool),
                       None if self.alternatives is None else self.alternatives[rows])

    def of_pairs(self, pair, flip):
        """Observed transforms of models with pair indices ``pair`` (all observed), inverted where ``flip``.

        Parameters
        ----------
        pair : ndarray of int, shape (k,)
        flip : ndarray of bool, shape (k,)

        Returns
        -------
        Z : ndarray, shape (k, 4, 4)
            ``parent2child`` for each model (a new array).
        """
        Z = self.Z[self.row[pair]]
        if np.any(flip):
            Z[flip] = invert_transform(Z[flip])
        return Z


class PartPairs:
    """The unordered pairs of parts, numbered once, and the relative observations of a time step.

    Parameters
    ----------
    part_ids : tuple of int
        Unique part ids; their order defines the canonical direction of each pair.
    noise : NoiseModel
        The current marker noise (``sigma_trans``, ``sigma_rot``: 3D RMS, m and rad) and validity thresholds
        (``theta_trans``, ``theta_rot``) behind :meth:`threshold`, read at every :meth:`observe`
        (:mod:`~body_scheme_core.calibration.noise_model`).
    exact : iterable of int
        Parts whose pose is given without noise (the sensor as the root, ``sensor_root``): a pair with one of them
        carries one marker's noise, and no lever arm of its orientation noise.
    mirrors : bool
        Also form each pair's readings with either pose, or both, mirrored about the camera's ray (a tracker's
        planar ambiguity; ``config.mirror_hypotheses``): :attr:`RelativeObservations.alternatives`. Exact parts are
        never mirrored.

    Attributes
    ----------
    part_ids : tuple of int
    part_index : dict of int to int
        Position of each part id in ``part_ids``.
    """

    def __init__(self, part_ids, noise, exact=(), mirrors=False):
        self.part_ids = tuple(part_ids)
        self.noise = noise
        self.part_index = {p: k for k, p in enumerate(self.part_ids)}
        n = len(self.part_ids)
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
        self._first = np.array([i for i, _ in pairs], dtype=np.intp)
        self._second = np.array([j for _, j in pairs], dtype=np.intp)
        noisy = np.array([p not in set(exact) for p in self.part_ids], dtype=float)
        self._mirrored = noisy.astype(bool) if mirrors else None
        # Per pair: how many of its two poses are noisy, and whether the first one's orientation noise has a lever.
        self._markers = noisy[self._first] + noisy[self._second]
        self._lever = noisy[self._first]
        self._index = {}
        for k, (i, j) in enumerate(pairs):
            self._index[(self.part_ids[i], self.part_ids[j])] = k
            self._index[(self.part_ids[j], self.part_ids[i])] = k

    @property
    def n_pairs(self):
        """Number of unordered pairs, ``n (n - 1) / 2``."""
        return self._first.size

    def index(self, parent, child):
        """Index of the unordered pair ``{parent, child}``."""
        return self._index[(parent, child)]

    def flip(self, parent, child):
        """Whether ``parent2child`` is the inverse of its pair's canonical direction."""
        return self.part_index[parent] > self.part_index[child]

    def threshold(self, Z, lever=1.0):
        """Translational validity thresholds (m) of relative transforms ``Z`` (..., 4, 4): they grow with distance,
        where the first pose's orientation is noisy (``lever`` 1, else 0)."""
        distance = np.linalg.norm(Z[..., :3, 3], axis=-1) * lever
        return translation_threshold(self.noise.theta_trans, self.noise.theta_rot, distance)

    def observe(self, observations):
        """Relative observations of every pair with both parts observed.

        Parameters
        ----------
        observations : dict of int to ndarray, shape (4, 4)
            Valid ``world2part`` of known parts.

        Returns
        -------
        relative : RelativeObservations
        """
        n_parts = len(self.part_ids)
        seen = np.zeros(n_parts, dtype=bool)
        Y = np.empty((n_parts, 4, 4))
        for part, pose in observations.items():
            k = self.part_index[part]
            seen[k] = True
            Y[k] = pose
        both = np.flatnonzero(seen[self._first] & seen[self._second])
        row = np.full(self._first.size, -1, dtype=np.intp)
        row[both] = np.arange(both.size)
        if both.size == 0:
            return RelativeObservations(np.zeros((0, 4, 4)), row, np.zeros(0), self.noise.theta_rot, np.ones((0, 2)))
        Ys = Y[seen]
        Yinv = invert_transform(Ys)
        inv_index = np.cumsum(seen) - 1
        first, second = inv_index[self._first[both]], inv_index[self._second[both]]
        Z = Yinv[first] @ Ys[second]
        markers, lever = self._markers[both], self._lever[both]
        d2 = np.sum(Z[:, :3, 3] ** 2, axis=1) * lever
        sigma_t, sigma_r = self.noise.sigma_trans, self.noise.sigma_rot
        sigma = np.stack([np.sqrt((markers * sigma_t**2 + (2.0 / 3.0) * sigma_r**2 * d2) / 3.0),
                          sigma_r * np.sqrt(markers / 3.0)], axis=1)
        alternatives = None
        if self._mirrored is not None:
            Ym = Ys.copy()
            Ym[self._mirrored[seen]] = mirror_about_ray(Ym[self._mirrored[seen]])
            Ymi = invert_transform(Ym)
            alternatives = np.stack([Ymi[first] @ Ys[second], Yinv[first] @ Ym[second], Ymi[first] @ Ym[second]],
                                    axis=1)
        return RelativeObservations(Z, row, self.threshold(Z, lever), self.noise.theta_rot, sigma, alternatives)
