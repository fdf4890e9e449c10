"""The strict readers of state-file values: what ``int()`` and ``float()`` would let through is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from body_scheme_core.errors import ModelFileError
from body_scheme_core.limits import MAX_INTEGER
from body_scheme_core.state_values import finite_array, integer, integer_array, number, optional_number, part_id


@pytest.mark.parametrize("value", [True, 1.0, "5", None, -1, MAX_INTEGER + 1, pytest.param(10**5000, id="5001_digits")])
def test_integer_refuses_what_int_would_accept(value):
    with pytest.raises(ModelFileError, match="step must be an integer"):
        integer(value, "step")


def test_integer_takes_its_bounds():
    assert integer(0, "n") == 0 and integer(MAX_INTEGER, "n") == MAX_INTEGER
    assert integer(-1, "slot", minimum=-1) == -1
    with pytest.raises(ModelFileError, match=r"in \[0, 3\]"):
        integer(4, "n", maximum=3)


@pytest.mark.parametrize("value", [True, "inf", "1.5", None, math.inf, math.nan, [1.0]])
def test_number_refuses_non_numbers_and_non_finite(value):
    with pytest.raises(ModelFileError, match="rms must be a finite number"):
        number(value, "rms")


def test_number_bounds_and_optional():
    assert number(2, "x") == 2.0 and isinstance(number(2, "x"), float)
    with pytest.raises(ModelFileError):
        number(0.0, "std", above=0.0)
    with pytest.raises(ModelFileError):
        number(101.0, "v", maximum=100.0)
    assert math.isnan(optional_number(None, "F"))


def test_part_id_is_one_of_the_parts():
    assert part_id(2, {1, 2}, "root") == 2
    for value in (3, True, 2.0, "2"):
        with pytest.raises(ModelFileError, match="unknown part"):
            part_id(value, {1, 2}, "root")


def test_arrays_refuse_strings_booleans_ragged_and_overflow():
    assert finite_array([[1, 2.5]], (1, 2), "a").dtype == float
    assert finite_array([], (0, 12), "Z").shape == (0, 12)
    for bad in (["1", "2"], [True, False], [[1.0], [1.0, 2.0]], [1.0, math.inf], [1.0, None]):
        with pytest.raises(ModelFileError):
            finite_array(bad, (2,), "a")
    assert integer_array([[0, -1]], (1, 2), "steps", -1).dtype == np.int64
    for bad in ([0.5, 1], [2**64, 0], [-2, 0]):
        with pytest.raises(ModelFileError):
            integer_array(bad, (2,), "steps", -1)
