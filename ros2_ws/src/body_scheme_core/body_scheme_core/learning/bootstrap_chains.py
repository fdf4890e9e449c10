"""The chains of the bootstrapping phase: fitted candidates that connect parts no layer connects.

A tool seen past six joints and the base have no model class of any layer between them: their chain
(:class:`~body_scheme_core.models.chain.ChainModel`) is identified from the recorded samples
(:func:`~body_scheme_core.learning.chain_search.identify_chain`), tracked as a *fitted* candidate of the pair (it does
not learn in a batch), tested prequentially like any candidate, and offered to the tree search when valid. The
:class:`~body_scheme_core.learning.bootstrap.Bootstrap` decides when a pair needs one
(:meth:`~body_scheme_core.learning.bootstrap.Bootstrap.connect_with_chains`); :class:`Chains` finds, tests and keeps
them.
"""

from __future__ import annotations

import math

import numpy as np

from ..events import Event
from .chain_search import ChainNotIdentified, identify_chain, order_decided
from .quality import model_cost
from .tracked import CANDIDATE, nested_models

__all__ = ["Chains", "CHAIN_RETRY", "CHAIN_RETRY_MIN"]

#: A pair's chain is identified again once the samples that observed both its parts grew by this fraction, and by
#: at least CHAIN_RETRY_MIN (excursions of other joints may have come, and a chain found learns from more data).
CHAIN_RETRY, CHAIN_RETRY_MIN = 0.25, 2


class Chains:
    """The chains found while bootstrapping: fitted candidates in ``pool``, identified from ``history``.

    Parameters
    ----------
    config : BodySchemeConfig
    pool : ModelPool
    pairs : PartPairs
    history : collections.deque of (int, ndarray, dict)
        The learner's recorded steps.

    Attributes
    ----------
    tried : dict of (int, int) to int
        Per pair (canonical direction), the samples of both parts at its last identification.
    """

    def __init__(self, config, pool, pairs, history=()):
        self.config = config
        self.pool = pool
        self.pairs = pairs
        self.history = history
        self.tried = {}

    def fitted(self):
        """Candidates with a fitted model (chains), in pool order."""
        return [e for e in self.pool.tracked.values() if e.role == CANDIDATE and e.slot < 0]

    def test(self, a, relative, step):
        """Fitted candidates predict this step's relative observation of their pair (prequential: they were
        identified from earlier samples), in its canonical direction."""
        fitted = self.fitted()
        if not fitted:
            return
        pair = np.array([self.pairs.index(e.parent, e.child) for e in fitted], dtype=np.intp)
        sel = np.flatnonzero(relative.row[pair] >= 0)
        if sel.size:
            self.pool.evaluate([fitted[k] for k in sel], a, relative.targets(pair[sel]), step,
                               cusum=np.zeros(sel.size, dtype=bool))

    def eligible(self, exclude=()):
        """``(parent, child, id, layer, cost)`` of the valid fitted candidates (chains) that no other one dominates,
        for the tree search."""
        fitted = [e for e in self.fitted() if e.id not in set(exclude)]
        if not fitted:
            return []
        pool = self.pool
        rows, sizes = [e.row for e in fitted], [e.n_train for e in fitted]
        st, valid = pool.window_stats(rows, sizes)
        valid &= ~pool.dominated(rows, sizes, *nested_models(fitted), valid)  # a chain of fewer of its joints
        layer = np.array([e.complexity for e in fitted], dtype=float)
        cost = model_cost(layer, st.trans_ratio, st.rot_ratio, np.array([e.rank for e in fitted]))
        return [(e.parent, e.child, e.id, int(layer[k]), float(cost[k])) for k, e in enumerate(fitted) if valid[k]]

    def undecided(self, tree):
        """Whether the tree holds a chain whose joints' order the data has not decided yet."""
        return any(not order_decided(self.pool.tracked[i].model) for i in tree
                   if self.pool.tracked[i].slot < 0)

    def drop_superseded(self, tree):
        """Chains of a pair identified again that the tree does not hold: only the newest of a pair is kept."""
        newest = {}
        for entry in self.fitted():
            newest[frozenset((entry.parent, entry.child))] = entry.id
        old = [e for e in self.fitted() if e.id != newest[frozenset((e.parent, e.child))] and e.id not in (tree or ())]
        if old:
            self.pool.remove(*old)

    def identify(self, u, v, tree, step, events, why, growth=CHAIN_RETRY):
        """Identify a chain between parts ``u`` and ``v`` from the recorded steps
        (:func:`~body_scheme_core.learning.chain_search.identify_chain`), when the samples that observed both grew
        enough since the last try (by the fraction ``growth``, at least
        ``CHAIN_RETRY_MIN``); a chain of 2 to ``config.max_chain_joints`` joints is tracked as a fitted candidate of
        the pair in its canonical direction, replacing the pair's earlier chain unless the tree holds it. ``why``
        opens the event's reason. Returns whether a chain was added."""
        c = self.config
        pool = self.pool
        parent, child = (u, v) if self.pairs.part_index[u] < self.pairs.part_index[v] else (v, u)
        tried = self.tried.get((parent, child), 0)
        n = sum(parent in obs and child in obs for _, _, obs in self.history)
        if c.max_chain_joints < 2 or n < tried + max(CHAIN_RETRY_MIN, math.ceil(growth * tried)):
            return False
        self.tried[(parent, child)] = n
        index = self.pairs.index(parent, child)
        A, Z, S, recorded = [], [], [], []
        for rec_step, a, obs in self.history:
            relative = self.pairs.observe({p: obs[p] for p in (parent, child) if p in obs})
            if relative.row[index] >= 0:
                targets = relative.targets(np.array([index]))
                A.append(a)
                Z.append(targets.Z[0])
                S.append(targets.sigma[0])
                recorded.append((rec_step, a, targets))
        try:
            model = identify_chain(np.array(A), np.array(Z), np.array(S), parent, child, range(pool.n_actions),
                                   sigma_trans=c.prior_sigma_trans, sigma_rot=c.prior_sigma_rot)
        except ChainNotIdentified:
            return False
        if not 2 <= len(model.actions) <= c.max_chain_joints:
            return False  # one action: the layers' own candidates of that pair say it better
        old = [e for e in self.fitted() if {e.parent, e.child} == {parent, child} and e.id not in (tree or ())]
        if old:  # (one in the tree stays until the search replaced it: drop_superseded)
            pool.remove(*old)
        entry = pool.add_fitted([model], CANDIDATE, origin="chain", last_used=step)[0]
        entry.n_train = len(A)
        # Its test window starts with the last recorded samples, which it was fitted on (a little optimistic: a
        # chain's parameters are few against a window of 6-dimensional samples), so that the last poses of a finite
        # recording need not wait for more; the next samples replace them.
        for rec_step, a, targets in recorded[-c.test_window:]:
            pool.evaluate([entry], a, targets, rec_step, cusum=np.zeros(1, dtype=bool))
        events.append(Event(step, "model_sampled",
                            f"{why}: identified {entry.describe()} from {len(A)} recorded steps "
                            f"({', '.join(model.types)}; fit rms {model.rms_:.2f} sigma)",
                            parent=parent, child=child, model=entry.describe()))
        return True
