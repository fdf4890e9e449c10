"""Tests of body_scheme_core.levenberg_marquardt: the damped step, alone and stacked, and the damping's schedule."""

import numpy as np
from numpy.testing import assert_allclose

from body_scheme_core.levenberg_marquardt import damped_increment, next_damping


def _problems(k, p, seed=0):
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(k, 3 * p, p))
    return np.swapaxes(J, 1, 2) @ J, rng.normal(size=(k, p))


def test_the_undamped_step_is_gauss_newtons_and_damping_shortens_it_towards_the_scaled_gradient():
    info, g = _problems(1, 4)
    info, g = info[0], g[0]
    assert_allclose(damped_increment(info, g, 0.0, 0.0), -np.linalg.solve(info, g), rtol=1e-12)
    steps = [np.linalg.norm(damped_increment(info, g, d, 0.0)) for d in (0.0, 1e-2, 1.0, 1e2)]
    assert all(a > b for a, b in zip(steps, steps[1:], strict=False))
    heavy = damped_increment(info, g, 1e8, 0.0)
    assert_allclose(heavy * 1e8, -g / np.diag(info), rtol=1e-6)  # Marquardt: the gradient scaled by the diagonal


def test_a_stack_of_problems_takes_each_problems_own_step_with_its_own_damping():
    info, g = _problems(3, 5, seed=1)
    damping = np.array([1e-3, 1.0, 30.0])
    stacked = damped_increment(info, g, damping, 1e-9)
    for k in range(3):
        assert_allclose(stacked[k], damped_increment(info[k], g[k], float(damping[k]), 1e-9), rtol=1e-12)


def test_the_damping_falls_to_a_third_after_a_better_step_not_below_its_minimum_and_rises_tenfold_after_a_worse():
    damping = np.array([3e-3, 1e-9, 1e-3])
    assert_allclose(next_damping(np.array([True, True, False]), damping, 1e-8), [1e-3, 1e-8, 1e-2])
    assert abs(float(next_damping(True, 0.3, 1e-9)) - 0.1) < 1e-15 and float(next_damping(False, 0.3, 1e-9)) == 3.0
