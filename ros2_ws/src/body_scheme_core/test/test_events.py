"""Tests of the event helpers: error text and JSON-safe error fields."""

import numpy as np

from body_scheme_core.events import finite_or_none, format_errors


def test_error_text():
    """Errors read as mm and degrees, and as n/a when unknown."""
    assert format_errors(0.078, np.radians(12.3)) == "78 mm / 12.3 deg"
    assert format_errors(np.inf, 0.1) == "n/a"


def test_event_error_fields_are_floats_or_none():
    """Finite errors stay floats; inf and NaN become None, so that events stay JSON-safe."""
    assert finite_or_none(np.float64(0.25)) == 0.25 and type(finite_or_none(np.float64(0.25))) is float
    assert finite_or_none(np.inf) is None and finite_or_none(np.nan) is None
