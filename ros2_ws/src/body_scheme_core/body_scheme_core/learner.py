"""The online lifelong body-scheme learner: bootstrapping, change detection, memory and repair (paper III-C, III-E).

One :meth:`BodySchemeLearner.update` call per time step, with the commanded action vector and the marker poses
observed after it. The learner goes through three phases:

``bootstrapping``
    Without a given body scheme, a candidate local model is instantiated for every pair of parts and every action
    subset of at most ``max_complexity`` actions (the fully connected network of Fig. 4). All of them are GPs in one
    :class:`~body_scheme_core.models.gp.GPBatch`. Each is a *temporal* local model: it learns from the first
    ``train_window`` observations of its pair and is then frozen. Evaluation is prequential (test-then-train): a
    candidate predicts every new observation before that observation may join its training set, so validity is
    never judged on training data. After every step the minimum spanning tree over the valid candidates is
    searched layer by layer (:func:`~body_scheme_core.structure.select_spanning_tree`), over the valid candidates
    that no candidate with more actions clearly beats (dominance rule). Bootstrapping ends when a valid tree
    exists, its models are frozen and every candidate is frozen (or the tree has been stable for
    ``bootstrap_patience`` steps): all other candidates are dropped; the tree's models keep learning up to
    ``refine_window`` samples and then become plain :class:`GPModel` objects.
``steady``
    Every step, each model of the tree and each remembered model whose two parts are observed records its
    prequential error. A tree model is in *mismatch* when its test window is invalid, a one-sided CUSUM on its
    normalised per-sample error crosses ``cusum_threshold`` (per edge, so the failure is localised), or a
    remembered model of its pair clearly fits the samples since the CUSUM left zero better.
``adapting``
    At least one tree edge is in mismatch. First the memory is asked: a remembered model (of that pair, or of any
    pair that reconnects the two halves of the tree) whose mean errors since the estimated change point are valid
    is put back (``model_reinstated``). Otherwise replacement models are sampled for the pair, ordered by relative
    complexity to the failed model (Eq. 11), and trained *only* on data since the change point: the recent raw
    history is replayed to them prequentially at once, so they need not wait for new data. The cheapest valid one
    by ``C(M2|M1) + e`` replaces the failed model (``model_replaced``), which goes to memory (``model_retired``).

Every decision is returned as an :class:`~body_scheme_core.events.Event` whose reason string carries the numbers.
``docs/core/learning-and-adaptation.md`` describes every rule and default and how they differ from the paper.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Mapping

import numpy as np

from .config import BodySchemeConfig
from .errors import InvalidInputError, ModelFileError, NotFittedError
from .events import Event
from .models import GPBatch, GPModel, model_from_dict
from .models.gp import GPHyperparameters
from .quality import ErrorMonitor, model_cost, prediction_errors, relative_complexity, translation_threshold
from .scheme import BodyScheme
from .structure import enumerate_candidates, replacement_action_sets, select_spanning_tree
from .transforms import invert_transform, project_to_rotation, transform_from_vector12

__all__ = ["BodySchemeLearner", "PHASES", "STATE_VERSION"]

#: Phases reported by :attr:`BodySchemeLearner.phase`.
PHASES = ("bootstrapping", "steady", "adapting")
#: Version of the dict layout of :meth:`BodySchemeLearner.to_state`.
STATE_VERSION = 1
#: Largest deviation of an observed rotation block from orthonormality (and of the last row from [0 0 0 1]).
OBSERVATION_TOLERANCE = 1e-4

_TREE, _MEMORY, _CANDIDATE = "tree", "memory", "candidate"


def _fmt_err(trans, rot):
    """``"78 mm / 12.3 deg"`` for a pair of errors in m and rad."""
    if not (math.isfinite(trans) and math.isfinite(rot)):
        return "n/a"
    return f"{1000.0 * trans:.0f} mm / {math.degrees(rot):.1f} deg"


class _Entry:
    """A local model the learner tracks: in the tree, in memory, or a candidate still learning in the batch.

    ``model`` is the materialised :class:`LocalModel` (for a learning tree model: a snapshot of its slot), ``slot``
    its GPBatch slot while it learns (-1 when frozen), ``row`` its row in the error monitor, ``n_train`` its number
    of training samples (0 for models the learner did not train, e.g. engineered ones), ``target`` the id of the
    tree model a replacement candidate is meant to replace.
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
        return len(self.actions)

    def describe(self):
        """``kind(parent->child | actions)#id``: the id tells apart models with equal structure (in events)."""
        kind = self.model.kind if self.model is not None else "gp"
        acts = ",".join(f"a{a}" for a in self.actions) or "-"
        return f"{kind}({self.parent}->{self.child} | {acts})#{self.id}"

    def to_dict(self, with_model):
        return {"id": self.id, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "role": self.role, "slot": self.slot, "row": self.row, "n_train": self.n_train,
                "created": self.created, "origin": self.origin, "last_used": self.last_used, "target": self.target,
                "model": self.model.to_dict() if (with_model and self.model is not None) else None}

    @classmethod
    def from_dict(cls, data):
        model = model_from_dict(data["model"]) if data["model"] is not None else None
        if data["role"] not in (_TREE, _MEMORY, _CANDIDATE):
            raise ModelFileError(f"unknown entry role {data['role']!r}")
        return cls(data["id"], data["parent"], data["child"], data["actions"], data["role"], data["row"],
                   data["slot"], model, data["n_train"], data["created"], data["origin"], data["last_used"],
                   data["target"])


class BodySchemeLearner:
    """Learns a body scheme from scratch (or starts from a given one) and keeps it valid for a lifetime.

    Parameters
    ----------
    part_ids : iterable of int
        Body part (marker) ids, any numbering.
    n_actions : int
        Length m of the action vectors.
    config : BodySchemeConfig, optional
        Hyperparameters; defaults to ``BodySchemeConfig()``.
    initial_models : list of LocalModel, optional
        A spanning tree of fitted models to start from (e.g. ``engineered_models(tree)``, as in the paper's Table I
        experiments): the learner starts in the ``steady`` phase. Without it, the learner bootstraps from scratch.
    action_lower, action_upper : array-like, shape (m,), optional
        Action (joint) limits, kept for callers (IK bounds, babbling); the learner does not clip actions.

    Attributes
    ----------
    part_ids : tuple of int
    root : int
        The root part: ``config.root`` or the lowest id.
    n_actions : int
    config : BodySchemeConfig
    step : int
        Number of :meth:`update` calls so far.
    rejected : collections.Counter
        Rejected observations by reason: ``unknown_id``, ``bad_shape``, ``not_finite``, ``not_rigid``.
    """

    def __init__(self, part_ids, n_actions, config=None, initial_models=None, action_lower=None, action_upper=None):
        config = BodySchemeConfig() if config is None else config
        if not isinstance(config, BodySchemeConfig):
            raise InvalidInputError(f"config must be a BodySchemeConfig, got {type(config).__name__}")
        try:
            parts = tuple(int(p) for p in part_ids)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"part_ids must be integer ids, got {part_ids!r}") from exc
        if not parts or len(set(parts)) != len(parts):
            raise InvalidInputError(f"part_ids must be non-empty and unique, got {parts}")
        if isinstance(n_actions, bool) or not isinstance(n_actions, (int, np.integer)) or n_actions < 0:
            raise InvalidInputError(f"n_actions must be an integer >= 0, got {n_actions!r}")
        root = min(parts) if config.root is None else int(config.root)
        if root not in parts:
            raise InvalidInputError(f"config.root {root} is not one of the parts {parts}")
        self.config = config
        self.part_ids = parts
        self.root = root
        self.n_actions = int(n_actions)
        self.action_lower = self._check_bounds(action_lower, "action_lower")
        self.action_upper = self._check_bounds(action_upper, "action_upper")
        if self.action_lower is not None and self.action_upper is not None and np.any(
                self.action_lower > self.action_upper):
            raise InvalidInputError(f"action_lower {self.action_lower.tolist()} exceeds action_upper "
                                    f"{self.action_upper.tolist()}")
        self.step = 0
        self.last_stamp = None
        self.rejected = Counter()
        self._setup_static()
        self._next_id = 0
        self._entries = {}
        self._mismatch = {}
        self._history = deque(maxlen=config.history_length)
        self._root_obs = deque(maxlen=config.root_window)
        self._tree = None
        self._tree_since = 0
        self._found = initial_models is not None
        self._root_pose = None
        self._invalidate()
        max_dim = config.max_complexity
        if initial_models is not None:
            models = list(initial_models)
            BodyScheme(parts, root, models)  # validates: fitted models forming a spanning tree over the parts
            for model in models:
                if model.actions and max(model.actions) >= self.n_actions:
                    raise InvalidInputError(f"{model.describe()} uses action {max(model.actions)} but n_actions is "
                                            f"{self.n_actions}")
            max_dim = max([max_dim] + [model.complexity for model in models])
        self._monitor = self._new_monitor()
        capacity = config.train_window if initial_models is None else self._refine_window
        self._batch = self._new_batch(capacity, max_dim)
        if initial_models is not None:
            self._bootstrapping = False
            rows = self._monitor.allocate(len(models))
            self._tree = []
            for model, row in zip(models, rows, strict=True):
                entry = self._add_entry(model.parent, model.child, model.actions, _TREE, row, model=model,
                                        origin="initial")
                entry.last_used = 0
                self._tree.append(entry.id)
        else:
            self._bootstrapping = True
            candidates = enumerate_candidates(parts, self.n_actions, config.max_complexity)
            rows = self._monitor.allocate(len(candidates))
            slots = self._batch.allocate([acts for _, _, acts in candidates])
            for (i, j, acts), row, slot in zip(candidates, rows, slots, strict=True):
                self._add_entry(i, j, acts, _CANDIDATE, row, slot=slot, origin="bootstrap")
            if len(parts) == 1:
                self._tree = []

    # ------------------------------------------------------------------ setup helpers
    def _check_bounds(self, bounds, name):
        if bounds is None:
            return None
        bounds = np.array(bounds, dtype=float)
        if bounds.shape != (self.n_actions,):
            raise InvalidInputError(f"{name} must have shape ({self.n_actions},), got {bounds.shape}")
        if np.any(np.isnan(bounds)):
            raise InvalidInputError(f"{name} contains NaN: {bounds.tolist()}")
        return bounds

    def _setup_static(self):
        """Lookup tables that depend only on the parts."""
        parts = self.part_ids
        self._part_index = {p: k for k, p in enumerate(parts)}
        pairs = [(i, j) for i in range(len(parts)) for j in range(i + 1, len(parts))]
        self._pair_i = np.array([i for i, _ in pairs], dtype=np.intp)
        self._pair_j = np.array([j for _, j in pairs], dtype=np.intp)
        self._pair_index = {}
        for k, (i, j) in enumerate(pairs):
            self._pair_index[(parts[i], parts[j])] = k
            self._pair_index[(parts[j], parts[i])] = k

    @property
    def _refine_window(self):
        return max(self.config.refine_window, self.config.train_window)

    def _new_batch(self, capacity, max_dim):
        hp = GPHyperparameters.from_config(self.config)
        return GPBatch(self.n_actions, capacity, max_dim, **hp.to_dict())

    def _new_monitor(self):
        c = self.config
        return ErrorMonitor(c.test_window, 0, c.theta_trans, c.theta_rot, c.cusum_drift, c.cusum_threshold,
                            c.cusum_clip)

    def _add_entry(self, parent, child, actions, role, row, **kwargs):
        entry = _Entry(self._next_id, parent, child, actions, role, row, **kwargs)
        self._next_id += 1
        self._entries[entry.id] = entry
        self._learning = None
        return entry

    def _remove_entry(self, entry):
        if entry.slot >= 0:
            self._batch.release([entry.slot])
        self._monitor.release([entry.row])
        del self._entries[entry.id]
        self._learning = None

    def _invalidate(self):
        """Forget cached derived objects (the body scheme, the learning-entry arrays)."""
        self._scheme = None
        self._learning = None

    def _flip(self, entry):
        """Whether ``entry`` predicts the reverse of its pair's canonical (part-order) direction."""
        return self._part_index[entry.parent] > self._part_index[entry.child]

    # ------------------------------------------------------------------ queries
    @property
    def phase(self):
        """``"bootstrapping"``, ``"steady"`` or ``"adapting"`` (a tree edge is in mismatch)."""
        if self._bootstrapping:
            return "bootstrapping"
        return "adapting" if self._mismatch else "steady"

    @property
    def n_candidates(self):
        """Number of models currently learning in the GP batch (bootstrap candidates or replacements)."""
        return sum(1 for e in self._entries.values() if e.slot >= 0)

    @property
    def memory(self):
        """Remembered (retired) local models, oldest first."""
        return [self._entry_model(e) for e in self._entries.values() if e.role == _MEMORY]

    @property
    def body_scheme(self):
        """The current body scheme (:class:`BodyScheme`), or ``None`` while no valid spanning tree exists."""
        if self._tree is None:
            return None
        if self._scheme is None:
            models = [self._entry_model(self._entries[i]) for i in self._tree]
            self._scheme = BodyScheme(self.part_ids, self.root, models)
        return self._scheme

    def _entry_model(self, entry):
        """The entry's fitted model; for a model still learning, a snapshot of its current training data."""
        if self._bootstrapping and entry.slot >= 0:
            return self._batch.to_model(entry.slot, entry.parent, entry.child)
        if entry.model is None:
            entry.model = self._batch.to_model(entry.slot, entry.parent, entry.child)
        return entry.model

    @property
    def root_pose(self):
        """Estimated ``world2root`` (4, 4): robust mean of the last ``root_window`` root observations.

        Translation: coordinate-wise median. Rotation: the element-wise median of the rotation matrices projected
        onto SO(3). Both ignore up to half of the samples being outliers. Identity while the root was never seen.
        """
        if self._root_pose is None:
            if not self._root_obs:
                self._root_pose = np.eye(4)
            else:
                Y = np.asarray(self._root_obs)
                pose = np.eye(4)
                pose[:3, :3] = project_to_rotation(np.median(Y[:, :3, :3], axis=0))
                pose[:3, 3] = np.median(Y[:, :3, 3], axis=0)
                self._root_pose = pose
        return self._root_pose

    def predict(self, a, return_std=False):
        """Predicted ``world2part`` of every part for one action vector (Eq. 8 and :attr:`root_pose`).

        Parameters
        ----------
        a : array-like, shape (m,)
        return_std : bool
            Also return the propagated isotropic standard deviation of every part (see :meth:`BodyScheme.predict`).

        Returns
        -------
        world2part : dict of int to ndarray, shape (4, 4)
        std : dict of int to ndarray, shape (2,)
            Only with ``return_std``: translational (m) and rotational (rad) std per part.

        Raises
        ------
        NotFittedError
            While no valid body scheme exists.
        """
        scheme = self.body_scheme
        if scheme is None:
            raise NotFittedError(f"no valid body scheme yet (phase {self.phase}, step {self.step})")
        a = self._check_actions(a)
        world2root = self.root_pose
        if return_std:
            root2part, std = scheme.predict(a, return_std=True)
        else:
            root2part, std = scheme.predict(a), None
        world2part = {part: world2root @ T for part, T in root2part.items()}
        return (world2part, std) if return_std else world2part

    def edge_status(self):
        """Status of every tree edge, in breadth-first order from the root.

        Returns
        -------
        status : list of dict
            Keys ``parent``, ``child`` (tree orientation, parent nearer the root), ``model`` (description with the
            learner's model id, as in events), ``model_id``, ``kind``, ``actions``, ``n_test``, ``trans_error``,
            ``rot_error`` (mean test-window errors, m and rad),
            ``theta_trans``, ``theta_rot``, ``valid``, ``in_mismatch``, ``cusum`` ([trans, rot]).
        """
        scheme = self.body_scheme
        if scheme is None:
            return []
        by_pair = {frozenset((self._entries[i].parent, self._entries[i].child)): self._entries[i] for i in self._tree}
        out = []
        c = self.config
        for parent, child, model, _ in scheme.edges:
            entry = by_pair[frozenset((parent, child))]
            n_now = self._batch.size([entry.slot])[0] if entry.slot >= 0 else entry.n_train
            st = self._monitor.stats([entry.row], n_train=[n_now], stale_fraction=c.stale_fraction)
            valid = bool(self._monitor.valid(st, c.min_test_samples)[0])
            theta_t = float(st.theta_trans[0]) if st.n[0] else c.theta_trans
            out.append({"parent": parent, "child": child, "model": entry.describe(), "model_id": entry.id,
                        "kind": model.kind,
                        "actions": list(model.actions), "n_test": int(st.n[0]), "trans_error": float(st.trans_error[0]),
                        "rot_error": float(st.rot_error[0]), "theta_trans": theta_t, "theta_rot": c.theta_rot,
                        "valid": valid, "in_mismatch": entry.id in self._mismatch,
                        "cusum": self._monitor.cusum[entry.row].tolist()})
        return out

    # ------------------------------------------------------------------ input validation
    def _check_actions(self, actions):
        a = np.asarray(actions, dtype=float)
        if a.shape != (self.n_actions,):
            raise InvalidInputError(f"actions must have shape ({self.n_actions},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InvalidInputError(f"actions contain NaN or inf: {a.tolist()}")
        return a

    def _filter_observations(self, observations, step, events):
        """Valid observations ``{part: world2part}``; rejected ones are counted and reported."""
        valid, rejected = {}, []
        for key, value in observations.items():
            part = key
            if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or int(key) not in self._part_index:
                what = f"id {key!r} is not an integer" if not isinstance(key, (int, np.integer)) else f"id {key}"
                rejected.append((key, "unknown_id", f"{what} is not one of the parts {self.part_ids}"))
                continue
            part = int(key)
            try:
                Y = np.array(value, dtype=float)  # a copy: the history must not change with the caller's arrays
            except (TypeError, ValueError):
                Y = None
            if Y is None or Y.shape != (4, 4):
                shape = None if Y is None else Y.shape
                rejected.append((part, "bad_shape", f"pose of part {part} must have shape (4, 4), got {shape}"))
            elif not np.all(np.isfinite(Y)):
                rejected.append((part, "not_finite", f"pose of part {part} contains NaN or inf"))
            else:
                valid[part] = Y
        if valid:
            # Rigidity of all remaining poses in one vectorised check.
            Y = np.stack(list(valid.values()))
            R = Y[:, :3, :3]
            dev = np.maximum(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2)),
                             np.abs(Y[:, 3] - (0.0, 0.0, 0.0, 1.0)).max(axis=1))
            bad = (dev > OBSERVATION_TOLERANCE) | (np.linalg.det(R) < 0.0)
            for part, is_bad, d in zip(list(valid), bad, dev, strict=True):
                if is_bad:
                    del valid[part]
                    rejected.append((part, "not_rigid", f"pose of part {part} is not a rigid transform (deviation "
                                                        f"{d:.3g} > {OBSERVATION_TOLERANCE:g} or det < 0)"))
        for part, reason, detail in rejected:
            self.rejected[reason] += 1
            events.append(Event(step, "input_rejected", f"observation rejected ({reason}): {detail}",
                                child=part if isinstance(part, (int, np.integer)) and not isinstance(part, bool)
                                else None))
        return valid

    # ------------------------------------------------------------------ the time step
    def update(self, actions, observations, stamp=None):
        """Process one time step: the action vector and the marker poses observed after executing it.

        Parameters
        ----------
        actions : array-like, shape (m,)
            The commanded action vector.
        observations : mapping of int to array-like, shape (4, 4)
            ``world2part`` per observed part; missing parts are normal. Invalid entries are rejected one by one.
        stamp : float, optional
            Time stamp, kept as :attr:`last_stamp`.

        Returns
        -------
        events : list of Event

        Raises
        ------
        InvalidInputError
            If ``actions`` has the wrong shape or is not finite, or ``observations`` is not a mapping; the learner
            is then unchanged.
        """
        a = self._check_actions(actions).copy()
        if not isinstance(observations, Mapping):
            raise InvalidInputError(f"observations must be a mapping part id -> (4, 4) pose, got "
                                    f"{type(observations).__name__}")
        if stamp is not None:
            try:
                stamp = float(stamp)
            except (TypeError, ValueError) as exc:
                raise InvalidInputError(f"stamp must be a number or None, got {stamp!r}") from exc
            if not math.isfinite(stamp):
                raise InvalidInputError(f"stamp must be finite, got {stamp!r}")
        step = self.step
        events = []
        obs = self._filter_observations(observations, step, events)
        self.last_stamp = stamp
        if self.root in obs:
            self._root_obs.append(obs[self.root])
            self._root_pose = None
        self._history.append((step, a, obs))
        rel = self._relative_observations(obs)
        if self._bootstrapping:
            self._bootstrap_step(a, rel, step, events)
        else:
            self._steady_step(a, rel, step, events)
        self.step = step + 1
        return events

    def _relative_observations(self, obs):
        """``Z = Y_i^-1 Y_j`` for every pair with both parts observed (canonical direction).

        Returns
        -------
        Zobs : ndarray, shape (k, 4, 4)
        zmap : ndarray of int, shape (n_pairs,)
            Row of each pair in ``Zobs``, -1 where the pair is not observed.
        theta : ndarray, shape (k,)
            Translational validity threshold of each observed pair (:func:`translation_threshold`).
        """
        n_parts = len(self.part_ids)
        seen = np.zeros(n_parts, dtype=bool)
        Y = np.empty((n_parts, 4, 4))
        for part, pose in obs.items():
            k = self._part_index[part]
            seen[k] = True
            Y[k] = pose
        both = np.flatnonzero(seen[self._pair_i] & seen[self._pair_j])
        zmap = np.full(self._pair_i.size, -1, dtype=np.intp)
        zmap[both] = np.arange(both.size)
        if both.size == 0:
            return np.zeros((0, 4, 4)), zmap, np.zeros(0)
        Yinv = invert_transform(Y[seen])
        inv_index = np.cumsum(seen) - 1
        Zobs = Yinv[inv_index[self._pair_i[both]]] @ Y[self._pair_j[both]]
        return Zobs, zmap, self._threshold(Zobs)

    def _threshold(self, Z):
        """Translational thresholds for observed relative transforms ``Z`` (k, 4, 4): they grow with distance."""
        c = self.config
        return translation_threshold(c.theta_trans, c.theta_rot, np.linalg.norm(Z[..., :3, 3], axis=-1))

    def _superset_pairs(self, entries):
        """Positions ``(sub, sup)`` of candidates of the same pair (and target) whose actions strictly contain others.

        These are the nested pairs the dominance rule compares.
        """
        groups = {}
        for k, e in enumerate(entries):
            groups.setdefault((e.parent, e.child, e.target), []).append(k)
        sub, sup = [], []
        for members in groups.values():
            sets = [(k, frozenset(entries[k].actions)) for k in members]
            for k, a in sets:
                for q, b in sets:
                    if a < b:
                        sub.append(k)
                        sup.append(q)
        return np.array(sub, dtype=np.intp), np.array(sup, dtype=np.intp)

    def _dominated(self, rows, n_now, sub, sup, valid=None):
        """Mask over candidates beaten by a model with more actions by more than ``dominance_margin`` (see config).

        With ``valid``, only valid candidates are examined (the others are out of the tree search anyway).
        """
        c = self.config
        dominated = np.zeros(len(rows), dtype=bool)
        if valid is not None and sub.size:
            keep = np.asarray(valid)[sub]
            sub, sup = sub[keep], sup[keep]
        if sub.size:
            rows = np.asarray(rows)
            n_now = np.asarray(n_now)
            n, diff = self._monitor.paired_difference(rows[sub], rows[sup], n_now[sub], n_now[sup],
                                                      c.stale_fraction)
            beaten = (n >= c.min_test_samples) & np.any(diff > c.dominance_margin, axis=1)
            dominated[sub[beaten]] = True
        return dominated

    def _learning_arrays(self):
        """Arrays over the entries learning in the batch: ids, slots, rows, pair index, flip, cusum flag, nesting
        pairs ``(sub, sup)`` and complexity; rebuilt only when the set of learning entries changes."""
        if self._learning is None:
            learning = [e for e in self._entries.values() if e.slot >= 0]
            self._learning = (
                np.array([e.id for e in learning], dtype=np.int64),
                np.array([e.slot for e in learning], dtype=np.intp),
                np.array([e.row for e in learning], dtype=np.int64),
                np.array([self._pair_index[(e.parent, e.child)] for e in learning], dtype=np.intp),
                np.array([self._flip(e) for e in learning], dtype=bool),
                np.array([e.role == _TREE for e in learning], dtype=bool),
                self._superset_pairs(learning),
                np.array([e.complexity for e in learning], dtype=float),
                np.array([self._refine_window if e.role == _TREE else self.config.train_window for e in learning],
                         dtype=np.int64),
            )
        return self._learning

    def _observed_Z(self, Zobs, zmap, pair, flip):
        """Observed transforms for entries with pair indices ``pair`` and direction flags ``flip`` (all observed)."""
        Z = Zobs[zmap[pair]]
        if np.any(flip):
            Z[flip] = invert_transform(Z[flip])
        return Z

    def _train_learning(self, a, rel, step):
        """Prequential step of every learning entry whose pair is observed: predict, record the error, train.

        Returns
        -------
        ids : ndarray of int
            Entries that were evaluated.
        alarm : ndarray of bool
            CUSUM alarms (only tree entries run a CUSUM).
        """
        Zobs, zmap, theta = rel
        ids, slots, rows, pair, flip, is_tree, _, _, limit = self._learning_arrays()
        sel = np.flatnonzero(zmap[pair] >= 0) if ids.size else np.zeros(0, dtype=np.intp)
        if sel.size == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
        Z = self._observed_Z(Zobs, zmap, pair[sel], flip[sel])
        alarm = self._prequential(slots[sel], rows[sel], a, Z, step, theta[zmap[pair[sel]]], is_tree[sel],
                                  limit[sel])
        return ids[sel], alarm

    def _prequential(self, slots, rows, a, Z, step, theta_trans, cusum, limit):
        """Test-then-train for batch slots: predict ``Z``, record the errors, then add the sample where not full.

        Slots are processed in groups of equal training-set size. GPBatch pads a group's arrays to its largest
        slot, and that padding changes the last bits of the results; equal-size groups are exactly the groups
        :meth:`GPBatch.from_state_dict` replays, so a restored learner continues bit-identically.

        Returns
        -------
        alarm : ndarray of bool, shape (k,)
        """
        n = self._batch.size(slots)
        alarm = np.zeros(slots.size, dtype=bool)
        for size in np.unique(n):
            group = np.flatnonzero(n == size)
            Zp = self._batch.predict(slots[group], a)
            if size > 0:  # an empty GP predicts the identity: its error says nothing about the model
                e_t, e_r = prediction_errors(Zp, Z[group])
                alarm[group] = self._monitor.record(rows[group], e_t, e_r, step, n_train=size, cusum=cusum[group],
                                                    theta_trans=theta_trans[group])
            open_ = group[size < limit[group]]
            if open_.size:
                self._batch.add_samples(slots[open_], a, Z[open_])
        return alarm

    # ------------------------------------------------------------------ bootstrapping
    def _bootstrap_step(self, a, rel, step, events):
        c = self.config
        evaluated, _ = self._train_learning(a, rel, step)
        ids, slots, rows, _, _, _, (sub, sup), layer, _ = self._learning_arrays()
        if evaluated.size == 0:
            # Nothing new was learned: the tree is unchanged, but the patience rule may end bootstrapping.
            self._maybe_finish_bootstrap(step, events)
            return
        n_now = self._batch.size(slots) if ids.size else np.zeros(0, dtype=np.int64)
        st = self._monitor.stats(rows, n_train=n_now, stale_fraction=c.stale_fraction)
        mt, mr = st.trans_error, st.rot_error
        valid = self._monitor.valid(st, c.min_test_samples)
        dominated = valid & self._dominated(rows, n_now, sub, sup, valid)
        valid &= ~dominated
        cost = model_cost(layer, st.trans_ratio, st.rot_ratio) if ids.size else np.zeros(0)
        models = [(self._entries[i].parent, self._entries[i].child, int(i), int(layer[k]), float(cost[k]))
                  for k, i in enumerate(ids) if valid[k]]
        keys = select_spanning_tree(self.part_ids, models)
        self._scheme = None
        if keys is None:
            if self._tree is not None and len(self.part_ids) > 1:
                events.append(Event(step, "structure_changed",
                                    f"no valid spanning tree any more: {len(models)} valid candidates of {ids.size} "
                                    f"({int(dominated.sum())} more valid but dominated) do not connect all parts"))
                self._tree = None
                self._tree_since = step
            return
        if self._tree is None or set(keys) != set(self._tree):
            pos = {int(i): k for k, i in enumerate(ids)}
            desc = "; ".join(f"{self._entries[i].describe()} cost {cost[pos[i]]:.2f} "
                             f"({_fmt_err(mt[pos[i]], mr[pos[i]])})" for i in keys)
            total = float(sum(cost[pos[i]] for i in keys))
            if self._tree is None and not self._found:
                kind, what = "structure_found", "first valid spanning tree"
            else:
                kind, what = "structure_changed", "spanning tree changed"
            if self._tree is not None:
                gone = [self._entries[i].describe() for i in self._tree if i not in set(keys)]
                what += f" (replacing {', '.join(gone)})" if gone else ""
            events.append(Event(step, kind, f"{what} from {len(models)} eligible of {ids.size} candidates "
                                            f"({int(dominated.sum())} more valid but dominated by a model with more "
                                            f"actions), total cost {total:.2f}: {desc}"))
            self._found = True
            self._tree = list(keys)
            self._tree_since = step
        self._maybe_finish_bootstrap(step, events, n_now=n_now, ids=ids)

    def _maybe_finish_bootstrap(self, step, events, n_now=None, ids=None):
        c = self.config
        if self._tree is None:
            return
        if ids is None:
            ids, slots, _, _, _, _, _, _, _ = self._learning_arrays()
            n_now = self._batch.size(slots) if ids.size else np.zeros(0, dtype=np.int64)
        pos = {int(i): k for k, i in enumerate(ids)}
        tree_frozen = all(n_now[pos[i]] >= c.train_window for i in self._tree)
        all_frozen = bool(np.all(n_now >= c.train_window))
        stable = step - self._tree_since >= c.bootstrap_patience
        if not (tree_frozen and (all_frozen or stable)):
            return
        tree = [self._entries[i] for i in self._tree]
        old_batch = self._batch
        # A fresh, compact batch for the steady state (candidates freed, state files small) whose capacity lets
        # the tree models keep refining up to refine_window samples.
        self._batch = self._new_batch(self._refine_window, old_batch.max_dim)
        refining = []
        for entry in tree:
            model = old_batch.to_model(entry.slot, entry.parent, entry.child)
            entry.n_train = int(n_now[pos[entry.id]])
            entry.role = _TREE
            entry.last_used = step
            entry.model = model
            entry.slot = -1
            if entry.n_train < self._refine_window:
                entry.slot = int(self._batch.allocate([entry.actions])[0])
                self._replay_training_data(entry.slot, model)
                refining.append(entry)
        old = self._monitor
        self._monitor = self._new_monitor()
        rows = self._monitor.allocate(len(tree))
        self._monitor.copy_rows(old, [e.row for e in tree], rows)
        self._monitor.reset_cusum(rows)
        for entry, row in zip(tree, rows, strict=True):
            entry.row = int(row)
        n_dropped = len(self._entries) - len(tree)
        self._entries = {e.id: e for e in tree}
        self._bootstrapping = False
        self._invalidate()
        why = "all candidates are frozen" if all_frozen else f"the tree was stable for {step - self._tree_since} steps"
        refine = (f"; the tree models keep learning up to {self._refine_window} samples" if refining else "")
        events.append(Event(step, "bootstrap_finished",
                            f"bootstrapping finished after {step + 1} steps ({why}): kept the {len(tree)} tree "
                            f"models ({', '.join(e.describe() for e in tree)}), trained on {c.train_window} samples "
                            f"each; dropped {n_dropped} other candidates{refine}"))

    def _replay_training_data(self, slot, model):
        """Add a fitted GP model's training samples, in order, to an empty batch slot."""
        X = model.X_train_
        Z = transform_from_vector12(model.Y_train_)
        a = np.zeros(self.n_actions)
        cols = list(model.actions)
        for k in range(X.shape[0]):
            a[cols] = X[k]
            self._batch.add_samples([slot], a, Z[k:k + 1])

    # ------------------------------------------------------------------ steady state and adaptation
    def _steady_step(self, a, rel, step, events):
        c = self.config
        Zobs, zmap, theta = rel
        # Materialised models (tree, memory): one predict call each; few of them.
        rows, e_t, e_r, n_tr, use_cusum, ids, theta_t = [], [], [], [], [], [], []
        A = a[None, :]
        fixed = [e for e in self._entries.values() if e.slot < 0 and e.role in (_TREE, _MEMORY)]
        if fixed:
            zi = []
            preds = []
            vectors = []  # GP means, projected onto SE(3) together: one batched SVD instead of one per model
            for e in fixed:
                k = self._pair_index[(e.parent, e.child)]
                if zmap[k] < 0:
                    continue
                if isinstance(e.model, GPModel):
                    vectors.append(len(preds))
                    preds.append(e.model.predict_components(A)[0])
                else:
                    preds.append(e.model.predict(A)[0])
                zi.append((k, self._flip(e)))
                ids.append(e.id)
                rows.append(e.row)
                n_tr.append(e.n_train)
                use_cusum.append(e.role == _TREE)
            if preds:
                Zp = np.empty((len(preds), 4, 4))
                if vectors:
                    Zp[vectors] = transform_from_vector12(np.asarray([preds[i] for i in vectors]))
                for i, P in enumerate(preds):
                    if P.shape == (4, 4):
                        Zp[i] = P
                Z = self._observed_Z(Zobs, zmap, np.array([k for k, _ in zi], dtype=np.intp),
                                     np.array([f for _, f in zi], dtype=bool))
                e_t, e_r = prediction_errors(Zp, Z)
                theta_t = theta[zmap[[k for k, _ in zi]]]
        alarm_fixed = np.zeros(0, dtype=bool)
        if ids:
            alarm_fixed = self._monitor.record(rows, e_t, e_r, step, n_train=n_tr, cusum=use_cusum,
                                               theta_trans=theta_t)
        # Models still learning in the batch: replacement candidates and installed, not yet frozen replacements.
        learn_ids, alarm_learn = self._train_learning(a, rel, step)
        self._refresh_learning_tree(step)
        alarms = dict(zip(ids, alarm_fixed.tolist(), strict=True))
        alarms.update(zip(learn_ids.tolist(), alarm_learn.tolist(), strict=True))
        # Mismatch detection on the tree edges observed in this step.
        observed_tree = [i for i in self._tree if i in alarms and i not in self._mismatch]
        if observed_tree:
            entries = [self._entries[i] for i in observed_tree]
            n_now = [self._n_now(e) for e in entries]
            st = self._monitor.stats([e.row for e in entries], n_train=n_now, stale_fraction=c.stale_fraction)
            valid = self._monitor.valid(st, c.min_test_samples)
            for k, e in enumerate(entries):
                window_bad = st.n[k] >= c.min_test_samples and not valid[k]
                if alarms[e.id] or window_bad:
                    self._start_mismatch(e, step, events, bool(alarms[e.id]), st, k)
                else:
                    self._challenge_from_memory(e, step, events, st, k)
        for edge_id in list(self._mismatch):
            if edge_id in self._mismatch:
                self._handle_mismatch(self._entries[edge_id], step, events)

    def _n_now(self, entry):
        return int(self._batch.size([entry.slot])[0]) if entry.slot >= 0 else entry.n_train

    def _refresh_learning_tree(self, step):
        """Tree models still learning: their snapshot is dropped after each new sample (rebuilt only when the body
        scheme is asked for); at ``refine_window`` samples they are frozen and leave the batch."""
        for i in self._tree:
            e = self._entries[i]
            if e.slot < 0:
                continue
            n = int(self._batch.size([e.slot])[0])
            if n != e.n_train:
                e.model = None
                e.n_train = n
                self._scheme = None
            if n >= self._refine_window:
                self._materialize(e)

    def _materialize(self, entry, before=None):
        """Turn a learning entry into a fitted model and free its slot.

        With ``before`` (a change-point step), only the samples the model had learned before that step are kept,
        so a model that kept refining after a change goes to memory uncontaminated.
        """
        model = self._batch.to_model(entry.slot, entry.parent, entry.child)
        n = model.n_samples
        if before is not None and n:
            steps = self._monitor.steps[entry.row]
            after = (steps >= before)
            if np.any(after):
                # Predictions are made before training: the training size at the first prediction after the
                # change point counts the samples learned before it.
                keep = int(self._monitor.n_train[entry.row][after].min())
                if 0 < keep < n:
                    data = model.to_dict()
                    data["X"], data["Y"] = data["X"][:keep], data["Y"][:keep]
                    model = GPModel.from_dict(data)
                    n = keep
        self._batch.release([entry.slot])
        entry.slot = -1
        entry.model = model
        entry.n_train = n
        self._learning = None
        self._scheme = None

    def _challenge_from_memory(self, entry, step, events, st, k):
        """Start a mismatch early when a remembered model of the same pair clearly fits the recent samples better.

        Only while the tree model's CUSUM is above zero (some evidence of drift): over the samples since the
        excursion started, a remembered model must be valid (at least ``reinstate_min_samples`` samples) and beat
        the tree model in a paired comparison in both channels, by more than ``challenge_margin`` on average. This
        is what lets a repair, or the same failure again, be handled within a few samples.
        """
        c = self.config
        if not np.any(self._monitor.cusum[entry.row] > 0.0):
            return
        pair = {entry.parent, entry.child}
        memory = [e for e in self._entries.values() if e.role == _MEMORY and {e.parent, e.child} == pair]
        if not memory:
            return
        tau = int(self._monitor.change_point([entry.row])[0])
        rows = [e.row for e in memory]
        ok = self._monitor.valid(self._monitor.stats(rows, since=tau), c.reinstate_min_samples)
        n, diff = self._monitor.paired_difference(rows, [entry.row] * len(rows), since=tau)
        better = (ok & (n >= c.reinstate_min_samples) & (diff.mean(axis=1) < -c.challenge_margin)
                  & np.all(diff < 0.0, axis=1))
        if np.any(better):
            best = int(np.argmin(np.where(better, diff.mean(axis=1), np.inf)))
            cause = (f"remembered {memory[best].describe()} fits the {n[best]} samples since step {tau} better by "
                     f"{-diff[best, 0]:.2f} (trans) / {-diff[best, 1]:.2f} (rot) thresholds")
            self._start_mismatch(entry, step, events, False, st, k, cause=cause)

    def _start_mismatch(self, entry, step, events, alarm, st, k, cause=None):
        c = self.config
        n, mt, mr, theta_t = int(st.n[k]), float(st.trans_error[k]), float(st.rot_error[k]), float(st.theta_trans[k])
        tau = int(self._monitor.change_point([entry.row])[0])
        if tau < 0:
            tau = int(self._monitor.first_step([entry.row])[0])
            tau = step if tau < 0 else tau
        S = self._monitor.cusum[entry.row]
        if cause is None:
            cause = (f"CUSUM {S[0]:.2f} (trans) / {S[1]:.2f} (rot) reached {c.cusum_threshold:g}" if alarm
                     else f"test window invalid over {n} samples")
        self._mismatch[entry.id] = {"tau": tau, "detected": step, "sampled_at": -1, "train_from": tau,
                                    "resamples": 0}
        events.append(Event(step, "mismatch_detected",
                            f"{entry.describe()} no longer matches the observations: {cause}; window mean "
                            f"{_fmt_err(mt, mr)} over {n} samples (thresholds {_fmt_err(theta_t, c.theta_rot)}); "
                            f"change point estimated at step {tau}",
                            parent=entry.parent, child=entry.child, model=entry.describe(),
                            trans_error=_finite_or_none(mt), rot_error=_finite_or_none(mr)))

    def _candidates_of(self, edge_id):
        return [e for e in self._entries.values() if e.role == _CANDIDATE and e.target == edge_id]

    def _handle_mismatch(self, failed, step, events):
        c = self.config
        state = self._mismatch[failed.id]
        if self._try_memory(failed, state, step, events):
            return
        candidates = self._candidates_of(failed.id)
        if not candidates:
            if state["sampled_at"] < 0:
                self._sample_replacements(failed, state, step, events, state["tau"], "no remembered model fits")
                candidates = self._candidates_of(failed.id)
        if not candidates:
            return
        rows = [e.row for e in candidates]
        n_now = [self._n_now(e) for e in candidates]
        st = self._monitor.stats(rows, n_train=n_now, stale_fraction=c.stale_fraction)
        valid = self._monitor.valid(st, c.min_test_samples)
        valid &= ~self._dominated(rows, n_now, *self._superset_pairs(candidates), valid)
        if np.any(valid):
            rel = np.array([relative_complexity(e.actions, failed.actions) for e in candidates])
            cost = np.where(valid, model_cost(rel, st.trans_ratio, st.rot_ratio), np.inf)
            best = int(np.argmin(cost))
            self._install_replacement(failed, candidates[best], step, events, int(st.n[best]),
                                      float(st.trans_error[best]), float(st.rot_error[best]), int(rel[best]),
                                      float(cost[best]), int(valid.sum()), len(candidates))
            return
        if step - state["sampled_at"] >= c.replacement_patience:
            for e in candidates:
                self._remove_entry(e)
            start = max(state["train_from"], step - c.test_window + 1)
            state["resamples"] += 1
            self._sample_replacements(
                failed, state, step, events, start,
                f"none of the {len(candidates)} replacements became valid within {c.replacement_patience} steps")

    def _tree_components(self, without):
        """Part sets of the two halves of the tree when edge entry ``without`` is removed."""
        parent = {p: p for p in self.part_ids}

        def find(p):
            while parent[p] != p:
                parent[p] = parent[parent[p]]
                p = parent[p]
            return p

        for i in self._tree:
            if i == without:
                continue
            e = self._entries[i]
            parent[find(e.parent)] = find(e.child)
        return find

    def _try_memory(self, failed, state, step, events):
        c = self.config
        memory = [e for e in self._entries.values() if e.role == _MEMORY]
        if not memory:
            return False
        find = self._tree_components(failed.id)
        bridges = [e for e in memory if find(e.parent) != find(e.child)]
        if not bridges:
            return False
        st = self._monitor.stats([e.row for e in bridges], since=state["tau"])
        n, mt, mr = st.n, st.trans_error, st.rot_error
        ok = self._monitor.valid(st, c.reinstate_min_samples)
        if not np.any(ok):
            return False
        layer = np.array([e.complexity for e in bridges])
        cost = np.where(ok, model_cost(layer, st.trans_ratio, st.rot_ratio), np.inf)
        best = int(np.argmin(cost))
        back = bridges[best]
        self._tree[self._tree.index(failed.id)] = back.id
        back.role = _TREE
        back.last_used = step
        self._monitor.forget_before([back.row], state["tau"])
        self._monitor.reset_cusum([back.row])
        del self._mismatch[failed.id]
        for e in self._candidates_of(failed.id):
            self._remove_entry(e)
        self._scheme = None
        events.append(Event(step, "model_reinstated",
                            f"remembered {back.describe()} fits again: mean error {_fmt_err(mt[best], mr[best])} over "
                            f"{n[best]} samples since the change point (step {state['tau']}), below "
                            f"{_fmt_err(st.theta_trans[best], c.theta_rot)}; it replaces {failed.describe()} "
                            f"(chosen among {int(ok.sum())} fitting of {len(bridges)} remembered)",
                            parent=back.parent, child=back.child, model=back.describe(),
                            trans_error=float(mt[best]), rot_error=float(mr[best])))
        if {back.parent, back.child} != {failed.parent, failed.child}:
            events.append(Event(step, "structure_changed",
                                f"edge {failed.parent}-{failed.child} replaced by {back.parent}-{back.child} "
                                f"({back.describe()}) from memory"))
        self._retire(failed, step, events, f"replaced by remembered {back.describe()}", state["tau"])
        return True

    def _sample_replacements(self, failed, state, step, events, start, why):
        c = self.config
        sets = [(r, acts) for r, acts in replacement_action_sets(failed.actions, self.n_actions, c.max_complexity,
                                                                 c.replacement_max_relative)
                if len(acts) <= self._batch.max_dim]
        slots = self._batch.allocate([acts for _, acts in sets])
        rows = self._monitor.allocate(len(sets))
        entries = [self._add_entry(failed.parent, failed.child, acts, _CANDIDATE, row, slot=slot, created=step,
                                   origin="replacement", target=failed.id)
                   for (_, acts), row, slot in zip(sets, rows, slots, strict=True)]
        # Replay the raw history since the change point, test-then-train, so they need not wait for new data.
        used = 0
        k = len(entries)
        limit = np.full(k, c.train_window)
        no_cusum = np.zeros(k, dtype=bool)
        for rec_step, a, obs in self._history:
            if rec_step < start or failed.parent not in obs or failed.child not in obs:
                continue
            Z = invert_transform(obs[failed.parent]) @ obs[failed.child]
            self._prequential(slots, rows, a, np.broadcast_to(Z, (k, 4, 4)), rec_step,
                              np.full(k, self._threshold(Z)), no_cusum, limit)
            used += 1
        state["sampled_at"] = step
        state["train_from"] = start
        listing = ", ".join(f"{e.describe()} [C={r}]" for (r, _), e in zip(sets, entries, strict=True))
        events.append(Event(step, "model_sampled",
                            f"{why}: sampled {len(entries)} replacement(s) for {failed.describe()}, ordered by "
                            f"relative complexity C(M2|M1) = |actions sym-diff|: {listing}; trained on the "
                            f"{used} samples of this pair since step {start} (replayed from history)",
                            parent=failed.parent, child=failed.child, model=failed.describe()))

    def _install_replacement(self, failed, new, step, events, n, mt, mr, rel, cost, n_valid, n_cand):
        new.role = _TREE
        new.target = -1
        new.last_used = step
        new.n_train = int(self._batch.size([new.slot])[0])
        new.model = None  # keeps learning up to refine_window samples as a tree model; snapshot on demand
        if new.n_train >= self._refine_window:
            self._materialize(new)
        self._monitor.reset_cusum([new.row])
        self._tree[self._tree.index(failed.id)] = new.id
        state = self._mismatch.pop(failed.id)
        for e in self._candidates_of(failed.id):
            self._remove_entry(e)
        self._invalidate()
        events.append(Event(step, "model_replaced",
                            f"{new.describe()} replaces {failed.describe()}: valid with mean error {_fmt_err(mt, mr)} "
                            f"over {n} test samples after {new.n_train} training samples since step "
                            f"{state['train_from']}; cost C(M2|M1) + e = {cost:.2f} (relative complexity {rel}), "
                            f"cheapest of {n_valid} valid among {n_cand} sampled; mismatch lasted "
                            f"{step - state['detected']} steps",
                            parent=new.parent, child=new.child, model=new.describe(), trans_error=float(mt),
                            rot_error=float(mr)))
        self._retire(failed, step, events, f"replaced by {new.describe()}", state["tau"])

    def _retire(self, entry, step, events, why, tau=None):
        c = self.config
        if entry.slot >= 0:
            self._materialize(entry, before=tau)
        entry.role = _MEMORY
        entry.last_used = step
        self._monitor.reset_cusum([entry.row])
        self._learning = None
        pair = {entry.parent, entry.child}
        same = sorted((e for e in self._entries.values() if e.role == _MEMORY and {e.parent, e.child} == pair),
                      key=lambda e: (e.last_used, e.id))
        forgotten = same[:max(0, len(same) - c.memory_size)]
        for e in forgotten:
            self._remove_entry(e)
        note = f"; forgot {', '.join(e.describe() for e in forgotten)} (least recently used)" if forgotten else ""
        kept = len(same) - len(forgotten)
        mt = mr = math.inf
        if entry.id in self._entries:
            st = self._monitor.stats([entry.row])
            mt, mr = float(st.trans_error[0]), float(st.rot_error[0])
        events.append(Event(step, "model_retired",
                            f"{entry.describe()} retired ({why}); window mean {_fmt_err(mt, mr)}; memory holds "
                            f"{kept} model(s) of pair {entry.parent}-{entry.child}{note}",
                            parent=entry.parent, child=entry.child, model=entry.describe(),
                            trans_error=_finite_or_none(mt), rot_error=_finite_or_none(mr)))

    # ------------------------------------------------------------------ state
    def to_state(self):
        """Everything needed to continue bit-identically, as a JSON-serialisable dict.

        Covers the configuration, parts, step, all tracked models (tree, memory, candidates) with their test
        windows and CUSUMs, the GP batch, the raw history, the root observations and the counters.
        """
        entries = []
        for e in self._entries.values():
            # Learning models are rebuilt from the batch; saving their snapshot too would duplicate the data.
            entries.append(e.to_dict(with_model=e.slot < 0))
        return {
            "version": STATE_VERSION,
            "config": self.config.to_dict(),
            "part_ids": list(self.part_ids),
            "n_actions": self.n_actions,
            "action_lower": _bounds_to_json(self.action_lower),
            "action_upper": _bounds_to_json(self.action_upper),
            "step": self.step,
            "last_stamp": self.last_stamp,
            "rejected": dict(self.rejected),
            "bootstrapping": self._bootstrapping,
            "found": self._found,
            "tree": None if self._tree is None else list(self._tree),
            "tree_since": self._tree_since,
            "next_id": self._next_id,
            "entries": entries,
            "mismatch": [{"edge": k, **v} for k, v in self._mismatch.items()],
            "monitor": self._monitor.to_dict(),
            "batch": self._batch.state_dict(),
            "history": [{"step": s, "actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()]}
                        for s, a, obs in self._history],
            "root_observations": [Y.tolist() for Y in self._root_obs],
        }

    @classmethod
    def from_state(cls, state):
        """Rebuild a learner from :meth:`to_state` output.

        Raises
        ------
        ModelFileError
            If keys are missing, values have the wrong type or shape, or arrays contain NaN or inf.
        """
        if not isinstance(state, dict):
            raise ModelFileError(f"learner state must be a dict, got {type(state).__name__}")
        if state.get("version") != STATE_VERSION:
            raise ModelFileError(f"unsupported learner state version {state.get('version')!r}; this reads "
                                 f"{STATE_VERSION}")
        try:
            config = BodySchemeConfig.from_dict(state["config"])
            self = cls.__new__(cls)
            self.config = config
            self.part_ids = tuple(int(p) for p in state["part_ids"])
            self.n_actions = int(state["n_actions"])
            if not self.part_ids or len(set(self.part_ids)) != len(self.part_ids) or self.n_actions < 0:
                raise ModelFileError(f"bad parts {self.part_ids} or n_actions {self.n_actions}")
            self.root = min(self.part_ids) if config.root is None else int(config.root)
            if self.root not in self.part_ids:
                raise ModelFileError(f"root {self.root} is not one of the parts {self.part_ids}")
            self.action_lower = _bounds_from_json(state["action_lower"], self.n_actions, "action_lower")
            self.action_upper = _bounds_from_json(state["action_upper"], self.n_actions, "action_upper")
            self.step = int(state["step"])
            self.last_stamp = state["last_stamp"]
            self.rejected = Counter({str(k): int(v) for k, v in state["rejected"].items()})
            self._setup_static()
            self._bootstrapping = bool(state["bootstrapping"])
            self._found = bool(state["found"])
            self._tree = None if state["tree"] is None else [int(i) for i in state["tree"]]
            self._tree_since = int(state["tree_since"])
            self._next_id = int(state["next_id"])
            self._monitor = ErrorMonitor.from_dict(state["monitor"])
            if self._monitor.window != config.test_window:
                raise ModelFileError(f"monitor window {self._monitor.window} != test_window {config.test_window}")
            self._batch = GPBatch.from_state_dict(state["batch"])
            if self._batch.n_actions != self.n_actions:
                raise ModelFileError(f"GP batch has {self._batch.n_actions} actions, learner {self.n_actions}")
            self._entries = {}
            for data in state["entries"]:
                entry = _Entry.from_dict(data)
                for part in (entry.parent, entry.child):
                    if part not in self.part_ids:
                        raise ModelFileError(f"model {entry.describe()} refers to unknown part {part}")
                if not (0 <= entry.row < self._monitor.capacity and self._monitor.in_use[entry.row]):
                    raise ModelFileError(f"model {entry.describe()} has no monitor row {entry.row}")
                if entry.slot >= 0:
                    if entry.slot not in set(self._batch.allocated_slots.tolist()):
                        raise ModelFileError(f"model {entry.describe()} refers to free GP slot {entry.slot}")
                elif entry.model is None:
                    raise ModelFileError(f"frozen model entry {entry.id} has no stored model")
                self._entries[entry.id] = entry
            if self._tree is not None and any(i not in self._entries for i in self._tree):
                raise ModelFileError(f"tree refers to unknown model ids {self._tree}")
            self._mismatch = {}
            for item in state["mismatch"]:
                item = dict(item)
                edge = int(item.pop("edge"))
                if edge not in self._entries:
                    raise ModelFileError(f"mismatch refers to unknown model id {edge}")
                self._mismatch[edge] = {k: int(item[k]) for k in ("tau", "detected", "sampled_at", "train_from",
                                                                   "resamples")}
            self._history = deque(maxlen=config.history_length)
            for rec in state["history"]:
                a = _finite_array(rec["actions"], (self.n_actions,), "history actions")
                obs = {}
                for part, Y in rec["observations"]:
                    if int(part) not in self._part_index:
                        raise ModelFileError(f"history observation of unknown part {part}")
                    obs[int(part)] = _finite_array(Y, (4, 4), "history observation")
                self._history.append((int(rec["step"]), a, obs))
            self._root_obs = deque((_finite_array(Y, (4, 4), "root observation") for Y in state["root_observations"]),
                                   maxlen=config.root_window)
            self._root_pose = None
            self._invalidate()
            if self._tree is not None:
                self.body_scheme  # noqa: B018 - validates that the stored tree is a spanning tree of fitted models
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, InvalidInputError,
                NotFittedError) as exc:
            raise ModelFileError(f"bad learner state: {type(exc).__name__}: {exc}") from exc
        return self

    def __repr__(self):
        return (f"<BodySchemeLearner parts={self.part_ids} actions={self.n_actions} phase={self.phase} "
                f"step={self.step}>")


def _finite_array(value, shape, name):
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ModelFileError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ModelFileError(f"{name} contains NaN or inf")
    return arr


def _finite_or_none(value):
    """Event error fields: a float, or None where no error is known (keeps events JSON-safe)."""
    value = float(value)
    return value if math.isfinite(value) else None


def _bounds_to_json(bounds):
    """Action limits as a JSON list; infinite limits (continuous joints) as the strings "inf" / "-inf"."""
    if bounds is None:
        return None
    return [float(b) if math.isfinite(b) else ("inf" if b > 0 else "-inf") for b in bounds]


def _bounds_from_json(value, n, name):
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != n:
        raise ModelFileError(f"{name} must be a list of {n} limits, got {value!r}")
    out = []
    for b in value:
        if b in ("inf", "-inf"):
            out.append(float(b))
        elif isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b):
            out.append(float(b))
        else:
            raise ModelFileError(f"{name} contains an invalid limit {b!r}")
    return np.array(out)

