"""Tests of the tracked models: prequential evaluation, storage, freezing, dominance and state."""

import json

import numpy as np
import pytest

from body_scheme_core.config import BodySchemeConfig
from body_scheme_core.errors import ModelFileError
from body_scheme_core.models import GPModel, StaticModel
from body_scheme_core.pool import (
    MEMORY,
    TREE,
    ModelPool,
    TrackedModel,
    format_errors,
    nested_pairs,
    new_batch,
    new_monitor,
    refine_window,
)
from body_scheme_core.quality import prediction_errors
from body_scheme_core.relative import PartPairs
from body_scheme_core.transforms import invert_transform, transform_from_rotvec


def _pool(config=None, parts=(1, 2), n_actions=1, capacity=None, max_dim=1):
    config = BodySchemeConfig() if config is None else config
    pairs = PartPairs(parts, config.theta_trans, config.theta_rot)
    batch = new_batch(config, n_actions, capacity or config.train_window, max_dim)
    return ModelPool(config, n_actions, pairs, batch, new_monitor(config))


def _link(a):
    """True ``1->2`` transform of a one-joint link: yaw ``a``, 0.3 m along the rotated x axis."""
    return transform_from_rotvec([0.0, 0.0, a], [0.3 * np.cos(a), 0.3 * np.sin(a), 0.0])


def _step(pool, a, step, train=True):
    """Observe parts 1 (at the origin) and 2 at action ``a``; run the learning or the frozen models."""
    relative = pool.pairs.observe({1: np.eye(4), 2: _link(a)})
    if train:
        return pool.train_learning(np.array([a]), relative, step)
    return pool.evaluate_frozen(np.array([a]), relative, step)


def test_each_sample_is_tested_before_it_is_learned():
    """The error recorded for a sample is the error of the model trained on the samples before it."""
    pool = _pool()
    (entry,) = pool.add_learning([(1, 2, (0,))], origin="test")
    ids, _ = _step(pool, 0.3, 0)
    assert ids.tolist() == [entry.id]
    assert pool.monitor.count[entry.row] == 0  # an empty GP's prediction says nothing and is not recorded
    assert pool.n_now(entry) == 1
    before = pool.batch.to_model(entry.slot, 1, 2)
    _step(pool, -0.5, 1)
    e_t, e_r = prediction_errors(before.predict([[-0.5]])[0], _link(-0.5))
    np.testing.assert_allclose(pool.monitor.errors[entry.row, 0], [e_t, e_r], rtol=1e-9, atol=1e-12)
    assert pool.monitor.n_train[entry.row, 0] == 1 and pool.n_now(entry) == 2


def test_candidates_stop_learning_at_train_window():
    """Candidates keep being tested after train_window samples but learn no more."""
    pool = _pool(BodySchemeConfig(train_window=3))
    (entry,) = pool.add_learning([(1, 2, (0,))], origin="test")
    for t, a in enumerate(np.linspace(-1.0, 1.0, 6)):
        _step(pool, a, t)
    assert pool.n_now(entry) == 3 and pool.monitor.count[entry.row] == 5


def test_unobserved_pairs_are_not_evaluated():
    """With only one part seen no model is tested or trained."""
    pool = _pool()
    (entry,) = pool.add_learning([(1, 2, (0,))], origin="test")
    ids, alarm = pool.train_learning(np.array([0.1]), pool.pairs.observe({2: np.eye(4)}), 0)
    assert ids.size == 0 and alarm.size == 0 and pool.n_now(entry) == 0


def test_frozen_models_are_tested_and_only_tree_models_run_a_cusum():
    """Tree and memory models both record errors; only the tree model's CUSUM rises and alarms."""
    pool = _pool()
    wrong = StaticModel(1, 2).fit(np.zeros((1, 1)), _link(1.5)[None])
    right = StaticModel(2, 1).fit(np.zeros((1, 1)), invert_transform(_link(0.0))[None])
    (tree,) = pool.add_fitted([wrong], TREE, origin="test", last_used=0)
    (memory,) = pool.add_fitted([right], MEMORY, origin="test", last_used=0)
    alarms = []
    for t in range(4):
        ids, alarm = _step(pool, 0.0, t, train=False)
        assert ids == [tree.id, memory.id]
        alarms.append(alarm.tolist())
    assert alarms[-1] == [True, False]
    assert np.all(pool.monitor.cusum[memory.row] == 0.0) and pool.monitor.count[memory.row] == 4
    # The reversed model 2->1 is compared with the inverse observation: it is exact.
    np.testing.assert_allclose(pool.monitor.errors[memory.row, :4], 0.0, atol=1e-7)


def test_materialize_before_a_change_point_keeps_only_earlier_samples():
    """A model frozen with a change point keeps exactly the samples it had learned before that step."""
    pool = _pool()
    (entry,) = pool.add_learning([(1, 2, (0,))], origin="test")
    actions = np.linspace(-1.0, 1.0, 10)
    for t, a in enumerate(actions):
        _step(pool, a, t)
    pool.materialize(entry, before=6)
    assert entry.slot == -1 and pool.batch.n_allocated == 0 and pool.learning().ids.size == 0
    assert isinstance(entry.model, GPModel) and entry.n_train == 6
    np.testing.assert_array_equal(entry.model.X_train_[:, 0], actions[:6])


def test_removing_a_model_frees_its_slot_and_row():
    """remove() releases the batch slot and the monitor row for reuse."""
    pool = _pool()
    entries = pool.add_learning([(1, 2, ()), (1, 2, (0,)), (2, 1, (0,))], origin="test")
    assert pool.n_learning == 3 and [e.id for e in entries] == [0, 1, 2] and pool.next_id == 3
    pool.remove(entries[1])
    assert pool.n_learning == 2 and pool.batch.n_allocated == 2 and int(pool.monitor.in_use.sum()) == 2
    assert list(pool.tracked) == [0, 2] and pool.learning().ids.tolist() == [0, 2]


def test_refining_tree_models_freeze_at_refine_window():
    """A learning tree model drops its snapshot after each new sample and freezes at refine_window samples."""
    config = BodySchemeConfig(train_window=3, refine_window=5)
    pool = _pool(config, capacity=refine_window(config))
    (entry,) = pool.add_learning([(1, 2, (0,))], origin="test")
    pool.assign(entry, TREE, 0)
    changes = []
    for t, a in enumerate(np.linspace(-1.0, 1.0, 7)):
        _step(pool, a, t)
        pool.model_of(entry)
        changes.append(pool.refresh_refining([entry.id]))
    assert changes == [True] * 5 + [False] * 2
    assert entry.slot == -1 and entry.n_train == 5 and entry.model.n_samples == 5


def test_a_frozen_gp_with_few_samples_resumes_refining():
    """resume_refining puts a GP below refine_window back into the batch with its data; others stay frozen."""
    config = BodySchemeConfig(train_window=3, refine_window=5)
    pool = _pool(config, capacity=refine_window(config))
    A = np.linspace(-1.0, 1.0, 3)[:, None]
    few = GPModel(1, 2, (0,)).fit(A, np.stack([_link(a) for a in A[:, 0]]))
    full = GPModel(1, 2, (0,)).fit(np.linspace(-1.0, 1.0, 5)[:, None], np.stack([_link(a) for a in np.linspace(
        -1.0, 1.0, 5)]))
    static = StaticModel(1, 2).fit(np.zeros((1, 1)), np.eye(4)[None])
    entry, done, other = pool.add_fitted([few, full, static], TREE, origin="test", last_used=0)
    assert pool.resume_refining(entry) and not pool.resume_refining(done) and not pool.resume_refining(other)
    assert entry.slot >= 0 and entry.model is None and pool.n_now(entry) == 3 and pool.n_learning == 1
    np.testing.assert_allclose(pool.model_of(entry).predict([[0.4]]), few.predict([[0.4]]), atol=1e-12)
    for t, a in enumerate([0.5, -0.5, 0.1]):
        _step(pool, a, t)
        pool.refresh_refining([entry.id])
    assert entry.slot == -1 and entry.n_train == 5  # learned two more samples, then froze at refine_window


def test_model_of_keeps_a_snapshot_only_when_asked():
    """Snapshots of learning models are cached in the entry with cache=True only; frozen models are returned."""
    pool = _pool()
    (entry,) = pool.add_learning([(1, 2, (0,))], origin="test")
    _step(pool, 0.2, 0)
    first = pool.model_of(entry, cache=False)
    assert entry.model is None and pool.model_of(entry, cache=False) is not first
    cached = pool.model_of(entry)
    assert entry.model is cached and pool.model_of(entry) is cached
    static = StaticModel(1, 2).fit(np.zeros((1, 1)), np.eye(4)[None])
    (frozen,) = pool.add_fitted([static], MEMORY, origin="test", last_used=0)
    assert pool.model_of(frozen, cache=False) is static


def test_nested_pairs_compare_strict_subsets_of_one_pair_and_target():
    """Only action sets strictly contained in another of the same pair and target are paired."""
    models = [TrackedModel(k, p, c, acts, "candidate", k, target=target)
              for k, (p, c, acts, target) in enumerate([(1, 2, (), -1), (1, 2, (0,), -1), (1, 2, (0, 1), -1),
                                                        (1, 2, (1,), 5), (1, 3, (0, 1), -1)])]
    sub, sup = nested_pairs(models)
    assert sorted(zip(sub.tolist(), sup.tolist(), strict=True)) == [(0, 1), (0, 2), (1, 2)]


def test_a_model_clearly_beaten_by_one_with_more_actions_is_dominated():
    """A paired advantage above dominance_margin marks the simpler model; a small one or an invalid model not."""
    config = BodySchemeConfig()
    pool = _pool(config)
    rows = pool.monitor.allocate(3)
    theta = config.theta_trans
    for t in range(5):
        pool.monitor.record(rows, [0.8 * theta, 0.2 * theta, 0.7 * theta], [0.1, 0.1, 0.1], t, n_train=10,
                            cusum=False)
    sub, sup = np.array([0, 2]), np.array([1, 0])
    np.testing.assert_array_equal(pool.dominated(rows, [10, 10, 10], sub, sup), [True, False, False])
    np.testing.assert_array_equal(pool.dominated(rows, [10, 10, 10], sub, sup, valid=[False, True, True]),
                                  [False, False, False])


def test_keep_only_compacts_the_storage_and_the_models_keep_learning():
    """Kept models move to a fresh batch and monitor with their data and test windows; the rest is dropped."""
    pool = _pool()
    dropped, kept = pool.add_learning([(1, 2, ()), (1, 2, (0,))], origin="test")
    for t, a in enumerate(np.linspace(-1.0, 1.0, 5)):
        _step(pool, a, t)
    errors = pool.monitor.errors[kept.row].copy()
    old_model = pool.batch.to_model(kept.slot, 1, 2)
    refining = pool.keep_only([kept])
    assert refining == [kept] and list(pool.tracked) == [kept.id] and dropped.id not in pool.tracked
    assert pool.batch.n_allocated == 1 and pool.batch.capacity == pool.refine_window
    assert pool.monitor.capacity == 1 and kept.n_train == 5
    np.testing.assert_array_equal(pool.monitor.errors[kept.row], errors)
    np.testing.assert_allclose(pool.batch.predict([kept.slot], np.array([0.4]))[0], old_model.predict([[0.4]])[0],
                               atol=1e-12)


def test_state_round_trip():
    """tracked_state and from_state give the same models, rows and slots; unknown parts are refused."""
    pool = _pool()
    pool.add_learning([(1, 2, (0,))], origin="test")
    pool.add_fitted([StaticModel(2, 1).fit(np.zeros((1, 1)), np.eye(4)[None])], MEMORY, origin="test", last_used=3)
    _step(pool, 0.2, 0)
    state = json.loads(json.dumps([pool.tracked_state(), pool.monitor.to_dict(), pool.batch.state_dict()]))
    restored = ModelPool.from_state(pool.config, 1, pool.pairs, state[0], pool.next_id, state[1], state[2])
    assert restored.tracked_state() == pool.tracked_state() and restored.next_id == 2
    state[0][1]["child"] = 7
    with pytest.raises(ModelFileError, match="unknown part 7"):
        ModelPool.from_state(pool.config, 1, pool.pairs, state[0], pool.next_id, state[1], state[2])


def test_error_text():
    """Errors read as mm and degrees, and as n/a when unknown."""
    assert format_errors(0.078, np.radians(12.3)) == "78 mm / 12.3 deg"
    assert format_errors(np.inf, 0.1) == "n/a"
