"""Tests of the Sec. IV-D control experiment: the 4-DOF arm following a trajectory after its upper arm is bent."""

from __future__ import annotations

import math

import numpy as np
import pytest

from body_scheme_apps.experiments import control
from body_scheme_core.events import Event

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


@pytest.fixture(scope="module")
def quick_run():
    """One quick noise-model run (seed 0)."""
    return control.run(0, "noise", quick=True)


def test_paper_and_target_figures_are_defined():
    """Every figure with a paper value or a target has a definition, and the issue's three keys are there."""
    assert {"control_undamaged_mm", "control_static_mm", "control_adaptive_mm"} <= set(control.PAPER)
    assert set(control.PAPER) | set(control.TARGETS) | set(control.SANITY) <= set(control.FIGURES)


def test_trajectory_is_a_closed_tilted_circle_of_30_waypoints():
    """30 distinct waypoints at the radius from the centre, in a plane tilted 30 deg from vertical."""
    waypoints = control.trajectory()
    assert waypoints.shape == (30, 3)
    np.testing.assert_allclose(np.linalg.norm(waypoints - control.CENTER, axis=1), control.RADIUS)
    normal = np.cross(waypoints[1] - waypoints[0], waypoints[2] - waypoints[0])
    tilt = math.degrees(math.acos(abs(normal[0]) / np.linalg.norm(normal)))
    assert tilt == pytest.approx(30.0)
    assert len({tuple(p) for p in np.round(waypoints, 9)}) == 30


def test_run_gives_every_figure_finite_with_the_curves(quick_run):
    """A quick run returns each defined figure as a finite float and the waypoints and reached positions."""
    assert set(control.FIGURES) <= set(quick_run)
    for key in control.FIGURES:
        assert isinstance(quick_run[key], float) and math.isfinite(quick_run[key]), key
    curves = quick_run["curves"]
    assert len(curves["waypoints_mm"]) == 90
    for condition in control.CONDITIONS:
        assert len(curves[f"{condition}_mm"]) == 90 and len(curves[f"{condition}_err_mm"]) == 30
        assert np.mean(curves[f"{condition}_err_mm"]) == pytest.approx(quick_run[f"control_{condition}_mm"])
    np.testing.assert_allclose(np.reshape(curves["waypoints_mm"], (30, 3)), 1e3 * control.trajectory())


def test_bent_arm_is_far_off_with_the_static_scheme_and_adaptation_brings_it_back(quick_run):
    """Exact scheme on the healthy arm: within the IK tolerance; never adapted after the bend: far off; adapted:
    much closer, after the learner replaced the changed edge 3->4."""
    assert quick_run["control_undamaged_mm"] < 1.5
    assert quick_run["control_static_mm"] > 100 * quick_run["control_undamaged_mm"]
    assert quick_run["control_adaptive_mm"] < 0.5 * quick_run["control_static_mm"]
    assert quick_run["control_not_replaced"] == 0.0
    assert 1.0 <= quick_run["control_samples_to_replace"] <= control.QUICK_AFTER
    assert any(e.split()[1] == "model_replaced" and "3->4" in e for e in quick_run["events"])


def test_samples_to_replace_count_from_the_first_bent_sample():
    """The first replacement of edge 3-4 at or after the bend counts s - t0 + 1; other edges and earlier events
    do not count; none gives None."""
    events = [Event(95, "model_replaced", "", parent=3, child=4), Event(101, "model_replaced", "", parent=1, child=2),
              Event(104, "model_reinstated", "", parent=4, child=3),
              Event(110, "model_replaced", "", parent=3, child=4)]
    assert control.samples_to_replace(events, 100) == 5
    assert control.samples_to_replace(events[:2], 100) is None


def test_runs_are_reproducible_from_the_seed(quick_run):
    """The same seed gives the same figures."""
    again = control.run(0, "noise", quick=True)
    assert {k: again[k] for k in control.FIGURES} == {k: quick_run[k] for k in control.FIGURES}


def test_rendered_quick_run_works():
    """Through the simulator's images and the ArUco tracker the three conditions give finite figures."""
    result = control.run(1, "rendered", quick=True)
    assert all(math.isfinite(result[key]) for key in control.FIGURES)
    assert result["control_static_mm"] > 100 * result["control_undamaged_mm"]


def test_unknown_perception_is_refused():
    """A perception mode other than noise or rendered raises ValueError."""
    with pytest.raises(ValueError, match="perception"):
        control.run(0, "lidar", quick=True)


def test_plot_writes_the_trajectory_and_the_error_bars(quick_run, tmp_path):
    """plot() writes two PNG files next to the prefix and returns their paths."""
    paths = control.plot([quick_run, quick_run], tmp_path / "control")
    assert [p.name for p in paths] == ["control_trajectory.png", "control_errors.png"]
    for path in paths:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
