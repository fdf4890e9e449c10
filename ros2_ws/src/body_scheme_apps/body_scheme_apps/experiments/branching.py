"""A branching body learned from scratch: does the learner find the true tree, and stay quiet on a healthy body?

Protocol (one run, everything from ``seed``): :func:`~body_scheme_core.world.branching_tree` ``(seed,
second_torso_marker=True, dummy_action=True)``: a torso on a yaw joint with two 2-DOF arms (segment lengths drawn
from the seed), two markers on the torso (2 and 7) and a sixth action that turns a link carrying no marker (it moves
nothing observed). :func:`~body_scheme_core.world.make_session` babbles :data:`N_STEPS` commands at the paper's
noise (44 mm / 15 deg) with every marker dropped independently in 20 % of the steps; the body never changes. A
:class:`~body_scheme_core.learning.learner.BodySchemeLearner` with the default configuration learns from scratch.

*True tree*: :func:`~body_scheme_core.world.is_true_tree`: the learned tree, with the markers of one link merged,
connects the same links as the robot's marker tree, every edge between two links depends on exactly the actions on
the kinematic path between them, and every edge within a link on none (so ``2 - 3`` and ``7 - 3`` are equally right,
and a model using the dummy action is wrong).
Rendered mode is not run for this experiment (the simulator's robots have no branching arm).
"""

from __future__ import annotations

import numpy as np

from body_scheme_core.learning import BodySchemeLearner
from body_scheme_core.world import Body, branching_tree, is_correct_model, is_true_tree, make_session

__all__ = ["FIGURES", "PAPER", "TARGETS", "MIN_TARGETS", "SANITY", "RUNS", "PERCEPTIONS", "N_STEPS", "robot", "run",
           "plot"]

#: Runs of ``make experiments`` (more than the other experiments: the fraction needs them); noise model only.
RUNS = 30
PERCEPTIONS = ("noise",)
N_STEPS, QUICK_STEPS = 300, 120
VISIBILITY = 0.8

FIGURES = {
    "branching_true_tree_fraction": "fraction of runs whose body scheme after the last step is the true tree (markers "
                                    "of one link merged, every edge on exactly its path's actions, see above)",
    "branching_false_mismatches": "mismatch_detected events on correct tree edges per run (the body never changes; "
                                  "the target is none in any run)",
    "branching_repairs": "mismatch_detected events on wrong tree edges per run (a wrong edge from bootstrapping, "
                         "detected on the calibrated scheme and repaired)",
    "branching_pred_err_mm": "after the last step: mean distance (mm) between predicted and true positions of every "
                             "part (root excepted) over 100 random configurations",
}
PAPER = {}
#: The issue's targets: lower is better (``TARGETS``), higher is better (``MIN_TARGETS``).
TARGETS = {"branching_false_mismatches": 0.0}
MIN_TARGETS = {"branching_true_tree_fraction": 0.96}
SANITY = {"branching_true_tree_fraction": (0.0, 1.0), "branching_false_mismatches": (0.0, 50.0),
          "branching_repairs": (0.0, 50.0), "branching_pred_err_mm": (0.0, 2000.0)}


def robot(seed):
    """The branching robot of one run."""
    return branching_tree(seed, second_torso_marker=True, dummy_action=True)


def run(seed, perception="noise", quick=False):
    """One run (see the module docstring); only ``perception="noise"`` exists."""
    if perception != "noise":
        raise ValueError("the branching experiment runs on the noise model only")
    tree = robot(seed)
    n = QUICK_STEPS if quick else N_STEPS
    session = make_session(tree, n, seed, visibility=VISIBILITY, above_ground=True)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    false_mismatches = repairs = 0
    events = []
    for t in range(n):
        scheme = learner.body_scheme
        for event in learner.update(session.actions[t], session.observations[t]):
            if event.kind == "input_rejected":
                continue
            events.append(f"{event.step} {event.kind} {event.model or ''}")
            if event.kind == "mismatch_detected":
                model = next((m for m in scheme.models if {m.parent, m.child} == {event.parent, event.child}), None)
                if model is None or is_correct_model(tree, model):  # None: the root pose (the body is healthy)
                    false_mismatches += 1
                else:
                    repairs += 1
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
    A = rng.uniform(tree.action_lower, tree.action_upper, (100, tree.n_actions))
    truth = Body(tree).true_marker_poses(A)
    errors = []
    if learner.body_scheme is not None:
        for a, k in zip(A, range(len(A)), strict=True):
            predicted = learner.predict(a)
            errors += [np.linalg.norm(predicted[p][:3, 3] - (session.world2root @ truth[p][k])[:3, 3])
                       for p in tree.marker_ids if p != tree.root_marker]
    return {"branching_true_tree_fraction": float(is_true_tree(tree, learner.body_scheme)),
            "branching_false_mismatches": float(false_mismatches), "branching_repairs": float(repairs),
            "branching_pred_err_mm": 1e3 * float(np.mean(errors)) if errors else float("nan"),
            "curves": {}, "events": events}


def plot(runs, path_prefix):
    """No plot: the figures are counts."""
    return []
