"""One joint fit's least-squares problem (:func:`~body_scheme_core.calibration.joint_fit.calibrate`): the observations,
the parameter layout, and the whitened residuals with their analytic Jacobian, evaluated over every step at once.
"""

from __future__ import annotations

import numpy as np

from ..models import GPModel
from ..rotations import rotation_log, skew
from ..transforms import invert_transform

__all__ = ["FitProblem", "covariance_whitening", "inverse_sqrt", "parts_below_gp",
           "models_below_gp"]


def _invert_twist_map(Z):
    """Maps (N, 6, 6) turning a twist of ``Z`` (N, 4, 4) into the twist of ``Z^-1``."""
    R, t = Z[:, :3, :3], Z[:, :3, 3]
    Rt = np.swapaxes(R, 1, 2)
    M = np.zeros((Z.shape[0], 6, 6))
    M[:, :3, :3] = -Rt
    M[:, :3, 3:] = -skew(np.einsum("nji,nj->ni", R, t))
    M[:, 3:, 3:] = -R
    return M


class FitProblem:
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
        part_below_gp = parts_below_gp(scheme, self.order)
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
            P[child_i] = P[parent_i] @ (invert_transform(Z) if inverted else Z)
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
            P[child_i] = P[parent_i] @ (invert_transform(Z_of[k]) if inverted else Z_of[k])
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


def parts_below_gp(scheme, order):
    """Per part of ``order`` (the root first, then breadth-first): whether a GP edge lies on its path."""
    index = {p: i for i, p in enumerate(order)}
    below = np.zeros(len(order), dtype=bool)
    for parent, child, model, _ in scheme.edges:  # breadth-first: a parent comes first
        below[index[child]] = below[index[parent]] or isinstance(model, GPModel)
    return below


def models_below_gp(scheme):
    """Positions in ``scheme.models`` of the models whose edge lies below a GP edge."""
    order = [scheme.root] + [child for _, child, _, _ in scheme.edges]
    below = dict(zip(order, parts_below_gp(scheme, order), strict=True))
    position = {id(m): k for k, m in enumerate(scheme.models)}
    return {position[id(model)] for parent, _, model, _ in scheme.edges if below[parent]}
