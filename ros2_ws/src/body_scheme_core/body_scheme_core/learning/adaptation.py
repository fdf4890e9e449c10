"""Change detection, memory and repair of the body scheme's local models (paper Sec. III-E).

After bootstrapping, every step, against the chain-consistent targets of the calibrated body scheme
(:mod:`~body_scheme_core.learning.chain`):

**Detection.** Each tree model and each remembered model that has a target records its prequential error
(:meth:`~body_scheme_core.learning.pool.ModelPool.evaluate`). A tree model is in *mismatch* when a one-sided CUSUM on
its normalised per-sample error crosses ``cusum_threshold``, its test window is invalid, or a remembered model of its
pair clearly fits the samples since the CUSUM left zero better (the memory challenge). A chain-consistent error rises
for every edge below a changed one (their parent's predicted pose is wrong too), so an alarm is attributed to the edge
nearest the root on its path whose CUSUM rose with it; the edges below wait (they get no targets while a part above
them is in mismatch) and restart their detectors when it is repaired.

**Repair**, for each edge in mismatch. First the memory is asked: a remembered model (of that pair, or of any pair
that reconnects the two halves of the tree) whose mean errors since the estimated change point are valid is put
back (``model_reinstated``). Otherwise replacement models are sampled for the pair, ordered by relative complexity
to the failed model (Eq. 11) and class rank, and trained *only* on data since the change point: the recent raw
history is replayed to them prequentially at once. If none is valid after ``bridge_patience`` steps, candidates of
every other pair that reconnects the two halves are sampled too (a local re-bootstrap), so that a wrong edge is
never permanent. The cheapest valid candidate by ``C(M2|M1)`` plus its error and class penalty replaces the failed model
(``model_replaced``); a different pair also reports ``structure_changed``. The other candidates keep learning until
they are frozen: a simpler one that becomes valid takes over unless the installed model is clearly better.

**Challengers.** Right after bootstrapping, every rigid joint of the tree gets a GP challenger trained on the
chain-consistent history; it takes the edge only if it predicts the same samples clearly better (a nonlinear
transmission, a flexing tool), else it is dropped.

**Memory.** A model that leaves the tree is retired to memory (``model_retired``): at most ``memory_size`` per pair,
the least recently used forgotten first (:func:`least_recently_used`).

``docs/core/learning-and-adaptation.md``, Sec. 5-6, gives every rule, default and measurement.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import NamedTuple

import networkx as nx
import numpy as np

from ..errors import ModelFileError
from ..events import Event, finite_or_none, format_errors
from ..limits import MAX_INTEGER
from ..state_values import integer, listing, mapping, part_id
from .quality import model_cost, nests, relative_complexity
from .structure import action_subsets, kinds_for, replacement_candidates
from .tracked import MEMORY, TREE, TrackedModel, nested_models

__all__ = ["Adaptation", "Mismatch", "Change", "least_recently_used", "tree_halves", "upstream_edges"]

#: An alarm is attributed to an edge above it only if that edge's CUSUM reached this fraction of the alarm level: a
#: change above raises the errors of its own child too, while healthy edges wander a little above zero (up to 0.7 of
#: the drift-adjusted statistic on clean data, learning-and-adaptation.md Sec. 6).
_ATTRIBUTION_FRACTION = 0.5
#: The memory challenge needs the tree model's CUSUM at this fraction of the alarm level: a changed part's first sample
#: (clipped at ``cusum_clip``) raises it by ``clip - drift`` = 4.5 of 12 with the defaults.
_CHALLENGE_FRACTION = 0.25


@dataclass
class Mismatch:
    """A tree edge whose model no longer matches the observations, until it is repaired.

    Attributes
    ----------
    tau : int
        Estimated change point (step): data from here on is post-change data.
    detected : int
        Step of detection.
    sampled_at : int
        Step at which replacements were last sampled; -1 before.
    train_from : int
        First step of the replacements' training data.
    resamples : int
        How often replacements were sampled again after ``replacement_patience``.
    bridged_at : int
        Step at which candidates of other pairs across the cut were sampled; -1 before.
    search : int
        1 when the edge is searched for like a new one (:meth:`Adaptation.flag`: the joint fit left a part below it
        unexplained; or its pair failed again within ``2 test_window`` steps): no remembered model is asked (the body
        did not change back), candidates of the pair and of every pair across the cut are sampled together, and the
        cheapest by absolute complexity wins, as while bootstrapping.
    """

    tau: int
    detected: int
    sampled_at: int = -1
    train_from: int = -1
    resamples: int = 0
    bridged_at: int = -1
    search: int = 0


#: The fields of a :class:`Mismatch` in a state file, with their bounds (-1: not yet).
_MISMATCH_FIELDS = (("tau", 0, MAX_INTEGER), ("detected", 0, MAX_INTEGER), ("sampled_at", -1, MAX_INTEGER),
                    ("train_from", -1, MAX_INTEGER), ("resamples", 0, MAX_INTEGER), ("bridged_at", -1, MAX_INTEGER),
                    ("search", 0, 1))


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


def least_recently_used(models, capacity):
    """The models to forget so that at most ``capacity`` remain: least recently used first, then oldest.

    Parameters
    ----------
    models : list of TrackedModel
        The remembered models of one pair.
    capacity : int
        ``memory_size``.

    Returns
    -------
    forgotten : list of TrackedModel
        Ordered by ``(last_used, id)``.
    """
    ordered = sorted(models, key=lambda e: (e.last_used, e.id))
    return ordered[:max(0, len(ordered) - capacity)]


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


def upstream_edges(root, edges):
    """Per tree edge, the edges on the path from the root to its part nearer the root, root-most first.

    Parameters
    ----------
    root : int
    edges : iterable of (int, int, key)
        The tree's edges ``(part, part, key)``, in any orientation.

    Returns
    -------
    upstream : dict of key to list of key
    """
    edges = list(edges)
    graph = nx.Graph()
    graph.add_node(root)
    for u, v, key in edges:
        graph.add_edge(u, v, key=key)
    above = {root: None}  # part -> (part above it, key of the edge between them)
    depth = {root: 0}
    for u, v in nx.bfs_edges(graph, root):
        above[v] = (u, graph.edges[u, v]["key"])
        depth[v] = depth[u] + 1
    out = {}
    for u, v, key in edges:
        part = u if depth[u] < depth[v] else v
        path = []
        while above[part] is not None:
            part, edge = above[part]
            path.append(edge)
        out[key] = path[::-1]
    return out


def _across(entries, halves):
    """The models of ``entries`` whose parts lie in different halves (``halves``: :func:`tree_halves`)."""
    return [e for e in entries if halves[e.parent] != halves[e.child]]


def bridge_relative_complexity(entry, failed):
    """C(M2|M1) of a candidate ``entry`` replacing ``failed`` (Eq. 11): differing actions, plus one for another
    pair of parts (fewer shared nodes)."""
    other_pair = {entry.parent, entry.child} != {failed.parent, failed.child}
    return relative_complexity(entry.actions, failed.actions) + int(other_pair)


class Adaptation:
    """Detects mismatching tree models and repairs them from memory or with newly learned replacements.

    Parameters
    ----------
    config : BodySchemeConfig
    pool : ModelPool
    history : collections.deque of (int, ndarray, dict)
        Recent raw steps ``(step, actions, {part: world2part})``, replayed to replacements (shared with the
        learner, which appends to it).
    part_ids : tuple of int
    root : int
    mismatch : dict of int to Mismatch, optional
        Edges in mismatch by tree-model id (a restored state).
    refining : dict of int to tuple (int, int), optional
        Installed replacements whose sibling candidates still learn: tree-model id -> (failed model id, tau).
    failed : dict of frozenset to tuple (int, int), optional
        The last step each pair of parts was found in mismatch, and that mismatch's change point.

    Attributes
    ----------
    mismatch : dict of int to Mismatch
    refining : dict of int to tuple (int, int)
    failed : dict of frozenset to tuple (int, int)
    """

    def __init__(self, config, pool, history, part_ids, root, mismatch=None, refining=None, failed=None):
        self.config = config
        self.pool = pool
        self.history = history
        self.part_ids = tuple(part_ids)
        self.root = root
        self.mismatch = {} if mismatch is None else mismatch
        self.refining = {} if refining is None else dict(refining)
        self.failed = {} if failed is None else dict(failed)

    def step(self, tree, a, chain, chain_at, step, events):
        """One step after bootstrapping: evaluate and train, detect mismatches, repair the edges in mismatch.

        Parameters
        ----------
        tree : list of int
            Ids of the tree's models; edges are replaced in place.
        a : ndarray, shape (m,)
        chain : ChainTargets
            Targets of this step.
        chain_at : callable
            ``chain_at(a, observations)`` gives the :class:`ChainTargets` of a past step (history replay).
        step : int
        events : list of Event
            Appended to.

        Returns
        -------
        changes : list of Change
            Tree edges that were replaced or reinstated (the learner re-fits the body scheme).
        """
        pool = self.pool
        edges = [pool.tracked[i] for i in tree]
        index, e_t, e_r, theta_t, theta_r = chain.tree_errors([chain.orient(e.parent, e.child) for e in edges])
        evaluated = [edges[k] for k in index]
        alarm = pool.monitor.record([e.row for e in evaluated], e_t, e_r, step,
                                    n_train=[e.n_train for e in evaluated], cusum=True, theta_trans=theta_t,
                                    theta_rot=theta_r)
        alarms = {e.id: bool(x) for e, x in zip(evaluated, alarm, strict=True)}
        memory = pool.with_role(MEMORY)
        index, targets = chain.for_entries(memory)
        pool.evaluate([memory[k] for k in index], a, targets, step, cusum=False)
        learning = [e for e in pool.tracked.values() if e.slot >= 0]
        if learning:
            index, targets = chain.for_entries(learning, own=True)
            pool.train([learning[k].id for k in index], a, targets, step)
        changes = self._refine_choices(tree, step, events) + self._challenge(tree, step, events)
        # After those changes: detection sees the tree as it is now (a replaced model is no edge of it any more).
        self._detect(tree, alarms, step, events)
        for edge_id in list(self.mismatch):
            if edge_id in self.mismatch:
                change = self._repair(tree, pool.tracked[edge_id], chain, chain_at, step, events)
                if change is not None:
                    changes.append(change)
        return changes

    # ------------------------------------------------------------------ detection
    def _detect(self, tree, alarms, step, events):
        """Mismatch detection on the tree edges evaluated in this step (``alarms``: CUSUM alarm by model id)."""
        c = self.config
        pool = self.pool
        monitor = pool.monitor
        observed = [pool.tracked[i] for i in tree if i in alarms and i not in self.mismatch]
        if not observed:
            return
        upstream = upstream_edges(self.root, [(pool.tracked[i].parent, pool.tracked[i].child, i) for i in tree])
        st, valid = pool.window_stats([e.row for e in observed], [pool.n_now(e) for e in observed])
        for k, e in enumerate(observed):
            if e.id in self.mismatch:  # attributed from an edge below it earlier in this loop
                continue
            window_bad = st.n[k] >= c.min_test_samples and not valid[k]
            if not (alarms[e.id] or window_bad):
                self._challenge_from_memory(e, step, events, st, k)
                continue
            above = upstream.get(e.id, [])
            if any(i in self.mismatch for i in above):
                continue  # its errors follow from the edge above (it should not have had a target)
            culprit = self._root_most_rising(above, e)
            if culprit is None:
                self._start_mismatch(e, step, events, bool(alarms[e.id]), st, k)
                continue
            f = pool.tracked[culprit]
            st_f, _ = pool.window_stats([f.row], [pool.n_now(f)])
            cause = (f"the errors of {e.describe()} below it rose with its own (CUSUM "
                     f"{monitor.cusum[f.row][0]:.2f} / {monitor.cusum[f.row][1]:.2f} since step "
                     f"{int(monitor.change_point([f.row])[0])})")
            self._start_mismatch(f, step, events, False, st_f, 0, cause=cause)

    def _root_most_rising(self, above, entry):
        """The edge nearest the root among ``above`` whose CUSUM excursion started no later than ``entry``'s and
        reached at least ``_ATTRIBUTION_FRACTION`` of the alarm level (a noise excursion of a healthy edge does not)."""
        monitor = self.pool.monitor
        start = int(monitor.change_point([entry.row])[0])
        start = math.inf if start < 0 else start
        level = _ATTRIBUTION_FRACTION * self.config.cusum_threshold
        for i in above:
            f = self.pool.tracked[i]
            if not np.any(monitor.cusum[f.row] >= level):
                continue
            tau = int(monitor.change_point([f.row])[0])
            if 0 <= tau <= start + 1:
                return i
        return None

    def _challenge_from_memory(self, entry, step, events, st, k):
        """Start a mismatch early when a remembered model of the same pair clearly fits the recent samples better.

        Only while the tree model's CUSUM is up by :data:`_CHALLENGE_FRACTION` of the alarm level (evidence of a drift,
        which one sample of a real change gives; noise excursions stay lower): over the samples since the excursion
        started, a remembered model must be valid (at least ``reinstate_min_samples`` samples) and beat the tree model
        in a paired comparison in both channels, by more than ``challenge_margin`` on average. This is what lets a
        repair, or the same failure again, be handled within a few samples.
        """
        c = self.config
        monitor = self.pool.monitor
        if not np.any(monitor.cusum[entry.row] >= _CHALLENGE_FRACTION * c.cusum_threshold):
            return
        memory = self.pool.memory_of_pair(entry.parent, entry.child)
        if not memory:
            return
        tau = int(monitor.change_point([entry.row])[0])
        rows = [e.row for e in memory]
        ok = monitor.valid(monitor.stats(rows, since=tau), c.reinstate_min_samples)
        n, diff = monitor.paired_difference(rows, [entry.row] * len(rows), since=tau)
        better = (ok & (n >= c.reinstate_min_samples) & (diff.mean(axis=1) < -c.challenge_margin)
                  & np.all(diff < 0.0, axis=1))
        if np.any(better):
            best = int(np.argmin(np.where(better, diff.mean(axis=1), np.inf)))
            cause = (f"remembered {memory[best].describe()} fits the {n[best]} samples since step {tau} better by "
                     f"{-diff[best, 0]:.2f} (trans) / {-diff[best, 1]:.2f} (rot) thresholds")
            self._start_mismatch(entry, step, events, False, st, k, cause=cause)

    def flag(self, entry, step, events, cause):
        """Put tree edge ``entry`` in mismatch for a reason the detectors did not see (the joint fit left a part below
        it unexplained): it is repaired like a detected change, by remembered models, replacements of other classes
        and action sets, and pairs across the cut. The change point is the CUSUM's if it rose, else the oldest step of
        the history (the model may have been wrong all along)."""
        st, _ = self.pool.window_stats([entry.row], [self.pool.n_now(entry)])
        oldest = self.history[0][0] if self.history else step
        self._start_mismatch(entry, step, events, False, st, 0, cause=cause, fallback_tau=oldest, search=True)

    def _start_mismatch(self, entry, step, events, alarm, st, k, cause=None, fallback_tau=None, search=False):
        """Put ``entry`` in mismatch, with the change point from its CUSUM (else ``fallback_tau``, else the oldest
        window sample); searched for like a new edge (``search``, or when its pair failed within ``2 test_window``
        steps: repairing it the usual way did not last)."""
        c = self.config
        monitor = self.pool.monitor
        n, mt, mr = int(st.n[k]), float(st.trans_error[k]), float(st.rot_error[k])
        theta_t, theta_r = float(st.theta_trans[k]), float(st.theta_rot[k])
        tau = int(monitor.change_point([entry.row])[0])
        if tau < 0 and fallback_tau is not None:
            tau = int(fallback_tau)
        elif tau < 0:
            tau = int(monitor.first_step([entry.row])[0])
            tau = step if tau < 0 else tau
        S = monitor.cusum[entry.row]
        if cause is None:
            cause = (f"CUSUM {S[0]:.2f} (trans) / {S[1]:.2f} (rot) reached {c.cusum_threshold:g}" if alarm
                     else f"test window invalid over {n} samples")
        pair = frozenset((entry.parent, entry.child))
        last, last_tau = self.failed.get(pair, (-math.inf, tau))
        again = step - last <= 2 * c.test_window
        if again:  # the repair of the same change did not last: its data since that change point is still good
            tau = min(tau, last_tau)
        self.failed[pair] = (step, tau)
        self.mismatch[entry.id] = Mismatch(tau=tau, detected=step, train_from=tau, search=int(search or again))
        events.append(Event(step, "mismatch_detected",
                            f"{entry.describe()} no longer matches the observations: {cause}; window mean "
                            f"{format_errors(mt, mr)} over {n} samples (thresholds "
                            f"{format_errors(theta_t, theta_r)}); change point estimated at step {tau}",
                            parent=entry.parent, child=entry.child, model=entry.describe(),
                            trans_error=finite_or_none(mt), rot_error=finite_or_none(mr)))

    # ------------------------------------------------------------------ repair
    def _halves(self, tree, failed):
        pool = self.pool
        return tree_halves(self.part_ids, [(pool.tracked[i].parent, pool.tracked[i].child)
                                                for i in tree if i != failed.id])

    def _repair(self, tree, failed, chain, chain_at, step, events):
        """Memory first, then replacements of the pair, then of pairs across the cut. Returns a Change or None."""
        c = self.config
        pool = self.pool
        mismatch = self.mismatch[failed.id]
        halves = self._halves(tree, failed)
        if not mismatch.search:
            change = self._reinstate_from_memory(tree, failed, mismatch, halves, step, events)
            if change is not None:
                return change
        candidates = pool.candidates_of(failed.id)
        if not candidates and mismatch.sampled_at < 0:
            self._sample(failed, mismatch, chain, chain_at, halves, step, events, mismatch.tau, bridges=False,
                         why="searched for like a new edge" if mismatch.search else "no remembered model fits")
            if mismatch.search:
                self._sample(failed, mismatch, chain, chain_at, halves, step, events, mismatch.tau, bridges=True,
                             why="searched for like a new edge")
            candidates = pool.candidates_of(failed.id)
        if candidates:
            # Only candidates that reconnect the two halves of the tree as it is now (another repair may have moved
            # the cut since they were sampled).
            choice = self._choose_replacement(failed, _across(candidates, halves), bool(mismatch.search))
            if choice is not None:
                return self._install_replacement(tree, failed, choice, step, events)
        if mismatch.sampled_at >= 0 and mismatch.bridged_at < 0 and step - mismatch.sampled_at >= c.bridge_patience:
            self._sample(failed, mismatch, chain, chain_at, halves, step, events, mismatch.train_from, bridges=True,
                         why=f"no replacement of pair {failed.parent}-{failed.child} became valid within "
                             f"{c.bridge_patience} steps")
        elif candidates and step - mismatch.sampled_at >= c.replacement_patience:
            for e in candidates:
                pool.remove(e)
            start = max(mismatch.train_from, step - c.test_window + 1)
            mismatch.resamples += 1
            mismatch.bridged_at = -1
            self._sample(failed, mismatch, chain, chain_at, halves, step, events, start, bridges=False,
                         why=f"none of the {len(candidates)} replacements became valid within "
                             f"{c.replacement_patience} steps")
        return None

    def _reinstate_from_memory(self, tree, failed, mismatch, halves, step, events):
        """Put back the cheapest remembered model that reconnects the tree and is valid since the change point."""
        c = self.config
        pool = self.pool
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
        self._take_over(tree, failed, back)
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
        self._retire(failed, step, events, f"replaced by remembered {back.describe()}")
        return Change(back, failed, mismatch.tau)

    def _orient(self, failed, halves):
        """The failed edge's pair ordered from the root's half (``u``) to the other (``v``)."""
        root_half = halves[self.root]
        return (failed.parent, failed.child) if halves[failed.parent] == root_half else (failed.child, failed.parent)

    def _sample(self, failed, mismatch, chain, chain_at, halves, step, events, start, bridges, why):
        """Start candidates for ``failed`` learning on the chain-consistent history since step ``start``.

        Without ``bridges``: one per (action set, class) of relative complexity at most ``replacement_max_relative``
        for the failed pair. With ``bridges``: every (action set, class) for every other pair across the cut.
        Candidates are oriented from the root's half to the other, the direction of their targets.
        """
        c = self.config
        pool = self.pool
        u, v = self._orient(failed, halves)
        if bridges:
            root_half = halves[self.root]
            near = [p for p in self.part_ids if halves[p] == root_half]
            far = [p for p in self.part_ids if halves[p] != root_half]
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
        used = self._replay(entries, chain_at, start)
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

    def _choose_replacement(self, failed, candidates, absolute=False):
        """The valid, not dominated candidate of least cost ``C(M2|M1)`` + error and class penalty (Eq. 11), or None;
        with ``absolute``, of least absolute complexity ``C(M2)`` instead (Eq. 4, as while bootstrapping)."""
        pool = self.pool
        rows = [e.row for e in candidates]
        n_now = [pool.n_now(e) for e in candidates]
        st, valid = pool.window_stats(rows, n_now)
        valid &= ~pool.dominated(rows, n_now, *nested_models(candidates), valid)
        if not np.any(valid):
            return None
        rel = np.array([e.complexity if absolute else bridge_relative_complexity(e, failed) for e in candidates])
        rank = np.array([e.rank for e in candidates])
        cost = np.where(valid, model_cost(rel, st.trans_ratio, st.rot_ratio, rank), np.inf)
        best = int(np.argmin(cost))
        return Replacement(candidates[best], int(st.n[best]), float(st.trans_error[best]),
                           float(st.rot_error[best]), int(rel[best]), float(cost[best]), int(valid.sum()),
                           len(candidates))

    def _take_over(self, tree, failed, new, keep_candidates=False):
        """``new`` takes ``failed``'s place in the tree: fresh CUSUM, mismatch closed, pending candidates dropped
        (unless ``keep_candidates``: they keep learning, see :meth:`_refine_choices`)."""
        tree[tree.index(failed.id)] = new.id
        self.pool.monitor.reset_cusum([new.row])
        if not keep_candidates:
            for e in self.pool.candidates_of(failed.id):
                self.pool.remove(e)
        return self.mismatch.pop(failed.id)

    def _refine_choices(self, tree, step, events):
        """A replacement is installed as soon as one candidate is valid; a simpler sibling (fewer actions, then class
        rank) may need a few more samples to be judged (a revolute joint predicts from its third sample, a GP from its
        first). Siblings keep learning until they are frozen, and a simpler one that becomes valid takes over
        (``model_replaced``) unless the installed model predicts the same samples clearly better (the dominance
        margin); the first choice is dropped, not remembered (it never described another body). Returns the
        changes."""
        pool = self.pool
        changes = []
        for new_id, (failed_id, tau) in list(self.refining.items()):
            candidates = pool.candidates_of(failed_id)
            current = pool.tracked.get(new_id)
            failed = pool.tracked.get(failed_id)
            if current is None or current.role != TREE or failed is None or not candidates:
                for e in candidates:
                    pool.remove(e)
                del self.refining[new_id]
                continue
            if current.id in self.mismatch:
                continue  # its repair decides
            sampled = candidates
            candidates = _across(sampled, self._halves(tree, current))  # the cut as it is now
            # The first choice followed Eq. 11 (close to the failed model: found fast); with more data the simplest
            # valid sibling that is not clearly worse takes over (absolute complexity, then class: a static model for
            # a blocked joint, a revolute one where a GP was valid first).
            choice = self._choose_replacement(failed, candidates, absolute=True)
            simpler = (choice is not None and (choice.entry.complexity, choice.entry.rank)
                       < (current.complexity, current.rank) and not self._clearly_better(current, choice.entry))
            if not simpler:
                dominating = self._dominating(current, candidates)
                choice = None if dominating is None else Replacement(dominating[0], *dominating[1:4], 0, 0.0, 1,
                                                                     len(candidates))
            if choice is not None and (simpler or dominating is not None):
                new = choice.entry
                pool.freeze(new)
                pool.assign(new, TREE, step)
                tree[tree.index(current.id)] = new.id
                pool.monitor.reset_cusum([new.row])
                why = ("the simpler candidate became valid" if simpler
                       else "a candidate that nests it predicts the same samples clearly better")
                events.append(Event(step, "model_replaced",
                                    f"{new.describe()} replaces {current.describe()}, the replacement of "
                                    f"{failed.describe()} installed first: {why}, with mean error "
                                    f"{format_errors(choice.trans_error, choice.rot_error)} over "
                                    f"{choice.n_test} test samples after {new.n_train} training samples",
                                    parent=new.parent, child=new.child, model=new.describe(),
                                    trans_error=choice.trans_error, rot_error=choice.rot_error))
                if {new.parent, new.child} != {current.parent, current.child}:
                    events.append(Event(step, "structure_changed",
                                        f"edge {current.parent}-{current.child} replaced by {new.parent}-{new.child} "
                                        f"({new.describe()}), a simpler candidate across the cut"))
                pool.remove(current)
                del self.refining[new_id]
                self.refining[new.id] = (failed_id, tau)
                changes.append(Change(new, current, tau))
            elif all(pool.n_now(e) >= self.config.train_window for e in candidates):
                for e in sampled:
                    pool.remove(e)
                del self.refining[new_id]
        return changes

    def _install_replacement(self, tree, failed, choice, step, events):
        """The chosen candidate becomes a fitted tree model; the failed one goes to memory."""
        pool = self.pool
        new = choice.entry
        pool.freeze(new)
        pool.assign(new, TREE, step)
        mismatch = self._take_over(tree, failed, new, keep_candidates=True)
        self.refining[new.id] = (failed.id, mismatch.tau)
        events.append(Event(step, "model_replaced",
                            f"{new.describe()} replaces {failed.describe()}: valid with mean error "
                            f"{format_errors(choice.trans_error, choice.rot_error)} over {choice.n_test} test samples "
                            f"after {new.n_train} training samples since step {mismatch.train_from}; cost "
                            f"{'C(M2)' if mismatch.search else 'C(M2|M1)'} + error and class penalty = "
                            f"{choice.cost:.2f} ({'' if mismatch.search else 'relative '}complexity "
                            f"{choice.relative}), "
                            f"cheapest of {choice.n_valid} valid among {choice.n_sampled} sampled; mismatch lasted "
                            f"{step - mismatch.detected} steps",
                            parent=new.parent, child=new.child, model=new.describe(),
                            trans_error=choice.trans_error, rot_error=choice.rot_error))
        if {new.parent, new.child} != {failed.parent, failed.child}:
            events.append(Event(step, "structure_changed",
                                f"edge {failed.parent}-{failed.child} replaced by {new.parent}-{new.child} "
                                f"({new.describe()}): no model of pair {failed.parent}-{failed.child} fits"))
        self._retire(failed, step, events, f"replaced by {new.describe()}")
        return Change(new, failed, mismatch.tau)

    def _clearly_better(self, entry, other):
        """Whether ``entry`` predicts the samples both were tested on clearly better than ``other``: by more than
        ``dominance_margin`` thresholds on average in either channel, over at least ``min_test_samples``."""
        pool = self.pool
        n, diff = pool.monitor.paired_difference([entry.row], [other.row], [pool.n_now(entry)], [pool.n_now(other)],
                                                 self.config.stale_fraction)
        return bool(n[0] >= self.config.min_test_samples and -diff[0].min() > self.config.dominance_margin)

    def _dominating(self, current, candidates):
        """The valid candidate that nests ``current`` and beats it most clearly in a paired comparison (more than
        ``dominance_margin`` thresholds on average in either channel, over a full ``test_window`` of common samples),
        as ``(entry, n, trans_error, rot_error)``; None if there is none. The dominance rule of the structure search,
        applied to a model already in the tree: a more flexible model takes over only on a window's evidence (over a
        few samples it fits the noise)."""
        c = self.config
        pool = self.pool
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

    def sample_challengers(self, tree, chain, chain_at, step, events):
        """Challengers of the tree's models in the other direction of flexibility, trained on the chain-consistent
        history: a GP for every rigid joint, and the rigid forms for every GP edge on one action.

        Relative observations cannot tell a rigid joint from a smooth nonlinear relation (a transmission, a flexing
        tool) at the paper's noise; chain-consistent targets can. Early in bootstrapping, a GP judged against its own
        wide uncertainty can also win an edge that a rigid joint describes with fewer parameters and less error.
        ``chain`` (this step's targets) orients each challenger from the root's side; ``chain_at`` gives the targets
        of past steps. Each challenger learns like a replacement candidate and is judged by :meth:`_challenge`; it is
        dropped once frozen and compared with the tree model over a full window of common samples without taking
        the edge.
        """
        pool = self.pool
        kinds = self.config.candidate_kinds
        rigid = [pool.tracked[i] for i in tree if pool.tracked[i].kind in ("static", "prismatic", "revolute")
                 and pool.tracked[i].actions] if "gp" in kinds else []
        flexible = [pool.tracked[i] for i in tree if pool.tracked[i].kind == "gp"
                    and len(pool.tracked[i].actions) == 1]
        simpler = [k for k in ("prismatic", "revolute") if k in kinds]
        challengers = []
        for e in rigid:
            u, v = chain.orient(e.parent, e.child)  # from the root's side, the direction of their targets
            challengers += pool.add_learning([(u, v, e.actions, "gp")], origin="challenger", created=step,
                                             target=e.id)
        for e in flexible if simpler else []:
            u, v = chain.orient(e.parent, e.child)
            challengers += pool.add_learning([(u, v, e.actions, kind) for kind in simpler], origin="challenger",
                                             created=step, target=e.id)
        if not challengers:
            return
        used = self._replay(challengers, chain_at, start=-1)
        what = []
        if rigid:
            what.append(f"a GP for each of the {len(rigid)} rigid joints (a relation no rigid form explains would "
                        f"show here)")
        if flexible and simpler:
            what.append(f"{' and '.join(simpler)} joints for each of the {len(flexible)} GP edges on one action (a "
                        f"rigid joint that predicts as well takes the edge)")
        events.append(Event(step, "model_sampled",
                            f"sampled challengers of the tree's models: {'; '.join(what)} "
                            f"({', '.join(e.describe() for e in challengers)}), trained on the {used} "
                            f"chain-consistent samples of the history"))

    def _challenge(self, tree, step, events):
        """Challengers that take their tree model's edge: a GP that dominates a rigid joint, or a valid rigid joint
        that a GP edge does not predict clearly better over a full window of common samples. The others are dropped
        once they are frozen and were compared with it over a full window. Returns the changes."""
        pool = self.pool
        c = self.config
        changes = []
        for current_id in [i for i in tree]:
            challengers = [e for e in pool.candidates_of(current_id) if e.origin == "challenger"]
            if not challengers:
                continue
            current = pool.tracked[current_id]
            if current_id in self.mismatch:
                continue
            if current.kind == "gp":
                choice = self._simpler(current, challengers)
                found = None if choice is None else (choice.entry, choice.n_test, choice.trans_error,
                                                     choice.rot_error)
                why = "a rigid joint predicts the same chain-consistent samples as well, with fewer parameters"
            else:
                found = self._dominating(current, challengers)
                why = ("it predicts the same chain-consistent samples clearly better: no rigid form explains this "
                       "relation")
            if found is not None:
                new, n, mt, mr = found
                pool.freeze(new)
                pool.assign(new, TREE, step)
                new.since = current.since
                tree[tree.index(current_id)] = new.id
                pool.monitor.reset_cusum([new.row])
                for e in pool.candidates_of(current_id):
                    if e is not new:
                        pool.remove(e)
                events.append(Event(step, "model_replaced",
                                    f"{new.describe()} replaces {current.describe()}: {why} (mean error "
                                    f"{format_errors(mt, mr)} over {n} test samples)",
                                    parent=new.parent, child=new.child, model=new.describe(),
                                    trans_error=mt, rot_error=mr))
                pool.remove(current)
                changes.append(Change(new, current, new.since))
                continue
            # Judged: frozen, and compared with the tree model on a full window of common samples.
            n, _ = pool.monitor.paired_difference([e.row for e in challengers], [current.row] * len(challengers),
                                                  [pool.n_now(e) for e in challengers],
                                                  [pool.n_now(current)] * len(challengers), c.stale_fraction)
            for e, n_common in zip(challengers, n, strict=True):
                if pool.n_now(e) >= c.train_window and n_common >= c.test_window:
                    pool.remove(e)
        return changes

    def _simpler(self, current, challengers):
        """The cheapest valid rigid challenger of a GP edge (:meth:`_choose_replacement`) once it shares a full
        test window of samples with it and the GP does not predict them clearly better; else None."""
        choice = self._choose_replacement(current, challengers, absolute=True)
        if choice is None:
            return None
        pool = self.pool
        n, _ = pool.monitor.paired_difference([current.row], [choice.entry.row], [pool.n_now(current)],
                                              [pool.n_now(choice.entry)], self.config.stale_fraction)
        if n[0] < self.config.test_window or self._clearly_better(current, choice.entry):
            return None
        return choice

    def _replay(self, entries, chain_at, start):
        """Replay the history since step ``start`` to learning ``entries`` (test-then-train); returns the number of
        steps that gave at least one of them a target."""
        pool = self.pool
        used = 0
        for rec_step, a, obs in self.history:
            if rec_step < start:
                continue
            past = chain_at(a, obs)
            index, targets = past.for_entries(entries, own=True)
            if index.size:
                pool.train([entries[k].id for k in index], a, targets, rec_step)
                used += 1
        return used

    # ------------------------------------------------------------------ memory
    def _retire(self, entry, step, events, why):
        """Move a model that left the tree to memory; forget the least recently used beyond ``memory_size``."""
        pool = self.pool
        pool.assign(entry, MEMORY, step)
        pool.monitor.reset_cusum([entry.row])
        same = pool.memory_of_pair(entry.parent, entry.child)
        forgotten = least_recently_used(same, self.config.memory_size)
        for e in forgotten:
            pool.remove(e)
        note = f"; forgot {', '.join(e.describe() for e in forgotten)} (least recently used)" if forgotten else ""
        kept = len(same) - len(forgotten)
        mt = mr = math.inf
        if entry.id in pool.tracked:
            st = pool.monitor.stats([entry.row])
            mt, mr = float(st.trans_error[0]), float(st.rot_error[0])
        events.append(Event(step, "model_retired",
                            f"{entry.describe()} retired ({why}); window mean {format_errors(mt, mr)}; memory holds "
                            f"{kept} model(s) of pair {entry.parent}-{entry.child}{note}",
                            parent=entry.parent, child=entry.child, model=entry.describe(),
                            trans_error=finite_or_none(mt), rot_error=finite_or_none(mr)))

    # ------------------------------------------------------------------ state
    def mismatch_state(self):
        """The edges in mismatch as JSON-serialisable dicts ``{"edge": id, "tau": ..., ...}``."""
        return [{"edge": k, **asdict(v)} for k, v in self.mismatch.items()]

    def refining_state(self):
        """:attr:`refining` as JSON-serialisable ``[[tree model id, failed model id, tau], ...]``."""
        return [[k, f, t] for k, (f, t) in self.refining.items()]

    def failed_state(self):
        """:attr:`failed` as JSON-serialisable ``[[part, part, step, tau], ...]``."""
        return [[*sorted(pair), step, tau] for pair, (step, tau) in self.failed.items()]

    @staticmethod
    def failed_from_state(items, part_ids):
        """Rebuild :attr:`failed` from :meth:`failed_state` output; pairs of two distinct known parts, once each."""
        failed = {}
        for item in listing(items, "failed"):
            p, q, step, tau = listing(item, "failed item", 4)
            pair = frozenset((part_id(p, part_ids, "failed pair"), part_id(q, part_ids, "failed pair")))
            if len(pair) != 2 or pair in failed:
                raise ModelFileError(f"failed pair {p}-{q} is not two distinct parts, or is listed twice")
            failed[pair] = (integer(step, "failed step"), integer(tau, "failed tau"))
        return failed

    @staticmethod
    def refining_from_state(items, tracked, next_id):
        """Rebuild :attr:`refining` from :meth:`refining_state` output; the installed model must be tracked, the
        failed one an id the pool gave out."""
        refining = {}
        for item in listing(items, "refining"):
            new_id, failed_id, tau = listing(item, "refining item", 3)
            if integer(new_id, "refining id") not in tracked or new_id in refining:
                raise ModelFileError(f"refining refers to unknown model id {new_id!r:.40}, or twice")
            refining[new_id] = (integer(failed_id, "refining failed id", maximum=next_id - 1),
                                integer(tau, "refining tau"))
        return refining

    @staticmethod
    def mismatch_from_state(items, tracked):
        """Rebuild :attr:`mismatch` from :meth:`mismatch_state` output; edges must be ids in ``tracked``."""
        mismatch = {}
        for item in listing(items, "mismatch"):
            item = dict(mapping(item, "mismatch item"))
            edge = integer(item.pop("edge", None), "mismatch edge")
            if edge not in tracked or edge in mismatch:
                raise ModelFileError(f"mismatch refers to unknown model id {edge}, or twice")
            mismatch[edge] = Mismatch(**{k: integer(item[k], f"mismatch {k}", minimum=low, maximum=high)
                                         for k, low, high in _MISMATCH_FIELDS})
        return mismatch
