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
This module orchestrates the time step; the pieces live in :mod:`~body_scheme_core.learning.inputs` (validation),
:mod:`~body_scheme_core.learning.relative` and :mod:`~body_scheme_core.learning.chain` (targets),
:mod:`~body_scheme_core.learning.pool` (tracked models and their prequential evaluation),
:mod:`~body_scheme_core.learning.bootstrap`, :mod:`~body_scheme_core.learning.adaptation` (change detection, memory,
repair), :mod:`~body_scheme_core.calibration.joint_fit` (the joint fit) and :mod:`~body_scheme_core.learning.root_pose`
(the root pose before the first fit). ``docs/core/learning-and-adaptation.md`` describes every rule and default and how
they differ from the paper.
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np

from ..calibration import NoiseModel
from ..errors import BodySchemeError, LearnerStepError, NotFittedError
from ..events import Event, format_errors
from ..models import ChainModel, GPModel, RigidJointModel
from ..prediction import BodyScheme
from ..transforms import invert_transform
from .adaptation import Adaptation
from .bootstrap import Bootstrap
from .chain import ChainTargets
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
    filter_observations,
    root_part,
)
from .learner_fit import JointFitSteps
from .learner_state import learner_from_state, learner_to_state, restore, snapshot
from .mirrors import MIRROR_BLOCK, MirrorWatch, decide_flips, rechosen_history
from .pool import ModelPool
from .relative import PartPairs
from .root_pose import RootPoseEstimator, RootWatch, still_part
from .tracked import MEMORY, TREE, Journal

__all__ = ["BodySchemeLearner", "PHASES"]

#: Phases reported by :attr:`BodySchemeLearner.phase`.
PHASES = ("bootstrapping", "steady", "adapting")
class BodySchemeLearner(JointFitSteps):
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

    def __init__(self, part_ids, n_actions, config=None, initial_models=None, action_lower=None, action_upper=None):
        config = check_config(BodySchemeConfig() if config is None else config)
        self._set_parts(config, check_part_ids(part_ids), check_n_actions(n_actions))
        self.action_lower, self.action_upper = check_action_bounds(action_lower, action_upper, self.n_actions)
        self.step = 0
        self.last_stamp = None
        self.rejected = Counter()
        self.corrected = Counter()
        self._history = deque(maxlen=config.history_length)
        self._covariances = {}  # step -> {part: (6, 6)}: the detections' own covariances of steps in the history
        self._root_pose = RootPoseEstimator(config.root_window, self.root)
        if initial_models is None:
            check_body_size(len(self.part_ids), self.n_actions, config)
            max_dim = config.max_complexity
        else:
            models = check_initial_models(initial_models, self.part_ids, self.root, self.n_actions)
            # A replacement may keep the given models' action sets.
            max_dim = max([config.max_complexity] + [model.complexity for model in models])
        pool = ModelPool(config, self.n_actions)
        pool.gp_batch = pool.new_gp_batch(max_dim)
        if initial_models is None:
            Bootstrap.add_candidates(pool, self.part_ids, self.n_actions, config)
            tree = [] if len(self.part_ids) == 1 else None
        else:
            entries = pool.add_fitted(models, TREE, origin="initial", last_used=0)
            for entry in entries:
                if isinstance(entry.model, ChainModel):  # a specification's chain: its covariance, its prior
                    entry.prior = (entry.model.params_.copy(), entry.model.param_cov_.copy())
            tree = [entry.id for entry in entries]
        self._set_models(pool, tree, bootstrapping=initial_models is None, found=initial_models is not None,
                         tree_since=0, mismatch=None, calibrated=None)

    def _set_parts(self, config, parts, n_actions):
        self.config = config
        self.part_ids = parts
        self.n_actions = n_actions
        self.root = root_part(parts, config.root)
        self.noise = NoiseModel.from_config(parts, config)
        self._pairs = PartPairs(parts, self.noise, exact=(self.root,) if config.sensor_root else (),
                                mirrors=config.mirror_hypotheses)

    def _set_models(self, pool, tree, bootstrapping, found, tree_since, mismatch, calibrated, vetoed=None,
                    refining=None, unexplained=None, lack_of_fit=(), failed=None, root_watch=None, root_since=0,
                    mirror_watch=None):
        """Install the tracked models and the phase objects working on them (shared by construction and restore)."""
        self._pool = pool
        self._tree = tree
        self._bootstrapping = bootstrapping
        self._bootstrap = Bootstrap(self.config, pool, self._pairs, found, tree_since, vetoed, self._history)
        self._adaptation = Adaptation(self.config, pool, self._history, self.part_ids, mismatch, refining, failed)
        self._calibrated = calibrated
        self._reach = None  # (the Calibrated it belongs to, reach in m) cache: see _workspace
        self._prediction = None  # (the Calibrated it belongs to, world2part at this step) cache: see _predicted
        self._just_finished = False
        self._unexplained = {} if unexplained is None else dict(unexplained)  # part -> step it was last flagged
        self._lack_of_fit = tuple(lack_of_fit)  # parts of the last joint fit whose residuals depend on the commands
        self._root_watch = RootWatch(self.config) if root_watch is None else root_watch
        self._root_since = int(root_since)  # first step of the root's own observations in the joint fit
        self._mirror_watch = MirrorWatch() if mirror_watch is None else mirror_watch  # see learning/mirrors.py
        pool.monitor.set_thresholds(self.noise.theta_trans, self.noise.theta_rot)

    # ------------------------------------------------------------------ queries
    @property
    def phase(self):
        """``"bootstrapping"``, ``"steady"`` or ``"adapting"`` (a tree edge is in mismatch)."""
        if self._bootstrapping:
            return "bootstrapping"
        return "adapting" if self._adaptation.mismatch else "steady"

    @property
    def n_candidates(self):
        """Number of models currently learning in the batches (bootstrap candidates or replacements)."""
        return self._pool.n_learning

    @property
    def n_raced(self):
        """Bootstrap candidates dropped by racing since this learner was built or loaded (``config.race_samples``)."""
        return self._bootstrap.raced

    @property
    def memory(self):
        """Remembered (retired) local models, oldest first."""
        return [e.model for e in self._pool.with_role(MEMORY)]

    @property
    def body_scheme(self):
        """The current body scheme (:class:`BodyScheme`), calibrated by the last joint fit; ``None`` while no valid
        spanning tree exists."""
        if self._tree is None:
            return None
        cal = self._calibrated
        if cal is not None and cal.tree == tuple(self._tree):
            return cal.scheme
        return self._raw_scheme()

    def _raw_scheme(self):
        """The tree's models as tracked (candidate snapshots while bootstrapping), not yet jointly refitted."""
        return BodyScheme(self.part_ids, self.root, [self._pool.model_of(self._pool.tracked[i]) for i in self._tree])

    @property
    def root_pose(self):
        """Estimated ``world2root`` (4, 4): from the last joint fit, else :mod:`~body_scheme_core.learning.root_pose`.

        Before a joint fit: the rigid transform that best maps the body scheme's predicted marker positions onto the
        observed ones, or the robust mean of the root's own observations; identity while nothing was seen.
        """
        if self._calibrated is not None:
            return self._calibrated.world2root
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
        if not self._history:
            lower = np.zeros(self.n_actions) if self.action_lower is None else np.nan_to_num(self.action_lower)
            upper = np.zeros(self.n_actions) if self.action_upper is None else np.nan_to_num(self.action_upper)
            return lower, upper
        A = np.stack([a for _, a, _ in self._history])
        return A.min(axis=0), A.max(axis=0)

    def samples(self):
        """The history window (the joint fit's data): ``(actions (n, m), observations)``, oldest first; e.g. to
        cross-validate the body scheme (:func:`~body_scheme_core.calibration.cross_validate`)."""
        A = np.array([a for _, a, _ in self._history], dtype=float).reshape(-1, self.n_actions)
        return A, [dict(obs) for _, _, obs in self._history]

    @property
    def consistency(self):
        """Per part, the lack-of-fit test of the last joint fit
        (:class:`~body_scheme_core.calibration.consistency.PartConsistency`:
        do its residuals depend on the commands?); empty before the first fit."""
        return {} if self._calibrated is None else dict(self._calibrated.consistency)

    @property
    def unexplained_parts(self):
        """Parts whose residuals at the last joint fit depend on the commands (the body scheme does not explain
        them), ascending."""
        return self._lack_of_fit

    @property
    def trusted(self):
        """Whether the body scheme can be relied on: one exists, bootstrapping is over, no edge is in mismatch, and
        the last joint fit explains every part (:attr:`unexplained_parts` is empty)."""
        return (self.body_scheme is not None and not self._bootstrapping and not self._adaptation.mismatch
                and not self._lack_of_fit)

    @property
    def fitted_at(self):
        """The step of the last joint fit and the tree it fitted, or None: changes exactly when the joint fit
        changes :attr:`body_scheme` without a new tree (e.g. to republish it)."""
        cal = self._calibrated
        return None if cal is None else (cal.step, cal.tree)

    @property
    def calibration_rms(self):
        """Root mean square normalised residual of the last joint fit (about 1 when the noise model holds), or NaN."""
        return math.nan if self._calibrated is None else self._calibrated.rms

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
        for parent, child, model, _ in scheme.edges:
            entry = by_pair[frozenset((parent, child))]
            st, valid = pool.window_stats([entry.row], [pool.n_now(entry)])
            theta_t = float(st.theta_trans[0]) if st.n[0] else self.noise.theta_trans
            out.append({"parent": parent, "child": child, "model": entry.describe(), "model_id": entry.id,
                        "kind": model.kind,
                        "actions": list(model.actions), "n_test": int(st.n[0]), "trans_error": float(st.trans_error[0]),
                        "rot_error": float(st.rot_error[0]), "theta_trans": theta_t, "theta_rot": self.noise.theta_rot,
                        "valid": bool(valid[0]), "in_mismatch": entry.id in self._adaptation.mismatch,
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
        with Journal() as journal:
            saved = snapshot(self, journal)
            try:
                return self._step(a, observations, stamp, covariances)
            except BaseException as error:
                restore(self, saved)
                if not isinstance(error, Exception):
                    raise  # KeyboardInterrupt, SystemExit: undone, and passed on as they are
                raise LearnerStepError(f"step {self.step} failed and was undone: {type(error).__name__}: "
                                       f"{error}") from error

    def _step(self, a, observations, stamp, covariances=None):
        """The time step proper, on checked inputs (:meth:`update`)."""
        step = self.step
        events = []
        self._prediction = None
        obs, mirrored, mirror_learned = self._accept(a, observations, step, events)
        covs = self._accept_covariances(covariances, obs, step, events)
        for part in mirrored:  # its detection's covariance is the other solution's
            covs.pop(part, None)
        if self.config.sensor_root:
            obs[self.root] = np.eye(4)  # the root is the sensor: its own pose in its frame, exactly
            covs.pop(self.root, None)
        if stamp is not None:
            self.last_stamp = stamp
        self._root_pose.add(a, obs)
        self._history.append((step, a, obs))
        if covs:
            self._covariances[step] = covs
        oldest = self._history[0][0]
        while self._covariances and next(iter(self._covariances)) < oldest:
            del self._covariances[next(iter(self._covariances))]
        if self._bootstrapping:
            tree_changed = self._bootstrap_step(a, obs, step, events)
        else:
            tree_changed = self._adapt_step(a, obs, step, events)
        if mirror_learned:
            self._undo_mirror(mirror_learned, step, events)
        if self._tree is not None and (tree_changed or mirror_learned or self._calibration_due(step)):
            self._fit_and_check(step, events)
        self._just_finished = False
        self.step = step + 1
        return events

    def _accept(self, a, observations, step, events):
        """The valid observations ``{part: world2part}``, the parts taken in as their mirror image and the parts whose
        mirror image the body scheme holds (:class:`~body_scheme_core.learning.mirrors.MirrorWatch`); rejected ones
        are counted and reported."""
        valid, rejections = filter_observations(observations, self.part_ids, self.config.max_distance,
                                                self._workspace())
        for part, reason, detail in rejections:
            self.rejected[reason] += 1
            events.append(Event(step, "input_rejected", f"observation rejected ({reason}): {detail}", child=part))
        cal = self._calibrated
        if cal is None:
            return valid, [], []
        flips = decide_flips(self._predicted(cal, a), valid, self.noise.theta_rot, self.noise.theta_trans,
                             eager=self.config.mirror_hypotheses)
        if flips.mirrored:  # (a counter gains a key only when it counts something)
            self.corrected["flipped"] += len(flips.mirrored)
        if flips.refused:
            self.rejected["flipped"] += len(flips.refused)
        events += [Event(step, "input_rejected", f"observation rejected (flipped): {detail}", child=part)
                   for part, detail in flips.refused]
        return flips.observations, flips.mirrored, self._mirror_watch.record(flips.judged, flips.mirrored)

    def _undo_mirror(self, parts, step, events):
        """The body scheme holds the mirror image of ``parts``: every stored pose of each is chosen again against the
        mirror of the prediction (:func:`~body_scheme_core.learning.mirrors.rechosen_history`), its detection
        covariance dropped where the pose changed (it is the other solution's), and a ``mirror_undone`` event is
        reported; the caller fits again."""
        cal = self._calibrated
        records, covariances = list(self._history), self._covariances
        for part in parts:
            column = cal.scheme.parts.index(part)
            records, covariances, changed, stored = rechosen_history(
                records, covariances, part, lambda A, c=column: cal.world2root @ cal.scheme.predict_batch(A)[:, c])
            events.append(Event(step, "mirror_undone", f"part {part} was taken in mirrored in more than half of its "
                                f"last {MIRROR_BLOCK} observations: the body scheme held its mirror image; "
                                f"{changed} of its {stored} stored poses chosen again", child=part))
        self._history.clear()
        self._history.extend(records)  # in place: the deque is shared with the phase objects
        self._covariances = covariances

    def _accept_covariances(self, covariances, obs, step, events):
        """The usable covariances of the accepted observations ``obs``; dropped ones are counted and reported."""
        if not self.config.detection_covariances:
            return {}
        usable, rejections = filter_covariances(covariances, obs)
        for part, reason, detail in rejections:
            self.rejected[reason] += 1
            events.append(Event(step, "input_rejected", f"covariance rejected ({reason}): {detail}", child=part))
        return usable

    def _predicted(self, cal, a):
        """``{part: world2part}`` the joint fit ``cal`` predicts at this step's actions ``a``, computed once per step
        and fit (the flip check and the chain targets both need it; :meth:`_step` forgets it first)."""
        if self._prediction is None or self._prediction[0] is not cal:
            self._prediction = (cal, {p: cal.world2root @ T for p, T in cal.scheme.predict(a).items()})
        return self._prediction[1]

    def _workspace(self):
        """``(root position, reach + workspace_margin)`` once a joint fit exists after bootstrapping, else None (only
        ``max_distance`` applies). The reach is the largest root-to-part distance the calibrated scheme predicts over
        the history's actions, computed once per joint fit."""
        cal = self._calibrated
        if cal is None or self._bootstrapping or not math.isfinite(self.config.workspace_margin):
            return None  # a provisional body scheme's reach says little (a wrong tree's may be short)
        if self._reach is None or self._reach[0] is not cal:
            A = np.stack([a for _, a, _ in self._history]) if self._history else np.zeros((1, self.n_actions))
            root2part = cal.scheme.predict_batch(A)
            self._reach = (cal, float(np.linalg.norm(root2part[:, :, :3, 3], axis=-1).max()))
        return cal.world2root[:3, 3], self._reach[1] + self.config.workspace_margin

    def _bootstrap_step(self, a, obs, step, events):
        """Search the tree over the candidates, then end bootstrapping if it is ready; returns whether the tree
        changed (the joint fit then runs at once)."""
        before = self._tree
        self._tree, _ = self._bootstrap.step(self._tree, a, self._pairs.observe(obs), step, events)
        if self._tree is not None and self._choose_root():
            return True  # a new root: the tree is fitted afresh
        if self._bootstrap.finish_if_ready(self._tree, step, events):
            self._bootstrapping = False
            self._just_finished = True
            for entry in (self._pool.tracked[i] for i in self._tree):
                entry.since = 0
            return True
        return self._tree is not None and (before is None or set(before) != set(self._tree))

    def _choose_root(self):
        """Without ``config.root``: make the part whose observations move least the root, as the joint fit assumes
        the root is fixed in the camera's view (:func:`still_part`). Returns whether the root changed."""
        if self.config.root is not None:
            return False
        root = still_part(self.part_ids, [obs for _, _, obs in self._history], self.noise.sigma_trans,
                          self.noise.sigma_rot)
        if root is None or root == self.root:
            return False
        self.root = self._root_pose.root = root
        self._root_pose.invalidate()
        self._root_watch.restart()
        self._root_since = 0
        self._calibrated = None  # its root pose belongs to the old root
        return True

    def _adapt_step(self, a, obs, step, events):
        """Evaluate, detect and repair against the chain-consistent targets; returns whether the tree changed."""
        if self._calibrated is None or self._calibrated.tree != tuple(self._tree):
            # A given scheme: its first joint fit (the root pose) before anything is tested.
            self._calibrate(step, events)
        scheme, world2root = self._calibrated.scheme, self._calibrated.world2root
        untrusted = self._untrusted_parts(scheme)
        noise = self.noise
        part_std = self._calibrated.part_std

        def chain_at(a_past, obs_past):
            return ChainTargets(scheme, world2root, a_past, obs_past, noise, untrusted, part_std)

        targets = ChainTargets(scheme, world2root, a, obs, noise, untrusted, part_std,
                               self._predicted(self._calibrated, a))
        changes = self._adaptation.step(self._tree, self.root, a, targets, chain_at, step, events)
        for change in changes:
            self._after_change(change)
        seen, expected = obs.get(self.root), self._root_watch.expected(world2root)
        errors = None if seen is None or expected is None else targets.observed_errors(expected, seen)
        moved = self._root_watch.check(errors, step, noise.theta_trans, noise.theta_rot)
        self._root_watch.learn_offset(world2root, seen)
        if moved is not None:
            self._root_moved(*moved, step, events)
        return bool(changes) or moved is not None

    def _root_moved(self, tau, cusum, stats, step, events):
        """The root's observations left the calibrated root pose at ``tau`` (its marker moved on the base, or was
        knocked): the root's own observations count from ``tau`` on, the edges at the root learn their new relation
        without a prior, and every edge's detector restarts (its targets used the old root pose)."""
        self._root_since = tau
        pool = self._pool
        for i in self._tree:
            entry = pool.tracked[i]
            if self.root in (entry.parent, entry.child) and isinstance(entry.model, RigidJointModel):
                entry.prior = None
            pool.monitor.forget_since([entry.row], tau)
            pool.monitor.reset_cusum([entry.row])
        events.append(Event(step, "mismatch_detected",
                            f"the root part {self.root} no longer matches its pose in the camera's view: CUSUM "
                            f"{cusum[0]:.2f} (trans) / {cusum[1]:.2f} (rot) reached {self.config.cusum_threshold:g}; "
                            f"window mean {format_errors(stats.trans_error[0], stats.rot_error[0])}; change point "
                            f"estimated at step {tau}: its marker moved; the root pose and the edges at the root are "
                            f"fitted again from its observations since then", child=self.root, model="root pose"))

    def _chain_at(self):
        """``chain_at(a, observations)``: the chain-consistent targets of a step from the current joint fit."""
        cal = self._calibrated
        untrusted = self._untrusted_parts(cal.scheme)
        noise = self.noise

        def chain_at(a, obs):
            return ChainTargets(cal.scheme, cal.world2root, a, obs, noise, untrusted, cal.part_std)
        return chain_at

    def _sample_challengers(self, step, events):
        """After bootstrapping: GP challengers of the tree's rigid joints
        (:func:`~body_scheme_core.learning.challengers.sample_challengers`)."""
        if self._calibrated is None or self._calibrated.tree != tuple(self._tree):
            return
        chain_at = self._chain_at()
        _, a, obs = self._history[-1]
        self._adaptation.sample_challengers(self._tree, chain_at(a, obs), chain_at, step, events)

    def _untrusted_parts(self, scheme):
        """Parts whose predicted pose passes through an edge in mismatch (the subtree below it)."""
        parts = set()
        for edge_id in self._adaptation.mismatch:
            entry = self._pool.tracked[edge_id]
            _, far = scheme.from_root(entry.parent, entry.child)
            parts.update(p for p in scheme.parts if far in scheme.path(p))
        return parts

    def _after_change(self, change):
        """Book-keeping of a replaced or reinstated edge: change point, priors below it, cleaned memory."""
        pool = self._pool
        new, old, tau = change
        reinstated = new.origin not in ("replacement", "bridge") or new.n_train == 0 or new.last_used != self.step
        new.since = tau
        if isinstance(new.model, RigidJointModel) and reinstated and new.prior is None:
            new.prior = (new.model.params_.copy(), new.model.param_cov_.copy())
        scheme = self._raw_scheme()
        _, far = scheme.from_root(new.parent, new.child)
        for i in self._tree:
            entry = pool.tracked[i]
            if entry is new:
                continue
            near, _ = scheme.from_root(entry.parent, entry.child)
            if far in scheme.path(near):
                # Below the changed edge: its observations before tau followed the old body; keep what they taught
                # as a prior, and restart its detector. An edge out of the changed edge's far part after a
                # replacement gets none: its relation is to that part's marker, which may be what moved.
                if isinstance(entry.model, RigidJointModel):
                    if near == far and not reinstated:
                        entry.prior = None
                    elif entry.prior is None:
                        entry.prior = (entry.model.params_.copy(), entry.model.param_cov_.copy())
                pool.monitor.forget_since([entry.row], tau)
                pool.monitor.reset_cusum([entry.row])
        if old.id in pool.tracked:
            self._clean_retired(old, tau)

    def _clean_retired(self, entry, tau):
        """Refit a retired model on its own chain-consistent data before the change point (none after it)."""
        cal = self._calibrated
        if cal is None or not isinstance(entry.model, (RigidJointModel, GPModel)):
            return
        steps = [(s, a, obs) for s, a, obs in self._history if entry.since <= s < tau]
        if not steps:
            return
        scheme = cal.scheme
        u, v = scheme.from_root(entry.parent, entry.child)
        A, Z, S = [], [], []
        for _, a, obs in steps:
            chain = ChainTargets(scheme, cal.world2root, a, obs, self.noise, std=cal.part_std)
            if v in obs:
                Zk, _, _, sk = chain.pair_target(u, v)
                A.append(a)
                Z.append(Zk if u == entry.parent else invert_transform(Zk))
                S.append(sk)
        model = entry.model
        try:
            if isinstance(model, RigidJointModel) and len(A) >= max(model.form.MIN_SAMPLES, model.n_params // 2):
                entry.model = type(model)(model.parent, model.child, model.actions,
                                          **model._hyperparameters()).fit(np.array(A), np.array(Z), np.array(S))
                entry.prior = None
            elif isinstance(model, GPModel) and len(A) >= self.config.train_window // 2:
                entry.model = GPModel(model.parent, model.child, model.actions,
                                      **model.hyperparameters.to_dict()).fit(np.array(A), np.array(Z))
        except (BodySchemeError, np.linalg.LinAlgError):
            pass  # keep the model as it was

    # ------------------------------------------------------------------ state (body_scheme_core.learning.learner_state)
    def to_state(self):
        """Everything needed to continue bit-identically, as a JSON-serialisable dict (:func:`learner_to_state`)."""
        return learner_to_state(self)

    @classmethod
    def from_state(cls, state):
        """Rebuild a learner from :meth:`to_state` output (:func:`learner_from_state`)."""
        return learner_from_state(cls, state)

    def __repr__(self):
        return (f"<BodySchemeLearner parts={self.part_ids} actions={self.n_actions} phase={self.phase} "
                f"step={self.step}>")
