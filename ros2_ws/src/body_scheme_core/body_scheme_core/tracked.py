"""The local models a learner tracks: their roles, and which of them nest which.

A :class:`TrackedModel` is a local model in one of three roles: ``tree`` (an edge of the body scheme), ``memory``
(retired, remembered for reuse) or ``candidate`` (still learning: a bootstrap candidate or a replacement for a
failed tree model). The :class:`~body_scheme_core.pool.ModelPool` holds all of them with their storage;
:func:`nested_models` finds the pairs the dominance rule compares.
"""

from __future__ import annotations

import numpy as np

from .errors import ModelFileError
from .models import model_from_dict
from .quality import class_rank, nests

__all__ = ["TREE", "MEMORY", "CANDIDATE", "TrackedModel", "nested_models"]

#: Roles of a tracked model.
TREE, MEMORY, CANDIDATE = "tree", "memory", "candidate"


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
        """Rank of the model class within its complexity layer (:func:`~body_scheme_core.quality.class_rank`)."""
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
    def from_dict(cls, data):
        """Rebuild from :meth:`to_dict` output; raises ModelFileError on an unknown role or a bad prior."""
        model = model_from_dict(data["model"]) if data["model"] is not None else None
        if data["role"] not in (TREE, MEMORY, CANDIDATE):
            raise ModelFileError(f"unknown entry role {data['role']!r}")
        prior = data["prior"]
        if prior is not None:
            params, cov = (np.asarray(v, dtype=float) for v in prior)
            if cov.ndim != 2 or cov.shape[0] != cov.shape[1] or not (np.all(np.isfinite(params))
                                                                      and np.all(np.isfinite(cov))):
                raise ModelFileError(f"bad prior of model {data['id']!r}")
            prior = (params, cov)
        return cls(data["id"], data["parent"], data["child"], data["actions"], data["kind"], data["role"],
                   data["row"], data["slot"], model, data["n_train"], data["created"], data["origin"],
                   data["last_used"], data["target"], data["since"], prior)


def nested_models(models):
    """Positions ``(sub, sup)`` of models of the same pair (and target) where ``sup`` nests ``sub``.

    ``sup`` nests ``sub`` when it can represent everything ``sub`` can (:func:`~body_scheme_core.quality.nests`): a
    model class at least as flexible and a superset of the actions. These are the pairs the dominance rule compares.

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
    sub, sup = [], []
    for members in groups.values():
        for k in members:
            for q in members:
                if k != q and nests(models[q].kind, models[q].actions, models[k].kind, models[k].actions):
                    sub.append(k)
                    sup.append(q)
    return np.array(sub, dtype=np.intp), np.array(sup, dtype=np.intp)
