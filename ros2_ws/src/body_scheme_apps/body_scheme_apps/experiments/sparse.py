"""A body scheme through unmarked links: real arms observed at the tool, from scratch and with the URDF as prior.

Protocol (one run per variant, everything from ``seed``): pybullet_data's Franka Panda, KUKA iiwa and xArm6, each
with one marker plate on its base and one on its tool (:func:`plated_robot`), nothing on the links between; a
640 x 480 camera's noise from 2 m (:data:`NOISE`: 1 mm per axis across the ray, 15 mm along it, 3 deg), every plate
seen. The learner is given no noise value.

- ``<robot>`` (from scratch): the excursion plan (:func:`~body_scheme_core.control.exploration.excursion_plan`: a
  reference posture in the middle of the joint ranges, 4 excursions of each joint over 40 % of its range, one posture
  per pair of joints), then uniform commands, :data:`N_STEPS` in all. *True chain*: the body scheme
  is one chain with the arm's joints and types in the arm's order, up to neighbours whose screws commute
  (:func:`~body_scheme_core.learning.same_chain`); *held-out error*: the median distance between the
  predicted and the true tool plate position over :data:`N_HELDOUT` uniform commands never commanded, at the end;
  *poses*: the first step (every :data:`EVERY`) from which the held-out error stays within :data:`TARGET_MM`
  (:data:`N_STEPS` + 1 when never).
- ``<robot>_urdf``: the true arm is its URDF with every joint's origin moved by 2 mm and turned by 0.5 deg (per axis,
  random), as a real arm is off its specification; the learner starts from the URDF's chain with three times that
  as its prior tolerance per joint (:func:`~body_scheme_core.models.chain_spec.chain_from_engineered`) and sees uniform
  commands: *poses* as above, every step. *Bound*: the same for a joint fit of the same observations from the URDF
  with the same prior, told the noise (:func:`_bound_curve`), every :data:`EVERY` poses: what the data and the prior
  allow a calibration tool that knows the camera.
- ``points``: the tool carries three reflectors (not collinear, 10 cm apart) measured with 0.5 mm noise each by a
  laser tracker or motion capture standing where the camera stood, rigid with the base and no base marker (the
  sensor as root, ``sensor_root``); the reflectors' pose (Kabsch) is the observation. The robot by seed in turn;
  *held-out error* at the end.
- ``fault``: after :data:`N_HEALTHY` steps (from scratch, as ``<robot>``) the arm's middle joint sticks; *named*: the
  first ``mismatch_detected`` within :data:`DETECT_WITHIN` steps and a replacement whose event names that joint.
- ``active``: with the URDF as prior (as ``<robot>_urdf``), the poses until the held-out error is within
  :data:`ACTIVE_MM`, the next command chosen by :class:`~body_scheme_core.control.ExplorationPolicy` (A-optimal on
  the joint fit's covariance) against uniform commands (the same seed): their ratio.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from body_scheme_apps.experiments.runner import aggregate
from body_scheme_core.calibration import calibrate
from body_scheme_core.control import ExplorationPolicy, excursion_plan
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner, register_points, same_chain
from body_scheme_core.models import EngineeredModel, chain_from_engineered
from body_scheme_core.prediction import BodyScheme
from body_scheme_core.transforms import transform_from_rotvec, transform_from_xyz_rpy
from body_scheme_core.world import Fault, KinematicTree, Marker, ObservationModel, default_world2root, make_session

__all__ = ["FIGURES", "PAPER", "TARGETS", "MIN_TARGETS", "SANITY", "RUNS", "QUICK_RUNS", "PERCEPTIONS",
           "NOISE_LEVELS", "run", "summarize", "plot", "plated_robot"]

RUNS = 20
QUICK_RUNS = 1  # ten variants: one quick run of each is CI's sanity check
PERCEPTIONS = ("noise",)
#: Robot name -> (URDF in pybullet_data, the tool's link).
ROBOTS = {"panda": ("franka_panda/panda.urdf", "panda_hand"), "iiwa": ("kuka_iiwa/model.urdf", "lbr_iiwa_link_7"),
          "xarm6": ("xarm/xarm6_robot.urdf", "link6")}
NOISE_LEVELS = (*ROBOTS, *(f"{r}_urdf" for r in ROBOTS), "points", "fault", "active")
#: Per-axis position noise across and along the ray (m) and the RMS orientation noise (rad): a 640 x 480 camera at 2 m.
LATERAL, DEPTH, ROTATION = 0.001, 0.015, math.radians(3.0)
NOISE = {"sigma_trans": LATERAL * math.sqrt(2 + (DEPTH / LATERAL) ** 2), "sigma_rot": ROTATION,
         "depth_ratio": DEPTH / LATERAL}
N_STEPS, QUICK_STEPS = 150, 80
N_URDF_STEPS, QUICK_URDF_STEPS = 100, 20
N_HELDOUT, QUICK_HELDOUT = 100, 30
EVERY = 5
TARGET_MM, ACTIVE_MM = 2.0, 2.0
#: A real arm off its URDF: per joint, origin moved by this std per axis (m) and turned by this std (rad).
SPEC_TRANS, SPEC_ROT = 0.002, math.radians(0.5)
POINT_NOISE = 0.0005
N_HEALTHY, N_FAULTY, DETECT_WITHIN = 110, 40, 10

FIGURES = {
    **{f"sparse_{r}_true_chain": f"{r}, from scratch: fraction of runs whose body scheme is the arm's chain (joints, "
                                 f"types, order)" for r in ROBOTS},
    **{f"sparse_{r}_heldout_mm": f"{r}, from scratch: median tool position error at {N_HELDOUT} commands never seen, "
                                 f"after {N_STEPS} poses (mm)" for r in ROBOTS},
    **{f"sparse_{r}_poses": f"{r}, from scratch: poses until the held-out error stays within {TARGET_MM:g} mm "
                            f"({N_STEPS + 1}: never)" for r in ROBOTS},
    **{f"sparse_{r}_poses_urdf": f"{r}, the URDF as prior (the arm 2 mm / 0.5 deg per joint off it): poses until the "
                                 f"held-out error stays within {TARGET_MM:g} mm ({N_URDF_STEPS + 1}: never)"
       for r in ROBOTS},
    **{f"sparse_{r}_poses_urdf_bound": f"{r}: the same for a joint fit of the same observations from the URDF with "
                                       f"the same prior, told the noise: what the data and the prior allow (the "
                                       f"scene's depth is known only to {1e3 * DEPTH:g} mm / sqrt(2 poses))"
       for r in ROBOTS},
    **{f"sparse_{r}_urdf_nominal_mm": f"{r}: the URDF's own held-out error on the perturbed arm (mm)" for r in ROBOTS},
    "sparse_points_heldout_mm": f"three reflectors on the tool (0.5 mm each), from scratch: held-out error after "
                                f"{N_STEPS} poses (mm)",
    "sparse_fault_named_fraction": f"fraction of runs in which a stuck middle joint is detected within "
                                   f"{DETECT_WITHIN} steps and named",
    "sparse_fault_detection_steps": "steps from the joint sticking to its detection",
    "sparse_active_poses_ratio": f"poses until the held-out error is within {ACTIVE_MM:g} mm, the URDF as prior: "
                                 f"active (A-optimal) over uniform commands",
    "sparse_seconds_per_run": "wall seconds of one from-scratch run",
}
PAPER = {}
TARGETS = {**{f"sparse_{r}_heldout_mm": 2.0 for r in ROBOTS}, **{f"sparse_{r}_poses": 150 for r in ROBOTS},
           **{f"sparse_{r}_poses_urdf": 40 for r in ROBOTS}, "sparse_points_heldout_mm": 2.0,
           "sparse_active_poses_ratio": 0.6}
MIN_TARGETS = {**{f"sparse_{r}_true_chain": 1.0 for r in ROBOTS}, "sparse_fault_named_fraction": 0.9}
SANITY = {}
NOTES = ("A chain's order is told only by postures in which several of its joints moved; neighbours whose screws "
         "commute (two sliding joints) have no order a tool's observations could tell.")


def plated_robot(name, world=None):
    """``(tree, tool marker id)``: pybullet_data's robot ``name`` (:data:`ROBOTS`) with a plate on its base (id 1,
    facing the camera) and one on its tool (id 2); ``world``: another :class:`KinematicTree` of the same robot (a
    perturbed one) to place them on."""
    import pybullet_data

    urdf, tool_link = ROBOTS[name]
    tree = world or KinematicTree.from_urdf((pathlib.Path(pybullet_data.getDataPath()) / urdf).read_text())
    markers = [Marker(1, tree.root_link, transform_from_xyz_rpy([0.15, 0.0, 0.02], [math.pi / 2, 0.0, 0.0]), 0.1),
               Marker(2, tool_link, transform_from_xyz_rpy([0.0, 0.0, 0.05], [0.0, 0.0, 0.0]), 0.1)]
    return KinematicTree(tree.joints, markers, root_link=tree.root_link), 2


def perturbed(tree, rng):
    """The same robot with every movable joint's origin moved by :data:`SPEC_TRANS` and turned by :data:`SPEC_ROT`
    (per axis): a real arm off its specification."""
    import dataclasses

    joints = [dataclasses.replace(j, origin=j.origin @ transform_from_rotvec(rng.normal(0, SPEC_ROT, 3),
                                                                              rng.normal(0, SPEC_TRANS, 3)))
              if j.action is not None else j for j in tree.joints]
    return KinematicTree(joints, tree.markers, root_link=tree.root_link)


def _inner(tree):
    lo, hi = tree.action_lower, tree.action_upper
    return lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo)


def _heldout(learner, tree, tool, commands, world2root):
    """Median distance (mm) of the predicted tool plate from the true one at ``commands``; inf without a body
    scheme."""
    if learner.body_scheme is None:
        return math.inf
    errors = [np.linalg.norm(learner.predict(a)[tool][:3, 3] - (world2root @ tree.marker_poses(a)[tool])[:3, 3])
              for a in commands]
    return 1e3 * float(np.median(errors))


def _from_scratch_commands(tree, rng, n):
    lo, hi = tree.action_lower, tree.action_upper
    reference = lo + (hi - lo) * rng.uniform(0.35, 0.65, tree.n_actions)
    plan = excursion_plan(reference, lo, hi, range(tree.n_actions), values=3, span=0.4, rng=rng)
    low, high = _inner(tree)
    return np.vstack([reference[None], plan, rng.uniform(low, high, size=(max(0, n - 1 - len(plan)),
                                                                         tree.n_actions))])[:n]


#: The part that stands for the sensor itself when it is the root (``points``).
SENSOR = 0


def _learn(tree, A, observations, heldout, every, initial=None, sensor=False):
    """Learn ``A`` / ``observations`` from scratch (or from ``initial``; with ``sensor``, the sensor as root and
    the tool's observations only); returns the learner, the held-out errors (mm) after each ``every``-th step and
    the events."""
    parts = [SENSOR, 2] if sensor else list(tree.marker_ids)
    config = (BodySchemeConfig(root=SENSOR, sensor_root=True, mirror_hypotheses=False)  # a laser tracker: no flips
              if sensor else BodySchemeConfig(root=1))
    learner = BodySchemeLearner(parts, tree.n_actions, config, initial_models=initial,
                                action_lower=tree.action_lower, action_upper=tree.action_upper)
    curve, events = [], []
    for k, (a, obs) in enumerate(zip(A, observations, strict=True)):
        events += learner.update(a, obs)
        if (k + 1) % every == 0 or k == len(A) - 1:
            curve.append((k + 1, heldout(learner)))
    return learner, curve, events


def _bound_curve(tree, tool, spec, A, observations, commands, world2root):
    """What the observations and the prior allow: the held-out errors (mm) of a joint fit
    (:func:`~body_scheme_core.calibration.calibrate`) of the first ``k`` observations, every :data:`EVERY` steps,
    from the URDF's chain ``spec`` with its prior, told the noise: the maximum a posteriori calibration. The scene's
    depth is known only to about :data:`DEPTH` / sqrt(2 k) (the two plates' positions along the ray), which no learner
    can beat."""
    base = world2root @ tree.marker_poses(A[0])[1]
    sigmas = (LATERAL, DEPTH, ROTATION / math.sqrt(3.0))
    true_tool = np.array([(world2root @ tree.marker_poses(a)[tool])[:3, 3] for a in commands])
    curve = []
    for k in range(EVERY, len(A) + 1, EVERY):
        fit = calibrate(BodyScheme([1, tool], 1, [spec]), base, A[:k], observations[:k], NOISE["sigma_trans"],
                        NOISE["sigma_rot"], priors={0: (spec.params_, spec.param_cov_)},
                        axis_sigmas=lambda part: sigmas)
        predicted = (fit.world2root @ fit.scheme.models[0].predict(commands))[:, :3, 3]
        curve.append((k, 1e3 * float(np.median(np.linalg.norm(predicted - true_tool, axis=1)))))
    return curve


def _poses_to(curve, target, never):
    """The first step from which the held-out error stays within ``target`` (``never`` otherwise)."""
    for k, (step, _) in enumerate(curve):
        if all(e <= target for _, e in curve[k:]):
            return step
    return never


def run(seed, perception="iiwa", quick=False):
    """One run of variant ``perception`` (a name of :data:`NOISE_LEVELS`); see the module docstring."""
    import time

    if perception not in NOISE_LEVELS:
        raise ValueError(f"unknown variant {perception!r}; known: {NOISE_LEVELS}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, NOISE_LEVELS.index(perception)]))
    robot = perception.split("_")[0] if perception.split("_")[0] in ROBOTS else list(ROBOTS)[seed % len(ROBOTS)]
    n = QUICK_STEPS if quick else N_STEPS
    n_heldout = QUICK_HELDOUT if quick else N_HELDOUT
    world2root = default_world2root()
    start = time.perf_counter()
    if perception.endswith("_urdf") or perception == "active":
        return _with_urdf(robot, perception, seed, rng, quick, n_heldout, world2root)
    tree, tool = plated_robot(robot)
    commands = _from_scratch_commands(tree, rng, n)
    heldout_commands = rng.uniform(*_inner(tree), size=(n_heldout, tree.n_actions))
    if perception == "fault":
        return _fault(tree, robot, commands, seed, quick)
    points = perception == "points"
    observations = _observe(tree, commands, rng, points=points)
    learner, curve, _ = _learn(tree, commands, observations,
                               lambda lr: _heldout(lr, tree, tool, heldout_commands, world2root), EVERY,
                               sensor=points)
    final = curve[-1][1]
    if perception == "points":
        return {"sparse_points_heldout_mm": final, "curves": {}, "events": []}
    truth = chain_from_engineered(EngineeredModel.from_tree(tree, 1, 2))
    models = learner.body_scheme.models if learner.body_scheme is not None else ()
    true_chain = len(models) == 1 and models[0].kind == "chain" and same_chain(models[0], truth)
    return {f"sparse_{robot}_true_chain": float(true_chain), f"sparse_{robot}_heldout_mm": final,
            f"sparse_{robot}_poses": float(_poses_to(curve, TARGET_MM, n + 1)),
            "sparse_seconds_per_run": time.perf_counter() - start,
            "curves": {f"{robot}_heldout": curve}, "events": []}


def _observe(tree, commands, rng, points=False):
    """The observations of ``commands`` at :data:`NOISE` (plates) or, with ``points``, the tool's pose alone from
    three reflectors measured with :data:`POINT_NOISE` each."""
    session = make_session(tree, len(commands), int(rng.integers(2**31)), actions=commands, **NOISE)
    if not points:
        return session.observations
    offsets = np.array([[0.05, 0.0, 0.0], [-0.05, 0.04, 0.0], [0.0, -0.05, 0.03]])
    out = []
    for k in range(len(session.observations)):
        true = session.true_poses[k, list(tree.marker_ids).index(2)]
        measured = (true[:3, :3] @ offsets.T).T + true[:3, 3] + rng.normal(0, POINT_NOISE, offsets.shape)
        out.append({2: register_points(offsets, measured)})
    return out


def _fault(tree, robot, commands, seed, quick):
    """The arm's middle joint sticks after :data:`N_HEALTHY` steps; detected within :data:`DETECT_WITHIN` steps and
    named?"""
    middle = tree.n_actions // 2 if robot != "panda" else 3
    low, high = _inner(tree)
    rng = np.random.default_rng(seed + 7919)
    n = N_HEALTHY + N_FAULTY
    A = np.vstack([commands[:N_HEALTHY], rng.uniform(low, high, size=(max(0, n - min(len(commands), N_HEALTHY)),
                                                                     tree.n_actions))])[:n]
    angle = float(0.5 * (low[middle] + high[middle]))
    session = make_session(tree, n, seed, faults=((N_HEALTHY, Fault("block_joint", action_index=middle,
                                                                    angle=angle)),), actions=A, **NOISE)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, BodySchemeConfig(root=1),
                                action_lower=tree.action_lower, action_upper=tree.action_upper)
    events = []
    for a, obs in zip(A, session.observations, strict=True):
        events += learner.update(a, obs)
    detected = [e.step for e in events if e.kind == "mismatch_detected" and e.step >= N_HEALTHY]
    named = [e for e in events if e.kind == "model_replaced" and e.step >= N_HEALTHY
             and f"joint a{middle} of the chain no longer moves it" in e.reason]
    delay = detected[0] - N_HEALTHY if detected else math.nan
    return {"sparse_fault_named_fraction": float(bool(detected) and delay <= DETECT_WITHIN and bool(named)),
            "sparse_fault_detection_steps": float(delay), "curves": {}, "events": []}


def _with_urdf(robot, perception, seed, rng, quick, n_heldout, world2root):
    """The URDF as prior: poses until the held-out error is within the target; with ``active``, against uniform
    commands."""
    nominal, tool = plated_robot(robot)
    true, _ = plated_robot(robot, world=perturbed(nominal, rng))
    spec = [chain_from_engineered(EngineeredModel.from_tree(nominal, 1, 2), prior=(SPEC_TRANS * 3, SPEC_ROT * 3))]
    n = QUICK_URDF_STEPS if quick else N_URDF_STEPS
    heldout_commands = rng.uniform(*_inner(true), size=(n_heldout, true.n_actions))

    def heldout(learner):
        return _heldout(learner, true, tool, heldout_commands, world2root)

    low, high = _inner(true)
    uniform = rng.uniform(low, high, size=(n, true.n_actions))
    noise_seed = int(rng.integers(2**31))
    if perception != "active":
        session = make_session(true, n, noise_seed, actions=uniform, **NOISE)
        learner, curve, _ = _learn(true, uniform, session.observations, heldout, 1, initial=spec)
        poses = [true.marker_poses(a) for a in heldout_commands]  # the tool as the URDF puts it on the true base
        nominal_error = 1e3 * float(np.median([np.linalg.norm((p[1] @ spec[0].predict(a[None])[0])[:3, 3]
                                                              - p[tool][:3, 3])
                                               for a, p in zip(heldout_commands, poses, strict=True)]))
        bound = _bound_curve(true, tool, spec[0], uniform, session.observations, heldout_commands, world2root)
        return {f"sparse_{robot}_poses_urdf": float(_poses_to(curve, TARGET_MM, n + 1)),
                f"sparse_{robot}_poses_urdf_bound": float(_poses_to(bound, TARGET_MM, n + 1)),
                f"sparse_{robot}_urdf_nominal_mm": nominal_error, "curves": {f"{robot}_urdf": curve}, "events": []}
    poses = {}
    for how in ("random", "active"):
        learner = BodySchemeLearner(true.marker_ids, true.n_actions, BodySchemeConfig(root=1), initial_models=spec,
                                    action_lower=true.action_lower, action_upper=true.action_upper)
        policy = ExplorationPolicy(low, high, 64, rng=np.random.default_rng(seed))
        observer = ObservationModel(rng=np.random.default_rng(noise_seed), world2root=world2root,
                                    sigma_trans=NOISE["sigma_trans"], sigma_rot=NOISE["sigma_rot"],
                                    depth_ratio=NOISE["depth_ratio"])
        curve = []
        for k in range(n):
            a = uniform[k] if how == "random" else policy.suggest(learner.body_scheme, current=None)
            a = uniform[k] if a is None else a
            learner.update(a, observer.observe_array(np.array([[true.marker_poses(a)[i] for i in true.marker_ids]]),
                                                     true.marker_ids)[0])
            curve.append((k + 1, heldout(learner)))
        poses[how] = _poses_to(curve, ACTIVE_MM, n + 1)
    return {"sparse_active_poses_ratio": poses["active"] / poses["random"], "curves": {}, "events": []}


def summarize(runs):
    """Mean and std over the runs of each variant (a run holds its variant's keys only)."""
    summary = {}
    keys = sorted({k for r in runs for k in r if k not in ("curves", "events")})
    for key in keys:
        summary.update({k: v for k, v in aggregate([r for r in runs if key in r]).items()
                        if k in (key, key + "_std")})
    return summary


def plot(runs, path_prefix):
    """Held-out tool error against poses, from scratch and with the URDF, per robot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for ax, suffix, title in ((axes[0], "heldout", "from scratch"), (axes[1], "urdf", "the URDF as prior")):
        for robot in ROBOTS:
            curves = [r["curves"][f"{robot}_{suffix}"] for r in runs if f"{robot}_{suffix}" in r.get("curves", {})]
            if not curves:
                continue
            steps = np.array([s for s, _ in curves[0]])
            values = np.array([[min(e, 1e3) for _, e in c][:len(steps)] for c in curves if len(c) >= len(steps)])
            ax.plot(steps, np.median(values, axis=0), label=robot)
        ax.axhline(TARGET_MM, color="grey", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_xlabel("poses")
        ax.set_ylabel("held-out tool error (mm, median over runs)")
        ax.set_title(title)
        ax.legend()
    fig.tight_layout()
    path = path_prefix.with_suffix(".png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]
