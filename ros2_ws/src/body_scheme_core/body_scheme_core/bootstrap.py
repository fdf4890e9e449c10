"""Bootstrapping: learning a body scheme from scratch (paper Sec. III-C).

A candidate local model is instantiated for every pair of parts and every action subset of at most
``max_complexity`` actions (the fully connected network of Fig. 4), all of them GPs in one batch of the
:class:`~body_scheme_core.pool.ModelPool`. Each is a *temporal* local model: it learns from the first
``train_window`` observations of its pair and is then frozen. After every step the minimum spanning tree over the
valid candidates that no candidate with more actions clearly beats (dominance rule) is searched layer by layer
(:func:`~body_scheme_core.structure.select_spanning_tree`).

Bootstrapping ends when a valid tree exists, its models are frozen and every candidate is frozen (or the tree has
been stable for ``bootstrap_patience`` steps): all other candidates are dropped and the tree's models keep learning
up to ``refine_window`` samples. ``docs/core/learning-and-adaptation.md``, Sec. 3-4, gives the rules and defaults.
"""

from __future__ import annotations

import numpy as np

from .events import Event
from .pool import TREE, format_errors
from .quality import model_cost
from .structure import enumerate_candidates, select_spanning_tree

__all__ = ["Bootstrap"]


class Bootstrap:
    """The structure search of the bootstrapping phase, and the decision that it is over.

    Parameters
    ----------
    config : BodySchemeConfig
    pool : ModelPool
        Holds the candidates (see :meth:`add_candidates`).
    found : bool
        Whether a valid tree was found before (losing and regaining it is then a change, not a find).
    tree_since : int
        Step at which the current tree (or the lack of one) began.

    Attributes
    ----------
    found : bool
    tree_since : int
    """

    def __init__(self, config, pool, found=False, tree_since=0):
        self.config = config
        self.pool = pool
        self.found = bool(found)
        self.tree_since = int(tree_since)

    @staticmethod
    def add_candidates(pool, part_ids, n_actions, max_complexity):
        """Start every candidate of the fully connected network learning in ``pool``."""
        pool.add_learning(enumerate_candidates(part_ids, n_actions, max_complexity), origin="bootstrap")

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
        parts = pool.pairs.part_ids
        evaluated, _ = pool.train_learning(a, relative, step)
        if evaluated.size == 0:
            return tree, False
        ls = pool.learning()
        n_now = pool.batch.size(ls.slots)
        st, valid = pool.window_stats(ls.rows, n_now)
        dominated = valid & pool.dominated(ls.rows, n_now, *ls.nested, valid)
        valid &= ~dominated
        cost = model_cost(ls.layer, st.trans_ratio, st.rot_ratio)
        eligible = [(pool.tracked[i].parent, pool.tracked[i].child, int(i), int(ls.layer[k]), float(cost[k]))
                    for k, i in enumerate(ls.ids) if valid[k]]
        keys = select_spanning_tree(parts, eligible)
        if keys is None:
            if tree is not None and len(parts) > 1:
                events.append(Event(step, "structure_changed",
                                    f"no valid spanning tree any more: {len(eligible)} valid candidates of "
                                    f"{ls.ids.size} ({int(dominated.sum())} more valid but dominated) do not "
                                    f"connect all parts"))
                self.tree_since = step
            return None, True
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
            events.append(Event(step, kind, f"{what} from {len(eligible)} eligible of {ls.ids.size} candidates "
                                            f"({int(dominated.sum())} more valid but dominated by a model with more "
                                            f"actions), total cost {total:.2f}: {desc}"))
            self.found = True
            tree = list(keys)
            self.tree_since = step
        return tree, True

    def finish_if_ready(self, tree, step, events):
        """End bootstrapping if the tree's models are frozen and all candidates are, or the tree is stable.

        Then the tree's models become tree models (test windows kept, CUSUMs reset) in a fresh, compact pool
        storage and every other candidate is dropped (``bootstrap_finished``).

        Returns
        -------
        finished : bool
        """
        if tree is None:
            return False
        c = self.config
        pool = self.pool
        ls = pool.learning()
        n_now = pool.batch.size(ls.slots)
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
        refining = pool.keep_only(kept)
        why = "all candidates are frozen" if all_frozen else f"the tree was stable for {step - self.tree_since} steps"
        refine = f"; the tree models keep learning up to {pool.refine_window} samples" if refining else ""
        events.append(Event(step, "bootstrap_finished",
                            f"bootstrapping finished after {step + 1} steps ({why}): kept the {len(kept)} tree "
                            f"models ({', '.join(e.describe() for e in kept)}), trained on {c.train_window} samples "
                            f"each; dropped {n_dropped} other candidates{refine}"))
        return True
