"""Your robot, not ours: real arms' URDFs that nobody here wrote, from the URDF alone to a calibrated body scheme.

What ``python -m body_scheme_apps.calibrate --simulate <urdf> --camera auto`` does, measured: pybullet ships the URDFs
(``pybullet_data``: ``franka_panda/panda.urdf`` with mimic fingers and ``package://`` meshes,
``kuka_iiwa/model.urdf``, ``xarm/xarm6_robot.urdf`` with transmissions and meshes in ``xarm_description``).

Protocol (one run per robot, everything from ``seed``): the markers are planned
(:func:`~body_scheme_sim.planning.plan_markers`: one per moving body, facing a 1280 x 960 camera placed to frame the
arm, :func:`~body_scheme_sim.planning.hd_camera`); the arm babbles :data:`N_STEPS` random collision-free commands over
its whole joint range; our ArUco tracker reads the simulator's rendered images; the learner (the tracker's noise
priors, 10 mm / 5 deg, as every rendered experiment) learns from scratch. Then:

- the learned body scheme as a URDF is compared with the robot's (:func:`~body_scheme_core.prediction.learned_body.
  calibration_report`): joint axes and origins in the parent marker's frame;
- how accurate it is as ``calibrate`` tells a user (:func:`~body_scheme_core.calibration.accuracy_report` on the
  learner's history window): the 5-fold cross-validated marker position error, the learned structure refitted per
  fold, next to the robot's own URDF's (its root pose fitted per fold); both include the tracker's noise;
- IK on the learned body scheme (within the trained range) sends the end-effector marker to 30 positions it reached
  at random commands; each solution is executed on the true robot and the distance from the target measured.

``--quick``: noise-model perception at the tracker's sigmas, :data:`QUICK_STEPS` commands (no rendering).
"""

from __future__ import annotations

import pathlib
import tempfile
import time

import numpy as np

__all__ = ["FIGURES", "PAPER", "TARGETS", "SANITY", "RUNS", "PERCEPTIONS", "NOISE_LEVELS", "ROBOTS", "N_STEPS",
           "run", "summarize", "plot"]

#: Robot key -> URDF path inside pybullet_data.
ROBOTS = {"panda": "franka_panda/panda.urdf", "iiwa": "kuka_iiwa/model.urdf", "xarm6": "xarm/xarm6_robot.urdf"}
RUNS = 1
PERCEPTIONS = ("noise",)  # the runs are the robots below (rendered, or noise with --quick), not a second perception
NOISE_LEVELS = tuple(ROBOTS)
N_STEPS, QUICK_STEPS = 1000, 250
N_TARGETS = 30
_KEYS = ("true_tree", "steps_to_tree", "max_axis_deg", "max_origin_mm", "ik_true_err_mm_median")

FIGURES = {}
for _robot in ROBOTS:
    FIGURES.update({
        f"yourrobot_{_robot}_true_tree": f"{_robot}: whether the body scheme after the last step is a true one",
        f"yourrobot_{_robot}_steps_to_tree": f"{_robot}: commands until the body scheme was first a true one "
                                              f"(the session's length if never)",
        f"yourrobot_{_robot}_max_axis_deg": f"{_robot}: largest angle between a learned and the specified joint axis",
        f"yourrobot_{_robot}_max_origin_mm": f"{_robot}: largest distance between a learned joint's axis line and the "
                                              f"specified one (mm)",
        f"yourrobot_{_robot}_ik_true_err_mm_median": f"{_robot}: median distance (mm) between an IK target and where "
                                                      f"the true robot's end-effector marker goes at the solution",
        f"yourrobot_{_robot}_cv_mm": f"{_robot}: 5-fold cross-validated mean marker position error of the learned "
                                     f"body scheme (mm, with the tracker's noise)",
        f"yourrobot_{_robot}_nominal_cv_mm": f"{_robot}: the same for the robot's URDF (mm)",
        f"yourrobot_{_robot}_wall_s": f"{_robot}: wall seconds of the run on this machine: plan the markers, render "
                                      f"and track {N_STEPS} commands, learn, report (make your-robot's path)",
    })
PAPER = {}
TARGETS = {**{f"yourrobot_{r}_max_axis_deg": 1.0 for r in ROBOTS}, **{f"yourrobot_{r}_max_origin_mm": 5.0
                                                                          for r in ROBOTS},
           **{f"yourrobot_{r}_ik_true_err_mm_median": 5.0 for r in ROBOTS}}
TARGETS.update({f"yourrobot_{r}_wall_s": 300.0 for r in ROBOTS})
MIN_TARGETS = {f"yourrobot_{r}_true_tree": 1.0 for r in ROBOTS}
SANITY = {**{f"yourrobot_{r}_true_tree": (0.0, 1.0) for r in ROBOTS},
          **{f"yourrobot_{r}_steps_to_tree": (1.0, float(N_STEPS)) for r in ROBOTS}}
NOTES = """These runs are on rendered images (through our tracker), though the table lists them in the "noise" column
(``--quick`` runs the noise model instead). Each robot's figures come from one session of its own (no averaging: a
user calibrates once). The report
pictures show the learned body (blue, red: joint axes) over the specified one (grey), and the per-joint deviations.
The markers of a gripper's fingers are not planned (their 4 cm stroke is within the camera's noise), so the finger
action is a dummy action the learner finds no model for."""


def _urdf(robot):
    import pybullet_data

    return pathlib.Path(pybullet_data.getDataPath()) / ROBOTS[robot]


def run(seed, perception="iiwa", quick=False):
    """One robot's run (``perception``: a key of :data:`ROBOTS`); see the module docstring."""
    from body_scheme_core.calibration import accuracy_report
    from body_scheme_core.control import solve_ik, trained_bounds
    from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
    from body_scheme_core.prediction import calibration_report, learned_tree
    from body_scheme_core.world import is_true_tree
    from body_scheme_sim.planning import plan_markers, write_markers
    from body_scheme_sim.robots import load_robot
    from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS, record_session

    if perception not in ROBOTS:
        raise ValueError(f"unknown robot {perception!r}; known: {list(ROBOTS)}")
    started = time.perf_counter()
    robot, urdf = perception, _urdf(perception)
    n = QUICK_STEPS if quick else N_STEPS
    with tempfile.TemporaryDirectory(prefix="yourrobot_") as tmp:
        planned, _, camera = plan_markers(urdf, seed=seed)
        markers_path = write_markers(planned, pathlib.Path(tmp) / "markers.yaml")
        nominal = load_robot(urdf, markers_path)
        session = record_session(urdf, n_steps=n, seed=seed, perception="noise" if quick else "rendered",
                                 sigma_trans=RENDERED_SIGMA_TRANS, sigma_rot=RENDERED_SIGMA_ROT, camera=camera,
                                 markers_path=markers_path)
    config = BodySchemeConfig(sigma_trans=RENDERED_SIGMA_TRANS, sigma_rot=RENDERED_SIGMA_ROT)
    learner = BodySchemeLearner(nominal.marker_ids, nominal.n_actions, config, action_lower=nominal.action_lower,
                                action_upper=nominal.action_upper)
    first = None
    for t in range(n):
        learner.update(session.actions[t], session.observations[t])
        if first is None and is_true_tree(nominal, learner.body_scheme):
            first = t + 1
    scheme = learner.body_scheme
    key = f"yourrobot_{robot}_"
    out = {key + "true_tree": float(is_true_tree(nominal, scheme)), key + "steps_to_tree": float(first or n),
           "curves": {}, "events": []}
    if scheme is None:
        out[key + "wall_s"] = time.perf_counter() - started
        return out
    body = learned_tree(scheme, nominal.action_joint_names, *learner.trained_range())
    report = calibration_report(body, nominal)
    out[key + "max_axis_deg"] = float(report["max_axis_deg"])
    out[key + "max_origin_mm"] = float(report["max_origin_mm"])
    out["curves"] = {"robot": robot, "body": body, "nominal": nominal, "report": report}
    actions, observations = learner.samples()
    accuracy = accuracy_report(scheme, learner.root_pose, actions, observations, learner.noise.sigma_trans,
                               learner.noise.sigma_rot, nominal.action_joint_names, *learner.trained_range(),
                               nominal=nominal, axis_sigmas=learner.noise.axis_sigmas, curve_points=0)
    out[key + "cv_mm"], out[key + "nominal_cv_mm"] = accuracy["cv_mm"], accuracy["nominal_cv_mm"]
    # IK: targets the end-effector marker truly reached, in the camera frame; solutions executed on the true robot.
    effector = nominal.marker_ids[-1]
    camera2root = np.linalg.inv(camera.world2camera)

    def truth(a):
        return (camera2root @ nominal.marker_poses(a)[effector])[:3, 3]

    lower, upper = trained_bounds(scheme, *learner.trained_range())
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(2)[1])
    errors = []
    for a in rng.uniform(lower, upper, size=(N_TARGETS, nominal.n_actions)):
        result = solve_ik(scheme, effector, truth(a), 0.5 * (lower + upper), lower, upper, rng=rng, confidence=0.0,
                          world2root=learner.root_pose)
        if result.success:
            errors.append(1e3 * float(np.linalg.norm(truth(result.actions) - truth(a))))
    if errors:
        out[key + "ik_true_err_mm_median"] = float(np.median(errors))
    out[key + "wall_s"] = time.perf_counter() - started
    return out


def summarize(runs):
    """Every robot's figures (each robot is one run of its own)."""
    summary = {}
    for result in runs:
        summary.update({k: v for k, v in result.items() if k.startswith("yourrobot_")})
    return summary


def plot(runs, path_prefix):
    """The calibration report picture of every robot with a body scheme: ``<prefix>_<robot>.png``."""
    from body_scheme_apps.calibrate import plot_report

    paths = []
    for result in runs:
        curves = result.get("curves") or {}
        if "body" in curves:
            path = pathlib.Path(f"{path_prefix}_{curves['robot']}.png")
            plot_report(curves["body"], curves["nominal"], curves["report"], path)
            paths.append(path)
    return paths
