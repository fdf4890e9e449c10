"""A nonlinear transmission learned from scratch: does a GP still win where no rigid joint fits?

What the GP's hyperparameters and the rigid models each contribute, on a relation no rigid joint explains.

Protocol (one run, everything from ``seed``): the paper's 2-DOF arm (:func:`~body_scheme_core.world.planar_2dof`)
whose elbow is driven through a nonlinear gear, ``q = 1.2 sin(1.3 a)`` (:class:`~body_scheme_core.world.Body`
``gears``), babbles :data:`N_STEPS` commands at the paper's noise (44 mm / 15 deg) with 5 % dropout. Three learners
learn the same session from scratch:

- the default configuration (rigid and GP candidates; GP edges of the tree refitted on chain-consistent targets with
  length scale and noise ratio of maximum marginal likelihood, ``gp_optimize``);
- the same with the GP hyperparameters fixed at their defaults (``gp_optimize: false``);
- rigid models only (``candidate_kinds: [static, prismatic, revolute]``), the best a calibration with the wrong
  joint model can do.

Rendered mode is not run for this experiment (the simulator's arms have no gear).
"""

from __future__ import annotations

import numpy as np

from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.world import Body, make_session, planar_2dof

__all__ = ["FIGURES", "PAPER", "TARGETS", "SANITY", "PERCEPTIONS", "N_STEPS", "GEAR", "VARIANTS", "run", "plot"]

PERCEPTIONS = ("noise",)
N_STEPS, QUICK_STEPS = 200, 80
VISIBILITY = 0.95
#: The elbow's gear: (amplitude, frequency) of ``q = amplitude sin(frequency a)``.
GEAR = (1.2, 1.3)
#: Learner variants: figure suffix -> configuration overrides.
VARIANTS = {"": {}, "_fixed_gp": {"gp_optimize": False},
            "_rigid_only": {"candidate_kinds": ("static", "prismatic", "revolute")}}

FIGURES = {
    "transmission_gp_edge_fraction": "fraction of runs whose learned elbow edge (markers 2-3) is a GP model after the "
                                     "last step (default configuration)",
    "transmission_ee_err_mm": "after the last step: mean distance (mm) between the predicted and the true end-effector "
                              "position over 100 random commands (default configuration)",
    "transmission_ee_err_mm_fixed_gp": "the same with the GP hyperparameters fixed (gp_optimize: false)",
    "transmission_ee_err_mm_rigid_only": "the same with rigid candidate models only",
}
PAPER = {}
TARGETS = {}
SANITY = {"transmission_gp_edge_fraction": (0.0, 1.0), "transmission_ee_err_mm": (0.0, 1000.0),
          "transmission_ee_err_mm_fixed_gp": (0.0, 1000.0), "transmission_ee_err_mm_rigid_only": (0.0, 1000.0)}
NOTES = """The end-effector figures isolate two choices of the learner on a relation no rigid joint explains: the
GP hyperparameters by marginal likelihood (`transmission_ee_err_mm` against `_fixed_gp`) and GP candidates at all
(against `_rigid_only`, where the best revolute joint absorbs the gear as well as it can)."""


def run(seed, perception="noise", quick=False):
    """One run (see the module docstring); only ``perception="noise"`` exists."""
    if perception != "noise":
        raise ValueError("the transmission experiment runs on the noise model only")
    robot = planar_2dof()
    body = Body(robot, gears={1: GEAR})
    n = QUICK_STEPS if quick else N_STEPS
    session = make_session(body, n, seed, visibility=VISIBILITY)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
    A = rng.uniform(robot.action_lower, robot.action_upper, (100, robot.n_actions))
    effector = robot.marker_ids[-1]
    truth = (session.world2root @ body.true_marker_poses(A)[effector])[:, :3, 3]
    out = {"curves": {}, "events": []}
    for suffix, overrides in VARIANTS.items():
        learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(**overrides),
                                    action_lower=robot.action_lower, action_upper=robot.action_upper)
        for t in range(n):
            events = learner.update(session.actions[t], session.observations[t])
            if not suffix:
                out["events"] += [f"{e.step} {e.kind} {e.model or ''}" for e in events if e.kind != "input_rejected"]
        scheme = learner.body_scheme
        if scheme is None:
            out[f"transmission_ee_err_mm{suffix}"] = float("nan")
            continue
        predicted = np.array([learner.predict(a)[effector][:3, 3] for a in A])
        out[f"transmission_ee_err_mm{suffix}"] = 1e3 * float(np.mean(np.linalg.norm(predicted - truth, axis=1)))
        if not suffix:
            elbow = [m for m in scheme.models if {m.parent, m.child} == set(robot.marker_ids[1:3])]
            out["transmission_gp_edge_fraction"] = float(bool(elbow) and elbow[0].kind == "gp")
    out.setdefault("transmission_gp_edge_fraction", 0.0)
    return out


def plot(runs, path_prefix):
    """No plot: one number per variant."""
    return []
