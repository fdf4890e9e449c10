"""Tests of the tracked models: prequential evaluation, storage, freezing, dominance and state."""


import numpy as np

from body_scheme_core.calibration.noise_model import NoiseModel
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.pool import ModelPool
from body_scheme_core.learning.quality import prediction_errors
from body_scheme_core.learning.relative import PartPairs
from body_scheme_core.learning.tracked import MEMORY, TREE, TrackedModel, nested_models
from body_scheme_core.models import GPModel, RevoluteModel, StaticModel
from body_scheme_core.transforms import invert_transform, transform_from_rotvec

CONFIG = BodySchemeConfig()
NOISE = NoiseModel.from_config((1, 2), CONFIG)
PAIRS = PartPairs((1, 2), NOISE)


def _link(a):
    """True ``1->2`` transform of a one-joint link: yaw ``a``, 0.3 m along the rotated x axis."""
    return transform_from_rotvec([0.0, 0.0, a], [0.3 * np.cos(a), 0.3 * np.sin(a), 0.0])


def _targets(a, k):
    """Relative-observation targets of k models of pair 1->2 at action ``a``."""
    relative = PAIRS.observe({1: np.eye(4), 2: _link(a)})
    return relative.targets(np.zeros(k, dtype=np.intp))


def _train(pool, a, step):
    ls = pool.learning()
    pool.train(ls.ids, np.array([a]), _targets(a, ls.ids.size), step)


def test_each_sample_is_tested_before_it_is_learned():
    """The error recorded for a sample is the error of the model trained on the samples before it."""
    pool = ModelPool(CONFIG, 1)
    (entry,) = pool.add_learning([(1, 2, (0,), "gp")], origin="test")
    _train(pool, 0.3, 0)
    assert pool.monitor.count[entry.row] == 0  # an empty GP's prediction says nothing and is not recorded
    assert pool.n_now(entry) == 1
    before = pool.model_of(entry)
    _train(pool, -0.5, 1)
    e_t, e_r = prediction_errors(before.predict([[-0.5]])[0], _link(-0.5))
    np.testing.assert_allclose(pool.monitor.errors[entry.row, 0], [e_t, e_r], rtol=1e-9, atol=1e-12)
    assert pool.monitor.n_train[entry.row, 0] == 1 and pool.n_now(entry) == 2


def test_rigid_candidates_are_tested_from_their_first_fit():
    """A revolute candidate predicts (and is tested) only once it holds three samples, then learns each sample."""
    pool = ModelPool(CONFIG, 1)
    (entry,) = pool.add_learning([(1, 2, (0,), "revolute")], origin="test")
    for t, a in enumerate([0.1, -0.6, 0.9, 0.4]):
        _train(pool, a, t)
    assert pool.n_now(entry) == 4 and pool.monitor.count[entry.row] == 1
    assert pool.monitor.n_train[entry.row, 0] == 3
    model = pool.model_of(entry)
    assert isinstance(model, RevoluteModel) and pool.model_of(entry) is not model  # snapshots are not kept


def test_candidates_stop_learning_at_train_window():
    """Candidates keep being tested after train_window samples but learn no more."""
    pool = ModelPool(BodySchemeConfig(train_window=3), 1)
    gp, rigid = pool.add_learning([(1, 2, (0,), "gp"), (1, 2, (0,), "revolute")], origin="test")
    for t, a in enumerate(np.linspace(-1.0, 1.0, 6)):
        _train(pool, a, t)
    assert pool.n_now(gp) == pool.n_now(rigid) == 3
    assert pool.monitor.count[gp.row] == 5 and pool.monitor.count[rigid.row] == 3


def test_fitted_models_are_tested_and_only_tree_models_run_a_cusum():
    """Tree and memory models both record errors; only the tree model's CUSUM rises and alarms."""
    pool = ModelPool(CONFIG, 1)
    wrong = StaticModel(1, 2).fit(np.zeros((1, 1)), _link(1.5)[None])
    right = StaticModel(2, 1).fit(np.zeros((1, 1)), invert_transform(_link(0.0))[None])
    (tree,) = pool.add_fitted([wrong], TREE, origin="test", last_used=0)
    (memory,) = pool.add_fitted([right], MEMORY, origin="test", last_used=0)
    alarms = []
    for t in range(4):
        targets = _targets(0.0, 2)
        targets = targets._replace(flip=np.array([False, True]))  # memory predicts 2->1: compared inverted
        alarms.append(pool.evaluate([tree, memory], np.array([0.0]), targets, t, cusum=[True, False]).tolist())
    assert alarms[-1] == [True, False]
    assert np.all(pool.monitor.cusum[memory.row] == 0.0) and pool.monitor.count[memory.row] == 4
    np.testing.assert_allclose(pool.monitor.errors[memory.row, :4], 0.0, atol=1e-7)


def test_freeze_turns_a_candidate_into_a_fitted_model():
    """A learning rigid candidate becomes a fitted model with a covariance and leaves its batch."""
    pool = ModelPool(CONFIG, 1)
    (entry,) = pool.add_learning([(1, 2, (0,), "revolute")], origin="test")
    for t, a in enumerate(np.linspace(-1.0, 1.0, 8)):
        _train(pool, a, t)
    model = pool.freeze(entry)
    assert entry.slot == -1 and pool.rigid_batch.n_allocated == 0 and pool.learning().ids.size == 0
    assert isinstance(entry.model, RevoluteModel) and model is entry.model and entry.n_train == 8
    assert model.param_cov_.shape == (10, 10)
    np.testing.assert_allclose(model.predict([[0.25]])[0], _link(0.25), atol=1e-6)


def test_removing_a_model_frees_its_slot_and_row():
    """remove() releases the batch slot and the monitor row for reuse."""
    pool = ModelPool(CONFIG, 1)
    entries = pool.add_learning([(1, 2, (), "static"), (1, 2, (0,), "gp"), (2, 1, (0,), "revolute")], origin="test")
    assert pool.n_learning == 3 and [e.id for e in entries] == [0, 1, 2] and pool.next_id == 3
    pool.remove(entries[1])
    assert pool.n_learning == 2 and pool.gp_batch.n_allocated == 0 and pool.rigid_batch.n_allocated == 2
    assert int(pool.monitor.in_use.sum()) == 2
    assert list(pool.tracked) == [0, 2] and pool.learning().ids.tolist() == [0, 2]


def test_nested_models_pair_what_a_more_flexible_model_can_represent():
    """Within one pair and target: static < revolute, prismatic < GP on the same or more actions; GP < larger GP."""
    specs = [(1, 2, (), "static", -1), (1, 2, (0,), "revolute", -1), (1, 2, (0,), "prismatic", -1),
             (1, 2, (0,), "gp", -1), (1, 2, (0, 1), "gp", -1), (1, 2, (1,), "gp", 5), (1, 3, (0, 1), "gp", -1)]
    models = [TrackedModel(k, p, c, acts, kind, "candidate", k, target=target)
              for k, (p, c, acts, kind, target) in enumerate(specs)]
    sub, sup = nested_models(models)
    assert sorted(zip(sub.tolist(), sup.tolist(), strict=True)) == [
        (0, 1), (0, 2), (0, 3), (0, 4), (1, 3), (1, 4), (2, 3), (2, 4), (3, 4)]


def test_a_model_clearly_beaten_by_one_that_nests_it_is_dominated():
    """A paired advantage above dominance_margin marks the simpler model; a small one or an invalid model not."""
    pool = ModelPool(CONFIG, 1)
    rows = pool.monitor.allocate(3)
    theta = NOISE.theta_trans
    for t in range(5):
        pool.monitor.record(rows, [0.8 * theta, 0.2 * theta, 0.7 * theta], [0.1, 0.1, 0.1], t, n_train=10,
                            cusum=False)
    sub, sup = np.array([0, 2]), np.array([1, 0])
    np.testing.assert_array_equal(pool.dominated(rows, [10, 10, 10], sub, sup), [True, False, False])
    np.testing.assert_array_equal(pool.dominated(rows, [10, 10, 10], sub, sup, valid=[False, True, True]),
                                  [False, False, False])


def test_keep_only_freezes_the_kept_models_in_compact_storage():
    """Kept models become fitted models with their test windows; the rest is dropped, batches start empty."""
    pool = ModelPool(CONFIG, 1)
    dropped, kept = pool.add_learning([(1, 2, (), "static"), (1, 2, (0,), "gp")], origin="test")
    for t, a in enumerate(np.linspace(-1.0, 1.0, 5)):
        _train(pool, a, t)
    errors = pool.monitor.errors[kept.row].copy()
    old_model = pool.model_of(kept)
    pool.keep_only([kept])
    assert list(pool.tracked) == [kept.id] and dropped.id not in pool.tracked and pool.n_learning == 0
    assert isinstance(kept.model, GPModel) and kept.n_train == 5 and pool.monitor.capacity == 1
    np.testing.assert_array_equal(pool.monitor.errors[kept.row], errors)
    np.testing.assert_allclose(kept.model.predict([[0.4]]), old_model.predict([[0.4]]), atol=1e-12)
