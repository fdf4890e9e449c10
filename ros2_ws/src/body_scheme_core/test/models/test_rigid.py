"""Tests of the rigid-joint local models (revolute, prismatic) and their shared least-squares machinery."""

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from body_scheme_core.errors import InvalidInputError, ModelFileError, NotFittedError
from body_scheme_core.models import PrismaticModel, RevoluteModel, StaticModel, model_from_dict
from body_scheme_core.models.prismatic import PrismaticForm, UnitPrismaticForm
from body_scheme_core.models.revolute import RevoluteForm, UnitRevoluteForm
from body_scheme_core.models.rigid_fit import gauss_newton, least_squares_fit
from body_scheme_core.models.static import StaticForm
from body_scheme_core.rotations import rotation_log, rotvec_matrix
from body_scheme_core.transforms import rotational_error, transform_from_rotvec, translational_error

#: Per-axis noise of a relative observation at the paper's noise, 0.3 m from the parent (two markers + lever arm).
SIGMA_T = math.sqrt((2 * 0.044**2 + (2 / 3) * math.radians(15) ** 2 * 0.3**2) / 3)
SIGMA_R = math.radians(15) * math.sqrt(2 / 3)


def _revolute_params(rng, scale=1.0):
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    r = rng.normal(size=3) * 0.2
    r -= (r @ u) * u
    return np.concatenate([u, r, rng.normal(size=3) * 0.2, rng.normal(size=3), [scale]])


def _noisy(rng, Z, sigma_t, sigma_r):
    noise = transform_from_rotvec(rng.normal(0.0, sigma_r, (len(Z), 3)), rng.normal(0.0, sigma_t, (len(Z), 3)))
    return Z @ noise


def _actions(x):
    A = np.zeros((len(x), 2))
    A[:, 1] = x
    return A


def test_revolute_fit_recovers_a_known_joint():
    """200 samples at the paper's relative-observation noise: axis within 3 deg, axis line within 25 mm, the child's
    pose at a = 0 within 25 mm / 3 deg."""
    rng = np.random.default_rng(0)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 200)
    Z = _noisy(rng, RevoluteForm.transforms(true[None], x[None])[0], SIGMA_T, SIGMA_R)
    model = RevoluteModel(0, 1, (1,), sigma_trans=SIGMA_T, sigma_rot=SIGMA_R).fit(_actions(x), Z)
    assert math.degrees(math.acos(min(1.0, abs(model.axis_ @ true[0:3])))) < 3.0
    # distance between the fitted axis point and the true axis line
    offset = model.axis_point_ - (true[6:9] + true[3:6])
    assert np.linalg.norm(offset - (offset @ true[0:3]) * true[0:3]) < 0.025
    origin = RevoluteForm.transforms(true[None], np.zeros((1, 1)))[0, 0]
    assert translational_error(model.origin_, origin) < 0.025
    assert math.degrees(rotational_error(model.origin_, origin)) < 3.0
    assert model.scale_ == 1.0 and model.n_params == 10 and 0.8 < model.rms_ < 1.2


def test_a_joint_swept_over_more_than_a_turn_is_fitted_from_its_angles_modulo_a_turn():
    """A wrist at -360, -72 and +216 deg (a laser-tracker sweep): the first sample is the identity, and each other
    is more than 2.5 rad from it; the start takes the differences modulo a turn and the fit is exact."""
    rng = np.random.default_rng(5)
    true = _revolute_params(rng)
    x = np.radians([-360.0, -72.0, 216.0])
    Z = RevoluteForm.transforms(true[None], x[None])[0]
    model = RevoluteModel(0, 1, (1,), sigma_trans=1e-4, sigma_rot=1e-4).fit(_actions(x), Z)
    assert model.rms_ < 1e-3
    assert math.degrees(math.acos(min(1.0, abs(model.axis_ @ true[0:3])))) < 1e-3


def test_revolute_fit_with_a_free_scale_recovers_a_gear_ratio():
    """With fit_scale the joint turns s = 0.5 rad per action unit: recovered within 3 %."""
    rng = np.random.default_rng(1)
    true = _revolute_params(rng, scale=0.5)
    x = rng.uniform(-3.0, 3.0, 200)
    Z = _noisy(rng, RevoluteForm.transforms(true[None], x[None])[0], 0.01, 0.02)
    model = RevoluteModel(0, 1, (1,), fit_scale=True, sigma_trans=0.01, sigma_rot=0.02).fit(_actions(x), Z)
    assert model.scale_ == pytest.approx(0.5, rel=0.03) and model.n_params == 11


def test_prismatic_fit_recovers_a_known_joint():
    """100 samples, 10 mm / 2 deg noise: axis within 1 deg, position at a = 0 within 5 mm."""
    rng = np.random.default_rng(2)
    u = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    true = np.concatenate([[0.1, 0.2, 0.3], [0.2, -0.1, 0.4], u])
    x = rng.uniform(-0.3, 0.3, 100)
    Z = _noisy(rng, PrismaticForm.transforms(true[None], x[None])[0], 0.01, math.radians(2))
    model = PrismaticModel(0, 1, (1,), sigma_trans=0.01, sigma_rot=math.radians(2)).fit(_actions(x), Z)
    assert math.degrees(math.acos(min(1.0, model.axis_ @ u))) < 1.0
    assert np.linalg.norm(model.origin_[:3, 3] - true[0:3]) < 0.005
    assert model.scale_ == pytest.approx(1.0) and model.n_params == 8


@pytest.mark.parametrize("form, params", [
    (RevoluteForm, _revolute_params(np.random.default_rng(3), 0.8)),
    (UnitRevoluteForm, _revolute_params(np.random.default_rng(4))),
    (PrismaticForm, np.random.default_rng(5).normal(size=9)),
    (UnitPrismaticForm, np.concatenate([np.random.default_rng(6).normal(size=6), [0.0, 0.6, 0.8]])),
    (StaticForm, np.random.default_rng(7).normal(size=6)),
])
def test_twists_match_finite_differences(form, params):
    """The analytic twist of every increment equals the finite difference of the prediction through retract."""
    x = np.random.default_rng(8).uniform(-1.5, 1.5, (1, 7))
    P = params[None]
    Z0, T = form.evaluate(P, x)
    h = 1e-7
    for i in range(form.N_PARAMS):
        delta = np.zeros((1, form.N_PARAMS))
        delta[0, i] = h
        Z1 = form.transforms(form.retract(P, delta), x)
        dt = (Z1[..., :3, 3] - Z0[..., :3, 3]) / h
        w = rotation_log(np.swapaxes(Z0[..., :3, :3], -1, -2) @ Z1[..., :3, :3]) / h
        assert_allclose(dt, T[..., :3, i], atol=2e-6)
        assert_allclose(w, T[..., 3:, i], atol=2e-6)


def test_action_jacobian_matches_finite_differences():
    """dZ/da of a fitted revolute joint equals the central difference of its prediction."""
    rng = np.random.default_rng(9)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 30)
    model = RevoluteModel(0, 1, (1,)).fit(_actions(x), RevoluteForm.transforms(true[None], x[None])[0])
    a, h = np.array([0.0, 0.3]), 1e-6
    numeric = (model.predict(a + [0, h])[0] - model.predict(a - [0, h])[0]) / (2 * h)
    J = model.jacobian(a)
    assert_allclose(J[1], numeric, atol=1e-7)
    assert_allclose(J[0], 0.0)


def test_batched_gauss_newton_matches_scipy_least_squares():
    """The numpy solver of the candidate batches reaches the scipy trust-region solution (Huber loss)."""
    rng = np.random.default_rng(10)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 25)
    Z = _noisy(rng, RevoluteForm.transforms(true[None], x[None])[0], SIGMA_T, SIGMA_R)
    S = np.broadcast_to([SIGMA_T, SIGMA_R], (25, 2)).copy()
    start = UnitRevoluteForm.initial(x[None], Z[None], S[None], np.ones((1, 25), bool))
    reference, _, _ = least_squares_fit(UnitRevoluteForm, start[0], x, Z, S)
    batched, _, _ = gauss_newton(UnitRevoluteForm, start, x[None], Z[None], S[None], np.ones((1, 25), bool), 20)
    assert_allclose(batched[0], reference, atol=1e-6)


def test_predictive_uncertainty_shrinks_with_data():
    """The std propagated from the parameter covariance falls roughly like 1 / sqrt(n)."""
    rng = np.random.default_rng(11)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 400)
    Z = _noisy(rng, RevoluteForm.transforms(true[None], x[None])[0], SIGMA_T, SIGMA_R)
    stds = [RevoluteModel(0, 1, (1,), sigma_trans=SIGMA_T, sigma_rot=SIGMA_R).fit(_actions(x[:n]), Z[:n]).predict(
        _actions([0.2]), return_std=True)[1][0] for n in (25, 400)]
    assert_allclose(stds[0] / stds[1], 4.0, rtol=0.35)


@pytest.mark.parametrize("model_class", [RevoluteModel, PrismaticModel, StaticModel])
def test_few_sample_predictions_equal_the_vectorised_form(model_class):
    """The compiled path of predict for a few action vectors gives what the vectorised form gives for many."""
    rng = np.random.default_rng(12)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 20)
    model = model_class(0, 1, (1,) if model_class is not StaticModel else ()).fit(
        _actions(x), RevoluteForm.transforms(true[None], x[None])[0])
    A = _actions(np.linspace(-1.0, 1.0, 12))
    many = model.predict(A)  # vectorised
    assert_allclose(np.concatenate([model.predict(A[:6]), model.predict(A[6:])]), many, atol=1e-12)
    with pytest.raises(InvalidInputError):
        RevoluteModel(0, 1, (1,)).fit(_actions(x), RevoluteForm.transforms(true[None], x[None])[0]).predict(
            np.zeros((1, 1)))  # the model reads action 1


def test_robust_loss_resists_mirrored_orientations():
    """Three of 40 samples with their orientation flipped move the robust fit far less than a plain fit."""
    rng = np.random.default_rng(13)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 40)
    clean = RevoluteForm.transforms(true[None], x[None])[0]
    Z = _noisy(rng, clean, 0.01, 0.02)
    Z[:3, :3, :3] = Z[:3, :3, :3] @ rotvec_matrix(np.array([math.pi * 0.9, 0.0, 0.0]))
    robust = RevoluteModel(0, 1, (1,), sigma_trans=0.01, sigma_rot=0.02).fit(_actions(x), Z)
    plain = RevoluteModel(0, 1, (1,), sigma_trans=0.01, sigma_rot=0.02, f_scale=1e6).fit(_actions(x), Z)
    test = np.linspace(-1.5, 1.5, 50)
    truth = RevoluteForm.transforms(true[None], test[None])[0]
    error = [np.mean(rotational_error(m.predict(_actions(test)), truth)) for m in (robust, plain)]
    assert error[0] < 0.3 * error[1]


def test_round_trip_and_corrupt_dicts():
    """to_dict -> JSON -> model_from_dict predicts the same; bad parameters raise ModelFileError."""
    rng = np.random.default_rng(14)
    true = _revolute_params(rng)
    x = rng.uniform(-1.5, 1.5, 20)
    model = RevoluteModel(3, 5, (1,)).fit(_actions(x), RevoluteForm.transforms(true[None], x[None])[0])
    data = json.loads(json.dumps(model.to_dict()))
    restored = model_from_dict(data)
    A = _actions([0.1])
    assert_allclose(restored.predict(A, return_std=True)[0], model.predict(A, return_std=True)[0])
    assert_allclose(restored.predict(A, return_std=True)[1], model.predict(A, return_std=True)[1])
    for key, value in [("params", [0.0] * 13), ("params", [1.0] * 5), ("param_cov", np.eye(3).tolist())]:
        with pytest.raises(ModelFileError):
            model_from_dict(dict(data, **{key: value}))
    assert not model_from_dict(RevoluteModel(0, 1, (2,)).to_dict()).is_fitted


def test_bad_construction_and_fits_are_refused():
    """One action exactly for joints; at least MIN_SAMPLES samples; predict before fit raises."""
    with pytest.raises(InvalidInputError):
        RevoluteModel(0, 1, (0, 1))
    with pytest.raises(InvalidInputError):
        PrismaticModel(0, 1, ())
    with pytest.raises(InvalidInputError):
        RevoluteModel(0, 1, (0,), sigma_trans=0.0)
    with pytest.raises(InvalidInputError, match="at least 3 samples"):
        RevoluteModel(0, 1, (0,)).fit(np.zeros((2, 1)), np.broadcast_to(np.eye(4), (2, 4, 4)))
    with pytest.raises(NotFittedError):
        PrismaticModel(0, 1, (0,)).predict(np.zeros((1, 1)))
    assert StaticModel(0, 1).n_params == 6
