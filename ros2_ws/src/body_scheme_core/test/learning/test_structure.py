"""Tests of candidate enumeration and the layered minimum-spanning-tree structure search."""

import itertools
import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning.quality import class_rank
from body_scheme_core.learning.structure import (
    action_subsets,
    enumerate_candidates,
    n_candidates,
    replacement_action_sets,
    select_spanning_tree,
)


def test_candidate_count_matches_the_paper_formula():
    """7 parts, 6 actions, at most 2 actions: the paper's C(7,2) * (1 + 6 + 15) = 462 GPs; with rigid joints each pair
    has 1 static + 6 x (prismatic, revolute, GP) + 15 GPs = 34 candidates; ordered by layer, then class rank."""
    paper = enumerate_candidates([1, 2, 3, 4, 5, 6, 7], 6, 2, kinds=("gp",))
    assert len(paper) == n_candidates(7, 6, 2, ("gp",)) == 462
    candidates = enumerate_candidates([1, 2, 3, 4, 5, 6, 7], 6, 2)
    assert len(candidates) == n_candidates(7, 6, 2) == 21 * 34 == 714
    order = [(len(acts), class_rank(kind)) for _, _, acts, kind in candidates]
    assert order == sorted(order)
    assert len(set(candidates)) == len(candidates)
    assert {kind for _, _, acts, kind in candidates if not acts} == {"static"}
    assert {kind for _, _, acts, kind in candidates if len(acts) == 2} == {"gp"}
    assert action_subsets(3, 5) == [(), (0,), (1,), (2,), (0, 1), (0, 2), (1, 2), (0, 1, 2)]


def test_candidates_follow_the_given_part_order():
    """Each pair appears once, parent before child in the given (arbitrary) id order."""
    candidates = enumerate_candidates([42, 7, 13], 1, 1)
    pairs = {(i, j) for i, j, _, _ in candidates}
    assert pairs == {(42, 7), (42, 13), (7, 13)}
    with pytest.raises(InvalidInputError):
        enumerate_candidates([1, 1], 1, 1)


def test_replacements_are_ordered_by_relative_complexity():
    """Same action set first, then one action added or removed, then two (paper Eq. 11)."""
    sets = replacement_action_sets((5,), 6, 2, max_relative=2)
    assert sets[0] == (0, (5,))
    rel = [r for r, _ in sets]
    assert rel == sorted(rel)
    assert (1, ()) in sets and (1, (0, 5)) in sets and (2, (0,)) in sets
    assert all(len(acts) <= 2 for _, acts in sets)
    assert len(sets) == 1 + (1 + 5) + 5
    # A failed model above max_complexity may still be re-learned with its own actions.
    assert replacement_action_sets((0, 1, 2), 3, 1, max_relative=0) == [(0, (0, 1, 2))]


def test_tree_picks_the_cheapest_model_per_edge():
    """Among parallel models of one pair the cheapest wins; keys are returned."""
    models = [(1, 2, "a", 1, 1.5), (1, 2, "b", 1, 1.2), (2, 3, "c", 0, 0.3), (1, 3, "d", 2, 2.1)]
    assert sorted(select_spanning_tree([1, 2, 3], models)) == ["b", "c"]


def test_no_tree_when_the_valid_models_do_not_connect_all_parts():
    """Returns None when some part is unreachable."""
    assert select_spanning_tree([1, 2, 3], [(1, 2, "a", 0, 0.5)]) is None
    assert select_spanning_tree([5], []) == []
    with pytest.raises(InvalidInputError):
        select_spanning_tree([1, 2], [(1, 9, "x", 0, 0.1)], layered=False)


def test_layered_search_equals_the_plain_minimum_spanning_tree():
    """With non-overlapping layer costs, stopping at the first connecting layer gives the global MST."""
    rng = np.random.default_rng(0)
    for trial in range(50):
        n = int(rng.integers(2, 8))
        parts = [int(p) for p in rng.permutation(100)[:n]]
        models = []
        for key, (i, j) in enumerate(itertools.combinations(parts, 2)):
            for k in range(3):
                if rng.uniform() < 0.4:
                    layer = int(rng.integers(0, 3))
                    models.append((i, j, (key, k), layer, layer + rng.uniform(0.0, math.nextafter(1.0, 0.0))))
        layered = select_spanning_tree(parts, models, layered=True)
        plain = select_spanning_tree(parts, models, layered=False)
        assert (layered is None) == (plain is None), trial
        if layered is not None:
            assert sorted(layered) == sorted(plain), trial
            assert len(layered) == n - 1


def test_layered_search_stops_at_the_first_connecting_layer():
    """A cheap layer-1 tree is found although layer-2 models would connect too; layer 2 is never needed."""
    models = [(1, 2, "x1", 1, 1.9), (2, 3, "y1", 1, 1.9), (1, 2, "x2", 2, 2.0), (2, 3, "y2", 2, 2.0),
              (1, 3, "z0", 0, 0.99)]
    assert sorted(select_spanning_tree([1, 2, 3], models)) == ["x1", "z0"]


def test_branching_tree_with_any_numbering():
    """A star-shaped tree over arbitrary ids is recovered exactly."""
    parts = [30, 4, 17, 99, 8]
    true_edges = {(30, 4), (30, 17), (30, 99), (17, 8)}
    models = [(i, j, (i, j), 1, 1.1) for i, j in true_edges]
    models += [(i, j, (i, j, "bad"), 1, 1.8) for i, j in itertools.combinations(parts, 2) if (i, j) not in true_edges]
    keys = select_spanning_tree(parts, models)
    assert set(keys) == true_edges
