"""Strict readers of the values in a saved learner state: each returns the value or raises ``ModelFileError``.

A state file is untrusted input (docs/core/state-file-format.md). Python's ``int()`` and ``float()`` accept far more
than a state file may hold (``True``, ``"inf"``, ``"5"``, ``1e308`` as a count, integers of thousands of digits), and a
value they let through fails steps later, far from the file. These readers are the one place where a JSON value
becomes a count, a step, an id, a number or an array, with the bounds a learner can reach.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ModelFileError
from .limits import MAX_INTEGER

__all__ = ["integer", "number", "optional_number", "boolean", "listing", "mapping", "part_id",
           "finite_array", "integer_array", "covariance"]



def integer(value, name, minimum=0, maximum=MAX_INTEGER):
    """A JSON integer in ``[minimum, maximum]`` (booleans, floats and strings refused)."""
    if isinstance(value, bool) or not isinstance(value, int) or not minimum <= value <= maximum:
        raise ModelFileError(f"{name} must be an integer in [{minimum}, {maximum}], got {_short(value)}")
    return value


def number(value, name, minimum=-math.inf, maximum=math.inf, above=None):
    """A finite JSON number in ``[minimum, maximum]`` (and ``> above`` if given), as a float; booleans and strings
    such as ``"inf"`` refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not (
            minimum <= value <= maximum) or (above is not None and not value > above):
        low = f"> {above}" if above is not None else f">= {minimum}"
        raise ModelFileError(f"{name} must be a finite number {low} and <= {maximum}, got {_short(value)}")
    return float(value)


def optional_number(value, name, **bounds):
    """``None`` as NaN (a statistic that was not computed), else :func:`number`."""
    return math.nan if value is None else number(value, name, **bounds)


def boolean(value, name):
    if not isinstance(value, bool):
        raise ModelFileError(f"{name} must be true or false, got {_short(value)}")
    return value


def listing(value, name, length=None):
    """A JSON list (of ``length`` items if given)."""
    if not isinstance(value, list):
        raise ModelFileError(f"{name} must be a list, got {type(value).__name__}")
    if length is not None and len(value) != length:
        raise ModelFileError(f"{name} must have {length} items, got {len(value)}")
    return value


def mapping(value, name):
    if not isinstance(value, dict):
        raise ModelFileError(f"{name} must be an object, got {type(value).__name__}")
    return value


def part_id(value, part_ids, name):
    """One of ``part_ids``."""
    if isinstance(value, bool) or not isinstance(value, int) or value not in part_ids:
        raise ModelFileError(f"{name} refers to unknown part {_short(value)}")
    return value


def finite_array(value, shape, name):
    """A float array of ``shape`` with finite entries (nested lists of JSON numbers only)."""
    arr = _array(value, name, float, shape)
    if arr.shape != tuple(shape):
        raise ModelFileError(f"{name} must have shape {tuple(shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ModelFileError(f"{name} contains NaN or inf")
    return arr


def covariance(value, size, name):
    """A ``(size, size)`` covariance: finite, symmetric and positive semi-definite, each up to rounding."""
    cov = finite_array(value, (size, size), name)
    scale = max(1.0, float(np.abs(cov).max(initial=0.0)))
    if not np.allclose(cov, cov.T, rtol=0.0, atol=1e-9 * scale):
        raise ModelFileError(f"{name} is not symmetric")
    if size and np.linalg.eigvalsh(0.5 * (cov + cov.T))[0] < -1e-9 * scale:
        raise ModelFileError(f"{name} is not positive semi-definite")
    return cov


def integer_array(value, shape, name, minimum, maximum=MAX_INTEGER):
    """An int64 array of ``shape`` with entries in ``[minimum, maximum]`` (JSON integers only)."""
    arr = _array(value, name, np.int64, shape)
    if arr.shape != tuple(shape):
        raise ModelFileError(f"{name} must have shape {tuple(shape)}, got {arr.shape}")
    if arr.size and not (arr.min() >= minimum and arr.max() <= maximum):
        raise ModelFileError(f"{name} must hold integers in [{minimum}, {maximum}]")
    return arr


def _array(value, name, dtype, shape):
    """``value`` as an array of ``dtype``, refusing what numpy would convert but JSON does not mean as a number
    (strings, booleans, nulls) and ragged lists; an empty list is an empty array of ``shape``."""
    try:
        arr = np.asarray(value)
    except ValueError as exc:  # ragged
        raise ModelFileError(f"{name} is not a regular array: {exc}") from exc
    if arr.size == 0 and math.prod(shape) == 0:
        return np.zeros(shape, dtype=dtype)
    if arr.size and not (np.issubdtype(arr.dtype, np.integer) or (dtype is float and arr.dtype == np.float64)):
        raise ModelFileError(f"{name} must hold {'numbers' if dtype is float else 'integers'}, got {arr.dtype} values")
    try:
        return arr.astype(dtype)
    except OverflowError as exc:
        raise ModelFileError(f"{name} holds an integer out of range") from exc


def _short(value):
    """``repr`` of a value, cut short (a mutated file may hold a 5,000-digit integer)."""
    big = isinstance(value, int) and abs(value) >= 10**30
    text = f"an integer of {value.bit_length()} bits" if big else repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
