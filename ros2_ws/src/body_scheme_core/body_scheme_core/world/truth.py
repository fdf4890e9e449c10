"""The ground truth a learned body scheme is judged against: which local models and which trees are the true ones.

A local model between two markers is *correct* when it depends on exactly the commanded joints on the kinematic path
between them: none between two markers of one rigid body (links joined by fixed joints, passive joints or blocked
ones), and never an action that moves nothing observed. A blocked joint no longer moves, so after a block the correct
models no longer depend on its action.

A learned body scheme is *true* when every one of its models is correct and together they depend on as few actions
as any spanning tree of correct models can (the paper's minimum spanning tree by complexity). Several trees can be
true: two markers on one rigid body can each carry the next link's edge, and two markers beyond a link without a
marker can hang off each other or off the marker above. The robot's own marker tree
(:meth:`~body_scheme_core.world.tree.KinematicTree.marker_tree_edges`) is one of them except where a link without a
marker is rigidly joined to a marked one: a joint on the bare link is one action from the marked link's markers.
"""

from __future__ import annotations

__all__ = ["is_correct_model", "wrong_models", "is_true_tree", "least_actions"]


def _moving_actions(tree, id_i, id_j, blocked):
    return set(tree.path_actions(id_i, id_j)) - set(blocked)


def is_correct_model(tree, model, blocked=()):
    """Whether a local model ``model`` (``parent``, ``child``, ``actions``) describes the true relation of its markers.

    Parameters
    ----------
    tree : KinematicTree
    model : LocalModel or TrackedModel
    blocked : iterable of int
        Actions whose joints are blocked (they move nothing).
    """
    return set(model.actions) == _moving_actions(tree, model.parent, model.child, blocked)


def wrong_models(tree, models, blocked=()):
    """The models of a learned tree that are not correct (:func:`is_correct_model`), in the given order."""
    return [m for m in models if not is_correct_model(tree, m, blocked)]


def is_true_tree(tree, scheme, blocked=()):
    """Whether ``scheme`` (a :class:`~body_scheme_core.prediction.scheme.BodyScheme`, or None) is a true body scheme of
    ``tree`` (see the module docstring)."""
    if scheme is None:
        return False
    if wrong_models(tree, scheme.models, blocked):
        return False
    return sum(len(m.actions) for m in scheme.models) == least_actions(tree, blocked)


def least_actions(tree, blocked=()):
    """The fewest actions a spanning tree of correct models over ``tree``'s markers depends on in total (Kruskal's
    minimum spanning tree over every pair, weighed by its moving actions)."""
    ids = list(tree.marker_ids)
    pairs = sorted((len(_moving_actions(tree, a, b, blocked)), a, b) for k, a in enumerate(ids) for b in ids[k + 1:])
    root = {i: i for i in ids}

    def find(i):
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    total = 0
    for weight, a, b in pairs:
        ra, rb = find(a), find(b)
        if ra != rb:
            root[ra] = rb
            total += weight
    return total
