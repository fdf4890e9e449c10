"""The joint fit as the learner runs it: when it is due, what it teaches, what it vetoes.

Functions of the learner's state (:class:`~body_scheme_core.learning.learner_state.LearnerState`) around
:func:`~body_scheme_core.calibration.calibrate`: it runs after every change of the tree and as the usable data grows
(:func:`calibration_due`), on the history window; its residuals teach the noise estimate
(:class:`~body_scheme_core.calibration.NoiseModel`), decide whether the body scheme is trusted (the lack-of-fit test of
:mod:`~body_scheme_core.calibration.consistency`), veto an edge that leaves a part unexplained while bootstrapping, and
flag one afterwards (:func:`fit_and_check`); a root the fit does not explain moves (:func:`choose_root`).
"""

from __future__ import annotations

import math

import numpy as np

from ..calibration import calibrate, covariance_whitening, part_consistency
from ..errors import BodySchemeError
from ..events import Event
from ..models import RigidJointModel
from ..prediction import BodyScheme
from .learner_state import Calibrated
from .root_pose import still_part
from .validity import RATIO_CLIP

__all__ = ["calibration_due", "fit", "calibrate_tree", "fit_and_check", "choose_root", "sample_challengers"]

#: A joint fit also runs once the steps usable by the newest edge of the tree grew by this fraction since the last fit
#: (every step early on and right after a change, every ``calibration_period`` steps at most), times the fit's free
#: parameters per ``_GROWTH_PARAMS`` when more: a fit costs in proportion to its parameters, so larger trees are
#: refitted after proportionally more new data (the 2-DOF arm every 10 %, the 6-DOF arm every 20 %).
_CALIBRATION_GROWTH = 0.1
_GROWTH_PARAMS = 30
#: Edges tried when the calibrated scheme leaves a part unexplained while bootstrapping, and the iterations of each
#: trial fit (:func:`_veto_inconsistent_edges`).
_SUSPECTS = 3
_TRIAL_ITERATIONS = 6


def _lacks_fit(s, cal, part):
    """Whether the last joint fit's residuals of ``part`` depend on the commands (the lack-of-fit test at
    ``config.consistency_alpha``, Bonferroni over the parts, and by a fraction that matters)."""
    test = cal.consistency.get(part)
    return test is not None and test.lacks_fit(s.config.consistency_alpha / len(s.part_ids))


def _veto_inconsistent_edges(s, step, events, rounds=3):
    """While bootstrapping: when the calibrated body scheme does not explain a part's absolute observations,
    one edge on that part's path is vetoed and the tree searched again (at most ``rounds`` times per step).

    Relative observations carry the parent's orientation noise times the link length, so with few samples a
    candidate that ignores an action (or has the wrong form) can pass the paper's validity test on them; the
    child's chain-consistent errors after the joint fit have no such lever arm. A wrong edge can absorb its own
    child's errors (it has parameters to spare) and push them onto the parts below, so the edges on the path of
    the first unexplained part are tried, nearest it first (at most ``_SUSPECTS``): the tree without one is
    searched and calibrated, and the edge whose removal explains the observations best (the first that explains
    them all) is vetoed.
    """
    for _ in range(rounds):
        cal = s.calibrated
        if s.tree is None or cal is None or cal.tree != tuple(s.tree):
            return
        bad = _inconsistent_edges(s, cal)
        if not bad:
            return
        first = bad[0]
        far = cal.scheme.models[first]
        _, far_part = cal.scheme.from_root(far.parent, far.child)
        position = {id(m): k for k, m in enumerate(cal.scheme.models)}
        # Nearest the unexplained part first (most often the culprit), at most _SUSPECTS of them.
        path = cal.scheme.path(far_part)[1:]
        suspects = [position[id(cal.scheme.edge_into(p)[2])] for p in reversed(path)][:_SUSPECTS]
        best = None
        for k in suspects:
            trial = s.bootstrap.search(s.tree, step, None, exclude=[s.tree[k]])
            if trial is None:
                continue
            fitted = fit(s, trial, step, max_iterations=_TRIAL_ITERATIONS)
            if fitted is None:
                continue
            trial_cal = fitted[0]
            score = (len(_inconsistent_edges(s, trial_cal)), trial_cal.rms)
            if best is None or score < best[0]:
                best = (score, k, fitted)
            if score[0] == 0:
                break  # this tree explains every observation: no need to try the others
        k = suspects[-1] if best is None else best[1]
        entry = s.pool.tracked[s.tree[k]]
        s.bootstrap.veto(entry.id)
        # Its two parts may be joined by more joints than any layer holds (a tool seen past six of them): their
        # chain, identified again every few samples while an edge of theirs leaves a part unexplained.
        s.bootstrap.chains.identify(entry.parent, entry.child, s.tree, step, events,
                                        f"{entry.describe()} leaves part {far_part} unexplained", growth=0.0)
        why = (f" (vetoed {entry.describe()}: without it the calibrated body scheme explains the absolute "
               f"observations best)")
        s.tree = s.bootstrap.search(s.tree, step, events, why)
        if s.tree is None:
            return
        if best is not None and best[2][0].tree == tuple(s.tree):
            _adopt(s, *best[2], step, events)  # its residuals teach the noise as any joint fit's
        else:
            calibrate_tree(s, step, events)


def _inconsistent_edges(s, cal):
    """Positions (in ``cal.scheme.models``, breadth-first) of the edges whose child the calibrated scheme does
    not explain: its observations' mean error of at least one threshold in either channel, or residuals that
    depend on the commands (:func:`_lacks_fit`)."""
    position = {id(m): k for k, m in enumerate(cal.scheme.models)}
    bad = []
    for _, child, model, _ in cal.scheme.edges:
        n, ratio_t, ratio_r = cal.part_ratios.get(child, (0, 0.0, 0.0))
        if (n >= s.config.min_test_samples and max(ratio_t, ratio_r) >= 1.0) or _lacks_fit(s, cal, child):
            bad.append(position[id(model)])
    return bad


# ---------------------------------------------------------------------- the joint fit
def calibration_due(s, step):
    cal = s.calibrated
    if cal is None or cal.tree != tuple(s.tree):
        return True
    if step - cal.step >= s.config.calibration_period:
        return True
    # Early on (and right after a change) the usable window grows: fit again once it grew by a tenth.
    n_params = sum(m.n_params for m in cal.scheme.models if isinstance(m, RigidJointModel))
    growth = _CALIBRATION_GROWTH * max(1.0, n_params / _GROWTH_PARAMS)
    if step - cal.step < max(1, math.ceil(growth * cal.n_steps)):
        return False
    since = max((s.pool.tracked[i].since for i in s.tree), default=0)
    if s.history[0][0] >= since:
        usable = len(s.history)
    else:
        usable = next(k for k, (s, _, _) in enumerate(reversed(s.history)) if s < since)
    return usable > cal.n_steps


def fit(s, tree, step, warm=True, max_iterations=20):
    """Joint fit of the root pose and the models of ``tree`` on the history
    (:func:`~body_scheme_core.calibration.calibrate`), and the lack-of-fit test of every part
    (:mod:`~body_scheme_core.calibration.consistency`): ``(Calibrated, Calibration)``, or None if the fit failed.
    Changes nothing."""
    pool = s.pool
    entries = [pool.tracked[i] for i in tree]
    cal = s.calibrated
    if warm and cal is not None and s.bootstrapping:
        # Warm start: the last fit's version of every model that is still in the tree.
        fitted = dict(zip(cal.tree, cal.scheme.models, strict=True))
        models = [fitted[i] if i in fitted else pool.model_of(e) for i, e in zip(tree, entries, strict=True)]
    else:
        models = [pool.model_of(e) for e in entries]
    scheme = BodyScheme(s.part_ids, s.root, models)
    history = list(s.history)
    steps = np.array([k for k, _, _ in history])
    A = np.stack([a for _, a, _ in history])
    observations = [obs for _, _, obs in history]
    noise, covariances = s.noise, None
    if s.covariances and s.config.detection_covariances:
        scaled = {k: {p: noise.detection_covariance(C) for p, C in covs.items()} for k, covs in s.covariances.items()}
        covariances = [scaled.get(k) for k, _, _ in history]
    since = [int(np.searchsorted(steps, e.since)) for e in entries]
    priors = {k: e.prior for k, e in enumerate(entries)
              if e.prior is not None and isinstance(models[k], RigidJointModel)}
    world2root = cal.world2root if cal is not None else s.root_pose.pose(scheme)
    try:
        result = calibrate(scheme, world2root, A, observations, noise.sigma_trans, noise.sigma_rot,
                           since=since, priors=priors, f_scale=s.config.f_scale,
                           gp_optimize=s.config.gp_optimize, max_iterations=max_iterations,
                           axis_sigmas=noise.axis_sigmas, root_since=int(np.searchsorted(steps, s.root_since)),
                           covariances=covariances)
    except (np.linalg.LinAlgError, BodySchemeError):
        return None
    # The parts' predictive std, averaged over (at most 10 of) the window's action vectors: the chain targets'
    # thresholds use it every step without propagating every model's uncertainty each time.
    pick = np.linspace(0, len(A) - 1, min(len(A), 10)).round().astype(int)
    _, std = result.scheme.predict_batch(A[pick], return_std=True)
    part_std = {p: std[:, k].mean(axis=0) for k, p in enumerate(result.scheme.parts)}
    usable = int(np.sum(steps >= max((e.since for e in entries), default=0)))
    consistency = part_consistency(result.parts, result.whitened, A[result.steps])
    return Calibrated(result.scheme, result.world2root, step, usable, tuple(tree), result.rms,
                      result.part_ratios(noise.theta_trans, noise.theta_rot, RATIO_CLIP), part_std,
                      consistency), result


def calibrate_tree(s, step, events):
    """Joint fit of the current tree, adopted (:func:`_adopt`)."""
    fitted = fit(s, s.tree, step)
    if fitted is None:
        return  # keep the previous estimate; the next step tries again
    _adopt(s, *fitted, step, events)


def _adopt(s, cal, result, step, events):
    """Make a joint fit of the current tree the learner's: the noise estimate learns from its residuals, after
    bootstrapping its models replace the tree's, and a change of what it explains is reported."""
    s.calibrated = cal
    _learn_noise(s, cal, result)
    if not s.bootstrapping:
        pool = s.pool
        entries = [pool.tracked[i] for i in s.tree]
        for entry, model in zip(entries, cal.scheme.models, strict=True):
            entry.model = model
        history_full = len(s.history) == s.history.maxlen
        oldest = s.history[0][0]
        for entry in entries:
            if entry.prior is not None and history_full and entry.since <= oldest:
                entry.prior = None  # every observation in the window is usable: the window alone decides
    _report_trust(s, cal, step, events)


def _learn_noise(s, cal, result):
    """Estimate the noise from the fit's residuals and hand the thresholds on.

    Only parts the fit explains speak: tested by the lack-of-fit test and passing it, with mean errors below the
    thresholds, and not below a GP edge; a wrong model's residuals, or a GP's approximation error, would otherwise
    make the noise look larger, the thresholds looser and a wrong model valid. While bootstrapping the tree is
    provisional: the estimate may lower the prior, not exceed it (``cap``). With ``sensor_root`` the root's pose
    is given, not observed: it says nothing about the noise."""
    explained = [p for p, test in cal.consistency.items()
                 if test.tested and not _lacks_fit(s, cal, p) and max(cal.part_ratios[p][1:]) < 1.0
                 and not (s.config.sensor_root and p == s.root)]  # the sensor's own pose is exact
    use = np.isin(result.parts, explained) & result.coupled  # below a GP edge its approximation would count
    fraction = 1.0 - result.n_params / max(6 * int(result.coupled.sum()), 1)
    # A provisional tree (few samples, maybe a wrong model) says little about the detector.
    detected = None if s.bootstrapping else _detection_whitened(s, result, use)
    s.noise.update(result.parts[use], result.residual_t[use], result.residual_r[use], result.positions[use],
                   fraction, cap=s.bootstrapping, detected=detected)
    s.share_thresholds()


def _detection_whitened(s, result, use):
    """``(mask, whitened)`` of the joint fit's residuals ``use``: which came with a detection's own covariance,
    and those whitened by it as given (:meth:`~body_scheme_core.calibration.NoiseModel.update`); None without any."""
    mask = result.detected[use]
    if not mask.any():
        return None
    history = list(s.history)  # the joint fit's rows (result.steps index it)
    rows = np.flatnonzero(use)[mask]
    records = [(history[result.steps[k]], int(result.parts[k])) for k in rows]
    C = np.stack([s.covariances[step][part] for (step, _, _), part in records])
    W_t, W_r = covariance_whitening(C, np.stack([obs[part][:3, :3] for (_, _, obs), part in records]))
    whitened = np.zeros((mask.size, 6))
    whitened[mask] = np.hstack([np.einsum("nij,nj->ni", W_t, result.residual_t[rows]),
                                np.einsum("nij,nj->ni", W_r, result.residual_r[rows])])
    return mask, whitened


def _report_trust(s, cal, step, events):
    """A ``trust_changed`` event when the set of parts whose residuals lack fit changed."""
    failing = tuple(sorted(p for p in cal.consistency if _lacks_fit(s, cal, p)))
    if failing == s.lack_of_fit:
        return
    if failing:
        worst = max(failing, key=lambda p: cal.consistency[p].F)
        t = cal.consistency[worst]
        reason = (f"not trusted: the body scheme does not explain part(s) {list(failing)}: their residuals depend "
                  f"on the commands (part {worst}: F = {t.F:.1f}, p = {t.p:.1g}, {100 * t.explained:.0f} % of "
                  f"the variance over {t.n} observations)")
    else:
        reason = "trusted again: the residuals of every part are independent of the commands (noise)"
    events.append(Event(step, "trust_changed", reason))
    s.lack_of_fit = failing


def _flag_unexplained(s, step, events):
    """After a joint fit in steady state: the root-most part the scheme does not explain puts the edge into it
    in mismatch (once per ``history_length`` steps and part), so that the pair, other classes and other pairs
    across the cut are searched for a model that explains it (:func:`~body_scheme_core.learning.detection.flag`).
    A root it does not explain moves: the part that moves least becomes the root (:func:`choose_root`)."""
    cal = s.calibrated
    if cal is None or cal.tree != tuple(s.tree):
        return
    scheme = cal.scheme
    if scheme.root in s.lack_of_fit and not s.adaptation.mismatch and choose_root(s):
        return  # the root moves: the next step fits the tree from the part that moves least
    untrusted = s.untrusted_parts(scheme)
    failing = [p for p in s.lack_of_fit if p not in untrusted and p != scheme.root
               and step - s.unexplained.get(p, -math.inf) >= s.config.history_length]
    if not failing:
        return
    part = min(failing, key=lambda p: len(scheme.path(p)))
    parent, child, _, _ = scheme.edge_into(part)
    entry = next(s.pool.tracked[i] for i in s.tree
                 if {s.pool.tracked[i].parent, s.pool.tracked[i].child} == {parent, child})
    if entry.id in s.adaptation.mismatch:
        return
    s.unexplained[part] = step
    t = cal.consistency[part]
    s.adaptation.flag(entry, step, events,
                      f"the body scheme does not explain part {part}: its residuals depend on the commands "
                      f"(F = {t.F:.1f}, p = {t.p:.1g}, {100 * t.explained:.0f} % of their variance)")


def fit_and_check(s, step, events):
    """The joint fit, then what follows it: while bootstrapping the vetoes, right after it the GP challengers,
    afterwards the parts the fit leaves unexplained."""
    calibrate_tree(s, step, events)
    if s.bootstrapping:
        _veto_inconsistent_edges(s, step, events)
    elif s.just_finished:
        sample_challengers(s, step, events)
    else:
        _flag_unexplained(s, step, events)


def choose_root(s):
    """Without ``config.root``: make the part whose observations move least the root, as the joint fit assumes
    the root is fixed in the camera's view (:func:`~body_scheme_core.learning.root_pose.still_part`). Returns whether
    the root changed."""
    if s.config.root is not None:
        return False
    root = still_part(s.part_ids, [obs for _, _, obs in s.history], s.noise.sigma_trans, s.noise.sigma_rot)
    if root is None or root == s.root:
        return False
    s.root = s.root_pose.root = root
    s.root_pose.invalidate()
    s.root_watch.restart()
    s.root_since = 0
    s.calibrated = None  # its root pose belongs to the old root
    return True


def sample_challengers(s, step, events):
    """After bootstrapping: GP challengers of the tree's rigid joints
    (:func:`~body_scheme_core.learning.challengers.sample_challengers`)."""
    if s.calibrated is None or s.calibrated.tree != tuple(s.tree):
        return
    chain_at = s.chain_at()
    _, a, obs = s.history[-1]
    s.adaptation.sample_challengers(s.tree, chain_at(a, obs), chain_at, step, events)
