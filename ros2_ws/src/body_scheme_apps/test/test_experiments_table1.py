"""Tests of the Table I experiment (recovery after a blocked joint and a deformed limb)."""

import math

import numpy as np
import pytest

from body_scheme_apps.experiments import table1
from body_scheme_core.events import Event

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


def test_recovery_counts_samples_up_to_the_adapting_one_and_the_whole_block_without_one():
    """s - t0 + 1 per block from the first replaced/reinstated event on the end-effector edge; other edges ignored."""
    events = [Event(104, "mismatch_detected", "", 6, 7), Event(107, "model_replaced", "", 6, 7),
              Event(201, "model_replaced", "", 2, 3),  # another edge: not the end effector's
              Event(202, "model_reinstated", "", 6, 7), Event(250, "model_reinstated", "", 6, 7)]
    assert table1.recovery_times(events, [100, 200, 300], 400, effector=7) == [(8.0, True), (3.0, True),
                                                                               (100.0, False)]


def test_blocked_joint_run_recovers_in_every_block_and_predicts_well_after():
    """Seed 0, noise model: adaptation in all three changed blocks, and after recovery the end-effector error is well
    below the error of the first samples after the change."""
    result = table1.run_protocol("joint_blocked", 0)
    assert result["blocked_not_recovered"] == 0.0
    for key in ("blocked_recovery_failure", "blocked_recovery_repair", "blocked_recovery_same"):
        assert 1.0 <= result[key] <= 20.0
    errors = np.array(result["curves"]["blocked_ee_err_mm"])
    assert errors.shape == (400,) and np.all(np.isfinite(errors))
    right_after_change = errors[100:104].mean()
    assert result["blocked_ee_err_mm_after"] < 0.5 * right_after_change
    assert result["curves"]["blocked_changes"] == [100, 200, 300]
    assert math.isclose(result["curves"]["blocked_visibility"], 0.919, abs_tol=0.03)


def test_run_has_every_documented_figure_and_plot_writes_one_png_per_protocol(tmp_path):
    """run() returns finite values for every FIGURES key; plot() writes the Fig. 6 PNGs."""
    result = table1.run(1, quick=True)
    assert set(table1.FIGURES) <= set(result)
    assert all(math.isfinite(result[key]) for key in table1.FIGURES)
    assert set(table1.TARGETS) <= set(table1.FIGURES) and set(table1.PAPER) <= set(table1.FIGURES)
    paths = table1.plot([result], tmp_path / "table1")
    assert [p.name for p in paths] == ["table1_blocked.png", "table1_deformed.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
