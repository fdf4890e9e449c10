"""Active exploration against random babbling: how many commands until the body scheme predicts the end effector
better than the camera sees it?

Protocol (one run per body, everything from ``seed``): the body learns from scratch twice, with the same noise
stream, once from commands drawn uniformly within its joint limits (``random``, what every other experiment does)
and once from :class:`~body_scheme_core.control.exploration.ExplorationPolicy` (``active``: uniform while the learner is
bootstrapping, then of 256 uniform candidates per step the one expected to reduce the parts' positional variance
most, no travel cost). Observations: the paper's noise (44 mm / 15 deg 3D RMS), every marker
seen. Bodies: the 2-DOF arm of Fig. 7 (``2dof``), the paper's 6-DOF arm (``6dof``) and a 7-joint arm
(``arm7``, :func:`~body_scheme_core.world.arm_7dof`).

*First true tree*: commands until the body scheme is first the true one (:func:`~body_scheme_core.world.is_true_tree`);
*bootstrapped*: until the learner leaves its bootstrapping phase; the budget if never.
*Samples*: commands until the end effector's predicted position relative to the root part, averaged over 50 random
postures (the same for both), is first within :data:`THRESHOLD_FRACTION` of the per-axis noise (44 / sqrt 3 = 25 mm)
of the truth; checked every :data:`EVAL_EVERY` commands; the budget if never. *Travel*: joint-space distance (rad)
commanded until then. A ratio is the mean over runs of ``active`` over the mean of ``random``.
*Information spread*: at the first step after bootstrapping, the 90th over the 10th percentile of the 256 candidates'
expected variance reduction (how much it matters which posture comes next; 1: not at all).
"""

from __future__ import annotations

import math

import numpy as np

from body_scheme_core.control import ExplorationPolicy
from body_scheme_core.learning import BodySchemeLearner
from body_scheme_core.world import (
    PAPER_SIGMA_ROT,
    PAPER_SIGMA_TRANS,
    Body,
    ObservationModel,
    arm_7dof,
    is_true_tree,
    planar_2dof,
    powercube_6dof,
)

__all__ = ["FIGURES", "PAPER", "TARGETS", "SANITY", "RUNS", "PERCEPTIONS", "NOISE_LEVELS", "BODIES", "run",
           "summarize", "plot"]

RUNS = 20
PERCEPTIONS = ("noise",)
#: Body key -> (builder, budget of commands).
BODIES = {"2dof": (planar_2dof, 200), "6dof": (powercube_6dof, 400), "arm7": (arm_7dof, 400)}
NOISE_LEVELS = tuple(BODIES)
QUICK_BUDGET = 120
EVAL_EVERY = 5
THRESHOLD_FRACTION = 1.0
POLICIES = ("random", "active")

FIGURES = {}
for _body in BODIES:
    FIGURES.update({
        f"explore_samples_ratio_{_body}": f"{_body}: mean samples until the end-effector error is below the noise, "
                                          f"active over random",
        f"explore_samples_random_{_body}": f"{_body}: mean samples until then, random babbling",
        f"explore_samples_active_{_body}": f"{_body}: mean samples until then, active exploration",
        f"explore_travel_ratio_{_body}": f"{_body}: mean joint-space distance commanded until then, active over "
                                         f"random",
        f"explore_information_spread_{_body}": f"{_body}: 90th over 10th percentile of the candidates' expected "
                                               f"variance reduction after bootstrapping (mean)",
        **{f"explore_{kind}_{policy}_{_body}": f"{_body}: mean commands until {what}, {policy}"
           for kind, what in (("tree", "the first true tree"), ("bootstrapped", "bootstrapping ended"))
           for policy in ("random", "active")},
    })
PAPER = {}
TARGETS = {"explore_samples_ratio_6dof": 0.5}
SANITY = {key: (0.0, 100.0) for key in FIGURES if "ratio" in key}


def _first_below(tree, policy, seed, budget):
    """``(samples, travel, first true tree, bootstrapped, information spread)`` of one learner from scratch with
    ``policy`` (see the module docstring)."""
    rng_commands, rng_noise, rng_test = np.random.default_rng(seed).spawn(3)
    observer = ObservationModel(PAPER_SIGMA_TRANS, PAPER_SIGMA_ROT, 1.0, rng_noise)
    body = Body(tree)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    explorer = ExplorationPolicy(tree.action_lower, tree.action_upper, rng=rng_commands)
    effector, threshold = tree.marker_ids[-1], THRESHOLD_FRACTION * PAPER_SIGMA_TRANS / math.sqrt(3.0)
    test = rng_test.uniform(tree.action_lower, tree.action_upper, size=(50, tree.n_actions))
    true = body.true_marker_array(test)
    index = {p: k for k, p in enumerate(tree.marker_ids)}
    current, travel = np.zeros(tree.n_actions), 0.0
    samples = true_tree = bootstrapped = budget
    travel_then = spread = math.nan
    for t in range(budget):
        if max(samples, true_tree, bootstrapped) < budget:
            break  # all three seen
        if policy == "active":
            a = explorer.suggest(learner.body_scheme if learner.phase == "steady" else None, current)
        else:
            a = rng_commands.uniform(tree.action_lower, tree.action_upper)
        travel += float(np.linalg.norm(a - current))
        current = a
        learner.update(a, observer.observe_array(body.true_marker_array(a[None]), tree.marker_ids)[0])
        scheme = learner.body_scheme
        if policy == "active" and math.isnan(spread) and learner.phase == "steady":  # bootstrapping just ended
            scores = explorer.information(rng_test.uniform(tree.action_lower, tree.action_upper,
                                                           (256, tree.n_actions)), scheme)
            spread = float(np.percentile(scores, 90) / np.percentile(scores, 10))
        if true_tree == budget and is_true_tree(tree, scheme):
            true_tree = t + 1
        if bootstrapped == budget and learner.phase != "bootstrapping":
            bootstrapped = t + 1
        if samples < budget or (t + 1) % EVAL_EVERY or scheme is None or effector not in scheme:
            continue
        predicted = scheme.predict_batch(test)
        k_root, k_eff = scheme.parts.index(scheme.root), scheme.parts.index(effector)
        relative = np.linalg.inv(predicted[:, k_root]) @ predicted[:, k_eff]
        truth = np.linalg.inv(true[:, index[scheme.root]]) @ true[:, index[effector]]
        if np.mean(np.linalg.norm(relative[:, :3, 3] - truth[:, :3, 3], axis=1)) < threshold:
            samples, travel_then = t + 1, travel
    return samples, travel_then if samples < budget else travel, true_tree, bootstrapped, spread


def run(seed, perception="6dof", quick=False):
    """One run on the body ``perception`` (a key of :data:`BODIES`): both policies, the same noise."""
    if perception not in BODIES:
        raise ValueError(f"unknown body {perception!r}; known: {list(BODIES)}")
    builder, budget = BODIES[perception]
    tree = builder()
    out = {"curves": {}, "events": []}
    for policy in POLICIES:
        samples, travel, true_tree, bootstrapped, spread = _first_below(tree, policy, seed,
                                                                        QUICK_BUDGET if quick else budget)
        out[f"explore_{policy}_samples_{perception}"] = float(samples)
        out[f"explore_{policy}_travel_{perception}"] = travel
        out[f"explore_{policy}_tree_{perception}"] = float(true_tree)
        out[f"explore_{policy}_bootstrapped_{perception}"] = float(bootstrapped)
        if policy == "active":
            out[f"explore_information_spread_{perception}"] = spread
    return out


def summarize(runs):
    """Per body: the mean samples of each policy, and the ratios of the means."""
    summary = {}
    for body in BODIES:
        mine = [r for r in runs if f"explore_random_samples_{body}" in r]
        if not mine:
            continue
        means = {f"{p}_{kind}": float(np.mean([r[f"explore_{p}_{kind}_{body}"] for r in mine]))
                 for p in POLICIES for kind in ("samples", "travel", "tree", "bootstrapped")}
        for policy in POLICIES:
            summary[f"explore_samples_{policy}_{body}"] = means[f"{policy}_samples"]
            summary[f"explore_samples_{policy}_{body}_std"] = float(np.std(
                [r[f"explore_{policy}_samples_{body}"] for r in mine]))
        summary[f"explore_samples_ratio_{body}"] = means["active_samples"] / means["random_samples"]
        summary[f"explore_travel_ratio_{body}"] = means["active_travel"] / means["random_travel"]
        spreads = [r[f"explore_information_spread_{body}"] for r in mine]
        spreads = [x for x in spreads if not math.isnan(x)]
        summary[f"explore_information_spread_{body}"] = float(np.mean(spreads)) if spreads else math.nan
        for kind in ("tree", "bootstrapped"):
            for policy in POLICIES:
                summary[f"explore_{kind}_{policy}_{body}"] = means[f"{policy}_{kind}"]
    return summary


def plot(runs, path_prefix):
    """No plot: the figures are ratios of means."""
    return []
