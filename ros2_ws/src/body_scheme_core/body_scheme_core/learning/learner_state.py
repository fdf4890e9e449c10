"""The learner's state in memory: every field once (:class:`LearnerState`), and what is derived from that list.

:func:`snapshot` and :func:`restore` copy what one time step may change and put it back, so that
:meth:`~body_scheme_core.learning.learner.BodySchemeLearner.update` either applies a whole step or none of it; each
field says how (its ``undo`` metadata). :func:`structural_problems` is the invariants check of a loaded state and of
every step of the stress test. The state as a JSON dict is :mod:`~body_scheme_core.learning.state_file`; each field
names the keys it is saved under (its ``file`` metadata), and a test holds the two to each other.
"""

from __future__ import annotations

import dataclasses
from collections import Counter, deque
from typing import NamedTuple

import numpy as np

from ..calibration import NoiseModel
from ..prediction import BodyScheme
from .adaptation import Adaptation
from .bootstrap import Bootstrap
from .chain import ChainTargets
from .config import BodySchemeConfig
from .mirrors import MirrorWatch
from .pool import ModelPool
from .relative import PartPairs
from .root_pose import RootPoseEstimator, RootWatch

__all__ = ["Calibrated", "LearnerState", "snapshot", "restore", "structural_problems"]

#: How :func:`snapshot` keeps a field and :func:`restore` puts it back (a field's ``undo`` metadata):
#: ``fixed`` - set at construction, never changed (not copied); ``value`` - immutable, replaced by a step (kept as
#: is); ``copy`` - a container a step changes (its ``copy()`` kept and put back); ``in_place`` - shared by reference
#: with other objects (its copy written back into the same object); ``own`` - an object with its own ``snapshot()`` and
#: ``restore(saved)``.
UNDO = ("fixed", "value", "copy", "in_place", "own")


def _field(undo, file=(), **kwargs):
    """A :class:`LearnerState` field kept by ``undo`` (:data:`UNDO`) and saved under the state-file keys ``file``."""
    return dataclasses.field(metadata={"undo": undo, "file": tuple(file)}, **kwargs)


class Calibrated(NamedTuple):
    """The last joint fit: the calibrated body scheme, the root pose, what it was computed from, per part
    ``(n, trans ratio, rot ratio)`` of its observations (:meth:`Calibration.part_ratios`), its predicted std, and its
    lack-of-fit test (:class:`~body_scheme_core.calibration.consistency.PartConsistency`)."""

    scheme: BodyScheme
    world2root: np.ndarray
    step: int
    n_steps: int
    tree: tuple
    rms: float
    part_ratios: dict
    part_std: dict
    consistency: dict


@dataclasses.dataclass(eq=False)
class LearnerState:
    """Everything a :class:`~body_scheme_core.learning.learner.BodySchemeLearner` holds, each field once.

    The fields left ``None`` are built from the others (the phase objects work on the same pool, history and part
    pairs).
    """

    # What the learner was built with.
    config: BodySchemeConfig = _field("fixed", ["config"])
    part_ids: tuple = _field("fixed", ["part_ids"])
    n_actions: int = _field("fixed", ["n_actions"])
    action_lower: np.ndarray | None = _field("fixed", ["action_lower"])
    action_upper: np.ndarray | None = _field("fixed", ["action_upper"])
    root: int = _field("value", ["root"])
    #: The tracked models (tree, memory, candidates), their batches and validity monitor.
    pool: ModelPool = _field("own", ["next_id", "entries", "monitor", "gp_batch", "rigid_batch"])
    #: Ids of the tree's models (candidates' while bootstrapping); None while no valid tree exists.
    tree: list | None = _field("copy", ["tree"])
    bootstrapping: bool = _field("value", ["bootstrapping"])
    #: The marker noise, prior then estimate; the part pairs read it.
    noise: NoiseModel | None = _field("in_place", ["noise"], default=None)
    pairs: PartPairs | None = _field("fixed", default=None)
    step: int = _field("value", ["step"], default=0)
    last_stamp: float | None = _field("value", ["last_stamp"], default=None)
    rejected: Counter = _field("copy", ["rejected"], default_factory=Counter)
    corrected: Counter = _field("copy", ["corrected"], default_factory=Counter)
    #: ``(step, actions, {part: world2part})`` of the last ``history_length`` steps: the joint fit's window and the
    #: replays' data, shared with the phase objects.
    history: deque | None = _field("in_place", ["history"], default=None)
    #: ``{step: {part: (6, 6)}}``: the detections' own covariances of steps in the history.
    covariances: dict = _field("copy", ["history"], default_factory=dict)
    root_pose: RootPoseEstimator | None = _field("own", ["root_samples"], default=None)
    bootstrap: Bootstrap | None = _field("own", ["found", "tree_since", "vetoed"], default=None)
    adaptation: Adaptation | None = _field("own", ["mismatch", "refining", "failed"], default=None)
    calibrated: Calibrated | None = _field("value", ["calibration"], default=None)
    #: Bootstrapping ended in this step (the GP challengers are sampled after its joint fit).
    just_finished: bool = _field("value", default=False)
    #: ``{part: step}`` a part the joint fit does not explain last put its edge in mismatch.
    unexplained: dict = _field("copy", ["unexplained"], default_factory=dict)
    #: Parts of the last joint fit whose residuals depend on the commands.
    lack_of_fit: tuple = _field("value", ["lack_of_fit"], default=())
    root_watch: RootWatch | None = _field("own", ["root_watch", "root_offset"], default=None)
    #: First step of the root's own observations in the joint fit.
    root_since: int = _field("value", ["root_since"], default=0)
    mirror_watch: MirrorWatch = _field("copy", ["mirror_watch"], default_factory=MirrorWatch)
    #: Caches: ``(the Calibrated it belongs to, reach in m)`` and ``(the Calibrated, world2part at this step)``.
    reach: tuple | None = _field("value", default=None)
    prediction: tuple | None = _field("value", default=None)

    def __post_init__(self):
        c = self.config
        if self.noise is None:
            self.noise = NoiseModel.from_config(self.part_ids, c)
        if self.pairs is None:
            self.pairs = PartPairs(self.part_ids, self.noise, exact=(self.root,) if c.sensor_root else (),
                                   mirrors=c.mirror_hypotheses)
        if self.history is None:
            self.history = deque(maxlen=c.history_length)
        if self.root_pose is None:
            self.root_pose = RootPoseEstimator(c.root_window, self.root)
        if self.root_watch is None:
            self.root_watch = RootWatch(c)
        if self.bootstrap is None:
            self.bootstrap = Bootstrap(c, self.pool, self.pairs, history=self.history)
        if self.adaptation is None:
            self.adaptation = Adaptation(c, self.pool, self.history, self.part_ids)
        self.share_thresholds()

    def share_thresholds(self):
        """Hand the noise model's validity thresholds on to the pool's monitor."""
        self.pool.monitor.set_thresholds(self.noise.theta_trans, self.noise.theta_rot)

    def raw_scheme(self):
        """The tree's models as tracked (candidate snapshots while bootstrapping), not yet jointly refitted."""
        return BodyScheme(self.part_ids, self.root, [self.pool.model_of(self.pool.tracked[i]) for i in self.tree])

    def untrusted_parts(self, scheme):
        """Parts whose predicted pose passes through an edge in mismatch (the subtree below it) in ``scheme``."""
        parts = set()
        for edge_id in self.adaptation.mismatch:
            entry = self.pool.tracked[edge_id]
            _, far = scheme.from_root(entry.parent, entry.child)
            parts.update(p for p in scheme.parts if far in scheme.path(p))
        return parts

    def chain_at(self):
        """``chain_at(a, observations)``: the chain-consistent targets of a step from the last joint fit."""
        cal, noise = self.calibrated, self.noise
        untrusted = self.untrusted_parts(cal.scheme)

        def chain_at(a, obs):
            return ChainTargets(cal.scheme, cal.world2root, a, obs, noise, untrusted, cal.part_std)
        return chain_at


#: ``(field name, undo policy)`` of every :class:`LearnerState` field, in order (``dataclasses.fields`` costs 10 us a
#: call, and a snapshot is taken every step).
_UNDO = tuple((f.name, f.metadata["undo"]) for f in dataclasses.fields(LearnerState))


def snapshot(state):
    """Everything one :meth:`~body_scheme_core.learning.learner.BodySchemeLearner.update` may change, copied.

    Local models, the calibrated scheme and the recorded observations are never changed in place (a step replaces
    them), so they are shared, not copied; what is copied is the book-keeping around them, field by field as each
    field's ``undo`` says. Changes to the tracked models' entries are not copied: an open
    :class:`~body_scheme_core.learning.tracked.Journal` records them (far cheaper than copying thousands of entries
    every step), and :func:`restore` undoes it.
    """
    saved = {}
    for name, undo in _UNDO:
        value = getattr(state, name)
        if undo == "value":
            saved[name] = value
        elif undo in ("copy", "in_place"):
            saved[name] = None if value is None else value.copy()
        elif undo == "own":
            saved[name] = value.snapshot()
    return saved


def restore(state, fields, journal):
    """Put back a :func:`snapshot` ``fields`` and undo ``journal`` (the tracked models' entries, journaled since the
    snapshot): the state is as it was when it was taken."""
    journal.undo()
    for name, undo in _UNDO:
        if undo in ("value", "copy"):
            setattr(state, name, fields[name])
        elif undo == "in_place":
            value = getattr(state, name)
            if isinstance(value, deque):
                value.clear()
                value.extend(fields[name])
            else:
                vars(value).update(vars(fields[name]))
        elif undo == "own":
            getattr(state, name).restore(fields[name])


def structural_problems(state):
    """What is wrong with the learner's structure, as a list of sentences (empty when it is sound).

    The tree spans the parts with tracked tree models; every model in the tree, in memory, in mismatch or refining is
    tracked; monitor rows and batch slots belong to exactly one tracked model each; the root is a part, the same for
    every object that uses it; the history's steps increase and come before the learner's step. Checked when a state
    is loaded, and after every step by the tests.
    """
    problems = []
    pool = state.pool
    tracked = pool.tracked
    parts = set(state.part_ids)
    tree = state.tree
    if tree is not None:
        if len(tree) != len(parts) - 1 or len(set(tree)) != len(tree):
            problems.append(f"the tree has {len(tree)} models for {len(parts)} parts")
        missing = [i for i in tree if i not in tracked]
        if missing:
            problems.append(f"tree models {missing} are not tracked")
        else:
            role = "candidate" if state.bootstrapping else "tree"  # bootstrapping: the tree is of candidates
            if any(tracked[i].role != role for i in tree):
                problems.append(f"a tree model is not in the {role} role")
            graph = {p: set() for p in parts}
            for i in tree:
                e = tracked[i]
                graph.setdefault(e.parent, set()).add(e.child)
                graph.setdefault(e.child, set()).add(e.parent)
            seen, stack = set(), [state.root]
            while stack:
                p = stack.pop()
                if p not in seen:
                    seen.add(p)
                    stack.extend(graph.get(p, ()))
            if seen != parts or set(graph) != parts:
                problems.append(f"the tree does not span the parts: reaches {sorted(seen)} of {sorted(parts)}")
    in_tree = set(tree or ())
    strays = [e.id for e in tracked.values() if e.role == "tree" and e.id not in in_tree]
    if strays:
        problems.append(f"models {strays} are in the tree role but not in the tree")
    for name, ids in (("mismatch", state.adaptation.mismatch), ("refining", state.adaptation.refining),
                      ("vetoed", state.bootstrap.vetoed)):
        unknown = [i for i in ids if i not in tracked]
        if unknown:
            problems.append(f"{name} refers to untracked models {unknown}")
    if any(i not in in_tree for i in state.adaptation.mismatch):
        problems.append("an edge in mismatch is not in the tree")
    rows = [e.row for e in tracked.values()]
    if len(set(rows)) != len(rows) or int(np.count_nonzero(pool.monitor.in_use)) != len(rows) or any(
            not (0 <= r < pool.monitor.capacity and pool.monitor.in_use[r]) for r in rows):
        problems.append("monitor rows and tracked models do not match one to one")
    for batch, rigid in ((pool.gp_batch, False), (pool.rigid_batch, True)):
        slots = [e.slot for e in tracked.values() if e.slot >= 0 and (e.kind in ("static", "prismatic", "revolute"))
                 == rigid]
        if len(set(slots)) != len(slots) or batch.n_allocated != len(slots) or any(
                not batch.is_allocated(s) for s in slots):
            problems.append(f"{'rigid' if rigid else 'GP'} batch slots and learning models do not match one to one")
    if state.root not in parts or state.root_pose.root != state.root:
        problems.append(f"the root {state.root} is not the same everywhere or not a part")
    steps = [s for s, _, _ in state.history]
    if any(b <= a for a, b in zip(steps, steps[1:], strict=False)) or (steps and steps[-1] >= state.step):
        problems.append("the history's steps do not increase up to the learner's step")
    if not set(state.covariances) <= set(steps) or any(
            not set(covs) <= set(obs) for s, _, obs in state.history if (covs := state.covariances.get(s))):
        problems.append("detection covariances of steps or parts the history does not hold")
    return problems
