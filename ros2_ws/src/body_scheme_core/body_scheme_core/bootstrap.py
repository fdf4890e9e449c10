"""Bootstrapping: learning a body scheme from scratch (paper Sec. III-C).

A candidate local model is instantiated for every pair of parts, every action subset of at most ``max_complexity``
actions and every model class of ``candidate_kinds`` that fits it (the fully connected network of Fig. 4): static
models for no action; prismatic, revolute and GP models for one; GP models for more
(:func:`~body_scheme_core.structure.enumerate_candidates`). Each is a *temporal* local model: it learns from the first
``train_window`` relative observations of its pair and is then frozen. After every step the minimum spanning tree
over the valid candidates that no nesting candidate clearly beats (dominance rule) is searched layer by layer, with
the classes of a layer ordered by their rank (:func:`~body_scheme_core.quality.model_cost`).

Bootstrapping ends when a valid tree exists, its models are frozen and every candidate is frozen (or the tree has
been stable for ``bootstrap_patience`` steps): all other candidates are dropped and the tree's models become fitted
models, refined from then on by the joint fit of the learner. ``docs/core/learning-and-adaptation.md``, Sec. 3-4,
gives the rules and defaults.
"""

from __future__ import annotations

import numpy as np

from .events import Event, format_errors
from .quality import model_cost
from .structure import enumerate_candidates, select_spanning_tree
from .tracked import TREE

__all__ = ["Bootstrap"]


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

    def __init__(self, config, pool, pairs, found=False, tree_since=0, vetoed=None):
        self.config = config
        self.pool = pool
        self.pairs = pairs
        self.found = bool(found)
        self.tree_since = int(tree_since)
        self.vetoed = {} if vetoed is None else dict(vetoed)
        self._pair_index = None

    @staticmethod
    def add_candidates(pool, part_ids, n_actions, config):
        """Start every candidate of the fully connected network learning in ``pool``."""
        pool.add_learning(enumerate_candidates(part_ids, n_actions, config.max_complexity, config.candidate_kinds),
                          origin="bootstrap")

    def _pairs_of_learning(self):
        ls = self.pool.learning()
        if self._pair_index is None or self._pair_index[0] is not ls:
            pair = np.array([self.pairs.index(self.pool.tracked[int(i)].parent, self.pool.tracked[int(i)].child)
                             for i in ls.ids], dtype=np.intp)
            self._pair_index = (ls, pair)
        return self._pair_index[1]

    def step(self, tree, a, relative, step, events):
        """One step: every candidate whose pair is observed is tested, then trained; the tree is searched again.

        Parameters
        ----------
        tree : list of int or None
            Ids of the models of the current spanning tree; None while no valid tree exists.
        a : ndarray, shape (m,)
        relative : RelativeObservations
        step : int
        events : list of Event
            Appended to: ``structure_found`` or ``structure_changed``.

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
        return self.search(tree, step, events), True

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
        n_now = pool.sizes(ls)
        st, valid = pool.window_stats(ls.rows, n_now)
        dominated = valid & pool.dominated(ls.rows, n_now, *ls.nested, valid)
        valid &= ~dominated
        if self.vetoed:
            at = np.array([self.vetoed.get(int(i), -1) for i in ls.ids])
            vetoed = at >= 0
            expired = vetoed & ((n_now >= 1.5 * at + 1) | (n_now >= self.config.train_window))
            valid &= ~(vetoed & ~expired)
            if events is not None:
                for i in ls.ids[expired]:
                    del self.vetoed[int(i)]
        if exclude:
            valid &= ~np.isin(ls.ids, list(exclude))
        cost = model_cost(ls.layer, st.trans_ratio, st.rot_ratio, ls.rank)
        eligible = [(pool.tracked[i].parent, pool.tracked[i].child, int(i), int(ls.layer[k]), float(cost[k]))
                    for k, i in enumerate(ls.ids) if valid[k]]
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
            pos = {int(i): k for k, i in enumerate(ls.ids)}
            desc = "; ".join(f"{pool.tracked[i].describe()} cost {cost[pos[i]]:.2f} "
                             f"({format_errors(st.trans_error[pos[i]], st.rot_error[pos[i]])})" for i in keys)
            total = float(sum(cost[pos[i]] for i in keys))
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
        tree_frozen = all(n_now[pos[i]] >= c.train_window for i in tree)
        all_frozen = bool(np.all(n_now >= c.train_window))
        stable = step - self.tree_since >= c.bootstrap_patience
        if not (tree_frozen and (all_frozen or stable)):
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
                            f"models ({', '.join(e.describe() for e in kept)}), trained on {c.train_window} samples "
                            f"each; dropped {n_dropped} other candidates; the tree's models keep learning through "
                            f"the joint fit"))
        return True
