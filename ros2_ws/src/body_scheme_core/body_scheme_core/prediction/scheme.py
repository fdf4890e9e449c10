"""The body scheme: a spanning tree of local models over all body parts (paper Sec. III-C/D, Eq. 8).

A set of ``n - 1`` local models that connect all ``n`` parts without a cycle defines the whole kinematic structure,
because every local model is a rigid transform and can be inverted. The maximum-likelihood posture for an action
vector is obtained by concatenating the models' predictions from the root outwards (Eq. 8): every part, observed or
not, is predicted from the actions alone. The Jacobian of that forward model (Eq. 10) drives gradient-based control
(:mod:`body_scheme_core.control.ik`).

Frame convention (see :mod:`body_scheme_core.transforms`): ``root2part`` is the pose of ``part`` in the root frame.
A model predicts ``model.parent2model.child``; when the tree traverses it from ``model.child`` to ``model.parent`` the
scheme uses the inverse transform and marks the edge ``inverted``.
"""

from __future__ import annotations

import networkx as nx
import numpy as np

from ..errors import InvalidInputError, ModelFileError, NotFittedError
from ..models import LocalModel, check_action_batch
from ..transforms import invert_transform
from .jacobian import jacobian, position_jacobian

__all__ = ["BodyScheme"]

#: Version of the dict layout written by :meth:`BodyScheme.to_dict`.
SCHEME_FORMAT_VERSION = 1


def _invert_single(A2B):
    """Inverse of one rigid transform (4, 4); cheaper than the stacked :func:`invert_transform` in hot loops."""
    B2A = np.empty((4, 4))
    Rt = A2B[:3, :3].T
    B2A[:3, :3] = Rt
    B2A[:3, 3] = -Rt @ A2B[:3, 3]
    B2A[3] = (0.0, 0.0, 0.0, 1.0)
    return B2A


def _checked_param_covariance(models, param_covariance):
    """``(tuple of model indices, (P, P) matrix)`` from the ``param_covariance`` argument, or None; see BodyScheme."""
    if param_covariance is None:
        return None
    try:
        indices, matrix = param_covariance
        indices = tuple(int(k) for k in indices)
        matrix = np.array(matrix, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"param_covariance must be (model indices, matrix), got {param_covariance!r}") from exc
    if len(set(indices)) != len(indices) or any(not 0 <= k < len(models) or not hasattr(models[k], "retract")
                                                 for k in indices):
        raise InvalidInputError(f"param_covariance names models {list(indices)}: each once, rigid-joint models of "
                                f"the scheme (0..{len(models) - 1})")
    size = sum(models[k].n_params for k in indices)
    if matrix.shape != (size, size) or not np.all(np.isfinite(matrix)):
        raise InvalidInputError(f"param_covariance's matrix must be finite, {size} x {size}, got {matrix.shape}")
    return indices, matrix


class BodyScheme:
    """A spanning tree of fitted local models over all body parts, used for prediction and control.

    Parameters
    ----------
    parts : iterable of int
        Part (marker) ids, any numbering; each id once.
    root : int
        The part serving as coordinate origin (the robot's trunk), one of ``parts``.
    models : list of LocalModel
        Exactly ``len(parts) - 1`` fitted models whose ``(parent, child)`` pairs connect all parts without a cycle.
        A model may be traversed in either direction.
    param_covariance : tuple (model indices, ndarray) or None
        The joint fit's covariance of the parameters of several models together (their cross-covariances included):
        ``(k_1, ..., k_j)`` positions in ``models`` of rigid-joint models, and the matrix over their parameter
        increments concatenated in that order. :func:`~body_scheme_core.prediction.uncertainty.position_covariance` uses
        it; models not named contribute their own covariance alone.

    Raises
    ------
    InvalidInputError
        If ids are duplicated or unknown, the root is not a part, or the models do not form a spanning tree.
    NotFittedError
        If a model is not fitted.

    Attributes
    ----------
    parts : tuple of int
        Part ids in the order given; :meth:`predict_batch` uses this order.
    root : int
    models : tuple of LocalModel
    edges : list of tuple (parent, child, model, inverted)
        Tree edges in breadth-first order from the root; ``parent`` is the part nearer the root and ``inverted`` says
        the model predicts ``child2parent`` and is used inverted.
    """

    def __init__(self, parts, root, models, param_covariance=None):
        try:
            parts = tuple(int(p) for p in parts)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"parts must be an iterable of integer ids, got {parts!r}") from exc
        if len(parts) == 0:
            raise InvalidInputError("a body scheme needs at least one part, got parts=()")
        if len(set(parts)) != len(parts):
            raise InvalidInputError(f"part ids must be unique, got {parts}")
        try:
            root = int(root)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"root must be an integer part id, got {root!r}") from exc
        if root not in parts:
            raise InvalidInputError(f"root {root} is not one of the parts {parts}")
        models = tuple(models)
        if len(models) != len(parts) - 1:
            raise InvalidInputError(
                f"a spanning tree over {len(parts)} parts needs exactly {len(parts) - 1} models, got {len(models)}")

        graph = nx.Graph()
        graph.add_nodes_from(parts)
        for model in models:
            if not isinstance(model, LocalModel):
                raise InvalidInputError(f"models must be LocalModel instances, got {type(model).__name__}")
            if model.parent not in graph or model.child not in graph:
                raise InvalidInputError(f"{model.describe()} refers to a part that is not in {parts}")
            if model.parent == model.child:
                raise InvalidInputError(f"{model.describe()} connects a part to itself")
            if graph.has_edge(model.parent, model.child):
                raise InvalidInputError(
                    f"parts {model.parent} and {model.child} are connected by more than one model (a cycle)")
            if not model.is_fitted:
                raise NotFittedError(f"{model.describe()} is not fitted; a body scheme needs fitted models")
            graph.add_edge(model.parent, model.child, model=model)
        # n - 1 distinct edges that connect n nodes form a tree; connectivity alone therefore rules out cycles.
        if not nx.is_connected(graph):
            components = [sorted(c) for c in nx.connected_components(graph)]
            raise InvalidInputError(f"the models do not connect all parts; components: {components}")

        self.parts = parts
        self.root = root
        self.models = models
        self.param_covariance = _checked_param_covariance(models, param_covariance)
        self.edges = []
        self._tree_parent = {root: None}
        self._edge_into = {}
        for parent, child in nx.bfs_edges(graph, root):
            model = graph.edges[parent, child]["model"]
            edge = (parent, child, model, model.parent != parent)
            self.edges.append(edge)
            self._tree_parent[child] = parent
            self._edge_into[child] = edge
        self._paths = {}
        self._path_actions = {}
        self._chains = {}
        for part in parts:
            path = [part]
            while self._tree_parent[path[-1]] is not None:
                path.append(self._tree_parent[path[-1]])
            path.reverse()
            self._paths[part] = tuple(path)
            acts = set()
            for p in path[1:]:
                acts.update(self._edge_into[p][2].actions)
            self._path_actions[part] = tuple(sorted(acts))
            # Per part, what the hot loops of prediction and IK need: (model, inverted, action index list).
            self._chains[part] = tuple((model, inverted, list(model.actions))
                                       for _, _, model, inverted in (self._edge_into[p] for p in path[1:]))
        self._index = {p: i for i, p in enumerate(parts)}
        self.actions_used = tuple(sorted({a for model in models for a in model.actions}))
        # Smallest admissible action-vector length, so a too-short vector gets one clear message from the scheme.
        self.min_n_actions = self.actions_used[-1] + 1 if self.actions_used else 0

    # ------------------------------------------------------------------ structure
    def __contains__(self, part):
        try:
            return int(part) in self._index
        except (TypeError, ValueError):
            return False

    def __repr__(self):
        return f"<BodyScheme parts={self.parts} root={self.root} actions={self.actions_used}>"

    def _check_part(self, part):
        try:
            part = int(part)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"part must be an integer id, got {part!r}") from exc
        if part not in self._index:
            raise InvalidInputError(f"part {part} is not in the body scheme (parts {self.parts})")
        return part

    def edge_into(self, part):
        """The tree edge ``(parent, child, model, inverted)`` ending at ``part``; None for the root."""
        return self._edge_into.get(self._check_part(part))

    def path(self, part):
        """Part ids from the root to ``part``, both included.

        Returns
        -------
        path : tuple of int
        """
        return self._paths[self._check_part(part)]

    def from_root(self, a, b):
        """``(near, far)``: parts ``a`` and ``b`` ordered from the root, the one with the shorter path first (ties: as
        given). The one answer to "which end of an edge is nearer the root"."""
        return (b, a) if len(self.path(b)) < len(self.path(a)) else (a, b)

    def path_actions(self, part):
        """Sorted indices of the actions that influence the pose of ``part`` (the union over its path's models)."""
        return self._path_actions[self._check_part(part)]

    def path_edges(self, part):
        """Tree edges ``(parent, child, model, inverted)`` from the root to ``part``, in order."""
        return [self._edge_into[p] for p in self.path(part)[1:]]

    def describe(self):
        """Multi-line human-readable description of the tree, children indented under their parents."""
        acts = ",".join(f"a{a}" for a in self.actions_used) or "none"
        lines = [f"BodyScheme: {len(self.parts)} parts, root {self.root}, actions {acts}", f"{self.root} (root)"]
        children = {p: [] for p in self.parts}
        for parent, child, model, inverted in self.edges:
            children[parent].append((child, model, inverted))

        def walk(part, prefix):
            for k, (child, model, inverted) in enumerate(children[part]):
                last = k == len(children[part]) - 1
                note = ", inverted" if inverted else ""
                lines.append(f"{prefix}{'`-- ' if last else '|-- '}{child}  via {model.describe()}{note}")
                walk(child, prefix + ("    " if last else "|   "))

        walk(self.root, "")
        return "\n".join(lines)

    # ------------------------------------------------------------------ prediction
    def check_action_vector(self, a):
        """``a`` as one finite action vector (m,) long enough for this scheme's models, or InvalidInputError."""
        a = np.asarray(a, dtype=float)
        if a.ndim == 2 and a.shape[0] == 1:
            a = a[0]
        if a.ndim != 1:
            raise InvalidInputError(f"a must be one action vector of shape (m,), got {a.shape}")
        if a.shape[0] < self.min_n_actions:
            raise InvalidInputError(
                f"the body scheme uses action index {self.min_n_actions - 1}; a must have at least "
                f"{self.min_n_actions} entries, got {a.shape[0]}")
        if not np.all(np.isfinite(a)):
            raise InvalidInputError("a contains NaN or inf")
        return a

    @staticmethod
    def edge_transform(model, inverted, A, return_std=False):
        """Transform(s) parent2child of one tree edge for action vectors ``A`` (k, m) [and std (k, 2)]."""
        if return_std:
            Z, std = model.predict(A, return_std=True)
        else:
            Z = model.predict(A)
        if inverted:
            Z = invert_transform(Z)
        return (Z, np.asarray(std, dtype=float)) if return_std else Z

    def predict(self, a, return_std=False):
        """Maximum-likelihood pose of every part for one action vector (Eq. 8).

        Concatenates the models' predictions from the root outwards, so parts that are never observed are predicted
        as well.

        Parameters
        ----------
        a : array-like, shape (m,)
            Full action vector.
        return_std : bool
            Also return a first-order isotropic standard deviation per part (see :meth:`predict_batch`).

        Returns
        -------
        root2part : dict of int to ndarray, shape (4, 4)
        std : dict of int to ndarray, shape (2,)
            ``[trans (m), rot (rad)]``; only if ``return_std``. Zero for the root.
        """
        a = self.check_action_vector(a)
        if return_std:
            out, std = self.predict_batch(a[None, :], return_std=True)
            return ({p: out[0, k] for k, p in enumerate(self.parts)},
                    {p: std[0, k] for k, p in enumerate(self.parts)})
        root2part = {self.root: np.eye(4)}
        for parent, child, model, inverted in self.edges:
            T = model.predict_one(a)
            root2part[child] = root2part[parent] @ (invert_transform(T) if inverted else T)
        return root2part

    def predict_batch(self, A, return_std=False):
        """Poses of all parts for many action vectors, in ``parts`` order.

        Parameters
        ----------
        A : array-like, shape (n, m)
        return_std : bool
            Also return the propagated std (see Notes).

        Returns
        -------
        root2part : ndarray, shape (n, n_parts, 4, 4)
        std : ndarray, shape (n, n_parts, 2)
            ``[trans (m), rot (rad)]``; only if ``return_std``.

        Notes
        -----
        Uncertainty is propagated along the chain to first order with isotropic errors and independent models. An
        edge with local std ``(s_t, s_r)`` into part ``j`` moves every part ``v`` below it by ``s_t`` and turns it
        about ``j``'s origin by ``s_r``, so that, with positions ``p`` in the root frame::

            var_trans(v) = sum over the edges e -> j on v's path of  s_t(e)^2 + s_r(e)^2 |p_v - p_j|^2
            var_rot(v)   = sum over the same edges of  s_r(e)^2

        The lever term bounds the true displacement ``|dtheta x (p_v - p_j)|`` from above and so errs on the safe
        side; it is exact in the lever arm over any number of edges (a rotation error near the root moves a far tip
        by the whole arm's length, not by each link's). For an inverted edge with local translation ``t`` its
        ``s_t^2`` additionally picks up the model's rotation error at lever arm ``|t|``: ``s_t^2 + |t|^2 s_r^2``.
        The sum over edges is kept as ``sum s_r^2``, ``sum s_r^2 p_j`` and ``sum s_r^2 |p_j|^2`` per part.
        """
        A = check_action_batch(A)
        if A.shape[1] < self.min_n_actions:
            raise InvalidInputError(
                f"A must have at least {self.min_n_actions} action columns, got {A.shape[1]}")
        n, k = A.shape[0], len(self.parts)
        out = np.zeros((n, k, 4, 4))
        out[:, self._index[self.root]] = np.eye(4)
        if return_std:
            var_t, var_r = np.zeros((n, k)), np.zeros((n, k))
            moment, square = np.zeros((n, k, 3)), np.zeros((n, k))  # sum s_r^2 p_j, sum s_r^2 |p_j|^2
        for parent, child, model, inverted in self.edges:
            i, j = self._index[parent], self._index[child]
            if not return_std:
                out[:, j] = out[:, i] @ self.edge_transform(model, inverted, A)
                continue
            T, std = self.edge_transform(model, inverted, A, return_std=True)
            out[:, j] = out[:, i] @ T
            s2 = np.asarray(std, dtype=float).reshape(n, 2) ** 2
            p = out[:, j, :3, 3]
            var_t[:, j] = var_t[:, i] + s2[:, 0] + (np.einsum("ni,ni->n", T[:, :3, 3], T[:, :3, 3]) * s2[:, 1]
                                                    if inverted else 0.0)
            var_r[:, j] = var_r[:, i] + s2[:, 1]
            moment[:, j] = moment[:, i] + s2[:, 1, None] * p
            square[:, j] = square[:, i] + s2[:, 1] * np.einsum("ni,ni->n", p, p)
        if not return_std:
            return out
        p = out[:, :, :3, 3]
        lever = var_r * np.einsum("nki,nki->nk", p, p) - 2.0 * np.einsum("nki,nki->nk", p, moment) + square
        var = np.stack([var_t + np.maximum(lever, 0.0), var_r], axis=-1)
        return out, np.sqrt(np.maximum(var, 0.0))

    def chain_transforms(self, a, part, derivative_step=None):
        """Local transforms along the path from the root to ``part``, each already in root-to-part direction.

        Their product is ``root2part``. Pass the result to :meth:`jacobian` or :meth:`position_jacobian` at the same
        ``a`` to avoid evaluating the forward chain twice (the IK solver does).

        Parameters
        ----------
        a : array-like, shape (m,)
        part : int
        derivative_step : float, optional
            If given, also return forward-difference derivatives of every local transform with this step, computed
            in the same model call (one batched ``predict`` on ``[a, a + h e_k, ...]`` per edge). This costs far less
            than the models' analytic ``jacobian`` (for a GP: one extra row of a kernel product instead of a
            second pass with an SVD derivative), at a relative error of about ``h``.

        Returns
        -------
        T : ndarray, shape (k, 4, 4)
            ``k = len(path(part)) - 1`` transforms (``k = 0`` for the root).
        dT : list of ndarray or None, length k
            Only if ``derivative_step`` is given: per edge ``dT/da`` for the edge model's actions, shape
            ``(len(model.actions), 4, 4)`` in ``model.actions`` order, or ``None`` for a model without actions.
        """
        a = self.check_action_vector(a)
        chain = self._chains[self._check_part(part)]
        T = np.empty((len(chain), 4, 4))
        if derivative_step is None:
            A = a[None, :]
            for i, (model, inverted, _) in enumerate(chain):
                Z = model.predict(A)[0]
                T[i] = _invert_single(Z) if inverted else Z
            return T
        h = float(derivative_step)
        if not (np.isfinite(h) and h > 0.0):
            raise InvalidInputError(f"derivative_step must be a finite number > 0, got {derivative_step!r}")
        dT = []
        for i, (model, inverted, acts) in enumerate(chain):
            A = np.tile(a, (1 + len(acts), 1))
            for j, k in enumerate(acts):
                A[1 + j, k] += h
            Z = model.predict(A)
            if inverted:
                Z = invert_transform(Z)
            T[i] = Z[0]
            dT.append((Z[1:] - Z[0]) / h if acts else None)
        return T, dT

    def predict_part(self, a, part):
        """``root2part`` (4, 4) of one part, evaluating only the models on its path."""
        T = self.chain_transforms(a, part)
        root2part = np.eye(4)
        for Ti in T:
            root2part = root2part @ Ti
        return root2part

    def jacobian(self, a, part, local_transforms=None, local_derivatives=None):
        """``d root2part / d a`` (m, 4, 4), Eq. 10: :func:`~body_scheme_core.prediction.jacobian.jacobian`."""
        return jacobian(self, a, part, local_transforms, local_derivatives)

    def position_jacobian(self, a, part, local_transforms=None, local_derivatives=None):
        """``d position(part) / d a`` (3, m): :func:`~body_scheme_core.prediction.jacobian.position_jacobian`."""
        return position_jacobian(self, a, part, local_transforms, local_derivatives)

    # ------------------------------------------------------------------ persistence
    def to_dict(self):
        """JSON-serialisable dict: parts, root and every model's own ``to_dict()``."""
        return {
            "kind": "body_scheme",
            "version": SCHEME_FORMAT_VERSION,
            "parts": list(self.parts),
            "root": self.root,
            "models": [model.to_dict() for model in self.models],
            **({} if self.param_covariance is None else {"param_covariance": {
                "models": list(self.param_covariance[0]), "matrix": self.param_covariance[1].tolist()}}),
        }

    @classmethod
    def from_dict(cls, data, model_from_dict=None):
        """Rebuild a body scheme from :meth:`to_dict` output.

        Parameters
        ----------
        data : dict
        model_from_dict : callable, optional
            Turns one model dict into a LocalModel. Default: ``body_scheme_core.models.model_from_dict`` (imported
            lazily to avoid an import cycle).

        Raises
        ------
        ModelFileError
            If the dict is not a body scheme of a supported version or is missing keys.
        """
        if model_from_dict is None:
            from ..models import model_from_dict
        if not isinstance(data, dict) or data.get("kind") != "body_scheme":
            raise ModelFileError("not a body scheme dict (expected kind 'body_scheme')")
        if data.get("version") != SCHEME_FORMAT_VERSION:
            raise ModelFileError(
                f"unsupported body scheme version {data.get('version')!r}; this reads {SCHEME_FORMAT_VERSION}")
        try:
            parts, root, model_dicts = data["parts"], data["root"], data["models"]
        except KeyError as exc:
            raise ModelFileError(f"body scheme dict is missing key {exc}") from exc
        models = [model_from_dict(d) for d in model_dicts]
        covariance = data.get("param_covariance")
        try:
            if covariance is not None:
                if not isinstance(covariance, dict) or set(covariance) != {"models", "matrix"}:
                    raise InvalidInputError("param_covariance must be {models: [...], matrix: [[...]]}")
                covariance = (covariance["models"], covariance["matrix"])
            return cls(parts, root, models, covariance)
        except (InvalidInputError, TypeError, ValueError) as exc:
            raise ModelFileError(f"body scheme dict does not describe a valid spanning tree: {exc}") from exc
