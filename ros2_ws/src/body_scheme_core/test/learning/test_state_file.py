"""Tests of the saved state's pieces (state_file.py): the pool and its validity monitors as JSON and back."""

import json
import math

import numpy as np
import pytest

from body_scheme_core.calibration.noise_model import NoiseModel
from body_scheme_core.errors import ModelFileError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.pool import ModelPool
from body_scheme_core.learning.relative import PartPairs
from body_scheme_core.learning.state_file import monitor_from_dict, monitor_to_dict, pool_from_dict
from body_scheme_core.learning.tracked import MEMORY
from body_scheme_core.learning.validity import ValidityMonitor
from body_scheme_core.models import StaticModel
from body_scheme_core.transforms import transform_from_rotvec

CONFIG = BodySchemeConfig()
PAIRS = PartPairs((1, 2), NoiseModel.from_config((1, 2), CONFIG))


def _monitor(window=5):
    return ValidityMonitor(window, 0, 0.15, math.radians(45.0))


def _train(pool, a, step):
    """Train the pool's learning models on pair 1->2 at action ``a`` (a one-joint link: yaw ``a``, 0.3 m along x)."""
    ls = pool.learning()
    Z = transform_from_rotvec([0.0, 0.0, a], [0.3 * np.cos(a), 0.3 * np.sin(a), 0.0])
    relative = PAIRS.observe({1: np.eye(4), 2: Z})
    pool.train(ls.ids, np.array([a]), relative.targets(np.zeros(ls.ids.size, dtype=int)), step)


def test_state_round_trip():
    """A pool's saved parts give the same models, rows and slots (pool_from_dict); unknown parts are refused."""
    pool = ModelPool(CONFIG, 1)
    pool.add_learning([(1, 2, (0,), "gp"), (1, 2, (0,), "revolute")], origin="test")
    pool.add_fitted([StaticModel(2, 1).fit(np.zeros((1, 1)), np.eye(4)[None])], MEMORY, origin="test", last_used=3)
    for t, a in enumerate([0.2, -0.4, 0.7]):
        _train(pool, a, t)
    state = json.loads(json.dumps([pool.tracked_state(), monitor_to_dict(pool.monitor), pool.gp_batch.state_dict(),
                                   pool.rigid_batch.state_dict()]))
    restored = pool_from_dict(CONFIG, 1, {1, 2}, state[0], pool.next_id, *state[1:])
    assert restored.tracked_state() == pool.tracked_state() and restored.next_id == 3
    state[0][2]["child"] = 7
    with pytest.raises(ModelFileError, match="unknown part 7"):
        pool_from_dict(CONFIG, 1, {1, 2}, state[0], pool.next_id, *state[1:])


def test_monitor_round_trip_through_json():
    """monitor_to_dict -> JSON -> monitor_from_dict reproduces every array exactly."""
    rng = np.random.default_rng(0)
    mon = _monitor(window=4)
    rows = mon.allocate(3)
    for step in range(7):
        mon.record(rows, rng.uniform(0, 0.3, 3), rng.uniform(0, 1, 3), step, n_train=step,
                   theta_trans=rng.uniform(0.15, 0.3, 3))
    back = monitor_from_dict(json.loads(json.dumps(monitor_to_dict(mon))))
    for name in ValidityMonitor.ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(mon, name))
    np.testing.assert_array_equal(back.stats(rows).trans_error, mon.stats(rows).trans_error)


def test_monitor_from_dict_rejects_bad_content():
    """Wrong shapes and NaN are ModelFileErrors."""
    mon = _monitor(window=4)
    mon.record(mon.allocate(2), [0.1, 0.1], [0.1, 0.1], 0)
    data = monitor_to_dict(mon)
    bad = dict(data, errors=[[[0.0, 0.0]] * 3] * 2)
    with pytest.raises(ModelFileError, match="shape"):
        monitor_from_dict(bad)
    bad = json.loads(json.dumps(data))
    bad["cusum"][0][0] = float("nan")
    with pytest.raises(ModelFileError, match="NaN"):
        monitor_from_dict(bad)
    with pytest.raises(ModelFileError):
        monitor_from_dict({"window": 4})
