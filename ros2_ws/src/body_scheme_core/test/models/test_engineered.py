"""Tests of body_scheme_core.models.engineered: the exact local model from the robot's specification."""

import json

import networkx as nx
import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.models.engineered import EngineeredModel, engineered_models
from body_scheme_core.world import arm_4dof, branching_tree, planar_2dof, powercube_6dof, random_tree

TREES = [planar_2dof(), arm_4dof(), powercube_6dof(), branching_tree(seed=3),
         random_tree(7, seed=4, prismatic_fraction=0.4), random_tree(5, seed=5, branching=False)]


def _random_pairs(tree, rng, n=6):
    ids = np.array(tree.marker_ids)
    return [tuple(rng.choice(ids, size=2, replace=False)) for _ in range(n)]


@pytest.mark.parametrize("tree", TREES)
def test_predict_equals_relative_transform(tree):
    """predict(A) equals tree.relative_transform for any pair of markers, edges or not."""
    rng = np.random.default_rng(0)
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(8, tree.n_actions))
    for i, j in _random_pairs(tree, rng) + tree.marker_tree_edges():
        model = EngineeredModel.from_tree(tree, i, j)
        Z, std = model.predict(A, return_std=True)
        np.testing.assert_allclose(Z, tree.relative_transform(i, j, A), atol=1e-12)
        np.testing.assert_array_equal(std, np.zeros((8, 2)))
        assert model.actions == tree.path_actions(i, j)


@pytest.mark.parametrize("tree", TREES)
def test_jacobian_matches_finite_differences(tree):
    """The analytic Jacobian equals central differences to 1e-7, and is zero for unused actions."""
    rng = np.random.default_rng(0)
    eps = 1e-6
    for i, j in _random_pairs(tree, rng):
        model = EngineeredModel.from_tree(tree, i, j)
        a = rng.uniform(tree.action_lower, tree.action_upper)
        J = model.jacobian(a)
        assert J.shape == (tree.n_actions, 4, 4)
        for k in range(tree.n_actions):
            step = np.zeros_like(a)
            step[k] = eps
            numeric = (model.predict(a + step)[0] - model.predict(a - step)[0]) / (2 * eps)
            np.testing.assert_allclose(J[k], numeric, atol=1e-7)
            if k not in model.actions:
                np.testing.assert_array_equal(J[k], 0.0)


def test_jacobian_of_planar_end_effector_is_textbook():
    """d(position of marker 3 in marker 1)/dq matches the planar-arm Jacobian."""
    model = EngineeredModel.from_tree(planar_2dof(), 1, 3)
    q1, q2 = 0.4, -0.7
    J = model.jacobian([q1, q2])[:, :2, 3]
    expected = np.array([[-0.5 * np.sin(q1) - 0.4 * np.sin(q1 + q2), 0.5 * np.cos(q1) + 0.4 * np.cos(q1 + q2)],
                         [-0.4 * np.sin(q1 + q2), 0.4 * np.cos(q1 + q2)]])
    np.testing.assert_allclose(J, expected, atol=1e-12)


@pytest.mark.parametrize("tree", TREES)
def test_to_dict_round_trip_through_json(tree):
    """to_dict is JSON-able and from_dict rebuilds a model with identical predictions."""
    rng = np.random.default_rng(0)
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(4, tree.n_actions))
    for model in engineered_models(tree):
        again = EngineeredModel.from_dict(json.loads(json.dumps(model.to_dict())))
        assert (again.parent, again.child, again.actions) == (model.parent, model.child, model.actions)
        np.testing.assert_array_equal(again.predict(A), model.predict(A))


@pytest.mark.parametrize("tree", TREES)
def test_engineered_models_span_all_markers(tree):
    """engineered_models(tree) gives n - 1 models whose pairs form a spanning tree over the markers."""
    models = engineered_models(tree)
    graph = nx.Graph([model.pair for model in models])
    graph.add_nodes_from(tree.marker_ids)
    assert len(models) == len(tree.marker_ids) - 1
    assert nx.is_tree(graph)
    assert set(graph.nodes) == set(tree.marker_ids)


def test_engineered_body_scheme_reproduces_marker_poses():
    """Composing the engineered models from the root marker gives every marker's pose relative to the root."""
    tree = branching_tree(seed=0)
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    root = tree.root_marker
    poses = {root: np.eye(4)}
    for model in engineered_models(tree):  # edges are ordered parents first
        poses[model.child] = poses[model.parent] @ model.predict(a)[0]
    for marker_id in tree.marker_ids:
        np.testing.assert_allclose(poses[marker_id], tree.relative_transform(root, marker_id, a), atol=1e-12)


def test_fit_is_a_no_op_and_model_always_fitted():
    """fit returns self without changing predictions; the model is always fitted."""
    tree = planar_2dof()
    model = EngineeredModel.from_tree(tree, 2, 3)
    assert model.is_fitted
    A = np.random.default_rng(0).uniform(-1, 1, size=(5, 2))
    before = model.predict(A)
    assert model.fit(A, np.tile(np.eye(4), (5, 1, 1))) is model
    np.testing.assert_array_equal(model.predict(A), before)
    assert model.kind == "engineered" and model.complexity == 1
    assert model.describe() == "engineered(2->3 | a1)"


def test_static_pair_has_no_actions():
    """Two markers on the same link give a constant model of complexity 0."""
    tree = powercube_6dof()
    model = EngineeredModel.from_tree(tree, 3, 3)
    assert model.actions == ()
    np.testing.assert_allclose(model.predict(np.zeros((2, 6))), np.tile(np.eye(4), (2, 1, 1)), atol=1e-12)


def test_invalid_input_rejected():
    """Mismatched actions, bad chains and short action vectors raise; bad dicts raise ModelFileError."""
    tree = planar_2dof()
    model = EngineeredModel.from_tree(tree, 1, 3)
    with pytest.raises(InvalidInputError, match="exactly the chain"):
        EngineeredModel(1, 3, (0,), model.chain)
    with pytest.raises(InvalidInputError, match="unknown type"):
        EngineeredModel(1, 3, (), [{"type": "helical"}])
    with pytest.raises(InvalidInputError, match="unit"):
        EngineeredModel(1, 3, (0,), [{"type": "revolute", "axis": [0, 0, 2], "action": 0}])
    with pytest.raises(InvalidInputError, match="length"):
        model.predict(np.zeros((1, 1)))
    with pytest.raises(ModelFileError):
        EngineeredModel.from_dict({"kind": "engineered", "parent": 1})
    with pytest.raises(ModelFileError):
        EngineeredModel.from_dict({"kind": "gp"})
    with pytest.raises(ModelFileError):
        bad_chain = [{"type": "fixed", "transform": np.ones((4, 4)).tolist()}]
        EngineeredModel.from_dict({**model.to_dict(), "chain": bad_chain})
