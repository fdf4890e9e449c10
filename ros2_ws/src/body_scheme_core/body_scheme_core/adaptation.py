"""Change detection, memory and repair of the body scheme's local models (paper Sec. III-E).

After bootstrapping, every step:

**Detection.** Each tree model and each remembered model whose two parts are observed records its prequential error
(:meth:`~body_scheme_core.pool.ModelPool.evaluate_frozen`). A tree model is in *mismatch* when a one-sided CUSUM on
its normalised per-sample error crosses ``cusum_threshold`` (per edge, so the failure is localised), its test
window is invalid, or a remembered model of its pair clearly fits the samples since the CUSUM left zero better
(the memory challenge).

**Repair**, for each edge in mismatch. First the memory is asked: a remembered model (of that pair, or of any pair
that reconnects the two halves of the tree) whose mean errors since the estimated change point are valid is put
back (``model_reinstated``). Otherwise replacement models are sampled for the pair, ordered by relative complexity
to the failed model (Eq. 11), and trained *only* on data since the change point: the recent raw history is
replayed to them prequentially at once. The cheapest valid one by ``C(M2|M1) + e`` replaces the failed model
(``model_replaced``).

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

from .errors import ModelFileError
from .events import Event
from .pool import MEMORY, TREE, TrackedModel, finite_or_none, format_errors, nested_pairs
from .quality import model_cost, relative_complexity
from .structure import replacement_action_sets
from .transforms import invert_transform

__all__ = ["Adaptation", "Mismatch", "least_recently_used", "tree_halves"]


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
    """

    tau: int
    detected: int
    sampled_at: int = -1
    train_from: int = -1
    resamples: int = 0


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


class Adaptation:
    """Detects mismatching tree models and repairs them from memory or with newly learned replacements.

    Parameters
    ----------
    config : BodySchemeConfig
    pool : ModelPool
    history : collections.deque of (int, ndarray, dict)
        Recent raw steps ``(step, actions, {part: world2part})``, replayed to replacements (shared with the
        learner, which appends to it).
    mismatch : dict of int to Mismatch, optional
        Edges in mismatch by tree-model id (a restored state).

    Attributes
    ----------
    mismatch : dict of int to Mismatch
    """

    def __init__(self, config, pool, history, mismatch=None):
        self.config = config
        self.pool = pool
        self.history = history
        self.mismatch = {} if mismatch is None else mismatch

    def step(self, tree, a, relative, step, events):
        """One step after bootstrapping: evaluate and train, detect mismatches, repair the edges in mismatch.

        Parameters
        ----------
        tree : list of int
            Ids of the tree's models; edges are replaced in place.
        a : ndarray, shape (m,)
        relative : RelativeObservations
        step : int
        events : list of Event
            Appended to.

        Returns
        -------
        changed : bool
            Whether the tree or one of its models changed.
        """
        pool = self.pool
        ids, alarm_fixed = pool.evaluate_frozen(a, relative, step)
        # Models still learning in the batch: replacement candidates and installed, not yet frozen replacements.
        learn_ids, alarm_learn = pool.train_learning(a, relative, step)
        changed = pool.refresh_refining(tree)
        alarms = dict(zip(ids, alarm_fixed.tolist(), strict=True))
        alarms.update(zip(learn_ids.tolist(), alarm_learn.tolist(), strict=True))
        self._detect(tree, alarms, step, events)
        for edge_id in list(self.mismatch):
            if edge_id in self.mismatch:
                changed |= self._repair(tree, pool.tracked[edge_id], step, events)
        return changed

    # ------------------------------------------------------------------ detection
    def _detect(self, tree, alarms, step, events):
        """Mismatch detection on the tree edges observed in this step (``alarms``: CUSUM alarm by model id)."""
        c = self.config
        observed = [self.pool.tracked[i] for i in tree if i in alarms and i not in self.mismatch]
        if not observed:
            return
        st, valid = self.pool.window_stats([e.row for e in observed], [self.pool.n_now(e) for e in observed])
        for k, e in enumerate(observed):
            window_bad = st.n[k] >= c.min_test_samples and not valid[k]
            if alarms[e.id] or window_bad:
                self._start_mismatch(e, step, events, bool(alarms[e.id]), st, k)
            else:
                self._challenge_from_memory(e, step, events, st, k)

    def _challenge_from_memory(self, entry, step, events, st, k):
        """Start a mismatch early when a remembered model of the same pair clearly fits the recent samples better.

        Only while the tree model's CUSUM is above zero (some evidence of drift): over the samples since the
        excursion started, a remembered model must be valid (at least ``reinstate_min_samples`` samples) and beat
        the tree model in a paired comparison in both channels, by more than ``challenge_margin`` on average. This
        is what lets a repair, or the same failure again, be handled within a few samples.
        """
        c = self.config
        monitor = self.pool.monitor
        if not np.any(monitor.cusum[entry.row] > 0.0):
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

    def _start_mismatch(self, entry, step, events, alarm, st, k, cause=None):
        """Put ``entry`` in mismatch, with the change point from its CUSUM (else the oldest window sample)."""
        c = self.config
        monitor = self.pool.monitor
        n, mt, mr, theta_t = int(st.n[k]), float(st.trans_error[k]), float(st.rot_error[k]), float(st.theta_trans[k])
        tau = int(monitor.change_point([entry.row])[0])
        if tau < 0:
            tau = int(monitor.first_step([entry.row])[0])
            tau = step if tau < 0 else tau
        S = monitor.cusum[entry.row]
        if cause is None:
            cause = (f"CUSUM {S[0]:.2f} (trans) / {S[1]:.2f} (rot) reached {c.cusum_threshold:g}" if alarm
                     else f"test window invalid over {n} samples")
        self.mismatch[entry.id] = Mismatch(tau=tau, detected=step, train_from=tau)
        events.append(Event(step, "mismatch_detected",
                            f"{entry.describe()} no longer matches the observations: {cause}; window mean "
                            f"{format_errors(mt, mr)} over {n} samples (thresholds "
                            f"{format_errors(theta_t, c.theta_rot)}); change point estimated at step {tau}",
                            parent=entry.parent, child=entry.child, model=entry.describe(),
                            trans_error=finite_or_none(mt), rot_error=finite_or_none(mr)))

    # ------------------------------------------------------------------ repair
    def _repair(self, tree, failed, step, events):
        """Memory first, then replacements (sampled once, resampled after ``replacement_patience``).

        Returns whether the edge was repaired.
        """
        c = self.config
        pool = self.pool
        mismatch = self.mismatch[failed.id]
        if self._reinstate_from_memory(tree, failed, mismatch, step, events):
            return True
        candidates = pool.candidates_of(failed.id)
        if not candidates and mismatch.sampled_at < 0:
            self._sample_replacements(failed, mismatch, step, events, mismatch.tau, "no remembered model fits")
            candidates = pool.candidates_of(failed.id)
        if not candidates:
            return False
        choice = self._choose_replacement(failed, candidates)
        if choice is not None:
            self._install_replacement(tree, failed, choice, step, events)
            return True
        if step - mismatch.sampled_at >= c.replacement_patience:
            for e in candidates:
                pool.remove(e)
            start = max(mismatch.train_from, step - c.test_window + 1)
            mismatch.resamples += 1
            self._sample_replacements(
                failed, mismatch, step, events, start,
                f"none of the {len(candidates)} replacements became valid within {c.replacement_patience} steps")
        return False

    def _reinstate_from_memory(self, tree, failed, mismatch, step, events):
        """Put back the cheapest remembered model that reconnects the tree and is valid since the change point."""
        c = self.config
        pool = self.pool
        monitor = pool.monitor
        memory = pool.with_role(MEMORY)
        if not memory:
            return False
        halves = tree_halves(pool.pairs.part_ids, [(pool.tracked[i].parent, pool.tracked[i].child)
                                                   for i in tree if i != failed.id])
        bridges = [e for e in memory if halves[e.parent] != halves[e.child]]
        if not bridges:
            return False
        st = monitor.stats([e.row for e in bridges], since=mismatch.tau)
        n, mt, mr = st.n, st.trans_error, st.rot_error
        ok = monitor.valid(st, c.reinstate_min_samples)
        if not np.any(ok):
            return False
        layer = np.array([e.complexity for e in bridges])
        cost = np.where(ok, model_cost(layer, st.trans_ratio, st.rot_ratio), np.inf)
        best = int(np.argmin(cost))
        back = bridges[best]
        pool.assign(back, TREE, step)
        pool.resume_refining(back)
        monitor.forget_before([back.row], mismatch.tau)
        self._take_over(tree, failed, back)
        events.append(Event(step, "model_reinstated",
                            f"remembered {back.describe()} fits again: mean error {format_errors(mt[best], mr[best])} "
                            f"over {n[best]} samples since the change point (step {mismatch.tau}), below "
                            f"{format_errors(st.theta_trans[best], c.theta_rot)}; it replaces {failed.describe()} "
                            f"(chosen among {int(ok.sum())} fitting of {len(bridges)} remembered)",
                            parent=back.parent, child=back.child, model=back.describe(),
                            trans_error=float(mt[best]), rot_error=float(mr[best])))
        if {back.parent, back.child} != {failed.parent, failed.child}:
            events.append(Event(step, "structure_changed",
                                f"edge {failed.parent}-{failed.child} replaced by {back.parent}-{back.child} "
                                f"({back.describe()}) from memory"))
        self._retire(failed, step, events, f"replaced by remembered {back.describe()}", mismatch.tau)
        return True

    def _sample_replacements(self, failed, mismatch, step, events, start, why):
        """Start replacements for ``failed`` learning on the history of its pair since step ``start``."""
        c = self.config
        pool = self.pool
        sets = [(r, acts) for r, acts in replacement_action_sets(failed.actions, pool.n_actions, c.max_complexity,
                                                                 c.replacement_max_relative)
                if len(acts) <= pool.batch.max_dim]
        entries = pool.add_learning([(failed.parent, failed.child, acts) for _, acts in sets], origin="replacement",
                                    created=step, target=failed.id)
        # Replay the raw history since the change point, test-then-train, so they need not wait for new data.
        k = len(entries)
        slots = np.array([e.slot for e in entries], dtype=np.intp)
        rows = np.array([e.row for e in entries], dtype=np.intp)
        limit = np.full(k, c.train_window)
        no_cusum = np.zeros(k, dtype=bool)
        used = 0
        for rec_step, a, obs in self.history:
            if rec_step < start or failed.parent not in obs or failed.child not in obs:
                continue
            Z = invert_transform(obs[failed.parent]) @ obs[failed.child]
            pool.prequential(slots, rows, a, np.broadcast_to(Z, (k, 4, 4)), rec_step,
                             np.full(k, pool.pairs.threshold(Z)), no_cusum, limit)
            used += 1
        mismatch.sampled_at = step
        mismatch.train_from = start
        listing = ", ".join(f"{e.describe()} [C={r}]" for (r, _), e in zip(sets, entries, strict=True))
        events.append(Event(step, "model_sampled",
                            f"{why}: sampled {len(entries)} replacement(s) for {failed.describe()}, ordered by "
                            f"relative complexity C(M2|M1) = |actions sym-diff|: {listing}; trained on the "
                            f"{used} samples of this pair since step {start} (replayed from history)",
                            parent=failed.parent, child=failed.child, model=failed.describe()))

    def _choose_replacement(self, failed, candidates):
        """The valid, not dominated candidate of least cost ``C(M2|M1) + e(M2)`` (Eq. 11), or None."""
        pool = self.pool
        rows = [e.row for e in candidates]
        n_now = [pool.n_now(e) for e in candidates]
        st, valid = pool.window_stats(rows, n_now)
        valid &= ~pool.dominated(rows, n_now, *nested_pairs(candidates), valid)
        if not np.any(valid):
            return None
        rel = np.array([relative_complexity(e.actions, failed.actions) for e in candidates])
        cost = np.where(valid, model_cost(rel, st.trans_ratio, st.rot_ratio), np.inf)
        best = int(np.argmin(cost))
        return Replacement(candidates[best], int(st.n[best]), float(st.trans_error[best]),
                           float(st.rot_error[best]), int(rel[best]), float(cost[best]), int(valid.sum()),
                           len(candidates))

    def _take_over(self, tree, failed, new):
        """``new`` takes ``failed``'s place in the tree: fresh CUSUM, mismatch closed, pending replacements dropped.

        Returns the closed :class:`Mismatch`.
        """
        tree[tree.index(failed.id)] = new.id
        self.pool.monitor.reset_cusum([new.row])
        for e in self.pool.candidates_of(failed.id):
            self.pool.remove(e)
        return self.mismatch.pop(failed.id)

    def _install_replacement(self, tree, failed, choice, step, events):
        """The chosen replacement becomes the tree model (still refining); the failed one goes to memory."""
        pool = self.pool
        new = choice.entry
        pool.assign(new, TREE, step)
        new.n_train = int(pool.batch.size([new.slot])[0])
        new.model = None  # keeps learning up to refine_window samples as a tree model; snapshot on demand
        if new.n_train >= pool.refine_window:
            pool.materialize(new)
        mismatch = self._take_over(tree, failed, new)
        events.append(Event(step, "model_replaced",
                            f"{new.describe()} replaces {failed.describe()}: valid with mean error "
                            f"{format_errors(choice.trans_error, choice.rot_error)} over {choice.n_test} test samples "
                            f"after {new.n_train} training samples since step {mismatch.train_from}; cost "
                            f"C(M2|M1) + e = {choice.cost:.2f} (relative complexity {choice.relative}), cheapest of "
                            f"{choice.n_valid} valid among {choice.n_sampled} sampled; mismatch lasted "
                            f"{step - mismatch.detected} steps",
                            parent=new.parent, child=new.child, model=new.describe(),
                            trans_error=choice.trans_error, rot_error=choice.rot_error))
        self._retire(failed, step, events, f"replaced by {new.describe()}", mismatch.tau)

    # ------------------------------------------------------------------ memory
    def _retire(self, entry, step, events, why, tau=None):
        """Move a model that left the tree to memory; forget the least recently used beyond ``memory_size``."""
        pool = self.pool
        if entry.slot >= 0:
            pool.materialize(entry, before=tau)
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

    @staticmethod
    def mismatch_from_state(items, tracked):
        """Rebuild :attr:`mismatch` from :meth:`mismatch_state` output; edges must be ids in ``tracked``."""
        mismatch = {}
        for item in items:
            item = dict(item)
            edge = int(item.pop("edge"))
            if edge not in tracked:
                raise ModelFileError(f"mismatch refers to unknown model id {edge}")
            mismatch[edge] = Mismatch(**{k: int(item[k]) for k in ("tau", "detected", "sampled_at", "train_from",
                                                                     "resamples")})
        return mismatch
