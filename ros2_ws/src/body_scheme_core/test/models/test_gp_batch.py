"""Tests of the batched incremental GP engine: equal to GPModel and scikit-learn, persistence, input checks."""

import itertools
import json

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel

from body_scheme_core.errors import BodySchemeError, InvalidInputError, ModelFileError, NotFittedError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.models import GPBatch, GPModel
from body_scheme_core.models.gp_kernel import squared_exponential
from body_scheme_core.rotations import project_to_rotation, project_to_rotation_batch
from body_scheme_core.transforms import check_transform, transform_from_rotvec

HYPER = dict(length_scale=0.8, signal_std_trans=0.3, signal_std_rot=0.7, noise_std_trans=0.06, noise_std_rot=0.14)
M = 5


def random_Z(rng, n):
    return transform_from_rotvec(rng.normal(0.0, 0.8, (n, 3)), rng.normal(0.0, 0.5, (n, 3)))


def filled_batch(rng, actions_list, n_samples, hyper=HYPER, capacity=12):
    """A batch whose slots received the same action vectors and per-slot random observations."""
    batch = GPBatch(M, capacity, 2, **hyper)
    slots = batch.allocate(actions_list)
    A = rng.uniform(-2.0, 2.0, (n_samples, M))
    Z = np.stack([random_Z(rng, len(slots)) for _ in range(n_samples)])
    for a, Zt in zip(A, Z, strict=True):
        batch.add_samples(slots, a, Zt)
    return batch, slots, A, Z


ACTIONS = [(), (0,), (3,), (1, 4), (4, 1), (2, 0)]


@pytest.mark.parametrize("hyper", [HYPER, dict(HYPER, noise_std_rot=0.3)])
def test_batch_matches_individual_gp_models(hyper):
    """Every slot predicts like a GPModel fitted from scratch on its data (mean and std), for 1 or 2 ratios."""
    rng = np.random.default_rng(0)
    batch, slots, A, Z = filled_batch(rng, ACTIONS, 9, hyper)
    models = [GPModel(0, 1, acts, **hyper).fit(A, Z[:, j]) for j, acts in enumerate(ACTIONS)]
    for a in rng.uniform(-2.5, 2.5, (4, M)):
        Zb, sb = batch.predict(slots, a, return_std=True)
        for j, model in enumerate(models):
            Zm, sm = model.predict(a, return_std=True)
            assert_allclose(Zb[j], Zm[0], atol=1e-10)
            assert_allclose(sb[j], sm[0], atol=1e-10)


def test_batch_matches_sklearn():
    """Slot means and latent std equal scikit-learn's GaussianProcessRegressor on centred targets to 1e-8."""
    rng = np.random.default_rng(0)
    batch, slots, A, Z = filled_batch(rng, [(1, 4)], 10)
    As = rng.uniform(-2.0, 2.0, (5, M))
    X = A[:, [1, 4]]
    t = Z[:, 0, :3, 3]
    kernel = ConstantKernel(HYPER["signal_std_trans"] ** 2, "fixed") * RBF(HYPER["length_scale"], "fixed")
    gp = GaussianProcessRegressor(kernel, alpha=HYPER["noise_std_trans"] ** 2, optimizer=None)
    gp.fit(X, t - t.mean(axis=0))
    mu, std = gp.predict(As[:, [1, 4]], return_std=True)
    for i, a in enumerate(As):
        Zb, sb = batch.predict(slots, a, return_std=True)
        assert_allclose(Zb[0, :3, 3], mu[i] + t.mean(axis=0), atol=1e-8)
        assert_allclose(sb[0, 0], np.atleast_1d(std[i])[0], atol=1e-8)


def test_incremental_inverse_equals_fit_from_scratch():
    """After n incremental updates each slot's stored inverse is (K + r^2 I)^-1 of its data."""
    rng = np.random.default_rng(0)
    batch, slots, A, _ = filled_batch(rng, [(0,), (1, 4)], 11)
    ratio2 = (HYPER["noise_std_trans"] / HYPER["signal_std_trans"]) ** 2
    for slot, acts in zip(slots, [(0,), (1, 4)], strict=True):
        X = A[:, list(acts)]
        expected = np.linalg.inv(squared_exponential(X, X, HYPER["length_scale"]) + ratio2 * np.eye(11))
        assert_allclose(batch._Kinv[slot, 0, :11, :11], expected, atol=1e-10)
        assert_allclose(batch._Kinv[slot, 0, 11:], 0.0)


def test_predictions_are_valid_transforms():
    """Projected slot predictions are rigid transforms even for wild training data."""
    rng = np.random.default_rng(0)
    batch, slots, _, _ = filled_batch(rng, ACTIONS * 10, 6)
    Z = batch.predict(slots, rng.uniform(-2.0, 2.0, M))
    check_transform(Z, tolerance=1e-10)


def test_fast_projection_equals_svd_projection():
    """The batched Newton projection agrees with the SVD projection, including det <= 0 and near-singular input."""
    rng = np.random.default_rng(0)
    R = Rotation.random(300, random_state=1).as_matrix()
    M_ = np.concatenate([R, R + 0.1 * rng.normal(size=R.shape), rng.normal(size=(300, 3, 3)),
                         0.2 * R + 0.3 * rng.normal(size=R.shape), R @ np.diag([1.0, 1.0, 1e-9])])
    assert np.any(np.linalg.det(M_) < 0)
    assert_allclose(project_to_rotation_batch(M_), project_to_rotation(M_), atol=1e-12)
    assert project_to_rotation_batch(np.zeros((0, 3, 3))).shape == (0, 3, 3)


def test_empty_slot_predicts_identity_with_infinite_std():
    """An empty slot returns the identity and std = inf; filled slots in the same call are unaffected."""
    rng = np.random.default_rng(0)
    batch, slots, _, _ = filled_batch(rng, [(0,)], 3)
    empty = batch.allocate([(1,)])
    Z, std = batch.predict(np.r_[slots, empty], np.zeros(M), return_std=True)
    assert_allclose(Z[1], np.eye(4))
    assert np.all(np.isinf(std[1])) and np.all(np.isfinite(std[0]))
    assert batch.size(np.r_[slots, empty]).tolist() == [3, 0]


def test_to_model_predicts_identically():
    """to_model gives a GPModel with the slot's actions and data; an empty slot gives an unfitted model."""
    rng = np.random.default_rng(0)
    batch, slots, _, _ = filled_batch(rng, ACTIONS, 7)
    for j, slot in enumerate(slots):
        model = batch.to_model(slot, 2, 3)
        assert model.actions == ACTIONS[j] and model.pair == (2, 3) and model.n_samples == 7
        for a in rng.uniform(-2.0, 2.0, (3, M)):
            Zb, sb = batch.predict([slot], a, return_std=True)
            Zm, sm = model.predict(a, return_std=True)
            assert_allclose(Zm, Zb, atol=1e-10)
            assert_allclose(sm, sb, atol=1e-10)
    with pytest.raises(NotFittedError):
        batch.to_model(batch.allocate([(0,)])[0], 0, 1).predict(np.zeros(M))


def test_state_dict_round_trip_predicts_identically():
    """state_dict -> JSON -> from_state_dict keeps slot indices, free slots, sizes and predictions."""
    rng = np.random.default_rng(0)
    batch, slots, _, _ = filled_batch(rng, ACTIONS, 5)
    batch.release(slots[[1, 3]])
    more = batch.allocate([(2,)])
    batch.add_samples(more, np.ones(M), random_Z(rng, 1))
    keep = np.r_[slots[[0, 2, 4, 5]], more]
    restored = GPBatch.from_state_dict(json.loads(json.dumps(batch.state_dict())))
    assert restored.allocated_slots.tolist() == batch.allocated_slots.tolist()
    assert restored.size(keep).tolist() == batch.size(keep).tolist()
    for a in rng.uniform(-2.0, 2.0, (3, M)):
        Z0, s0 = batch.predict(keep, a, return_std=True)
        Z1, s1 = restored.predict(keep, a, return_std=True)
        assert_allclose(Z1, Z0, rtol=0, atol=1e-12)
        assert_allclose(s1, s0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("corrupt", [
    lambda d: d.update(format="other"),
    lambda d: d.update(version=99),
    lambda d: d.pop("slots"),
    lambda d: d["slots"][0].update(Y=[[0.0] * 11]),
    lambda d: d["slots"][0].update(actions=[0, 99]),
    lambda d: d["slots"][0].update(X=[[float("nan")]]),
    lambda d: d["hyperparameters"].update(length_scale=-1.0),
])
def test_corrupt_state_raises_model_file_error(corrupt):
    """Malformed saved states raise ModelFileError."""
    rng = np.random.default_rng(0)
    batch, _, _, _ = filled_batch(rng, [(0,)], 1)
    data = json.loads(json.dumps(batch.state_dict()))
    corrupt(data)
    with pytest.raises(ModelFileError):
        GPBatch.from_state_dict(data)


def test_prediction_cache_is_not_reused_for_another_action():
    """add_samples after predict at a different action vector still adds the right sample."""
    rng = np.random.default_rng(0)
    batch, slots, A, Z = filled_batch(rng, [(0, 2)], 4)
    a_new, Z_new = rng.uniform(-2.0, 2.0, M), random_Z(rng, 1)
    batch.predict(slots, rng.uniform(-2.0, 2.0, M))
    batch.add_samples(slots, a_new, Z_new)
    model = GPModel(0, 1, (0, 2), **HYPER).fit(np.r_[A, a_new[None]], np.r_[Z[:, 0], Z_new])
    assert_allclose(batch.predict(slots, A[0]), model.predict(A[0]), atol=1e-10)


def test_non_contiguous_slots_match_contiguous():
    """Permuted slot order (index path) and consecutive slots (view path) give the same state and predictions."""
    rng = np.random.default_rng(0)
    A = rng.uniform(-2.0, 2.0, (6, M))
    Z = np.stack([random_Z(rng, 4) for _ in range(6)])
    b1, b2 = GPBatch(M, 8, 2, **HYPER), GPBatch(M, 8, 2, **HYPER)
    s1, s2 = b1.allocate(ACTIONS[:4]), b2.allocate(ACTIONS[:4])
    order = np.array([2, 0, 3, 1])
    for a, Zt in zip(A, Z, strict=True):
        b1.predict(s1, a)
        b1.add_samples(s1, a, Zt)
        b2.predict(s2[order], a)
        b2.add_samples(s2[order], a, Zt[order])
    a = rng.uniform(-2.0, 2.0, M)
    assert_allclose(b2.predict(s2, a), b1.predict(s1, a), atol=1e-12)


def test_broadcast_single_observation_and_full_slots():
    """One (4, 4) Z is broadcast to all slots; a full slot rejects further samples with InvalidInputError."""
    batch = GPBatch(M, 2, 1, **HYPER)
    slots = batch.allocate([(0,), (1,)])
    Z = transform_from_rotvec([0.1, 0.2, 0.3], [0.0, 1.0, 0.0])
    batch.add_samples(slots, np.zeros(M), Z)
    batch.add_samples(slots[:1], np.ones(M), Z)
    assert batch.size(slots).tolist() == [2, 1]
    with pytest.raises(InvalidInputError, match="capacity"):
        batch.add_samples(slots, np.full(M, 2.0), Z)
    assert batch.size(slots).tolist() == [2, 1]  # nothing was added to the other slot either
    assert batch.capacity == 2


def test_allocate_reuses_released_slots_and_grows():
    """Released slots are reused lowest first; storage grows past its initial size."""
    batch = GPBatch(M, 3, 2, **HYPER)
    slots = batch.allocate([(0,)] * 40)
    assert slots.tolist() == list(range(40))
    batch.add_samples(slots[5:7], np.zeros(M), np.eye(4))
    batch.release(slots[5:7])
    again = batch.allocate([(1, 2), (3,)])
    assert again.tolist() == [5, 6]
    assert batch.size(again).tolist() == [0, 0]
    assert batch.slot_actions(5) == (1, 2) and batch.n_allocated == 40


@pytest.mark.parametrize("call", [
    lambda b, s: b.predict(s, np.full(M, np.nan)),                       # NaN action
    lambda b, s: b.predict(s, np.zeros(M + 1)),                          # wrong length
    lambda b, s: b.predict(s, np.zeros((2, M))),                         # more than one vector
    lambda b, s: b.predict([99], np.zeros(M)),                           # slot out of range
    lambda b, s: b.predict([-1], np.zeros(M)),                           # negative slot
    lambda b, s: b.predict(np.array([0.5]), np.zeros(M)),                # float slot
    lambda b, s: b.add_samples(s, np.zeros(M), np.diag([1.0, 2.0, 1.0, 1.0])),       # not rigid
    lambda b, s: b.add_samples(s, np.zeros(M), np.full((4, 4), np.nan)),             # NaN observation
    lambda b, s: b.add_samples(s, np.zeros(M), np.broadcast_to(np.eye(4), (5, 4, 4))),  # wrong count
    lambda b, s: b.add_samples(np.r_[s, s[:1]], np.zeros(M), np.eye(4)),             # repeated slot
    lambda b, s: b.allocate([(M,)]),                                     # action index out of range
    lambda b, s: b.allocate([(0, 1, 2)]),                                # more than max_dim actions
    lambda b, s: b.allocate([(1, 1)]),                                   # repeated action
    lambda b, s: b.allocate([("a",)]),                                   # not an index
])
def test_rejects_bad_input(call):
    """Bad slots, actions and observations raise InvalidInputError."""
    batch = GPBatch(M, 4, 2, **HYPER)
    slots = batch.allocate([(0,), (1, 2)])
    with pytest.raises(InvalidInputError):
        call(batch, slots)


def test_released_slot_is_rejected():
    """A released slot cannot be used until it is allocated again."""
    batch = GPBatch(M, 4, 2, **HYPER)
    slots = batch.allocate([(0,), (1,)])
    batch.release(slots[:1])
    with pytest.raises(InvalidInputError, match="not allocated"):
        batch.predict(slots, np.zeros(M))


def test_lost_positive_definiteness_raises_with_advice():
    """A noise-free duplicate sample makes the Schur complement vanish: BodySchemeError, state unchanged."""
    batch = GPBatch(M, 4, 1, **dict(HYPER, noise_std_trans=1e-12, noise_std_rot=1e-12 * 0.7 / 0.3))
    slots = batch.allocate([(0,)])
    batch.add_samples(slots, np.zeros(M), np.eye(4))
    with pytest.raises(BodySchemeError, match="noise std"):
        batch.add_samples(slots, np.zeros(M), np.eye(4))
    assert batch.size(slots).tolist() == [1]


def test_from_config_sizes():
    """capacity is the training window and max_dim the largest complexity unless given."""
    config = BodySchemeConfig(train_window=17, max_complexity=2)
    assert (GPBatch.from_config(6, config).capacity, GPBatch.from_config(6, config).max_dim) == (17, 2)
    assert GPBatch.from_config(6, config, max_dim=4).max_dim == 4


def test_bootstrapping_workload_fills_every_slot():
    """The paper's 462-candidate bootstrapping (7 parts, 6 actions, complexity <= 2) fills all slots exactly."""
    rng = np.random.default_rng(0)
    subsets = [()] + [(i,) for i in range(6)] + list(itertools.combinations(range(6), 2))
    batch = GPBatch.from_config(6, BodySchemeConfig())
    slots = batch.allocate(subsets * 21)
    for _ in range(batch.capacity):
        a = rng.uniform(-2.0, 2.0, 6)
        batch.predict(slots, a, return_std=True)
        batch.add_samples(slots, a, random_Z(rng, slots.size))
    assert slots.size == 462 and np.all(batch.size(slots) == batch.capacity)
    with pytest.raises(InvalidInputError):
        batch.add_samples(slots[:1], rng.uniform(-2.0, 2.0, 6), random_Z(rng, 1))


def test_adding_to_a_subset_after_predicting_all():
    """The learner's pattern, predict all slots then add to those not full, matches models fitted from scratch."""
    rng = np.random.default_rng(0)
    batch = GPBatch(M, 3, 2, **HYPER)
    slots = batch.allocate(ACTIONS)
    data = {int(s): ([], []) for s in slots}
    for step in range(6):
        a = rng.uniform(-2.0, 2.0, M)
        Z = random_Z(rng, slots.size)
        batch.predict(slots, a)
        open_ = (batch.size(slots) < batch.capacity) & (rng.random(slots.size) < 0.7 if step else True)
        batch.add_samples(slots[open_][::-1], a, Z[open_][::-1])
        for s, Zs in zip(slots[open_], Z[open_], strict=True):
            data[int(s)][0].append(a)
            data[int(s)][1].append(Zs)
    a = rng.uniform(-2.0, 2.0, M)
    for s, acts in zip(slots, ACTIONS, strict=True):
        model = GPModel(0, 1, acts, **HYPER).fit(np.array(data[int(s)][0]), np.array(data[int(s)][1]))
        assert batch.size([s])[0] == len(data[int(s)][0])
        assert_allclose(batch.predict([s], a), model.predict(a), atol=1e-10)
