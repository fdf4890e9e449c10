"""Tests of the branching-body experiment: its robot and a quick run (the true-tree judgement: core test_truth)."""

import math

import pytest

from body_scheme_apps.experiments import branching

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


def test_the_robot_has_two_markers_on_the_torso_and_a_dummy_action():
    """Markers 2 and 7 share the torso; action 5 moves a link without markers: no marker path uses it."""
    tree = branching.robot(0)
    assert tree.marker(2).link == tree.marker(7).link == "torso"
    assert tree.n_actions == 6
    assert all(5 not in tree.path_actions(i, j) for i in tree.marker_ids for j in tree.marker_ids if i != j)


def test_a_quick_run_reports_every_figure():
    """A quick run returns the FIGURES keys, finite, with the fraction 0 or 1 and counts >= 0."""
    result = branching.run(0, quick=True)
    assert set(branching.FIGURES) <= set(result)
    assert all(math.isfinite(result[key]) for key in branching.FIGURES)
    assert result["branching_true_tree_fraction"] in (0.0, 1.0)
    assert result["branching_false_mismatches"] >= 0 and result["branching_repairs"] >= 0
