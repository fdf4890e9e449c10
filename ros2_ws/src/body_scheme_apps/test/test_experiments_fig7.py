"""Tests of the Fig. 7 experiment: the 2-DOF arm learning from scratch (prediction and control error vs samples)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from body_scheme_apps.experiments import fig7
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.transforms import invert_transform
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_sim.camera import Camera, look_at
from body_scheme_sim.robots import load_robot
from body_scheme_sim.sessions import record_session

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


@pytest.fixture(scope="module")
def quick_run():
    """One quick noise-model run (seed 0)."""
    return fig7.run(0, "noise", quick=True)


def test_quick_run_reports_every_figure_finite(quick_run):
    """A quick run returns exactly the FIGURES keys, all finite, and curves with one value per sample."""
    assert set(quick_run) == set(fig7.FIGURES) | {"curves"}
    assert all(math.isfinite(quick_run[key]) for key in fig7.FIGURES)
    curves = quick_run["curves"]
    assert set(curves) == {"n", "pred_err_mm", "ctrl_err_mm", "noise_mm", "oracle_err_mm"}
    assert all(len(values) == fig7.QUICK_SAMPLES for values in curves.values())
    assert curves["n"] == [float(n) for n in range(1, fig7.QUICK_SAMPLES + 1)]
    assert set(fig7.PAPER) <= set(fig7.FIGURES) and set(fig7.TARGETS) <= set(fig7.FIGURES)


def test_prediction_error_falls_below_the_noise(quick_run):
    """The end-effector prediction error of the last 5 samples is below the first one with a scheme and below the
    observation noise, and close to what the same estimator reaches on the true structure."""
    pred = np.array(quick_run["curves"]["pred_err_mm"])
    oracle = np.array(quick_run["curves"]["oracle_err_mm"])
    defined = pred[np.isfinite(pred)]
    assert defined.size >= 10
    assert np.mean(defined[-5:]) < defined[0] and np.mean(defined[-5:]) < quick_run["fig7_noise_mm"]
    assert np.mean(defined[-5:]) < 1.2 * np.mean(oracle[-5:])
    assert quick_run["fig7_pred_err_mm_50"] == pred[-1]  # quick: taken after the last sample


def test_errors_are_undefined_exactly_while_there_is_no_body_scheme(quick_run):
    """Prediction and control errors are NaN at the same samples, the first one included (no scheme yet)."""
    pred, ctrl = (np.array(quick_run["curves"][key]) for key in ("pred_err_mm", "ctrl_err_mm"))
    assert math.isnan(pred[0]) and np.array_equal(np.isfinite(ctrl), np.isfinite(pred))
    learner = BodySchemeLearner((1, 2, 3), 2)
    assert learner.body_scheme is None
    assert math.isnan(fig7.prediction_error_mm(learner, np.zeros((1, 2)), np.zeros((1, 3))))
    assert math.isnan(fig7.control_error_mm(learner, np.zeros((1, 3)), np.zeros(2), planar_2dof(), np.eye(4), None))


def test_noise_level_matches_the_paper_noise_model(quick_run):
    """In noise mode the measured observation noise is near the noise model's expected mean error (40.5 mm)."""
    assert quick_run["fig7_noise_mm"] == pytest.approx(fig7.PAPER_NOISE_MEAN_MM, abs=6.0)
    assert np.nanmean(quick_run["curves"]["noise_mm"]) == pytest.approx(quick_run["fig7_noise_mm"], rel=0.1)


def test_samples_below_is_the_start_of_the_final_run_below_the_level():
    """samples_below: first n from which every error is below the level; NaN is not below; n_max + 1 if never."""
    assert fig7.samples_below([math.nan, 50.0, 30.0, 45.0, 30.0, 20.0], 40.0) == 5
    assert fig7.samples_below([10.0, 20.0], 40.0) == 1
    assert fig7.samples_below([math.nan, 30.0, 50.0], 40.0) == 4
    assert fig7.samples_below([30.0, math.nan], 40.0) == 3


def test_true_positions_match_the_sessions_ground_truth():
    """true_positions reproduces the end effector's recorded true pose in the camera frame."""
    tree = planar_2dof()
    session = make_session(tree, 20, seed=1)
    column = session.marker_ids.index(fig7.EFFECTOR)
    expected = session.true_poses[:, column, :3, 3]
    assert np.allclose(fig7.true_positions(tree, session.world2root, session.actions, fig7.EFFECTOR), expected)


def test_true_structure_reference_is_exact_on_noise_free_observations():
    """Fitted on true poses, the true-structure joint fit predicts the end effector to a fraction of a millimetre."""
    tree = planar_2dof()
    session = make_session(tree, 8, seed=2)
    observations = [{i: session.true_poses[t, k] for k, i in enumerate(session.marker_ids)} for t in range(8)]
    A = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper, (20, 2))
    truth = fig7.true_positions(tree, session.world2root, A, fig7.EFFECTOR)
    config = BodySchemeConfig()
    assert fig7.true_structure_error_mm(tree, session.actions, observations, A, truth, config) < 0.1
    assert math.isnan(fig7.true_structure_error_mm(tree, session.actions[:2], observations[:2], A, truth, config))


def test_control_error_with_the_true_scheme_is_within_the_ik_tolerance():
    """With the engineered (exact) body scheme, IK brings the true end effector within 5 mm of reachable targets."""
    tree = planar_2dof()
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, initial_models=engineered_models(tree))
    rng = np.random.default_rng(0)
    targets = fig7.true_positions(tree, learner.root_pose, rng.uniform(tree.action_lower, tree.action_upper, (5, 2)),
                                  fig7.EFFECTOR)
    error = fig7.control_error_mm(learner, targets, np.zeros(2), tree, learner.root_pose, rng)
    assert error <= 1e3 * fig7.IK_TOLERANCE


def test_rendered_run_works_on_a_tiny_run(monkeypatch):
    """Rendered perception: 12 samples through the ArUco tracker give a body scheme and millimetre-level noise."""
    monkeypatch.setattr(fig7, "QUICK_SAMPLES", 12)
    result = fig7.run(0, "rendered", quick=True)
    assert len(result["curves"]["n"]) == 12
    assert 0.5 < result["fig7_noise_mm"] < 30.0
    assert math.isfinite(result["fig7_pred_err_mm_50"]) and result["fig7_pred_err_mm_50"] < 100.0
    assert math.isfinite(result["fig7_ctrl_err_mm_50"])


def test_rendered_ground_truth_is_the_sim_robot_seen_from_the_camera():
    """true_positions of the sim robot's tree from the rendered camera equals the recorded ground truth."""
    camera = Camera(world2camera=look_at(fig7.RENDERED_EYE, fig7.RENDERED_TARGET))
    session = record_session(fig7.ROBOT, 3, seed=0, camera=camera)
    column = session.marker_ids.index(fig7.EFFECTOR)
    positions = fig7.true_positions(load_robot(fig7.ROBOT), invert_transform(camera.world2camera), session.actions,
                                    fig7.EFFECTOR)
    assert np.allclose(positions, session.true_poses[:, column, :3, 3])


def test_plot_writes_one_png(quick_run, tmp_path):
    """plot writes the Fig. 7 PNG next to the prefix and returns its path."""
    curves = {k: v if k == "n" else (1.1 * np.array(v)).tolist() for k, v in quick_run["curves"].items()}
    other = {**quick_run, "curves": curves}
    paths = fig7.plot([quick_run, other], tmp_path / "fig7")
    assert paths == [tmp_path / "fig7.png"]
    assert paths[0].stat().st_size > 1000
