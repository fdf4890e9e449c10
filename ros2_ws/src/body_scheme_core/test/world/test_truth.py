"""Tests of the ground truth learned body schemes are judged against (world/truth.py)."""

import numpy as np

from body_scheme_core.models import GPModel, RevoluteModel, StaticModel
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.world import (
    Joint,
    KinematicTree,
    Marker,
    branching_tree,
    is_correct_model,
    is_true_tree,
    least_actions,
    wrong_models,
)


def _revolute(parent, child, actions):
    """A fitted revolute model of the given pair and actions (its parameters do not matter here)."""
    return RevoluteModel(parent, child, actions)._set_fit(np.r_[0, 0, 1.0, np.zeros(9), 1.0], np.eye(10), 1, 0.0)


def _static(parent, child):
    return StaticModel(parent, child).fit(np.zeros((1, 6)), np.eye(4)[None])


def test_the_true_tree_is_recognised_up_to_markers_sharing_a_link():
    """The specification's tree is true, and so is the one hanging the left arm from marker 7; a model on the dummy
    action, or a moving model between the torso's two markers, is not."""
    tree = branching_tree(1, second_torso_marker=True, dummy_action=True)
    models = engineered_models(tree)
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, models))
    rehung = [_revolute(7, 3, (1,)) if m.pair == (2, 3) else m for m in models]
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, rehung))
    dummy = [_revolute(m.parent, m.child, (5,)) if m.pair == (2, 3) else m for m in models]
    assert not is_true_tree(tree, BodyScheme(tree.marker_ids, 1, dummy))
    assert [m.pair for m in wrong_models(tree, dummy)] == [(2, 3)]
    moving = [_revolute(2, 7, (0,)) if m.pair == (2, 7) else m for m in models]
    assert not is_true_tree(tree, BodyScheme(tree.marker_ids, 1, moving))
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, [_static(2, 7) if m.pair == (2, 7) else m
                                                            for m in models]))
    assert not is_true_tree(tree, None)


def _chain_with_a_fixed_link_and_a_bare_link():
    """base (1) -a0- link1 (2) -fixed- tool (3) -a1- bare (no marker) -a2- tip (4); bare -a3- side (5)."""
    z = (0.0, 0.0, 1.0)
    joints = [Joint("j0", "revolute", "base", "link1", axis=z, lower=-1, upper=1, action=0),
              Joint("fix", "fixed", "link1", "tool"),
              Joint("j1", "revolute", "tool", "bare", axis=z, lower=-1, upper=1, action=1),
              Joint("j2", "revolute", "bare", "tip", axis=z, lower=-1, upper=1, action=2),
              Joint("j3", "revolute", "bare", "side", axis=z, lower=-1, upper=1, action=3)]
    markers = [Marker(i, link, np.eye(4), 0.05) for i, link in
               ((1, "base"), (2, "link1"), (3, "tool"), (4, "tip"), (5, "side"))]
    return KinematicTree(joints, markers)


def test_markers_on_fixed_links_are_one_body_and_edges_past_a_bare_link_carry_both_joints():
    """Markers on links joined by a fixed joint relate statically and either can carry the next edge; beyond a link
    without a marker an edge depends on both joints, and the two markers there may hang off each other."""
    tree = _chain_with_a_fixed_link_and_a_bare_link()
    gp = GPModel(3, 4, (1, 2)).fit(np.zeros((3, 4)), np.stack([np.eye(4)] * 3))
    base = [_revolute(1, 2, (0,)), _static(2, 3)]
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, base + [gp, GPModel(3, 5, (1, 3)).fit(
        np.zeros((3, 4)), np.stack([np.eye(4)] * 3))]))
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, base + [gp, GPModel(4, 5, (2, 3)).fit(
        np.zeros((3, 4)), np.stack([np.eye(4)] * 3))]))
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, [_revolute(1, 3, (0,)), _static(2, 3), gp,
                                                            GPModel(2, 5, (1, 3)).fit(np.zeros((3, 4)),
                                                                                     np.stack([np.eye(4)] * 3))]))
    # Correct models, but more actions in all than the robot's tree needs: not the minimum.
    longer = base + [gp, GPModel(1, 5, (0, 1, 3)).fit(np.zeros((3, 4)), np.stack([np.eye(4)] * 3))]
    assert not wrong_models(tree, longer)
    assert not is_true_tree(tree, BodyScheme(tree.marker_ids, 1, longer))


def test_a_blocked_joint_moves_nothing():
    """With action 0 blocked, the correct model between the base and link 1 is static."""
    tree = _chain_with_a_fixed_link_and_a_bare_link()
    assert is_correct_model(tree, _static(1, 2), blocked={0})
    assert not is_correct_model(tree, _revolute(1, 2, (0,)), blocked={0})
    assert is_correct_model(tree, _revolute(1, 2, (0,)))


def test_a_bare_link_rigidly_joined_to_a_marked_one_is_one_action_from_its_markers():
    """A joint on a bare link whose fixed child carries a marker hangs one action off that marker, though the robot's
    marker tree reaches it from above with two (zoo body 12): the tree of fewest actions is the true one."""
    joints = [Joint("j0", "prismatic", "base", "bare", axis=(1, 0, 0), lower=-0.2, upper=0.2, action=0),
              Joint("fixed", "fixed", "bare", "plate"),
              Joint("j1", "revolute", "bare", "arm", axis=(0, 0, 1), lower=-1, upper=1, action=1)]
    markers = [Marker(1, "base", np.eye(4), 0.05), Marker(2, "plate", np.eye(4), 0.05),
               Marker(3, "arm", np.eye(4), 0.05)]
    tree = KinematicTree(joints, markers)
    assert sum(len(tree.path_actions(p, c)) for p, c in tree.marker_tree_edges()) == 3
    assert least_actions(tree) == 2
    assert is_true_tree(tree, BodyScheme(tree.marker_ids, 1, [_revolute(1, 2, (0,)), _revolute(2, 3, (1,))]))
    assert not is_true_tree(tree, BodyScheme(tree.marker_ids, 1, [
        _revolute(1, 2, (0,)), GPModel(1, 3, (0, 1)).fit(np.zeros((3, 2)), np.stack([np.eye(4)] * 3))]))
