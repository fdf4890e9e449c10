"""The root pose in the world (``world2root``): where the body scheme's predictions are placed.

:class:`RootWatch` checks, once the body scheme is calibrated, that the root's own observations stay where the root pose
puts them: the root has no edge whose detector would notice its marker being moved.

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

from ..rotations import project_to_rotation
from ..transforms import invert_transform, rotational_error
from .validity import ValidityMonitor

__all__ = ["still_part", "RootPoseEstimator", "RootWatch", "register_points", "point_spread", "MIN_SPREAD",
           "OUTLIER_SIGMAS", "OFFSET_SAMPLES"]

#: Points whose residual after the first fit exceeds this many times the median residual are dropped (about 4.6 sigma
#: per axis for Gaussian noise).
OUTLIER_SIGMAS = 3.0
#: Observations of the root's marker that set where :class:`RootWatch` expects it relative to the root pose.
OFFSET_SAMPLES = 10
# Below this many points, or points (nearly) on a line, the registration's rotation is not determined.
_MIN_POINTS = 6
MIN_SPREAD = 1e-3  # m, second singular value of the centred points / sqrt(n) (point_spread)


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

    def snapshot(self):
        """What :meth:`restore` needs to undo a learner's step."""
        return self.root, self._cache, self._samples.copy()

    def restore(self, saved):
        """Undo every change since :meth:`snapshot` returned ``saved``."""
        self.root, self._cache, self._samples = saved

    def invalidate(self):
        """Forget the cached estimate (the root changed)."""
        self._cache = None

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
    return len(P) >= _MIN_POINTS and point_spread(P) > MIN_SPREAD


def point_spread(P):
    """How far points ``P`` (n, 3) are from one line: the second singular value of the centred points per
    ``sqrt(n)`` (m); below :data:`MIN_SPREAD` they do not determine a rotation."""
    P = np.asarray(P, dtype=float)
    return float(np.linalg.svd(P - P.mean(axis=0), compute_uv=False)[1] / np.sqrt(len(P)))


class RootWatch:
    """The root's own observations against the calibrated root pose: a change detector for the part without an edge.

    Every edge of the tree has a CUSUM on its child's errors (:mod:`~body_scheme_core.learning.adaptation`); the root
    has no edge, so a marker moved on the robot's base, or knocked, would go unnoticed while the joint fit slowly
    absorbed it. One validity-monitor row, with the same thresholds, CUSUM and change point as the edges'.

    After an alarm it detects a *change* from what followed: the root's marker is then expected where it was seen
    relative to the root pose over the next :data:`OFFSET_SAMPLES` observations (its :attr:`offset`; identity until
    the first alarm and after a restart). An offset the joint fit cannot follow (a real tracker's depth bias on the
    base marker) then raises one alarm, not one every few steps.

    Parameters
    ----------
    config : BodySchemeConfig
    monitor : ValidityMonitor, optional
        A restored state (one row).
    offset : ndarray, shape (4, 4), optional
        A restored :attr:`offset` (root pose to the observed root marker, on average).
    n_offset : int, optional
        Observations the offset was learnt from (default: :data:`OFFSET_SAMPLES`, the identity taken as learnt).
    """

    def __init__(self, config, monitor=None, offset=None, n_offset=None):
        if monitor is None:
            monitor = ValidityMonitor.from_config(config)
            monitor.allocate(1)
        self.monitor = monitor
        self.offset = np.eye(4) if offset is None else np.array(offset, dtype=float)
        self.n_offset = OFFSET_SAMPLES if n_offset is None else int(n_offset)

    def snapshot(self):
        """What :meth:`restore` needs to undo a learner's step."""
        return self.monitor.copy(), self.offset.copy(), self.n_offset

    def restore(self, saved):
        """Undo every change since :meth:`snapshot` returned ``saved``."""
        self.monitor, self.offset, self.n_offset = saved

    def expected(self, world2root):
        """Where the root's marker is expected in the world ``(4, 4)``, or None while its offset is being learnt."""
        return world2root @ self.offset if self.n_offset >= OFFSET_SAMPLES else None

    def learn_offset(self, world2root, observation):
        """One observation of the root's marker ``(4, 4)`` (or None) into its offset from the root pose ``world2root``,
        while fewer than :data:`OFFSET_SAMPLES` were seen."""
        if observation is None or self.n_offset >= OFFSET_SAMPLES:
            return
        D = invert_transform(world2root) @ observation
        n = self.n_offset = self.n_offset + 1
        self.offset[:3, 3] += (D[:3, 3] - self.offset[:3, 3]) / n
        self.offset[:3, :3] = project_to_rotation(self.offset[:3, :3] + (D[:3, :3] - self.offset[:3, :3]) / n)

    def check(self, errors, step, theta_trans, theta_rot):
        """Record the errors ``(trans, rot)`` of the root's observation against :meth:`expected` (or None when the
        root was not seen; :meth:`~body_scheme_core.learning.chain.ChainTargets.observed_errors`).

        Returns
        -------
        alarm : tuple (int, ndarray (2,), WindowStats) or None
            When the CUSUM alarms: the change point, the CUSUM and the window's statistics (then the detector starts
            afresh from the change point and learns the offset again); else None.
        """
        self.monitor.set_thresholds(theta_trans, theta_rot)
        if errors is None:
            return None
        alarm = self.monitor.record([0], [errors[0]], [errors[1]], step)
        if not alarm[0]:
            return None
        tau = int(self.monitor.change_point([0])[0])
        found = (tau, self.monitor.cusum[0].copy(), self.monitor.stats([0]))
        self.monitor.reset_cusum([0])
        self.monitor.forget_before([0], tau)
        self.offset, self.n_offset = np.eye(4), 0
        return found

    def restart(self):
        """Forget everything (a new root part)."""
        self.monitor.clear([0])
        self.offset, self.n_offset = np.eye(4), OFFSET_SAMPLES


#: Observations of a part before it can be chosen as the root (:func:`still_part`).
_ROOT_SAMPLES = 3


def still_part(part_ids, observations, sigma_trans, sigma_rot):
    """The part whose observed pose moves least in the camera's view: the robot's trunk, the root of the body scheme.

    A part's motion is the median distance of its observed positions from their median, in units of the position
    noise, or the median angle of its observed orientations from their mean, in units of the orientation noise,
    whichever is larger (a joint whose axis passes through a marker turns it without moving it). Parts seen fewer than
    :data:`_ROOT_SAMPLES` times are not considered; ties go to the lowest id.

    Parameters
    ----------
    part_ids : iterable of int
    observations : list of dict of int to ndarray, shape (4, 4)
        Observed ``world2part`` per step.
    sigma_trans, sigma_rot : float
        The noise (3D RMS, m and rad).

    Returns
    -------
    part : int or None
        None while no part was seen often enough.
    """
    motion = {}
    for part in part_ids:
        Y = np.array([obs[part] for obs in observations if part in obs])
        if len(Y) < _ROOT_SAMPLES:
            continue
        P = Y[:, :3, 3]
        moved = np.median(np.linalg.norm(P - np.median(P, axis=0), axis=1)) / sigma_trans
        mean = project_to_rotation(Y[:, :3, :3].mean(axis=0))
        turned = np.median(rotational_error(np.broadcast_to(mean, Y[:, :3, :3].shape), Y[:, :3, :3])) / sigma_rot
        motion[part] = max(float(moved), float(turned))
    return min(motion, key=lambda p: (motion[p], p)) if motion else None
