"""Bootstrapping: learning a body scheme from scratch (paper Sec. III-C).

A candidate local model is instantiated for every pair of parts, every action subset of at most one action and
every model class of ``candidate_kinds`` that fits it (static models for no action; prismatic, revolute and GP
models for one: :func:`~body_scheme_core.learning.structure.enumerate_candidates`). The next complexity layer (GP models
on more actions) is instantiated lazily, only for the pairs across the parts the layers so far cannot connect
(:meth:`Bootstrap.expand`, paper Sec. III-D), and learns the recorded history at once; with ``lazy_layers`` off
every layer up to ``max_complexity`` starts at once (the fully connected network of Fig. 4). Each candidate is a
*temporal* local model: it learns from the first ``train_window`` relative observations of its pair and is then
frozen. After every step the candidates that are invalid with high confidence are dropped (racing,
:meth:`Bootstrap.race`), and the minimum spanning tree over the valid candidates that no nesting candidate clearly
beats (dominance rule) is searched layer by layer, with the classes of a layer ordered by their rank
(:func:`~body_scheme_core.learning.quality.model_cost`).

Parts that no layer connects (a tool whose marker is the only one past six joints, and the base) are connected by a
*chain* (:class:`~body_scheme_core.models.chain.ChainModel`): its joints, their order and their types are identified
from the recorded samples in which few actions moved (:func:`~body_scheme_core.learning.chain_search.identify_chain`,
:meth:`Bootstrap.connect_with_chains`), and it is then tested like any candidate, prequentially, before the search
may take it. A chain of k actions is in layer k, where a GP of as many actions would be.

Bootstrapping ends when a valid tree exists, its models are frozen and every candidate is frozen (or the tree has
been stable for ``bootstrap_patience`` steps): all other candidates are dropped and the tree's models become fitted
models, refined from then on by the joint fit of the learner. ``docs/core/learning-and-adaptation.md``, Sec. 3-4,
gives the rules and defaults.
"""

from __future__ import annotations

import itertools

import networkx as nx
import numpy as np

from ..events import Event, format_errors
from .bootstrap_chains import Chains
from .chain_search import order_decided
from .quality import model_cost
from .structure import enumerate_candidates, kinds_for, select_spanning_tree
from .tracked import TREE, nested_models

__all__ = ["Bootstrap", "SUSPECT_RATIO"]

#: A tree model whose window mean error ratio exceeds this in either channel when bootstrapping would end has its
#: pair's next layer instantiated first (:meth:`Bootstrap.expand_suspects`); right models stay below about half.
SUSPECT_RATIO = 0.6


class Bootstrap:
    """The structure search of the bootstrapping phase, and the decision that it is over.

    Parameters
    ----------
    config : BodySchemeConfig
    pool : ModelPool
        Holds the candidates (see :meth:`add_candidates`).
    pairs : PartPairs
        Pair numbering of the relative observations.
    found : bool
        Whether a valid tree was found before (losing and regaining it is then a change, not a find).
    tree_since : int
        Step at which the current tree (or the lack of one) began.

    vetoed : dict of int to int, optional
        Candidates excluded from the search (see :meth:`veto`), with their training-set size at the veto.

    Attributes
    ----------
    found : bool
    tree_since : int
    vetoed : dict of int to int
    """

    def __init__(self, config, pool, pairs, found=False, tree_since=0, vetoed=None, history=()):
        self.config = config
        self.pool = pool
        self.pairs = pairs
        self.found = bool(found)
        self.tree_since = int(tree_since)
        self.vetoed = {} if vetoed is None else dict(vetoed)
        self.history = history
        self.raced = 0
        self._pair_index = None
        self._layers = None  # {(parent, child): highest complexity instantiated}, see _instantiated_layers
        self.chains = Chains(config, pool, pairs, history)  # the chains that connect what no layer connects

    def snapshot(self):
        """What :meth:`restore` needs to undo a learner's step."""
        return (self.found, self.tree_since, dict(self.vetoed), self.raced,
                None if self._layers is None else dict(self._layers), dict(self.chains.tried))

    def restore(self, saved):
        """Undo every change since :meth:`snapshot` returned ``saved``."""
        self.found, self.tree_since, self.vetoed, self.raced, self._layers, self.chains.tried = saved
        self._pair_index = None

    @staticmethod
    def add_candidates(pool, part_ids, n_actions, config):
        """Start the candidates of the fully connected network learning in ``pool``: those of complexity <= 1 with
        ``config.lazy_layers`` (the others follow where needed, :meth:`expand`), else all."""
        top = min(config.max_complexity, 1) if config.lazy_layers else config.max_complexity
        pool.add_learning(enumerate_candidates(part_ids, n_actions, top, config.candidate_kinds), origin="bootstrap")

    def _pairs_of_learning(self):
        ls = self.pool.learning()
        if self._pair_index is None or self._pair_index[0] is not ls:
            pair = np.array([self.pairs.index(self.pool.tracked[int(i)].parent, self.pool.tracked[int(i)].child)
                             for i in ls.ids], dtype=np.intp)
            self._pair_index = (ls, pair)
        return self._pair_index[1]

    def step(self, tree, a, relative, step, events):
        """One step: every candidate whose pair is observed is tested, then trained; hopeless ones are raced out; the
        tree is searched again, and without one the next layer is instantiated where needed (:meth:`expand`).

        Parameters
        ----------
        tree : list of int or None
            Ids of the models of the current spanning tree; None while no valid tree exists.
        a : ndarray, shape (m,)
        relative : RelativeObservations
        step : int
        events : list of Event
            Appended to: ``structure_found``, ``structure_changed`` or ``model_sampled`` (a new layer).

        Returns
        -------
        tree : list of int or None
            The tree after this step.
        learned : bool
            Whether any candidate was evaluated (and so possibly learned).
        """
        pool = self.pool
        ls = pool.learning()
        pair = self._pairs_of_learning()
        sel = np.flatnonzero(relative.row[pair] >= 0)
        if sel.size == 0:
            return tree, False
        # Candidates are enumerated in the canonical direction of their pair, so the targets need no flip.
        pool.train(ls.ids[sel], a, relative.targets(pair[sel]), step)
        self.chains.test(a, relative, step)
        self.race(tree)
        tree = self.search(tree, step, events)
        if tree is None and self.expand(step, events):
            tree = self.search(tree, step, events)
        if (tree is None or self.chains.undecided(tree)) and self.connect_with_chains(tree, step, events):
            tree = self.search(tree, step, events)
            self.chains.drop_superseded(tree)
        return tree, True

    def connect_with_chains(self, tree, step, events):
        """Where the eligible candidates (chains whose joints' order is not decided yet left out) cannot connect the
        parts, identify a chain between the two parts of each pair of components that were observed together most
        (:func:`~body_scheme_core.learning.chain_search.identify_chain`), from the recorded steps, once that pair's
        candidates of every layer were tested on a full test window; a chain found is tracked as a fitted candidate
        of the pair (:meth:`~body_scheme_core.learning.bootstrap_chains.Chains.identify`). Up to
        ``config.max_chain_joints`` joints; 0 or 1 turns chains off. Returns whether a chain was added."""
        c = self.config
        if c.max_chain_joints < 2 or len(self.history) == 0:
            return False
        pool = self.pool
        ls = pool.learning()
        _, valid, _, _ = self._eligible(ls)
        graph = nx.Graph()
        graph.add_nodes_from(self.pairs.part_ids)
        graph.add_edges_from((pool.tracked[int(i)].parent, pool.tracked[int(i)].child) for i in ls.ids[valid])
        graph.add_edges_from((p, q) for p, q, key, _, _ in self.chains.eligible()
                             if order_decided(pool.tracked[key].model))
        components = [sorted(members) for members in nx.connected_components(graph)]
        if len(components) < 2:
            return False
        seen = [set(obs) for _, _, obs in self.history]
        tested, layers = self._tested(ls), self._instantiated_layers()
        added = False
        for first, second in itertools.combinations(components, 2):
            counts = {(u, v): sum(u in s and v in s for s in seen) for u in first for v in second}
            u, v = max(counts, key=lambda uv: (counts[uv], uv))
            pair = (u, v) if self.pairs.part_index[u] < self.pairs.part_index[v] else (v, u)
            if layers.get(pair, 0) < c.max_complexity or tested.get(pair, c.test_window) < c.test_window:
                continue  # the layers have not had their chance yet
            why = f"parts {u} and {v} are not connected by the candidates of layers up to {c.max_complexity}"
            added |= self.chains.identify(u, v, tree, step, events, why)
        return added

    def _tested(self, ls):
        """``{(parent, child): fewest test samples of its learning candidates}`` in the canonical direction."""
        tested = {}
        for i, count in zip(ls.ids, self.pool.monitor.count[ls.rows], strict=True):
            entry = self.pool.tracked[int(i)]
            key = (entry.parent, entry.child)
            tested[key] = min(tested.get(key, count), count)
        return tested

    def race(self, tree):
        """Drop the candidates that are invalid with high confidence
        (:meth:`~body_scheme_core.learning.validity.ValidityMonitor.hopeless`), except those of the current tree (the
        search drops them first); counted in :attr:`raced`."""
        c = self.config
        if c.race_samples < 1:
            return
        pool = self.pool
        ls = pool.learning()
        hopeless = pool.monitor.hopeless(ls.rows, c.race_samples, c.race_ratio, c.race_min_train)
        keep = set(tree or ())
        drop = [pool.tracked[int(i)] for i in ls.ids[hopeless] if int(i) not in keep]
        if drop:
            for entry in drop:
                self.vetoed.pop(entry.id, None)
            pool.remove(*drop)
            self.raced += len(drop)

    def expand(self, step, events):
        """Lazy layers (paper Sec. III-D): where the eligible candidates of the layers instantiated so far (valid, not
        dominated, not vetoed: those the search takes) cannot connect the parts, start the next layer's candidates of
        every pair across the parts they leave apart, once each of that pair's candidates has been tested on a full
        test window; they learn the recorded history at once. Returns whether candidates were added."""
        c = self.config
        if not c.lazy_layers:
            return False
        pool = self.pool
        ls = pool.learning()
        _, valid, _, _ = self._eligible(ls)
        entries = [pool.tracked[int(i)] for i in ls.ids]
        graph = nx.Graph()
        graph.add_nodes_from(self.pairs.part_ids)
        graph.add_edges_from((entries[k].parent, entries[k].child) for k in np.flatnonzero(valid))
        component = {p: k for k, members in enumerate(nx.connected_components(graph)) for p in members}
        if max(component.values(), default=0) == 0:
            return False
        tested = self._tested(ls)
        layers = self._instantiated_layers()
        pairs = [pair for pair, top in layers.items() if top < c.max_complexity
                 and component[pair[0]] != component[pair[1]] and tested.get(pair, c.test_window) >= c.test_window]
        return self._next_layer(pairs, step, events, "do not connect the parts")

    def expand_suspects(self, tree, step, events):
        """Before bootstrapping ends, the next layer for the pairs of tree models that fit poorly (a window mean
        error ratio over :data:`SUSPECT_RATIO` in either channel; right models stay below about half): a higher
        layer may nest them and clearly beat them (dominance), as the eager search would have seen. Returns whether
        candidates were added (then bootstrapping goes on)."""
        c = self.config
        if not c.lazy_layers or not tree:
            return False
        pool = self.pool
        entries = [pool.tracked[i] for i in tree]
        n_now = np.array([pool.n_now(e) for e in entries])
        st, _ = pool.window_stats([e.row for e in entries], n_now)
        layers = self._instantiated_layers()
        pairs = [(e.parent, e.child) for k, e in enumerate(entries)
                 if max(st.trans_ratio[k], st.rot_ratio[k]) > SUSPECT_RATIO
                 and layers.get((e.parent, e.child), c.max_complexity) < c.max_complexity]
        return self._next_layer(pairs, step, events, "leave tree models that fit poorly")

    def _next_layer(self, pairs, step, events, why):
        """Start the next layer's candidates of ``pairs`` and train them on the history; whether any were added."""
        c = self.config
        layers = self._instantiated_layers()
        specs = []
        for pair in pairs:
            top = layers[pair]
            layers[pair] = top + 1
            specs += [(*pair, acts, kind) for acts in itertools.combinations(range(self.pool.n_actions), top + 1)
                      for kind in kinds_for(acts, c.candidate_kinds)]
        if not specs:
            return False
        added = self.pool.add_learning(specs, origin="bootstrap")
        used = self._replay(added)
        events.append(Event(step, "model_sampled",
                            f"the eligible candidates of the layers instantiated so far {why}: sampled {len(added)} "
                            f"candidates of the next layer for {len(pairs)} pair(s), trained on the {used} recorded "
                            f"steps that observed their pairs"))
        return True

    def _instantiated_layers(self):
        """``{(parent, child): highest complexity instantiated}`` of every pair, in the direction candidates are
        enumerated (:func:`enumerate_candidates`); from the pool at first use, so after a restart a layer whose
        candidates were all raced out is instantiated again."""
        if self._layers is None:
            start = min(self.config.max_complexity, 1) if self.config.lazy_layers else self.config.max_complexity
            self._layers = {pair: start for pair in itertools.combinations(self.pairs.part_ids, 2)}
            for entry in self.pool.tracked.values():
                key = (entry.parent, entry.child)
                if key in self._layers:
                    self._layers[key] = max(self._layers[key], entry.complexity)
        return self._layers

    def _replay(self, entries):
        """Train new candidates on the recorded history, test-then-train; returns the steps that observed a pair."""
        pair = np.array([self.pairs.index(e.parent, e.child) for e in entries], dtype=np.intp)

        def targets_at(a, obs):
            relative = self.pairs.observe(obs)
            sel = np.flatnonzero(relative.row[pair] >= 0)
            return sel, relative.targets(pair[sel])

        return self.pool.replay(entries, self.history, targets_at)

    def veto(self, entry_id):
        """Exclude a candidate from the search until its training set has grown by half (a tree edge whose calibrated
        body scheme does not explain the absolute observations of its child, :meth:`BodySchemeLearner` checks)."""
        self.vetoed[int(entry_id)] = self.pool.n_now(self.pool.tracked[int(entry_id)])

    def search(self, tree, step, events, why="", exclude=()):
        """The layered minimum spanning tree over the eligible candidates; events when it changed.

        Parameters
        ----------
        tree : list of int or None
            The current tree.
        step : int
        events : list of Event or None
            Appended to; None for a trial search that changes nothing.
        why : str
            Appended to the event's reason.
        exclude : iterable of int
            Candidates left out of this search only.

        Returns
        -------
        tree : list of int or None
        """
        pool = self.pool
        parts = self.pairs.part_ids
        ls = pool.learning()
        st, valid, dominated, expired = self._eligible(ls)
        if events is not None:
            for i in expired:
                del self.vetoed[int(i)]
        if exclude:
            valid &= ~np.isin(ls.ids, list(exclude))
        cost = model_cost(ls.layer, st.trans_ratio, st.rot_ratio, ls.rank)
        eligible = [(pool.tracked[i].parent, pool.tracked[i].child, int(i), int(ls.layer[k]), float(cost[k]))
                    for k, i in enumerate(ls.ids) if valid[k]]
        eligible += self.chains.eligible(exclude)
        cost_of = {key: c for _, _, key, _, c in eligible}
        keys = select_spanning_tree(parts, eligible)
        if events is None:
            return keys
        if keys is None:
            if tree is not None and len(parts) > 1:
                events.append(Event(step, "structure_changed",
                                    f"no valid spanning tree any more{why}: {len(eligible)} valid candidates of "
                                    f"{ls.ids.size} ({int(dominated.sum())} more valid but dominated) do not "
                                    f"connect all parts"))
                self.tree_since = step
            return None
        if tree is None or set(keys) != set(tree):
            entries = [pool.tracked[i] for i in keys]
            stats, _ = pool.window_stats([e.row for e in entries], [pool.n_now(e) for e in entries])
            desc = "; ".join(f"{e.describe()} cost {cost_of[e.id]:.2f} "
                             f"({format_errors(stats.trans_error[k], stats.rot_error[k])})"
                             for k, e in enumerate(entries))
            total = float(sum(cost_of[i] for i in keys))
            if tree is None and not self.found:
                kind, what = "structure_found", "first valid spanning tree"
            else:
                kind, what = "structure_changed", "spanning tree changed"
            if tree is not None:
                gone = [pool.tracked[i].describe() for i in tree if i not in set(keys)]
                what += f" (replacing {', '.join(gone)})" if gone else ""
            events.append(Event(step, kind, f"{what}{why} from {len(eligible)} eligible of {ls.ids.size} candidates "
                                            f"({int(dominated.sum())} more valid but dominated by a model that nests "
                                            f"them), total cost {total:.2f}: {desc}"))
            self.found = True
            tree = list(keys)
            self.tree_since = step
        return tree

    def _eligible(self, ls):
        """``(stats, eligible, dominated, expired vetoes)`` of the learning candidates ``ls``: valid, not dominated
        by a nesting candidate, and not vetoed (a veto expires once its candidate's training set grew by half or is
        full)."""
        pool = self.pool
        n_now = pool.sizes(ls)
        st, valid = pool.window_stats(ls.rows, n_now)
        dominated = valid & (pool.dominated(ls.rows, n_now, *ls.nested, valid)
                             | self._dominated_by_fitted(ls, n_now, valid))
        valid &= ~dominated
        expired = ls.ids[:0]
        if self.vetoed:
            at = np.array([self.vetoed.get(int(i), -1) for i in ls.ids])
            vetoed = at >= 0
            done = vetoed & ((n_now >= 1.5 * at + 1) | (n_now >= self.config.train_window))
            valid &= ~(vetoed & ~done)
            expired = ls.ids[done]
        return st, valid, dominated, expired

    def _dominated_by_fitted(self, ls, n_now, valid):
        """Mask over the learning candidates ``ls``: valid ones that a valid fitted candidate of their pair nests and
        beats by the dominance rule (a chain on actions that include theirs, clearly better: the actions it adds
        matter). No fitted candidates, no cost."""
        fitted = self.chains.fitted()
        out = np.zeros(ls.ids.size, dtype=bool)
        if not fitted:
            return out
        pool = self.pool
        groups = {(e.parent, e.child, e.target) for e in fitted}
        entries = [pool.tracked[int(i)] for i in ls.ids]
        sel = [k for k in np.flatnonzero(valid) if (entries[k].parent, entries[k].child, entries[k].target) in groups]
        if not sel:
            return out
        _, fitted_valid = pool.window_stats([e.row for e in fitted], [e.n_train for e in fitted])
        sub, sup = nested_models([entries[k] for k in sel] + fitted)
        keep = sup >= len(sel)
        keep[keep] &= (sub[keep] < len(sel)) & fitted_valid[sup[keep] - len(sel)]
        rows = np.concatenate([ls.rows[sel], [e.row for e in fitted]])
        sizes = np.concatenate([n_now[sel], [e.n_train for e in fitted]])
        beaten = pool.dominated(rows, sizes, sub[keep], sup[keep])
        out[np.asarray(sel)[beaten[:len(sel)]]] = True
        return out

    def finish_if_ready(self, tree, step, events):
        """End bootstrapping if the tree's models are frozen and all candidates are, or the tree is stable.

        Then the tree's models become fitted tree models (rigid candidates refitted robustly) in fresh, compact pool
        storage with empty test windows, and every other candidate is dropped (``bootstrap_finished``).

        Returns
        -------
        finished : bool
        """
        if tree is None:
            return False
        c = self.config
        pool = self.pool
        ls = pool.learning()
        n_now = pool.sizes(ls)
        pos = {int(i): k for k, i in enumerate(ls.ids)}
        # A fitted candidate (a chain) learns no more: it is frozen once its joints' order was decided by data.
        tree_frozen = all(n_now[pos[i]] >= c.train_window if i in pos else order_decided(pool.tracked[i].model)
                          for i in tree)
        all_frozen = bool(np.all(n_now >= c.train_window))
        stable = step - self.tree_since >= c.bootstrap_patience
        if not (tree_frozen and (all_frozen or stable)):
            return False
        if self.expand_suspects(tree, step, events):
            return False
        kept = [pool.tracked[i] for i in tree]
        n_dropped = len(pool.tracked) - len(kept)
        for entry in kept:
            pool.assign(entry, TREE, step)
        pool.keep_only(kept)
        # From here on the tree's models are tested against chain-consistent targets (a different error than the
        # relative observations of the windows so far): start their windows afresh.
        pool.monitor.clear([e.row for e in kept])
        why = "all candidates are frozen" if all_frozen else f"the tree was stable for {step - self.tree_since} steps"
        events.append(Event(step, "bootstrap_finished",
                            f"bootstrapping finished after {step + 1} steps ({why}): kept the {len(kept)} tree "
                            f"models ({', '.join(f'{e.describe()} on {e.n_train} samples' for e in kept)}); "
                            f"dropped {n_dropped} other candidates; the tree's models keep learning through the "
                            f"joint fit"))
        return True
