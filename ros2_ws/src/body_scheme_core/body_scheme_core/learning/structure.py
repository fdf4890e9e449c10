"""Structure search: candidate local models and the minimum spanning tree over the valid ones (paper Sec. III-C).

The body scheme is the spanning tree over all body parts whose local models maximise the overall quality, i.e.
minimise the summed cost of :func:`~body_scheme_core.learning.quality.model_cost`. Candidates are enumerated in
complexity layers (number of actions a model depends on). Because costs of different layers never overlap (every valid
model of layer ``k`` costs in ``[k, k + 1)``), Kruskal's algorithm consumes all edges of layer ``k`` before any edge of
layer ``k + 1``; so once the valid models of layers ``<= k`` connect all parts, the minimum spanning tree over them
*is* the minimum spanning tree over all valid models. :func:`select_spanning_tree` therefore searches layer by
layer and stops at the first layer that connects all parts, exactly as the paper prescribes, without ever looking
at higher layers.

The graph is a networkx ``MultiGraph`` whose nodes are part ids and whose parallel edges are the competing models
of one pair (edge key = model key), so any part numbering and any tree shape (chains, branches) work alike.
"""

from __future__ import annotations

import itertools
import math

import networkx as nx

from ..errors import InvalidInputError
from .quality import class_rank, relative_complexity

__all__ = [
    "CANDIDATE_KINDS",
    "action_subsets",
    "kinds_for",
    "enumerate_candidates",
    "n_candidates",
    "replacement_action_sets",
    "replacement_candidates",
    "select_spanning_tree",
]

#: The local-model classes a learner can instantiate as candidates.
CANDIDATE_KINDS = ("static", "prismatic", "revolute", "gp")


def kinds_for(actions, kinds=CANDIDATE_KINDS):
    """Model classes instantiated for one action set, by class rank: static for no action, prismatic, revolute and
    GP for one, GP for more (no rigid form spans several actions). A GP on no action stands in for ``static`` when
    static models are not among ``kinds``."""
    n = len(actions)
    if n == 0:
        out = ["static"] if "static" in kinds else (["gp"] if "gp" in kinds else [])
    elif n == 1:
        out = [k for k in ("prismatic", "revolute", "gp") if k in kinds]
    else:
        out = ["gp"] if "gp" in kinds else []
    return sorted(out, key=class_rank)


def action_subsets(n_actions, max_complexity):
    """All subsets of ``range(n_actions)`` with at most ``max_complexity`` elements, by size then lexicographically.

    Returns
    -------
    subsets : list of tuple of int
        Starts with ``()``.
    """
    if n_actions < 0 or max_complexity < 0:
        raise InvalidInputError(f"need n_actions >= 0 and max_complexity >= 0, got {n_actions}, {max_complexity}")
    return [c for k in range(min(max_complexity, n_actions) + 1) for c in itertools.combinations(range(n_actions), k)]


def enumerate_candidates(part_ids, n_actions, max_complexity, kinds=CANDIDATE_KINDS):
    """Every candidate local model of the fully connected network (paper Sec. III-C1, Fig. 4).

    Parameters
    ----------
    part_ids : sequence of int
        Part ids; a pair ``(p_i, p_j)`` is enumerated once, with ``i < j`` in the given order, and its model
        predicts ``p_i 2 p_j`` (the reverse direction is the inverse transform).
    n_actions : int
    max_complexity : int
        Largest number of actions a candidate depends on.
    kinds : iterable of str
        Model classes to instantiate (:func:`kinds_for` gives the classes per action set).

    Returns
    -------
    candidates : list of tuple (parent, child, actions, kind)
        Ordered by complexity layer, then class rank, then pair, then action indices.
    """
    parts = [int(p) for p in part_ids]
    if len(set(parts)) != len(parts):
        raise InvalidInputError(f"part ids must be unique, got {parts}")
    pairs = list(itertools.combinations(parts, 2))
    subsets = action_subsets(n_actions, max_complexity)
    out = [(i, j, acts, kind) for acts in subsets for kind in kinds_for(acts, kinds) for i, j in pairs]
    return sorted(out, key=lambda c: (len(c[2]), class_rank(c[3])))


def n_candidates(n_parts, n_actions, max_complexity, kinds=CANDIDATE_KINDS):
    """Number of candidates: ``C(n, 2)`` times the (action set, class) combinations of :func:`kinds_for`."""
    per_pair = sum(math.comb(n_actions, k) * len(kinds_for(tuple(range(k)), kinds))
                   for k in range(min(max_complexity, n_actions) + 1))
    return math.comb(n_parts, 2) * per_pair


def replacement_action_sets(failed_actions, n_actions, max_complexity, max_relative=None):
    """Action sets for replacements of a failed model, ordered by relative complexity (paper Eq. 11).

    Parameters
    ----------
    failed_actions : iterable of int
        Action set of the model being replaced.
    n_actions, max_complexity : int
    max_relative : int or None
        Largest relative complexity ``|A2 sym-diff A1|`` to include; ``None``: all.

    Returns
    -------
    sets : list of tuple (relative_complexity, actions)
        The same action set first (0), then one action added or removed (1), and so on; within a layer by
        absolute complexity, then lexicographically.
    """
    failed = tuple(sorted(int(a) for a in failed_actions))
    out = []
    for acts in action_subsets(n_actions, max(max_complexity, len(failed))):
        if len(acts) > max_complexity and acts != failed:
            continue
        rel = relative_complexity(acts, failed)
        if max_relative is None or rel <= max_relative:
            out.append((rel, acts))
    return sorted(out, key=lambda item: (item[0], len(item[1]), item[1]))


def replacement_candidates(failed_actions, n_actions, max_complexity, max_relative=None, kinds=CANDIDATE_KINDS):
    """``(relative_complexity, actions, kind)`` of the replacements of a failed model (paper Eq. 11).

    Every action set of :func:`replacement_action_sets` with each class of :func:`kinds_for`, ordered by relative
    complexity, then class rank.
    """
    out = [(rel, acts, kind) for rel, acts in replacement_action_sets(failed_actions, n_actions, max_complexity,
                                                                       max_relative)
           for kind in kinds_for(acts, kinds)]
    return sorted(out, key=lambda item: (item[0], class_rank(item[2]), len(item[1]), item[1]))


def select_spanning_tree(part_ids, models, layered=True):
    """Minimum-cost spanning tree over valid local models (paper Sec. III-C2).

    Parameters
    ----------
    part_ids : iterable of int
        All body parts; the tree must cover every one of them.
    models : iterable of tuple (parent, child, key, layer, cost)
        The *valid* models only. ``key`` identifies the model (any hashable), ``layer`` is its (relative)
        complexity and ``cost`` its :func:`~body_scheme_core.learning.quality.model_cost`, which must lie in
        ``[layer, layer + 1)``.
    layered : bool
        Search layer by layer and stop at the first layer whose models connect all parts (the paper's heuristic).
        With non-overlapping costs the result equals the plain minimum spanning tree over all models
        (``layered=False``), only cheaper to compute.

    Returns
    -------
    keys : list or None
        Keys of the ``len(part_ids) - 1`` selected models in Kruskal order (cheapest first), or ``None`` if the
        valid models do not connect all parts. A single part gives ``[]``.
    """
    parts = [int(p) for p in part_ids]
    if len(parts) <= 1:
        return []
    edges = sorted(models, key=lambda m: m[3]) if layered else list(models)
    graph = nx.MultiGraph()
    graph.add_nodes_from(parts)
    if layered:
        k = 0
        while k < len(edges):
            layer = edges[k][3]
            while k < len(edges) and edges[k][3] == layer:
                u, v, key, _, cost = edges[k]
                graph.add_edge(u, v, key=key, weight=cost)
                k += 1
            if nx.is_connected(graph):
                break
    else:
        for u, v, key, _, cost in edges:
            graph.add_edge(u, v, key=key, weight=cost)
    if graph.number_of_nodes() != len(parts):
        unknown = sorted(set(graph.nodes) - set(parts))
        raise InvalidInputError(f"models refer to parts {unknown} that are not in {parts}")
    if not nx.is_connected(graph):
        return None
    mst = nx.minimum_spanning_edges(graph, algorithm="kruskal", weight="weight", keys=True, data=False)
    return [key for _, _, key in mst]
