"""Tests of the GP local model: against scikit-learn, analytic Jacobian, persistence and input checks."""

import json
import math
import warnings

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel

from body_scheme_core.errors import BodySchemeError, InvalidInputError, ModelFileError, NotFittedError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.models import GPModel, model_from_dict
from body_scheme_core.models.gp_kernel import (
    GPHyperparameters,
    _clamp_variance,
    squared_exponential,
    squared_exponential_gradient,
)
from body_scheme_core.rotations import polar_derivative, project_to_rotation
from body_scheme_core.transforms import check_transform, concat, transform_from_rotvec, vector12_from_transform

HYPER = dict(length_scale=0.8, signal_std_trans=0.3, signal_std_rot=0.7, noise_std_trans=0.06, noise_std_rot=0.14)


def chain(A, actions=(1, 3)):
    """Noise-free relative transforms of a two-joint chain driven by ``actions``."""
    return np.stack([concat(transform_from_rotvec([0.0, 0.0, a[actions[0]]], [0.3, 0.0, 0.0]),
                            transform_from_rotvec([a[actions[1]], 0.0, 0.0], [0.0, 0.2, 0.1])) for a in A])


def joint_data(rng, n, m=4, actions=(1, 3), noise=0.02):
    """Training data of :func:`chain` with small noise on rotation and translation."""
    A = rng.uniform(-2.0, 2.0, (n, m))
    Z = chain(A, actions)
    noise_T = transform_from_rotvec(rng.normal(0.0, noise, (n, 3)), rng.normal(0.0, noise, (n, 3)))
    return A, concat(Z, noise_T)


def sklearn_reference(X, Y, Xs, signal_std, noise_std, length_scale):
    """scikit-learn GP with the same fixed kernel on manually centred targets: mean and latent std."""
    kernel = ConstantKernel(signal_std**2, "fixed") * RBF(length_scale, "fixed")
    mean = Y.mean(axis=0)
    gp = GaussianProcessRegressor(kernel, alpha=noise_std**2, optimizer=None, normalize_y=False).fit(X, Y - mean)
    mu, std = gp.predict(Xs, return_std=True)
    return mu + mean, np.broadcast_to(std.reshape(len(Xs), -1), mu.shape)


@pytest.mark.parametrize("hyper", [
    HYPER,                                                        # one noise-to-signal ratio
    dict(HYPER, noise_std_rot=0.3),                               # two ratios
])
def test_matches_sklearn_mean_and_latent_std(hyper):
    """Posterior mean and latent std of all 12 components equal scikit-learn's to 1e-8."""
    rng = np.random.default_rng(0)
    A, Z = joint_data(rng, 25)
    As = rng.uniform(-2.5, 2.5, (7, 4))
    model = GPModel(0, 1, (1, 3), **hyper).fit(A, Z)
    mean, std = model.predict_components(As, return_std=True)
    Y = vector12_from_transform(Z)
    X, Xs = A[:, [1, 3]], As[:, [1, 3]]
    for cols, s, r in [(slice(0, 9), hyper["signal_std_rot"], hyper["noise_std_rot"]),
                       (slice(9, 12), hyper["signal_std_trans"], hyper["noise_std_trans"])]:
        mu_ref, std_ref = sklearn_reference(X, Y[:, cols], Xs, s, r, hyper["length_scale"])
        assert_allclose(mean[:, cols], mu_ref, atol=1e-8)
        assert_allclose(std[:, cols], std_ref, atol=1e-8)
    assert model.L_.shape[0] == len(model.hyperparameters.ratios)


def test_predictions_are_valid_and_close_to_truth():
    """Projected predictions are rigid transforms close to the noise-free chain."""
    rng = np.random.default_rng(0)
    A, Z = joint_data(rng, 30, noise=0.01)
    model = GPModel(0, 1, (1, 3), **HYPER).fit(A, Z)
    As = rng.uniform(-1.5, 1.5, (20, 4))
    P, std = model.predict(As, return_std=True)
    check_transform(P, tolerance=1e-10)
    truth = chain(As)
    assert np.max(np.linalg.norm(P[:, :3, 3] - truth[:, :3, 3], axis=1)) < 0.05
    assert std.shape == (20, 2) and np.all(std >= 0.0)


def test_std_grows_to_prior_far_from_data():
    """Far from the data the latent std is the prior: signal_std_trans and sqrt(3/2) signal_std_rot."""
    rng = np.random.default_rng(0)
    A, Z = joint_data(rng, 10)
    model = GPModel(0, 1, (1, 3), **HYPER).fit(A, Z)
    _, std_far = model.predict(np.full((1, 4), 50.0), return_std=True)
    assert_allclose(std_far[0], [HYPER["signal_std_trans"], math.sqrt(1.5) * HYPER["signal_std_rot"]], rtol=1e-12)
    _, std_near = model.predict(A[:1], return_std=True)
    assert np.all(std_near < 0.5 * std_far)


def test_zero_dim_gp_predicts_training_mean():
    """Without actions the GP predicts the (projected) mean of the training targets everywhere."""
    rng = np.random.default_rng(0)
    Z = transform_from_rotvec(rng.normal(0.0, 0.2, (12, 3)), rng.normal(0.0, 0.1, (12, 3)))
    model = GPModel(0, 1, (), **HYPER).fit(rng.normal(size=(12, 3)), Z)
    P = model.predict(rng.normal(size=(3, 3)))
    expected = np.eye(4)
    expected[:3, :3] = project_to_rotation(Z[:, :3, :3].mean(axis=0))
    expected[:3, 3] = Z[:, :3, 3].mean(axis=0)
    assert_allclose(P, np.broadcast_to(expected, (3, 4, 4)), atol=1e-12)
    assert_allclose(model.jacobian(np.zeros(3)), 0.0)


def test_jacobian_matches_central_differences():
    """The analytic Jacobian (GP mean and polar projection) matches central differences of predict."""
    rng = np.random.default_rng(0)
    A, Z = joint_data(rng, 20, m=5, noise=0.2)  # noisy: the mean is far from orthonormal
    model = GPModel(0, 1, (1, 3), **HYPER).fit(A, Z)
    for a in rng.uniform(-2.0, 2.0, (5, 5)):
        J = model.jacobian(a)
        assert J.shape == (5, 4, 4)
        eps = 1e-6
        J_num = np.zeros_like(J)
        for k in range(5):
            step = np.zeros(5)
            step[k] = eps
            J_num[k] = (model.predict(a + step)[0] - model.predict(a - step)[0]) / (2.0 * eps)
        assert_allclose(J, J_num, rtol=1e-6, atol=1e-6 * np.max(np.abs(J_num)))
        assert_allclose(J[[0, 2, 4]], 0.0)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_polar_derivative_matches_central_differences(sign):
    """dR of the SVD projection is exact, also when the determinant is negative and has to be fixed."""
    rng = np.random.default_rng(0)
    M = Rotation.random(random_state=2).as_matrix() @ np.diag([1.3, 0.8, sign * 0.5]) + 0.1 * rng.normal(size=(3, 3))
    dM = rng.normal(size=(4, 3, 3))
    eps = 1e-6
    numeric = (project_to_rotation(M + eps * dM) - project_to_rotation(M - eps * dM)) / (2.0 * eps)
    assert_allclose(polar_derivative(M, dM), numeric, atol=1e-8)


def test_kernel_gradient_matches_central_differences():
    """The kernel gradient helper matches finite differences, batched over leading dims."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 3))
    X = rng.normal(size=(2, 5, 3))
    grad = squared_exponential_gradient(x, X, 0.7)
    eps = 1e-6
    for d in range(3):
        step = np.zeros(3)
        step[d] = eps
        num = (squared_exponential((x + step)[:, None], X, 0.7) - squared_exponential((x - step)[:, None], X, 0.7))
        assert_allclose(grad[..., d], num[:, 0] / (2.0 * eps), atol=1e-9)


@pytest.mark.parametrize("actions", [(1, 3), ()])
def test_round_trip_to_dict_predicts_identically(actions):
    """to_dict -> JSON -> from_dict (directly and via the registry) gives identical predictions."""
    rng = np.random.default_rng(0)
    A, Z = joint_data(rng, 15)
    model = GPModel(3, 4, actions, **HYPER).fit(A, Z)
    data = json.loads(json.dumps(model.to_dict()))
    As = rng.uniform(-2.0, 2.0, (6, 4))
    Z0, s0 = model.predict(As, return_std=True)
    for restored in (GPModel.from_dict(data), model_from_dict(data)):
        Z1, s1 = restored.predict(As, return_std=True)
        assert_allclose(Z1, Z0, rtol=0, atol=1e-15)
        assert_allclose(s1, s0, rtol=0, atol=1e-15)
        assert restored.describe() == model.describe()


def test_predict_before_fit_raises():
    """An unfitted GP (also after a round trip) raises NotFittedError."""
    model = GPModel(0, 1, (0,), **HYPER)
    for m in (model, GPModel.from_dict(model.to_dict())):
        with pytest.raises(NotFittedError):
            m.predict(np.zeros((1, 2)))
        with pytest.raises(NotFittedError):
            m.jacobian(np.zeros(2))


@pytest.mark.parametrize("A, Z", [
    (np.full((3, 4), np.nan), None),                              # NaN action
    (np.zeros((3, 2)), None),                                     # action index 3 out of range
    (np.zeros((3, 4, 1)), None),                                  # wrong shape
    (None, np.full((3, 4, 4), np.inf)),                           # inf observation
    (None, np.broadcast_to(np.diag([1.0, 1.0, 1.5, 1.0]), (3, 4, 4))),  # not rigid
    (None, np.broadcast_to(np.eye(4), (2, 4, 4))),                # length mismatch
])
def test_fit_rejects_bad_input(A, Z):
    """Bad training data raise InvalidInputError naming what was wrong."""
    A = np.zeros((3, 4)) if A is None else A
    Z = np.broadcast_to(np.eye(4), (3, 4, 4)) if Z is None else Z
    with pytest.raises(InvalidInputError):
        GPModel(0, 1, (1, 3), **HYPER).fit(A, Z)


def test_predict_rejects_bad_input():
    """NaN or too short action vectors are rejected at prediction time too."""
    rng = np.random.default_rng(0)
    model = GPModel(0, 1, (1, 3), **HYPER).fit(*joint_data(rng, 5))
    for bad in (np.full(4, np.nan), np.zeros(3), np.zeros((2, 2, 4))):
        with pytest.raises(InvalidInputError):
            model.predict(bad)


@pytest.mark.parametrize("kwargs", [
    dict(HYPER, length_scale=0.0), dict(HYPER, noise_std_rot=-1.0), dict(HYPER, signal_std_trans=np.nan),
    dict(HYPER, noise_std_trans="0.1"),
])
def test_rejects_bad_hyperparameters(kwargs):
    """Hyperparameters must be finite numbers > 0."""
    with pytest.raises(InvalidInputError):
        GPModel(0, 1, (0,), **kwargs)


def test_rejects_repeated_actions():
    """A model cannot depend on the same action twice."""
    with pytest.raises(InvalidInputError):
        GPModel(0, 1, (2, 2), **HYPER)


def test_failed_cholesky_is_reraised_with_advice():
    """A kernel matrix that is not positive definite in floating point raises BodySchemeError with advice."""
    model = GPModel(0, 1, (0,), **dict(HYPER, noise_std_trans=1e-12, noise_std_rot=1e-12 * 0.7 / 0.3))
    with pytest.raises(BodySchemeError, match="noise std"):
        model.fit(np.zeros((4, 2)), np.broadcast_to(np.eye(4), (4, 4, 4)))


def test_negative_variance_is_clamped_with_warning():
    """Round-off below zero becomes 0 with a RuntimeWarning; valid variances pass silently."""
    with pytest.warns(RuntimeWarning, match="smaller than 0"):
        var = _clamp_variance(np.array([[0.5], [-1e-17]]))
    assert_allclose(var, [[0.5], [0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _clamp_variance(np.array([[0.0], [1.0]]))


def test_from_config_uses_one_ratio_from_marker_noise():
    """Per-axis noise (3D RMS / sqrt 3) of two markers; both groups share the larger noise-to-signal ratio."""
    config = BodySchemeConfig(sigma_trans=0.05, sigma_rot=math.radians(15.0), gp_signal_std_trans=0.3,
                              gp_signal_std_rot=0.7, gp_length_scale=0.9)
    hp = GPHyperparameters.from_config(config)
    s_t, s_r = 0.05 / math.sqrt(3), math.radians(15.0) / math.sqrt(3)
    ratio = max(math.sqrt(2) * s_t / 0.3, 2 / math.sqrt(3) * s_r / 0.7)
    assert_allclose([hp.noise_std_trans, hp.noise_std_rot], [ratio * 0.3, ratio * 0.7])
    assert hp.length_scale == 0.9 and len(hp.ratios) == 1
    model = GPModel.from_config(1, 2, (0,), config)
    assert model.hyperparameters == hp
    quiet = BodySchemeConfig(sigma_trans=0.05, sigma_rot=0.001)
    assert_allclose(GPHyperparameters.from_config(quiet).noise_std_trans, math.sqrt(2) * 0.05 / math.sqrt(3))


def test_default_hyperparameters_are_those_of_the_default_config():
    """A GP built without hyperparameters uses exactly what the default configuration derives (models own them)."""
    assert GPModel(1, 2, (0,)).hyperparameters == GPHyperparameters.from_config(BodySchemeConfig())
    partial = GPModel(1, 2, (0,), length_scale=0.5).hyperparameters
    assert partial == GPHyperparameters.from_config(BodySchemeConfig(gp_length_scale=0.5))


@pytest.mark.parametrize("corrupt", [
    lambda d: d.update(kind="static"),
    lambda d: d.pop("hyperparameters"),
    lambda d: d.update(Y=[[0.0] * 11] * 15),
    lambda d: d.update(X=[[0.0]] * 15),
    lambda d: d.update(X=[[float("nan"), 0.0]] * 15),
    lambda d: d["hyperparameters"].update(noise_std_rot=0.0),
])
def test_corrupt_dict_raises_model_file_error(corrupt):
    """Malformed saved GP models raise ModelFileError."""
    rng = np.random.default_rng(0)
    data = json.loads(json.dumps(GPModel(0, 1, (1, 3), **HYPER).fit(*joint_data(rng, 15)).to_dict()))
    corrupt(data)
    with pytest.raises(ModelFileError):
        GPModel.from_dict(data)
