"""The learner's saved state: a :class:`~body_scheme_core.learner.BodySchemeLearner` as a JSON dict and back.

Files (atomic writes, strict JSON reading) are :mod:`body_scheme_core.persistence`; the layout is documented in
docs/core/state-file-format.md. Reading validates every value: a bad dict raises ``ModelFileError``, never a crash
later on.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from typing import NamedTuple

import numpy as np

from .adaptation import Adaptation
from .config import BodySchemeConfig
from .errors import InvalidInputError, ModelFileError, NotFittedError
from .inputs import check_n_actions, check_part_ids
from .pool import ModelPool
from .root_pose import RootPoseEstimator
from .scheme import BodyScheme

__all__ = ["STATE_VERSION", "Calibrated", "learner_to_state", "learner_from_state"]

#: Version of the dict layout of :func:`learner_to_state`.
STATE_VERSION = 3  # 3: rigid-joint models, two candidate batches, the joint fit; 2: GP-only learner


class Calibrated(NamedTuple):
    """The last joint fit: the calibrated body scheme, the root pose, what it was computed from, and per part
    ``(n, trans ratio, rot ratio)`` of its observations (:meth:`Calibration.part_ratios`)."""

    scheme: BodyScheme
    world2root: np.ndarray
    step: int
    n_steps: int
    tree: tuple
    rms: float
    part_ratios: dict
    part_std: dict



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
        "refining": self._adaptation.refining_state(),
        "vetoed": [[k, v] for k, v in self._bootstrap.vetoed.items()],
        "monitor": self._pool.monitor.to_dict(),
        "gp_batch": self._pool.gp_batch.state_dict(),
        "rigid_batch": self._pool.rigid_batch.state_dict(),
        "calibration": None if cal is None else {
            "scheme": cal.scheme.to_dict(), "world2root": cal.world2root.tolist(), "step": cal.step,
            "n_steps": cal.n_steps, "tree": list(cal.tree), "rms": cal.rms,
            "part_ratios": [[p, n, t, r] for p, (n, t, r) in cal.part_ratios.items()],
            "part_std": [[p, float(v[0]), float(v[1])] for p, v in cal.part_std.items()]},
        "history": [{"step": s, "actions": a.tolist(), "observations": [[p, Y.tolist()] for p, Y in obs.items()]}
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
        hint = (" (version 2 is the GP-only learner before rigid-joint models and the joint fit: its models cannot "
                "be carried over; learn again from scratch, or start from the robot's specification)"
                if version == 2 else "")
        raise ModelFileError(f"unsupported learner state version {version!r}; this reads {STATE_VERSION}{hint}")
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
        pool = ModelPool.from_state(config, self.n_actions, set(self.part_ids), state["entries"],
                                    state["next_id"], state["monitor"], state["gp_batch"], state["rigid_batch"])
        if tree is not None and any(i not in pool.tracked for i in tree):
            raise ModelFileError(f"tree refers to unknown model ids {tree}")
        mismatch = Adaptation.mismatch_from_state(state["mismatch"], pool.tracked)
        refining = Adaptation.refining_from_state(state["refining"], pool.tracked)
        vetoed = {int(k): int(v) for k, v in state["vetoed"]}
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
        calibrated = _calibrated_from_state(state["calibration"])
        self._set_models(pool, tree, bootstrapping, found, tree_since, mismatch, calibrated, vetoed, refining)
        if self._tree is not None:
            self.body_scheme  # noqa: B018 - validates that the stored tree is a spanning tree of fitted models
    except ModelFileError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError, IndexError, InvalidInputError,
            NotFittedError) as exc:
        raise ModelFileError(f"bad learner state: {type(exc).__name__}: {exc}") from exc
    return self


def _calibrated_from_state(data):
    if data is None:
        return None
    scheme = BodyScheme.from_dict(data["scheme"])
    world2root = _finite_array(data["world2root"], (4, 4), "calibration world2root")
    ratios = {int(p): (int(n), float(t), float(r)) for p, n, t, r in data["part_ratios"]}
    std = {int(p): _finite_array([t, r], (2,), "calibration part std") for p, t, r in data["part_std"]}
    return Calibrated(scheme, world2root, int(data["step"]), int(data["n_steps"]), tuple(int(i) for i in data["tree"]),
                      float(data["rms"]), ratios, std)


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
