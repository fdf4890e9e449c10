"""The local models a learner tracks: their roles, and which of them nest which.

A :class:`TrackedModel` is a local model in one of three roles: ``tree`` (an edge of the body scheme), ``memory``
(retired, remembered for reuse) or ``candidate`` (still learning: a bootstrap candidate or a replacement for a
failed tree model). The :class:`~body_scheme_core.learning.pool.ModelPool` holds all of them with their storage;
:func:`nested_models` finds the pairs the dominance rule compares.
"""

from __future__ import annotations

import threading

import numpy as np

from ..errors import ModelFileError
from ..models import MODEL_CLASSES, RigidJointModel, model_from_dict
from ..state_values import integer, listing, mapping, part_id
from .quality import class_rank, nesting_matrix

__all__ = ["TREE", "MEMORY", "CANDIDATE", "TrackedModel", "nested_models", "Journal"]

#: Roles of a tracked model.
TREE, MEMORY, CANDIDATE = "tree", "memory", "candidate"
ROLES = (TREE, MEMORY, CANDIDATE)


#: The open journal of this thread, if any (:class:`Journal`).
_journal = threading.local()


class Journal:
    """Every change to any :class:`TrackedModel`'s attributes in this thread while it is open, so that it can be
    undone: what makes a learner's step all or nothing without copying thousands of entries every step.

    Use as a context manager; :meth:`undo` puts back every old value, newest first. Journals do not nest.
    """

    def __enter__(self):
        if getattr(_journal, "log", None) is not None:
            raise RuntimeError("a journal of tracked models is already open in this thread")
        self.log = _journal.log = []
        return self

    def __exit__(self, *exc):
        _journal.log = None
        return False

    def undo(self):
        for entry, name, value in reversed(self.log):
            object.__setattr__(entry, name, value)
        self.log.clear()


class TrackedModel:
    """A local model the learner tracks: in the tree, in memory, or a candidate still learning in a batch.

    Attributes
    ----------
    id : int
        Unique id, shown in events (``describe``) and used as the tree's edge key.
    parent, child : int
        Part ids; the model predicts ``parent2child``.
    actions : tuple of int
    kind : str
        Model class (``"static"``, ``"prismatic"``, ``"revolute"``, ``"gp"``, ``"engineered"``).
    role : str
        ``"tree"``, ``"memory"`` or ``"candidate"``.
    model : LocalModel or None
        The fitted model; None while a candidate learns (its batch slot holds it).
    slot : int
        Batch slot while the model learns, -1 when frozen.
    row : int
        Row in the validity monitor.
    n_train : int
        Training samples (0 for models the learner did not train, e.g. engineered ones).
    created : int
        Step at which a replacement was sampled (0 otherwise).
    origin : str
        ``"bootstrap"``, ``"replacement"``, ``"bridge"`` or ``"initial"``.
    last_used : int
        Last step at which the model entered the tree or memory (-1 never); memory forgets the least recent.
    target : int
        For a replacement candidate, the id of the tree model it is meant to replace; -1 otherwise.
    since : int
        First step at which the model describes the body (its change point), for the joint fit.
    prior : tuple (params, cov) or None
        A Gaussian prior on a rigid model's parameters in the joint fit, for knowledge from data the fit does not
        use (a reinstated model's earlier life, or observations cut by a change above it in the tree).
    """

    __slots__ = ("id", "parent", "child", "actions", "kind", "role", "model", "slot", "row", "n_train", "created",
                 "origin", "last_used", "target", "since", "prior")

    def __setattr__(self, name, value):
        log = getattr(_journal, "log", None)
        if log is not None and hasattr(self, name):
            log.append((self, name, getattr(self, name)))
        object.__setattr__(self, name, value)

    def __init__(self, id, parent, child, actions, kind, role, row, slot=-1, model=None, n_train=0, created=0,
                 origin="", last_used=-1, target=-1, since=0, prior=None):
        self.id = int(id)
        self.parent = int(parent)
        self.child = int(child)
        self.actions = tuple(int(a) for a in actions)
        self.kind = str(kind)
        self.role = role
        self.model = model
        self.slot = int(slot)
        self.row = int(row)
        self.n_train = int(n_train)
        self.created = int(created)
        self.origin = origin
        self.last_used = int(last_used)
        self.target = int(target)
        self.since = int(since)
        self.prior = prior

    def copy(self):
        """A copy of the entry (its model and prior are shared: they are replaced, never changed in place)."""
        clone = TrackedModel.__new__(TrackedModel)
        for name in self.__slots__:
            setattr(clone, name, getattr(self, name))
        return clone

    @property
    def complexity(self):
        """Number of actions the model depends on."""
        return len(self.actions)

    @property
    def rank(self):
        """Rank of the model class within its complexity layer (:func:`.quality.class_rank`)."""
        return class_rank(self.kind)

    def describe(self):
        """``kind(parent->child | actions)#id``: the id tells apart models with equal structure (in events)."""
        acts = ",".join(f"a{a}" for a in self.actions) or "-"
        return f"{self.kind}({self.parent}->{self.child} | {acts})#{self.id}"

    def to_dict(self, with_model):
        """JSON-serialisable dict; the model itself only ``with_model``."""
        prior = None if self.prior is None else [np.asarray(self.prior[0]).tolist(), np.asarray(self.prior[1]).tolist()]
        return {"id": self.id, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "kind": self.kind, "role": self.role, "slot": self.slot, "row": self.row, "n_train": self.n_train,
                "created": self.created, "origin": self.origin, "last_used": self.last_used, "target": self.target,
                "since": self.since, "prior": prior,
                "model": self.model.to_dict() if (with_model and self.model is not None) else None}

    @classmethod
    def from_dict(cls, data, n_actions, part_ids):
        """Rebuild from :meth:`to_dict` output for a learner of ``n_actions`` actions and parts ``part_ids``.

        Raises
        ------
        ModelFileError
            On a value that is not what a learner writes: an id, step or count that is not a bounded integer, a model
            of an unknown part or of a part to itself, actions that are not distinct and in range, an unknown kind
            or role, a bad prior, or a stored model that is unfitted or is not the model the entry describes.
        """
        data = mapping(data, "tracked model")
        model_id = integer(data["id"], "tracked model id")
        name = f"tracked model {model_id}"
        parent, child = (part_id(data[k], part_ids, f"{name} {k}") for k in ("parent", "child"))
        actions = tuple(integer(a, f"{name} action", maximum=n_actions - 1) for a in listing(data["actions"], name))
        kind, role = data["kind"], data["role"]
        if parent == child or len(set(actions)) != len(actions) or kind not in MODEL_CLASSES or role not in ROLES:
            raise ModelFileError(f"{name}: parts {parent}->{child}, actions {list(actions)}, kind {kind!r} and role "
                                 f"{role!r} do not describe a model of this learner")
        model = None if data["model"] is None else model_from_dict(data["model"])
        if model is not None and not (model.is_fitted and (model.kind, model.parent, model.child, model.actions)
                                      == (kind, parent, child, actions)):
            raise ModelFileError(f"{name}: the stored model {model.describe()} is not the fitted {kind} model of "
                                 f"{parent}->{child} with actions {list(actions)}")
        prior = None if data["prior"] is None else _prior(data["prior"], model, name)
        counts = {k: integer(data[k], f"{name} {k}", minimum=-1 if k in ("slot", "last_used", "target") else 0)
                  for k in ("row", "slot", "n_train", "created", "last_used", "target", "since")}
        return cls(model_id, parent, child, actions, kind, role, model=model, origin=_origin(data["origin"], name),
                   prior=prior, **counts)


def _prior(value, model, name):
    """A rigid model's prior ``(params, cov)``, read as the model's own parameters are
    (:meth:`RigidJointModel.read_params`: the storage layout and the covariance of a local increment)."""
    if not isinstance(model, RigidJointModel):
        raise ModelFileError(f"{name}: a prior needs the fitted rigid-joint model it belongs to")
    params, cov = listing(value, f"{name} prior", 2)
    return model.read_params(params, cov, f"{name} prior")


def _origin(value, name):
    if not isinstance(value, str) or len(value) > 40:
        raise ModelFileError(f"{name}: origin must be a short string, got {value!r:.60}")
    return value


def nested_models(models):
    """Positions ``(sub, sup)`` of models of the same pair (and target) where ``sup`` nests ``sub``.

    ``sup`` nests ``sub`` when it can represent everything ``sub`` can
    (:func:`~body_scheme_core.learning.quality.nests`): a model class at least as flexible and a superset of the
    actions, a chain's actions counted with those found not to move its child (``inert_actions``). These are the
    pairs the dominance rule compares.

    Parameters
    ----------
    models : list of TrackedModel

    Returns
    -------
    sub, sup : ndarray of int
    """
    groups = {}
    for k, e in enumerate(models):
        groups.setdefault((e.parent, e.child, e.target), []).append(k)
    # As the nesting one, a chain also covers the actions its identification found not to move its child.
    covers = [(*e.actions, *getattr(e.model, "inert_actions", ())) for e in models]
    n_actions = max((max(acts, default=0) for acts in covers), default=0) + 1
    sub, sup = [np.zeros(0, dtype=np.intp)], [np.zeros(0, dtype=np.intp)]
    for members in groups.values():
        nest = nesting_matrix([models[k].kind for k in members], [models[k].actions for k in members], n_actions,
                              [covers[k] for k in members])
        k, q = np.nonzero(nest)
        members = np.asarray(members, dtype=np.intp)
        sub.append(members[k])
        sup.append(members[q])
    return np.concatenate(sub), np.concatenate(sup)
