"""Tests of the validity monitor: thresholds, test windows, validity, the CUSUM change detector and its state."""

import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.validity import RATIO_CLIP, ValidityMonitor

THETA_T, THETA_R = 0.15, math.radians(45.0)


def _monitor(window=5, **kwargs):
    return ValidityMonitor(window, 0, THETA_T, THETA_R, **kwargs)


def test_window_keeps_only_the_last_samples():
    """The ring buffer averages exactly the last `window` samples, with their steps."""
    mon = _monitor(window=5)
    rows = mon.allocate(2)
    for step in range(8):
        mon.record(rows, [0.01 * step, 0.02 * step], [0.0, 0.0], step)
    st = mon.stats(rows)
    np.testing.assert_array_equal(st.n, [5, 5])
    np.testing.assert_allclose(st.trans_error, [0.01 * 5, 0.02 * 5])  # mean of steps 3..7
    assert sorted(mon.steps[rows[0]].tolist()) == [3, 4, 5, 6, 7]
    assert mon.first_step(rows).tolist() == [3, 3]


def test_validity_needs_samples_and_both_thresholds():
    """Valid iff enough samples and both mean error ratios below 1."""
    mon = _monitor(window=5)
    rows = mon.allocate(3)
    mon.record(rows, [0.1, 0.2, 0.1], [0.1, 0.1, 1.0], 0)
    mon.record(rows, [0.1, 0.2, 0.1], [0.1, 0.1, 1.0], 1)
    assert mon.valid(mon.stats(rows), 3).tolist() == [False, False, False]
    mon.record(rows, [0.1, 0.2, 0.1], [0.1, 0.1, 1.0], 2)
    assert mon.valid(mon.stats(rows), 3).tolist() == [True, False, False]


def test_per_sample_thresholds_enter_the_ratios():
    """A 0.2 m error is invalid at theta 0.15 m but valid at the larger threshold of a distant pair."""
    mon = _monitor(window=3)
    rows = mon.allocate(2)
    for step in range(3):
        mon.record(rows, [0.2, 0.2], [0.0, 0.0], step, theta_trans=[0.15, 0.4])
    st = mon.stats(rows)
    np.testing.assert_allclose(st.trans_ratio, [0.2 / 0.15, 0.5])
    np.testing.assert_allclose(st.theta_trans, [0.15, 0.4])
    assert mon.valid(st, 3).tolist() == [False, True]


def test_stale_predictions_of_a_learning_model_are_ignored():
    """Errors made with fewer than half of the current training samples do not count."""
    mon = _monitor(window=10)
    (row,) = mon.allocate(1)
    for n in range(1, 9):  # predictions by a model with n training samples: bad early, good later
        mon.record([row], [1.0 if n < 6 else 0.01], [0.0], n, n_train=n)
    assert not mon.valid(mon.stats([row]), 3)[0]  # 5 of 8 far off (clipped at 2 thresholds each)
    st = mon.stats([row], n_train=[8], stale_fraction=0.5)
    assert st.n[0] == 5  # predictions made with 4..8 samples: 2 bad, 3 good
    assert mon.valid(st, 3)[0]


def test_one_outlier_cannot_invalidate_a_window():
    """Per-sample ratios are clipped at RATIO_CLIP: one wild error moves a window mean by at most clip/window."""
    mon = _monitor(window=10)
    (row,) = mon.allocate(1)
    for step in range(10):
        mon.record([row], [0.05 if step != 4 else 100.0], [0.1], step)
    st = mon.stats([row])
    assert mon.valid(st, 3)[0]
    assert st.trans_ratio[0] == pytest.approx((9 * 0.05 / 0.15 + RATIO_CLIP) / 10)


def test_stats_since_a_change_point():
    """`since` restricts the statistics to samples observed at or after a step."""
    mon = _monitor(window=10)
    (row,) = mon.allocate(1)
    for step in range(6):
        mon.record([row], [0.5 if step < 3 else 0.05], [0.0], step)
    st = mon.stats([row], since=3)
    assert st.n[0] == 3
    assert st.trans_error[0] == pytest.approx(0.05)


def test_cusum_alarms_after_a_shift_and_estimates_the_change_point():
    """Errors within half the threshold keep the CUSUM low; errors of twice the threshold (six noise sigmas) alarm at
    the third sample, and the change point is the first of them."""
    mon = _monitor(window=15)
    (row,) = mon.allocate(1)
    rng = np.random.default_rng(0)
    for step in range(100):
        alarm = mon.record([row], [rng.uniform(0, 0.5) * THETA_T], [rng.uniform(0, 0.5) * THETA_R], step)
        assert not alarm[0]
    mon.reset_cusum([row])
    alarms = [mon.record([row], [2.0 * THETA_T], [0.1], step)[0] for step in range(100, 104)]
    assert alarms == [False, False, True, True]
    assert mon.change_point([row])[0] == 100


def _gaussian_errors(rng, n, sigma, shift=0.0):
    """Norms of 3D errors with RMS ``sigma`` (isotropic), shifted by ``shift`` along one axis."""
    e = rng.normal(scale=sigma / math.sqrt(3.0), size=(n, 3))
    e[:, 0] += shift
    return np.linalg.norm(e, axis=1)


def test_cusum_is_quiet_on_noise_and_finds_a_shift_of_one_sigma():
    """On Gaussian noise of the thresholds' sigma the CUSUM does not alarm in 20,000 samples; a lasting shift of
    1.33 sigma (a 20 deg bend at 15 deg of noise) alarms within 25 samples, a shift of 3 sigma within 5."""
    rng = np.random.default_rng(0)
    sigma_t, sigma_r = THETA_T / 3.0, THETA_R / 3.0
    mon = _monitor(window=15)
    (row,) = mon.allocate(1)
    quiet = [mon.record([row], [et], [er], step)[0]
             for step, (et, er) in enumerate(zip(_gaussian_errors(rng, 20000, sigma_t),
                                                 _gaussian_errors(rng, 20000, sigma_r), strict=True))]
    assert not any(quiet)
    for shift, within in ((1.33, 25), (3.0, 5)):
        mon.reset_cusum([row])
        errors = _gaussian_errors(rng, within, sigma_r, shift * sigma_r)
        alarms = [mon.record([row], [0.0], [er], 30000 + k)[0] for k, er in enumerate(errors)]
        assert any(alarms)


def test_cusum_needs_more_than_one_outlier():
    """A single huge error is clipped: it raises the statistic by at most clip - drift."""
    mon = _monitor(window=15)
    (row,) = mon.allocate(1)
    assert not mon.record([row], [100.0], [3.0], 0)[0]
    np.testing.assert_allclose(mon.cusum[row], [6.0 - 1.5, 6.0 - 1.5])
    mon.reset_cusum([row])
    assert np.all(mon.cusum[row] == 0.0)


def test_paired_difference_matches_samples_by_step():
    """Rows created at different times are compared on their common steps only."""
    mon = _monitor(window=4)
    a, b = mon.allocate(2)
    for step in range(6):
        mon.record([a], [0.3], [0.0], step)
        if step >= 3:
            mon.record([b], [0.15], [0.0], step)
    n, diff = mon.paired_difference([a], [b])
    assert n[0] == 3
    np.testing.assert_allclose(diff[0], [(0.3 - 0.15) / THETA_T, 0.0])
    n, _ = mon.paired_difference([a], [b], since=5)
    assert n[0] == 1


def test_forget_before_drops_old_samples():
    """Samples from before a change point can be dropped from a window."""
    mon = _monitor(window=5)
    (row,) = mon.allocate(1)
    for step in range(5):
        mon.record([row], [0.5], [0.0], step)
    mon.forget_before([row], 3)
    assert mon.stats([row]).n[0] == 2


def test_rows_are_reused_and_grow():
    """Released rows are reused; allocation grows the arrays when needed."""
    mon = _monitor(window=3)
    rows = mon.allocate(3)
    mon.record(rows, [0.1] * 3, [0.1] * 3, 0)
    mon.release(rows[1:2])
    again = mon.allocate(2)
    assert again[0] == rows[1]
    assert mon.stats(again).n.tolist() == [0, 0]
    assert mon.capacity >= 4


def test_zero_length_windows_are_rejected():
    """test_window = 0 is refused by the config and by the monitor."""
    with pytest.raises(InvalidInputError, match="test_window"):
        BodySchemeConfig(test_window=0)
    with pytest.raises(InvalidInputError, match="window"):
        ValidityMonitor(0)
    with pytest.raises(InvalidInputError):
        BodySchemeConfig(cusum_drift=2.0, cusum_clip=1.5)


def test_monitor_from_config_takes_window_thresholds_and_cusum_settings():
    """The monitor built for a learner has the configuration's test window, thresholds and CUSUM settings."""
    config = BodySchemeConfig(sigma_trans=0.02, sigma_rot=0.1, test_window=7, cusum_drift=0.5, cusum_threshold=2.0)
    mon = ValidityMonitor.from_config(config)
    assert mon.window == 7 and mon.capacity == 0
    np.testing.assert_allclose(mon.theta, [3 * 0.02, 3 * 0.1])  # validity_sigmas times the noise prior
    assert (mon.cusum_drift, mon.cusum_threshold, mon.cusum_clip) == (0.5, 2.0, config.cusum_clip)
