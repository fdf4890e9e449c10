"""Tests of the learner's input validation: constructor arguments, actions, stamps and observations."""

import math

import numpy as np
import pytest

from body_scheme_core.errors import ActionOutOfRangeError, InvalidInputError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.inputs import (
    MAX_ACTION,
    OBSERVATION_TOLERANCE,
    check_action_bounds,
    check_action_vector,
    check_config,
    check_initial_models,
    check_n_actions,
    check_observation_mapping,
    check_part_ids,
    check_stamp,
    filter_observations,
    root_part,
)
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import planar_2dof

PARTS = (1, 2, 3)


def _pose(rng):
    return transform_from_rotvec(rng.normal(size=3), rng.normal(size=3))


def test_check_actions_accepts_one_finite_vector():
    """A finite vector of length m passes as floats; other lengths, stacks and NaN or inf are refused."""
    np.testing.assert_array_equal(check_action_vector([1, 2], 2), [1.0, 2.0])
    for bad in ([0.1, 0.2, 0.3], [[0.1, 0.2]], 0.5):
        with pytest.raises(InvalidInputError, match=r"shape \(2,\)"):
            check_action_vector(bad, 2)
    for bad in ([np.nan, 0.0], [0.0, np.inf]):
        with pytest.raises(InvalidInputError, match="NaN or inf"):
            check_action_vector(bad, 2)


def test_check_stamp_wants_a_finite_number_or_none():
    """None stays None, numbers become floats; NaN, inf and non-numbers are refused."""
    assert check_stamp(None) is None
    assert check_stamp(3) == 3.0 and isinstance(check_stamp(3), float)
    for bad in (float("nan"), float("inf"), "soon", [1.0]):
        with pytest.raises(InvalidInputError, match="stamp"):
            check_stamp(bad)


def test_observations_must_be_a_mapping():
    """A list of poses is refused with a message naming the expected mapping."""
    check_observation_mapping({})
    with pytest.raises(InvalidInputError, match="mapping"):
        check_observation_mapping([np.eye(4)])


def test_valid_observations_are_kept_as_copies():
    """Valid poses are returned in the given order, as copies the caller may change afterwards."""
    rng = np.random.default_rng(0)
    Y3, Y1 = _pose(rng), _pose(rng)
    valid, rejections = filter_observations({3: Y3, np.int64(1): Y1}, PARTS)
    assert rejections == [] and list(valid) == [3, 1] and all(type(p) is int for p in valid)
    Y3[0, 3] += 1.0
    assert valid[3][0, 3] != Y3[0, 3]
    np.testing.assert_array_equal(valid[1], Y1)


def test_each_bad_observation_is_rejected_with_its_reason():
    """Unknown ids, wrong shapes, NaN, scaled and reflected poses are dropped one by one; the good pose stays."""
    rng = np.random.default_rng(1)
    good = _pose(rng)
    nan = _pose(rng)
    nan[0, 3] = np.nan
    scaled = good @ np.diag([1.1, 1.0, 1.0, 1.0])
    reflected = good @ np.diag([-1.0, 1.0, 1.0, 1.0])
    observations = {1: good, 99: good, "x": good, 2: good[:3], 3: nan}
    valid, rejections = filter_observations(observations, PARTS)
    assert list(valid) == [1]
    assert [(r.part, r.reason) for r in rejections] == [(99, "unknown_id"), (None, "unknown_id"),
                                                        (2, "bad_shape"), (3, "not_finite")]
    assert "id 'x' is not an integer" in rejections[1].detail and "(3, 4)" in rejections[2].detail
    valid, rejections = filter_observations({True: good}, PARTS)  # a bool is no id, although True == 1
    assert valid == {} and [(r.part, r.reason) for r in rejections] == [(None, "unknown_id")]
    valid, rejections = filter_observations({2: scaled, 3: reflected, 1: object()}, PARTS)
    assert valid == {}
    assert [(r.part, r.reason) for r in rejections] == [(1, "bad_shape"), (2, "not_rigid"), (3, "not_rigid")]


def test_rigidity_tolerance():
    """A rotation block off by less than the tolerance passes, one off by more is rejected."""
    pose = np.eye(4)
    pose[0, 0] = 1.0 + 0.4 * OBSERVATION_TOLERANCE
    valid, _ = filter_observations({1: pose}, PARTS)
    assert list(valid) == [1]
    pose[0, 0] = 1.0 + 0.6 * OBSERVATION_TOLERANCE  # R^T R deviates by about twice this
    valid, rejections = filter_observations({1: pose}, PARTS)
    assert valid == {} and rejections[0].reason == "not_rigid"
    pose = np.eye(4)
    pose[3, 0] = 2.0 * OBSERVATION_TOLERANCE
    assert filter_observations({1: pose}, PARTS)[1][0].reason == "not_rigid"


def test_constructor_arguments():
    """Part ids must be unique integers, n_actions a non-negative int, the root one of the parts."""
    assert check_part_ids([3, np.int64(1)]) == (3, 1)
    for bad in ([], [1, 1], ["a"], None):
        with pytest.raises(InvalidInputError, match="part_ids"):
            check_part_ids(bad)
    assert check_n_actions(np.int64(2)) == 2
    for bad in (-1, True, 2.0):
        with pytest.raises(InvalidInputError, match="n_actions"):
            check_n_actions(bad)
    assert root_part((5, 3, 9)) == 3 and root_part((5, 3, 9), 9) == 9
    with pytest.raises(InvalidInputError, match="root"):
        root_part((5, 3, 9), 4)
    assert check_config(BodySchemeConfig()) == BodySchemeConfig()
    with pytest.raises(InvalidInputError, match="BodySchemeConfig"):
        check_config({"root": 1})


def test_action_bounds():
    """Limits have shape (m,), no NaN and lower <= upper; infinite limits (continuous joints) are fine."""
    lower, upper = check_action_bounds([-np.inf, -1], [np.inf, 1], 2)
    np.testing.assert_array_equal(upper, [np.inf, 1.0])
    assert check_action_bounds(None, None, 2) == (None, None)
    with pytest.raises(InvalidInputError, match=r"action_upper must have shape \(2,\)"):
        check_action_bounds(None, [1.0], 2)
    with pytest.raises(InvalidInputError, match="action_lower contains NaN"):
        check_action_bounds([np.nan, 0.0], None, 2)
    with pytest.raises(InvalidInputError, match="exceeds"):
        check_action_bounds([0.0, 2.0], [1.0, 1.0], 2)


def test_initial_models_must_be_a_spanning_tree_within_the_actions():
    """The engineered scheme of the 2-DOF robot passes; a partial tree or too few actions are refused."""
    robot = planar_2dof()
    models = engineered_models(robot)
    assert check_initial_models(iter(models), robot.marker_ids, 1, 2) == models
    with pytest.raises(InvalidInputError):
        check_initial_models(models[:1], robot.marker_ids, 1, 2)
    with pytest.raises(InvalidInputError, match="uses action 1 but n_actions is 1"):
        check_initial_models(models, robot.marker_ids, 1, 1)
    assert math.isfinite(OBSERVATION_TOLERANCE)


def test_actions_must_be_real_numbers():
    """Strings, objects and complex numbers are refused with InvalidInputError, not numpy's bare errors or a
    ComplexWarning that drops the imaginary part."""
    for bad in ("abc", ["a", "b"], [1 + 2j, 0.0], [None, 0.0], [[0.1], [0.2, 0.3]]):
        with pytest.raises(InvalidInputError, match="real numbers"):
            check_action_vector(bad, 2)
    np.testing.assert_array_equal(check_action_vector(np.array([1, 0], dtype=np.int8), 2), [1.0, 0.0])


def test_float_and_bool_part_ids_are_refused_not_truncated():
    """1.5 would become part 1 and True part 1: both are refused; numpy integers are ids."""
    assert check_part_ids([np.int64(1), 2]) == (1, 2)
    for bad in ([1.5, 2], [True, 2], ["1", 2], 3):
        with pytest.raises(InvalidInputError, match="integer ids"):
            check_part_ids(bad)


def test_stamps_must_not_go_back_in_time():
    """A stamp before the previous one is refused; an equal one passes (two steps may share a camera frame)."""
    assert check_stamp(2.0, previous=2.0) == 2.0
    with pytest.raises(InvalidInputError, match="before the last step"):
        check_stamp(1.0, previous=2.0)
    for bad in (True, 1 + 0j, "3"):
        with pytest.raises(InvalidInputError, match="stamp"):
            check_stamp(bad)


def test_an_action_no_joint_can_have_is_out_of_range_even_without_limits():
    """1e300 rad (a corrupt command or other units) is refused as out of range, also by a learner without limits."""
    assert check_action_vector([0.0, MAX_ACTION], 2).tolist() == [0.0, MAX_ACTION]
    with pytest.raises(ActionOutOfRangeError, match="units"):
        check_action_vector([0.0, 1e300], 2)
    from body_scheme_core.learning.learner import BodySchemeLearner
    learner = BodySchemeLearner([1, 2], 2)
    with pytest.raises(ActionOutOfRangeError):
        learner.update([-1e300, 0.0], {})
    assert learner.step == 0


def test_bodies_beyond_what_fits_in_memory_are_refused_with_the_reason():
    """200 parts or 300 joints ended in a MemoryError after 4-5 GB before issue 20; now one clear line, at once."""
    from body_scheme_core.learning.config import BodySchemeConfig
    from body_scheme_core.learning.inputs import MAX_CANDIDATES, check_body_size, check_n_actions, check_part_ids

    with pytest.raises(InvalidInputError, match="200 parts"):
        check_part_ids(range(200))
    with pytest.raises(InvalidInputError, match="300 actions"):
        check_n_actions(300)
    with pytest.raises(InvalidInputError, match=f"at most {MAX_CANDIDATES:,}"):
        check_body_size(40, 30, BodySchemeConfig())
    check_body_size(20, 14, BodySchemeConfig())  # 20 markers on a 14-joint dual arm: fine
    check_body_size(40, 30, BodySchemeConfig(max_complexity=1, candidate_kinds=("static", "gp")))  # fewer: fine


@pytest.mark.parametrize("field, value, message", [
    ("train_window", True, r"train_window must be an integer in \[1, 10000\]"),
    ("train_window", 10**9, r"train_window must be an integer in \[1, 10000\]"),  # would allocate the memory
    ("memory_size", -1, "memory_size must be an integer"),
    ("f_scale", True, "f_scale must be a finite number"),
    ("cusum_threshold", 1e308, "cusum_threshold must be a finite number"),
    ("sigma_trans", "inf", '"auto" or a finite number'),
    ("theta_rot", 0.0, "null or a finite number"),
    ("consistency_alpha", 1.0, "consistency_alpha must be below 1"),
    ("cusum_clip", 1.0, "must exceed cusum_drift"),
    ("root", 1.5, "root must be a part id or null"),
])
def test_every_setting_is_bounded_and_typed(field, value, message):
    """Settings come from YAML and state files: booleans are not numbers, and no setting may be large enough to
    allocate the machine's memory or overflow a count."""
    with pytest.raises(InvalidInputError, match=message):
        BodySchemeConfig(**{field: value})
