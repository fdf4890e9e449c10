"""The root pose in the world: a robust running mean of the recent root observations (``world2root``).

Predictions of the body scheme are relative to the root part; :meth:`BodySchemeLearner.predict` places them in the
world with this estimate. See ``docs/core/learning-and-adaptation.md``, Sec. 7.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .transforms import project_to_rotation

__all__ = ["RootPoseEstimator"]


class RootPoseEstimator:
    """Robust mean of the last ``window`` observations of the root part.

    Translation: coordinate-wise median. Rotation: the element-wise median of the rotation matrices projected onto
    SO(3). Both ignore up to half of the samples being outliers. Identity while the root was never seen.

    Parameters
    ----------
    window : int
        Number of recent observations kept (``config.root_window``).
    observations : iterable of ndarray, shape (4, 4), optional
        Initial observations, oldest first (a restored state).
    """

    def __init__(self, window, observations=()):
        self._observations = deque(observations, maxlen=window)
        self._pose = None

    @property
    def observations(self):
        """The kept observations, oldest first (list of ndarray, shape (4, 4))."""
        return list(self._observations)

    def add(self, world2root):
        """Add one observation ``world2root`` (4, 4); the oldest is dropped beyond ``window``."""
        self._observations.append(world2root)
        self._pose = None

    @property
    def pose(self):
        """Estimated ``world2root``, ndarray of shape (4, 4); cached until the next :meth:`add`."""
        if self._pose is None:
            pose = np.eye(4)
            if self._observations:
                Y = np.asarray(self._observations)
                pose[:3, :3] = project_to_rotation(np.median(Y[:, :3, :3], axis=0))
                pose[:3, 3] = np.median(Y[:, :3, 3], axis=0)
            self._pose = pose
        return self._pose
