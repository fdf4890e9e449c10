"""Fig. 7 of the paper (Sec. IV-A): the 2-DOF arm learns its body scheme from scratch; prediction and control error.

Protocol (one run, everything from ``seed``):

- Robot :func:`~body_scheme_core.world.planar_2dof` (sim robot ``"planar_2dof"``): two revolute joints with
  parallel axes, limits +-90 deg, markers 1 (base, the root), 2 (on joint 2), 3 (end effector, the part farthest from
  the root). A :class:`~body_scheme_core.learning.learner.BodySchemeLearner` with no initial models (bootstrapping from
  scratch, the paper's configuration: thresholds 3 sigma, test window 15, training 30) gets one babbling sample per
  update: uniformly random commands within the limits and the markers seen after them, every marker visible.
- Noise mode: :func:`~body_scheme_core.world.make_session` with the paper's marker noise, 44 mm / 15 deg RMS (the
  learner's default sigmas). Rendered mode: :func:`~body_scheme_sim.sessions.record_session` with
  ``perception="rendered"`` (the simulator's camera images through the ArUco tracker), the learner with the
  tracker's sigmas (``RENDERED_SIGMA_TRANS``, ``RENDERED_SIGMA_ROT``) and a camera above the arm
  (:data:`RENDERED_EYE`, see there why not the simulator's default).
- After each sample n = 1 .. :data:`N_SAMPLES` (quick: :data:`QUICK_SAMPLES`):

  - prediction error: over :data:`N_TEST` test configurations drawn once per run (uniform within the limits, not
    babbled), the mean distance between the end effector's position predicted by ``learner.predict(a)`` (the
    camera-frame root pose estimate times the learned chain) and its true position in the camera frame;
  - control error: for :data:`N_TARGETS` targets drawn once per run (the true camera-frame end-effector positions of
    uniformly random configurations, so every target is reachable), :func:`~body_scheme_core.control.ik.solve_ik` on the
    learned body scheme within :func:`~body_scheme_core.control.ik.trained_bounds`, with ``control_node``'s defaults
    (tolerance 5 mm, 100 iterations, 3 restarts, start at the current command, the camera-frame target converted
    with the learner's root pose); the error is the true distance of the end effector from the target at the
    returned actions (the arm's ground-truth kinematics), mean over the targets.

  Both are undefined (NaN, left out of means and plots) while the learner has no body scheme: before its first
  valid spanning tree and whenever bootstrapping loses every valid tree again. The sample count n counts every
  sample from the first.
- Noise level: the mean 3D position error of every marker observation of the run against ground truth.

- All-parts error: the same as the prediction error, averaged over every part but the root (markers 2 and 3).
- Reference (curve ``oracle_err_mm``, :func:`true_structure_error_mm`): the joint fit of revolute joints on the *true*
  structure from the same samples, i.e. what the learner's estimator reaches when the structure is known; the gap
  between it and the learner is the cost of finding the structure.
"""

from __future__ import annotations

import math

import numpy as np

from body_scheme_core.calibration import calibrate
from body_scheme_core.control import solve_ik, trained_bounds
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner, RootPoseEstimator
from body_scheme_core.models import RevoluteModel
from body_scheme_core.prediction import BodyScheme
from body_scheme_core.transforms import invert_transform
from body_scheme_core.world import PAPER_SIGMA_TRANS, Body, make_session, planar_2dof

__all__ = ["FIGURES", "PAPER", "TARGETS", "SANITY", "NOTES", "ROBOT", "EFFECTOR", "RENDERED_EYE", "RENDERED_TARGET",
           "N_SAMPLES", "QUICK_SAMPLES", "true_positions", "noise_level_mm", "prediction_error_mm", "control_error_mm",
           "true_structure_error_mm", "samples_below", "run", "plot"]

ROBOT = "planar_2dof"
#: The end effector: marker 3, the part farthest from the root (marker 1).
EFFECTOR = 3
#: Samples per run, test configurations and IK targets (full / quick).
N_SAMPLES, N_TEST, N_TARGETS = 60, 100, 20
QUICK_SAMPLES, QUICK_TEST, QUICK_TARGETS = 20, 30, 5
#: IK settings: ``control_node``'s defaults (config/control_node.yaml).
IK_TOLERANCE, IK_ITERATIONS, IK_RESTARTS = 0.005, 100, 3
#: Sample counts of the reported errors.
EARLY, LATE = 15, 50
#: Rendered mode's camera (eye and target, m, world = robot base frame): above the planar arm's workspace, about 2 m
#: from it. With the simulator's default camera (placed for the 3D arms) the tracker never finds the base marker,
#: which faces up at the middle of the image as a 25 x 19 px quadrilateral (0 of 60 samples; ``corner_refinement``
#: "apriltag" loses it), so no body scheme can ever connect the root. From here all three markers are in view in every
#: babbled configuration and detected in 93-98 % of the samples, with mean position errors of 13 / 6 / 6 mm.
RENDERED_EYE, RENDERED_TARGET = (1.3, 0.0, 1.7), (0.25, 0.0, 0.13)
#: Expected mean 3D error (mm) of the paper's noise model: E|e| = sigma sqrt(8 / (3 pi)) for isotropic Gaussian noise
#: with 3D RMS sigma = 44 mm; the "noise level" the issue's target is relative to.
PAPER_NOISE_MEAN_MM = 1e3 * PAPER_SIGMA_TRANS * math.sqrt(8.0 / (3.0 * math.pi))

FIGURES = {
    "fig7_noise_mm": "2-DOF arm: mean 3D position error (mm) of all marker observations of the run against ground "
                     "truth (the noise level)",
    "fig7_samples_below_noise": "first sample count n from which the end-effector prediction error stays below the "
                                "run's noise level up to the last n of the curve (60; no body scheme counts as not "
                                "below); 61 (quick: 21) if it is not below at the end, i.e. not reached in the run",
    "fig7_pred_err_mm_15": "mean distance (mm) between the predicted (learner.predict, camera frame) and the true "
                           "end-effector position over 100 fixed random test configurations, after 15 samples",
    "fig7_pred_err_mm_50": "the same after 50 samples (quick: after the last, 20)",
    "fig7_pred_err_all_mm_15": "the prediction error averaged over every part but the root (markers 2 and 3), after "
                               "15 samples",
    "fig7_pred_err_all_mm_50": "the same after 50 samples (quick: after the last, 20)",
    "fig7_ctrl_err_mm_50": "after 50 samples (quick: 20): IK on the learned scheme (trained_bounds, control_node "
                           "defaults) to 20 reachable random targets; mean true distance (mm) of the end effector "
                           "from the target",
}
#: The paper's Sec. IV-A: sigma 44 mm; below the noise after 7 samples; control error about 50 mm.
PAPER = {"fig7_noise_mm": 44.0, "fig7_samples_below_noise": 7.0, "fig7_ctrl_err_mm_50": 50.0}
#: The issue's targets, lower is better (the paper's 7 samples was probably reached at a lower orientation noise).
TARGETS = {"fig7_samples_below_noise": 7.0, "fig7_pred_err_mm_15": 25.0, "fig7_pred_err_mm_50": 13.0}
#: Loose bounds for ``make experiments-quick`` (a broken pipeline, not a weak result, falls outside).
SANITY = {"fig7_noise_mm": (1.0, 100.0), "fig7_samples_below_noise": (1.0, N_SAMPLES + 1.0),
          "fig7_pred_err_mm_15": (1.0, 1000.0), "fig7_pred_err_mm_50": (1.0, 1000.0),
          "fig7_pred_err_all_mm_15": (1.0, 1000.0), "fig7_pred_err_all_mm_50": (1.0, 1000.0),
          "fig7_ctrl_err_mm_50": (0.0, 1000.0)}
NOTES = """\
How the learner gets below the noise. Each local model is a rigid joint (here revolute, found among static,
prismatic, revolute and GP candidates), and once a spanning tree is found the root pose and all joints are fitted
together to the absolute marker observations (the joint fit): no edge learns from its parent marker's noisy
orientation, whose 15 deg times the 0.4-0.5 m links made every relative observation 90-110 mm noisy. The grey dotted
curve (`oracle_err_mm`) is the same joint fit on the *true* structure from the same samples: from the sixth sample on
the learner follows it exactly (the structure is found after 5-6 samples: the revolute candidates predict from their
third sample and are judged on three test samples), so what separates the learner from the paper's "below the noise
after 7" is the estimator at 6-10 samples of 44 mm / 15 deg noise, not the structure search. With the joint scale
fitted (`fit_joint_scale`, one parameter more per joint) the reference needs 0.6 samples more on average (10 seeds)."""


def true_positions(tree, world2root, A, part):
    """True camera-frame positions of ``part`` for commanded actions (clipped to the joint limits as the arm does).

    Parameters
    ----------
    tree : KinematicTree
        The arm as it is.
    world2root : array-like, shape (4, 4)
        Pose of the robot's root link in the camera (world) frame.
    A : array-like, shape (k, m)
    part : int

    Returns
    -------
    positions : ndarray, shape (k, 3)
    """
    root2part = Body(tree).true_marker_poses(np.atleast_2d(A))[part]
    return (np.asarray(world2root, dtype=float) @ root2part)[:, :3, 3]


def noise_level_mm(observations, true_poses, marker_ids):
    """Mean 3D position error (mm) of marker observations against ground truth, per sample.

    Parameters
    ----------
    observations : list of dict of int to ndarray, shape (4, 4)
        Per sample ``{marker id: camera2marker}`` as perceived.
    true_poses : ndarray, shape (n, n_markers, 4, 4)
        True ``camera2marker`` in ``marker_ids`` order.
    marker_ids : sequence of int

    Returns
    -------
    per_sample : ndarray, shape (n,)
        Mean error of the markers seen in each sample (NaN where none was seen).
    overall : float
        Mean over all observations of the run.
    """
    column = {marker: k for k, marker in enumerate(marker_ids)}
    errors = [[np.linalg.norm(Y[:3, 3] - true_poses[t, column[i], :3, 3]) for i, Y in obs.items()]
              for t, obs in enumerate(observations)]
    per_sample = np.array([1e3 * np.mean(e) if e else math.nan for e in errors])
    flat = [x for e in errors for x in e]
    return per_sample, (1e3 * float(np.mean(flat)) if flat else math.nan)


def prediction_error_mm(learner, A, truth):
    """Mean distance (mm) between the predicted and the true end-effector positions; NaN without a body scheme.

    Parameters
    ----------
    learner : BodySchemeLearner
    A : ndarray, shape (k, m)
        Test configurations.
    truth : ndarray, shape (k, 3)
        True camera-frame end-effector positions at ``A``.
    """
    if learner.body_scheme is None:
        return math.nan
    predicted = np.array([learner.predict(a)[EFFECTOR][:3, 3] for a in A])
    return 1e3 * float(np.mean(np.linalg.norm(predicted - truth, axis=1)))


def control_error_mm(learner, targets, a0, tree, world2root, rng):
    """Mean true distance (mm) of the end effector from IK targets reached on the learned scheme; NaN without one.

    Parameters
    ----------
    learner : BodySchemeLearner
    targets : ndarray, shape (k, 3)
        Camera-frame target positions of the end effector.
    a0 : ndarray, shape (m,)
        Start of every IK search (the current command).
    tree, world2root
        Ground truth, see :func:`true_positions`.
    rng : numpy.random.Generator
        Restart points of the IK.
    """
    scheme = learner.body_scheme
    if scheme is None:
        return math.nan
    lower, upper = trained_bounds(scheme, tree.action_lower, tree.action_upper)
    actions = np.array([solve_ik(scheme, EFFECTOR, target, a0, lower, upper, tol=IK_TOLERANCE,
                                 max_iterations=IK_ITERATIONS, n_restarts=IK_RESTARTS, rng=rng,
                                 world2root=learner.root_pose).actions for target in targets])
    reached = true_positions(tree, world2root, actions, EFFECTOR)
    return 1e3 * float(np.mean(np.linalg.norm(reached - targets, axis=1)))


def all_parts_error_mm(learner, A, truths):
    """Mean distance (mm) between predicted and true positions of every part but the root; NaN without a scheme.

    Parameters
    ----------
    learner : BodySchemeLearner
    A : ndarray, shape (k, m)
    truths : dict of int to ndarray, shape (k, 3)
        True camera-frame positions per part.
    """
    if learner.body_scheme is None:
        return math.nan
    predicted = [learner.predict(a) for a in A]
    return 1e3 * float(np.mean([np.linalg.norm(np.array([p[part][:3, 3] for p in predicted]) - truth, axis=1).mean()
                                for part, truth in truths.items()]))


def true_structure_error_mm(tree, actions, observations, A, truth, config):
    """Reference: end-effector error of the joint fit of revolute joints on the true structure, same samples.

    Each true edge's revolute joint is fitted to its relative observations, then the root pose and the joints are
    fitted jointly to all observations (:func:`~body_scheme_core.calibration.joint_fit.calibrate`), exactly as the
    learner does once it has found the tree. NaN while an edge has fewer than 3 samples.

    Parameters
    ----------
    tree : KinematicTree
    actions : ndarray, shape (n, m)
    observations : list of dict of int to ndarray, shape (4, 4)
    A : ndarray, shape (k, m)
        Test configurations.
    truth : ndarray, shape (k, 3)
    config : BodySchemeConfig
        Noise sigmas.

    Returns
    -------
    error : float
        Mean error (mm).
    """
    models = []
    for parent, child in tree.marker_tree_edges():
        (action,) = tree.path_actions(parent, child)
        seen = [t for t, obs in enumerate(observations) if parent in obs and child in obs]
        if len(seen) < 3:
            return math.nan
        Z = np.array([invert_transform(observations[t][parent]) @ observations[t][child] for t in seen])
        d2 = np.sum(Z[:, :3, 3] ** 2, axis=1)
        sigma_trans, sigma_rot = config.prior_sigma_trans, config.prior_sigma_rot
        S = np.stack([np.sqrt((2 * sigma_trans**2 + (2 / 3) * sigma_rot**2 * d2) / 3),
                      np.full(len(seen), sigma_rot * math.sqrt(2 / 3))], axis=1)
        models.append(RevoluteModel(parent, child, (action,)).fit(actions[seen], Z, sigma=S))
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, models)
    world2root = RootPoseEstimator(config.root_window, tree.root_marker, zip(actions, observations, strict=True)).pose(
        scheme)
    fit = calibrate(scheme, world2root, actions, observations, config.prior_sigma_trans, config.prior_sigma_rot)
    predicted = (fit.world2root @ fit.scheme.predict_batch(A)[:, fit.scheme.parts.index(EFFECTOR)])[:, :3, 3]
    return 1e3 * float(np.mean(np.linalg.norm(predicted - truth, axis=1)))


def samples_below(errors, level):
    """First sample count n from which every error up to the end is below ``level`` (NaN is not below).

    Parameters
    ----------
    errors : array-like, shape (n_max,)
        Error after 1, 2, ..., n_max samples.
    level : float

    Returns
    -------
    n : int
        In ``1 .. n_max``, or ``n_max + 1`` if the last error is not below ``level``.
    """
    below = np.asarray(errors, dtype=float) < level  # NaN compares False
    n = below.size
    while n > 0 and below[n - 1]:
        n -= 1
    return n + 1


def _evaluation_rng(seed):
    """Stream of the test configurations, targets and IK restarts, independent of the session's: make_session and
    record_session use children 0 and 1 of ``default_rng(seed)``; this is child 2."""
    return np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])


def _noise_world(seed, n_samples):
    """Tree, session, camera2root and learner config of the noise-model run."""
    tree = planar_2dof()
    session = make_session(tree, n_samples, seed)
    return tree, session, session.world2root, BodySchemeConfig()


def _rendered_world(seed, n_samples):
    """The same from the simulator's rendered images through the ArUco tracker; truth from the sim robot's tree."""
    from body_scheme_sim.camera import Camera, look_at
    from body_scheme_sim.robots import load_robot
    from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS, record_session

    tree = load_robot(ROBOT)
    camera = Camera(world2camera=look_at(RENDERED_EYE, RENDERED_TARGET))
    session = record_session(ROBOT, n_samples, seed, perception="rendered", camera=camera)
    config = BodySchemeConfig(sigma_trans=RENDERED_SIGMA_TRANS, sigma_rot=RENDERED_SIGMA_ROT)
    return tree, session, invert_transform(session.camera.world2camera), config


def run(seed, perception="noise", quick=False):
    """One run of Fig. 7 (see the module docstring).

    Parameters
    ----------
    seed : int
    perception : {"noise", "rendered"}
    quick : bool
        :data:`QUICK_SAMPLES` samples, fewer test configurations and targets; the ``_50`` figures are then taken
        after the last sample.

    Returns
    -------
    result : dict
        The :data:`FIGURES` keys, and ``"curves"``: ``n``, ``pred_err_mm``, ``ctrl_err_mm``, ``noise_mm`` (mean
        error of the markers seen in sample n) and ``oracle_err_mm`` (:func:`true_structure_error_mm`), one value per
        sample count (NaN where undefined).
    """
    n_samples, n_test, n_targets = (QUICK_SAMPLES, QUICK_TEST, QUICK_TARGETS) if quick else \
        (N_SAMPLES, N_TEST, N_TARGETS)
    if perception == "noise":
        tree, session, world2root, config = _noise_world(seed, n_samples)
    elif perception == "rendered":
        tree, session, world2root, config = _rendered_world(seed, n_samples)
    else:
        raise ValueError(f"perception must be 'noise' or 'rendered', got {perception!r}")
    rng = _evaluation_rng(seed)
    lower, upper = tree.action_lower, tree.action_upper
    A_test = rng.uniform(lower, upper, (n_test, tree.n_actions))
    test_truth = true_positions(tree, world2root, A_test, EFFECTOR)
    part_truths = {part: true_positions(tree, world2root, A_test, part) for part in tree.marker_ids
                   if part != tree.root_marker}
    targets = true_positions(tree, world2root, rng.uniform(lower, upper, (n_targets, tree.n_actions)), EFFECTOR)

    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, config, action_lower=lower, action_upper=upper)
    pred, ctrl, oracle, every = (np.full(n_samples, math.nan) for _ in range(4))
    checkpoints = {min(EARLY, n_samples) - 1, min(LATE, n_samples) - 1}
    for k in range(n_samples):
        learner.update(session.actions[k], session.observations[k], stamp=float(k))
        pred[k] = prediction_error_mm(learner, A_test, test_truth)
        ctrl[k] = control_error_mm(learner, targets, session.actions[k], tree, world2root, rng)
        oracle[k] = true_structure_error_mm(tree, session.actions[:k + 1], session.observations[:k + 1], A_test,
                                            test_truth, config)
        if k in checkpoints:
            every[k] = all_parts_error_mm(learner, A_test, part_truths)
    noise_curve, noise = noise_level_mm(session.observations, session.true_poses, session.marker_ids)
    late = min(LATE, n_samples) - 1
    return {
        "fig7_noise_mm": noise,
        "fig7_samples_below_noise": float(samples_below(pred, noise)),
        "fig7_pred_err_mm_15": float(pred[min(EARLY, n_samples) - 1]),
        "fig7_pred_err_mm_50": float(pred[late]),
        "fig7_pred_err_all_mm_15": float(every[min(EARLY, n_samples) - 1]),
        "fig7_pred_err_all_mm_50": float(every[late]),
        "fig7_ctrl_err_mm_50": float(ctrl[late]),
        "curves": {"n": [float(n) for n in range(1, n_samples + 1)], "pred_err_mm": pred.tolist(),
                   "ctrl_err_mm": ctrl.tolist(), "noise_mm": noise_curve.tolist(), "oracle_err_mm": oracle.tolist()},
    }


def plot(runs, path_prefix):
    """Fig. 7: prediction and control error vs samples (mean +- std over runs) with the noise level; PNG paths.

    Parameters
    ----------
    runs : list of dict
        :func:`run` results (of one mode, equal curve lengths).
    path_prefix : pathlib.Path
        The figure is written to ``<path_prefix>.png``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    n = np.asarray(runs[0]["curves"]["n"], dtype=float)
    noise = float(np.nanmean([r["fig7_noise_mm"] for r in runs]))
    fig, ax = plt.subplots(figsize=(7, 4))
    for key, label, color, band in (("pred_err_mm", "prediction error (end effector)", "C0", True),
                                    ("ctrl_err_mm", "control error (IK, true distance)", "C3", True),
                                    ("oracle_err_mm", "prediction, joint fit of the true structure", "0.4",
                                     False)):
        curves = np.array([r["curves"][key] for r in runs], dtype=float)
        defined = np.isfinite(curves).any(axis=0)
        mean = np.nanmean(curves[:, defined], axis=0)
        if band:
            std = np.nanstd(curves[:, defined], axis=0)
            ax.fill_between(n[defined], np.maximum(mean - std, 1.0), mean + std, color=color, alpha=0.2)
        ax.plot(n[defined], mean, color=color, lw=1.5 if band else 1.0, ls="-" if band else ":", label=label)
    ax.axhline(noise, color="k", ls="--", lw=1.0, label=f"observation noise ({noise:.0f} mm)")
    ax.set(xlabel="samples", ylabel="error (mm)", yscale="log", xlim=(1, n[-1]),
           title=f"2-DOF arm learned from scratch: mean +- std over {len(runs)} runs (cf. paper Fig. 7)")
    ax.set_ylim(top=min(ax.get_ylim()[1], 1000.0))  # the first samples' errors are meaningless beyond 1 m
    plain = FuncFormatter(lambda value, _: f"{value:g}" if f"{value:g}"[0] in "1235" else "")
    ax.yaxis.set_major_formatter(plain)
    ax.yaxis.set_minor_formatter(plain)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right")
    fig.tight_layout()
    path = path_prefix.parent / f"{path_prefix.name}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]
