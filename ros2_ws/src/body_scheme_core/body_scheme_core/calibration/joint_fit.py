"""The joint fit of a body scheme: root pose and every local model of the tree against absolute observations.

A calibration in the sense of ``robot_calibration``: once the structure is known, the body scheme is one kinematic
tree whose parameters — the root's pose in the camera frame ``world2root`` and the parameters of each rigid-joint
model (static, prismatic, revolute) — are refined together against every marker observation ``Y_q = world2part``,
predicted as ``world2root @ root2part(a)`` (a bundle adjustment over the tree). Each edge then learns from the
absolute observations of the parts below it, never from its parent marker's noisy orientation alone: the lever arm
that makes relative observations ``Y_i^-1 Y_j`` noisy (15 deg of orientation noise times the link length) is gone.

The problem is solved by Levenberg-Marquardt with Huber re-weighting on whitened residuals: the position residual of
an observation in units of its marker's noise across and along the camera's ray (``axis_sigmas``: lateral, depth;
isotropic ``sigma / sqrt(3)`` of a 3D RMS ``sigma`` by default), the rotation vector of
``R_obs^T R_pred`` in units of its per-axis sigma (as :func:`~body_scheme_core.models.rigid_fit.pose_residuals`), with
analytic Jacobians: the twist ``[dt, w]`` of an edge (its model's ``twists``, mapped through the
inversion for edges used backwards) moves a part at the end of the chain ``P @ T_edge @ S`` by::

    dt_part = R_P (dt - R_edge [t_S]x w),   w_part = R_S^T w

and the root pose likewise. Engineered models (the specification) and GP models have no parameters here: GP edges are
refitted afterwards on *chain-consistent* targets ``(world2root root2parent(a))^-1 Y_child`` — the child's
observation relative to the parent's *predicted* pose — and the rigid parameters are refined once more around them.
Observations of parts below a GP edge never steer the rigid edges above it (the GP's approximation errors would bend
them); the rigid edges below a GP are fitted last, to those observations, with everything above them held.

Observations are used per part only from the step at which every edge on its path from the root became valid
(``since``, e.g. a replacement's change point). A model can carry a Gaussian prior on its parameters (its earlier
estimate and covariance), for the knowledge that data no longer in the window (or excluded) brought.

An observation may come with its own covariance (a tag detector's, from its corners through PnP:
:func:`~body_scheme_core.perception.pose_covariance`, as the learner scales it; ``covariances``): its position is then
whitened by the inverse square root of that covariance's position block and its rotation by the rotation block's
(:func:`covariance_whitening`), instead of by its marker's per-axis sigmas; the cross terms between position and
rotation are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from ..models import DEFAULT_F_SCALE, GPModel, RigidJointModel, huber_weights, robust_cost
from ..prediction import BodyScheme
from ..transforms import rotation_log, rotvec_matrix, skew

__all__ = ["Calibration", "calibrate", "chain_targets", "covariance_whitening", "edge_consistency"]

#: Levenberg-Marquardt damping relative to the diagonal and its bounds.
_DAMPING, _DAMPING_MIN, _DAMPING_MAX = 1e-3, 1e-9, 1e6
#: An iteration that lowers the cost (chi-square, in sigma units) by less than this ends the fit: its step moved the
#: parameters by about a third of their standard deviation, and Gauss-Newton's next step would move them far less.
_MIN_DECREASE = 0.1
#: A GP edge is refitted on chain-consistent targets only with at least this many of them.
MIN_GP_TARGETS = 10


@dataclass(frozen=True, eq=False)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    scheme : BodyScheme
        The tree with refined copies of its models (the input scheme is not modified).
    world2root : ndarray, shape (4, 4)
    root_cov : ndarray, shape (6, 6)
        Covariance of a local increment ``[dt, w]`` of ``world2root``.
    n_observations : int
        Marker observations used.
    cost : float
        Robust cost at the solution (sum of ``rho(r^2)`` over residual components, in sigmas).
    rms : float
        Root mean square normalised residual (about 1 when the noise model holds).
    iterations : int
    parts, trans_errors, rot_errors : ndarray, shape (n_observations,)
        Per used observation at the solution: the part, and the distance (m) and angle (rad) between its predicted
        and observed pose.
    steps : ndarray of int, shape (n_observations,)
        Per used observation: its row in ``actions``.
    residual_t, residual_r : ndarray, shape (n_observations, 3)
        ``t_pred - t_obs`` in the world (camera) frame (m) and the rotation vector of ``R_obs^T R_pred`` (rad).
    positions : ndarray, shape (n_observations, 3)
        Observed positions (the rays of the noise model).
    whitened : ndarray, shape (n_observations, 6)
        The residuals in units of their noise sigmas (what the fit minimised, before the robust loss).
    n_params : int
        Parameters fitted (the root pose's 6 included).
    coupled : ndarray of bool, shape (n_observations,)
        Observations that steered the rigid parameters (not of a part below a GP edge).
    detected : ndarray of bool, shape (n_observations,)
        Observations whitened by their own covariance (``covariances``), not by their marker's sigmas.
    """

    scheme: BodyScheme
    world2root: np.ndarray
    root_cov: np.ndarray
    n_observations: int
    cost: float
    rms: float
    iterations: int
    parts: np.ndarray
    trans_errors: np.ndarray
    rot_errors: np.ndarray
    steps: np.ndarray
    residual_t: np.ndarray
    residual_r: np.ndarray
    positions: np.ndarray
    whitened: np.ndarray
    n_params: int
    coupled: np.ndarray
    detected: np.ndarray

    def part_ratios(self, theta_trans, theta_rot, clip):
        """Per part: ``(n, mean clipped e_t / theta_trans, mean clipped e_r / theta_rot)`` of its observations.

        A mean of 1 or more in either channel: the calibrated body scheme does not explain that part's absolute
        observations (the edge into it, or one above it, is wrong).
        """
        out = {}
        for part in np.unique(self.parts):
            sel = self.parts == part
            out[int(part)] = (int(sel.sum()), float(np.mean(np.minimum(self.trans_errors[sel] / theta_trans, clip))),
                              float(np.mean(np.minimum(self.rot_errors[sel] / theta_rot, clip))))
        return out


def _invert_twist_map(Z):
    """Maps (N, 6, 6) turning a twist of ``Z`` (N, 4, 4) into the twist of ``Z^-1``."""
    R, t = Z[:, :3, :3], Z[:, :3, 3]
    Rt = np.swapaxes(R, 1, 2)
    M = np.zeros((Z.shape[0], 6, 6))
    M[:, :3, :3] = -Rt
    M[:, :3, 3:] = -skew(np.einsum("nji,nj->ni", R, t))
    M[:, 3:, 3:] = -R
    return M


class _Problem:
    """The observations, the parameter layout and the residual/Jacobian evaluation of one joint fit.

    Everything is evaluated on arrays over all steps at once: the world pose of every part (``P``, level by level
    from the root), the residuals of every usable observation, and one Jacobian block per (edge, part below it,
    step) from the world poses alone::

        d t_q = R_u dt - [t_q - t_v]x R_v w,     d w_q = R_q^T R_v w

    for the edge ``u -> v`` with twist ``[dt, w]`` (translation added, rotation right-multiplied on the edge's
    transform) and an observed part ``q`` below ``v``; the root pose is an edge from the world.
    """

    def __init__(self, scheme, actions, observations, since, free, axis_sigmas, root_since=0, below_gp=False,
                 covariances=None):
        self.scheme = scheme
        self.A = actions
        n = actions.shape[0]
        self.position = {id(m): k for k, m in enumerate(scheme.models)}
        # Parts in breadth-first order; each non-root part with its parent and the model of the edge into it.
        self.order = [scheme.root] + [child for _, child, _, _ in scheme.edges]
        index = {p: i for i, p in enumerate(self.order)}
        self.edges = [(index[parent], index[child], self.position[id(model)], inverted)
                      for parent, child, model, inverted in scheme.edges]
        first = np.zeros(len(self.order), dtype=np.int64)
        for parent_i, child_i, k, _ in self.edges:
            first[child_i] = max(first[parent_i], since[k])
        first[0] = max(first[0], root_since)  # the root's own observations only (its marker moved then)
        # Usable observations: observed, and no earlier than every edge on the part's path.
        n_parts = len(self.order)
        self.Y = np.broadcast_to(np.eye(4), (n_parts, n, 4, 4)).copy()
        valid = np.zeros((n_parts, n), dtype=bool)
        for t, obs in enumerate(observations):
            for part, pose in obs.items():
                i = index.get(part)
                if i is not None and t >= first[i]:
                    valid[i, t] = True
                    self.Y[i, t] = pose
        self.obs_q, self.obs_t = np.nonzero(valid)
        given = {(index[part], t): cov for t, covs in enumerate(covariances or ()) if covs
                 for part, cov in covs.items() if part in index}
        self.n_obs = self.obs_q.size
        # Parts below a GP edge do not steer the rigid parameters above it: a GP is refitted to their targets afterwards
        # and is only as good as its data, and its errors would bend the rigid edges above to make up for them. They
        # steer the rigid edges below the GP in a second problem (``below_gp``) with everything above held.
        self.below_gp = below_gp
        part_below_gp = _parts_below_gp(scheme, self.order)
        self.coupled = part_below_gp[self.obs_q] if below_gp else ~part_below_gp[self.obs_q]
        self.n_used = int(self.coupled.sum())
        row_of = np.full((n_parts, n), -1, dtype=np.int64)
        row_of[self.obs_q, self.obs_t] = np.arange(self.n_obs)
        # Parameter layout: root pose first, then each free model.
        self.free = list(free)
        self.offset = {}
        col = 6
        for k in self.free:
            self.offset[k] = col
            col += scheme.models[k].n_params
        self.n_params = col
        # (edge, part below it, step) triples of the Jacobian blocks of free edges, as flat indices into per-(edge,
        # step), per-(part, step) and per-observation arrays.
        below = {i: [i] for i in range(n_parts)}
        for parent_i, child_i, _, _ in reversed(self.edges):
            below[parent_i] = below[parent_i] + below[child_i]
        pe, pq, pt = [], [], []
        for e, (_, child_i, k, _) in enumerate(self.edges):
            if k not in self.offset:
                continue
            for q in below[child_i]:
                steps = np.flatnonzero(valid[q])
                pe.append(np.full(steps.size, e))
                pq.append(np.full(steps.size, q))
                pt.append(steps)
        pe, pq, pt = (np.concatenate(x) if x else np.zeros(0, dtype=np.int64) for x in (pe, pq, pt))
        self.obs_flat = self.obs_q * n + self.obs_t
        self.triple_edge = pe * n + pt
        self.triple_obs = row_of[pq, pt]
        self.p_max = max([scheme.models[k].n_params for k in self.free], default=0)
        # Per free edge: its slice of the triples, the Jacobian rows they fill, and its columns.
        self.blocks_of = []
        for e in np.unique(pe):
            sel = np.flatnonzero(pe == e)
            k = self.edges[e][2]
            block_rows = (self.triple_obs[sel][:, None] * 6 + np.arange(6)[None, :]).ravel()
            self.blocks_of.append((slice(int(sel[0]), int(sel[-1]) + 1), block_rows, self.offset[k],
                                   scheme.models[k].n_params))
        # Per observation: the position whitening W = (I - v v^T) / s_lateral + v v^T / s_depth (v: the ray) and the
        # rotation's sigma s_rot, from its marker's (lateral, depth, rotation) sigmas; or, when any observation has its
        # own covariance (the module docstring), every rotation's whitening W_r (I / s_rot without one).
        sig = np.array([axis_sigmas(self.order[q]) for q in range(n_parts)], dtype=float)[self.obs_q]
        Yt = self.Y[self.obs_q, self.obs_t, :3, 3]
        ray = Yt / np.maximum(np.linalg.norm(Yt, axis=1, keepdims=True), 1e-12)
        vv = ray[:, :, None] * ray[:, None, :]
        self.W = (np.eye(3) - vv) / sig[:, 0, None, None] + vv / sig[:, 1, None, None]
        self.sigma_r = sig[:, 2]
        self.W_r = None
        rows = ([k for k, key in enumerate(zip(self.obs_q.tolist(), self.obs_t.tolist(), strict=True)) if key in given]
                if given else [])
        self.detected = np.zeros(self.n_obs, dtype=bool)
        if rows:
            C = np.stack([given[(int(self.obs_q[k]), int(self.obs_t[k]))] for k in rows])
            self.W_r = np.eye(3) / self.sigma_r[:, None, None]
            self.W[rows], self.W_r[rows] = covariance_whitening(C, self.Y[self.obs_q[rows], self.obs_t[rows], :3, :3])
            self.detected[rows] = True
        self._J = None  # the Jacobian's storage, reused: its zero pattern is the same in every evaluation
        # Free models grouped by form, so each group is evaluated and retracted in one vectorised call.
        self.groups = {}
        for k in self.free:
            self.groups.setdefault(scheme.models[k].form, []).append(k)
        self.x = {k: scheme.models[k].form_input(actions) for k in self.free}
        self.edge_of = {k: e for e, (_, _, k, _) in enumerate(self.edges)}
        self.fixed_Z = {}

    def set_fixed(self, models):
        """Predict the models that are not refined (engineered, GP) once; they do not change during a solve."""
        self.fixed_Z = {k: models[k].predict(self.A) for _, _, k, _ in self.edges if k not in self.offset}

    def stack(self, models):
        """Parameters of the free models, stacked per form: ``{form: (k, q) array}``."""
        return {form: np.stack([models[k].params_ for k in ks]) for form, ks in self.groups.items()}

    def retract(self, params, delta):
        """Stacked parameters after the increment ``delta`` (n_params,) of the free models."""
        out = {}
        for form, ks in self.groups.items():
            d = np.stack([delta[self.offset[k]:self.offset[k] + form.N_PARAMS] for k in ks])
            out[form] = form.retract(params[form], d)
        return out

    def evaluate(self, params, world2root, jacobian=True):
        """Residuals (n_obs, 6) and, with ``jacobian``, the Jacobian (n_obs * 6, n_params), in sigma units.

        ``params``: the free models' parameters stacked per form (:meth:`stack`). The Jacobian's storage is reused
        by the next call with ``jacobian``.
        """
        n = self.A.shape[0]
        n_edges = len(self.edges)
        Z_of = dict(self.fixed_Z)
        TW = np.zeros((n_edges, n, 6, self.p_max)) if jacobian and self.p_max else None
        for form, ks in self.groups.items():
            Z, T = form.evaluate(params[form], np.stack([self.x[k] for k in ks]), twists=TW is not None)
            for j, k in enumerate(ks):
                Z_of[k] = Z[j]
                if TW is not None:
                    e = self.edge_of[k]
                    TW[e, :, :, :form.N_PARAMS] = _invert_twist_map(Z[j]) @ T[j] if self.edges[e][3] else T[j]
        P = np.empty((len(self.order), n, 4, 4))
        P[0] = world2root
        for parent_i, child_i, k, inverted in self.edges:
            Z = Z_of[k]
            P[child_i] = P[parent_i] @ (_inverse(Z) if inverted else Z)
        P_flat = P.reshape(-1, 4, 4)
        pred = P_flat[self.obs_flat]
        r = self.whiten(*self.raw_residuals(pred)) * self.coupled[:, None]
        if not jacobian:
            return r, None
        if self._J is None:
            self._J = np.zeros((self.n_obs * 6, self.n_params))
        J = self._J
        # An edge's twist [dt, w] moves the observed part q (pose R_q, t_q) below it, in world axes U = R_u dt and
        # V = R_v w (u, v: the edge's parent and child poses), by
        #     d t_q = U + [t_v]x V - [t_q]x V,    d w_q = R_q^T V,
        # i.e. [C; 0] + M_q V with C = U + [t_v]x V per (edge, step) and M_q = [-[t_q]x; R_q^T] per observation,
        # each whitened like the residuals (W_q on the position rows, 1 / s_rot on the rotation rows).
        M = np.empty((self.n_obs, 6, 3))
        M[:, :3] = self.W @ -skew(pred[:, :3, 3])
        M[:, 3:] = (np.swapaxes(pred[:, :3, :3], 1, 2) / self.sigma_r[:, None, None] if self.W_r is None
                    else self.W_r @ np.swapaxes(pred[:, :3, :3], 1, 2))
        # The root pose: an edge from the world (U = [I 0], V = [0 R_root], t_v = t_root).
        R_root, t_root = world2root[:3, :3], world2root[:3, 3]
        root = M @ R_root  # M V for V = [0 R_root]: the rotation columns
        root[:, :3] += self.W @ (skew(t_root) @ R_root)
        rows = J.reshape(self.n_obs, 6, self.n_params)  # a view: one observation's six rows per entry
        rows[:, :3, 0:3] = self.W
        rows[:, :, 3:6] = root
        if self.blocks_of:
            parent = [u for u, _, _, _ in self.edges]
            child = [v for _, v, _, _ in self.edges]
            V = (P[child, :, :3, :3] @ TW[:, :, 3:]).reshape(n_edges * n, 3, self.p_max)
            C = (P[parent, :, :3, :3] @ TW[:, :, :3]).reshape(n_edges * n, 3, self.p_max)
            C += skew(P[child, :, :3, 3]).reshape(n_edges * n, 3, 3) @ V
            blocks = M[self.triple_obs] @ V[self.triple_edge]
            blocks[:, :3] += self.W[self.triple_obs] @ C[self.triple_edge]
            for sel, block_rows, col, p in self.blocks_of:
                J[block_rows, col:col + p] = blocks[sel, :, :p].reshape(-1, p)
        rows[~self.coupled] = 0.0
        if self.below_gp:
            rows[:, :, :6] = 0.0  # the root pose is held
        return r, J

    def raw_residuals(self, pred):
        """``(t_pred - t_obs, rotation vector of R_obs^T R_pred)`` per observation, (n_obs, 3) each."""
        Y = self.Y[self.obs_q, self.obs_t]
        return pred[:, :3, 3] - Y[:, :3, 3], rotation_log(np.swapaxes(Y[:, :3, :3], 1, 2) @ pred[:, :3, :3])

    def whiten(self, dt, dr):
        """Residuals (n_obs, 6) in units of their noise sigmas."""
        rotation = dr / self.sigma_r[:, None] if self.W_r is None else np.einsum("nij,nj->ni", self.W_r, dr)
        return np.concatenate([np.einsum("nij,nj->ni", self.W, dt), rotation], axis=1)

    def part_errors(self, dt, dr):
        """Per usable observation: part id, translational (m) and rotational (rad) error, from raw residuals."""
        return np.array(self.order)[self.obs_q], np.linalg.norm(dt, axis=1), np.linalg.norm(dr, axis=1)

    def predicted(self, params, world2root):
        """World poses (n_obs, 4, 4) of the observed parts at ``params``."""
        n = self.A.shape[0]
        Z_of = dict(self.fixed_Z)
        for form, ks in self.groups.items():
            Z, _ = form.evaluate(params[form], np.stack([self.x[k] for k in ks]), twists=False)
            for j, k in enumerate(ks):
                Z_of[k] = Z[j]
        P = np.empty((len(self.order), n, 4, 4))
        P[0] = world2root
        for parent_i, child_i, k, inverted in self.edges:
            P[child_i] = P[parent_i] @ (_inverse(Z_of[k]) if inverted else Z_of[k])
        return P.reshape(-1, 4, 4)[self.obs_flat]


def inverse_sqrt(C):
    """The symmetric inverse square roots of a stack of positive definite matrices ``C`` (k, 3, 3)."""
    values, vectors = np.linalg.eigh(C)
    return (vectors / np.sqrt(values)[:, None, :]) @ np.swapaxes(vectors, 1, 2)


def covariance_whitening(C, R):
    """``(W_t, W_r)``, each (k, 3, 3): what whitens the residuals (``t_pred - t_obs`` in the camera frame, the rotation
    vector of ``R_obs^T R_pred``) of observations with orientations ``R`` (k, 3, 3) and covariances ``C`` (k, 6, 6)
    over ``(x, y, z, rot_x, rot_y, rot_z)``, rotations about the camera's axes (the residual's are the marker's)."""
    return inverse_sqrt(C[:, :3, :3]), inverse_sqrt(np.swapaxes(R, 1, 2) @ C[:, 3:, 3:] @ R)


def _inverse(Z):
    out = np.zeros_like(Z)
    Rt = np.swapaxes(Z[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, Z[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _retract_pose(T, delta):
    out = T.copy()
    out[:3, 3] = T[:3, 3] + delta[0:3]
    out[:3, :3] = T[:3, :3] @ rotvec_matrix(delta[3:6])
    return out


def chain_targets(scheme, world2root, actions, observations, parent, child):
    """Chain-consistent observations of a tree edge: the child's pose relative to the parent's *predicted* pose.

    Parameters
    ----------
    scheme : BodyScheme
    world2root : ndarray, shape (4, 4)
    actions : ndarray, shape (N, m)
    observations : list of dict of int to ndarray, shape (4, 4)
    parent, child : int
        The edge as traversed from the root (``parent`` nearer the root).

    Returns
    -------
    steps : ndarray of int, shape (k,)
        Steps at which the child was observed.
    Z : ndarray, shape (k, 4, 4)
        ``(world2root root2parent(a))^-1 Y_child``.
    """
    steps = np.array([t for t, obs in enumerate(observations) if child in obs], dtype=np.intp)
    if steps.size == 0:
        return steps, np.zeros((0, 4, 4))
    root2parent = scheme.predict_batch(actions[steps])[:, scheme.parts.index(parent)]
    world2parent = world2root @ root2parent
    Y = np.stack([observations[t][child] for t in steps])
    return steps, _inverse(world2parent) @ Y


def edge_consistency(scheme, world2root, actions, observations, theta_trans, theta_rot, clip, since=None):
    """How well each tree edge's child is explained: mean threshold ratios of its chain-consistent errors.

    For every edge (``scheme.models`` order), the errors between the child's observations and its prediction from
    the parent's *predicted* pose (:func:`chain_targets` against the edge's model), each divided by its threshold
    (``theta_trans``, ``theta_rot``: one marker's validity thresholds) and clipped at ``clip``, averaged over the
    steps from the edge's ``since``. A mean of 1 or more in either channel means the edge does not explain the
    absolute observations of its child, whatever its relative observations said.

    Returns
    -------
    n : ndarray of int, shape (k,)
    ratio : ndarray, shape (k, 2)
        Mean clipped ratios (trans, rot); inf where ``n == 0``.
    """
    A = np.asarray(actions, dtype=float)
    k = len(scheme.models)
    since = [0] * k if since is None else list(since)
    pos = {id(m): i for i, m in enumerate(scheme.models)}
    n = np.zeros(k, dtype=np.int64)
    ratio = np.full((k, 2), np.inf)
    for parent, child, model, inverted in scheme.edges:
        i = pos[id(model)]
        steps, Z = chain_targets(scheme, world2root, A, observations, parent, child)
        keep = steps >= since[i]
        steps, Z = steps[keep], Z[keep]
        if steps.size == 0:
            continue
        P = model.predict(A[steps])
        P = _inverse(P) if inverted else P
        e_t = np.linalg.norm(P[:, :3, 3] - Z[:, :3, 3], axis=1)
        cos = np.clip((np.einsum("nij,nij->n", P[:, :3, :3], Z[:, :3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        e_r = np.arccos(cos)
        n[i] = steps.size
        ratio[i] = [np.mean(np.minimum(e_t / theta_trans, clip)), np.mean(np.minimum(e_r / theta_rot, clip))]
    return n, ratio


def calibrate(scheme, world2root, actions, observations, sigma_trans, sigma_rot, since=None, priors=None,
              fixed=(), f_scale=DEFAULT_F_SCALE, max_iterations=20, gp_optimize=True, axis_sigmas=None, root_since=0,
              covariances=None):
    """Refine ``world2root`` and every rigid-joint model of ``scheme`` together (see the module docstring).

    Parameters
    ----------
    scheme : BodyScheme
    world2root : array-like, shape (4, 4)
        Starting estimate of the root's pose in the world (camera) frame.
    actions : array-like, shape (N, m)
    observations : sequence of dict of int to ndarray, shape (4, 4)
        ``world2part`` per step; parts not in the scheme are ignored.
    sigma_trans, sigma_rot : float
        3D RMS noise of one marker observation (m, rad), as in
        :class:`~body_scheme_core.learning.config.BodySchemeConfig`.
    since : sequence of int, optional
        Per model of ``scheme.models``: the first step index (into ``actions``) at which it describes the body; a
        part's observations are used from the largest ``since`` on its path. Default 0 for all.
    priors : dict of int to (params, cov), optional
        Per model position: a Gaussian prior on its parameters (storage layout, and the covariance of a local
        increment). The model starts from the prior's parameters.
    fixed : iterable of int
        Model positions that are not refined (besides engineered and GP models, which never are).
    f_scale : float
        Huber threshold, in sigmas.
    max_iterations : int
    gp_optimize : bool
        Choose each refitted GP edge's length scale and noise ratio by marginal likelihood.
    axis_sigmas : callable, optional
        ``axis_sigmas(part) -> (lateral, depth, rotation)``: per-axis noise sigmas of a marker's position across
        and along the camera's ray (m) and of its orientation (rad), e.g.
        :meth:`~body_scheme_core.calibration.noise_model.NoiseModel.axis_sigmas`. Default: isotropic, ``sigma /
        sqrt(3)``.
    root_since : int
        First step index at which the root's own observations are used (its marker moved before it); the other
        parts keep theirs.
    covariances : sequence of (dict of int to ndarray, shape (6, 6)) or None, optional
        Per step (as ``observations``): the covariance of an observation over ``(x, y, z, rot_x, rot_y, rot_z)``
        (position in the camera frame, rotation about its axes, as ``geometry_msgs/PoseWithCovariance``), positive
        definite; observations without one are whitened by ``axis_sigmas``.

    Returns
    -------
    Calibration
    """
    if not isinstance(scheme, BodyScheme):
        raise InvalidInputError(f"scheme must be a BodyScheme, got {type(scheme).__name__}")
    A = np.asarray(actions, dtype=float)
    if A.ndim != 2 or A.shape[0] != len(observations):
        raise InvalidInputError(f"actions must be (N, m) with N = len(observations) = {len(observations)}, got "
                                f"{A.shape}")
    n_models = len(scheme.models)
    since = [0] * n_models if since is None else [int(s) for s in since]
    if len(since) != n_models:
        raise InvalidInputError(f"since needs one step per model ({n_models}), got {len(since)}")
    priors = dict(priors or {})
    fixed = set(fixed)
    models = list(scheme.models)
    for k, (params, cov) in priors.items():
        models[k] = models[k].with_params(np.asarray(params, dtype=float), np.asarray(cov, dtype=float))
    below = _models_below_gp(scheme)
    free = [k for k, m in enumerate(models) if isinstance(m, RigidJointModel) and k not in fixed and k not in below]
    if axis_sigmas is None:
        isotropic = (sigma_trans / math.sqrt(3.0), sigma_trans / math.sqrt(3.0), sigma_rot / math.sqrt(3.0))

        def axis_sigmas(part):
            return isotropic
    W = np.array(world2root, dtype=float)
    problem = _Problem(scheme, A, observations, since, free, axis_sigmas, root_since, covariances=covariances)
    has_gp = any(isinstance(m, GPModel) for m in models)
    iterations = 0
    for round_ in range(2 if has_gp else 1):
        problem.set_fixed(models)
        params, W, info, cost, it, r = _solve(problem, problem.stack(models), W, priors, f_scale, max_iterations)
        iterations += it
        models = _unstack(problem, models, params)
        if has_gp and round_ == 0:
            models = _refit_gp_edges(scheme, models, W, A, observations, since, gp_optimize)
    cov = _covariance(problem, info, cost)
    models = _with_covariances(problem, models, cov)
    joint = [(problem.free, cov[6:, 6:])]  # without the root pose's 6
    free_below = [k for k, m in enumerate(models) if isinstance(m, RigidJointModel) and k not in fixed and k in below]
    if free_below:
        below_problem = _Problem(scheme, A, observations, since, free_below, axis_sigmas, root_since, below_gp=True,
                                 covariances=covariances)
        below_problem.set_fixed(models)
        below_priors = {k: v for k, v in priors.items() if k in below_problem.offset}
        params_b, _, info_b, cost_b, it, _ = _solve(below_problem, below_problem.stack(models), W, below_priors,
                                                     f_scale, max_iterations)
        iterations += it
        cov_b = _covariance(below_problem, info_b, cost_b)
        models = _with_covariances(below_problem, _unstack(below_problem, models, params_b), cov_b)
        joint.append((below_problem.free, cov_b[6:, 6:]))
    refined = BodyScheme(scheme.parts, scheme.root, models, _joint_covariance(joint))
    rms = math.sqrt(cost / max(6 * problem.n_used, 1))
    problem.set_fixed(models)
    dt, dr = problem.raw_residuals(problem.predicted(problem.stack(models), W))
    parts, e_t, e_r = problem.part_errors(dt, dr)
    positions = problem.Y[problem.obs_q, problem.obs_t, :3, 3]
    return Calibration(refined, W, cov[:6, :6], problem.n_obs, float(cost), rms, iterations, parts, e_t, e_r,
                       problem.obs_t.copy(), dt, dr, positions, problem.whiten(dt, dr), problem.n_params,
                       problem.coupled.copy(), problem.detected.copy())


def _parts_below_gp(scheme, order):
    """Per part of ``order`` (the root first, then breadth-first): whether a GP edge lies on its path."""
    index = {p: i for i, p in enumerate(order)}
    below = np.zeros(len(order), dtype=bool)
    for parent, child, model, _ in scheme.edges:  # breadth-first: a parent comes first
        below[index[child]] = below[index[parent]] or isinstance(model, GPModel)
    return below


def _models_below_gp(scheme):
    """Positions in ``scheme.models`` of the models whose edge lies below a GP edge."""
    order = [scheme.root] + [child for _, child, _, _ in scheme.edges]
    below = dict(zip(order, _parts_below_gp(scheme, order), strict=True))
    position = {id(m): k for k, m in enumerate(scheme.models)}
    return {position[id(model)] for parent, _, model, _ in scheme.edges if below[parent]}


def _covariance(problem, info, cost):
    """Parameter covariance of a solved problem, scaled up by its residuals' chi-square per degree of freedom."""
    if not problem.n_params:
        return info
    cov = np.linalg.pinv(info + 1e-9 * np.eye(problem.n_params), hermitian=True)
    return cov * max(1.0, cost / max(6 * problem.n_used - problem.n_params, 1))


def _joint_covariance(blocks):
    """``(model indices, matrix)`` for :class:`BodyScheme`'s ``param_covariance`` from the solved problems'
    ``(free models, covariance without the root pose)`` blocks (independent of each other), or None."""
    indices = [k for free, _ in blocks for k in free]
    if not indices:
        return None
    matrix = np.zeros((sum(c.shape[0] for _, c in blocks),) * 2)
    start = 0
    for _, c in blocks:
        matrix[start:start + c.shape[0], start:start + c.shape[0]] = c
        start += c.shape[0]
    return tuple(indices), matrix


def _with_covariances(problem, models, cov):
    """The free models of ``problem`` with their blocks of ``cov`` as their parameter covariances."""
    models = list(models)
    for k in problem.free:
        c, p = problem.offset[k], models[k].n_params
        models[k] = models[k].with_params(models[k].params_, cov[c:c + p, c:c + p])
    return models


def _unstack(problem, models, params):
    """The models with the stacked parameters put back (covariances kept for now)."""
    models = list(models)
    for form, ks in problem.groups.items():
        for j, k in enumerate(ks):
            models[k] = models[k].with_params(params[form][j])
    return models


def _solve(problem, params, W, priors, f_scale, max_iterations):
    """Levenberg-Marquardt with Huber re-weighting on stacked parameters; returns (params, W, information matrix,
    cost, iterations, residuals)."""
    n = problem.n_params
    # Prior residuals L^T (offset + delta), with L L^T = cov^-1; offsets accumulate the accepted increments.
    prior_L = {k: np.linalg.cholesky(np.linalg.pinv(np.asarray(cov, dtype=float), hermitian=True)
                                     + 1e-12 * np.eye(len(cov)))
               for k, (_, cov) in priors.items() if k in problem.offset}
    prior_offset = {k: np.zeros(L.shape[0]) for k, L in prior_L.items()}

    def total(params, W, offsets, jacobian):
        r, J = problem.evaluate(params, W, jacobian)
        w = huber_weights(r, f_scale)
        cost = float(robust_cost(r, f_scale))
        for k, L in prior_L.items():
            rp = L.T @ offsets[k]
            cost += float(rp @ rp)
        return r, J, w, cost

    def information(J, w):
        info = J.T @ (J * w.reshape(-1, 1))
        for k, L in prior_L.items():
            c = problem.offset[k]
            info[c:c + L.shape[0], c:c + L.shape[0]] += L @ L.T
        return info

    def gradient(J, w, r, offsets):
        g = J.T @ (w.reshape(-1) * r.reshape(-1))
        for k, L in prior_L.items():
            c = problem.offset[k]
            g[c:c + L.shape[0]] += L @ (L.T @ offsets[k])
        return g

    r, J, w, cost = total(params, W, prior_offset, True)
    damping = _DAMPING
    iterations = 0
    info = information(J, w)
    g = gradient(J, w, r, prior_offset)
    while iterations < max_iterations:
        iterations += 1
        improved = False
        while damping < _DAMPING_MAX:
            H = info + (damping * np.diag(info) + 1e-12) * np.eye(n)
            delta = -np.linalg.solve(H, g)
            trial = problem.retract(params, delta)
            trial_W = _retract_pose(W, delta[0:6])
            trial_offset = {k: prior_offset[k] + delta[problem.offset[k]:problem.offset[k] + L.shape[0]]
                            for k, L in prior_L.items()}
            r_t, _, w_t, cost_t = total(trial, trial_W, trial_offset, False)
            if cost_t <= cost:
                decrease = cost - cost_t
                params, W, prior_offset, r, w, cost = trial, trial_W, trial_offset, r_t, w_t, cost_t
                damping = max(damping / 3.0, _DAMPING_MIN)
                improved = True
                break
            damping *= 10.0
        if not improved or decrease < _MIN_DECREASE:
            break  # the covariance uses the last Jacobian, a step away from this point at most
        # Converged if even the Gauss-Newton step of the last Jacobian (a step away) would lower the cost by less
        # than _MIN_DECREASE: that saves the Jacobian of a warm start's second iteration.
        g = gradient(J, w, r, prior_offset)
        if float(g @ np.linalg.solve(info + 1e-12 * np.eye(n), g)) < _MIN_DECREASE:
            break
        _, J = problem.evaluate(params, W, True)
        info = information(J, w)
        g = gradient(J, w, r, prior_offset)
    return params, W, info, cost, iterations, r


def _refit_gp_edges(scheme, models, W, A, observations, since, optimize=True):
    """GP edges refitted, from the root outwards, on chain-consistent targets of the current estimate."""
    models = list(models)
    pos = {id(m): k for k, m in enumerate(scheme.models)}
    for parent, child, model, inverted in scheme.edges:
        k = pos[id(model)]
        if not isinstance(models[k], GPModel):
            continue
        current = BodyScheme(scheme.parts, scheme.root, models)
        steps, Z = chain_targets(current, W, A, observations, parent, child)
        keep = steps >= since[k]
        steps, Z = steps[keep], Z[keep]
        if steps.size < MIN_GP_TARGETS:
            continue
        models[k] = GPModel(models[k].parent, models[k].child, models[k].actions,
                            **models[k].hyperparameters.to_dict()).fit(A[steps], _inverse(Z) if inverted else Z,
                                                                       optimize=optimize)
    return models

