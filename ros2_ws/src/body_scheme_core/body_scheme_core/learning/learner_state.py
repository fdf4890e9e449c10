"""The learner's state: as a JSON dict and back (saved state), and in memory (the snapshot that makes a step atomic).

Files (atomic writes, strict JSON reading) are :mod:`body_scheme_core.learning.persistence`; the layout is documented in
docs/core/state-file-format.md. Reading validates every value: a bad dict raises ``ModelFileError``, never a crash
later on. :func:`snapshot` and :func:`restore` copy what one time step may change and put it back, so that
:meth:`~body_scheme_core.learning.learner.BodySchemeLearner.update` either applies a whole step or none of it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections import Counter, deque
from typing import NamedTuple

import numpy as np

from ..calibration import PartConsistency
from ..errors import BodySchemeError, InvalidInputError, ModelFileError
from ..limits import MAX_COORDINATE
from ..prediction import BodyScheme
from ..state_values import boolean, finite_array, integer, listing, mapping, number, optional_number, part_id
from .config import BodySchemeConfig
from .detection import mismatch_from_state, mismatch_state
from .inputs import check_action_vector, check_n_actions, check_part_ids, filter_covariances, rigidity_problem
from .mirrors import MirrorWatch
from .pool import ModelPool, check_monitor_settings
from .repair import failed_from_state, failed_state, refining_from_state, refining_state
from .root_pose import RootPoseEstimator, RootWatch
from .validity import ValidityMonitor

__all__ = ["STATE_VERSION", "Calibrated", "learner_to_state", "learner_from_state", "snapshot", "restore",
           "structural_problems"]

#: Version of the dict layout of :func:`learner_to_state`.
STATE_VERSION = 4  # 4: the learned noise and the lack-of-fit test; 3: rigid-joint models, two candidate batches, the
#                    joint fit; 2: GP-only learner


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



def learner_to_state(self):
    """Everything needed to continue bit-identically, as a JSON-serialisable dict.

    Covers the configuration, parts, step, all tracked models (tree, memory, candidates) with their test
    windows and CUSUMs, both candidate batches, the last joint fit, the raw history, the root samples and the
    counters.
    """
    cal = self._calibrated
    return {
        "version": STATE_VERSION,
        "config": self.config.to_dict(),
        "part_ids": list(self.part_ids),
        "root": self.root,
        "n_actions": self.n_actions,
        "action_lower": _bounds_to_json(self.action_lower),
        "action_upper": _bounds_to_json(self.action_upper),
        "step": self.step,
        "last_stamp": self.last_stamp,
        "rejected": dict(self.rejected),
        "corrected": dict(self.corrected),
        "bootstrapping": self._bootstrapping,
        "found": self._bootstrap.found,
        "tree": None if self._tree is None else list(self._tree),
        "tree_since": self._bootstrap.tree_since,
        "next_id": self._pool.next_id,
        "entries": self._pool.tracked_state(),
        "mismatch": mismatch_state(self._adaptation.mismatch),
        "refining": refining_state(self._adaptation.refining),
        "failed": failed_state(self._adaptation.failed),
        "vetoed": [[k, v] for k, v in self._bootstrap.vetoed.items()],
        "monitor": self._pool.monitor.to_dict(),
        "gp_batch": self._pool.gp_batch.state_dict(),
        "rigid_batch": self._pool.rigid_batch.state_dict(),
        "calibration": None if cal is None else {
            "scheme": cal.scheme.to_dict(), "world2root": cal.world2root.tolist(), "step": cal.step,
            "n_steps": cal.n_steps, "tree": list(cal.tree), "rms": cal.rms,
            "part_ratios": [[p, n, t, r] for p, (n, t, r) in cal.part_ratios.items()],
            "part_std": [[p, float(v[0]), float(v[1])] for p, v in cal.part_std.items()],
            "consistency": [[p, t.n, _json_float(t.F), _json_float(t.p), _json_float(t.explained), _json_float(t.rms)]
                            for p, t in cal.consistency.items()]},
        "noise": self.noise.to_dict(),
        "unexplained": [[p, s] for p, s in self._unexplained.items()],
        "mirror_watch": self._mirror_watch.to_list(),
        "lack_of_fit": list(self._lack_of_fit),
        "root_watch": self._root_watch.monitor.to_dict(),
        "root_offset": {"pose": self._root_watch.offset.tolist(), "n": self._root_watch.n_offset},
        "root_since": self._root_since,
        "history": [{"step": s, "actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()],
                     **({"covariances": [[p, C.tolist()] for p, C in self._covariances[s].items()]}
                        if s in self._covariances else {})}
                    for s, a, obs in self._history],
        "root_samples": [{"actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()]}
                         for a, obs in self._root_pose.samples],
    }

def learner_from_state(cls, state):
    """Rebuild a learner of class ``cls`` from :func:`learner_to_state` output.

    Raises
    ------
    ModelFileError
        If the version is not this one's, keys are missing, values have the wrong type or shape, or arrays
        contain NaN or inf.
    """
    if not isinstance(state, dict):
        raise ModelFileError(f"learner state must be a dict, got {type(state).__name__}")
    version = state.get("version")
    if version != STATE_VERSION:
        hint = (" (versions 2 and 3 come from learners before the learned noise: learn again from scratch, or start "
                "from the robot's specification)" if version in (2, 3) else "")
        raise ModelFileError(f"unsupported learner state version {version!r}; this reads {STATE_VERSION}{hint}")
    try:
        config = BodySchemeConfig.from_dict(mapping(state["config"], "config"))
        self = cls.__new__(cls)
        self._set_parts(config, check_part_ids(state["part_ids"]), check_n_actions(state["n_actions"]))
        parts = set(self.part_ids)
        root = part_id(state["root"], parts, "root")
        if config.root is not None and root != config.root:
            raise ModelFileError(f"root {root} is not the configuration's root {config.root}")
        self.root = root
        self.action_lower = _bounds_from_json(state["action_lower"], self.n_actions, "action_lower")
        self.action_upper = _bounds_from_json(state["action_upper"], self.n_actions, "action_upper")
        self.step = integer(state["step"], "step")
        self.last_stamp = None if state["last_stamp"] is None else number(state["last_stamp"], "last_stamp")
        self.rejected, self.corrected = (Counter({str(k): integer(v, f"{name}[{k!r}]")
                                                  for k, v in mapping(value, name).items()})
                                         for name, value in (("rejected", state["rejected"]),
                                                             ("corrected", state.get("corrected", {}))))
        # (files written before flips were corrected have no "corrected")
        bootstrapping, found = boolean(state["bootstrapping"], "bootstrapping"), boolean(state["found"], "found")
        tree = None if state["tree"] is None else [integer(i, "tree id") for i in listing(state["tree"], "tree")]
        tree_since = integer(state["tree_since"], "tree_since")
        pool = ModelPool.from_state(config, self.n_actions, parts, state["entries"], state["next_id"],
                                    state["monitor"], state["gp_batch"], state["rigid_batch"])
        if tree is not None and any(i not in pool.tracked for i in tree):
            raise ModelFileError(f"tree refers to unknown model ids {tree}")
        mismatch = mismatch_from_state(state["mismatch"], pool.tracked)
        refining = refining_from_state(state["refining"], pool.tracked, pool.next_id)
        failed = failed_from_state(state["failed"], parts)
        vetoed = {integer(k, "vetoed id"): integer(v, "vetoed size")
                  for k, v in (listing(item, "vetoed item", 2) for item in listing(state["vetoed"], "vetoed"))}
        self._history = deque(maxlen=config.history_length)
        self._covariances = {}
        for rec in listing(state["history"], "history"):
            a = _actions(rec["actions"], self.n_actions, "history actions")
            step, obs = integer(rec["step"], "history step"), _observations(rec["observations"], parts, "history")
            self._history.append((step, a, obs))
            if "covariances" in rec:  # (files written before detections' own covariances have none)
                self._covariances[step] = _covariances(rec["covariances"], obs, "history")
        kept = {s for s, _, _ in self._history}  # (a history longer than history_length loses its oldest steps)
        self._covariances = {s: covs for s, covs in self._covariances.items() if s in kept}
        self._root_pose = RootPoseEstimator(config.root_window, self.root, (
            (_actions(rec["actions"], self.n_actions, "root sample actions"),
             _observations(rec["observations"], parts, "root sample"))
            for rec in listing(state["root_samples"], "root_samples")))
        calibrated = _calibrated_from_state(state["calibration"], self, pool)
        self.noise.load_dict(state["noise"])
        unexplained = {part_id(p, parts, "unexplained"): integer(s, "unexplained step")
                       for p, s in (listing(item, "unexplained item", 2)
                                    for item in listing(state["unexplained"], "unexplained"))}
        lack_of_fit = tuple(part_id(p, parts, "lack_of_fit") for p in listing(state["lack_of_fit"], "lack_of_fit"))
        watch = ValidityMonitor.from_dict(state["root_watch"])
        if watch.capacity != 1 or not watch.in_use[0]:
            raise ModelFileError("root_watch must be one monitor row")
        check_monitor_settings(watch, config, "root_watch")
        offset = mapping(state["root_offset"], "root_offset")
        offset_pose = _rigid(offset["pose"], "root_offset pose")
        n_offset = integer(offset["n"], "root_offset n")
        self._set_models(pool, tree, bootstrapping, found, tree_since, mismatch, calibrated, vetoed, refining,
                         unexplained, lack_of_fit, failed, RootWatch(config, watch, offset_pose, n_offset),
                         integer(state["root_since"], "root_since"),
                         MirrorWatch.from_list(state.get("mirror_watch", []), parts))  # (older files: none)
        if self._tree is not None:
            self.body_scheme  # noqa: B018 - validates that the stored tree is a spanning tree of fitted models
        problems = structural_problems(self)
        if problems:
            raise ModelFileError(f"inconsistent learner state: {'; '.join(problems)}")
    except ModelFileError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError, IndexError, BodySchemeError) as exc:
        raise ModelFileError(f"bad learner state: {type(exc).__name__}: {exc}") from exc
    return self


def _json_float(value):
    """A float for JSON: None where it is not finite (an untested part's statistics)."""
    return float(value) if math.isfinite(value) else None


def _calibrated_from_state(data, learner, pool):
    """The last joint fit, checked against the learner: its scheme spans the learner's parts from its root with
    actions the learner has; its tree ids are distinct, as many as the scheme's models, and each that is still
    tracked relates the parts its model relates; every part has its statistics."""
    if data is None:
        return None
    data = mapping(data, "calibration")
    scheme = BodyScheme.from_dict(data["scheme"])
    parts = set(learner.part_ids)
    if set(scheme.parts) != parts or scheme.root != learner.root:
        raise ModelFileError(f"the calibrated scheme has parts {sorted(scheme.parts)} and root {scheme.root}, the "
                             f"learner {sorted(parts)} and {learner.root}")
    if any(a >= learner.n_actions for m in scheme.models for a in m.actions):
        raise ModelFileError(f"the calibrated scheme uses actions the learner does not have ({learner.n_actions})")
    tree = tuple(integer(i, "calibration tree id", maximum=pool.next_id - 1)
                 for i in listing(data["tree"], "calibration tree", len(scheme.models)))
    if len(set(tree)) != len(tree):
        raise ModelFileError(f"calibration tree ids repeat: {list(tree)}")
    for i, model in zip(tree, scheme.models, strict=True):
        entry = pool.tracked.get(i)
        if entry is not None and {entry.parent, entry.child} != {model.parent, model.child}:
            raise ModelFileError(f"calibration tree model {i} relates parts {model.parent}-{model.child}, the tracked "
                                 f"model {entry.describe()}")
    ratios = _part_rows(data["part_ratios"], parts, "part_ratios", lambda p, n, t, r: (
        integer(n, "part_ratios n"), number(t, "part_ratios trans", 0.0), number(r, "part_ratios rot", 0.0)))
    std = _part_rows(data["part_std"], parts, "part_std", lambda p, t, r: np.array(
        [number(t, "part_std trans", 0.0), number(r, "part_std rot", 0.0)]))
    if set(std) != parts:
        raise ModelFileError(f"calibration part_std covers parts {sorted(std)}, not {sorted(parts)}")
    consistency = _part_rows(data["consistency"], parts, "consistency", lambda p, n, F, pv, e, r: PartConsistency(
        integer(n, "consistency n"), *(optional_number(v, f"consistency {name}", minimum=0.0)
                                       for v, name in ((F, "F"), (pv, "p"), (e, "explained"), (r, "rms")))))
    return Calibrated(scheme, _rigid(data["world2root"], "calibration world2root"), integer(data["step"], "step"),
                      integer(data["n_steps"], "n_steps"), tree, number(data["rms"], "calibration rms", 0.0), ratios,
                      std, consistency)


def _part_rows(rows, parts, name, read):
    """``{part: read(part, *values)}`` from ``[[part, *values], ...]`` with each part at most once."""
    out = {}
    width = read.__code__.co_argcount
    for row in listing(rows, name):
        p = part_id(listing(row, f"{name} row", width)[0], parts, name)
        if p in out:
            raise ModelFileError(f"{name} lists part {p} twice")
        out[p] = read(*row)
    return out


def _actions(value, n_actions, name):
    """An action vector as a learner takes it (:func:`~body_scheme_core.learning.inputs.check_action_vector`), of JSON
    numbers only."""
    try:
        return check_action_vector(finite_array(value, (n_actions,), name), n_actions)
    except InvalidInputError as exc:
        raise ModelFileError(f"{name}: {exc}") from exc


def _rigid(value, name):
    """A finite 4x4 rigid transform whose translation is within :data:`~body_scheme_core.limits.MAX_COORDINATE`."""
    pose = finite_array(value, (4, 4), name)
    if rigidity_problem(pose) is not None:
        raise ModelFileError(f"{name} is not a rigid transform: {rigidity_problem(pose)}")
    if np.abs(pose[:3, 3]).max() > MAX_COORDINATE:
        raise ModelFileError(f"{name} lies beyond {MAX_COORDINATE:g} m")
    return pose


def _observations(pairs, part_ids, name):
    """``{part: world2part}`` from ``[[part, pose], ...]``: known parts, finite rigid poses."""
    out = {}
    for item in listing(pairs, f"{name} observations"):
        p, Y = listing(item, f"{name} observation", 2)
        out[part_id(p, part_ids, f"{name} observation")] = _rigid(Y, f"{name} observation of part {p}")
    return out


def _covariances(pairs, obs, name):
    """``{part: (6, 6)}`` from ``[[part, matrix], ...]``: covariances of parts observed at that step, usable as
    :func:`~body_scheme_core.learning.inputs.filter_covariances` accepts them."""
    given = {}
    for item in listing(pairs, f"{name} covariances"):
        p, C = listing(item, f"{name} covariance", 2)
        given[part_id(p, obs, f"{name} covariance (of a part observed at that step)")] = C
    try:
        usable, rejected = filter_covariances(given, obs)
    except InvalidInputError as error:
        raise ModelFileError(str(error)) from None
    if rejected:
        raise ModelFileError(f"{name}: {rejected[0].detail.split(';')[0]}")
    return usable


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


# ---------------------------------------------------------------------- in memory: one step, all or nothing
def _with_copied_arrays(obj):
    """A shallow copy of ``obj`` whose numpy arrays are copies (batches, the validity monitor: all their state is
    arrays and immutable values)."""
    clone = copy.copy(obj)
    for name, value in vars(obj).items():
        if isinstance(value, np.ndarray):
            setattr(clone, name, value.copy())
    return clone


def snapshot(learner, journal):
    """Everything one :meth:`~body_scheme_core.learning.learner.BodySchemeLearner.update` may change, copied.

    Local models, the calibrated scheme and the recorded observations are never changed in place (a step replaces
    them), so they are shared, not copied; what is copied is the book-keeping around them: the set of tracked
    models, the batches' and the monitor's arrays, the phase objects' dicts, the history and the counters. Changes
    to the tracked models' entries go into ``journal`` (an open :class:`~body_scheme_core.learning.tracked.Journal`),
    which is far cheaper than copying thousands of entries every step.
    """
    pool, boot, adapt = learner._pool, learner._bootstrap, learner._adaptation
    return {
        "learner": {name: getattr(learner, name) for name in (
            "step", "last_stamp", "root", "_bootstrapping", "_calibrated", "_reach", "_just_finished", "_lack_of_fit",
            "_root_since")},
        "unexplained": dict(learner._unexplained),
        "mirror_watch": learner._mirror_watch.copy(),
        "lists": {"_tree": None if learner._tree is None else list(learner._tree),
                  "rejected": Counter(learner.rejected), "corrected": Counter(learner.corrected),
                  "_history": deque(learner._history, maxlen=learner._history.maxlen),
                  "_covariances": dict(learner._covariances)},
        "root_pose": (learner._root_pose, copy.copy(learner._root_pose), deque(learner._root_pose._samples,
                                                                                maxlen=learner._root_pose._samples.maxlen)),
        "noise": learner.noise.copy(),
        "root_watch": (_with_copied_arrays(learner._root_watch.monitor), learner._root_watch.offset.copy(),
                       learner._root_watch.n_offset),
        "journal": journal,
        "pool": (pool.next_id, dict(pool.tracked), (pool.gp_batch, pool.gp_batch.snapshot()),
                 (pool.rigid_batch, pool.rigid_batch.snapshot()), _with_copied_arrays(pool.monitor)),
        "bootstrap": (boot.found, boot.tree_since, dict(boot.vetoed), boot.raced,
                      None if boot._layers is None else dict(boot._layers)),
        "adaptation": ({k: dataclasses.replace(v) for k, v in adapt.mismatch.items()}, dict(adapt.refining),
                       dict(adapt.failed)),
    }


def restore(learner, saved):
    """Put back a :func:`snapshot`: the learner is as it was when it was taken."""
    for name, value in saved["learner"].items():
        setattr(learner, name, value)
    learner._tree = saved["lists"]["_tree"]
    learner._unexplained = saved["unexplained"]
    learner._mirror_watch = saved["mirror_watch"]
    learner.rejected, learner.corrected = saved["lists"]["rejected"], saved["lists"]["corrected"]
    learner._history.clear()
    learner._history.extend(saved["lists"]["_history"])  # the deque is shared with the adaptation object
    learner._covariances = saved["lists"]["_covariances"]
    estimator, fields, samples = saved["root_pose"]
    vars(estimator).update(vars(fields))
    estimator._samples = samples
    vars(learner.noise).update(vars(saved["noise"]))  # in place: the part pairs read it
    watch = learner._root_watch
    watch.monitor, watch.offset, watch.n_offset = saved["root_watch"]
    pool = learner._pool
    pool.next_id, pool.tracked, (pool.gp_batch, gp_saved), (pool.rigid_batch, rigid_saved), pool.monitor = saved["pool"]
    pool.gp_batch.restore(gp_saved)
    pool.rigid_batch.restore(rigid_saved)
    saved["journal"].undo()
    pool._changed()
    boot = learner._bootstrap
    boot.found, boot.tree_since, boot.vetoed, boot.raced, boot._layers = saved["bootstrap"]
    boot._pair_index = None
    learner._adaptation.mismatch, learner._adaptation.refining, learner._adaptation.failed = saved["adaptation"]


# ---------------------------------------------------------------------- structure
def structural_problems(learner):
    """What is wrong with the learner's structure, as a list of sentences (empty when it is sound).

    The tree spans the parts with tracked tree models; every model in the tree, in memory, in mismatch or refining is
    tracked; monitor rows and batch slots belong to exactly one tracked model each; the root is a part, the same for
    every object that uses it; the history's steps increase and come before the learner's step. Checked when a state
    is loaded, and after every step by the tests.
    """
    problems = []
    pool = learner._pool
    tracked = pool.tracked
    parts = set(learner.part_ids)
    tree = learner._tree
    if tree is not None:
        if len(tree) != len(parts) - 1 or len(set(tree)) != len(tree):
            problems.append(f"the tree has {len(tree)} models for {len(parts)} parts")
        missing = [i for i in tree if i not in tracked]
        if missing:
            problems.append(f"tree models {missing} are not tracked")
        else:
            role = "candidate" if learner._bootstrapping else "tree"  # bootstrapping: the tree is of candidates
            if any(tracked[i].role != role for i in tree):
                problems.append(f"a tree model is not in the {role} role")
            graph = {p: set() for p in parts}
            for i in tree:
                e = tracked[i]
                graph.setdefault(e.parent, set()).add(e.child)
                graph.setdefault(e.child, set()).add(e.parent)
            seen, stack = set(), [learner.root]
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
    for name, ids in (("mismatch", learner._adaptation.mismatch), ("refining", learner._adaptation.refining),
                      ("vetoed", learner._bootstrap.vetoed)):
        unknown = [i for i in ids if i not in tracked]
        if unknown:
            problems.append(f"{name} refers to untracked models {unknown}")
    if any(i not in in_tree for i in learner._adaptation.mismatch):
        problems.append("an edge in mismatch is not in the tree")
    rows = [e.row for e in tracked.values()]
    if len(set(rows)) != len(rows) or int(np.count_nonzero(pool.monitor.in_use)) != len(rows) or any(
            not (0 <= r < pool.monitor.capacity and pool.monitor.in_use[r]) for r in rows):
        problems.append("monitor rows and tracked models do not match one to one")
    for batch, rigid in ((pool.gp_batch, False), (pool.rigid_batch, True)):
        slots = [e.slot for e in tracked.values() if e.slot >= 0 and (e.kind in ("static", "prismatic", "revolute"))
                 == rigid]
        if len(set(slots)) != len(slots) or batch.n_allocated != len(slots) or any(
                not batch._allocated[s] for s in slots if 0 <= s < len(batch._allocated)):
            problems.append(f"{'rigid' if rigid else 'GP'} batch slots and learning models do not match one to one")
    if learner.root not in parts or learner._root_pose.root != learner.root:
        problems.append(f"the root {learner.root} is not the same everywhere or not a part")
    steps = [s for s, _, _ in learner._history]
    if any(b <= a for a, b in zip(steps, steps[1:], strict=False)) or (steps and steps[-1] >= learner.step):
        problems.append("the history's steps do not increase up to the learner's step")
    if not set(learner._covariances) <= set(steps) or any(
            not set(covs) <= set(obs) for s, _, obs in learner._history if (covs := learner._covariances.get(s))):
        problems.append("detection covariances of steps or parts the history does not hold")
    return problems
