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
(:func:`~.fit_problem.covariance_whitening`), instead of by its marker's per-axis sigmas; the cross terms between
position and rotation are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from ..levenberg_marquardt import INITIAL_DAMPING, damped_increment, next_damping
from ..models import DEFAULT_F_SCALE, GPModel, RigidJointModel, huber_weights, robust_cost
from ..prediction import BodyScheme
from ..rotations import rotvec_matrix
from ..transforms import invert_transform
from .fit_problem import FitProblem, models_below_gp

__all__ = ["Calibration", "calibrate", "chain_targets", "edge_consistency"]

#: Bounds of the Levenberg-Marquardt damping (relative to the diagonal; it starts at ``INITIAL_DAMPING``), and the
#: constant added to the diagonal.
_DAMPING_MIN, _DAMPING_MAX, _DAMPING_FLOOR = 1e-9, 1e6, 1e-12
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
    return steps, invert_transform(world2parent) @ Y


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
        P = invert_transform(P) if inverted else P
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
    below = models_below_gp(scheme)
    free = [k for k, m in enumerate(models) if isinstance(m, RigidJointModel) and k not in fixed and k not in below]
    if axis_sigmas is None:
        isotropic = (sigma_trans / math.sqrt(3.0), sigma_trans / math.sqrt(3.0), sigma_rot / math.sqrt(3.0))

        def axis_sigmas(part):
            return isotropic
    W = np.array(world2root, dtype=float)
    problem = FitProblem(scheme, A, observations, since, free, axis_sigmas, root_since, covariances=covariances)
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
        below_problem = FitProblem(scheme, A, observations, since, free_below, axis_sigmas, root_since, below_gp=True,
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
    cost, iterations, residuals); the step of :mod:`~body_scheme_core.levenberg_marquardt`."""
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
    damping = INITIAL_DAMPING
    iterations = 0
    info = information(J, w)
    g = gradient(J, w, r, prior_offset)
    while iterations < max_iterations:
        iterations += 1
        improved = False
        while damping < _DAMPING_MAX:
            delta = damped_increment(info, g, damping, _DAMPING_FLOOR)
            trial = problem.retract(params, delta)
            trial_W = _retract_pose(W, delta[0:6])
            trial_offset = {k: prior_offset[k] + delta[problem.offset[k]:problem.offset[k] + L.shape[0]]
                            for k, L in prior_L.items()}
            r_t, _, w_t, cost_t = total(trial, trial_W, trial_offset, False)
            if cost_t <= cost:
                decrease = cost - cost_t
                params, W, prior_offset, r, w, cost = trial, trial_W, trial_offset, r_t, w_t, cost_t
                damping = float(next_damping(True, damping, _DAMPING_MIN))
                improved = True
                break
            damping = float(next_damping(False, damping, _DAMPING_MIN))
        if not improved or decrease < _MIN_DECREASE:
            break  # the covariance uses the last Jacobian, a step away from this point at most
        # Converged if even the Gauss-Newton step of the last Jacobian (a step away) would lower the cost by less
        # than _MIN_DECREASE: that saves the Jacobian of a warm start's second iteration.
        g = gradient(J, w, r, prior_offset)
        if -float(g @ damped_increment(info, g, 0.0, _DAMPING_FLOOR)) < _MIN_DECREASE:
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
        targets = invert_transform(Z) if inverted else Z
        models[k] = GPModel(models[k].parent, models[k].child, models[k].actions,
                            **models[k].hyperparameters.to_dict()).fit(A[steps], targets, optimize=optimize)
    return models

