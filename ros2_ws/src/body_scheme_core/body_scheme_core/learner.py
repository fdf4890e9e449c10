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
This module orchestrates the time step; the pieces live in :mod:`~body_scheme_core.inputs` (validation),
:mod:`~body_scheme_core.relative` (relative observations), :mod:`~body_scheme_core.pool` (tracked models and their
prequential evaluation), :mod:`~body_scheme_core.bootstrap`, :mod:`~body_scheme_core.adaptation` (change detection,
memory, repair) and :mod:`~body_scheme_core.root_pose`. ``docs/core/learning-and-adaptation.md`` describes every
rule and default and how they differ from the paper.
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np

from .adaptation import Adaptation
from .bootstrap import Bootstrap
from .config import BodySchemeConfig
from .errors import InvalidInputError, ModelFileError, NotFittedError
from .events import Event
from .inputs import (
    check_action_bounds,
    check_actions,
    check_config,
    check_initial_models,
    check_n_actions,
    check_observation_mapping,
    check_part_ids,
    check_stamp,
    filter_observations,
    root_part,
)
from .pool import MEMORY, TREE, ModelPool, new_batch, new_monitor, refine_window
from .relative import PartPairs
from .root_pose import RootPoseEstimator
from .scheme import BodyScheme

__all__ = ["BodySchemeLearner", "PHASES", "STATE_VERSION"]

#: Phases reported by :attr:`BodySchemeLearner.phase`.
PHASES = ("bootstrapping", "steady", "adapting")
#: Version of the dict layout of :meth:`BodySchemeLearner.to_state`.
STATE_VERSION = 2  # 2: root_samples (actions + all observations) replace root_observations


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
        config = check_config(BodySchemeConfig() if config is None else config)
        self._set_parts(config, check_part_ids(part_ids), check_n_actions(n_actions))
        self.action_lower, self.action_upper = check_action_bounds(action_lower, action_upper, self.n_actions)
        self.step = 0
        self.last_stamp = None
        self.rejected = Counter()
        self._history = deque(maxlen=config.history_length)
        self._root_pose = RootPoseEstimator(config.root_window, self.root)
        if initial_models is None:
            # Candidates learn up to train_window samples.
            batch = new_batch(config, self.n_actions, config.train_window, config.max_complexity)
            pool = ModelPool(config, self.n_actions, self._pairs, batch, new_monitor(config))
            Bootstrap.add_candidates(pool, self.part_ids, self.n_actions, config.max_complexity)
            tree = [] if len(self.part_ids) == 1 else None
        else:
            models = check_initial_models(initial_models, self.part_ids, self.root, self.n_actions)
            # Replacements of the given models learn up to train_window samples, and then as tree models up to
            # refine_window; the batch must also hold a replacement with the given models' action sets.
            max_dim = max([config.max_complexity] + [model.complexity for model in models])
            batch = new_batch(config, self.n_actions, refine_window(config), max_dim)
            pool = ModelPool(config, self.n_actions, self._pairs, batch, new_monitor(config))
            tree = [entry.id for entry in pool.add_fitted(models, TREE, origin="initial", last_used=0)]
        self._set_models(pool, tree, bootstrapping=initial_models is None, found=initial_models is not None,
                         tree_since=0, mismatch=None)

    def _set_parts(self, config, parts, n_actions):
        self.config = config
        self.part_ids = parts
        self.n_actions = n_actions
        self.root = root_part(parts, config.root)
        self._pairs = PartPairs(parts, config.theta_trans, config.theta_rot)

    def _set_models(self, pool, tree, bootstrapping, found, tree_since, mismatch):
        """Install the tracked models and the phase objects working on them (shared by construction and restore)."""
        self._pool = pool
        self._tree = tree
        self._bootstrapping = bootstrapping
        self._bootstrap = Bootstrap(self.config, pool, found, tree_since)
        self._adaptation = Adaptation(self.config, pool, self._history, mismatch)
        self._scheme = None

    # ------------------------------------------------------------------ queries
    @property
    def phase(self):
        """``"bootstrapping"``, ``"steady"`` or ``"adapting"`` (a tree edge is in mismatch)."""
        if self._bootstrapping:
            return "bootstrapping"
        return "adapting" if self._adaptation.mismatch else "steady"

    @property
    def n_candidates(self):
        """Number of models currently learning in the GP batch (bootstrap candidates or replacements)."""
        return self._pool.n_learning

    @property
    def memory(self):
        """Remembered (retired) local models, oldest first."""
        return [self._model_of(e) for e in self._pool.with_role(MEMORY)]

    @property
    def body_scheme(self):
        """The current body scheme (:class:`BodyScheme`), or ``None`` while no valid spanning tree exists."""
        if self._tree is None:
            return None
        if self._scheme is None:
            models = [self._model_of(self._pool.tracked[i]) for i in self._tree]
            self._scheme = BodyScheme(self.part_ids, self.root, models)
        return self._scheme

    def _model_of(self, entry):
        # Bootstrap candidates change every step and nothing refreshes their snapshots: do not keep them.
        return self._pool.model_of(entry, cache=not self._bootstrapping)

    @property
    def root_pose(self):
        """Estimated ``world2root`` (4, 4) from the last ``root_window`` samples (:mod:`~body_scheme_core.root_pose`).

        With a body scheme: the rigid transform that best maps its predicted marker positions onto the observed ones
        (all markers, outliers dropped). Before: the robust mean of the root's own observations. Identity while
        nothing was seen.
        """
        return self._root_pose.pose(self.body_scheme)

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
        a = check_actions(a, self.n_actions)
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
        pool = self._pool
        by_pair = {frozenset((pool.tracked[i].parent, pool.tracked[i].child)): pool.tracked[i] for i in self._tree}
        out = []
        c = self.config
        for parent, child, model, _ in scheme.edges:
            entry = by_pair[frozenset((parent, child))]
            st, valid = pool.window_stats([entry.row], [pool.n_now(entry)])
            theta_t = float(st.theta_trans[0]) if st.n[0] else c.theta_trans
            out.append({"parent": parent, "child": child, "model": entry.describe(), "model_id": entry.id,
                        "kind": model.kind,
                        "actions": list(model.actions), "n_test": int(st.n[0]), "trans_error": float(st.trans_error[0]),
                        "rot_error": float(st.rot_error[0]), "theta_trans": theta_t, "theta_rot": c.theta_rot,
                        "valid": bool(valid[0]), "in_mismatch": entry.id in self._adaptation.mismatch,
                        "cusum": pool.monitor.cusum[entry.row].tolist()})
        return out

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
        a = check_actions(actions, self.n_actions).copy()
        check_observation_mapping(observations)
        stamp = check_stamp(stamp)
        step = self.step
        events = []
        obs = self._accept(observations, step, events)
        self.last_stamp = stamp
        self._root_pose.add(a, obs)
        self._history.append((step, a, obs))
        relative = self._pairs.observe(obs)
        if self._bootstrapping:
            changed = self._bootstrap_step(a, relative, step, events)
        else:
            changed = self._adaptation.step(self._tree, a, relative, step, events)
        if changed:
            self._scheme = None
        self.step = step + 1
        return events

    def _accept(self, observations, step, events):
        """The valid observations ``{part: world2part}``; rejected ones are counted and reported."""
        valid, rejections = filter_observations(observations, self.part_ids)
        for part, reason, detail in rejections:
            self.rejected[reason] += 1
            events.append(Event(step, "input_rejected", f"observation rejected ({reason}): {detail}", child=part))
        return valid

    def _bootstrap_step(self, a, relative, step, events):
        """Search the tree over the candidates, then end bootstrapping if it is ready; returns whether the scheme
        may have changed."""
        self._tree, learned = self._bootstrap.step(self._tree, a, relative, step, events)
        if self._bootstrap.finish_if_ready(self._tree, step, events):
            self._bootstrapping = False
            return True
        return learned

    # ------------------------------------------------------------------ state
    def to_state(self):
        """Everything needed to continue bit-identically, as a JSON-serialisable dict.

        Covers the configuration, parts, step, all tracked models (tree, memory, candidates) with their test
        windows and CUSUMs, the GP batch, the raw history, the root observations and the counters.
        """
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
            "found": self._bootstrap.found,
            "tree": None if self._tree is None else list(self._tree),
            "tree_since": self._bootstrap.tree_since,
            "next_id": self._pool.next_id,
            "entries": self._pool.tracked_state(),
            "mismatch": self._adaptation.mismatch_state(),
            "monitor": self._pool.monitor.to_dict(),
            "batch": self._pool.batch.state_dict(),
            "history": [{"step": s, "actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()]}
                        for s, a, obs in self._history],
            "root_samples": [{"actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()]}
                             for a, obs in self._root_pose.samples],
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
            self._set_parts(config, check_part_ids(state["part_ids"]), check_n_actions(state["n_actions"]))
            self.action_lower = _bounds_from_json(state["action_lower"], self.n_actions, "action_lower")
            self.action_upper = _bounds_from_json(state["action_upper"], self.n_actions, "action_upper")
            self.step = int(state["step"])
            self.last_stamp = state["last_stamp"]
            self.rejected = Counter({str(k): int(v) for k, v in state["rejected"].items()})
            bootstrapping, found = bool(state["bootstrapping"]), bool(state["found"])
            tree = None if state["tree"] is None else [int(i) for i in state["tree"]]
            tree_since = int(state["tree_since"])
            pool = ModelPool.from_state(config, self.n_actions, self._pairs, state["entries"], state["next_id"],
                                        state["monitor"], state["batch"])
            if tree is not None and any(i not in pool.tracked for i in tree):
                raise ModelFileError(f"tree refers to unknown model ids {tree}")
            mismatch = Adaptation.mismatch_from_state(state["mismatch"], pool.tracked)
            self._history = deque(maxlen=config.history_length)
            for rec in state["history"]:
                a = _finite_array(rec["actions"], (self.n_actions,), "history actions")
                obs = {}
                for part, Y in rec["observations"]:
                    if int(part) not in self._pairs.part_index:
                        raise ModelFileError(f"history observation of unknown part {part}")
                    obs[int(part)] = _finite_array(Y, (4, 4), "history observation")
                self._history.append((int(rec["step"]), a, obs))
            self._root_pose = RootPoseEstimator(config.root_window, self.root, (
                (_finite_array(rec["actions"], (self.n_actions,), "root sample actions"),
                 {int(part): _finite_array(Y, (4, 4), "root sample observation") for part, Y in rec["observations"]})
                for rec in state["root_samples"]))
            self._set_models(pool, tree, bootstrapping, found, tree_since, mismatch)
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
