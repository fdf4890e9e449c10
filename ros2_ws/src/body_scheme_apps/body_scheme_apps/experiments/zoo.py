"""The robot zoo: random bodies at five noise levels, learned from scratch, then changed once.

Protocol (one run, everything from ``seed`` and the noise level): :func:`~body_scheme_core.world.zoo_robot` ``(seed)``,
a random serial or branching body of 1-14 joints, revolute and prismatic, with fixed (passive) links, links without a
marker, links with two, dummy actions and shuffled marker ids. :func:`~body_scheme_core.world.make_session` babbles
:data:`N_HEALTHY` commands on the healthy body, then :data:`N_CHANGED` after one change of its physiology
(:func:`~body_scheme_core.world.random_fault`, by seed in turn: a joint blocked in the middle of its range, a limb bent
by 20 deg, a marker moved by 3 noise RMS, a tool lengthening a last limb by 3 noise RMS), every marker dropped in 15 %
of the steps. A :class:`~body_scheme_core.learning.learner.BodySchemeLearner` learns from scratch with the default
configuration, given no noise value; at the levels with mirrored orientations (``realcam``, ``flips30``) it is told
what a tag tracker's user would tell it, ``mirror_hypotheses`` (:data:`LEARNER_SETTINGS`). The noise levels (position
as the RMS of the 3D error, orientation as the RMS angle, see :class:`~body_scheme_core.world.ObservationModel`):

- ``camera``: 5 mm / 1 deg, isotropic;
- ``realcam``: 3 mm per axis across the ray, 20 mm along it, 3 deg, 3 % of the orientations mirrored about the ray
  (the planar ambiguity);
- ``paper``: 44 mm / 15 deg (the paper's);
- ``harsh``: 76 mm / 26 deg (the paper's per axis, as a learner reading 44 mm per axis sees it);
- ``flips30``: ``realcam`` with 30 % of the orientations mirrored (a 640x480 camera's rate for an 8 cm tag at 2 m);
  its change is reported, not counted in the detection figures.

*Flips*, judged against the true poses: an observation is a flip when its mirror image about the ray is nearer the
true orientation than it is by more than :data:`FLIP_MARGIN` noise RMS, a true pose when it is farther by as much
(a mirror image within that margin, as of a face-on marker, is neither). The learner's ``corrected["flipped"]`` and
``rejected["flipped"]`` are attributed to parts (the accepted observation differs from the one given; the
``input_rejected`` event names the part) and judged: a correction of a flip uses it, a correction or refusal of a
true pose is wrong.

*True tree*: :func:`~body_scheme_core.world.is_true_tree` (markers of one link merged, every edge on exactly the
commanded joints of its path). A change is *detected* by the first ``mismatch_detected`` event after it on an edge
with a marker whose pose the change moved.
"""

from __future__ import annotations

import math
import time

import numpy as np

from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.transforms import mirror_about_ray, rotational_error
from body_scheme_core.world import RANDOM_FAULTS, Body, is_correct_model, is_true_tree, make_session, random_fault
from body_scheme_core.world import zoo_robot as _zoo_robot

__all__ = ["FIGURES", "PAPER", "TARGETS", "MIN_TARGETS", "SANITY", "RUNS", "VARIANTS", "NOISE_LEVELS", "FlipTally",
           "run", "summarize", "plot"]

RUNS = 40
PERCEPTIONS = ("noise",)
#: Position noise (3D RMS, m), orientation noise (RMS angle, rad), depth over lateral per-axis std, mirror rate.
NOISE_LEVELS = {
    "camera": {"sigma_trans": 0.005, "sigma_rot": math.radians(1.0)},
    "realcam": {"sigma_trans": math.sqrt(2 * 0.003**2 + 0.020**2), "sigma_rot": math.radians(3.0),
                "depth_ratio": 0.020 / 0.003, "flip_rate": 0.03},
    "paper": {"sigma_trans": 0.044, "sigma_rot": math.radians(15.0)},
    "harsh": {"sigma_trans": 0.076, "sigma_rot": math.radians(26.0)},
    "flips30": {"sigma_trans": math.sqrt(2 * 0.003**2 + 0.020**2), "sigma_rot": math.radians(3.0),
                "depth_ratio": 0.020 / 0.003, "flip_rate": 0.30},
}
#: The learner's settings per level beyond the defaults: the levels of a tag tracker whose poses flip are learned as
#: its user would (``learner.mirror_hypotheses``); the learner is never told the noise.
LEARNER_SETTINGS = {"realcam": {"mirror_hypotheses": True}, "flips30": {"mirror_hypotheses": True}}
#: A flip's mirror image is nearer the true orientation than the observation by more than this many noise RMS.
FLIP_MARGIN = 3.0
VARIANTS = tuple(NOISE_LEVELS)
#: Levels whose faults must be detected (harsh: reported only).
DETECTING = ("camera", "realcam", "paper")
N_HEALTHY, N_CHANGED = 400, 200
QUICK_HEALTHY, QUICK_CHANGED, QUICK_MAX_JOINTS = 150, 60, 5
VISIBILITY = 0.85

FIGURES = {
    "zoo_exceptions": "exceptions raised by the learner's update, over every run and level (the step is skipped)",
    **{f"zoo_true_tree_fraction_{v}": f"{v}: fraction of runs whose body scheme after the {N_HEALTHY} healthy steps "
                                      "is the true tree" for v in VARIANTS},
    "zoo_silent_wrong_trees": "runs whose body scheme is wrong (after the healthy steps, or at the end against the "
                              "changed body) and that the learner does not flag as not trusted",
    **{f"zoo_false_alarms_per_1000_steps_{v}": f"{v}: mismatch_detected events on correct edges during the healthy "
                                               "steps, per 1000 healthy steps" for v in VARIANTS},
    "zoo_fault_detected_fraction": f"fraction of runs at {', '.join(DETECTING)} whose change is detected within "
                                   f"{N_CHANGED} steps",
    "zoo_fault_detection_steps_median": f"median over the detected changes at {', '.join(DETECTING)}: steps from "
                                        "the change to its detection (1: the first changed sample)",
    "zoo_fault_detected_fraction_harsh": "the same at harsh (reported)",
    "zoo_fault_repaired_fraction": f"fraction of detected changes at {', '.join(DETECTING)} after which the body "
                                   "scheme predicts every part within the noise RMS at the end",
    **{f"zoo_pred_err_over_noise_{v}": f"{v}: median over runs of the mean position error of every part (root "
                                       "excepted) over 100 random commands after the healthy steps, over the noise's "
                                       "3D RMS" for v in VARIANTS},
    "zoo_noise_estimate_rel_err": "median over runs and levels of the larger relative error of the learner's "
                                  "position and orientation noise estimates (3D RMS) after the healthy steps",
    "zoo_false_flip_rejections": "true poses refused as flipped, over every run and level",
    "zoo_wrong_flip_corrections": "true poses taken in as their mirror image, over every run and level",
    **{f"zoo_flips_used_fraction_{v}": f"{v}: fraction of the flips of the healthy steps after bootstrapping that "
                                       "are taken in corrected" for v in ("realcam", "flips30")},
    "zoo_collateral_replacements": f"model_replaced events after a moved marker at {', '.join(DETECTING)} on edges "
                                   "that do not end at the moved marker",
}
PAPER = {}
TARGETS = {"zoo_exceptions": 0.0, "zoo_silent_wrong_trees": 0.0, "zoo_false_flip_rejections": 0.0,
           "zoo_wrong_flip_corrections": 0.0, "zoo_collateral_replacements": 0.0,
           **{f"zoo_false_alarms_per_1000_steps_{v}": 1.0 for v in DETECTING},
           "zoo_fault_detection_steps_median": 10.0, "zoo_noise_estimate_rel_err": 0.2}
MIN_TARGETS = {"zoo_true_tree_fraction_camera": 0.99, "zoo_true_tree_fraction_realcam": 0.97,
               "zoo_true_tree_fraction_paper": 0.95, "zoo_true_tree_fraction_harsh": 0.8,
               "zoo_fault_detected_fraction": 0.95, "zoo_true_tree_fraction_flips30": 0.95,
               "zoo_flips_used_fraction_flips30": 0.95}
SANITY = {"zoo_exceptions": (0, 0)}


def _robot(seed, quick):
    tree = _zoo_robot(seed)
    if quick and tree.n_actions > QUICK_MAX_JOINTS:
        tree = _zoo_robot(seed, n_joints=QUICK_MAX_JOINTS)
    return tree


def _blocked(fault):
    return {fault.params["action_index"]} if fault.kind == "block_joint" else set()


def _affected(tree, body, A):
    """Markers whose true pose the change moved at some of the commands ``A``."""
    before = Body(tree).true_marker_array(A)
    after = body.true_marker_array(A)
    moved = np.abs(after - before).max(axis=(0, 2, 3)) > 1e-6
    return {m for m, k in zip(tree.marker_ids, moved, strict=True) if k}


def _prediction_error(learner, tree, body, world2root, A):
    """Mean position error (m) of every part but the learner's root over commands ``A`` against ``body``."""
    if learner.body_scheme is None:
        return math.inf
    truth = body.true_marker_array(A)
    errors = []
    for k, a in enumerate(A):
        predicted = learner.predict(a)
        errors += [np.linalg.norm(predicted[p][:3, 3] - (world2root @ truth[k, c])[:3, 3])
                   for c, p in enumerate(tree.marker_ids) if p != learner.root]
    return float(np.mean(errors)) if errors else 0.0


def _noise_error(learner, level):
    """Larger relative error of the learner's 3D RMS noise estimates (position, orientation), NaN without one."""
    noise = getattr(learner, "noise", None)
    if noise is None:
        return math.nan
    trans, rot = noise.rms()
    return max(abs(trans - level["sigma_trans"]) / level["sigma_trans"],
               abs(rot - level["sigma_rot"]) / level["sigma_rot"])


def run(seed, perception="camera", quick=False):
    """One run of one noise level (``perception``: a key of :data:`NOISE_LEVELS`); see the module docstring."""
    if perception not in NOISE_LEVELS:
        raise ValueError(f"the zoo runs at the noise levels {VARIANTS}, got {perception!r}")
    level = NOISE_LEVELS[perception]
    tree = _robot(seed, quick)
    n_healthy, n_changed = (QUICK_HEALTHY, QUICK_CHANGED) if quick else (N_HEALTHY, N_CHANGED)
    rng = np.random.default_rng([seed, 7])
    kind = RANDOM_FAULTS[seed % len(RANDOM_FAULTS)]
    fault = random_fault(tree, kind, rng, 3.0 * level["sigma_trans"])
    session = make_session(tree, n_healthy + n_changed, seed, faults=[(n_healthy, fault)], visibility=VISIBILITY,
                           **level)
    changed = fault.apply(Body(tree), Body(tree))
    A_test = rng.uniform(tree.action_lower, tree.action_upper, (100, tree.n_actions))
    affected = _affected(tree, changed, A_test)
    config = BodySchemeConfig(**LEARNER_SETTINGS.get(perception, {}))
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, config, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    exceptions, false_alarms, repairs, detected_at, collateral = 0, 0, 0, None, 0
    flips = FlipTally(FLIP_MARGIN * level["sigma_rot"])
    errors = []
    start = time.process_time()
    result = {}
    for t in range(session.n_steps):
        if t == n_healthy:
            result.update(_snapshot(learner, tree, Body(tree), session.world2root, A_test, level, set()))
        scheme = learner.body_scheme
        counted = t < n_healthy and learner.phase != "bootstrapping"
        corrected = learner.corrected["flipped"]
        try:
            events = learner.update(session.actions[t], session.observations[t])
        except Exception as error:  # counted: the zoo's first figure
            exceptions += 1
            errors.append(f"{t}: {type(error).__name__}: {error}")
            continue
        flips.add(session.true_poses[t], tree.marker_ids, session.observations[t],
                  learner.samples()[1][-1] if learner.corrected["flipped"] > corrected else {},
                  {e.child for e in events if e.kind == "input_rejected" and "(flipped)" in e.reason}, counted)
        for event in events:
            if event.kind == "model_replaced" and t >= n_healthy and kind == "move_marker":
                collateral += int(not {event.parent, event.child} & affected)
            if event.kind != "mismatch_detected":
                continue
            model = next((m for m in scheme.models if {m.parent, m.child} == {event.parent, event.child}), None)
            if t < n_healthy:
                if model is not None and is_correct_model(tree, model):
                    false_alarms += 1
                else:
                    repairs += 1
            elif detected_at is None and {event.parent, event.child} & affected:
                detected_at = t - n_healthy + 1
    end = _snapshot(learner, tree, changed, session.world2root, A_test, level, _blocked(fault))
    return {**{f"healthy_{k}": v for k, v in result.items()}, **{f"end_{k}": v for k, v in end.items()},
            "variant": perception, "seed": seed, "n_actions": tree.n_actions, "n_markers": len(tree.marker_ids),
            "fault": fault.entry, "fault_kind": kind, "affected": sorted(affected), "exceptions": exceptions,
            "exception_texts": errors[:5], "false_alarms": false_alarms, "repairs": repairs,
            "healthy_steps": n_healthy, "detected_at": detected_at, "collateral": collateral, **flips.counts(),
            "cpu_seconds": time.process_time() - start,
            "curves": {}, "events": []}


class FlipTally:
    """The learner's flip decisions judged against the true poses (see the module docstring); ``threshold`` (rad):
    how much nearer the true orientation a flip's mirror image is."""

    def __init__(self, threshold):
        self.threshold = threshold
        self.flips = self.flips_used = self.wrong_corrections = self.false_rejections = 0

    def add(self, world2marker, marker_ids, observed, taken, refused, counted):
        """One step: true poses ``world2marker`` (k, 4, 4) of ``marker_ids``, the ``observed`` poses, the poses the
        learner ``taken`` in (only needed when it corrected some), the parts it ``refused`` as flipped; flips are
        counted (``flips``, ``flips_used``) only where ``counted``."""
        parts = [p for p in marker_ids if p in observed]
        if not parts:
            return
        index = {p: c for c, p in enumerate(marker_ids)}
        truth = np.stack([world2marker[index[p]] for p in parts])
        seen = np.stack([np.asarray(observed[p], dtype=float) for p in parts])
        gain = rotational_error(truth, seen) - rotational_error(truth, mirror_about_ray(seen))
        for p, g, obs in zip(parts, gain, seen, strict=True):
            flip, true = g > self.threshold, g < -self.threshold
            corrected = p in taken and not np.array_equal(taken[p], obs)
            self.wrong_corrections += int(corrected and true)
            self.false_rejections += int(p in refused and true)
            if counted and flip:
                self.flips += 1
                self.flips_used += int(corrected)

    def counts(self):
        """The tallies, for a run's result."""
        return {"flips": self.flips, "flips_used": self.flips_used, "wrong_flip_corrections": self.wrong_corrections,
                "false_flip_rejections": self.false_rejections}


def _snapshot(learner, tree, body, world2root, A_test, level, blocked):
    true = is_true_tree(tree, learner.body_scheme, blocked)
    trusted = bool(getattr(learner, "trusted", learner.body_scheme is not None))
    return {"true_tree": true, "trusted": trusted,
            "pred_err_over_noise": _prediction_error(learner, tree, body, world2root, A_test) / level["sigma_trans"],
            "noise_rel_err": _noise_error(learner, level), "phase": learner.phase}


def summarize(runs):
    """The zoo's figures from its runs (every level): fractions, rates and medians as defined in :data:`FIGURES`."""
    out = {"zoo_exceptions": float(sum(r["exceptions"] for r in runs))}
    silent = 0
    for r in runs:
        silent += int((not r["healthy_true_tree"] and r["healthy_trusted"])
                      or (not r["end_true_tree"] and r["end_trusted"]))
    out["zoo_silent_wrong_trees"] = float(silent)
    for v in VARIANTS:
        rs = [r for r in runs if r["variant"] == v]
        if not rs:
            continue
        out[f"zoo_true_tree_fraction_{v}"] = float(np.mean([r["healthy_true_tree"] for r in rs]))
        out[f"zoo_false_alarms_per_1000_steps_{v}"] = (1000.0 * sum(r["false_alarms"] for r in rs)
                                                       / sum(r["healthy_steps"] for r in rs))
        out[f"zoo_pred_err_over_noise_{v}"] = float(np.median([r["healthy_pred_err_over_noise"] for r in rs]))
    detecting = [r for r in runs if r["variant"] in DETECTING]
    if detecting:
        found = [r for r in detecting if r["detected_at"] is not None]
        out["zoo_fault_detected_fraction"] = len(found) / len(detecting)
        out["zoo_fault_detection_steps_median"] = (float(np.median([r["detected_at"] for r in found])) if found
                                                   else math.nan)
        out["zoo_fault_repaired_fraction"] = (float(np.mean([r["end_pred_err_over_noise"] < 1.0 for r in found]))
                                              if found else math.nan)
    harsh = [r for r in runs if r["variant"] == "harsh"]
    if harsh:
        out["zoo_fault_detected_fraction_harsh"] = float(np.mean([r["detected_at"] is not None for r in harsh]))
    for key in ("false_flip_rejections", "wrong_flip_corrections"):
        if all(key in r for r in runs):
            out[f"zoo_{key}"] = float(sum(r[key] for r in runs))
    for v in ("realcam", "flips30"):
        rs = [r for r in runs if r["variant"] == v and "flips" in r]
        if rs and sum(r["flips"] for r in rs):
            out[f"zoo_flips_used_fraction_{v}"] = sum(r["flips_used"] for r in rs) / sum(r["flips"] for r in rs)
    moved = [r for r in detecting if r["fault_kind"] == "move_marker" and "collateral" in r]
    if moved:
        out["zoo_collateral_replacements"] = float(sum(r["collateral"] for r in moved))
    noise = [r["healthy_noise_rel_err"] for r in runs if math.isfinite(r["healthy_noise_rel_err"])]
    out["zoo_noise_estimate_rel_err"] = float(np.median(noise)) if noise else math.nan
    return out


#: The per-run fields :func:`plot` writes to ``zoo_runs.json`` beside the plot (which seeds and levels went wrong).
RUN_FIELDS = ("seed", "variant", "n_actions", "n_markers", "fault_kind", "exceptions", "false_alarms", "repairs",
              "detected_at", "collateral", "flips", "flips_used", "wrong_flip_corrections", "false_flip_rejections",
              "healthy_true_tree", "healthy_trusted", "end_true_tree", "end_trusted",
              "healthy_pred_err_over_noise", "healthy_noise_rel_err", "cpu_seconds")


def plot(runs, path_prefix):
    """Per level: true-tree fraction and false alarms; detection delays by change; prediction error over noise. The
    runs' :data:`RUN_FIELDS` go to ``zoo_runs.json`` beside the plot."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = [{k: r.get(k) for k in RUN_FIELDS} for r in sorted(runs, key=lambda r: (r["seed"], r["variant"]))]
    path_prefix.with_name(path_prefix.name + "_runs.json").write_text(json.dumps(table, indent=0) + "\n")
    summary = summarize(runs)
    levels = [v for v in VARIANTS if f"zoo_true_tree_fraction_{v}" in summary]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    x = np.arange(len(levels))
    axes[0].bar(x - 0.2, [summary[f"zoo_true_tree_fraction_{v}"] for v in levels], 0.4, label="true tree")
    axes[0].bar(x + 0.2, [np.mean([r["healthy_trusted"] for r in runs if r["variant"] == v]) for v in levels], 0.4,
                label="trusted")
    axes[0].set_xticks(x, levels)
    axes[0].set_ylim(0, 1.05)
    axes[0].set_title(f"after {N_HEALTHY} healthy steps")
    axes[0].legend(loc="lower left")
    for k, kind in enumerate(RANDOM_FAULTS):
        delays = [r["detected_at"] for r in runs if r["fault_kind"] == kind and r["detected_at"] is not None]
        axes[1].scatter(np.full(len(delays), k) + np.random.default_rng(k).uniform(-0.2, 0.2, len(delays)), delays,
                        s=10)
    axes[1].set_xticks(range(len(RANDOM_FAULTS)), RANDOM_FAULTS)
    axes[1].set_ylabel("steps to detection")
    axes[1].set_title("changes")
    for k, v in enumerate(levels):
        values = [r["healthy_pred_err_over_noise"] for r in runs if r["variant"] == v]
        axes[2].scatter(np.full(len(values), k), values, s=10)
    axes[2].set_yscale("log")
    axes[2].set_xticks(x, levels)
    axes[2].set_ylabel("prediction error / noise RMS")
    axes[2].set_title("all parts, after the healthy steps")
    fig.tight_layout()
    path = path_prefix.with_name(path_prefix.name + ".png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]
