"""The pool of local models a learner tracks, and their prequential (test-then-train) evaluation.

A :class:`~body_scheme_core.learning.tracked.TrackedModel` is a local model in one of three roles: ``tree`` (an edge of
the body scheme), ``memory`` (retired, remembered for reuse) or ``candidate`` (still learning: a bootstrap candidate or
a replacement for a failed tree model). :class:`ModelPool` holds all of them with their storage:

- candidates learn in one of two batches: GP candidates in a :class:`~body_scheme_core.models.gp_batch.GPBatch`,
  rigid-joint candidates (static, prismatic, revolute) in a :class:`~body_scheme_core.models.rigid_batch.RigidBatch`
  (one *slot* each); tree and memory models are fitted :class:`~body_scheme_core.models.base.LocalModel` objects (the
  tree's are refined by the joint fit, :mod:`~body_scheme_core.calibration.joint_fit`);
- every tracked model has one *row* in the :class:`~body_scheme_core.learning.validity.ValidityMonitor` (test window and
  CUSUM).

Every step each tracked model whose *target* is available first predicts it, its error enters its test window, and
only then may a learning model add the sample to its training set (:meth:`ModelPool.evaluate`,
:meth:`ModelPool.train`). The targets come from the caller as a :class:`~body_scheme_core.learning.targets.Targets`:
the relative observations ``Y_i^-1 Y_j`` while bootstrapping (:mod:`~body_scheme_core.learning.relative`), the
chain-consistent observations of the calibrated body scheme afterwards (:mod:`~body_scheme_core.learning.chain`). The
decisions built on top (structure search, change detection, repair) live in
:mod:`~body_scheme_core.learning.bootstrap` and :mod:`~body_scheme_core.learning.adaptation`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..models import RIGID_CLASSES, GPBatch, GPModel, RigidBatch
from ..transforms import invert_transform, transform_from_vector12
from .quality import prediction_errors
from .tracked import CANDIDATE, MEMORY, TrackedModel, nested_models
from .validity import ValidityMonitor

__all__ = ["LearningSlots", "ModelPool"]

#: Rigid candidates are refitted with every sample only while they are among the ``_PROMISING`` best of their pair
#: and class (by mean error over the test window) or not yet judged; the others every ``_SLOW_REFIT`` samples. A
#: slightly stale fit still tests a candidate fairly (prequentially), at a fraction of the cost.
_PROMISING = 2
_SLOW_REFIT = 8
#: Training-set sizes at which promising rigid candidates are refitted: every sample while few, then ever more
#: sparsely (the body scheme's accuracy comes from the joint fit; candidate fits only rank and validate).
_REFIT_SIZES = frozenset((1, 2, 3, 4, 5, 6, 7, 8, 10, 12, 15, 19, 24, 30))


class LearningSlots(NamedTuple):
    """Arrays over the tracked models that are learning in a batch, in pool order (shape (k,) each).

    Attributes
    ----------
    ids, slots, rows : ndarray of int
        Model ids, batch slots and monitor rows.
    rigid : ndarray of bool
        Whether the slot is in the rigid batch (else the GP batch).
    nested : tuple (sub, sup) of ndarray of int
        Positions of nested candidates for the dominance rule
        (:func:`~body_scheme_core.learning.tracked.nested_models`).
    layer : ndarray of float
        Complexity (number of actions).
    rank : ndarray of int
        Class rank within the layer.
    """

    ids: np.ndarray
    slots: np.ndarray
    rows: np.ndarray
    rigid: np.ndarray
    nested: tuple
    layer: np.ndarray
    rank: np.ndarray


class ModelPool:
    """Every local model a learner tracks, with its batch slot and its validity-monitor row.

    Parameters
    ----------
    config : BodySchemeConfig
    n_actions : int
    gp_batch : GPBatch
        Storage of the GP candidates.
    rigid_batch : RigidBatch
        Storage of the rigid-joint candidates.
    monitor : ValidityMonitor
        Test windows and CUSUMs, one row per tracked model.
    next_id : int
        Id of the next model added.

    Attributes
    ----------
    tracked : dict of int to TrackedModel
        By id, in the order they were added (the order of evaluation and of the state file).
    gp_batch, rigid_batch, monitor, next_id
    """

    def __init__(self, config, n_actions, gp_batch=None, rigid_batch=None, monitor=None, next_id=0):
        self.config = config
        self.n_actions = n_actions
        self.gp_batch = gp_batch if gp_batch is not None else self.new_gp_batch()
        self.rigid_batch = rigid_batch if rigid_batch is not None else self.new_rigid_batch()
        self.monitor = monitor if monitor is not None else ValidityMonitor.from_config(config)
        self.next_id = int(next_id)
        self.tracked = {}
        self._changed()

    def new_gp_batch(self, max_dim=None):
        """An empty GP batch of ``train_window`` capacity with the configuration's hyperparameters."""
        return GPBatch.from_config(self.n_actions, self.config, max_dim)

    def new_rigid_batch(self):
        """An empty rigid-joint batch of ``train_window`` capacity with the configuration's loss and scale option."""
        c = self.config
        return RigidBatch(self.n_actions, c.train_window, c.f_scale, c.fit_joint_scale)

    def _changed(self):
        """Forget what is derived from the set of tracked models, their roles and slots (rebuilt on demand)."""
        self._learning = None

    def snapshot(self):
        """What :meth:`restore` needs to undo a learner's step: the set of tracked models (their entries' own changes
        are journaled, :class:`~body_scheme_core.learning.tracked.Journal`), the batches' slots and the monitor."""
        return (self.next_id, dict(self.tracked), (self.gp_batch, self.gp_batch.snapshot()),
                (self.rigid_batch, self.rigid_batch.snapshot()), self.monitor.copy())

    def restore(self, saved):
        """Undo every change since :meth:`snapshot` returned ``saved`` (but the entries', which the journal undoes)."""
        self.next_id, self.tracked, (self.gp_batch, gp_saved), (self.rigid_batch, rigid_saved), self.monitor = saved
        self.gp_batch.restore(gp_saved)
        self.rigid_batch.restore(rigid_saved)
        self._changed()

    # ------------------------------------------------------------------ membership
    def _add(self, parent, child, actions, kind, role, row, **kwargs):
        entry = TrackedModel(self.next_id, parent, child, actions, kind, role, row, **kwargs)
        self.next_id += 1
        self.tracked[entry.id] = entry
        self._changed()
        return entry

    def add_fitted(self, models, role, origin, last_used, since=0):
        """Track fitted local models (e.g. a given body scheme); returns their TrackedModels."""
        rows = self.monitor.allocate(len(models))
        return [self._add(m.parent, m.child, m.actions, m.kind, role, row, model=m, origin=origin,
                          last_used=last_used, since=since, n_train=getattr(m, "n_samples_", 0))
                for m, row in zip(models, rows, strict=True)]

    def add_learning(self, specs, origin, created=0, target=-1):
        """Start new candidates learning, one per ``(parent, child, actions, kind)`` of ``specs``."""
        rows = self.monitor.allocate(len(specs))
        rigid = [k for k, spec in enumerate(specs) if spec[3] in RIGID_CLASSES]
        gp = [k for k, spec in enumerate(specs) if spec[3] not in RIGID_CLASSES]
        slots = np.empty(len(specs), dtype=np.intp)
        if gp:
            slots[gp] = self.gp_batch.allocate([specs[k][2] for k in gp])
        if rigid:
            slots[rigid] = self.rigid_batch.allocate([(specs[k][3], specs[k][2]) for k in rigid])
        return [self._add(parent, child, acts, kind, CANDIDATE, row, slot=slot, created=created, origin=origin,
                          target=target, since=created)
                for (parent, child, acts, kind), row, slot in zip(specs, rows, slots, strict=True)]

    def _batch(self, entry):
        return self.rigid_batch if entry.kind in RIGID_CLASSES else self.gp_batch

    def remove(self, *entries):
        """Stop tracking ``entries``: free their slots and rows."""
        for batch in (self.gp_batch, self.rigid_batch):
            slots = [e.slot for e in entries if e.slot >= 0 and self._batch(e) is batch]
            if slots:
                batch.release(slots)
        self.monitor.release([e.row for e in entries])
        for e in entries:
            del self.tracked[e.id]
        self._changed()

    def assign(self, entry, role, step):
        """Move ``entry`` into the tree or memory at ``step`` (it is no replacement candidate any more)."""
        entry.role = role
        entry.target = -1
        entry.last_used = step
        self._changed()

    def with_role(self, role):
        """Tracked models of one role, in pool order."""
        return [e for e in self.tracked.values() if e.role == role]

    def memory_of_pair(self, parent, child):
        """Remembered models of the unordered pair ``{parent, child}``, in pool order."""
        pair = {parent, child}
        return [e for e in self.tracked.values() if e.role == MEMORY and {e.parent, e.child} == pair]

    def candidates_of(self, target):
        """Replacement candidates sampled for the tree model with id ``target``."""
        return [e for e in self.tracked.values() if e.role == CANDIDATE and e.target == target]

    @property
    def n_learning(self):
        """Number of models learning in the batches."""
        return sum(1 for e in self.tracked.values() if e.slot >= 0)

    # ------------------------------------------------------------------ models and statistics
    def n_now(self, entry):
        """Current number of training samples of ``entry``."""
        return int(self._batch(entry).size([entry.slot])[0]) if entry.slot >= 0 else entry.n_train

    def model_of(self, entry):
        """The entry's fitted model; for a candidate still learning, a snapshot of its batch slot (not kept)."""
        if entry.slot < 0:
            return entry.model
        return self._batch(entry).to_model(entry.slot, entry.parent, entry.child)

    def window_stats(self, rows, n_now):
        """Test-window statistics under the staleness rule, and validity.

        Parameters
        ----------
        rows : array-like of int, shape (k,)
        n_now : array-like of int, shape (k,)
            Current training-set sizes.

        Returns
        -------
        stats : WindowStats
        valid : ndarray of bool, shape (k,)
            At least ``min_test_samples`` samples and both mean error ratios below 1.
        """
        c = self.config
        stats = self.monitor.stats(rows, n_train=n_now, stale_fraction=c.stale_fraction)
        return stats, self.monitor.valid(stats, c.min_test_samples)

    def dominated(self, rows, n_now, sub, sup, valid=None):
        """Mask over models beaten by a model that nests them by more than ``dominance_margin`` (see config).

        Parameters
        ----------
        rows, n_now : array-like of int, shape (k,)
            Monitor rows and training-set sizes of the models compared.
        sub, sup : ndarray of int
            Nested positions (:func:`~body_scheme_core.learning.tracked.nested_models`).
        valid : array-like of bool, shape (k,), optional
            Only valid models are examined (the others are out of the tree search anyway).

        Returns
        -------
        dominated : ndarray of bool, shape (k,)
        """
        c = self.config
        dominated = np.zeros(len(rows), dtype=bool)
        if valid is not None and sub.size:
            keep = np.asarray(valid)[sub]
            sub, sup = sub[keep], sup[keep]
        if sub.size:
            rows = np.asarray(rows)
            n_now = np.asarray(n_now)
            n, diff = self.monitor.paired_difference(rows[sub], rows[sup], n_now[sub], n_now[sup],
                                                     c.stale_fraction)
            beaten = (n >= c.min_test_samples) & np.any(diff > c.dominance_margin, axis=1)
            dominated[sub[beaten]] = True
        return dominated

    def learning(self):
        """:class:`LearningSlots` of the models learning in the batches; rebuilt only when that set changes."""
        if self._learning is None:
            learning = [e for e in self.tracked.values() if e.slot >= 0]
            self._learning = LearningSlots(
                np.array([e.id for e in learning], dtype=np.int64),
                np.array([e.slot for e in learning], dtype=np.intp),
                np.array([e.row for e in learning], dtype=np.int64),
                np.array([e.kind in RIGID_CLASSES for e in learning], dtype=bool),
                nested_models(learning),
                np.array([e.complexity for e in learning], dtype=float),
                np.array([e.rank for e in learning], dtype=np.int64),
            )
        return self._learning

    def sizes(self, ls=None):
        """Training-set sizes of the learning models (:meth:`learning` order), shape (k,)."""
        ls = self.learning() if ls is None else ls
        n = np.zeros(ls.ids.size, dtype=np.int64)
        if np.any(ls.rigid):
            n[ls.rigid] = self.rigid_batch.size(ls.slots[ls.rigid])
        if np.any(~ls.rigid):
            n[~ls.rigid] = self.gp_batch.size(ls.slots[~ls.rigid])
        return n

    # ------------------------------------------------------------------ prequential evaluation
    def evaluate(self, entries, a, targets, step, cusum):
        """Fitted models (tree and memory) predict their targets; the errors are recorded.

        Parameters
        ----------
        entries : list of TrackedModel
            Frozen models, one per row of ``targets``.
        a : ndarray, shape (m,)
        targets : Targets
        step : int
        cusum : array-like of bool, shape (k,)
            Which rows run their CUSUM (tree models).

        Returns
        -------
        alarm : ndarray of bool, shape (k,)
            CUSUM alarm of each.
        """
        if not entries:
            return np.zeros(0, dtype=bool)
        A = a[None, :]
        preds, vectors = [], []  # GP means are projected onto SE(3) together: one batched SVD, not one per model
        for e in entries:
            if isinstance(e.model, GPModel):
                vectors.append(len(preds))
                preds.append(e.model.predict_components(A)[0])
            else:
                preds.append(e.model.predict(A)[0])
        Zp = np.empty((len(preds), 4, 4))
        if vectors:
            Zp[vectors] = transform_from_vector12(np.asarray([preds[i] for i in vectors]))
        for i, P in enumerate(preds):
            if P.shape == (4, 4):
                Zp[i] = P
        if np.any(targets.flip):
            Zp[targets.flip] = invert_transform(Zp[targets.flip])
        e_t, e_r = prediction_errors(Zp, targets.nearest(Zp))
        return self.monitor.record([e.row for e in entries], e_t, e_r, step, n_train=[e.n_train for e in entries],
                                   cusum=cusum, theta_trans=targets.theta_trans, theta_rot=targets.theta_rot)

    def train(self, ids, a, targets, step):
        """Prequential step of learning candidates: predict, record the error, then learn (until full).

        Parameters
        ----------
        ids : array-like of int
            Learning models, one per row of ``targets``.
        a : ndarray, shape (m,)
        targets : Targets
            Oriented as the candidates predict (``flip`` all False: candidates are created in the direction of their
            targets).
        step : int

        Notes
        -----
        Slots are processed per batch in groups of equal training-set size. GPBatch pads a group's arrays to its
        largest slot, and that padding changes the last bits of the results; equal-size groups are exactly the
        groups :meth:`GPBatch.from_state_dict` replays, so a restored learner continues bit-identically. Rigid
        candidates far from valid are refitted only every few samples (see ``_PROMISING``).
        """
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return
        entries = [self.tracked[int(i)] for i in ids]
        rigid = np.array([e.kind in RIGID_CLASSES for e in entries], dtype=bool)
        slots = np.array([e.slot for e in entries], dtype=np.intp)
        rows = np.array([e.row for e in entries], dtype=np.int64)
        limit = self.config.train_window
        if np.any(~rigid):
            g = np.flatnonzero(~rigid)
            n = self.gp_batch.size(slots[g])
            for size in np.unique(n):
                group = g[n == size]
                Zp = self.gp_batch.predict(slots[group], a)
                Z = targets.Z[group]
                if size > 0:  # an empty GP predicts the identity: its error says nothing about the model
                    Z = targets.nearest(Zp, group)
                    e_t, e_r = prediction_errors(Zp, Z)
                    self.monitor.record(rows[group], e_t, e_r, step, n_train=size, cusum=False,
                                        theta_trans=targets.theta_trans[group], theta_rot=targets.theta_rot[group])
                if size < limit:
                    self.gp_batch.add_samples(slots[group], a, Z)
        if np.any(rigid):
            r = np.flatnonzero(rigid)
            batch = self.rigid_batch
            n = batch.size(slots[r])
            Zp, ready = batch.predict(slots[r], a)
            Z = targets.Z[r]
            if np.any(ready):
                seen = r[ready]
                Z[ready] = targets.nearest(Zp[ready], seen)
                e_t, e_r = prediction_errors(Zp[ready], Z[ready])
                self.monitor.record(rows[seen], e_t, e_r, step, n_train=n[ready], cusum=False,
                                    theta_trans=targets.theta_trans[seen], theta_rot=targets.theta_rot[seen])
            open_ = n < limit
            if np.any(open_):
                learn = r[open_]
                size = n[open_] + 1
                refit = self._promising([entries[k] for k in learn], rows[learn]) & np.isin(size, list(_REFIT_SIZES))
                refit |= (size % _SLOW_REFIT == 0) | (size >= limit)
                batch.add_samples(slots[learn], a, Z[open_], targets.sigma[learn], refit=refit)

    def replay(self, entries, history, targets_at, start=None):
        """Train learning ``entries`` on recorded ``history`` (``(step, a, observations)`` records) at once,
        test-then-train as if live, from step ``start`` on (None: all of it). ``targets_at(a, observations)`` gives
        ``(index, targets)``: which entries the record gives a target, and their
        :class:`~body_scheme_core.learning.targets.Targets`. Returns the number of records that gave at least one
        entry a target. The one history replay of bootstrapping, repair and the challengers."""
        ids = np.array([e.id for e in entries], dtype=np.int64)
        used = 0
        for rec_step, a, obs in history:
            if start is not None and rec_step < start:
                continue
            index, targets = targets_at(a, obs)
            if len(index):
                self.train(ids[index], a, targets, rec_step)
                used += 1
        return used

    def _promising(self, entries, rows):
        """Mask: not yet judged (fewer than ``min_test_samples``), or among the ``_PROMISING`` lowest mean errors of
        its pair, target and class."""
        st = self.monitor.stats(rows)
        unjudged = st.n < self.config.min_test_samples
        score = np.where(unjudged, -np.inf, 0.5 * (st.trans_ratio + st.rot_ratio))
        keys = {}
        group = np.array([keys.setdefault((e.parent, e.child, e.target, e.kind), len(keys)) for e in entries])
        order = np.lexsort((score, group))  # by group, then score
        sorted_group = group[order]
        start = np.searchsorted(sorted_group, sorted_group, side="left")
        rank = np.arange(order.size) - start  # position within its group
        promising = np.zeros(len(entries), dtype=bool)
        promising[order[rank < _PROMISING]] = True
        return promising | unjudged

    # ------------------------------------------------------------------ freezing
    def freeze(self, entry):
        """Freeze a learning entry: fit a model on its slot (rigid candidates re-weighted robustly), free the slot.
        A fitted candidate (a chain) is frozen already."""
        if entry.slot < 0:
            return entry.model
        batch = self._batch(entry)
        model = batch.to_model(entry.slot, entry.parent, entry.child)
        entry.n_train = int(batch.size([entry.slot])[0])
        batch.release([entry.slot])
        entry.slot = -1
        entry.model = model
        self._changed()
        return model

    def keep_only(self, keep):
        """Drop every other model, freeze ``keep`` and move them into fresh, compact storage.

        Test windows are kept, CUSUMs reset.
        """
        for entry in keep:
            if entry.slot >= 0:
                self.freeze(entry)
        old_monitor = self.monitor
        self.gp_batch = self.new_gp_batch(self.gp_batch.max_dim)
        self.rigid_batch = self.new_rigid_batch()
        self.monitor = ValidityMonitor.from_config(self.config)
        self.monitor.set_thresholds(*old_monitor.theta)
        rows = self.monitor.allocate(len(keep))
        self.monitor.copy_rows(old_monitor, [e.row for e in keep], rows)
        self.monitor.reset_cusum(rows)
        for entry, row in zip(keep, rows, strict=True):
            entry.row = int(row)
        self.tracked = {e.id: e for e in keep}
        self._changed()

    # ------------------------------------------------------------------ state
    def tracked_state(self):
        """The tracked models as dicts; learning models are in the batches, so no snapshot is saved."""
        return [e.to_dict(with_model=e.slot < 0) for e in self.tracked.values()]
