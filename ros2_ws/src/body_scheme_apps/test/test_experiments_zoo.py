"""Tests of the robot zoo experiment: its protocol's pieces, a quick run and the summary of its figures."""

import json
import math

import numpy as np
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
    json.dumps({k: result[k] for k in zoo.RUN_FIELDS})  # plain numbers: zoo_runs.json is written from them


@pytest.mark.heavy(seconds=22)
def test_a_run_with_flips_judges_the_learners_flip_decisions():
    """30 % mirrored orientations: the run counts flips after bootstrapping, and the judged decisions, as ints."""
    result = zoo.run(3, "flips30", quick=True)
    assert result["flips"] > 0 and 0 <= result["flips_used"] <= result["flips"]
    assert all(type(result[k]) is int for k in ("flips", "flips_used", "wrong_flip_corrections",
                                                "false_flip_rejections", "collateral"))



def test_a_mirror_image_learned_while_bootstrapping_is_undone(monkeypatch):
    """Seed 19 at 30 % flips, without mirror hypotheses (the default): a two-marker body whose scheme learns marker
    80's mirror image while bootstrapping (every true pose then looked flipped: 334 were taken in mirrored, no flip of
    it was used). The learner undoes it after one block of observations (learning/mirrors.py)."""
    monkeypatch.setitem(zoo.LEARNER_SETTINGS, "flips30", {})
    result = zoo.run(19, "flips30")
    assert result["healthy_true_tree"] and result["wrong_flip_corrections"] < 100, result
    assert result["flips_used"] >= 0.8 * result["flips"], result


def test_with_mirror_hypotheses_the_mirror_image_is_not_learned_at_all():
    """The same body with ``mirror_hypotheses`` (the flips30 level's setting): no true pose is taken in mirrored and
    every flip after bootstrapping is used."""
    result = zoo.run(19, "flips30")
    assert result["healthy_true_tree"] and result["wrong_flip_corrections"] == 0, result
    assert result["flips_used"] == result["flips"] > 100, result


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
    runs = [{**_run(level), "seed": seed, "n_actions": 3, "n_markers": 4, "repairs": 0, "cpu_seconds": 1.0}
            for seed in (1, 0) for level in ("paper", "camera")]
    assert zoo.plot(runs, tmp_path / "zoo")
    table = json.loads((tmp_path / "zoo_runs.json").read_text())
    assert [(r["seed"], r["variant"]) for r in table] == [(0, "camera"), (0, "paper"), (1, "camera"), (1, "paper")]
    assert all(set(r) == set(zoo.RUN_FIELDS) for r in table)


def _tilted(deg):
    """A marker 2 m in front of the camera, tilted ``deg`` about the camera's x axis."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", deg, degrees=True).as_matrix()
    T[2, 3] = 2.0
    return T


def test_the_flip_tally_judges_each_decision_against_the_truth():
    """A flip taken in corrected is used; a correction or refusal of a true pose is wrong; an observation whose
    mirror image is within the threshold of it (a face-on marker) is neither, whatever the learner does."""
    from body_scheme_core.transforms import mirror_about_ray

    truth = np.stack([_tilted(40.0), _tilted(40.0), _tilted(0.5)])
    flipped = mirror_about_ray(truth[0])
    observed = {1: flipped, 2: truth[1], 3: mirror_about_ray(truth[2])}
    tally = zoo.FlipTally(math.radians(9.0))
    tally.add(truth, [1, 2, 3], observed, {1: truth[0], 2: mirror_about_ray(truth[1]), 3: truth[2]}, set(), True)
    assert tally.counts() == {"flips": 1, "flips_used": 1, "wrong_flip_corrections": 1, "false_flip_rejections": 0}
    tally.add(truth, [1, 2, 3], observed, {}, {1, 2, 3}, True)  # a flip refused (not used), a true pose refused
    assert tally.counts() == {"flips": 2, "flips_used": 1, "wrong_flip_corrections": 1, "false_flip_rejections": 1}
    tally.add(truth, [1, 2, 3], observed, {}, set(), False)  # not counted: bootstrapping or after the change
    assert tally.counts()["flips"] == 2


def test_the_summary_counts_flip_decisions_and_collateral_replacements():
    runs = [{**_run("flips30"), "flips": 10, "flips_used": 9, "wrong_flip_corrections": 1, "false_flip_rejections": 0,
             "collateral": 0},
            {**_run("paper"), "fault_kind": "move_marker", "flips": 0, "flips_used": 0, "wrong_flip_corrections": 0,
             "false_flip_rejections": 2, "collateral": 3},
            {**_run("harsh"), "fault_kind": "move_marker", "flips": 0, "flips_used": 0, "wrong_flip_corrections": 0,
             "false_flip_rejections": 0, "collateral": 5}]
    summary = zoo.summarize(runs)
    assert summary["zoo_flips_used_fraction_flips30"] == 0.9
    assert "zoo_flips_used_fraction_realcam" not in summary
    assert summary["zoo_wrong_flip_corrections"] == 1.0 and summary["zoo_false_flip_rejections"] == 2.0
    assert summary["zoo_collateral_replacements"] == 3.0  # harsh is not a detecting level
