"""Tests of the branching-body experiment: its robot, the true-tree judgement and a quick run."""

import math

import numpy as np
import pytest
from body_scheme_apps.experiments import branching

from body_scheme_core.models import RevoluteModel, StaticModel
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.scheme import BodyScheme

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


def test_the_robot_has_two_markers_on_the_torso_and_a_dummy_action():
    """Markers 2 and 7 share the torso; action 5 moves a link without markers: no marker path uses it."""
    tree = branching.robot(0)
    assert tree.marker(2).link == tree.marker(7).link == "torso"
    assert tree.n_actions == 6
    assert all(5 not in tree.path_actions(i, j) for i in tree.marker_ids for j in tree.marker_ids if i != j)


def test_the_true_tree_is_recognised_up_to_markers_sharing_a_link():
    """The specification's tree is true, and so is the one hanging the left arm from marker 7; a model on the dummy
    action, or a moving model between the torso's two markers, is not."""
    tree = branching.robot(1)
    models = engineered_models(tree)
    assert branching.is_true_tree(tree, BodyScheme(tree.marker_ids, 1, models))
    swapped = [m for m in models if {m.parent, m.child} != {2, 3}]
    swapped.append(next(m for m in engineered_models(tree) if m.pair == (2, 3)))
    rehung = [RevoluteModel(7, 3, (1,))._set_fit(np.r_[0, 0, 1.0, np.zeros(9), 1.0], np.eye(10), 1, 0.0)
              if m.pair == (2, 3) else m for m in swapped]
    assert branching.is_true_tree(tree, BodyScheme(tree.marker_ids, 1, rehung))
    dummy = [RevoluteModel(m.parent, m.child, (5,))._set_fit(np.r_[0, 0, 1.0, np.zeros(9), 1.0], np.eye(10), 1, 0.0)
             if m.pair == (2, 3) else m for m in models]
    assert not branching.is_true_tree(tree, BodyScheme(tree.marker_ids, 1, dummy))
    moving = [RevoluteModel(2, 7, (0,))._set_fit(np.r_[0, 0, 1.0, np.zeros(9), 1.0], np.eye(10), 1, 0.0)
              if m.pair == (2, 7) else m for m in models]
    assert not branching.is_true_tree(tree, BodyScheme(tree.marker_ids, 1, moving))
    assert branching.is_true_tree(tree, BodyScheme(tree.marker_ids, 1, [
        StaticModel(2, 7).fit(np.zeros((1, 6)), np.eye(4)[None]) if m.pair == (2, 7) else m for m in models]))
    assert not branching.is_true_tree(tree, None)


def test_a_quick_run_reports_every_figure():
    """A quick run returns the FIGURES keys, finite, with the fraction 0 or 1 and counts >= 0."""
    result = branching.run(0, quick=True)
    assert set(branching.FIGURES) <= set(result)
    assert all(math.isfinite(result[key]) for key in branching.FIGURES)
    assert result["branching_true_tree_fraction"] in (0.0, 1.0)
    assert result["branching_false_mismatches"] >= 0 and result["branching_repairs"] >= 0
