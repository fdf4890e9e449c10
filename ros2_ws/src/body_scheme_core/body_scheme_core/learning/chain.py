"""Chain-consistent observations: what a local model is tested against once the body scheme is calibrated.

A relative observation ``Y_u^-1 Y_v`` expresses the child marker's position in the parent marker's *observed* frame,
so the parent's orientation noise moves it by the lever arm: 15 deg RMS at 0.6 m is 160 mm, and with the paper's
3-sigma rule the translational validity threshold of such a pair reaches 300-400 mm. A local model that ignores a
joint moving its child by +-1 rad at 0.3 m then still counts as valid. Once a calibrated body scheme exists, the
parent's pose is known far better from the scheme than from its own marker: :class:`ChainTargets` replaces the
observed parent by its *predicted* pose,

    Z_uv = (world2root root2u(a))^-1 Y_v

where ``u`` is the part of the pair nearer the root of the current tree. Its noise is the child's own (44 mm / 15 deg
at the paper's noise) plus the prediction error of ``u`` (small once calibrated, taken from the scheme's propagated
std); the translational threshold follows with the same ``validity_sigmas``::

    theta_t = sqrt(theta_trans^2 + k^2 (3 s_t^2 + 2 s_r^2 d^2))     (s_t, s_r: per-axis predicted std of u, d = |t_uv|)

A model predicting ``v -> u`` is compared after inverting its prediction (``Targets.flip``), so the error is always
measured in the direction without the lever arm. Parts below an edge in mismatch are not trusted (their predicted pose
uses the failed model), and models whose ``u`` is such a part get no target.

For an edge *of the tree* the chain-consistent error is simply the child's absolute prediction error: its predicted
pose is ``world2u @ Z_uv(a)``, and a rigid map preserves distances and angles. :meth:`ChainTargets.tree_errors` uses
that and needs no second prediction; its thresholds add the uncertainty of the child's whole predicted pose (every
model on its path, the edge's own included) to the marker's noise, in both channels.
"""

from __future__ import annotations

import math

import numpy as np

from ..transforms import invert_transform, rotational_error
from .targets import Targets

__all__ = ["ChainTargets"]


class ChainTargets:
    """Chain-consistent targets of one time step.

    Parameters
    ----------
    scheme : BodyScheme
        The calibrated body scheme.
    world2root : ndarray, shape (4, 4)
    a : ndarray, shape (m,)
    observations : dict of int to ndarray, shape (4, 4)
        Accepted ``world2part`` of this step.
    noise : NoiseModel
        The current noise sigmas and validity thresholds (:mod:`~body_scheme_core.calibration.noise_model`).
    untrusted : iterable of int
        Parts whose predicted pose is not trusted (below an edge in mismatch).
    std : dict of int to array-like, shape (2,), optional
        Per-axis std ``[trans m, rot rad]`` of each part's predicted pose; default: propagated at ``a``
        (:meth:`BodyScheme.predict`), which costs every model's uncertainty at every step, so the learner passes the
        joint fit's average instead.
    world2part : dict of int to array-like, shape (4, 4), optional
        ``scheme``'s prediction at ``a`` placed at ``world2root``, if the caller has it (with ``std`` given).
    """

    def __init__(self, scheme, world2root, a, observations, noise, untrusted=(), std=None, world2part=None):
        if std is None:
            root2part, std = scheme.predict(a, return_std=True)
            world2part = {p: world2root @ T for p, T in root2part.items()}
        elif world2part is None:
            world2part = {p: world2root @ T for p, T in scheme.predict(a).items()}
        self.world2part = world2part
        self.std = std
        self.scheme = scheme
        self.observations = observations
        self.untrusted = frozenset(untrusted)
        # The noise of this step, read once: a replay asks for thousands of targets.
        self._sigma = (noise.sigma_trans, noise.sigma_rot)
        self._theta = (noise.theta_trans, noise.theta_rot)
        lateral, depth, _ = noise.axis_sigmas()
        self._axis = (lateral**2, depth**2)  # per-axis variances across and along the ray
        self._k2 = noise.validity_sigmas**2
        self._targets = {}  # (u, v) -> pair_target(u, v)

    def orient(self, parent, child):
        """``(u, v)``: the pair ordered from the root (``u`` nearer the root in the current tree; ties: as given)."""
        return self.scheme.from_root(parent, child)

    def available(self, parent, child):
        """Whether the pair has a target now: its far part observed and its near part trusted."""
        u, v = self.orient(parent, child)
        return v in self.observations and u not in self.untrusted

    def pair_target(self, u, v):
        """Target ``Z_uv`` (4, 4), its translational and rotational thresholds (m, rad) and per-axis sigma (2,) of the
        pair ``u -> v`` (computed once per pair and step)."""
        target = self._targets.get((u, v))
        if target is None:
            Z = invert_transform(self.world2part[u]) @ self.observations[v]
            s_t, s_r = self.std[u]
            d2 = float(Z[:3, 3] @ Z[:3, 3])
            sigma_t, sigma_r = self._sigma
            sigma = np.array([math.sqrt(sigma_t**2 / 3.0 + s_t**2 + (2.0 / 3.0) * s_r**2 * d2),
                              math.sqrt(sigma_r**2 / 3.0 + s_r**2)])
            target = self._targets[(u, v)] = (Z, self.threshold(u, d2), self.rotation_threshold(s_r), sigma)
        return target

    def _orientation(self, entry, own):
        """``(u, v)`` of a model's target, or None: its own direction for candidates (``own``), else from the root,
        or reversed when the part nearer the root is not trusted (a remembered model bridging a cut)."""
        if own:
            u, v = entry.parent, entry.child
            return (u, v) if (v in self.observations and u not in self.untrusted) else None
        near, far = self.orient(entry.parent, entry.child)
        for u, v in ((near, far), (far, near)):
            if v in self.observations and u not in self.untrusted:
                return u, v
        return None

    def threshold(self, u, d2):
        """Translational threshold (m) of a target from part ``u`` at squared distance ``d2`` (module docstring)."""
        s_t, s_r = self.std[u]
        return math.sqrt(self._theta[0]**2 + self._k2 * (3.0 * s_t**2 + 2.0 * s_r**2 * d2))

    def rotation_threshold(self, s_r):
        """Rotational threshold (rad) of a target whose reference orientation has per-axis std ``s_r``."""
        return math.sqrt(self._theta[1]**2 + self._k2 * 3.0 * s_r**2)

    def tree_errors(self, edges):
        """Chain-consistent errors of tree edges: the absolute prediction errors of their children.

        Parameters
        ----------
        edges : list of (int, int)
            ``(u, v)`` per tree edge, ``u`` nearer the root.

        Returns
        -------
        index : ndarray of int
            Positions in ``edges`` with a target (``v`` observed, ``u`` trusted).
        trans_error, rot_error, theta_trans, theta_rot : ndarray, shape (k,)
            Errors (m, rad) and thresholds: the marker's noise plus the uncertainty of the child's predicted pose,
            the edge's own model included (a GP far from its data, or one that cannot be more accurate, is judged
            against what it claims). The position error is weighed across and along the camera's ray by the noise
            there (:meth:`_isotropic_error`).
        """
        k2 = 3.0 * self._k2
        scale = self._theta[0] / math.sqrt(self._k2 * (2.0 * self._axis[0] + self._axis[1]))  # the threshold's margin
        index, e_t, e_r, theta_t, theta_r = [], [], [], [], []
        for k, (u, v) in enumerate(edges):
            Y = self.observations.get(v)
            if Y is None or u in self.untrusted:
                continue
            P = self.world2part[v]
            s_t, s_r = self.std[v]
            index.append(k)
            e_t.append(self._isotropic_error(P[:3, 3] - Y[:3, 3], Y[:3, 3], s_t, scale))
            e_r.append(math.acos(max(-1.0, min(1.0, (float(np.sum(P[:3, :3] * Y[:3, :3])) - 1.0) / 2.0))))
            theta_t.append(math.sqrt(self._theta[0]**2 + k2 * s_t**2))
            theta_r.append(math.sqrt(self._theta[1]**2 + k2 * s_r**2))
        return (np.array(index, dtype=np.intp), np.array(e_t), np.array(e_r), np.array(theta_t),
                np.array(theta_r))

    def _isotropic_error(self, residual, position, s_t, scale):
        """The position error ``residual`` (3,) of a marker at ``position`` as the error of the same likelihood under
        isotropic noise of the same 3D RMS: a camera's error along its ray is several times its error across, and a
        plain distance would make every large depth error look like a change. Equal to ``|residual|`` for isotropic
        noise. ``s_t``: per-axis std of the prediction; ``scale``: the thresholds' margin over the noise."""
        lateral, depth = self._axis[0] * scale**2 + s_t**2, self._axis[1] * scale**2 + s_t**2
        ray = position / max(math.sqrt(float(position @ position)), 1e-12)
        along = float(residual @ ray)
        across = max(float(residual @ residual) - along * along, 0.0)
        return math.sqrt((2.0 * lateral + depth) * (across / lateral + along * along / depth) / 3.0)

    def observed_errors(self, predicted, observed):
        """Errors of an observed pose ``(4, 4)`` against a predicted one without model uncertainty (the root's own
        observation against the root pose): the position error weighed across and along the camera's ray as for the
        edges (:meth:`_isotropic_error`, m) and the rotation angle (rad)."""
        scale = self._theta[0] / math.sqrt(self._k2 * (2.0 * self._axis[0] + self._axis[1]))
        e_t = self._isotropic_error(predicted[:3, 3] - observed[:3, 3], observed[:3, 3], 0.0, scale)
        return e_t, float(rotational_error(predicted, observed))

    def for_entries(self, entries, own=False, reverse=True):
        """Targets of the tracked models that have one.

        Parameters
        ----------
        entries : list of TrackedModel
        own : bool
            Use each model's own direction (candidates, created from the root side of their pair).
        reverse : bool
            Allow the reversed direction when the part nearer the root is not trusted (not for tree edges, whose
            errors would then follow from the mismatch above them).

        Returns
        -------
        index : ndarray of int
            Positions in ``entries`` with a target.
        targets : Targets
            One row per position of ``index``.
        """
        index, Z, theta_t, theta_r, sigma, flip = [], [], [], [], [], []
        for k, e in enumerate(entries):
            uv = self._orientation(e, own)
            if uv is None or (not reverse and not own and uv != self.orient(e.parent, e.child)):
                continue
            u, v = uv
            Zk, tk, rk, sk = self.pair_target(u, v)
            index.append(k)
            Z.append(Zk)
            theta_t.append(tk)
            theta_r.append(rk)
            sigma.append(sk)
            flip.append(u != e.parent)
        if not index:
            return np.zeros(0, dtype=np.intp), Targets(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.ones((0, 2)),
                                                       np.zeros(0, dtype=bool))
        return np.array(index, dtype=np.intp), Targets(np.array(Z), np.array(theta_t), np.array(theta_r),
                                                       np.array(sigma), np.array(flip, dtype=bool))
