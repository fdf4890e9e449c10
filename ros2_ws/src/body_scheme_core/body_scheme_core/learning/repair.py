"""Repair: a replacement for a tree model in mismatch, from memory or newly learned (paper Sec. III-E, Eq. 11).

For each edge in mismatch, first the memory is asked: a remembered model (of that pair, or of any pair that
reconnects the two halves of the tree, :func:`tree_halves`) whose mean errors since the estimated change point are
valid is put back (``model_reinstated``). Otherwise replacement models are sampled for the pair, ordered by relative
complexity to the failed model (Eq. 11) and class rank, and trained *only* on data since the change point: the recent
raw history is replayed to them prequentially at once. If none is valid after ``bridge_patience`` steps, candidates of
every other pair that reconnects the two halves are sampled too (a local re-bootstrap), so that a wrong edge is never
permanent. The cheapest valid candidate by ``C(M2|M1)`` plus its error and class penalty replaces the failed model
(``model_replaced``); a different pair also reports ``structure_changed``. The other candidates keep learning until
they are frozen: a simpler one that becomes valid takes over unless the installed model is clearly better.

The steps are functions of ``adapt`` (:class:`~body_scheme_core.learning.adaptation.Adaptation`: the pool, the
configuration, the history, the edges in mismatch, the replacements refining and the pairs that failed); they
change it and the tree in place and append their events. Comparisons of models take the pool and the
configuration only.
"""

from __future__ import annotations

from typing import NamedTuple

import networkx as nx
import numpy as np

from ..errors import ModelFileError
from ..events import Event, format_errors
from ..state_values import integer, listing, part_id
from .chain_refit import chain_replacements
from .chain_search import ChainNotIdentified, identify_chain, order_decided
from .memory import retire
from .quality import model_cost, nests, relative_complexity
from .structure import action_subsets, kinds_for, replacement_candidates
from .tracked import CANDIDATE, MEMORY, TREE, TrackedModel, nested_models

__all__ = ["Change", "Replacement", "tree_halves", "bridge_relative_complexity", "repair", "refine_choices",
           "choose_replacement", "clearly_better", "dominating", "replay", "refining_state", "failed_state",
           "failed_from_state", "refining_from_state"]

#: Chain-consistent samples since the change point before a failed chain's replacements are fitted, and how many
#: more (at least; a quarter more later) before they are fitted again.
CHAIN_MIN_SAMPLES = 8
CHAIN_RETRY = 4


class Change(NamedTuple):
    """A tree edge that changed in this step: the new model, the one it replaced, and the change point."""

    new: TrackedModel
    old: TrackedModel
    tau: int


class Replacement(NamedTuple):
    """The chosen replacement and the numbers behind the choice (for the ``model_replaced`` event)."""

    entry: TrackedModel
    n_test: int
    trans_error: float
    rot_error: float
    relative: int
    cost: float
    n_valid: int
    n_sampled: int


def _chain_change(failed, new):
    """What a chain's replacement says about the body: which joint stopped moving it, or that its geometry changed
    ("" for other models)."""
    if failed.kind != "chain" or new.kind != "chain":
        return ""
    gone = [a for a in failed.actions if a not in new.actions]
    if len(gone) == 1 and len(new.actions) == len(failed.actions) - 1:
        return f"; joint a{gone[0]} of the chain no longer moves it (blocked)"
    if new.actions == failed.actions:
        return "; the chain's joints are the same, its geometry changed (a bent link or a moved marker)"
    return ""


def _replaced(step, new, old, choice, how, across):
    """The events of ``new`` taking ``old``'s place in the tree: ``model_replaced`` (``how`` follows the two models'
    names; the errors of ``choice``), and ``structure_changed`` (``across`` follows the new edge) when it joins
    another pair of parts."""
    events = [Event(step, "model_replaced", f"{new.describe()} replaces {old.describe()}{how}", parent=new.parent,
                    child=new.child, model=new.describe(), trans_error=choice.trans_error,
                    rot_error=choice.rot_error)]
    if {new.parent, new.child} != {old.parent, old.child}:
        events.append(Event(step, "structure_changed", f"edge {old.parent}-{old.child} replaced by "
                                                       f"{new.parent}-{new.child} ({new.describe()}){across}"))
    return events


def tree_halves(part_ids, edges):
    """Label of the connected component of every part, for a tree with one edge removed (two halves).

    Parameters
    ----------
    part_ids : iterable of int
    edges : iterable of (int, int)
        The remaining tree edges.

    Returns
    -------
    component : dict of int to int
        Parts with equal labels are connected.
    """
    graph = nx.Graph()
    graph.add_nodes_from(part_ids)
    graph.add_edges_from(edges)
    return {part: k for k, parts in enumerate(nx.connected_components(graph)) for part in parts}


def _across(entries, halves):
    """The models of ``entries`` whose parts lie in different halves (``halves``: :func:`tree_halves`)."""
    return [e for e in entries if halves[e.parent] != halves[e.child]]


def bridge_relative_complexity(entry, failed):
    """C(M2|M1) of a candidate ``entry`` replacing ``failed`` (Eq. 11): differing actions, plus one for another
    pair of parts (fewer shared nodes)."""
    other_pair = {entry.parent, entry.child} != {failed.parent, failed.child}
    return relative_complexity(entry.actions, failed.actions) + int(other_pair)


def _halves(adapt, tree, failed):
    pool = adapt.pool
    return tree_halves(adapt.part_ids, [(pool.tracked[i].parent, pool.tracked[i].child)
                                        for i in tree if i != failed.id])


def repair(adapt, tree, root, failed, chain, chain_at, step, events):
    """Memory first, then replacements of the pair, then of pairs across the cut (``root``: the tree's root part).
    Returns a Change or None."""
    c = adapt.config
    pool = adapt.pool
    mismatch = adapt.mismatch[failed.id]
    halves = _halves(adapt, tree, failed)

    def sample(start, bridges, why):
        _sample(adapt, failed, mismatch, chain, chain_at, halves, halves[root], step, events, start, bridges, why)

    if not mismatch.search:
        change = _reinstate_from_memory(adapt, tree, failed, mismatch, halves, step, events)
        if change is not None:
            return change
    if failed.kind == "chain" or mismatch.search:
        _sample_chains(adapt, failed, mismatch, chain_at, step, events)
    candidates = pool.candidates_of(failed.id)
    if not candidates and mismatch.sampled_at < 0:
        sample(mismatch.tau, bridges=False,
               why="searched for like a new edge" if mismatch.search else "no remembered model fits")
        if mismatch.search:
            sample(mismatch.tau, bridges=True, why="searched for like a new edge")
    if failed.kind == "gp" and not mismatch.search:  # besides its replacements: the pair may need a chain
        _sample_chains(adapt, failed, mismatch, chain_at, step, events)
    candidates = pool.candidates_of(failed.id)
    if candidates:
        # Only candidates that reconnect the two halves of the tree as it is now (another repair may have moved
        # the cut since they were sampled).
        choice = choose_replacement(adapt.pool, failed, _across(candidates, halves), bool(mismatch.search))
        if choice is not None:
            return _install_replacement(adapt, tree, failed, choice, step, events)
    if mismatch.sampled_at >= 0 and mismatch.bridged_at < 0 and step - mismatch.sampled_at >= c.bridge_patience:
        sample(mismatch.train_from, bridges=True,
               why=f"no replacement of pair {failed.parent}-{failed.child} became valid within {c.bridge_patience} "
                   f"steps")
    elif candidates and step - mismatch.sampled_at >= c.replacement_patience:
        for e in candidates:
            pool.remove(e)
        start = max(mismatch.train_from, step - c.test_window + 1)
        mismatch.resamples += 1
        mismatch.bridged_at = -1
        sample(start, bridges=False,
               why=f"none of the {len(candidates)} replacements became valid within {c.replacement_patience} steps")
    return None


def _reinstate_from_memory(adapt, tree, failed, mismatch, halves, step, events):
    """Put back the cheapest remembered model that reconnects the tree and is valid since the change point."""
    c = adapt.config
    pool = adapt.pool
    monitor = pool.monitor
    bridges = [e for e in pool.with_role(MEMORY) if halves[e.parent] != halves[e.child]]
    if not bridges:
        return None
    st = monitor.stats([e.row for e in bridges], since=mismatch.tau)
    n, mt, mr = st.n, st.trans_error, st.rot_error
    ok = monitor.valid(st, c.reinstate_min_samples)
    if not np.any(ok):
        return None
    layer = np.array([e.complexity for e in bridges])
    rank = np.array([e.rank for e in bridges])
    cost = np.where(ok, model_cost(layer, st.trans_ratio, st.rot_ratio, rank), np.inf)
    best = int(np.argmin(cost))
    back = bridges[best]
    pool.assign(back, TREE, step)
    monitor.forget_before([back.row], mismatch.tau)
    _take_over(adapt, tree, failed, back)
    events.append(Event(step, "model_reinstated",
                        f"remembered {back.describe()} fits again: mean error {format_errors(mt[best], mr[best])} "
                        f"over {n[best]} samples since the change point (step {mismatch.tau}), below "
                        f"{format_errors(st.theta_trans[best], st.theta_rot[best])}; it replaces "
                        f"{failed.describe()} "
                        f"(chosen among {int(ok.sum())} fitting of {len(bridges)} remembered)",
                        parent=back.parent, child=back.child, model=back.describe(),
                        trans_error=float(mt[best]), rot_error=float(mr[best])))
    if {back.parent, back.child} != {failed.parent, failed.child}:
        events.append(Event(step, "structure_changed",
                            f"edge {failed.parent}-{failed.child} replaced by {back.parent}-{back.child} "
                            f"({back.describe()}) from memory"))
    retire(adapt.pool, adapt.config.memory_size, failed, step, events, f"replaced by remembered {back.describe()}")
    return Change(back, failed, mismatch.tau)


def _orient(failed, halves, root_half):
    """The failed edge's pair ordered from the root's half (label ``root_half`` of ``halves``: ``u``) to the other
    (``v``)."""
    return (failed.parent, failed.child) if halves[failed.parent] == root_half else (failed.child, failed.parent)


def _sample(adapt, failed, mismatch, chain, chain_at, halves, root_half, step, events, start, bridges, why):
    """Start candidates for ``failed`` learning on the chain-consistent history since step ``start``.

    Without ``bridges``: one per (action set, class) of relative complexity at most ``replacement_max_relative``
    for the failed pair. With ``bridges``: every (action set, class) for every other pair across the cut.
    Candidates are oriented from the root's half to the other, the direction of their targets.
    """
    c = adapt.config
    pool = adapt.pool
    u, v = _orient(failed, halves, root_half)
    if bridges:
        near = [p for p in adapt.part_ids if halves[p] == root_half]
        far = [p for p in adapt.part_ids if halves[p] != root_half]
        subsets = action_subsets(pool.n_actions, c.max_complexity)
        specs = [(p, q, acts, kind) for p in near for q in far if {p, q} != {u, v}
                 for acts in subsets for kind in kinds_for(acts, c.candidate_kinds)]
        origin = "bridge"
    else:
        specs = [(u, v, acts, kind)
                 for _, acts, kind in replacement_candidates(failed.actions, pool.n_actions, c.max_complexity,
                                                             c.replacement_max_relative, c.candidate_kinds)]
        specs = [spec for spec in specs if len(spec[2]) <= max(pool.gp_batch.max_dim, 1)]
        origin = "replacement"
    if not specs:
        return
    entries = pool.add_learning(specs, origin=origin, created=step, target=failed.id)
    # Replay the raw history since the change point, test-then-train, so they need not wait for new data.
    used = replay(adapt.pool, adapt.history, entries, chain_at, start)
    if bridges:
        mismatch.bridged_at = step
    else:
        mismatch.sampled_at = step
        mismatch.train_from = start
    n_pairs = len({(e.parent, e.child) for e in entries})
    listing = ", ".join(e.describe() for e in entries[:12]) + (", ..." if len(entries) > 12 else "")
    what = (f"{len(entries)} candidate(s) of {n_pairs} other pair(s) across the cut" if bridges
            else f"{len(entries)} replacement(s) of pair {u}-{v}, ordered by relative complexity and class")
    events.append(Event(step, "model_sampled",
                        f"{why}: sampled {what} for {failed.describe()}: {listing}; trained on the {used} "
                        f"samples since step {start} (replayed from history)",
                        parent=failed.parent, child=failed.child, model=failed.describe()))


def _sample_chains(adapt, failed, mismatch, chain_at, step, events):
    """Chains that may replace ``failed``, fitted on its pair's chain-consistent targets once there are enough of
    them, and again every ``CHAIN_RETRY`` more; they replace the edge's earlier chain candidates and are judged on
    the samples that follow.

    A failed chain (since the change point): :func:`chain_replacements`, the chain fitted again (a bent link, a
    moved marker) and the chain without each joint (a blocked one). An edge searched for like a new one
    (``mismatch.search``: the structure was wrong, not the body changed) or a failed GP (a pair that more actions
    move than a GP of a few can follow: a tool past six joints, taken for a GP while the noise was still the
    generous prior): a chain identified from scratch (:func:`identify_chain`) on the whole history, as while
    bootstrapping.
    """
    pool = adapt.pool
    tried = adapt.chain_samples.get(failed.id, 0)
    needed = max(CHAIN_MIN_SAMPLES, tried + max(CHAIN_RETRY, tried // 4))
    if sum(s >= mismatch.tau for s, _, _ in adapt.history) < needed:
        return  # not enough steps since the change point for the samples the retry needs
    samples = []  # (step, a, target Z, sigma) of the failed pair, over the whole history
    for rec_step, a, obs in adapt.history:
        index, targets = chain_at(a, obs).for_entries([failed], own=True)
        if index.size:
            samples.append((rec_step, a, targets.Z[0], targets.sigma[0]))
    since = [k for k, item in enumerate(samples) if item[0] >= mismatch.tau]
    if len(since) < needed:
        return
    adapt.chain_samples[failed.id] = len(since)
    A, Z, S = (np.array([item[k] for item in samples]) for k in (1, 2, 3))
    found, how = [], []
    if failed.kind == "chain":
        found += chain_replacements(failed.model, A[since], Z[since], S[since])
        how.append(f"on the {len(since)} samples since the change point (step {mismatch.tau}), the chain again "
                   f"(a bent link, a moved marker) and the chain without each joint (a blocked joint)")
    try:  # in the failed model's direction, as its targets are
        identified = identify_chain(A, Z, S, failed.parent, failed.child, range(pool.n_actions),
                                    sigma_trans=adapt.config.prior_sigma_trans,
                                    sigma_rot=adapt.config.prior_sigma_rot)
        if 2 <= len(identified.actions) <= adapt.config.max_chain_joints:
            found.append(identified)
            how.append(f"a chain identified from the excursions of the {len(A)} samples of the whole history "
                       f"(the structure {'may have been' if failed.kind == 'gp' else 'was'} wrong)")
    except ChainNotIdentified:
        pass
    if not found:
        return
    for e in pool.candidates_of(failed.id):
        if e.kind == "chain":
            pool.remove(e)
    added = pool.add_fitted(found, CANDIDATE, origin="replacement", last_used=step, since=mismatch.tau)
    for entry in added:
        entry.target, entry.created, entry.n_train = failed.id, step, entry.model.n_samples_
    mismatch.sampled_at = max(mismatch.sampled_at, step)
    events.append(Event(step, "model_sampled",
                        f"{failed.describe()} failed: fitted {len(added)} chain candidate(s): {'; '.join(how)}: "
                        f"{', '.join(e.describe() for e in added)}",
                        parent=failed.parent, child=failed.child, model=failed.describe()))


def choose_replacement(pool, failed, candidates, absolute=False):
    """The valid, not dominated candidate of least cost ``C(M2|M1)`` + error and class penalty (Eq. 11), or None;
    with ``absolute``, of least absolute complexity ``C(M2)`` instead (Eq. 4, as while bootstrapping)."""
    rows = [e.row for e in candidates]
    n_now = [pool.n_now(e) for e in candidates]
    st, valid = pool.window_stats(rows, n_now)
    valid &= ~pool.dominated(rows, n_now, *nested_models(candidates), valid)
    valid &= np.array([order_decided(e.model) for e in candidates], dtype=bool)  # a chain's order known
    if not np.any(valid):
        return None
    rel = np.array([e.complexity if absolute else bridge_relative_complexity(e, failed) for e in candidates])
    rank = np.array([e.rank for e in candidates])
    cost = np.where(valid, model_cost(rel, st.trans_ratio, st.rot_ratio, rank), np.inf)
    best = int(np.argmin(cost))
    return Replacement(candidates[best], int(st.n[best]), float(st.trans_error[best]),
                       float(st.rot_error[best]), int(rel[best]), float(cost[best]), int(valid.sum()),
                       len(candidates))


def _take_over(adapt, tree, failed, new, keep_candidates=False):
    """``new`` takes ``failed``'s place in the tree: fresh CUSUM, mismatch closed, pending candidates dropped
    (unless ``keep_candidates``: they keep learning, see :func:`refine_choices`)."""
    tree[tree.index(failed.id)] = new.id
    adapt.pool.monitor.reset_cusum([new.row])
    if not keep_candidates:
        for e in adapt.pool.candidates_of(failed.id):
            adapt.pool.remove(e)
    return adapt.mismatch.pop(failed.id)


def refine_choices(adapt, tree, step, events):
    """A replacement is installed as soon as one candidate is valid; a simpler sibling (fewer actions, then class
    rank) may need a few more samples to be judged (a revolute joint predicts from its third sample, a GP from its
    first). Siblings keep learning until they are frozen, and a simpler one that becomes valid takes over
    (``model_replaced``) unless the installed model predicts the same samples clearly better (the dominance
    margin); the first choice is dropped, not remembered (it never described another body). Returns the
    changes."""
    pool = adapt.pool
    changes = []
    for new_id, (failed_id, tau) in list(adapt.refining.items()):
        candidates = pool.candidates_of(failed_id)
        current = pool.tracked.get(new_id)
        failed = pool.tracked.get(failed_id)
        if current is None or current.role != TREE or failed is None or not candidates:
            for e in candidates:
                pool.remove(e)
            del adapt.refining[new_id]
            continue
        if current.id in adapt.mismatch:
            continue  # its repair decides
        sampled = candidates
        candidates = _across(sampled, _halves(adapt, tree, current))  # the cut as it is now
        # The first choice followed Eq. 11 (close to the failed model: found fast); with more data the simplest
        # valid sibling that is not clearly worse takes over (absolute complexity, then class: a static model for
        # a blocked joint, a revolute one where a GP was valid first).
        choice = choose_replacement(pool, failed, candidates, absolute=True)
        simpler = (choice is not None and (choice.entry.complexity, choice.entry.rank)
                   < (current.complexity, current.rank)
                   and not clearly_better(pool, adapt.config, current, choice.entry))
        if not simpler:
            dominant = dominating(pool, adapt.config, current, candidates)
            choice = None if dominant is None else Replacement(dominant[0], *dominant[1:4], 0, 0.0, 1,
                                                               len(candidates))
        if choice is not None and (simpler or dominant is not None):
            new = choice.entry
            pool.freeze(new)
            pool.assign(new, TREE, step)
            tree[tree.index(current.id)] = new.id
            pool.monitor.reset_cusum([new.row])
            why = ("the simpler candidate became valid" if simpler
                   else "a candidate that nests it predicts the same samples clearly better")
            events += _replaced(step, new, current, choice,
                                f", the replacement of {failed.describe()} installed first: {why}, with mean error "
                                f"{format_errors(choice.trans_error, choice.rot_error)} over {choice.n_test} test "
                                f"samples after {new.n_train} training samples", ", a simpler candidate across the cut")
            pool.remove(current)
            del adapt.refining[new_id]
            adapt.refining[new.id] = (failed_id, tau)
            changes.append(Change(new, current, tau))
        elif all(pool.n_now(e) >= adapt.config.train_window for e in candidates):
            for e in sampled:
                pool.remove(e)
            del adapt.refining[new_id]
    return changes


def _install_replacement(adapt, tree, failed, choice, step, events):
    """The chosen candidate becomes a fitted tree model; the failed one goes to memory."""
    pool = adapt.pool
    new = choice.entry
    pool.freeze(new)
    pool.assign(new, TREE, step)
    mismatch = _take_over(adapt, tree, failed, new, keep_candidates=True)
    adapt.refining[new.id] = (failed.id, mismatch.tau)
    events += _replaced(step, new, failed, choice,
                        f": valid with mean error {format_errors(choice.trans_error, choice.rot_error)} over "
                        f"{choice.n_test} test samples after {new.n_train} training samples since step "
                        f"{mismatch.train_from}; cost {'C(M2)' if mismatch.search else 'C(M2|M1)'} + error and class "
                        f"penalty = {choice.cost:.2f} ({'' if mismatch.search else 'relative '}complexity "
                        f"{choice.relative}), cheapest of {choice.n_valid} valid among {choice.n_sampled} sampled; "
                        f"mismatch lasted {step - mismatch.detected} steps{_chain_change(failed, new)}",
                        f": no model of pair {failed.parent}-{failed.child} fits")
    retire(adapt.pool, adapt.config.memory_size, failed, step, events, f"replaced by {new.describe()}")
    return Change(new, failed, mismatch.tau)


def clearly_better(pool, config, entry, other):
    """Whether ``entry`` predicts the samples both were tested on clearly better than ``other``: by more than
    ``dominance_margin`` thresholds on average in either channel, over at least ``min_test_samples``."""
    n, diff = pool.monitor.paired_difference([entry.row], [other.row], [pool.n_now(entry)], [pool.n_now(other)],
                                             config.stale_fraction)
    return bool(n[0] >= config.min_test_samples and -diff[0].min() > config.dominance_margin)


def dominating(pool, config, current, candidates):
    """The valid candidate that nests ``current`` and beats it most clearly in a paired comparison (more than
    ``dominance_margin`` thresholds on average in either channel, over a full ``test_window`` of common samples),
    as ``(entry, n, trans_error, rot_error)``; None if there is none. The dominance rule of the structure search,
    applied to a model already in the tree: a more flexible model takes over only on a window's evidence (over a
    few samples it fits the noise)."""
    c = config
    nesting = [e for e in candidates if nests(e.kind, e.actions, current.kind, current.actions)]
    if not nesting:
        return None
    rows = [e.row for e in nesting]
    n_now = [pool.n_now(e) for e in nesting]
    st, valid = pool.window_stats(rows, n_now)
    n, diff = pool.monitor.paired_difference(rows, [current.row] * len(rows), n_now,
                                             [pool.n_now(current)] * len(rows), c.stale_fraction)
    gain = -diff.min(axis=1)
    ok = valid & (n >= c.test_window) & (gain > c.dominance_margin)
    if not np.any(ok):
        return None
    best = int(np.argmax(np.where(ok, gain, -np.inf)))
    return nesting[best], int(st.n[best]), float(st.trans_error[best]), float(st.rot_error[best])


def replay(pool, history, entries, chain_at, start):
    """Replay the history since step ``start`` to learning ``entries`` (test-then-train); returns the number of
    steps that gave at least one of them a target."""
    return pool.replay(entries, history, lambda a, obs: chain_at(a, obs).for_entries(entries, own=True), start)


# ------------------------------------------------------------------ state
def refining_state(refining):
    """``Adaptation.refining`` as JSON-serialisable ``[[tree model id, failed model id, tau], ...]``."""
    return [[k, f, t] for k, (f, t) in refining.items()]


def failed_state(failed):
    """``Adaptation.failed`` as JSON-serialisable ``[[part, part, step, tau], ...]``."""
    return [[*sorted(pair), step, tau] for pair, (step, tau) in failed.items()]


def failed_from_state(items, part_ids):
    """Rebuild ``Adaptation.failed`` from :func:`failed_state` output; pairs of two distinct known parts, once each."""
    failed = {}
    for item in listing(items, "failed"):
        p, q, step, tau = listing(item, "failed item", 4)
        pair = frozenset((part_id(p, part_ids, "failed pair"), part_id(q, part_ids, "failed pair")))
        if len(pair) != 2 or pair in failed:
            raise ModelFileError(f"failed pair {p}-{q} is not two distinct parts, or is listed twice")
        failed[pair] = (integer(step, "failed step"), integer(tau, "failed tau"))
    return failed


def refining_from_state(items, tracked, next_id):
    """Rebuild ``Adaptation.refining`` from :func:`refining_state` output; the installed model must be tracked, the
    failed one an id the pool gave out."""
    refining = {}
    for item in listing(items, "refining"):
        new_id, failed_id, tau = listing(item, "refining item", 3)
        if integer(new_id, "refining id") not in tracked or new_id in refining:
            raise ModelFileError(f"refining refers to unknown model id {new_id!r:.40}, or twice")
        refining[new_id] = (integer(failed_id, "refining failed id", maximum=next_id - 1),
                            integer(tau, "refining tau"))
    return refining
