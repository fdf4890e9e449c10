"""The local model interface: p(Z_parent->child | A) between two body parts (paper Sec. III-A).

Every local model class follows the scikit-learn estimator shape:

- ``__init__`` stores hyperparameters only: the two part ids, the action indices it depends on, and its own
  settings. Nothing is computed there.
- ``fit(A, Z)`` learns from full action vectors ``A`` (n, m) and relative observations ``Z`` (n, 4, 4) and returns
  ``self``. Learned state ends in ``_``.
- ``predict(A, return_std=False)`` gives valid rigid transforms ``parent2child`` (k, 4, 4) and, on request, an
  isotropic standard deviation per sample ``[trans (m), rot (rad)]`` (k, 2).
- ``jacobian(a)`` gives ``dZ/da`` for one full action vector: (m, 4, 4), zero for actions the model ignores.
- ``to_dict()`` / ``from_dict()`` give a JSON-serialisable dict (numbers and lists only) for persistence.

Models take *full* action vectors and select their own columns, so callers never slice.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from ..errors import InvalidInputError, ModelFileError, NotFittedError
from ..limits import MAX_ACTIONS
from ..transforms import check_transform

__all__ = ["LocalModel", "check_action_batch", "check_observations"]


def check_action_batch(A, n_actions=None, name="A"):
    """Validate a stack of full action vectors for the models; one vector (m,) becomes a stack of one.

    Not to be confused with :func:`~body_scheme_core.learning.inputs.check_action_vector`, which checks the one action
    vector a caller hands the learner per step (exact length, never a stack).

    Parameters
    ----------
    A : array-like, shape (n, m) or (m,)
    n_actions : int or None
        Required m, if known.

    Returns
    -------
    A : ndarray, shape (n, m)
    """
    A = np.asarray(A, dtype=float)
    if A.ndim == 1:
        A = A[None, :]
    if A.ndim != 2:
        raise InvalidInputError(f"{name} must have shape (n, m) or (m,), got {A.shape}")
    if n_actions is not None and A.shape[1] != n_actions:
        raise InvalidInputError(f"{name} must have {n_actions} action columns, got {A.shape[1]}")
    if not np.all(np.isfinite(A)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    return A


def check_observations(A, Z):
    """Validate a training set: action vectors (n, m) and relative transforms (n, 4, 4) of equal length."""
    A = check_action_batch(A)
    Z = check_transform(Z, name="Z", tolerance=1e-4)
    if Z.ndim != 3 or Z.shape[0] != A.shape[0]:
        raise InvalidInputError(f"A and Z must have the same length, got A {A.shape} and Z {Z.shape}")
    if A.shape[0] == 0:
        raise InvalidInputError("cannot fit a local model on zero samples")
    return A, Z


class LocalModel(ABC):
    """Base class of local models p(Z_parent->child | A_parent->child).

    Parameters
    ----------
    parent, child : int
        Part ids (marker ids) of the two body parts; the model predicts ``parent2child``.
    actions : tuple of int
        Indices into the full action vector that the model depends on; ``()`` for a static model.
    """

    #: Short name of the model class, used in descriptions, events and saved files.
    kind: ClassVar[str] = "abstract"

    def __init__(self, parent, child, actions=()):
        self.parent = int(parent)
        self.child = int(child)
        actions = tuple(actions)
        if any(isinstance(a, bool) or not isinstance(a, (int, np.integer)) or not 0 <= a < MAX_ACTIONS
               for a in actions):
            raise InvalidInputError(f"actions must be indices in [0, {MAX_ACTIONS}), got {actions!r:.80}")
        self.actions = tuple(int(a) for a in actions)

    @property
    def complexity(self):
        """C(M): the number of actions the model depends on (the paper's complexity layers)."""
        return len(self.actions)

    @property
    def pair(self):
        """``(parent, child)``."""
        return (self.parent, self.child)

    def describe(self):
        """Short description like ``gp(1->2 | a0,a3)``."""
        acts = ",".join(f"a{a}" for a in self.actions) or "-"
        return f"{self.kind}({self.parent}->{self.child} | {acts})"

    def __repr__(self):
        return f"<{type(self).__name__} {self.describe()}>"

    def _check_fitted(self):
        if not self.is_fitted:
            raise NotFittedError(f"{self.describe()} is not fitted yet; call fit(A, Z) first")

    def _select(self, A):
        """Columns of ``A`` this model depends on, after validating ``A``."""
        A = check_action_batch(A)
        if self.actions and A.shape[1] <= max(self.actions):
            raise InvalidInputError(
                f"{self.describe()} needs action index {max(self.actions)}, got vectors of length {A.shape[1]}")
        return A[:, list(self.actions)]

    @property
    @abstractmethod
    def is_fitted(self):
        """Whether ``predict`` may be called."""

    @abstractmethod
    def fit(self, A, Z):
        """Learn from action vectors ``A`` (n, m) and relative observations ``Z`` (n, 4, 4); returns ``self``."""

    @abstractmethod
    def predict(self, A, return_std=False):
        """Predict ``parent2child`` (k, 4, 4) for action vectors ``A`` (k, m) [and std (k, 2): trans m, rot rad]."""

    def predict_one(self, a):
        """``parent2child`` (4, 4) for one full action vector ``a`` (m,) that the caller has checked (finite, long
        enough): the per-step path of :meth:`BodyScheme.predict`."""
        return self.predict(a[None])[0]

    def training_range(self):
        """``(low, high)`` per action of :attr:`actions` that the model saw in training, or ``None``.

        ``None`` (the default, e.g. for a model from the robot's specification) means the model claims to hold over
        the whole action range; a model learned from data returns the box of its training inputs, outside of which it
        extrapolates.
        """
        return None

    def jacobian(self, a, eps=1e-6):
        """Derivative ``dZ/da`` (m, 4, 4) at one full action vector ``a`` (m,).

        The base implementation uses central differences on the model's own actions; subclasses override it
        analytically where they can.
        """
        a = check_action_batch(a)[0]
        J = np.zeros((a.shape[0], 4, 4))
        for k in self.actions:
            step = np.zeros_like(a)
            step[k] = eps
            J[k] = (self.predict(a + step)[0] - self.predict(a - step)[0]) / (2.0 * eps)
        return J

    @abstractmethod
    def to_dict(self):
        """JSON-serialisable dict with ``kind``, ``parent``, ``child``, ``actions`` and the learned state."""

    @classmethod
    @abstractmethod
    def from_dict(cls, data):
        """Rebuild a model from :meth:`to_dict` output; raises ``ModelFileError`` on bad content."""

    @classmethod
    def _unfitted_from_dict(cls, data):
        """The model of ``data``'s kind, parts, actions and hyperparameters, before its learned state is restored."""
        if data["kind"] != cls.kind:
            raise ModelFileError(f"expected kind {cls.kind!r}, got {data['kind']!r}")
        return cls(data["parent"], data["child"], data["actions"], **data["hyperparameters"])
