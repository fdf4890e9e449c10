"""Tests of the robot zoo experiment: its protocol's pieces, a quick run and the summary of its figures."""

import math

import pytest

from body_scheme_apps.experiments import zoo

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


def test_an_unknown_noise_level_is_refused():
    with pytest.raises(ValueError, match="noise levels"):
        zoo.run(0, "noise")


def test_the_quick_robot_is_small_and_the_full_one_is_not_cut():
    """Quick runs cut a body to QUICK_MAX_JOINTS joints (plus up to two dummy actions); full runs take the seed's."""
    sizes = [zoo._robot(seed, quick=False).n_actions for seed in range(12)]
    assert max(sizes) > zoo.QUICK_MAX_JOINTS + 2
    assert all(zoo._robot(seed, quick=True).n_actions <= zoo.QUICK_MAX_JOINTS + 2 for seed in range(12))


def test_a_quick_run_reports_its_judgements():
    """One quick run at the camera's noise: no exception, a snapshot after the healthy steps and at the end."""
    result = zoo.run(1, "camera", quick=True)
    assert result["exceptions"] == 0 and result["variant"] == "camera"
    assert result["healthy_steps"] == zoo.QUICK_HEALTHY
    for phase in ("healthy", "end"):
        assert isinstance(result[f"{phase}_true_tree"], bool) and isinstance(result[f"{phase}_trusted"], bool)
        assert math.isfinite(result[f"{phase}_pred_err_over_noise"])
    assert result["healthy_noise_rel_err"] >= 0.0
    assert result["detected_at"] is None or 1 <= result["detected_at"] <= zoo.QUICK_CHANGED


def _run(variant, true=True, trusted=True, end_true=True, end_trusted=True, detected_at=3, false_alarms=0):
    return {"variant": variant, "exceptions": 0, "healthy_true_tree": true, "healthy_trusted": trusted,
            "end_true_tree": end_true, "end_trusted": end_trusted, "false_alarms": false_alarms,
            "healthy_steps": 400, "healthy_pred_err_over_noise": 0.2, "end_pred_err_over_noise": 0.5,
            "detected_at": detected_at, "healthy_noise_rel_err": 0.1, "fault_kind": "block_joint"}


def test_the_summary_counts_silent_wrong_trees_false_alarms_and_detections():
    runs = [_run("camera"), _run("camera", true=False, trusted=True),           # wrong and trusted: silent
            _run("paper", end_true=False, end_trusted=False, detected_at=None),  # wrong at the end, but flagged
            _run("paper", false_alarms=2), _run("harsh", detected_at=None)]
    summary = zoo.summarize(runs)
    assert summary["zoo_silent_wrong_trees"] == 1.0
    assert summary["zoo_true_tree_fraction_camera"] == 0.5
    assert summary["zoo_false_alarms_per_1000_steps_paper"] == pytest.approx(1000.0 * 2 / 800)
    assert summary["zoo_fault_detected_fraction"] == pytest.approx(3 / 4)
    assert summary["zoo_fault_detection_steps_median"] == 3.0
    assert summary["zoo_fault_detected_fraction_harsh"] == 0.0
    assert "zoo_true_tree_fraction_realcam" not in summary  # a level without runs has no figures, not NaN


def test_the_summary_of_runs_without_any_detection_is_nan_not_an_error():
    summary = zoo.summarize([_run("camera", detected_at=None)])
    assert summary["zoo_fault_detected_fraction"] == 0.0
    assert math.isnan(summary["zoo_fault_detection_steps_median"])


def test_the_plot_writes_every_runs_fields_beside_it(tmp_path):
    """``zoo_runs.json`` lists each run's :data:`zoo.RUN_FIELDS` (which seeds and levels went wrong), sorted."""
    import json

    runs = [{**_run(level), "seed": seed, "n_actions": 3, "n_markers": 4, "repairs": 0, "cpu_seconds": 1.0}
            for seed in (1, 0) for level in ("paper", "camera")]
    assert zoo.plot(runs, tmp_path / "zoo")
    table = json.loads((tmp_path / "zoo_runs.json").read_text())
    assert [(r["seed"], r["variant"]) for r in table] == [(0, "camera"), (0, "paper"), (1, "camera"), (1, "paper")]
    assert all(set(r) == set(zoo.RUN_FIELDS) for r in table)
