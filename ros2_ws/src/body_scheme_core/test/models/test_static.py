"""Tests of the static local model and of the model registry."""

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError, ModelFileError, NotFittedError
from body_scheme_core.models import (
    MODEL_CLASSES,
    EngineeredModel,
    GPModel,
    PrismaticModel,
    RevoluteModel,
    StaticModel,
    model_from_dict,
)
from body_scheme_core.transforms import concat, transform_from_rotvec


def noisy_observations(rng, parent2child, n, sigma_trans, sigma_rot):
    noise = transform_from_rotvec(rng.normal(0.0, sigma_rot, (n, 3)), rng.normal(0.0, sigma_trans, (n, 3)))
    return concat(parent2child, noise)


def test_fit_recovers_noise_free_transform():
    """Identical observations give back that transform; its uncertainty is that of the mean of five samples."""
    parent2child = transform_from_rotvec([0.1, -0.5, 0.3], [0.2, 0.0, -0.1])
    model = StaticModel(1, 2, sigma_trans=0.01, sigma_rot=0.02).fit(np.zeros((5, 3)),
                                                                    np.broadcast_to(parent2child, (5, 4, 4)))
    Z, std = model.predict(np.zeros((2, 3)), return_std=True)
    assert_allclose(Z, np.broadcast_to(parent2child, (2, 4, 4)), atol=1e-12)
    assert_allclose(std, np.broadcast_to([0.01, 0.02], (2, 2)) / math.sqrt(5), rtol=1e-6)
    assert model.complexity == 0 and model.actions == () and model.n_params == 6


def test_fit_is_close_to_the_chordal_mean():
    """Without outliers the robust fit is the arithmetic mean position and (nearly) the chordal mean rotation."""
    rng = np.random.default_rng(0)
    Z = noisy_observations(rng, np.eye(4), 40, 0.05, 0.3)
    model = StaticModel(0, 1, sigma_trans=0.05, sigma_rot=0.3).fit(np.zeros((40, 2)), Z)
    expected = Rotation.from_matrix(Z[:, :3, :3]).mean().as_matrix()
    assert_allclose(model.parent2child_[:3, :3], expected, atol=0.02)
    assert_allclose(model.parent2child_[:3, 3], Z[:, :3, 3].mean(axis=0), atol=1e-3)


def test_std_is_the_uncertainty_of_the_mean():
    """With many samples the predictive std is sigma / sqrt(n), with sigma the given per-axis noise."""
    rng = np.random.default_rng(0)
    parent2child = transform_from_rotvec([0.0, 0.4, 0.0], [0.3, 0.1, 0.0])
    Z = noisy_observations(rng, parent2child, 4000, 0.05, math.radians(5.0))
    model = StaticModel(0, 1, sigma_trans=0.05, sigma_rot=math.radians(5.0)).fit(np.zeros((4000, 1)), Z)
    _, std = model.predict(np.zeros((1, 1)), return_std=True)
    assert_allclose(std[0], [0.05, math.radians(5.0)] / np.sqrt(4000), rtol=0.1)
    assert 0.9 < model.rms_ < 1.1  # the residuals match the assumed noise


def test_one_outlier_barely_moves_the_fit():
    """A mirrored orientation among 20 samples moves the robust rotation by far less than it moves a plain mean."""
    rng = np.random.default_rng(1)
    Z = noisy_observations(rng, np.eye(4), 20, 0.01, 0.02)
    bad = Z.copy()
    bad[0, :3, :3] = Rotation.from_rotvec([math.pi * 0.9, 0.0, 0.0]).as_matrix()

    def fitted(Z):
        return Rotation.from_matrix(StaticModel(0, 1, sigma_trans=0.01, sigma_rot=0.02).fit(
            np.zeros((20, 1)), Z).parent2child_[:3, :3])

    robust_shift = (fitted(bad) * fitted(Z).inv()).magnitude()
    plain_shift = (Rotation.from_matrix(bad[:, :3, :3]).mean() * Rotation.from_matrix(Z[:, :3, :3]).mean().inv())
    assert robust_shift < 0.25 * plain_shift.magnitude()


def test_predict_ignores_actions_and_repeats():
    """Every row gets the same transform; the Jacobian is zero with one row per action."""
    rng = np.random.default_rng(0)
    Z = noisy_observations(rng, np.eye(4), 10, 0.01, 0.01)
    model = StaticModel(3, 4).fit(rng.normal(size=(10, 6)), Z)
    P = model.predict(rng.normal(size=(4, 6)))
    assert P.shape == (4, 4, 4)
    assert_allclose(P, np.broadcast_to(P[0], P.shape))
    assert_allclose(model.jacobian(np.zeros(6)), np.zeros((6, 4, 4)))


def test_to_dict_round_trip_is_json_and_identical():
    """to_dict -> JSON -> from_dict (and the registry) predicts the same, uncertainty included."""
    rng = np.random.default_rng(0)
    model = StaticModel(2, 5).fit(np.zeros((8, 3)), noisy_observations(rng, np.eye(4), 8, 0.02, 0.05))
    data = json.loads(json.dumps(model.to_dict()))
    for restored in (StaticModel.from_dict(data), model_from_dict(data)):
        assert isinstance(restored, StaticModel) and restored.pair == (2, 5)
        Z, std = restored.predict(np.zeros((1, 3)), return_std=True)
        Z0, std0 = model.predict(np.zeros((1, 3)), return_std=True)
        assert_allclose(Z, Z0)
        assert_allclose(std, std0)


def test_unfitted_round_trip_and_predict_raises():
    """An unfitted model round-trips unfitted and refuses to predict."""
    model = StaticModel.from_dict(StaticModel(0, 1).to_dict())
    assert not model.is_fitted
    with pytest.raises(NotFittedError):
        model.predict(np.zeros((1, 2)))


@pytest.mark.parametrize("A, Z", [
    (np.zeros((2, 2)), np.full((2, 4, 4), np.nan)),                        # NaN observation
    (np.zeros((2, 2)), np.broadcast_to(np.diag([2.0, 1, 1, 1]), (2, 4, 4))),  # not rigid
    (np.zeros((3, 2)), np.broadcast_to(np.eye(4), (2, 4, 4))),              # length mismatch
    (np.full((2, 2), np.inf), np.broadcast_to(np.eye(4), (2, 4, 4))),       # inf action
    (np.zeros((0, 2)), np.zeros((0, 4, 4))),                                # no samples
])
def test_fit_rejects_bad_input(A, Z):
    """Bad training data raise InvalidInputError."""
    with pytest.raises(InvalidInputError):
        StaticModel(0, 1).fit(A, Z)


def test_constructor_rejects_actions():
    """A static model depends on no action."""
    with pytest.raises(InvalidInputError):
        StaticModel(0, 1, (2,))


def test_registry_knows_learned_models():
    """The registry maps kinds to classes."""
    assert MODEL_CLASSES["static"] is StaticModel
    assert MODEL_CLASSES["revolute"] is RevoluteModel
    assert MODEL_CLASSES["prismatic"] is PrismaticModel
    assert MODEL_CLASSES["gp"] is GPModel
    assert MODEL_CLASSES["engineered"] is EngineeredModel
    assert all(cls.kind == kind for kind, cls in MODEL_CLASSES.items())


@pytest.mark.parametrize("data", [
    [],                                                          # not a dict
    {"parent": 0, "child": 1},                                   # no kind
    {"kind": "spline", "parent": 0, "child": 1},                 # unknown kind
    {"kind": "static", "parent": 0},                             # missing child
    {"kind": "static", "parent": 0, "child": 1, "actions": [], "hyperparameters": {}, "params": [0, 0],
     "param_cov": np.eye(6).tolist(), "n_samples": 1, "rms": 1.0},                 # params too short
    {"kind": "static", "parent": 0, "child": 1, "actions": [], "hyperparameters": {}, "params": [0] * 6,
     "param_cov": np.full((6, 6), np.nan).tolist(), "n_samples": 1, "rms": 1.0},   # NaN covariance
    {"kind": "static", "parent": 0, "child": 1, "actions": [], "hyperparameters": {"f_scale": -1.0}},
    {"kind": "static", "parent": 0, "child": 1, "actions": [2]},
])
def test_corrupt_dicts_raise_model_file_error(data):
    """Unknown kinds and malformed content raise ModelFileError."""
    with pytest.raises(ModelFileError):
        model_from_dict(data)
