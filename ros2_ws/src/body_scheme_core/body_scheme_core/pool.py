"""The local models a learner tracks, and their prequential (test-then-train) evaluation.

A :class:`TrackedModel` is a local model in one of three roles: ``tree`` (an edge of the body scheme), ``memory``
(retired, remembered for reuse) or ``candidate`` (still learning: a bootstrap candidate or a replacement for a
failed tree model). :class:`ModelPool` holds all of them with their storage:

- models still learning live in one :class:`~body_scheme_core.models.gp.GPBatch` (one *slot* each), frozen ones as
  fitted :class:`~body_scheme_core.models.base.LocalModel` objects;
- every tracked model has one *row* in an :class:`~body_scheme_core.quality.ErrorMonitor` (test window and CUSUM).

Each step every tracked model whose pair is observed first predicts the relative observation, its error enters its
test window, and only then may a learning model add the sample to its training set
(:meth:`ModelPool.evaluate_frozen`, :meth:`ModelPool.train_learning`). The decisions built on top (structure
search, change detection, repair) live in :mod:`~body_scheme_core.bootstrap` and
:mod:`~body_scheme_core.adaptation`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .errors import ModelFileError
from .models import GPBatch, GPModel, model_from_dict
from .models.gp import GPHyperparameters
from .quality import ErrorMonitor, prediction_errors
from .transforms import transform_from_vector12

__all__ = [
    "TREE",
    "MEMORY",
    "CANDIDATE",
    "TrackedModel",
    "LearningSlots",
    "ModelPool",
    "nested_pairs",
    "refine_window",
    "new_batch",
    "new_monitor",
    "format_errors",
    "finite_or_none",
]

#: Roles of a tracked model.
TREE, MEMORY, CANDIDATE = "tree", "memory", "candidate"


def format_errors(trans, rot):
    """``"78 mm / 12.3 deg"`` for a pair of errors in m and rad; ``"n/a"`` if one is not finite."""
    if not (math.isfinite(trans) and math.isfinite(rot)):
        return "n/a"
    return f"{1000.0 * trans:.0f} mm / {math.degrees(rot):.1f} deg"


def finite_or_none(value):
    """Event error fields: a float, or None where no error is known (keeps events JSON-safe)."""
    value = float(value)
    return value if math.isfinite(value) else None


def refine_window(config):
    """Training samples after which a tree model is frozen: ``refine_window``, at least ``train_window``."""
    return max(config.refine_window, config.train_window)


def new_batch(config, n_actions, capacity, max_dim):
    """An empty :class:`GPBatch` with the GP hyperparameters of ``config``."""
    return GPBatch(n_actions, capacity, max_dim, **GPHyperparameters.from_config(config).to_dict())


def new_monitor(config):
    """An empty :class:`ErrorMonitor` with the test window, thresholds and CUSUM settings of ``config``."""
    c = config
    return ErrorMonitor(c.test_window, 0, c.theta_trans, c.theta_rot, c.cusum_drift, c.cusum_threshold, c.cusum_clip)


class TrackedModel:
    """A local model the learner tracks: in the tree, in memory, or a candidate still learning in the batch.

    Attributes
    ----------
    id : int
        Unique id, shown in events (``describe``) and used as the tree's edge key.
    parent, child : int
        Part ids; the model predicts ``parent2child``.
    actions : tuple of int
    role : str
        ``"tree"``, ``"memory"`` or ``"candidate"``.
    model : LocalModel or None
        The fitted model; for a tree model still learning, a snapshot of its slot (None until asked for).
    slot : int
        GPBatch slot while the model learns, -1 when frozen.
    row : int
        Row in the error monitor.
    n_train : int
        Training samples (0 for models the learner did not train, e.g. engineered ones).
    created : int
        Step at which a replacement was sampled (0 otherwise).
    origin : str
        ``"bootstrap"``, ``"replacement"`` or ``"initial"``.
    last_used : int
        Last step at which the model entered the tree or memory (-1 never); memory forgets the least recent.
    target : int
        For a replacement candidate, the id of the tree model it is meant to replace; -1 otherwise.
    """

    __slots__ = ("id", "parent", "child", "actions", "role", "model", "slot", "row", "n_train", "created", "origin",
                 "last_used", "target")

    def __init__(self, id, parent, child, actions, role, row, slot=-1, model=None, n_train=0, created=0,
                 origin="", last_used=-1, target=-1):
        self.id = int(id)
        self.parent = int(parent)
        self.child = int(child)
        self.actions = tuple(int(a) for a in actions)
        self.role = role
        self.model = model
        self.slot = int(slot)
        self.row = int(row)
        self.n_train = int(n_train)
        self.created = int(created)
        self.origin = origin
        self.last_used = int(last_used)
        self.target = int(target)

    @property
    def complexity(self):
        """Number of actions the model depends on."""
        return len(self.actions)

    def describe(self):
        """``kind(parent->child | actions)#id``: the id tells apart models with equal structure (in events)."""
        kind = self.model.kind if self.model is not None else "gp"
        acts = ",".join(f"a{a}" for a in self.actions) or "-"
        return f"{kind}({self.parent}->{self.child} | {acts})#{self.id}"

    def to_dict(self, with_model):
        """JSON-serialisable dict; the model itself only ``with_model``."""
        return {"id": self.id, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "role": self.role, "slot": self.slot, "row": self.row, "n_train": self.n_train,
                "created": self.created, "origin": self.origin, "last_used": self.last_used, "target": self.target,
                "model": self.model.to_dict() if (with_model and self.model is not None) else None}

    @classmethod
    def from_dict(cls, data):
        """Rebuild from :meth:`to_dict` output; raises ModelFileError on an unknown role."""
        model = model_from_dict(data["model"]) if data["model"] is not None else None
        if data["role"] not in (TREE, MEMORY, CANDIDATE):
            raise ModelFileError(f"unknown entry role {data['role']!r}")
        return cls(data["id"], data["parent"], data["child"], data["actions"], data["role"], data["row"],
                   data["slot"], model, data["n_train"], data["created"], data["origin"], data["last_used"],
                   data["target"])


class LearningSlots(NamedTuple):
    """Arrays over the tracked models that are learning in the batch, in pool order (shape (k,) each).

    Attributes
    ----------
    ids, slots, rows : ndarray of int
        Model ids, batch slots and monitor rows.
    pair : ndarray of int
        Pair index (:meth:`PartPairs.index`).
    flip : ndarray of bool
        Whether the model predicts the reverse of its pair's canonical direction.
    is_tree : ndarray of bool
        Tree models (only they run a CUSUM).
    nested : tuple (sub, sup) of ndarray of int
        Positions of nested candidates for the dominance rule (:func:`nested_pairs`).
    layer : ndarray of float
        Complexity (number of actions).
    limit : ndarray of int
        Training samples after which the model stops learning: ``refine_window`` for tree models, else
        ``train_window``.
    """

    ids: np.ndarray
    slots: np.ndarray
    rows: np.ndarray
    pair: np.ndarray
    flip: np.ndarray
    is_tree: np.ndarray
    nested: tuple
    layer: np.ndarray
    limit: np.ndarray


def nested_pairs(models):
    """Positions ``(sub, sup)`` of models of the same pair (and target) whose actions strictly contain others'.

    These are the nested pairs the dominance rule compares.

    Parameters
    ----------
    models : list of TrackedModel

    Returns
    -------
    sub, sup : ndarray of int
        ``models[sup[k]].actions`` strictly contains ``models[sub[k]].actions``.
    """
    groups = {}
    for k, e in enumerate(models):
        groups.setdefault((e.parent, e.child, e.target), []).append(k)
    sub, sup = [], []
    for members in groups.values():
        sets = [(k, frozenset(models[k].actions)) for k in members]
        for k, a in sets:
            for q, b in sets:
                if a < b:
                    sub.append(k)
                    sup.append(q)
    return np.array(sub, dtype=np.intp), np.array(sup, dtype=np.intp)


class ModelPool:
    """Every local model a learner tracks, with its GP-batch slot and its error-monitor row.

    Parameters
    ----------
    config : BodySchemeConfig
    n_actions : int
    pairs : PartPairs
    batch : GPBatch
        Storage of the models still learning.
    monitor : ErrorMonitor
        Test windows and CUSUMs, one row per tracked model.
    next_id : int
        Id of the next model added.

    Attributes
    ----------
    tracked : dict of int to TrackedModel
        By id, in the order they were added (the order of evaluation and of the state file).
    batch, monitor, next_id
    """

    def __init__(self, config, n_actions, pairs, batch, monitor, next_id=0):
        self.config = config
        self.n_actions = n_actions
        self.pairs = pairs
        self.batch = batch
        self.monitor = monitor
        self.next_id = int(next_id)
        self.tracked = {}
        self._changed()

    @property
    def refine_window(self):
        """Training samples after which a tree model is frozen (see :func:`refine_window`)."""
        return refine_window(self.config)

    def _changed(self):
        """Forget what is derived from the set of tracked models, their roles and slots (rebuilt on demand)."""
        self._learning = None
        self._frozen = None

    # ------------------------------------------------------------------ membership
    def _add(self, parent, child, actions, role, row, **kwargs):
        entry = TrackedModel(self.next_id, parent, child, actions, role, row, **kwargs)
        self.next_id += 1
        self.tracked[entry.id] = entry
        self._changed()
        return entry

    def add_fitted(self, models, role, origin, last_used):
        """Track fitted local models (e.g. a given body scheme); returns their TrackedModels."""
        rows = self.monitor.allocate(len(models))
        return [self._add(m.parent, m.child, m.actions, role, row, model=m, origin=origin, last_used=last_used)
                for m, row in zip(models, rows, strict=True)]

    def add_learning(self, specs, origin, created=0, target=-1):
        """Start new candidates learning in the batch, one per ``(parent, child, actions)`` of ``specs``."""
        rows = self.monitor.allocate(len(specs))
        slots = self.batch.allocate([acts for _, _, acts in specs])
        return [self._add(parent, child, acts, CANDIDATE, row, slot=slot, created=created, origin=origin,
                          target=target)
                for (parent, child, acts), row, slot in zip(specs, rows, slots, strict=True)]

    def remove(self, entry):
        """Stop tracking ``entry``: free its slot and row."""
        if entry.slot >= 0:
            self.batch.release([entry.slot])
        self.monitor.release([entry.row])
        del self.tracked[entry.id]
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
        """Number of models learning in the batch."""
        return sum(1 for e in self.tracked.values() if e.slot >= 0)

    # ------------------------------------------------------------------ models and statistics
    def n_now(self, entry):
        """Current number of training samples of ``entry``."""
        return int(self.batch.size([entry.slot])[0]) if entry.slot >= 0 else entry.n_train

    def model_of(self, entry, cache=True):
        """The entry's fitted model; for a model still learning, a snapshot of its current training data.

        With ``cache`` the snapshot is kept in ``entry.model`` until the entry learns again (see
        :meth:`refresh_refining`); while bootstrapping nothing refreshes candidates, so their snapshots are not kept.
        """
        if entry.slot < 0 or (cache and entry.model is not None):
            return entry.model
        model = self.batch.to_model(entry.slot, entry.parent, entry.child)
        if cache:
            entry.model = model
        return model

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
        """Mask over models beaten by a model with more actions by more than ``dominance_margin`` (see config).

        Parameters
        ----------
        rows, n_now : array-like of int, shape (k,)
            Monitor rows and training-set sizes of the models compared.
        sub, sup : ndarray of int
            Nested positions (:func:`nested_pairs`).
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
        """:class:`LearningSlots` of the models learning in the batch; rebuilt only when that set changes."""
        if self._learning is None:
            learning = [e for e in self.tracked.values() if e.slot >= 0]
            self._learning = LearningSlots(
                np.array([e.id for e in learning], dtype=np.int64),
                np.array([e.slot for e in learning], dtype=np.intp),
                np.array([e.row for e in learning], dtype=np.int64),
                np.array([self.pairs.index(e.parent, e.child) for e in learning], dtype=np.intp),
                np.array([self.pairs.flip(e.parent, e.child) for e in learning], dtype=bool),
                np.array([e.role == TREE for e in learning], dtype=bool),
                nested_pairs(learning),
                np.array([e.complexity for e in learning], dtype=float),
                np.array([self.refine_window if e.role == TREE else self.config.train_window for e in learning],
                         dtype=np.int64),
            )
        return self._learning

    def frozen(self):
        """Frozen tree and memory models as ``(entry, pair index, flip)``, in pool order (cached like ``learning``)."""
        if self._frozen is None:
            self._frozen = [(e, self.pairs.index(e.parent, e.child), self.pairs.flip(e.parent, e.child))
                            for e in self.tracked.values() if e.slot < 0 and e.role in (TREE, MEMORY)]
        return self._frozen

    # ------------------------------------------------------------------ prequential evaluation
    def evaluate_frozen(self, a, relative, step):
        """Frozen models (tree and memory) whose pair is observed predict it; their errors are recorded.

        Only tree models run their CUSUM.

        Parameters
        ----------
        a : ndarray, shape (m,)
        relative : RelativeObservations
        step : int

        Returns
        -------
        ids : list of int
            Models that were evaluated.
        alarm : ndarray of bool
            CUSUM alarm of each.
        """
        A = a[None, :]
        ids, rows, n_train, use_cusum, pairs, flips = [], [], [], [], [], []
        preds, vectors = [], []  # GP means are projected onto SE(3) together: one batched SVD, not one per model
        for e, k, flip in self.frozen():
            if relative.row[k] < 0:
                continue
            if isinstance(e.model, GPModel):
                vectors.append(len(preds))
                preds.append(e.model.predict_components(A)[0])
            else:
                preds.append(e.model.predict(A)[0])
            pairs.append(k)
            flips.append(flip)
            ids.append(e.id)
            rows.append(e.row)
            n_train.append(e.n_train)
            use_cusum.append(e.role == TREE)
        if not preds:
            return ids, np.zeros(0, dtype=bool)
        Zp = np.empty((len(preds), 4, 4))
        if vectors:
            Zp[vectors] = transform_from_vector12(np.asarray([preds[i] for i in vectors]))
        for i, P in enumerate(preds):
            if P.shape == (4, 4):
                Zp[i] = P
        Z = relative.of_pairs(np.array(pairs, dtype=np.intp), np.array(flips, dtype=bool))
        e_t, e_r = prediction_errors(Zp, Z)
        alarm = self.monitor.record(rows, e_t, e_r, step, n_train=n_train, cusum=use_cusum,
                                    theta_trans=relative.theta_trans[relative.row[pairs]])
        return ids, alarm

    def train_learning(self, a, relative, step):
        """Prequential step of every learning model whose pair is observed: predict, record the error, train.

        Returns
        -------
        ids : ndarray of int
            Models that were evaluated.
        alarm : ndarray of bool
            CUSUM alarms (only tree models run a CUSUM).
        """
        ls = self.learning()
        sel = np.flatnonzero(relative.row[ls.pair] >= 0)
        if sel.size == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
        Z = relative.of_pairs(ls.pair[sel], ls.flip[sel])
        alarm = self.prequential(ls.slots[sel], ls.rows[sel], a, Z, step,
                                 relative.theta_trans[relative.row[ls.pair[sel]]], ls.is_tree[sel], ls.limit[sel])
        return ls.ids[sel], alarm

    def prequential(self, slots, rows, a, Z, step, theta_trans, cusum, limit):
        """Test-then-train for batch slots: predict ``Z``, record the errors, then add the sample where not full.

        Slots are processed in groups of equal training-set size. GPBatch pads a group's arrays to its largest
        slot, and that padding changes the last bits of the results; equal-size groups are exactly the groups
        :meth:`GPBatch.from_state_dict` replays, so a restored learner continues bit-identically.

        Parameters
        ----------
        slots, rows : ndarray of int, shape (k,)
        a : ndarray, shape (m,)
        Z : ndarray, shape (k, 4, 4)
            Observed ``parent2child`` per slot.
        step : int
        theta_trans : ndarray, shape (k,)
            Translational threshold of each sample.
        cusum : ndarray of bool, shape (k,)
            Which rows run their CUSUM.
        limit : ndarray of int, shape (k,)
            Training-set size at which each slot stops learning.

        Returns
        -------
        alarm : ndarray of bool, shape (k,)
        """
        n = self.batch.size(slots)
        alarm = np.zeros(slots.size, dtype=bool)
        for size in np.unique(n):
            group = np.flatnonzero(n == size)
            Zp = self.batch.predict(slots[group], a)
            if size > 0:  # an empty GP predicts the identity: its error says nothing about the model
                e_t, e_r = prediction_errors(Zp, Z[group])
                alarm[group] = self.monitor.record(rows[group], e_t, e_r, step, n_train=size, cusum=cusum[group],
                                                   theta_trans=theta_trans[group])
            open_ = group[size < limit[group]]
            if open_.size:
                self.batch.add_samples(slots[open_], a, Z[open_])
        return alarm

    # ------------------------------------------------------------------ freezing
    def refresh_refining(self, ids):
        """Tree models still learning (``ids``): their snapshot is dropped after each new sample (rebuilt only when
        the body scheme is asked for); at ``refine_window`` samples they are frozen and leave the batch.

        Returns
        -------
        changed : bool
            Whether any of these models changed.
        """
        changed = False
        for i in ids:
            e = self.tracked[i]
            if e.slot < 0:
                continue
            n = int(self.batch.size([e.slot])[0])
            if n != e.n_train:
                e.model = None
                e.n_train = n
                changed = True
            if n >= self.refine_window:
                self.materialize(e)
                changed = True
        return changed

    def materialize(self, entry, before=None):
        """Turn a learning entry into a fitted model and free its slot.

        With ``before`` (a change-point step), only the samples the model had learned before that step are kept,
        so a model that kept refining after a change goes to memory uncontaminated.
        """
        model = self.batch.to_model(entry.slot, entry.parent, entry.child)
        n = model.n_samples
        if before is not None and n:
            steps = self.monitor.steps[entry.row]
            after = (steps >= before)
            if np.any(after):
                # Predictions are made before training: the training size at the first prediction after the
                # change point counts the samples learned before it.
                keep = int(self.monitor.n_train[entry.row][after].min())
                if 0 < keep < n:
                    data = model.to_dict()
                    data["X"], data["Y"] = data["X"][:keep], data["Y"][:keep]
                    model = GPModel.from_dict(data)
                    n = keep
        self.batch.release([entry.slot])
        entry.slot = -1
        entry.model = model
        entry.n_train = n
        self._changed()

    def resume_refining(self, entry):
        """Put a frozen GP with fewer than ``refine_window`` samples back into the batch to keep learning.

        For a model that returns to the tree from memory: it was retired while still refining, so it holds fewer
        samples than a tree model should (a replacement retired soon after its installation may hold only a handful);
        like every tree model it refines up to ``refine_window``. Other models are left alone.

        Returns
        -------
        resumed : bool
        """
        model = entry.model
        if (entry.slot >= 0 or not isinstance(model, GPModel) or model.n_samples >= self.refine_window
                or self.batch.capacity < self.refine_window or len(entry.actions) > self.batch.max_dim):
            return False
        entry.slot = int(self.batch.allocate([entry.actions])[0])
        self._replay_training_data(entry.slot, model)
        entry.n_train = model.n_samples
        entry.model = None  # a snapshot of the batch slot on demand, like every refining tree model
        self._changed()
        return True

    def keep_only(self, keep):
        """Drop every other model and move ``keep`` into a fresh, compact batch and monitor.

        The new batch can hold ``refine_window`` samples: kept models below that keep learning (their samples are
        replayed in order), the others are frozen. Test windows are kept, CUSUMs reset.

        Returns
        -------
        refining : list of TrackedModel
            The kept models that keep learning.
        """
        old_batch, old_monitor = self.batch, self.monitor
        self.batch = new_batch(self.config, self.n_actions, self.refine_window, old_batch.max_dim)
        refining = []
        for entry in keep:
            model = old_batch.to_model(entry.slot, entry.parent, entry.child)
            entry.n_train = int(old_batch.size([entry.slot])[0])
            entry.model = model
            entry.slot = -1
            if entry.n_train < self.refine_window:
                entry.slot = int(self.batch.allocate([entry.actions])[0])
                self._replay_training_data(entry.slot, model)
                refining.append(entry)
        self.monitor = new_monitor(self.config)
        rows = self.monitor.allocate(len(keep))
        self.monitor.copy_rows(old_monitor, [e.row for e in keep], rows)
        self.monitor.reset_cusum(rows)
        for entry, row in zip(keep, rows, strict=True):
            entry.row = int(row)
        self.tracked = {e.id: e for e in keep}
        self._changed()
        return refining

    def _replay_training_data(self, slot, model):
        """Add a fitted GP model's training samples, in order, to an empty batch slot."""
        X = model.X_train_
        Z = transform_from_vector12(model.Y_train_)
        a = np.zeros(self.n_actions)
        cols = list(model.actions)
        for k in range(X.shape[0]):
            a[cols] = X[k]
            self.batch.add_samples([slot], a, Z[k:k + 1])

    # ------------------------------------------------------------------ state
    def tracked_state(self):
        """The tracked models as dicts; learning models are rebuilt from the batch, so their snapshot is not saved."""
        return [e.to_dict(with_model=e.slot < 0) for e in self.tracked.values()]

    @classmethod
    def from_state(cls, config, n_actions, pairs, tracked, next_id, monitor, batch):
        """Rebuild from :meth:`tracked_state`, ``next_id``, ``ErrorMonitor.to_dict`` and ``GPBatch.state_dict``.

        Raises
        ------
        ModelFileError
            If the monitor or batch do not fit the configuration, or a model refers to an unknown part, a free
            monitor row or GP slot, or is frozen without a stored model.
        """
        monitor = ErrorMonitor.from_dict(monitor)
        if monitor.window != config.test_window:
            raise ModelFileError(f"monitor window {monitor.window} != test_window {config.test_window}")
        batch = GPBatch.from_state_dict(batch)
        if batch.n_actions != n_actions:
            raise ModelFileError(f"GP batch has {batch.n_actions} actions, learner {n_actions}")
        pool = cls(config, n_actions, pairs, batch, monitor, int(next_id))
        allocated = set(batch.allocated_slots.tolist())
        for data in tracked:
            entry = TrackedModel.from_dict(data)
            for part in (entry.parent, entry.child):
                if part not in pairs.part_index:
                    raise ModelFileError(f"model {entry.describe()} refers to unknown part {part}")
            if not (0 <= entry.row < monitor.capacity and monitor.in_use[entry.row]):
                raise ModelFileError(f"model {entry.describe()} has no monitor row {entry.row}")
            if entry.slot >= 0:
                if entry.slot not in allocated:
                    raise ModelFileError(f"model {entry.describe()} refers to free GP slot {entry.slot}")
            elif entry.model is None:
                raise ModelFileError(f"frozen model entry {entry.id} has no stored model")
            pool.tracked[entry.id] = entry
        return pool
