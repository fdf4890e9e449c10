"""The root pose in the world (``world2root``): where the body scheme's predictions are placed.

Once a body scheme exists, the root pose is the rigid transform that best maps the scheme's predicted marker
positions (root frame) onto the observed ones (world frame) over the last ``window`` samples: all markers, not
just the root's, and positions only, whose noise (the paper's 44 mm) is far smaller in effect than the orientation
noise (15 deg) of a single marker times the ~1 m lever arm to the end effector. Robust: points more than
:data:`OUTLIER_SIGMAS` times the median residual off the first fit (a model in mismatch, a mirrored pose) are
dropped before the final fit. Before a body scheme exists (or with too few points) it falls back to a robust mean of
the root part's own observations. See ``docs/core/learning-and-adaptation.md``, Sec. 7.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .transforms import project_to_rotation

__all__ = ["RootPoseEstimator", "register_points", "OUTLIER_SIGMAS"]

#: Points whose residual after the first fit exceeds this many times the median residual are dropped (about 4.6 sigma
#: per axis for Gaussian noise).
OUTLIER_SIGMAS = 3.0
# Below this many points, or points (nearly) on a line, the registration's rotation is not determined.
_MIN_POINTS = 6
_MIN_SPREAD = 1e-3  # m, second singular value of the centred points / sqrt(n)


def register_points(P, Q):
    """Least-squares rigid transform ``T`` with ``Q ~ T @ P`` (Kabsch / Umeyama without scale).

    Parameters
    ----------
    P, Q : ndarray, shape (n, 3)
        Corresponding points, ``n >= 3``, not all on one line.

    Returns
    -------
    T : ndarray, shape (4, 4)
    """
    p0, q0 = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - p0).T @ (Q - q0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    T = np.eye(4)
    T[:3, :3] = Vt.T @ D @ U.T
    T[:3, 3] = q0 - T[:3, :3] @ p0
    return T


class RootPoseEstimator:
    """``world2root`` from the last ``window`` samples.

    Parameters
    ----------
    window : int
        Number of recent samples kept (``config.root_window``).
    root : int or None
        The root part id (its own observations are the fallback estimate).
    samples : iterable of (ndarray (m,), dict of int to ndarray (4, 4)), optional
        Initial ``(actions, {part: world2part})`` samples, oldest first (a restored state).
    """

    def __init__(self, window, root=None, samples=()):
        self.root = root
        self._samples = deque(maxlen=window)
        self._cache = None  # (scheme, pose) of the last estimate
        for a, observations in samples:
            self.add(a, observations)

    @property
    def samples(self):
        """The kept samples ``[(actions, {part: world2part})]``, oldest first."""
        return list(self._samples)

    def add(self, a, observations):
        """Add one sample: the action vector (m,) and the accepted observations ``{part: world2part (4, 4)}``."""
        if observations:
            self._samples.append((np.asarray(a, dtype=float), dict(observations)))
        self._cache = None

    def pose(self, scheme=None):
        """Estimated ``world2root`` (4, 4), cached until the next :meth:`add` or another ``scheme``.

        Parameters
        ----------
        scheme : BodyScheme or None
            The current body scheme; ``None`` (or too few or collinear points) gives the robust mean of the root's
            own observations: coordinate-wise median of the positions and element-wise median of the rotation
            matrices projected onto SO(3). Identity while the root was never seen.
        """
        if self._cache is not None and self._cache[0] is scheme:
            return self._cache[1]
        pose = self._registered(scheme) if scheme is not None else None
        if pose is None:
            pose = self._root_mean()
        self._cache = (scheme, pose)
        return pose

    def _root_mean(self):
        pose = np.eye(4)
        Y = [obs[self.root] for _, obs in self._samples if self.root in obs]
        if Y:
            Y = np.asarray(Y)
            pose[:3, :3] = project_to_rotation(np.median(Y[:, :3, :3], axis=0))
            pose[:3, 3] = np.median(Y[:, :3, 3], axis=0)
        return pose

    def _registered(self, scheme):
        if not self._samples:
            return None
        index = {part: k for k, part in enumerate(scheme.parts)}
        A = np.stack([a for a, _ in self._samples])
        predicted = scheme.predict_batch(A)[:, :, :3, 3]  # (n, n_parts, 3) root2part positions
        P, Q = [], []
        for k, (_, observations) in enumerate(self._samples):
            for part, Y in observations.items():
                if part in index:
                    P.append(predicted[k, index[part]])
                    Q.append(Y[:3, 3])
        P, Q = np.asarray(P), np.asarray(Q)
        if not _well_spread(P):
            return None
        T = register_points(P, Q)
        residual = np.linalg.norm(Q - (P @ T[:3, :3].T + T[:3, 3]), axis=1)
        keep = residual <= OUTLIER_SIGMAS * np.median(residual) + 1e-12
        if keep.sum() < len(keep) and _well_spread(P[keep]):
            T = register_points(P[keep], Q[keep])
        return T


def _well_spread(P):
    if len(P) < _MIN_POINTS:
        return False
    singular = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return singular[1] / np.sqrt(len(P)) > _MIN_SPREAD
