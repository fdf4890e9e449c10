"""The online lifelong body-scheme learner: bootstrapping, joint fit, change detection, memory and repair.

One :meth:`BodySchemeLearner.update` call per time step, with the commanded action vector and the marker poses
observed after it (paper Sec. III-C, III-E). The learner goes through three phases:

``bootstrapping``
    Without a given body scheme, a candidate local model is instantiated for every pair of parts, every action
    subset of at most ``max_complexity`` actions and every model class that fits it (static, prismatic, revolute,
    GP: the fully connected network of Fig. 4). Each is a *temporal* local model: it learns from the first
    ``train_window`` relative observations ``Y_i^-1 Y_j`` of its pair and is then frozen. Evaluation is prequential
    (test-then-train), so validity is never judged on training data. After every step the minimum spanning tree
    over the valid candidates is searched layer by layer, classes of a layer by rank (rigid joints before GPs), over
    the candidates that no nesting candidate clearly beats (dominance rule). Bootstrapping ends when a valid tree
    exists, its models are frozen and every candidate is frozen (or the tree has been stable for
    ``bootstrap_patience`` steps); the other candidates are dropped.
``steady``
    The tree's models keep learning through the **joint fit** (:mod:`~body_scheme_core.calibration.joint_fit`): the root
    pose and every rigid-joint model refined together against the absolute observations of the last ``history_length``
    steps, after every change of the tree and every ``calibration_period`` steps; the predictions come from that
    calibrated body scheme. Every step, each tree model and each remembered model is tested against its
    *chain-consistent* target (:mod:`~body_scheme_core.learning.chain`: the child's observation relative to the parent's
    predicted pose). A tree model is in *mismatch* when its test window is invalid, its CUSUM alarms, or a
    remembered model of its pair clearly fits the samples since the CUSUM left zero better.
``adapting``
    At least one tree edge is in mismatch. First the memory is asked (a remembered model of that pair, or of any
    pair across the cut, valid since the change point: ``model_reinstated``); otherwise replacement models of the
    pair are sampled, ordered by relative complexity (Eq. 11) and class, trained only on data since the change point
    (replayed from the history); if none becomes valid, candidates of the other pairs across the cut too. The
    cheapest valid one replaces the failed model (``model_replaced``), which goes to memory (``model_retired``).

Every decision is returned as an :class:`~body_scheme_core.events.Event` whose reason string carries the numbers.
This module is the learner's face: it checks the inputs and runs the time step
(:func:`~body_scheme_core.learning.learner_step.time_step`) on its one state
(:class:`~body_scheme_core.learning.learner_state.LearnerState`), all or nothing; the pieces live in
:mod:`~body_scheme_core.learning.inputs` (validation),
:mod:`~body_scheme_core.learning.relative` and :mod:`~body_scheme_core.learning.chain` (targets),
:mod:`~body_scheme_core.learning.pool` (tracked models and their prequential evaluation),
:mod:`~body_scheme_core.learning.bootstrap`, :mod:`~body_scheme_core.learning.adaptation` (change detection, memory,
repair), :mod:`~body_scheme_core.calibration.joint_fit` (the joint fit) and :mod:`~body_scheme_core.learning.root_pose`
(the root pose before the first fit). ``docs/core/learning-and-adaptation.md`` describes every rule and default and how
they differ from the paper.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import LearnerStepError, NotFittedError
from ..models import ChainModel
from .bootstrap import Bootstrap
from .config import BodySchemeConfig
from .inputs import (
    check_action_bounds,
    check_action_range,
    check_action_vector,
    check_body_size,
    check_config,
    check_initial_models,
    check_n_actions,
    check_observation_mapping,
    check_part_ids,
    check_stamp,
    filter_covariances,
    root_part,
)
from .learner_fit import fit_and_check
from .learner_state import LearnerState, restore, snapshot
from .learner_step import time_step
from .pool import ModelPool
from .state_file import from_dict, to_dict
from .tracked import MEMORY, TREE, Journal

__all__ = ["BodySchemeLearner", "PHASES"]

#: Phases reported by :attr:`BodySchemeLearner.phase`.
PHASES = ("bootstrapping", "steady", "adapting")


class _StateField:
    """A read-only attribute of the learner: the field of the same name of its state (:class:`LearnerState`)."""

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, learner, owner=None):
        return self if learner is None else getattr(learner._state, self.name)


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
        The root part, the robot's trunk, fixed in the camera's view: ``config.root``; without it, while bootstrapping,
        the part whose observed position moves least (the lowest id until anything was seen); with
        ``initial_models`` and no ``config.root``, the lowest id.
    n_actions : int
    config : BodySchemeConfig
    step : int
        Number of accepted :meth:`update` calls so far.
    rejected : collections.Counter
        Rejected observations by reason: ``unknown_id``, ``bad_shape``, ``not_finite``, ``not_rigid``,
        ``out_of_workspace``, ``flipped`` (a mirrored orientation where the scheme does not explain the position);
        ``bad_covariance`` counts covariances dropped (their poses kept).
    corrected : collections.Counter
        Observations taken in corrected, by kind: ``flipped`` (an orientation mirrored about the camera's ray, taken
        as its mirror image: the one the calibrated scheme predicts, at the position it predicts).
    noise : NoiseModel
        The marker noise the learner works with: its prior, then its estimate
        (:mod:`~body_scheme_core.calibration.noise_model`).
    """

    config = _StateField()
    part_ids = _StateField()
    n_actions = _StateField()
    action_lower = _StateField()
    action_upper = _StateField()
    root = _StateField()
    step = _StateField()
    last_stamp = _StateField()
    rejected = _StateField()
    corrected = _StateField()
    noise = _StateField()

    def __init__(self, part_ids, n_actions, config=None, initial_models=None, action_lower=None, action_upper=None):
        config = check_config(BodySchemeConfig() if config is None else config)
        part_ids, n_actions = check_part_ids(part_ids), check_n_actions(n_actions)
        root = root_part(part_ids, config.root)
        if initial_models is None:
            check_body_size(len(part_ids), n_actions, config)
            max_dim = config.max_complexity
        else:
            models = check_initial_models(initial_models, part_ids, root, n_actions)
            # A replacement may keep the given models' action sets.
            max_dim = max([config.max_complexity] + [model.complexity for model in models])
        pool = ModelPool(config, n_actions)
        pool.gp_batch = pool.new_gp_batch(max_dim)
        if initial_models is None:
            Bootstrap.add_candidates(pool, part_ids, n_actions, config)
            tree = [] if len(part_ids) == 1 else None
        else:
            entries = pool.add_fitted(models, TREE, origin="initial", last_used=0)
            for entry in entries:
                if isinstance(entry.model, ChainModel):  # a specification's chain: its covariance, its prior
                    entry.prior = (entry.model.params_.copy(), entry.model.param_cov_.copy())
            tree = [entry.id for entry in entries]
        lower, upper = check_action_bounds(action_lower, action_upper, n_actions)
        self._state = LearnerState(config, part_ids, n_actions, lower, upper, root, pool, tree,
                                   bootstrapping=initial_models is None)
        self._state.bootstrap.found = initial_models is not None

    @property
    def state(self):
        """The learner's whole state (:class:`~body_scheme_core.learning.learner_state.LearnerState`), to read: what
        the state file saves (:meth:`to_state`) and the invariants check reads
        (:func:`~body_scheme_core.learning.learner_state.structural_problems`)."""
        return self._state

    # ------------------------------------------------------------------ queries
    @property
    def phase(self):
        """``"bootstrapping"``, ``"steady"`` or ``"adapting"`` (a tree edge is in mismatch)."""
        if self._state.bootstrapping:
            return "bootstrapping"
        return "adapting" if self._state.adaptation.mismatch else "steady"

    @property
    def n_candidates(self):
        """Number of models currently learning in the batches (bootstrap candidates or replacements)."""
        return self._state.pool.n_learning

    @property
    def n_raced(self):
        """Bootstrap candidates dropped by racing since this learner was built or loaded (``config.race_samples``)."""
        return self._state.bootstrap.raced

    @property
    def memory(self):
        """Remembered (retired) local models, oldest first."""
        return [e.model for e in self._state.pool.with_role(MEMORY)]

    @property
    def body_scheme(self):
        """The current body scheme (:class:`BodyScheme`), calibrated by the last joint fit; ``None`` while no valid
        spanning tree exists."""
        if self._state.tree is None:
            return None
        cal = self._state.calibrated
        if cal is not None and cal.tree == tuple(self._state.tree):
            return cal.scheme
        return self._state.raw_scheme()

    @property
    def root_pose(self):
        """Estimated ``world2root`` (4, 4): from the last joint fit, else :mod:`~body_scheme_core.learning.root_pose`.

        Before a joint fit: the rigid transform that best maps the body scheme's predicted marker positions onto the
        observed ones, or the robust mean of the root's own observations; identity while nothing was seen.
        """
        if self._state.calibrated is not None:
            return self._state.calibrated.world2root
        return self._state.root_pose.pose(self.body_scheme)

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
        a = check_action_vector(a, self.n_actions)
        world2root = self.root_pose
        if return_std:
            root2part, std = scheme.predict(a, return_std=True)
        else:
            root2part, std = scheme.predict(a), None
        world2part = {part: world2root @ T for part, T in root2part.items()}
        return (world2part, std) if return_std else world2part

    def trained_range(self):
        """``(lower, upper)`` (m,): the smallest and largest value of each action in the history (the joint fit's
        window), where the learned models are trustworthy; the action limits (or 0) while the history is empty."""
        if not self._state.history:
            lower = np.zeros(self.n_actions) if self.action_lower is None else np.nan_to_num(self.action_lower)
            upper = np.zeros(self.n_actions) if self.action_upper is None else np.nan_to_num(self.action_upper)
            return lower, upper
        A = np.stack([a for _, a, _ in self._state.history])
        return A.min(axis=0), A.max(axis=0)

    def samples(self):
        """The history window (the joint fit's data): ``(actions (n, m), observations)``, oldest first; e.g. to
        cross-validate the body scheme (:func:`~body_scheme_core.calibration.cross_validate`)."""
        A = np.array([a for _, a, _ in self._state.history], dtype=float).reshape(-1, self.n_actions)
        return A, [dict(obs) for _, _, obs in self._state.history]

    @property
    def consistency(self):
        """Per part, the lack-of-fit test of the last joint fit
        (:class:`~body_scheme_core.calibration.consistency.PartConsistency`:
        do its residuals depend on the commands?); empty before the first fit."""
        return {} if self._state.calibrated is None else dict(self._state.calibrated.consistency)

    @property
    def unexplained_parts(self):
        """Parts whose residuals at the last joint fit depend on the commands (the body scheme does not explain
        them), ascending."""
        return self._state.lack_of_fit

    @property
    def trusted(self):
        """Whether the body scheme can be relied on: one exists, bootstrapping is over, no edge is in mismatch, and
        the last joint fit explains every part (:attr:`unexplained_parts` is empty)."""
        return (self.body_scheme is not None and not self._state.bootstrapping and not self._state.adaptation.mismatch
                and not self._state.lack_of_fit)

    @property
    def fitted_at(self):
        """The step of the last joint fit and the tree it fitted, or None: changes exactly when the joint fit
        changes :attr:`body_scheme` without a new tree (e.g. to republish it)."""
        cal = self._state.calibrated
        return None if cal is None else (cal.step, cal.tree)

    @property
    def calibration_rms(self):
        """Root mean square normalised residual of the last joint fit (about 1 when the noise model holds), or NaN."""
        return math.nan if self._state.calibrated is None else self._state.calibrated.rms

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
        pool = self._state.pool
        by_pair = {frozenset((pool.tracked[i].parent, pool.tracked[i].child)): pool.tracked[i]
                   for i in self._state.tree}
        out = []
        for parent, child, model, _ in scheme.edges:
            entry = by_pair[frozenset((parent, child))]
            st, valid = pool.window_stats([entry.row], [pool.n_now(entry)])
            theta_t = float(st.theta_trans[0]) if st.n[0] else self.noise.theta_trans
            out.append({"parent": parent, "child": child, "model": entry.describe(), "model_id": entry.id,
                        "kind": model.kind,
                        "actions": list(model.actions), "n_test": int(st.n[0]), "trans_error": float(st.trans_error[0]),
                        "rot_error": float(st.rot_error[0]), "theta_trans": theta_t, "theta_rot": self.noise.theta_rot,
                        "valid": bool(valid[0]), "in_mismatch": entry.id in self._state.adaptation.mismatch,
                        "cusum": pool.monitor.cusum[entry.row].tolist()})
        return out

    # ------------------------------------------------------------------ the time step
    def update(self, actions, observations, stamp=None, covariances=None):
        """Process one time step: the action vector and the marker poses observed after executing it.

        Parameters
        ----------
        actions : array-like, shape (m,)
            The commanded action vector.
        observations : mapping of int to array-like, shape (4, 4)
            ``world2part`` per observed part; missing parts are normal. Invalid entries are rejected one by one.
        stamp : float, optional
            Time stamp, kept as :attr:`last_stamp`; not before the previous step's.
        covariances : mapping of int to array-like, shape (6, 6), optional
            Per observed part: its detection's own covariance over ``(x, y, z, rot_x, rot_y, rot_z)`` (a tag
            detector's, as in ``geometry_msgs/PoseWithCovariance``; all zeros: not estimated). The joint fit weighs
            the pose by it, times a scale it learns (:attr:`NoiseModel.detection_scale
            <body_scheme_core.calibration.NoiseModel.detection_scale>`); without one, by the learned per-marker noise.
            An unusable covariance is dropped and counted (``bad_covariance``), its pose kept.

        Returns
        -------
        events : list of Event

        Raises
        ------
        InvalidInputError
            If ``actions`` are not real numbers of the right shape or not finite, ``stamp`` is not a finite real
            number or goes back in time, or ``observations`` is not a mapping; the learner is then unchanged.
        LearnerStepError
            If the step failed inside the learner (a defect): it was undone, the learner is exactly as before the call
            (``step`` included) and the original error is the ``__cause__``; the next call may go on.

        Notes
        -----
        A step is all or nothing: the inputs are checked first, then everything the step may change is copied
        (:func:`~body_scheme_core.learning.learner_state.snapshot`: the candidates' arrays and the book-keeping, never
        the models or the recorded observations) and put back if it fails.
        """
        a = check_action_vector(actions, self.n_actions).copy()
        check_action_range(a, self.action_lower, self.action_upper, self.config.action_margin)
        check_observation_mapping(observations)
        filter_covariances(covariances, {})  # its type, before anything changes
        stamp = check_stamp(stamp, self.last_stamp)
        return self._all_or_nothing(lambda: time_step(self._state, a, observations, stamp, covariances),
                                    f"step {self.step}")

    def recalibrate(self):
        """Run the joint fit of the current tree and what follows it now, on the whole history window, instead of
        when it is next due (after samples taken on purpose, e.g.
        :func:`~body_scheme_core.control.exploration.explore_near`). All or nothing, as :meth:`update`: a failure is
        undone and raised as ``LearnerStepError``. Returns the events it raised (none before the first tree)."""
        if self._state.tree is None or self.step == 0:
            return []

        def run():
            events = []
            fit_and_check(self._state, self.step - 1, events)
            return events
        return self._all_or_nothing(run, f"the joint fit after step {self.step - 1}")

    def _all_or_nothing(self, run, what):
        """``run()``, undone if it fails (:func:`~body_scheme_core.learning.learner_state.snapshot`): an ``Exception``
        is raised as ``LearnerStepError`` with it as the ``__cause__``, anything else (``KeyboardInterrupt``) as it
        is."""
        with Journal() as journal:
            saved = snapshot(self._state)
            try:
                return run()
            except BaseException as error:
                restore(self._state, saved, journal)
                if not isinstance(error, Exception):
                    raise
                raise LearnerStepError(f"{what} failed and was undone: {type(error).__name__}: {error}") from error

    # ------------------------------------------------------------------ saved state (learning/state_file.py)
    def to_state(self):
        """Everything needed to continue bit-identically, as a JSON-serialisable dict
        (:func:`~body_scheme_core.learning.state_file.to_dict`)."""
        return to_dict(self._state)

    @classmethod
    def from_state(cls, state):
        """Rebuild a learner from :meth:`to_state` output (:func:`~body_scheme_core.learning.state_file.from_dict`;
        ``ModelFileError`` if it is not one)."""
        learner = cls.__new__(cls)
        learner._state = from_dict(state)
        return learner

    def __repr__(self):
        return (f"<BodySchemeLearner parts={self.part_ids} actions={self.n_actions} phase={self.phase} "
                f"step={self.step}>")
