"""Lifelong adaptation of the body scheme's local models (paper Sec. III-E): one step after bootstrapping.

Every step, against the chain-consistent targets of the calibrated body scheme
(:mod:`~body_scheme_core.learning.chain`), :class:`Adaptation` evaluates and trains the tracked models, then

- **detects** the tree models that no longer match (:mod:`~body_scheme_core.learning.detection`),
- **repairs** each from memory or with a newly learned replacement (:mod:`~body_scheme_core.learning.repair`),
- lets a GP **challenge** each rigid joint once after bootstrapping (:mod:`~body_scheme_core.learning.challengers`),
- and **remembers** every model that leaves the tree (:mod:`~body_scheme_core.learning.memory`).

``docs/core/learning-and-adaptation.md``, Sec. 5-6, gives every rule, default and measurement.
"""

from __future__ import annotations

import dataclasses

from . import challengers, detection, repair
from .tracked import CANDIDATE, MEMORY

__all__ = ["Adaptation"]


class Adaptation:
    """Detects mismatching tree models and repairs them from memory or with newly learned replacements.

    The state the steps share; the steps are functions of :mod:`~body_scheme_core.learning.detection`,
    :mod:`~body_scheme_core.learning.repair`, :mod:`~body_scheme_core.learning.challengers` and
    :mod:`~body_scheme_core.learning.memory` that take it (``adapt``).

    Parameters
    ----------
    config : BodySchemeConfig
    pool : ModelPool
    history : collections.deque of (int, ndarray, dict)
        Recent raw steps ``(step, actions, {part: world2part})``, replayed to replacements (shared with the
        learner, which appends to it).
    part_ids : tuple of int
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
    chain_samples : dict of int to int
        Per failed chain's model id, the samples its replacements were last fitted on (not saved: after a load they
        are fitted again once there are enough).
    """

    def __init__(self, config, pool, history, part_ids, mismatch=None, refining=None, failed=None):
        self.config = config
        self.pool = pool
        self.history = history
        self.part_ids = tuple(part_ids)
        self.mismatch = {} if mismatch is None else mismatch
        self.refining = {} if refining is None else dict(refining)
        self.failed = {} if failed is None else dict(failed)
        self.chain_samples = {}

    def snapshot(self):
        """What :meth:`restore` needs to undo a learner's step (the mismatch records are copied: a step updates
        them)."""
        return ({k: dataclasses.replace(v) for k, v in self.mismatch.items()}, dict(self.refining), dict(self.failed),
                dict(self.chain_samples))

    def restore(self, saved):
        """Undo every change since :meth:`snapshot` returned ``saved``."""
        self.mismatch, self.refining, self.failed, self.chain_samples = saved

    def step(self, tree, root, a, chain, chain_at, step, events):
        """One step after bootstrapping: evaluate and train, detect mismatches, repair the edges in mismatch.

        Parameters
        ----------
        tree : list of int
            Ids of the tree's models; edges are replaced in place.
        root : int
            The tree's root part (the learner's).
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
        fitted = [e for e in pool.tracked.values() if e.role == CANDIDATE and e.slot < 0]  # chain replacements
        if fitted:
            index, targets = chain.for_entries(fitted, own=True)
            pool.evaluate([fitted[k] for k in index], a, targets, step, cusum=False)
        changes = repair.refine_choices(self, tree, step, events) + challengers.challenge(self, tree, step, events)
        # After those changes: detection sees the tree as it is now (a replaced model is no edge of it any more).
        detection.detect(self, tree, root, alarms, step, events)
        for edge_id in list(self.mismatch):
            if edge_id in self.mismatch:
                change = repair.repair(self, tree, root, pool.tracked[edge_id], chain, chain_at, step, events)
                if change is not None:
                    changes.append(change)
        return changes

    def sample_challengers(self, tree, chain, chain_at, step, events):
        """:func:`~body_scheme_core.learning.challengers.sample_challengers` (right after bootstrapping)."""
        challengers.sample_challengers(self, tree, chain, chain_at, step, events)

    def flag(self, entry, step, events, cause):
        """:func:`~body_scheme_core.learning.detection.flag`: tree edge ``entry`` in mismatch for ``cause``."""
        detection.flag(self, entry, step, events, cause)
