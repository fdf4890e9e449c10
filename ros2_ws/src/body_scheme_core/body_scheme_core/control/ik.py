"""Gradient-based control on a body scheme: inverse kinematics for the position of one part (paper Sec. III-D).

The forward model of a :class:`~body_scheme_core.prediction.scheme.BodyScheme` is continuous, so its Jacobian (Eq. 10)
drives a damped least-squares (Levenberg-Marquardt) search for actions that bring a part to a target position. The
solver is honest: it reports ``success=False`` with a reason rather than returning a wrong answer labelled as success. A
solution the *model* reaches is not enough: the body scheme is learned, so the part's predicted position has an
uncertainty (:func:`~body_scheme_core.prediction.uncertainty.position_std`: the joint fit's parameter covariance and the
GPs' latent variances, propagated along the chain), and ``success`` also needs the residual plus the radius that holds
the part's true position with the probability of ``confidence`` standard deviations (95.4 % at 2;
:func:`~body_scheme_core.prediction.uncertainty.error_radius`) within the tolerance.

The residual is a separate small class so that a pose target (position and orientation) can be added later by
writing another residual with the same ``evaluate``/``jacobian`` pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from ..prediction import error_radius, position_covariance
from ..transforms import check_transform, invert_transform

__all__ = ["IKResult", "solve_ik", "trained_bounds"]

#: Stop an attempt when the residual improved by less than this fraction over ``_STALL_WINDOW`` iterations.
_STALL_FRACTION = 1e-3
_STALL_WINDOW = 8
#: With ``confidence > 0`` the search stops at this fraction of the tolerance, or at this residual (m) if smaller: the
#: residual is part of the bound, and a loose tolerance should not leave the part centimetres off in the model.
_MODEL_FRACTION = 0.1
_MODEL_STOP = 1e-3
#: Relative step size below which an attempt counts as stuck.
_XTOL = 1e-10
#: Damping above which the local linear model is useless: the attempt is stuck.
_MAX_DAMPING = 1e12
#: Step of the forward differences (rad or m) when ``derivatives="forward"``: truncation error ~1e-7, round-off
#: ~1e-16 / 1e-7 = 1e-9, both far below what the damped step needs.
_FORWARD_STEP = 1e-7


@dataclass(frozen=True, eq=False)
class IKResult:
    """Outcome of :func:`solve_ik`.

    Attributes
    ----------
    actions : ndarray, shape (m,)
        Best full action vector found, always within the joint limits (also when ``success`` is False).
    success : bool
        True only if the model reaches the target (``converged``) and ``error_bound`` is at most ``tol``.
    iterations : int
        Total Levenberg-Marquardt iterations over all attempts.
    residual : float
        Distance in m between the predicted part position at ``actions`` and the target (NaN if not evaluated).
    reason : str
        Human-readable explanation, e.g. ``"converged"`` or ``"target unreachable: best residual 0.231 m after 3
        restarts"``.
    restarts : int
        Number of random restarts used.
    position : ndarray, shape (3,)
        Predicted position of the part in the root frame at ``actions`` (NaN if not evaluated).
    position_std : float
        The RMS length (m, ``sqrt(trace(cov))``) of the error of the part's predicted position at
        ``actions``; 0 for exact (engineered) models, NaN if not evaluated. The root's pose in the world is not
        included.
    converged : bool
        Whether the residual at ``actions`` is at most ``tol`` (the model reaches the target, however unsure).
    error_bound : float
        The residual plus :func:`~body_scheme_core.prediction.uncertainty.error_radius` of the predicted position's
        covariance at ``confidence`` (m): how far from the target the part may truly go, with the probability of
        ``confidence`` standard deviations of a normal variable (95.4 % at 2).
    """

    actions: np.ndarray
    success: bool
    iterations: int
    residual: float
    reason: str
    restarts: int = 0
    position: np.ndarray | None = None
    position_std: float = float("nan")
    converged: bool = False
    error_bound: float = float("nan")


class _PositionResidual:
    """Residual ``target - position(part)`` in the root frame as a function of the varied actions ``x``.

    ``evaluate`` returns the residual together with the chain state it computed, which ``jacobian`` then reuses,
    so the forward chain is evaluated once per iteration.
    """

    def __init__(self, scheme, part, target, a_full, active, derivative_step):
        self.scheme = scheme
        self.part = part
        self.target = target
        self.a = a_full.copy()
        self.active = active
        self.derivative_step = derivative_step

    def evaluate(self, x):
        """Residual (3,) and the chain state ``(T, dT)`` at ``x``."""
        self.a[self.active] = x
        if self.derivative_step is None:
            T, dT = self.scheme.chain_transforms(self.a, self.part), None
        else:
            T, dT = self.scheme.chain_transforms(self.a, self.part, derivative_step=self.derivative_step)
        root2part = np.eye(4)
        for Ti in T:
            root2part = root2part @ Ti
        return self.target - root2part[:3, 3], (T, dT)

    def jacobian(self, x, state):
        """d residual / d x, shape (3, k): minus the position Jacobian restricted to the varied actions."""
        self.a[self.active] = x
        T, dT = state
        J = self.scheme.position_jacobian(self.a, self.part, local_transforms=T, local_derivatives=dT)
        return -J[:, self.active]


def _as_vector(value, m, name):
    v = np.asarray(value, dtype=float)
    try:
        v = np.broadcast_to(v, (m,)).copy()
    except ValueError as exc:
        raise InvalidInputError(f"{name} must be a scalar or have shape ({m},), got {v.shape}") from exc
    if np.any(np.isnan(v)):
        raise InvalidInputError(f"{name} contains NaN")
    return v


def _attempt(residual, x0, lo, hi, tol, max_iterations, damping):
    """One Levenberg-Marquardt run with bound projection.

    Returns
    -------
    x : ndarray, shape (k,)
        Best point of the run.
    e : ndarray, shape (3,)
        Residual at ``x``.
    iterations : int
    status : str
        ``"converged"``, ``"stuck"`` or ``"max_iterations"``.
    """
    x = x0.copy()
    e, state = residual.evaluate(x)
    F = 0.5 * float(e @ e)
    if np.sqrt(2.0 * F) <= tol:
        return x, e, 0, "converged"
    J = residual.jacobian(x, state)
    g = J.T @ e  # gradient of F = |e|^2 / 2 (J is de/dx); descent goes along -g
    JtJ = J.T @ J
    mu = damping * max(float(np.max(np.diag(JtJ))), 1e-12)
    nu = 2.0
    history = [np.sqrt(2.0 * F)]
    width = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    for it in range(1, max_iterations + 1):
        # Variables pinned at a bound whose descent direction points outside are held fixed (projected LM); the
        # others take a damped Gauss-Newton step that is then clipped into the box.
        at_lo = (x <= lo + 1e-12 * width) & (g > 0.0)
        at_hi = (x >= hi - 1e-12 * width) & (g < 0.0)
        free = ~(at_lo | at_hi)
        if not np.any(free) or np.max(np.abs(g[free])) <= 1e-14:
            return x, e, it - 1, "stuck"
        H = JtJ[np.ix_(free, free)] + mu * np.eye(int(free.sum()))
        try:
            step = np.linalg.solve(H, -g[free])
        except np.linalg.LinAlgError:
            return x, e, it, "stuck"
        x_new = x.copy()
        x_new[free] += step
        np.clip(x_new, lo, hi, out=x_new)
        h = x_new - x
        if np.linalg.norm(h) <= _XTOL * (np.linalg.norm(x) + _XTOL):
            return x, e, it, "stuck"
        e_new, state_new = residual.evaluate(x_new)
        F_new = 0.5 * float(e_new @ e_new)
        # Gain ratio of actual to linearly predicted decrease (the step was clipped, so predict with the clipped h).
        e_lin = e + J @ h
        predicted = F - 0.5 * float(e_lin @ e_lin)
        rho = (F - F_new) / predicted if predicted > 0.0 else -1.0
        if F_new < F and rho > 0.0:
            x, e, state, F = x_new, e_new, state_new, F_new
            if np.sqrt(2.0 * F) <= tol:
                return x, e, it, "converged"
            J = residual.jacobian(x, state)
            g = J.T @ e
            JtJ = J.T @ J
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
        else:
            mu *= nu
            nu *= 2.0
            if mu > _MAX_DAMPING * max(float(np.max(np.diag(JtJ))), 1.0):
                return x, e, it, "stuck"
        history.append(np.sqrt(2.0 * F))
        if len(history) > _STALL_WINDOW and history[-1 - _STALL_WINDOW] - history[-1] < (
                _STALL_FRACTION * history[-1 - _STALL_WINDOW]):
            return x, e, it, "stuck"
    return x, e, max_iterations, "max_iterations"


def trained_bounds(scheme, lower, upper):
    """Joint limits shrunk to the actions the body scheme's local models were trained on.

    A learned local model is only trustworthy near its training inputs: a camera sees a link only in part of its
    joint range, and beyond that a GP's mean falls back to the training mean. Measured on a 300-step rendered
    session of ``powercube_6dof``: the shoulder model ``2 -> 3`` had no samples for a1 > 0.6 rad (marker 3 out of
    view) and was 127 mm off at the joint limit; IK within the joint limits then left 5 of 20 targets more than
    100 mm away (median 30 mm, max 274 mm); within the trained range none (median 14 mm, max 33 mm).

    Parameters
    ----------
    scheme : BodyScheme
    lower, upper : array-like, shape (m,)
        Joint limits.

    Returns
    -------
    lower, upper : ndarray, shape (m,)
        Per action the intersection of its limits with the training range of every tree model depending on it
        (:meth:`~body_scheme_core.models.base.LocalModel.training_range`); actions no learned model depends on keep
        their limits. Where the two do not overlap, the bounds collapse onto the training range's nearest end.
    """
    lower = np.array(lower, dtype=float)
    upper = np.array(upper, dtype=float)
    if lower.shape != upper.shape or lower.ndim != 1:
        raise InvalidInputError(f"lower and upper must be vectors of one length, got {lower.shape} and {upper.shape}")
    for model in scheme.models:
        trained = model.training_range()
        if trained is None:
            continue
        for index, low, high in zip(model.actions, *trained, strict=True):
            if index >= lower.size:
                raise InvalidInputError(f"{model.describe()} depends on action {index}; the limits have {lower.size}")
            lower[index] = min(max(lower[index], low), high)
            upper[index] = max(min(upper[index], high), lower[index])
    return lower, upper


def solve_ik(scheme, part, target_position, a0, lower, upper, tol=1e-3, max_iterations=100, damping=0.1,
             n_restarts=3, rng=None, world2root=None, derivatives="forward", confidence=2.0, prefer_certain=False):
    """Actions that bring ``part`` to a target position, by damped least squares on the body scheme.

    Levenberg-Marquardt with adaptive damping (Nielsen's update) on ``|target - position(part)|^2``, using
    :meth:`BodyScheme.position_jacobian`. Joint limits are enforced by projection: variables at a bound that the
    gradient pushes outward are held, every step is clipped into the box. Only the actions on the part's path in the
    tree (and with ``lower < upper``) are varied; all others keep their value from ``a0``. When an attempt stalls
    away from the target, it restarts from a random point within the limits, up to ``n_restarts`` times.

    Parameters
    ----------
    scheme : BodyScheme
    part : int
        Part whose origin should reach the target.
    target_position : array-like, shape (3,)
        Target in the root frame, or in the world frame if ``world2root`` is given.
    a0 : array-like, shape (m,)
        Start action vector (clipped into the limits first).
    lower, upper : float or array-like, shape (m,)
        Joint limits; may be infinite (restarts then sample within pi of ``a0``).
    tol : float
        Position tolerance in m for success.
    max_iterations : int
        Iteration budget per attempt (the first and each restart).
    damping : float
        Initial damping relative to the largest diagonal entry of ``J^T J``. 0.1 took a third fewer iterations than
        1e-3 from random starts on a 6-DOF GP scheme (fewer rejected over-long first steps).
    n_restarts : int
        Random restarts allowed after the first attempt.
    rng : numpy.random.Generator, int or None
        Source of restart points; ``None`` uses a fixed seed so results are reproducible.
    world2root : array-like, shape (4, 4), optional
        Pose of the root in the world frame; if given, ``target_position`` is in world coordinates.
    derivatives : {"forward", "analytic"}
        How the local models are differentiated inside :meth:`BodyScheme.position_jacobian`. ``"forward"``:
        forward differences computed in the same batched ``predict`` call as the forward chain (one model call per
        edge and iteration; about 1.5x faster on GP schemes). ``"analytic"``: each model's ``jacobian``. Both give
        the same iterates up to ~1e-7.
    confidence : float
        The level of ``error_bound``, in standard deviations: its radius holds the part's true position with the
        probability that a normal variable lies within ``confidence`` sigma (95.4 % at 2); 0: the model's word
        alone.
    prefer_certain : bool
        Use every restart and return, among the solutions that reach the target in the model, the one with the
        smallest ``error_bound`` (at ``confidence`` 0: the least ``position_std``; e.g. postures near the training
        data); default: the first.

    Returns
    -------
    result : IKResult
        ``success`` is True only if the residual is at most ``tol`` and so is ``error_bound``; otherwise ``reason``
        says why (``"part not in body scheme"``, ``"no action influences part"``, ``"target unreachable: ..."``,
        ``"max iterations reached: ..."``, ``"not sure enough: ..."``) and ``actions`` is the best vector found,
        within the limits.

    Raises
    ------
    InvalidInputError
        On malformed arguments (shapes, NaN, ``lower > upper``, non-positive ``tol``).
    """
    a0 = np.asarray(a0, dtype=float)
    if a0.ndim != 1 or not np.all(np.isfinite(a0)):
        raise InvalidInputError(f"a0 must be a finite vector of shape (m,), got shape {a0.shape}")
    m = a0.shape[0]
    lower = _as_vector(lower, m, "lower")
    upper = _as_vector(upper, m, "upper")
    if np.any(lower > upper):
        raise InvalidInputError(f"lower must not exceed upper, got lower={lower.tolist()} upper={upper.tolist()}")
    target = np.asarray(target_position, dtype=float)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise InvalidInputError(f"target_position must be a finite vector of shape (3,), got {target.shape}")
    if not (np.isfinite(tol) and tol > 0.0):
        raise InvalidInputError(f"tol must be a finite number > 0, got {tol!r}")
    if not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
        raise InvalidInputError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    if not (isinstance(n_restarts, (int, np.integer)) and n_restarts >= 0):
        raise InvalidInputError(f"n_restarts must be an integer >= 0, got {n_restarts!r}")
    if not (np.isfinite(damping) and damping > 0.0):
        raise InvalidInputError(f"damping must be a finite number > 0, got {damping!r}")
    if not (np.isfinite(confidence) and confidence >= 0.0):
        raise InvalidInputError(f"confidence must be a finite number >= 0, got {confidence!r}")
    if derivatives not in ("forward", "analytic"):
        raise InvalidInputError(f"derivatives must be 'forward' or 'analytic', got {derivatives!r}")
    if world2root is not None:
        root2world = invert_transform(check_transform(world2root, name="world2root"))
        target = root2world[:3, :3] @ target + root2world[:3, 3]
    if not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(0 if rng is None else rng)

    a = np.clip(a0, lower, upper)
    nan3 = np.full(3, np.nan)
    if part not in scheme:
        return IKResult(a, False, 0, float("nan"), f"part not in body scheme: {part!r} is not one of {scheme.parts}",
                        position=nan3)
    part = int(part)
    active = np.array([k for k in scheme.path_actions(part) if k < m and upper[k] > lower[k]], dtype=int)
    residual = _PositionResidual(scheme, part, target, a, active,
                                 _FORWARD_STEP if derivatives == "forward" else None)
    if active.size == 0:
        e, _ = residual.evaluate(np.zeros(0))
        r = float(np.linalg.norm(e))
        if r > tol:
            return _result(scheme, part, a, e, target, tol, confidence, 0, 0,
                           f"no action influences part {part}: residual {r:.3g} m cannot be reduced")
        return _result(scheme, part, a, e, target, tol, confidence, 0, 0, "converged: target already reached")

    lo, hi = lower[active], upper[active]
    # Restart box: the limits, or pi around the start where a limit is infinite.
    start = a[active]
    box_lo = np.where(np.isfinite(lo), lo, np.maximum(lo, start - np.pi))
    box_hi = np.where(np.isfinite(hi), hi, np.minimum(hi, start + np.pi))

    best_x, best_e, best_status = None, None, None
    reached = []  # (x, e) of the attempts that reached the target in the model
    iterations = 0
    restarts = 0
    x0 = start
    # With an uncertainty to add, the model's own residual is driven well below the tolerance (it is part of the
    # bound); without, reaching the tolerance is enough.
    stop = tol if confidence == 0 else min(_MODEL_FRACTION * tol, _MODEL_STOP)
    while True:
        x, e, it, status = _attempt(residual, x0, lo, hi, stop, max_iterations, damping)
        iterations += it
        if best_e is None or e @ e < best_e @ best_e:
            best_x, best_e, best_status = x, e, status
        if status == "converged" or float(np.linalg.norm(e)) <= tol:
            reached.append((x, e))
        if (reached and not prefer_certain) or restarts >= n_restarts:
            break
        restarts += 1
        x0 = rng.uniform(box_lo, box_hi)

    def full(x):
        vector = a.copy()
        vector[active] = np.clip(x, lo, hi)
        return vector

    if len(reached) > 1:  # prefer_certain: the solution with the smallest bound (the least uncertain at confidence 0)
        best_x, best_e = min(reached, key=lambda xe: _uncertainty(scheme, part, full(xe[0]), xe[1],
                                                                  confidence)[1 if confidence > 0 else 0])
    r = float(np.linalg.norm(best_e))
    plural = "restart" if restarts == 1 else "restarts"
    if r <= tol:
        reason = f"converged: residual {r:.3g} m after {iterations} iterations and {restarts} {plural}"
    elif best_status == "max_iterations":
        reason = f"max iterations reached: best residual {r:.3g} m after {restarts} {plural}"
    else:
        reason = f"target unreachable: best residual {r:.3g} m after {restarts} {plural}"
    return _result(scheme, part, full(best_x), best_e, target, tol, confidence, iterations, restarts, reason)




def _uncertainty(scheme, part, actions, e, confidence):
    """``(position_std, error_bound)`` of the solution ``actions`` with residual vector ``e``."""
    cov = position_covariance(scheme, actions, part)
    return float(np.sqrt(max(np.trace(cov), 0.0))), float(np.linalg.norm(e)) + error_radius(cov, confidence)


def _result(scheme, part, actions, e, target, tol, confidence, iterations, restarts, reason):
    """The IKResult of a solution with residual vector ``e``: converged and sure, or why not."""
    r = float(np.linalg.norm(e))
    std, bound = _uncertainty(scheme, part, actions, e, confidence)
    success = r <= tol and bound <= tol
    if r <= tol and not success:
        reason = (f"not sure enough: the model reaches the target (residual {r:.3g} m) but the predicted error "
                  f"bound ({confidence:g} sigma level) is {bound:.3g} m > tolerance {tol:.3g} m")
    return IKResult(actions, success, iterations, r, reason, restarts=restarts, position=target - e,
                    position_std=std, converged=r <= tol, error_bound=bound)
