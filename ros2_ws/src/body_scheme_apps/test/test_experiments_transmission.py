"""Tests of the nonlinear-transmission experiment: a quick run."""

import math

import pytest

from body_scheme_apps.experiments import transmission

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


def test_a_quick_run_finds_the_gp_edge_and_beats_the_rigid_only_learner():
    """A quick run returns the FIGURES keys, finite; the elbow is a GP, and rigid models alone predict far worse."""
    result = transmission.run(0, quick=True)
    assert set(transmission.FIGURES) <= set(result)
    assert all(math.isfinite(result[key]) for key in transmission.FIGURES)
    assert result["transmission_gp_edge_fraction"] == 1.0
    assert result["transmission_ee_err_mm_rigid_only"] > 2 * result["transmission_ee_err_mm"]


def test_only_the_noise_model_is_run():
    with pytest.raises(ValueError, match="noise model only"):
        transmission.run(0, perception="rendered")
