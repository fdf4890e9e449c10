"""The core demo (core_demo.py) end to end."""

from __future__ import annotations

import pytest

from body_scheme_apps import core_demo


@pytest.mark.slow  # 270 learning steps end to end
def test_core_demo_runs_end_to_end(capsys):
    """core_demo bootstraps, detects the blocked joint, repairs and reinstates (short run)."""
    assert core_demo.main(["--steps", "270", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    assert "Structure recovered exactly: yes" in out
    assert "mismatch_detected" in out and "model_replaced" in out and out.count("model_reinstated") >= 2
