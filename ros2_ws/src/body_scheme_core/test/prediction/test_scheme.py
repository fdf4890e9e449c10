"""Tests of BodyScheme: structure validation, forward prediction, uncertainty, Jacobian and persistence."""

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from body_scheme_core.errors import InvalidInputError, ModelFileError, NotFittedError
from body_scheme_core.models.base import LocalModel
from body_scheme_core.models.engineered import EngineeredModel, engineered_models
from body_scheme_core.models.gp import GPModel
from body_scheme_core.models.static import StaticModel
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.transforms import invert_transform, transform_from_rotvec
from body_scheme_core.world import branching_tree, powercube_6dof


def rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def drot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    T = np.zeros((4, 4))
    T[:2, :2] = [[-s, -c], [c, -s]]
    return T


class RevoluteModel(LocalModel):
    """Analytic test model ``parent2child(a) = A @ Rz(a_k) @ B`` (static ``A @ B`` without an action)."""

    kind = "test_revolute"

    def __init__(self, parent, child, action=None, A=None, B=None, std=(0.0, 0.0), analytic=True):
        super().__init__(parent, child, () if action is None else (action,))
        self.A = np.eye(4) if A is None else np.asarray(A, dtype=float)
        self.B = np.eye(4) if B is None else np.asarray(B, dtype=float)
        self.std = np.asarray(std, dtype=float)
        self.analytic = analytic

    @property
    def is_fitted(self):
        return True

    def fit(self, A, Z):
        return self

    def predict(self, A, return_std=False):
        q = self._select(A)
        angles = q[:, 0] if self.actions else np.zeros(len(q))
        Z = np.array([self.A @ rot_z(t) @ self.B for t in angles])
        if return_std:
            return Z, np.tile(self.std, (len(Z), 1))
        return Z

    def jacobian(self, a, eps=1e-6):
        if not self.analytic:
            return super().jacobian(a, eps)
        a = np.asarray(a, dtype=float)
        J = np.zeros((a.shape[0], 4, 4))
        for k in self.actions:
            J[k] = self.A @ drot_z(a[k]) @ self.B
        return J

    def to_dict(self):
        return {"kind": self.kind, "parent": self.parent, "child": self.child, "actions": list(self.actions),
                "A": self.A.tolist(), "B": self.B.tolist(), "std": self.std.tolist()}

    @classmethod
    def from_dict(cls, data):
        action = data["actions"][0] if data["actions"] else None
        return cls(data["parent"], data["child"], action, data["A"], data["B"], data["std"])


class UnfittedModel(RevoluteModel):
    @property
    def is_fitted(self):
        return False


def random_transform(rng, scale=0.3):
    return transform_from_rotvec(rng.normal(size=3), scale * rng.normal(size=3))


def random_revolute(rng, parent, child, action, **kwargs):
    return RevoluteModel(parent, child, action, random_transform(rng), random_transform(rng), **kwargs)


def branching_scheme(rng, analytic=True):
    """Tree over parts (7, 3, 12, 5, 9) rooted at 7: 7->3->12 and 3->5 (inverted), 7->9 (inverted, static)."""
    models = [
        random_revolute(rng, 7, 3, 0, analytic=analytic),
        random_revolute(rng, 3, 12, 1, analytic=analytic),
        random_revolute(rng, 5, 3, 2, analytic=analytic),  # stored 5->3, traversed 3->5
        random_revolute(rng, 9, 7, None),  # static, traversed 7->9
    ]
    return BodyScheme((7, 3, 12, 5, 9), 7, models), models


def test_predict_chains_models_from_root():
    """predict concatenates the models along each path; unobserved parts are predicted from actions alone."""
    rng = np.random.default_rng(0)
    scheme, (m73, m312, m53, m97) = branching_scheme(rng)
    a = rng.uniform(-np.pi, np.pi, size=3)
    root2part = scheme.predict(a)
    assert set(root2part) == {7, 3, 12, 5, 9}
    assert_allclose(root2part[7], np.eye(4))
    Z73 = m73.predict(a)[0]
    assert_allclose(root2part[3], Z73)
    assert_allclose(root2part[12], Z73 @ m312.predict(a)[0])
    assert_allclose(root2part[5], Z73 @ invert_transform(m53.predict(a)[0]))
    assert_allclose(root2part[9], invert_transform(m97.predict(a)[0]))


def test_inverted_edges_are_marked():
    """Edges traversed against the model direction are flagged inverted, with parent nearer the root."""
    rng = np.random.default_rng(0)
    scheme, models = branching_scheme(rng)
    edges = {(p, c): (model, inv) for p, c, model, inv in scheme.edges}
    assert set(edges) == {(7, 3), (3, 12), (3, 5), (7, 9)}
    assert edges[(7, 3)] == (models[0], False)
    assert edges[(3, 5)] == (models[2], True)
    assert edges[(7, 9)] == (models[3], True)
    assert scheme.path(12) == (7, 3, 12)
    assert scheme.path(7) == (7,)
    assert scheme.path_actions(12) == (0, 1)
    assert scheme.path_actions(9) == ()
    assert scheme.actions_used == (0, 1, 2)


def test_chain_with_every_edge_inverted_equals_forward_chain():
    """A chain stored tip-to-root predicts the same poses as the same chain stored root-to-tip."""
    rng = np.random.default_rng(0)
    forward = [random_revolute(rng, 1, 2, 0), random_revolute(rng, 2, 3, 1)]
    backward = [RevoluteModel(3, 2, 1, invert_transform(forward[1].B), invert_transform(forward[1].A)),
                RevoluteModel(2, 1, 0, invert_transform(forward[0].B), invert_transform(forward[0].A))]
    # inverse of A Rz(t) B is B^-1 Rz(-t) A^-1: flip the sign of the actions to compare.
    a = rng.uniform(-2, 2, size=2)
    fwd = BodyScheme((1, 2, 3), 1, forward).predict(a)
    bwd = BodyScheme((1, 2, 3), 1, backward).predict(-a)
    for part in (1, 2, 3):
        assert_allclose(bwd[part], fwd[part], atol=1e-12)


def test_root_can_be_any_part():
    """Re-rooting the same models gives poses related by the new root's pose in the old root frame."""
    rng = np.random.default_rng(0)
    _, models = branching_scheme(rng)
    a = rng.uniform(-np.pi, np.pi, size=3)
    at7 = BodyScheme((7, 3, 12, 5, 9), 7, models).predict(a)
    at12 = BodyScheme((7, 3, 12, 5, 9), 12, models).predict(a)
    for part in (7, 3, 12, 5, 9):
        assert_allclose(at12[part], invert_transform(at7[12]) @ at7[part], atol=1e-12)


def test_from_root_orders_an_edges_ends_whichever_part_is_the_root():
    """The end nearer the root first, in either argument order and after re-rooting; two parts at the same depth (not
    an edge) stay as given."""
    _, models = branching_scheme(np.random.default_rng(0))
    scheme = BodyScheme((7, 3, 12, 5, 9), 7, models)
    for parent, child in ((e[0], e[1]) for e in scheme.edges):
        assert scheme.from_root(parent, child) == scheme.from_root(child, parent) == (parent, child)
    rerooted = BodyScheme((7, 3, 12, 5, 9), 12, models)
    for parent, child in ((e[0], e[1]) for e in rerooted.edges):
        assert rerooted.from_root(child, parent) == (parent, child)
    a, b = (p for p in scheme.parts if len(scheme.path(p)) == 2)  # 3 and 9, both below the root
    assert scheme.from_root(a, b) == (a, b) and scheme.from_root(b, a) == (b, a)


def test_predict_batch_matches_predict():
    """predict_batch stacks predict in parts order, including the std."""
    rng = np.random.default_rng(0)
    _, models = branching_scheme(rng)
    for model in models:
        model.std = rng.uniform(0.01, 0.1, size=2)
    scheme = BodyScheme((7, 3, 12, 5, 9), 7, models)
    A = rng.uniform(-np.pi, np.pi, size=(4, 3))
    P, S = scheme.predict_batch(A, return_std=True)
    assert P.shape == (4, 5, 4, 4)
    assert S.shape == (4, 5, 2)
    assert_allclose(scheme.predict_batch(A), P)
    for n, a in enumerate(A):
        root2part, std = scheme.predict(a, return_std=True)
        for i, part in enumerate(scheme.parts):
            assert_allclose(P[n, i], root2part[part], atol=1e-12)
            assert_allclose(S[n, i], std[part], atol=1e-12)


def test_std_propagates_along_the_chain():
    """Position variance grows by lever arm times parent rotation variance plus local variance; rot var adds."""
    offset = np.eye(4)
    offset[:3, 3] = [0.5, 0.0, 0.0]
    models = [RevoluteModel(0, 1, 0, B=offset, std=(0.01, 0.02)), RevoluteModel(1, 2, 1, B=offset, std=(0.03, 0.04))]
    _, std = BodyScheme((0, 1, 2), 0, models).predict([0.3, -0.2], return_std=True)
    assert_allclose(std[0], [0.0, 0.0])
    assert_allclose(std[1], [0.01, 0.02])
    assert_allclose(std[2], [np.sqrt(0.01**2 + 0.25 * 0.02**2 + 0.03**2), np.sqrt(0.02**2 + 0.04**2)])
    # Inverted edge: the inverse translation -R^T t also carries the model's own rotation error at lever |t|.
    inverted = [RevoluteModel(1, 0, 0, A=offset, std=(0.01, 0.02))]
    _, std = BodyScheme((0, 1), 0, inverted).predict([0.3], return_std=True)
    assert_allclose(std[1], [np.sqrt(0.01**2 + 0.25 * 0.02**2), 0.02])



def test_a_rotation_error_moves_a_far_tip_by_the_whole_lever_arm():
    """Three straight links of 0.5 m, only the first edge uncertain in rotation: the tip 1.0 m beyond it moves by
    s_r * 1.0 (not by sqrt(2) * 0.5 * s_r, which summing each link's lever arm alone would give)."""
    offset = np.eye(4)
    offset[:3, 3] = [0.5, 0.0, 0.0]
    models = [RevoluteModel(0, 1, 0, B=offset, std=(0.0, 0.02)), RevoluteModel(1, 2, 1, B=offset),
              RevoluteModel(2, 3, 2, B=offset)]
    _, std = BodyScheme((0, 1, 2, 3), 0, models).predict([0.0, 0.0, 0.0], return_std=True)
    assert_allclose(std[3], [0.02 * 1.0, 0.02])
    assert_allclose(std[2], [0.02 * 0.5, 0.02])

@pytest.mark.parametrize("analytic", [True, False])
def test_jacobian_matches_finite_differences(analytic):
    """The product-rule Jacobian (incl. inverted edges) equals central differences of predict."""
    rng = np.random.default_rng(0)
    scheme, _ = branching_scheme(rng, analytic=analytic)
    a = rng.uniform(-np.pi, np.pi, size=4)  # one extra unused action: its column must be zero
    eps = 1e-6
    for part in scheme.parts:
        J = scheme.jacobian(a, part)
        assert J.shape == (4, 4, 4)
        Jp = scheme.position_jacobian(a, part)
        assert Jp.shape == (3, 4)
        numeric = np.zeros((4, 4, 4))
        for k in range(4):
            step = np.zeros(4)
            step[k] = eps
            numeric[k] = (scheme.predict(a + step)[part] - scheme.predict(a - step)[part]) / (2 * eps)
        assert_allclose(J, numeric, atol=1e-6)
        assert_allclose(Jp, numeric[:, :3, 3].T, atol=1e-6)
        assert_allclose(J[3], 0.0)
        assert np.all(J[[k for k in range(3) if k not in scheme.path_actions(part)]] == 0.0)


def test_forward_difference_derivatives_match_analytic():
    """chain_transforms(derivative_step) gives local derivatives whose Jacobians match the analytic ones."""
    rng = np.random.default_rng(0)
    scheme, _ = branching_scheme(rng)
    a = rng.uniform(-np.pi, np.pi, size=3)
    for part in scheme.parts:
        T, dT = scheme.chain_transforms(a, part, derivative_step=1e-7)
        assert_allclose(T, scheme.chain_transforms(a, part))
        assert len(dT) == len(scheme.path(part)) - 1
        assert_allclose(scheme.position_jacobian(a, part, T, dT), scheme.position_jacobian(a, part), atol=1e-6)
        assert_allclose(scheme.jacobian(a, part, T, dT), scheme.jacobian(a, part), atol=1e-6)
    with pytest.raises(InvalidInputError, match="derivative_step"):
        scheme.chain_transforms(a, 12, derivative_step=0.0)
    with pytest.raises(InvalidInputError, match="local_transforms"):
        scheme.position_jacobian(a, 12, local_derivatives=dT)


def test_jacobian_reuses_local_transforms():
    """Passing chain_transforms gives the same Jacobian; a wrong shape is rejected."""
    rng = np.random.default_rng(0)
    scheme, _ = branching_scheme(rng)
    a = rng.uniform(-1, 1, size=3)
    T = scheme.chain_transforms(a, 12)
    assert T.shape == (2, 4, 4)
    assert_allclose(T[0] @ T[1], scheme.predict(a)[12])
    assert_allclose(scheme.predict_part(a, 12), scheme.predict(a)[12])
    assert_allclose(scheme.position_jacobian(a, 12, local_transforms=T), scheme.position_jacobian(a, 12))
    assert_allclose(scheme.jacobian(a, 12, local_transforms=T), scheme.jacobian(a, 12))
    with pytest.raises(InvalidInputError, match=r"\(2, 4, 4\)"):
        scheme.position_jacobian(a, 12, local_transforms=T[:1])


def test_single_part_scheme():
    """A scheme of only the root predicts the identity and has zero Jacobian."""
    scheme = BodyScheme([4], 4, [])
    assert_allclose(scheme.predict(np.zeros(2))[4], np.eye(4))
    assert_allclose(scheme.jacobian(np.zeros(2), 4), 0.0)
    assert scheme.actions_used == ()


@pytest.mark.parametrize("parts, root, pairs, match", [
    ((1, 2, 3), 1, [(1, 2)], "exactly 2 models"),
    ((1, 2, 3), 1, [(1, 2), (2, 1)], "more than one model"),
    ((1, 2, 3, 4), 1, [(1, 2), (2, 1), (3, 4)], "more than one model"),
    ((1, 2, 3, 4), 1, [(1, 2), (2, 3), (3, 1)], "do not connect"),
    ((1, 2, 3), 1, [(1, 2), (2, 8)], "not in"),
    ((1, 2, 3), 1, [(1, 2), (3, 3)], "itself"),
    ((1, 2, 3), 5, [(1, 2), (2, 3)], "root 5"),
    ((1, 2, 2), 1, [(1, 2), (2, 3)], "unique"),
    ((), 1, [], "at least one part"),
])
def test_invalid_trees_are_rejected(parts, root, pairs, match):
    """Wrong model count, cycles, duplicate edges, unknown ids and bad roots raise InvalidInputError."""
    models = [RevoluteModel(p, c) for p, c in pairs]
    with pytest.raises(InvalidInputError, match=match):
        BodyScheme(parts, root, models)


def test_unfitted_model_and_non_model_are_rejected():
    """Models must be fitted LocalModel instances."""
    with pytest.raises(NotFittedError):
        BodyScheme((1, 2), 1, [UnfittedModel(1, 2)])
    with pytest.raises(InvalidInputError, match="LocalModel"):
        BodyScheme((1, 2), 1, [object()])


def test_bad_actions_and_parts_are_rejected():
    """Too short, NaN or batched action vectors and unknown parts raise InvalidInputError."""
    rng = np.random.default_rng(0)
    scheme, _ = branching_scheme(rng)
    with pytest.raises(InvalidInputError, match="at least 3"):
        scheme.predict(np.zeros(2))
    with pytest.raises(InvalidInputError, match="NaN"):
        scheme.predict([0.0, np.nan, 0.0])
    with pytest.raises(InvalidInputError, match=r"\(2, 3\)"):
        scheme.predict(np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match="part 4"):
        scheme.jacobian(np.zeros(3), 4)
    with pytest.raises(InvalidInputError, match="at least 3"):
        scheme.predict_batch(np.zeros((5, 2)))
    assert 12 in scheme and 4 not in scheme and "x" not in scheme


def test_describe_lists_every_edge():
    """describe names every part and model, and marks inverted edges."""
    rng = np.random.default_rng(0)
    scheme, models = branching_scheme(rng)
    text = scheme.describe()
    assert text.splitlines()[1] == "7 (root)"
    assert len(text.splitlines()) == 2 + len(models)
    for model in models:
        assert model.describe() in text
    assert text.count("inverted") == 2


def test_dict_round_trip():
    """to_dict survives JSON and from_dict rebuilds a scheme with the same predictions."""
    rng = np.random.default_rng(0)
    scheme, _ = branching_scheme(rng)
    data = json.loads(json.dumps(scheme.to_dict()))
    again = BodyScheme.from_dict(data, RevoluteModel.from_dict)
    assert again.parts == scheme.parts and again.root == scheme.root
    a = rng.uniform(-1, 1, size=3)
    assert_allclose(again.predict_batch(a[None]), scheme.predict_batch(a[None]))
    with pytest.raises(ModelFileError, match="version"):
        BodyScheme.from_dict({**data, "version": 99}, RevoluteModel.from_dict)
    with pytest.raises(ModelFileError, match="spanning tree"):
        BodyScheme.from_dict({**data, "models": data["models"][:-1]}, RevoluteModel.from_dict)
    with pytest.raises(ModelFileError):
        BodyScheme.from_dict({"kind": "something else"}, RevoluteModel.from_dict)


# ---------------------------------------------------------------------- with the package's own local models
def fd_jacobian(scheme, a, part, eps=1e-6):
    """Central differences of predict, shape (m, 4, 4)."""
    J = np.zeros((a.shape[0], 4, 4))
    for k in range(a.shape[0]):
        step = np.zeros_like(a)
        step[k] = eps
        J[k] = (scheme.predict(a + step)[part] - scheme.predict(a - step)[part]) / (2 * eps)
    return J


def test_engineered_scheme_equals_forward_kinematics():
    """An engineered scheme predicts exactly the tree's marker-to-marker forward kinematics, every part."""
    rng = np.random.default_rng(0)
    for tree in (powercube_6dof(), branching_tree(seed=0)):
        root = tree.root_marker
        scheme = BodyScheme(tree.marker_ids, root, engineered_models(tree))
        A = rng.uniform(tree.action_lower, tree.action_upper, size=(5, tree.n_actions))
        P = scheme.predict_batch(A)
        for n, a in enumerate(A):
            for i, part in enumerate(scheme.parts):
                assert_allclose(P[n, i], tree.relative_transform(root, part, a), atol=1e-12)


def test_engineered_scheme_reversed_and_rerooted():
    """Engineered models stored leaf-to-root and a leaf as root still give the tree's forward kinematics."""
    rng = np.random.default_rng(0)
    tree = branching_tree(seed=0)
    models = [EngineeredModel.from_tree(tree, child, parent) for parent, child in tree.marker_tree_edges()]
    root = 4  # left forearm: the path to the right arm crosses the fork
    scheme = BodyScheme(tree.marker_ids, root, models)
    assert any(inverted for *_, inverted in scheme.edges)
    a = rng.uniform(tree.action_lower, tree.action_upper)
    root2part = scheme.predict(a)
    for part in tree.marker_ids:
        assert_allclose(root2part[part], tree.relative_transform(root, part, a), atol=1e-12)


def gp_scheme(tree, rng, n=30, reverse=()):
    """Scheme of GP models fitted on ``n`` noise-free samples of the tree's true relative transforms."""
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(n, tree.n_actions))
    models = []
    for parent, child in tree.marker_tree_edges():
        if child in reverse:
            parent, child = child, parent
        models.append(GPModel(parent, child, tree.path_actions(parent, child)).fit(
            A, tree.relative_transform(parent, child, A)))
    return BodyScheme(tree.marker_ids, tree.root_marker, models)


def test_jacobian_of_gp_and_engineered_schemes_matches_finite_differences():
    """Analytic Jacobians through GP and engineered models (some inverted) equal central differences."""
    rng = np.random.default_rng(0)
    tree = branching_tree(seed=0)
    edges = tree.marker_tree_edges()
    schemes = [
        gp_scheme(tree, rng, reverse=(4, 5)),
        BodyScheme(tree.marker_ids, 6, [EngineeredModel.from_tree(tree, *e) for e in edges]),
    ]
    for scheme in schemes:
        assert any(inverted for *_, inverted in scheme.edges)
        a = rng.uniform(tree.action_lower, tree.action_upper)
        for part in scheme.parts:
            numeric = fd_jacobian(scheme, a, part)
            assert_allclose(scheme.jacobian(a, part), numeric, atol=1e-6)
            assert_allclose(scheme.position_jacobian(a, part), numeric[:, :3, 3].T, atol=1e-6)


def test_gp_scheme_predicts_unobserved_parts():
    """A GP scheme learned from 30 samples predicts every part from actions alone, close to the truth."""
    rng = np.random.default_rng(0)
    tree = powercube_6dof()
    scheme = gp_scheme(tree, rng)
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(20, tree.n_actions))
    P = scheme.predict_batch(A)
    truth = np.stack([[tree.relative_transform(scheme.root, part, a) for part in scheme.parts] for a in A])
    errors = np.linalg.norm(P[..., :3, 3] - truth[..., :3, 3], axis=-1)
    assert np.median(errors[:, -1]) < 0.05  # end effector, 7 models away from the root
    _, std = scheme.predict_batch(A, return_std=True)
    assert np.all(np.diff(std[..., 0], axis=1) >= 0.0)  # a chain: uncertainty grows towards the tip


def test_dict_round_trip_with_the_model_registry():
    """A mixed GP / engineered / static scheme survives JSON using the default model deserialiser."""
    rng = np.random.default_rng(0)
    tree = branching_tree(seed=0)
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(30, tree.n_actions))
    models = []
    for k, (parent, child) in enumerate(tree.marker_tree_edges()):
        actions = tree.path_actions(parent, child)
        if not actions:
            models.append(StaticModel(parent, child).fit(A, tree.relative_transform(parent, child, A)))
        elif k % 2:
            models.append(GPModel(parent, child, actions).fit(A, tree.relative_transform(parent, child, A)))
        else:
            models.append(EngineeredModel.from_tree(tree, parent, child))
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, models)
    again = BodyScheme.from_dict(json.loads(json.dumps(scheme.to_dict())))
    assert [type(m) for m in again.models] == [type(m) for m in models]
    assert_allclose(again.predict_batch(A[:5]), scheme.predict_batch(A[:5]), atol=1e-12)
