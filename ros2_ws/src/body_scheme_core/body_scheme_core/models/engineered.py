"""The engineered local model: the exact ``parent2child`` transform from the robot's specification (Sec. III-A).

"If an analytic model of the robot exists from its specifications, it can be used directly [...]: they are exact
and efficient in evaluation." The model stores only the kinematic chain between the two markers, so it is
serialisable on its own and does not depend on the :class:`~body_scheme_core.world.KinematicTree` it was
built from. It is never trained: when the robot changes (a blocked joint, a bent limb, a displaced marker) it keeps
predicting the specification, which is exactly what lets the learner detect the mismatch.

Chain format
------------
A list of elements applied left to right, ``parent2child = E_0 @ E_1 @ ...``:

- ``{"type": "fixed", "transform": [[4 x 4]]}`` a constant transform;
- ``{"type": "revolute" | "prismatic", "axis": [x, y, z], "action": k, "sign": +1 | -1}`` a rotation about
  (translation along) the unit ``axis`` by ``sign * a[k]``. ``sign = -1`` appears where the path runs from a child
  link up to its parent (``inverse(origin @ motion(q)) = motion(-q) @ inverse(origin)``). A mimic joint's element
  also has ``"scale"`` and ``"offset"`` (its URDF multiplier and offset): the motion is by
  ``sign * (scale * a[k] + offset)``.
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError, ModelFileError
from ..transforms import check_transform, invert_transform
from .base import LocalModel, check_action_batch, check_observations
from .chain_spec import chain_from_engineered

__all__ = ["EngineeredModel", "engineered_models", "chain_from_tree"]

_JOINT_ELEMENTS = ("revolute", "prismatic")


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def chain_from_tree(tree, parent_marker, child_marker):
    """Minimal chain (see module docstring) from marker ``parent_marker`` to marker ``child_marker``.

    Parameters
    ----------
    tree : KinematicTree
    parent_marker, child_marker : int

    Returns
    -------
    chain : list of dict
        JSON-serialisable; consecutive constant transforms are merged and passive joints folded in at zero.
    """
    parent, child = tree.marker(parent_marker), tree.marker(child_marker)
    up, down = tree.link_path(parent.link, child.link)
    raw = [("fixed", invert_transform(parent.link2marker))]
    for joint in up:  # child link -> parent link: inverse(origin @ motion(q)) = motion(-q) @ inverse(origin)
        if joint.action is not None:
            raw.append(("joint", joint, -1))
        raw.append(("fixed", invert_transform(joint.origin)))
    for joint in down:
        raw.append(("fixed", joint.origin))
        if joint.action is not None:
            raw.append(("joint", joint, 1))
    raw.append(("fixed", child.link2marker))

    chain, pending = [], np.eye(4)
    for item in raw:
        if item[0] == "fixed":
            pending = pending @ item[1]
            continue
        _, joint, sign = item
        if not np.array_equal(pending, np.eye(4)):
            chain.append({"type": "fixed", "transform": pending.tolist()})
        pending = np.eye(4)
        kind = "prismatic" if joint.type == "prismatic" else "revolute"
        element = {"type": kind, "axis": joint.axis.tolist(), "action": joint.action, "sign": sign}
        if joint.mimic is not None:
            element.update(scale=joint.multiplier, offset=joint.offset)
        chain.append(element)
    if not chain or not np.array_equal(pending, np.eye(4)):
        chain.append({"type": "fixed", "transform": pending.tolist()})
    return chain


def _parse_chain(chain, error=InvalidInputError):
    """Validate a chain and convert it into ``[("fixed", T) | (kind, axis, action, gain, bias)]`` with arrays
    (``q = gain * a[k] + bias``)."""
    if not isinstance(chain, (list, tuple)) or not chain:
        raise error(f"chain must be a non-empty list of elements, got {chain!r}")
    parsed = []
    for index, element in enumerate(chain):
        if not isinstance(element, dict) or "type" not in element:
            raise error(f"chain element {index} must be a dict with a 'type', got {element!r}")
        kind = element["type"]
        try:
            if kind == "fixed":
                T = check_transform(np.asarray(element["transform"], dtype=float), name=f"chain element {index}")
                if T.shape != (4, 4):
                    raise InvalidInputError(f"chain element {index} transform must be (4, 4), got {T.shape}")
                parsed.append(("fixed", T))
            elif kind in _JOINT_ELEMENTS:
                axis = np.asarray(element["axis"], dtype=float)
                if axis.shape != (3,) or not np.all(np.isfinite(axis)) or abs(np.linalg.norm(axis) - 1.0) > 1e-6:
                    raise InvalidInputError(f"chain element {index} axis must be a unit (3,) vector, got {axis}")
                action = element["action"]
                if isinstance(action, bool) or int(action) != action or action < 0:
                    raise InvalidInputError(f"chain element {index} action must be an integer >= 0, got {action!r}")
                sign = element.get("sign", 1)
                if sign not in (1, -1):
                    raise InvalidInputError(f"chain element {index} sign must be +1 or -1, got {sign!r}")
                scale, offset = float(element.get("scale", 1.0)), float(element.get("offset", 0.0))
                if not (np.isfinite(scale) and np.isfinite(offset)):
                    raise InvalidInputError(f"chain element {index} scale and offset must be finite")
                # Stored as q = gain * a[k] + bias.
                parsed.append((kind, axis, int(action), float(sign) * scale, float(sign) * offset))
            else:
                raise InvalidInputError(f"chain element {index} has unknown type {kind!r}")
        except (KeyError, TypeError, ValueError) as exc:
            raise error(f"bad chain element {index} {element!r}: {exc}") from exc
    return parsed


class EngineeredModel(LocalModel):
    """Exact local model ``parent2child = f(a)`` from the robot's specification.

    Parameters
    ----------
    parent, child : int
        Marker ids; the model predicts ``parent2child``.
    actions : tuple of int
        Action indices on the kinematic path; must be exactly the actions the chain uses.
    chain : list of dict
        Kinematic path from marker ``parent`` to marker ``child`` (format in the module docstring). Build it with
        :meth:`from_tree`.

    Notes
    -----
    ``fit`` does not learn: the model is exact by assumption and cheap, so it is always fitted and its predictive
    standard deviation is zero.
    """

    kind = "engineered"

    def __init__(self, parent, child, actions, chain):
        super().__init__(parent, child, actions)
        self.chain = copy.deepcopy(list(chain))
        self._elements = _parse_chain(self.chain)
        used = sorted({e[2] for e in self._elements if e[0] != "fixed"})
        if used != sorted(set(self.actions)) or len(set(self.actions)) != len(self.actions):
            raise InvalidInputError(
                f"engineered model {parent}->{child}: actions {list(self.actions)} must be exactly the chain's "
                f"actions {used}")

    @classmethod
    def from_tree(cls, tree, parent_marker, child_marker):
        """The engineered model between two markers of a :class:`~body_scheme_core.world.KinematicTree`."""
        return cls(parent_marker, child_marker, tree.path_actions(parent_marker, child_marker),
                   chain_from_tree(tree, parent_marker, child_marker))

    @property
    def is_fitted(self):
        """Always ``True``: the model comes from the specification."""
        return True

    def fit(self, A, Z):
        """No-op (the model is exact by assumption); validates the input and returns ``self``."""
        check_observations(A, Z)
        return self

    def _forward(self, A):
        """Per-element transforms for validated action vectors ``A`` (k, m): list of (k, 4, 4) or (4, 4)."""
        if self.actions and A.shape[1] <= max(self.actions):
            raise InvalidInputError(
                f"{self.describe()} needs action index {max(self.actions)}, got vectors of length {A.shape[1]}")
        transforms = []
        for element in self._elements:
            if element[0] == "fixed":
                transforms.append(element[1])
                continue
            kind, axis, action, gain, bias = element
            q = gain * A[:, action] + bias
            T = np.tile(np.eye(4), (A.shape[0], 1, 1))
            if kind == "revolute":
                T[:, :3, :3] = Rotation.from_rotvec(q[:, None] * axis[None, :]).as_matrix()
            else:
                T[:, :3, 3] = q[:, None] * axis[None, :]
            transforms.append(T)
        return transforms

    def predict(self, A, return_std=False):
        """Predict ``parent2child``.

        Parameters
        ----------
        A : array-like, shape (k, m) or (m,)
            Full action vectors.
        return_std : bool

        Returns
        -------
        Z : ndarray, shape (k, 4, 4)
        std : ndarray, shape (k, 2)
            Zeros (trans m, rot rad); only if ``return_std``.
        """
        A = check_action_batch(A)
        Z = np.tile(np.eye(4), (A.shape[0], 1, 1))
        for T in self._forward(A):
            Z = Z @ T
        if return_std:
            return Z, np.zeros((A.shape[0], 2))
        return Z

    def jacobian(self, a, eps=None):
        """Analytic ``dZ/da`` (m, 4, 4) at one full action vector ``a`` (m,).

        For a joint element ``E_k(a) = exp((gain * a + bias) * xi)`` (``gain = sign * scale``) with generator ``xi``
        (``[axis]x`` for revolute, a translation along ``axis`` for prismatic), ``dE_k/da = gain * E_k @ xi``, so
        ``dZ/da = gain * (E_0 ... E_k) @ xi @ (E_k+1 ...)``: the joint's screw axis applied in place.

        Parameters
        ----------
        a : array-like, shape (m,)
        eps : ignored
            Accepted for signature compatibility with :meth:`LocalModel.jacobian`.
        """
        A = check_action_batch(a)
        if A.shape[0] != 1:
            raise InvalidInputError(f"jacobian takes one action vector (m,), got shape {np.shape(a)}")
        transforms = [T[0] if T.ndim == 3 else T for T in self._forward(A)]
        n = len(transforms)
        prefix = [np.eye(4)]
        for T in transforms:
            prefix.append(prefix[-1] @ T)
        suffix = [np.eye(4)] * (n + 1)
        for i in range(n - 1, -1, -1):
            suffix[i] = transforms[i] @ suffix[i + 1]
        J = np.zeros((A.shape[1], 4, 4))
        for i, element in enumerate(self._elements):
            if element[0] == "fixed":
                continue
            kind, axis, action, gain, _ = element
            xi = np.zeros((4, 4))
            if kind == "revolute":
                xi[:3, :3] = _skew(axis)
            else:
                xi[:3, 3] = axis
            J[action] += gain * prefix[i + 1] @ xi @ suffix[i + 1]
        return J

    def to_dict(self):
        """JSON-serialisable dict: ``kind``, ``parent``, ``child``, ``actions``, ``chain``."""
        return {"kind": self.kind, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "chain": copy.deepcopy(self.chain)}

    @classmethod
    def from_dict(cls, data):
        """Rebuild from :meth:`to_dict` output; raises ``ModelFileError`` on bad content."""
        if not isinstance(data, dict) or data.get("kind") != cls.kind:
            raise ModelFileError(f"not an engineered model dict: {data!r:.200}")
        try:
            return cls(data["parent"], data["child"], data["actions"], data["chain"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"bad engineered model dict: {exc}") from exc


def engineered_models(tree, tolerance=None):
    """The initial engineered body scheme: one model per edge of ``tree.marker_tree_edges()``.

    Parameters
    ----------
    tree : KinematicTree
    tolerance : (float, float), optional
        How far each joint may be from its specification (m, rad per axis). Given, an edge over two joints or more
        (markers with unmarked links between them) becomes the specification's chain with that prior, which the
        joint fit calibrates (:func:`~body_scheme_core.models.chain_spec.chain_from_engineered`); an edge that has
        no chain form (a mimic joint) stays an engineered model. Default: every edge an :class:`EngineeredModel`.

    Returns
    -------
    models : list of LocalModel
        ``n_markers - 1`` models forming a spanning tree over the markers, each oriented away from the root.
    """
    models = []
    for parent, child in tree.marker_tree_edges():
        model = EngineeredModel.from_tree(tree, parent, child)
        if tolerance is not None and len(model.actions) >= 2:
            try:
                model = chain_from_engineered(model, prior=tuple(float(v) for v in tolerance))
            except InvalidInputError:
                pass  # an action moving several joints: no chain form
        models.append(model)
    return models
