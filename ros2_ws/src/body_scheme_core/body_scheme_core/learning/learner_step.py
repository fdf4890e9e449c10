"""The learner's time step as plain functions of its state
(:class:`~body_scheme_core.learning.learner_state.LearnerState`).

:func:`time_step` takes one step's checked inputs through the phases: the observations accepted (the flip check of
:mod:`~body_scheme_core.learning.mirrors`, the workspace), then while bootstrapping the tree search
(:mod:`~body_scheme_core.learning.bootstrap`), afterwards evaluation, detection and repair against the chain-consistent
targets (:mod:`~body_scheme_core.learning.adaptation`) and the root's own watch, and the joint fit when it is due
(:mod:`~body_scheme_core.learning.learner_fit`). A replaced or reinstated edge's book-keeping (:func:`_after_change`)
is here too.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import BodySchemeError
from ..events import Event, format_errors
from ..models import GPModel, RigidJointModel
from ..transforms import invert_transform
from .chain import ChainTargets
from .inputs import filter_covariances, filter_observations
from .learner_fit import calibrate_tree, calibration_due, choose_root, fit_and_check
from .mirrors import MIRROR_BLOCK, decide_flips, rechosen_history

__all__ = ["time_step", "predicted", "workspace"]


def time_step(s, a, observations, stamp, covariances=None):
    """One time step of the learner's state ``s`` on checked inputs
    (:meth:`~body_scheme_core.learning.learner.BodySchemeLearner.update` checks them and makes it all or nothing);
    returns its events."""
    step = s.step
    events = []
    s.prediction = None
    obs, mirrored, mirror_learned = _accept(s, a, observations, step, events)
    covs = _accept_covariances(s, covariances, obs, step, events)
    for part in mirrored:  # its detection's covariance is the other solution's
        covs.pop(part, None)
    if s.config.sensor_root:
        obs[s.root] = np.eye(4)  # the root is the sensor: its own pose in its frame, exactly
        covs.pop(s.root, None)
    if stamp is not None:
        s.last_stamp = stamp
    s.root_pose.add(a, obs)
    s.history.append((step, a, obs))
    if covs:
        s.covariances[step] = covs
    oldest = s.history[0][0]
    while s.covariances and next(iter(s.covariances)) < oldest:
        del s.covariances[next(iter(s.covariances))]
    if s.bootstrapping:
        tree_changed = _bootstrap_step(s, a, obs, step, events)
    else:
        tree_changed = _adapt_step(s, a, obs, step, events)
    if mirror_learned:
        _undo_mirror(s, mirror_learned, step, events)
    if s.tree is not None and (tree_changed or mirror_learned or calibration_due(s, step)):
        fit_and_check(s, step, events)
    s.just_finished = False
    s.step = step + 1
    return events


def _accept(s, a, observations, step, events):
    """The valid observations ``{part: world2part}``, the parts taken in as their mirror image and the parts whose
    mirror image the body scheme holds (:class:`~body_scheme_core.learning.mirrors.MirrorWatch`); rejected ones
    are counted and reported."""
    valid, rejections = filter_observations(observations, s.part_ids, s.config.max_distance, workspace(s))
    for part, reason, detail in rejections:
        s.rejected[reason] += 1
        events.append(Event(step, "input_rejected", f"observation rejected ({reason}): {detail}", child=part))
    cal = s.calibrated
    if cal is None:
        return valid, [], []
    flips = decide_flips(predicted(s, cal, a), valid, s.noise.theta_rot, s.noise.theta_trans,
                         eager=s.config.mirror_hypotheses)
    if flips.mirrored:  # (a counter gains a key only when it counts something)
        s.corrected["flipped"] += len(flips.mirrored)
    if flips.refused:
        s.rejected["flipped"] += len(flips.refused)
    events += [Event(step, "input_rejected", f"observation rejected (flipped): {detail}", child=part)
               for part, detail in flips.refused]
    return flips.observations, flips.mirrored, s.mirror_watch.record(flips.judged, flips.mirrored)


def _undo_mirror(s, parts, step, events):
    """The body scheme holds the mirror image of ``parts``: every stored pose of each is chosen again against the
    mirror of the prediction (:func:`~body_scheme_core.learning.mirrors.rechosen_history`), its detection
    covariance dropped where the pose changed (it is the other solution's), and a ``mirror_undone`` event is
    reported; the caller fits again."""
    cal = s.calibrated
    records, covariances = list(s.history), s.covariances
    for part in parts:
        column = cal.scheme.parts.index(part)
        records, covariances, changed, stored = rechosen_history(
            records, covariances, part, lambda A, c=column: cal.world2root @ cal.scheme.predict_batch(A)[:, c])
        events.append(Event(step, "mirror_undone", f"part {part} was taken in mirrored in more than half of its "
                            f"last {MIRROR_BLOCK} observations: the body scheme held its mirror image; "
                            f"{changed} of its {stored} stored poses chosen again", child=part))
    s.history.clear()
    s.history.extend(records)  # in place: the deque is shared with the phase objects
    s.covariances = covariances


def _accept_covariances(s, covariances, obs, step, events):
    """The usable covariances of the accepted observations ``obs``; dropped ones are counted and reported."""
    if not s.config.detection_covariances:
        return {}
    usable, rejections = filter_covariances(covariances, obs)
    for part, reason, detail in rejections:
        s.rejected[reason] += 1
        events.append(Event(step, "input_rejected", f"covariance rejected ({reason}): {detail}", child=part))
    return usable


def predicted(s, cal, a):
    """``{part: world2part}`` the joint fit ``cal`` predicts at this step's actions ``a``, computed once per step
    and fit (the flip check and the chain targets both need it; :func:`time_step` forgets it first)."""
    if s.prediction is None or s.prediction[0] is not cal:
        s.prediction = (cal, {p: cal.world2root @ T for p, T in cal.scheme.predict(a).items()})
    return s.prediction[1]


def workspace(s):
    """``(root position, reach + workspace_margin)`` once a joint fit exists after bootstrapping, else None (only
    ``max_distance`` applies). The reach is the largest root-to-part distance the calibrated scheme predicts over
    the history's actions, computed once per joint fit."""
    cal = s.calibrated
    if cal is None or s.bootstrapping or not math.isfinite(s.config.workspace_margin):
        return None  # a provisional body scheme's reach says little (a wrong tree's may be short)
    if s.reach is None or s.reach[0] is not cal:
        A = np.stack([a for _, a, _ in s.history]) if s.history else np.zeros((1, s.n_actions))
        root2part = cal.scheme.predict_batch(A)
        s.reach = (cal, float(np.linalg.norm(root2part[:, :, :3, 3], axis=-1).max()))
    return cal.world2root[:3, 3], s.reach[1] + s.config.workspace_margin


def _bootstrap_step(s, a, obs, step, events):
    """Search the tree over the candidates, then end bootstrapping if it is ready; returns whether the tree
    changed (the joint fit then runs at once)."""
    before = s.tree
    s.tree, _ = s.bootstrap.step(s.tree, a, s.pairs.observe(obs), step, events)
    if s.tree is not None and choose_root(s):
        return True  # a new root: the tree is fitted afresh
    if s.bootstrap.finish_if_ready(s.tree, step, events):
        s.bootstrapping = False
        s.just_finished = True
        for entry in (s.pool.tracked[i] for i in s.tree):
            entry.since = 0
        return True
    return s.tree is not None and (before is None or set(before) != set(s.tree))


def _adapt_step(s, a, obs, step, events):
    """Evaluate, detect and repair against the chain-consistent targets; returns whether the tree changed."""
    if s.calibrated is None or s.calibrated.tree != tuple(s.tree):
        # A given scheme: its first joint fit (the root pose) before anything is tested.
        calibrate_tree(s, step, events)
    cal, noise = s.calibrated, s.noise
    world2root = cal.world2root
    targets = ChainTargets(cal.scheme, world2root, a, obs, noise, s.untrusted_parts(cal.scheme), cal.part_std,
                           predicted(s, cal, a))
    changes = s.adaptation.step(s.tree, s.root, a, targets, s.chain_at(), step, events)
    for change in changes:
        _after_change(s, change)
    seen, expected = obs.get(s.root), s.root_watch.expected(world2root)
    errors = None if seen is None or expected is None else targets.observed_errors(expected, seen)
    moved = s.root_watch.check(errors, step, noise.theta_trans, noise.theta_rot)
    s.root_watch.learn_offset(world2root, seen)
    if moved is not None:
        _root_moved(s, *moved, step, events)
    return bool(changes) or moved is not None


def _root_moved(s, tau, cusum, stats, step, events):
    """The root's observations left the calibrated root pose at ``tau`` (its marker moved on the base, or was
    knocked): the root's own observations count from ``tau`` on, the edges at the root learn their new relation
    without a prior, and every edge's detector restarts (its targets used the old root pose)."""
    s.root_since = tau
    pool = s.pool
    for i in s.tree:
        entry = pool.tracked[i]
        if s.root in (entry.parent, entry.child) and isinstance(entry.model, RigidJointModel):
            entry.prior = None
        pool.monitor.forget_since([entry.row], tau)
        pool.monitor.reset_cusum([entry.row])
    events.append(Event(step, "mismatch_detected",
                        f"the root part {s.root} no longer matches its pose in the camera's view: CUSUM "
                        f"{cusum[0]:.2f} (trans) / {cusum[1]:.2f} (rot) reached {s.config.cusum_threshold:g}; "
                        f"window mean {format_errors(stats.trans_error[0], stats.rot_error[0])}; change point "
                        f"estimated at step {tau}: its marker moved; the root pose and the edges at the root are "
                        f"fitted again from its observations since then", child=s.root, model="root pose"))


def _after_change(s, change):
    """Book-keeping of a replaced or reinstated edge: change point, priors below it, cleaned memory."""
    pool = s.pool
    new, old, tau = change
    reinstated = new.origin not in ("replacement", "bridge") or new.n_train == 0 or new.last_used != s.step
    new.since = tau
    if isinstance(new.model, RigidJointModel) and reinstated and new.prior is None:
        new.prior = (new.model.params_.copy(), new.model.param_cov_.copy())
    scheme = s.raw_scheme()
    _, far = scheme.from_root(new.parent, new.child)
    for i in s.tree:
        entry = pool.tracked[i]
        if entry is new:
            continue
        near, _ = scheme.from_root(entry.parent, entry.child)
        if far in scheme.path(near):
            # Below the changed edge: its observations before tau followed the old body; keep what they taught
            # as a prior, and restart its detector. An edge out of the changed edge's far part after a
            # replacement gets none: its relation is to that part's marker, which may be what moved.
            if isinstance(entry.model, RigidJointModel):
                if near == far and not reinstated:
                    entry.prior = None
                elif entry.prior is None:
                    entry.prior = (entry.model.params_.copy(), entry.model.param_cov_.copy())
            pool.monitor.forget_since([entry.row], tau)
            pool.monitor.reset_cusum([entry.row])
    if old.id in pool.tracked:
        _clean_retired(s, old, tau)


def _clean_retired(s, entry, tau):
    """Refit a retired model on its own chain-consistent data before the change point (none after it)."""
    cal = s.calibrated
    if cal is None or not isinstance(entry.model, (RigidJointModel, GPModel)):
        return
    steps = [(k, a, obs) for k, a, obs in s.history if entry.since <= k < tau]
    if not steps:
        return
    scheme = cal.scheme
    u, v = scheme.from_root(entry.parent, entry.child)
    A, Z, S = [], [], []
    for _, a, obs in steps:
        chain = ChainTargets(scheme, cal.world2root, a, obs, s.noise, std=cal.part_std)
        if v in obs:
            Zk, _, _, sk = chain.pair_target(u, v)
            A.append(a)
            Z.append(Zk if u == entry.parent else invert_transform(Zk))
            S.append(sk)
    model = entry.model
    try:
        if isinstance(model, RigidJointModel) and len(A) >= max(model.form.MIN_SAMPLES, model.n_params // 2):
            entry.model = type(model)(model.parent, model.child, model.actions,
                                      **model._hyperparameters()).fit(np.array(A), np.array(Z), np.array(S))
            entry.prior = None
        elif isinstance(model, GPModel) and len(A) >= s.config.train_window // 2:
            entry.model = GPModel(model.parent, model.child, model.actions,
                                  **model.hyperparameters.to_dict()).fit(np.array(A), np.array(Z))
    except (BodySchemeError, np.linalg.LinAlgError):
        pass  # keep the model as it was
