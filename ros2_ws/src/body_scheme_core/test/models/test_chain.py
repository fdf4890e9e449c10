"""The chain local model: a product of exponentials between two parts, its analytic twists and action Jacobian, its
couplings, its state, and the robot's specification as its start."""

import json
import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.models import ChainModel, EngineeredModel, chain_form, chain_from_engineered, model_from_dict
from body_scheme_core.rotations import rotation_log
from body_scheme_core.transforms import transform_from_xyz_rpy
from body_scheme_core.world import KinematicTree, Marker, random_tree

TYPES = ("revolute", "prismatic", "revolute", "revolute")
COUPLINGS = ((2, 0), (3, 1))


def _params(rng, types, n_couplings=0):
    out = []
    for kind in types:
        w = rng.normal(size=3)
        w /= np.linalg.norm(w)
        if kind == "revolute":
            p = rng.normal(size=3)
            out += [*w, *(p - (p @ w) * w)]
        else:
            out += list(w)
    return np.array(out + list(rng.normal(size=n_couplings)) + list(rng.normal(size=3))
                    + list(0.5 * rng.normal(size=3)))


@pytest.mark.parametrize("couplings", [(), COUPLINGS])
def test_twists_are_the_derivatives_of_the_retraction(couplings):
    """The analytic twists [dt, w] match finite differences of the chart (forward differences, 1e-6)."""
    rng = np.random.default_rng(0)
    form = chain_form(TYPES, couplings)
    params = _params(rng, TYPES, len(couplings))
    form.validate(params)
    x = rng.normal(size=(1, 6, len(TYPES)))
    Z, T = form.evaluate(params[None], x)
    eps = 1e-6
    for j in range(form.N_PARAMS):
        delta = np.zeros((1, form.N_PARAMS))
        delta[0, j] = eps
        Zp = form.transforms(form.retract(params[None], delta), x)
        dt = (Zp[..., :3, 3] - Z[..., :3, 3]) / eps
        dw = rotation_log(np.swapaxes(Z[..., :3, :3], -1, -2) @ Zp[..., :3, :3]) / eps
        assert np.allclose(T[..., :3, j], dt, atol=1e-4) and np.allclose(T[..., 3:, j], dw, atol=1e-4), j


def test_the_action_jacobian_and_the_one_sample_path_agree_with_predict():
    """jacobian(a) is dZ/da by finite differences, zero for actions outside the chain; predict_one equals predict."""
    rng = np.random.default_rng(1)
    model = ChainModel(1, 2, (0, 2, 3, 5), TYPES, reference=rng.normal(size=4), couplings=COUPLINGS)
    model._set_fit(_params(rng, TYPES, 2), np.eye(model.n_params) * 1e-6, 10, 1.0)
    a = rng.normal(size=7)
    J = model.jacobian(a)
    for i in range(7):
        ap = a.copy()
        ap[i] += 1e-6
        assert np.allclose((model.predict(ap[None])[0] - model.predict(a[None])[0]) / 1e-6, J[i], atol=1e-4)
    assert not np.any(J[[1, 4, 6]])
    assert np.allclose(model.predict_one(a), model.predict(a[None])[0])
    Z, std = model.predict(rng.normal(size=(3, 7)), return_std=True)
    assert std.shape == (3, 2) and np.all(std > 0)


def test_a_chain_round_trips_through_its_dict_and_refuses_bad_ones():
    """to_dict / model_from_dict keep types, reference, couplings and parameters; a bad type or a coupling of a
    joint to itself is a ModelFileError."""
    rng = np.random.default_rng(2)
    model = ChainModel(3, 4, (1, 0, 2, 4), TYPES, reference=[0.1, 0.2, 0.3, 0.4], couplings=COUPLINGS,
                       order_evidence=9)
    model._set_fit(_params(rng, TYPES, 2), np.eye(model.n_params) * 1e-6, 10, 1.0)
    data = json.loads(json.dumps(model.to_dict()))
    again = model_from_dict(data)
    A = rng.normal(size=(4, 5))
    assert again.types == model.types and again.couplings == model.couplings and again.order_evidence == 9
    assert np.allclose(again.predict(A), model.predict(A))
    for key, value in (("types", ["revolute", "spherical", "revolute", "revolute"]), ("couplings", [[1, 1]])):
        bad = json.loads(json.dumps(data))
        bad["hyperparameters"][key] = value
        with pytest.raises(ModelFileError):
            model_from_dict(bad)
    with pytest.raises(InvalidInputError, match="distinct"):
        ChainModel(1, 2, (0, 0), ("revolute", "revolute"))


def test_the_specification_as_a_chain_predicts_as_the_engineered_model():
    """chain_from_engineered: the same transforms and Jacobians as the engineered model, at any reference posture,
    prismatic joints and joints traversed from child to parent included."""
    rng = np.random.default_rng(3)
    tree = random_tree(5, seed=4, branching=False, prismatic_fraction=0.4)
    links = [j.child for j in tree.joints]
    marked = KinematicTree(tree.joints, [Marker(1, links[-1], transform_from_xyz_rpy([0.1, 0, 0], [0.2, 0, 0])),
                                         Marker(2, tree.root_link, transform_from_xyz_rpy([0, 0.1, 0], [0, 0.3, 0]))],
                           root_link=tree.root_link)
    engineered = EngineeredModel.from_tree(marked, 1, 2)  # from the tool up to the base: signs -1
    A = rng.uniform(marked.action_lower, marked.action_upper, size=(10, marked.n_actions))
    for reference in (None, rng.uniform(-0.5, 0.5, len(engineered.actions))):
        chain = chain_from_engineered(engineered, reference=reference)
        assert np.allclose(chain.predict(A), engineered.predict(A), atol=1e-12)
        assert np.allclose(chain.jacobian(A[0]), engineered.jacobian(A[0]), atol=1e-12)


def test_a_specification_prior_is_every_joint_off_by_the_tolerance():
    """chain_from_engineered's prior: the spread of the child's predicted position over robots whose every joint
    origin and child mount are off the specification by (2 mm, 0.5 deg) per axis (Monte Carlo, 400 robots) is the
    one the chain's covariance predicts, within 15 %, at several postures; far larger than one joint's 2 mm."""
    import dataclasses

    from body_scheme_core.transforms import transform_from_rotvec

    rng = np.random.default_rng(11)
    tree = random_tree(5, seed=6, branching=False, prismatic_fraction=0.4)
    tool = tree.joints[-1].child
    markers = [Marker(1, tree.root_link, np.eye(4)), Marker(2, tool, transform_from_xyz_rpy([0.05, 0, 0], [0, 0, 0]))]
    sigma_t, sigma_r = 0.002, math.radians(0.5)

    def off(xi):
        return transform_from_rotvec(xi[3:], xi[:3])

    def robot(errors=None):
        joints = list(tree.joints)
        mount = markers[1].link2marker
        if errors is not None:
            moved = iter(errors[:-1])
            joints = [dataclasses.replace(j, origin=j.origin @ off(next(moved))) if j.action is not None else j
                      for j in joints]
            mount = mount @ off(errors[-1])
        marked = KinematicTree(joints, [markers[0], dataclasses.replace(markers[1], link2marker=mount)],
                               root_link=tree.root_link)
        return EngineeredModel.from_tree(marked, 1, 2)

    nominal = robot()
    spec = chain_from_engineered(nominal, prior=(sigma_t, sigma_r))
    A = rng.uniform(-1, 1, size=(4, tree.n_actions))
    _, std = spec.predict(A, return_std=True)
    n_moving = sum(j.action is not None for j in tree.joints)
    scale = np.r_[[sigma_t] * 3, [sigma_r] * 3]
    samples = np.stack([robot(rng.normal(size=(n_moving + 1, 6)) * scale).predict(A)[:, :3, 3] for _ in range(400)])
    spread = np.sqrt(np.mean(np.var(samples, axis=0), axis=1))  # per-axis RMS std of the position, per posture
    assert np.all(np.abs(spread / std[:, 0] - 1.0) < 0.15), (spread, std[:, 0])
    assert np.all(std[:, 0] > 2 * sigma_t)


def test_a_specification_prior_holds_at_a_half_turn():
    """A marker mounted upside down (the chain's M a half turn, where a rotation vector flips its sign): the prior is
    the same as a hair away from it, not bent by a difference across the flip."""
    def engineered(angle):
        chain = [{"type": "revolute", "axis": [0.0, 0.0, 1.0], "action": 0},
                 {"type": "fixed", "transform": transform_from_xyz_rpy([0.3, 0, 0.1], [0, 0, 0]).tolist()},
                 {"type": "revolute", "axis": [0.0, 1.0, 0.0], "action": 1},
                 {"type": "fixed", "transform": transform_from_xyz_rpy([0.2, 0, 0], [angle, 0, 1.0]).tolist()}]
        return EngineeredModel(1, 2, (0, 1), chain)

    A = np.random.default_rng(4).uniform(-1, 1, size=(5, 2))
    stds = [chain_from_engineered(engineered(angle), prior=(0.002, math.radians(0.5))).predict(A, return_std=True)[1]
            for angle in (math.pi, math.pi - 1e-4)]
    assert np.all(np.isfinite(stds[0])) and np.allclose(stds[0], stds[1], rtol=1e-3)


def test_a_fit_needs_a_start_and_refines_from_a_perturbed_one():
    """A chain has no closed-form start; from the truth moved by 2 cm and 2 deg per joint the fit returns within
    noise on 40 samples."""
    rng = np.random.default_rng(5)
    types = ("revolute", "revolute", "prismatic")
    truth = ChainModel(1, 2, (0, 1, 2), types)
    true_params = _params(rng, types)
    truth._set_fit(true_params, np.eye(truth.n_params) * 1e-9, 0, 0.0)
    A = rng.uniform(-1, 1, size=(40, 3))
    Z = truth.predict(A)
    with pytest.raises(InvalidInputError, match="needs a start"):
        ChainModel(1, 2, (0, 1, 2), types).fit(A, Z)
    start = truth.form.retract(true_params[None], rng.normal(0, math.radians(2), size=(1, truth.n_params)))[0]
    fitted = ChainModel(1, 2, (0, 1, 2), types, sigma_trans=1e-3, sigma_rot=1e-3).fit(A, Z, start=start)
    assert np.abs(fitted.predict(A) - Z).max() < 1e-6
