"""The covariance of a part's predicted position (uncertainty.py) and the joint covariance a body scheme carries."""

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.prediction.uncertainty import (
    error_radius,
    parameter_jacobian,
    perturbed_models,
    position_covariance,
    position_std,
)
from body_scheme_core.world import make_session, powercube_6dof


@pytest.fixture(scope="module")
def learned():
    """The 6-DOF arm learned from scratch (150 steps, the paper's noise): rigid-joint models and a joint fit."""
    tree = powercube_6dof()
    session = make_session(tree, 150, 0)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    for t in range(150):
        learner.update(session.actions[t], session.observations[t])
    return tree, learner.body_scheme


def test_the_joint_fit_leaves_its_covariance_with_the_scheme(learned):
    """Every rigid model of the tree is in it, and its diagonal block is the model's own covariance."""
    _, scheme = learned
    indices, matrix = scheme.param_covariance
    assert sorted(indices) == [k for k, m in enumerate(scheme.models) if hasattr(m, "retract")]
    start = 0
    for k in indices:
        p = scheme.models[k].n_params
        np.testing.assert_allclose(matrix[start:start + p, start:start + p], scheme.models[k].param_cov_)
        start += p


@pytest.mark.slow
def test_first_order_propagation_matches_sampling_the_joint_covariance(learned):
    """Parameters drawn from the joint covariance (cross terms included) move the tip as the first-order covariance
    says (within 15 % in every direction); dropping the cross terms gives another, larger answer."""
    tree, scheme = learned
    indices, matrix = scheme.param_covariance
    a, tip = np.full(tree.n_actions, 0.3), tree.marker_ids[-1]
    predicted = position_covariance(scheme, a, tip)
    rng = np.random.default_rng(0)
    sizes = [scheme.models[k].n_params for k in indices]
    tips = []
    for delta in rng.multivariate_normal(np.zeros(matrix.shape[0]), matrix, size=2000):
        models, start = list(scheme.models), 0
        for k, p in zip(indices, sizes, strict=True):
            models[k] = models[k].with_params(models[k].retract(delta[start:start + p]))
            start += p
        tips.append(BodyScheme(scheme.parts, scheme.root, models).predict(a)[tip][:3, 3])
    sampled = np.cov(np.array(tips).T)
    w, V = np.linalg.eigh(predicted)
    np.testing.assert_allclose(np.diag(V.T @ sampled @ V), w, rtol=0.15)
    independent = BodyScheme(scheme.parts, scheme.root, scheme.models)
    assert position_std(independent, a, tip) > 1.2 * position_std(scheme, a, tip)


def test_the_parameter_jacobian_carries_the_joint_covariance_to_every_part(learned):
    """Through the parameter Jacobian the joint covariance gives each part's position covariance (every model of the
    learned tree is in the joint fit); a scheme without one has none."""
    tree, scheme = learned
    A = np.random.default_rng(1).uniform(tree.action_lower, tree.action_upper, size=(3, tree.n_actions))
    J = parameter_jacobian(scheme, A)
    assert J.shape == (3, len(scheme.parts), 3, scheme.param_covariance[1].shape[0])
    for n, a in enumerate(A):
        for k, part in enumerate(scheme.parts):
            np.testing.assert_allclose(J[n, k] @ scheme.param_covariance[1] @ J[n, k].T,
                                       position_covariance(scheme, a, part), rtol=1e-3, atol=1e-12)
    assert parameter_jacobian(BodyScheme(scheme.parts, scheme.root, scheme.models), A) is None


def test_exact_models_are_certain_and_the_root_is_its_own_origin(learned):
    """Engineered models (the robot's specification) give zero; the root part has nothing above it."""
    tree, _ = learned
    exact = BodyScheme(tree.marker_ids, tree.root_marker, engineered_models(tree))
    assert position_std(exact, np.zeros(tree.n_actions), tree.marker_ids[-1]) == 0.0
    assert position_std(exact, np.zeros(tree.n_actions), tree.root_marker) == 0.0
    with pytest.raises(InvalidInputError):
        position_covariance(exact, np.array([np.nan] * tree.n_actions), tree.root_marker)


def test_the_joint_covariance_survives_a_round_trip_and_bad_ones_are_refused(learned):
    _, scheme = learned
    again = BodyScheme.from_dict(scheme.to_dict())
    assert again.param_covariance[0] == scheme.param_covariance[0]
    np.testing.assert_array_equal(again.param_covariance[1], scheme.param_covariance[1])
    data = scheme.to_dict()
    data["param_covariance"]["matrix"] = [[1.0]]
    with pytest.raises(ModelFileError, match="param_covariance"):
        BodyScheme.from_dict(data)
    with pytest.raises(InvalidInputError, match="param_covariance"):
        BodyScheme(scheme.parts, scheme.root, scheme.models, ([0, 0], np.eye(2)))


def test_a_models_rotation_error_turns_what_follows_about_its_own_child_also_when_inverted():
    """A GP edge seen from its parent moves its child by its translation error only (the rotation turns the child
    about itself); seen from its child (inverted), its rotation error swings the parent on the whole link."""
    from body_scheme_core.models.gp import GPModel
    from body_scheme_core.world import planar_2dof

    tree = planar_2dof()
    A = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper, size=(30, tree.n_actions))
    parent, child = tree.marker_tree_edges()[0]
    gp = GPModel(parent, child, tree.path_actions(parent, child)).fit(A, tree.relative_transform(parent, child, A))
    a = np.array([0.3, -0.2])
    _, std = gp.predict(a[None], return_std=True)
    s_t, s_r = std[0]
    forward = BodyScheme([parent, child], parent, [gp])
    inverted = BodyScheme([parent, child], child, [gp])
    lever = np.linalg.norm(inverted.predict(a)[parent][:3, 3])
    assert np.trace(position_covariance(forward, a, child)) == pytest.approx(3 * s_t**2)
    assert np.trace(position_covariance(inverted, a, parent)) == pytest.approx(3 * s_t**2 + 2 * s_r**2 * lever**2)


def test_the_perturbed_models_follow_their_models_parameters(learned):
    """The cached models after a parameter step are reused while the model's parameters stay, and rebuilt when they
    change in place (a refit)."""
    _, scheme = learned
    model = next(m for m in scheme.models if hasattr(m, "retract"))
    model = model.with_params(model.params_)
    first = perturbed_models(model)
    assert perturbed_models(model) is first and len(first) == model.n_params
    refit = model.retract(np.full(model.n_params, 1e-3))
    model._set_fit(refit, model.param_cov_, model.n_samples_, model.rms_)  # what fit() does, in place
    again = perturbed_models(model)
    assert again is not first
    np.testing.assert_allclose(again[0].params_, model.retract(np.eye(model.n_params)[0] * 1e-6))


@pytest.mark.parametrize("stds", [(1.0, 1.0, 1.0), (1.0, 0.0, 0.0), (1.0, 0.3, 0.05), (0.2, 1.0, 1.0)])
def test_the_error_radius_holds_the_stated_probability_whatever_the_covariances_shape(stds):
    """At confidence 2 the radius holds 95.4 % of Gaussian errors (Monte Carlo, 200,000 draws, a rotated covariance),
    from three equal axes (where ``2 sqrt(trace)`` holds 99.3 %) to one dominant axis; 0 at confidence 0 and for a
    zero covariance; a bad confidence is refused."""
    rng = np.random.default_rng(0)
    rotation, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    cov = rotation @ np.diag(np.square(stds)) @ rotation.T
    errors = rng.multivariate_normal(np.zeros(3), cov, size=200_000)
    radius = error_radius(cov, 2.0)
    assert np.mean(np.linalg.norm(errors, axis=1) <= radius) == pytest.approx(0.9545, abs=0.003)
    assert error_radius(cov, 0.0) == 0.0 and error_radius(np.zeros((3, 3)), 2.0) == 0.0
    with pytest.raises(InvalidInputError):
        error_radius(cov, -1.0)


def test_the_error_radius_of_a_broken_or_extreme_covariance_is_still_a_number():
    """NaN or inf in the covariance: an infinite radius (never sure), not an exception inside a node's IK; variances
    of 1e-160 m^2 do not underflow; a confidence of 9 sigma is finite."""
    assert error_radius(np.full((3, 3), np.nan), 2.0) == np.inf and error_radius(np.diag([np.inf, 1, 1]), 2.0) == np.inf
    assert error_radius(np.diag([1e-160, 1e-170, 0.0]), 2.0) == pytest.approx(2e-80)
    assert np.isfinite(error_radius(np.eye(3), 9.0)) and error_radius(np.eye(3), 9.0) > error_radius(np.eye(3), 2.0)
