"""The learner's state as a JSON dict and back (the saved state).

Files (atomic writes, strict JSON reading) are :mod:`body_scheme_core.learning.persistence`; the layout is documented in
docs/core/state-file-format.md. Reading validates every value: a bad dict raises ``ModelFileError``, never a crash
later on. The fields are :class:`~body_scheme_core.learning.learner_state.LearnerState`'s, each saved under the keys
its ``file`` metadata names.
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np

from ..calibration import PartConsistency
from ..errors import BodySchemeError, InvalidInputError, ModelFileError
from ..limits import MAX_COORDINATE, MAX_WINDOW
from ..models import RIGID_CLASSES, GPBatch, RigidBatch
from ..prediction import BodyScheme
from ..state_values import (
    boolean,
    finite_array,
    integer,
    integer_array,
    listing,
    mapping,
    number,
    optional_number,
    part_id,
)
from .config import BodySchemeConfig
from .detection import mismatch_from_state, mismatch_state
from .inputs import check_action_vector, check_n_actions, check_part_ids, filter_covariances, rigidity_problem
from .learner_state import Calibrated, LearnerState, structural_problems
from .mirrors import MirrorWatch
from .pool import ModelPool
from .repair import failed_from_state, failed_state, refining_from_state, refining_state
from .root_pose import RootPoseEstimator, RootWatch
from .tracked import TrackedModel
from .validity import ValidityMonitor

__all__ = ["STATE_VERSION", "to_dict", "from_dict", "pool_from_dict", "monitor_to_dict", "monitor_from_dict"]

#: Version of the dict layout of :func:`to_dict`.
STATE_VERSION = 4  # 4: the learned noise and the lack-of-fit test; 3: rigid-joint models, two candidate batches, the
#                    joint fit; 2: GP-only learner


def to_dict(state):
    """Everything needed to continue bit-identically, as a JSON-serialisable dict.

    Covers the configuration, parts, step, all tracked models (tree, memory, candidates) with their test
    windows and CUSUMs, both candidate batches, the last joint fit, the raw history, the root samples and the
    counters of ``state`` (:class:`~body_scheme_core.learning.learner_state.LearnerState`).
    """
    s = state
    cal = s.calibrated
    return {
        "version": STATE_VERSION,
        "config": s.config.to_dict(),
        "part_ids": list(s.part_ids),
        "root": s.root,
        "n_actions": s.n_actions,
        "action_lower": _bounds_to_json(s.action_lower),
        "action_upper": _bounds_to_json(s.action_upper),
        "step": s.step,
        "last_stamp": s.last_stamp,
        "rejected": dict(s.rejected),
        "corrected": dict(s.corrected),
        "bootstrapping": s.bootstrapping,
        "found": s.bootstrap.found,
        "tree": None if s.tree is None else list(s.tree),
        "tree_since": s.bootstrap.tree_since,
        "next_id": s.pool.next_id,
        "entries": s.pool.tracked_state(),
        "mismatch": mismatch_state(s.adaptation.mismatch),
        "refining": refining_state(s.adaptation.refining),
        "failed": failed_state(s.adaptation.failed),
        "vetoed": [[k, v] for k, v in s.bootstrap.vetoed.items()],
        "monitor": monitor_to_dict(s.pool.monitor),
        "gp_batch": s.pool.gp_batch.state_dict(),
        "rigid_batch": s.pool.rigid_batch.state_dict(),
        "calibration": None if cal is None else {
            "scheme": cal.scheme.to_dict(), "world2root": cal.world2root.tolist(), "step": cal.step,
            "n_steps": cal.n_steps, "tree": list(cal.tree), "rms": cal.rms,
            "part_ratios": [[p, n, t, r] for p, (n, t, r) in cal.part_ratios.items()],
            "part_std": [[p, float(v[0]), float(v[1])] for p, v in cal.part_std.items()],
            "consistency": [[p, t.n, _json_float(t.F), _json_float(t.p), _json_float(t.explained), _json_float(t.rms)]
                            for p, t in cal.consistency.items()]},
        "noise": s.noise.to_dict(),
        "unexplained": [[p, k] for p, k in s.unexplained.items()],
        "mirror_watch": s.mirror_watch.to_list(),
        "lack_of_fit": list(s.lack_of_fit),
        "root_watch": monitor_to_dict(s.root_watch.monitor),
        "root_offset": {"pose": s.root_watch.offset.tolist(), "n": s.root_watch.n_offset},
        "root_since": s.root_since,
        "history": [{"step": k, "actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()],
                     **({"covariances": [[p, C.tolist()] for p, C in s.covariances[k].items()]}
                        if k in s.covariances else {})}
                    for k, a, obs in s.history],
        "root_samples": [{"actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()]}
                         for a, obs in s.root_pose.samples],
    }


def from_dict(data):
    """The :class:`~body_scheme_core.learning.learner_state.LearnerState` of :func:`to_dict` output.

    Raises
    ------
    ModelFileError
        If the version is not this one's, keys are missing, values have the wrong type or shape, arrays contain NaN
        or inf, or the structure is inconsistent
        (:func:`~body_scheme_core.learning.learner_state.structural_problems`).
    """
    if not isinstance(data, dict):
        raise ModelFileError(f"learner state must be a dict, got {type(data).__name__}")
    version = data.get("version")
    if version != STATE_VERSION:
        hint = (" (versions 2 and 3 come from learners before the learned noise: learn again from scratch, or start "
                "from the robot's specification)" if version in (2, 3) else "")
        raise ModelFileError(f"unsupported learner state version {version!r}; this reads {STATE_VERSION}{hint}")
    try:
        state = _state_from_dict(data)
        problems = structural_problems(state)
    except ModelFileError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError, IndexError, BodySchemeError) as exc:
        raise ModelFileError(f"bad learner state: {type(exc).__name__}: {exc}") from exc
    if problems:
        raise ModelFileError(f"inconsistent learner state: {'; '.join(problems)}")
    return state


def _state_from_dict(data):
    config = BodySchemeConfig.from_dict(mapping(data["config"], "config"))
    part_ids, n_actions = check_part_ids(data["part_ids"]), check_n_actions(data["n_actions"])
    parts = set(part_ids)
    root = part_id(data["root"], parts, "root")
    if config.root is not None and root != config.root:
        raise ModelFileError(f"root {root} is not the configuration's root {config.root}")
    pool = pool_from_dict(config, n_actions, parts, data["entries"], data["next_id"], data["monitor"],
                          data["gp_batch"], data["rigid_batch"])
    tree = None if data["tree"] is None else [integer(i, "tree id") for i in listing(data["tree"], "tree")]
    if tree is not None and any(i not in pool.tracked for i in tree):
        raise ModelFileError(f"tree refers to unknown model ids {tree}")
    history, covariances = deque(maxlen=config.history_length), {}
    for rec in listing(data["history"], "history"):
        a = _actions(rec["actions"], n_actions, "history actions")
        step, obs = integer(rec["step"], "history step"), _observations(rec["observations"], parts, "history")
        history.append((step, a, obs))
        if "covariances" in rec:  # (files written before detections' own covariances have none)
            covariances[step] = _covariances(rec["covariances"], obs, "history")
    kept = {k for k, _, _ in history}  # (a history longer than history_length loses its oldest steps)
    rejected, corrected = (Counter({str(k): integer(v, f"{name}[{k!r}]") for k, v in mapping(value, name).items()})
                           for name, value in (("rejected", data["rejected"]),
                                               ("corrected", data.get("corrected", {}))))  # (older files: none)
    watch = monitor_from_dict(data["root_watch"])
    if watch.capacity != 1 or not watch.in_use[0]:
        raise ModelFileError("root_watch must be one monitor row")
    _check_monitor_settings(watch, config, "root_watch")
    offset = mapping(data["root_offset"], "root_offset")
    state = LearnerState(
        config, part_ids, n_actions, _bounds_from_json(data["action_lower"], n_actions, "action_lower"),
        _bounds_from_json(data["action_upper"], n_actions, "action_upper"), root, pool, tree,
        boolean(data["bootstrapping"], "bootstrapping"),
        step=integer(data["step"], "step"),
        last_stamp=None if data["last_stamp"] is None else number(data["last_stamp"], "last_stamp"),
        rejected=rejected, corrected=corrected, history=history,
        covariances={k: covs for k, covs in covariances.items() if k in kept},
        root_pose=RootPoseEstimator(config.root_window, root, (
            (_actions(rec["actions"], n_actions, "root sample actions"),
             _observations(rec["observations"], parts, "root sample"))
            for rec in listing(data["root_samples"], "root_samples"))),
        unexplained={part_id(p, parts, "unexplained"): integer(k, "unexplained step")
                     for p, k in (listing(item, "unexplained item", 2)
                                  for item in listing(data["unexplained"], "unexplained"))},
        lack_of_fit=tuple(part_id(p, parts, "lack_of_fit") for p in listing(data["lack_of_fit"], "lack_of_fit")),
        root_watch=RootWatch(config, watch, _rigid(offset["pose"], "root_offset pose"),
                             integer(offset["n"], "root_offset n")),
        root_since=integer(data["root_since"], "root_since"),
        mirror_watch=MirrorWatch.from_list(data.get("mirror_watch", []), parts))  # (older files: none)
    boot, adapt = state.bootstrap, state.adaptation  # the phase objects' saved book-keeping
    boot.found, boot.tree_since = boolean(data["found"], "found"), integer(data["tree_since"], "tree_since")
    boot.vetoed = {integer(k, "vetoed id"): integer(v, "vetoed size")
                   for k, v in (listing(item, "vetoed item", 2) for item in listing(data["vetoed"], "vetoed"))}
    adapt.mismatch = mismatch_from_state(data["mismatch"], pool.tracked)
    adapt.refining = refining_from_state(data["refining"], pool.tracked, pool.next_id)
    adapt.failed = failed_from_state(data["failed"], parts)
    state.calibrated = _calibrated_from_state(data["calibration"], state, pool)
    state.noise.load_dict(data["noise"])
    state.share_thresholds()
    if tree is not None and (state.calibrated is None or state.calibrated.tree != tuple(tree)):
        state.raw_scheme()  # raises unless the tree is a spanning tree of fitted models
    return state


def _json_float(value):
    """A float for JSON: None where it is not finite (an untested part's statistics)."""
    return float(value) if math.isfinite(value) else None


def _calibrated_from_state(data, state, pool):
    """The last joint fit, checked against the learner's ``state``: its scheme spans the learner's parts from its root
    with actions the learner has; its tree ids are distinct, as many as the scheme's models, and each that is still
    tracked relates the parts its model relates; every part has its statistics."""
    if data is None:
        return None
    data = mapping(data, "calibration")
    scheme = BodyScheme.from_dict(data["scheme"])
    parts = set(state.part_ids)
    if set(scheme.parts) != parts or scheme.root != state.root:
        raise ModelFileError(f"the calibrated scheme has parts {sorted(scheme.parts)} and root {scheme.root}, the "
                             f"learner {sorted(parts)} and {state.root}")
    if any(a >= state.n_actions for m in scheme.models for a in m.actions):
        raise ModelFileError(f"the calibrated scheme uses actions the learner does not have ({state.n_actions})")
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


# ---------------------------------------------------------------------- the pool and its validity monitors
def pool_from_dict(config, n_actions, part_ids, tracked, next_id, monitor, gp_batch, rigid_batch):
    """A :class:`~body_scheme_core.learning.pool.ModelPool` from its saved parts: ``ModelPool.tracked_state``,
    ``next_id``, :func:`monitor_to_dict` and the batches' state dicts.

    Raises
    ------
    ModelFileError
        If the monitor or batches do not have the configuration's settings, or a model refers to an unknown part,
        a free monitor row or batch slot (or one of another model class or actions), has an id at or above
        ``next_id`` or twice, or is frozen without a stored model.
    """
    monitor = monitor_from_dict(monitor)
    _check_monitor_settings(monitor, config, "monitor")
    gp = GPBatch.from_state_dict(gp_batch)
    rigid = RigidBatch.from_state_dict(rigid_batch)
    expected = GPBatch.from_config(n_actions, config, gp.max_dim)
    if (gp.n_actions, gp.capacity, gp.hyperparameters) != (n_actions, config.train_window, expected.hyperparameters):
        raise ModelFileError(f"the GP batch ({gp.n_actions} actions, capacity {gp.capacity}, "
                             f"{gp.hyperparameters}) does not have the configuration's settings "
                             f"({n_actions}, {config.train_window}, {expected.hyperparameters})")
    if not config.max_complexity <= gp.max_dim <= max(config.max_complexity, n_actions):
        raise ModelFileError(f"the GP batch's max_dim {gp.max_dim} is below max_complexity or above the actions")
    if (rigid.n_actions, rigid.capacity, rigid.f_scale, rigid.fit_scale) != (
            n_actions, config.train_window, config.f_scale, config.fit_joint_scale):
        raise ModelFileError("the rigid batch does not have the configuration's actions, train_window, f_scale "
                             "and fit_joint_scale")
    pool = ModelPool(config, n_actions, gp, rigid, monitor, integer(next_id, "next_id"))
    for data in listing(tracked, "entries"):
        entry = TrackedModel.from_dict(data, n_actions, part_ids)
        problem = _entry_problem(pool, entry)
        if problem:
            raise ModelFileError(f"model {entry.describe()}: {problem}")
        pool.tracked[entry.id] = entry
    return pool


def _entry_problem(pool, entry):
    """What is wrong with a loaded entry given the pool's monitor, batches and the entries before it, or None."""
    if entry.id >= pool.next_id or entry.id in pool.tracked:
        return f"its id is at or above next_id {pool.next_id}, or taken"
    if not (0 <= entry.row < pool.monitor.capacity and pool.monitor.in_use[entry.row]):
        return f"has no monitor row {entry.row}"
    if entry.slot < 0:
        return None if entry.model is not None else "is frozen without a stored model"
    if entry.model is not None:
        return "is learning in a batch slot and has a stored model"
    rigid = entry.kind in RIGID_CLASSES
    batch = pool.rigid_batch if rigid else pool.gp_batch
    if not batch.is_allocated(entry.slot):
        return f"refers to free batch slot {entry.slot}"
    held = (batch.slot_kind(entry.slot) if rigid else "gp", batch.slot_actions(entry.slot))
    if held != (entry.kind, entry.actions):
        return f"its batch slot {entry.slot} holds a {held[0]} model of actions {list(held[1])}"
    return None


def _check_monitor_settings(monitor, config, name):
    """Raise ``ModelFileError`` unless a loaded validity monitor has the configuration's test window and CUSUM."""
    settings = (monitor.window, monitor.cusum_drift, monitor.cusum_threshold, monitor.cusum_clip, monitor.sigmas)
    expected = (config.test_window, config.cusum_drift, config.cusum_threshold, config.cusum_clip,
                config.validity_sigmas)
    if settings != tuple(float(v) if k else v for k, v in enumerate(expected)):
        raise ModelFileError(f"{name} has window and CUSUM settings {settings}, the configuration {expected}")


def monitor_to_dict(monitor):
    """A :class:`~body_scheme_core.learning.validity.ValidityMonitor` as JSON-serialisable data (all rows, used or
    free, so row indices survive a round trip)."""
    data = {"window": monitor.window, "theta": monitor.theta.tolist(), "cusum_drift": monitor.cusum_drift,
            "cusum_threshold": monitor.cusum_threshold, "cusum_clip": monitor.cusum_clip, "sigmas": monitor.sigmas}
    for name in monitor.ARRAYS:
        data[name] = getattr(monitor, name).tolist()
    return data


def monitor_from_dict(data):
    """Rebuild a validity monitor from :func:`monitor_to_dict` output.

    Raises
    ------
    ModelFileError
        On a missing key, a bad shape, NaN, a value out of its range (negative errors or counts, heads outside
        the window), or a CUSUM that is above zero without the step it left zero at (or the reverse).
    """
    try:
        theta = listing(data["theta"], "validity-monitor theta", 2)
        monitor = ValidityMonitor(integer(data["window"], "validity-monitor window", 1, MAX_WINDOW), 0,
                                  *(number(v, "validity-monitor theta", above=0.0) for v in theta),
                                  *(number(data[k], f"validity-monitor {k}", above=0.0)
                                    for k in ("cusum_drift", "cusum_threshold", "cusum_clip", "sigmas")))
        n = len(listing(data["in_use"], "validity-monitor in_use"))
        template = monitor.empty_rows(n)
        for name in monitor.ARRAYS:
            shape, dtype = template[name].shape, template[name].dtype
            if dtype.kind == "b":
                value = np.array([boolean(v, "validity-monitor in_use") for v in data[name]], dtype=bool)
            elif dtype.kind == "f":
                value = finite_array(data[name], shape, f"validity-monitor {name}") if n else template[name]
            else:
                value = integer_array(data[name], shape, f"validity-monitor {name}", -1) if n else template[name]
            setattr(monitor, name, value)
    except (KeyError, TypeError, InvalidInputError) as exc:
        raise ModelFileError(f"bad validity-monitor state: {type(exc).__name__}: {exc}") from exc
    problems = [what for what, bad in (
        ("errors must be >= 0", np.any(monitor.errors < 0)),
        ("thresholds must be > 0", np.any(monitor.thresholds <= 0)),
        ("n_train and count must be >= 0", np.any(monitor.n_train < 0) or np.any(monitor.count < 0)),
        ("ring-buffer heads must be in the window", np.any((monitor.head < 0) | (monitor.head >= monitor.window))),
        ("a CUSUM is above zero exactly when it has a start step",
         np.any((monitor.cusum < 0) | ((monitor.cusum > 0) != (monitor.cusum_start >= 0))))) if bad]
    if problems:
        raise ModelFileError(f"bad validity-monitor state: {'; '.join(problems)}")
    return monitor
