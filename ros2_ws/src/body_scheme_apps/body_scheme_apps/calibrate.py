"""``calibrate``: the learned body scheme as URDF, and its calibration report against the robot's specification.

    python -m body_scheme_apps.calibrate --state STATE.json --joint-names j1,j2,... [--urdf NOMINAL.urdf
        --markers NOMINAL.markers.yaml] [--prefix robot1/] --out DIR
    python -m body_scheme_apps.calibrate --simulate ROBOT [--markers FILE] [--camera auto | "x y z r p y"]
        [--package-path DIR] [--perception rendered | noise] [--steps 600] --out DIR

``--state`` reads a state saved by scheme_node (``~/save``, checkpoints) or the core (``save_state``); ``--simulate``
learns one first from a babbling session in the simulator and compares it with the robot's specification. ``ROBOT``
is a shipped robot's name or any URDF path: its markers come from ``--markers``, else ``<stem>.markers.yaml`` beside
the URDF, else they are planned (:func:`body_scheme_sim.planning.plan_markers`, written to ``DIR/markers.yaml`` with
the camera they were planned for, ``DIR/camera.yaml``). The camera is ``--camera``; by default the one the markers
were planned for (``camera.yaml`` beside them), else the simulator's camera for a shipped robot and ``auto`` for a
URDF (framing every marker). ``rendered`` perception (the default) runs our ArUco tracker on the simulator's images;
``noise`` draws observations at the rendered tracker's accuracy (10 mm, 5 deg). ``--simulate`` first names the
markers the camera had in view but the tracker seldom took (:func:`seldom_taken`). Writes to ``DIR``:

- ``learned.urdf``: :func:`body_scheme_core.prediction.learned_body.learned_urdf` (limits: the trained range);
- with a nominal robot: ``report.txt``, ``report.json`` (per joint ``axis_deg``, ``origin_mm``, ``marker_mm``,
  ``marker_deg``; ``max_*``) and ``report.png`` (the learned body against the nominal one at zero actions, and the
  deviations per joint);
- ``accuracy.txt``, ``accuracy.json`` and ``accuracy.png``: how accurate it is on poses no fit saw
  (:func:`body_scheme_core.calibration.accuracy_report` on the learner's history window): the 5-fold
  cross-validated prediction error of every observed part (mm, deg; it includes the sensor's own noise), the same
  for the nominal robot when one is given (its root pose fitted per fold), each joint's standard deviation (the
  jackknife over the folds' refits: axis deg, origin mm), and the held-out error against the number of poses;
- with the robot's URDF (``--urdf``, or the simulated robot's): ``calibrated.urdf``, the robot's own file with the
  learned joint axes (a drop-in replacement: its links, names, meshes and limits, each learned joint's ``<origin>``
  moved onto its learned axis; :func:`body_scheme_core.prediction.calibrated_urdf`), ``calibrated_diff.txt`` (per
  joint: how far its origin moved, mm and deg, and its axis) and ``calibrated.markers.yaml`` (the markers' learned
  places on those links);
- with ``--repeat-state`` (a second session's state of the same robot): ``repeatability.json``, the two learned
  bodies' difference at every joint (axis deg, origin mm), as :func:`~body_scheme_core.prediction.calibration_report`
  compares a body with its specification.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
from tqdm import tqdm

from body_scheme_core.calibration import accuracy_report
from body_scheme_core.errors import BodySchemeError
from body_scheme_core.learning import load_state
from body_scheme_core.prediction import (
    calibrated_urdf,
    calibration_report,
    format_diff,
    format_report,
    learned_tree,
    learned_urdf,
)
from body_scheme_core.world import Marker, is_true_tree, load_markers_yaml, markers_to_yaml, tree_from_urdf

from .entry import command
from .robot_option import add_camera_arguments, resolve_robot

__all__ = ["calibrate", "learned_accuracy", "format_accuracy", "plot_accuracy", "plot_report", "seldom_taken",
           "verdict", "main"]

#: Folds of the cross-validation.
FOLDS = 5
#: ``--simulate`` names each marker the tracker took in fewer than this fraction of the pictures that had it in view.
SELDOM_TAKEN = 0.5


def calibrate(learner, joint_names, out, nominal=None, prefix="", repeat=None, urdf_text=None):
    """Write ``learned.urdf``, the accuracy files (and, given the nominal ``KinematicTree``, the report files; with
    its ``urdf_text`` too, the calibrated URDF; given a second session's learner ``repeat``, ``repeatability.json``)
    to ``out``; returns the report (or None)."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scheme = learner.body_scheme
    if scheme is None:
        raise BodySchemeError(f"the state has no body scheme yet ({learner.phase}, step {learner.step})")
    body = learned_tree(scheme, joint_names, *learner.trained_range(), prefix=prefix, nominal=nominal)
    (out / "learned.urdf").write_text(learned_urdf(body))
    if len(learner.samples()[0]) >= 2 * FOLDS:
        accuracy = learned_accuracy(learner, joint_names, nominal)
        (out / "accuracy.json").write_text(json.dumps(accuracy, indent=2, allow_nan=False) + "\n")
        (out / "accuracy.txt").write_text(format_accuracy(accuracy))
        plot_accuracy(accuracy, out / "accuracy.png")
    else:
        (out / "accuracy.txt").write_text(f"no accuracy report: {len(learner.samples()[0])} poses in the learner's "
                                          f"history, cross-validation needs at least {2 * FOLDS}\n")
    if repeat is not None:
        if repeat.body_scheme is None:
            raise BodySchemeError("the second session's state (--repeat-state) has no body scheme yet")
        other = learned_tree(repeat.body_scheme, joint_names, *repeat.trained_range())
        (out / "repeatability.json").write_text(json.dumps(calibration_report(other, body.tree), indent=2) + "\n")
    if nominal is None:
        return None
    if urdf_text is not None:
        calibrated = calibrated_urdf(urdf_text, body, nominal, scheme.root)
        (out / "calibrated.urdf").write_text(calibrated.text)
        (out / "calibrated_diff.txt").write_text(format_diff(calibrated))
        (out / "calibrated.markers.yaml").write_text(markers_to_yaml(
            [Marker(part, link, place) for part, (link, place) in calibrated.markers.items()]))
    report = calibration_report(body, nominal)
    (out / "report.txt").write_text(format_report(report) + "\n")
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    plot_report(body, nominal, report, out / "report.png")
    return report


def learned_accuracy(learner, joint_names, nominal=None):
    """:func:`~body_scheme_core.calibration.accuracy_report` of the learner's body scheme on its history window."""
    actions, observations = learner.samples()
    if len(actions) < 2 * FOLDS:
        raise BodySchemeError(f"{len(actions)} poses in the learner's history: cross-validation needs at least "
                              f"{2 * FOLDS}")
    return accuracy_report(learner.body_scheme, learner.root_pose, actions, observations, learner.noise.sigma_trans,
                           learner.noise.sigma_rot, joint_names, *learner.trained_range(), nominal=nominal,
                           folds=FOLDS, axis_sigmas=learner.noise.axis_sigmas)


def format_accuracy(accuracy):
    """The accuracy report as text: one line per part, the nominal robot's, each joint's std, the curve."""
    lines = [f"held-out prediction error, {accuracy['folds']}-fold cross-validation over {accuracy['n_poses']} poses "
             f"(includes the sensor's noise):"]
    for part, figures in accuracy["cv"].items():
        nominal = (accuracy["nominal_cv"] or {}).get(part)
        spec = f"   nominal robot: mean {nominal['mean_mm']:.2f} mm" if nominal else ""
        lines.append(f"  part {part:>4s}: mean {figures['mean_mm']:.2f} mm, rms {figures['rms_mm']:.2f} mm, "
                     f"95 % {figures['p95_mm']:.2f} mm, {figures['mean_deg']:.2f} deg over {figures['n']}{spec}")
    lines.append("parameter standard deviation per joint (jackknife over the folds):")
    for row in accuracy["joint_std"]:
        origin = "-" if row["origin_mm"] is None else f"{row['origin_mm']:.2f} mm"
        lines.append(f"  {row['joint']:24s} axis {row['axis_deg']:.3f} deg, origin {origin}")
    lines.append("held-out error against the number of poses: " + ", ".join(
        f"{point['poses']}: {point['cv_mm']:.2f} mm" for point in accuracy["curve"]))
    return "\n".join(lines) + "\n"


def plot_accuracy(accuracy, path):
    """The held-out error against the number of poses (and the nominal robot's, dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    curve = accuracy["curve"]
    ax.plot([p["poses"] for p in curve], [p["cv_mm"] for p in curve], "o-", label="learned, refitted per fold")
    if accuracy["nominal_cv_mm"] is not None:
        ax.axhline(accuracy["nominal_cv_mm"], color="0.5", ls="--", label="nominal robot (all poses)")
    ax.set_xscale("log")
    ax.set_xlabel("poses")
    ax.set_ylabel(f"{accuracy['folds']}-fold held-out error (mm)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_report(body, nominal, report, path):
    """The learned body (colour) against the nominal one (grey) in a bent configuration (half of each joint's upper
    limit), in the root marker's frame, with the learned joint axes; and the per-joint deviations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bent = 0.5 * np.nan_to_num(np.asarray(nominal.action_upper, dtype=float))
    learned = body.marker_poses(bent[:body.n_actions])
    specified = nominal.marker_poses(bent)
    root = min(learned, key=lambda p: np.linalg.norm(learned[p][:3, 3]))
    to_root = np.linalg.inv(specified[root])
    truth = {p: to_root @ T for p, T in specified.items() if p in learned}
    fig = plt.figure(figsize=(11, 4.8))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for joint in body.joints:
        for poses, style in ((truth, dict(color="0.6", lw=5, alpha=0.6)), (learned, dict(color="tab:blue", lw=2))):
            a, b = poses[joint.parent][:3, 3], poses[joint.child][:3, 3]
            ax.plot(*zip(a, b, strict=True), **style)
        if joint.type == "revolute":
            point = learned[joint.parent] @ np.append(joint.point, 1.0)
            axis = learned[joint.parent][:3, :3] @ np.asarray(joint.axis)
            ax.quiver(*point[:3], *(0.12 * axis), color="tab:red")
    for p, T in learned.items():
        ax.text(*T[:3, 3], f" {p}", fontsize=8)
    ax.set_title("learned (blue, red: joint axes) vs specification (grey)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_box_aspect((1, 1, 1))
    span = max(np.ptp([T[:3, 3] for T in truth.values()], axis=0).max(), 0.2)
    centre = np.mean([T[:3, 3] for T in truth.values()], axis=0)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        setter(c - span / 2, c + span / 2)
    bars = fig.add_subplot(1, 2, 2)
    rows = report["joints"]
    x = np.arange(len(rows))
    bars.bar(x - 0.2, [r["axis_deg"] for r in rows], 0.4, label="axis (deg)")
    bars.bar(x + 0.2, [r["origin_mm"] or 0.0 for r in rows], 0.4, label="origin (mm)")
    bars.set_xticks(x, [r["nominal_joint"] for r in rows], rotation=30)
    bars.axhline(2.0, color="tab:blue", ls=":", lw=1)
    bars.axhline(5.0, color="tab:orange", ls=":", lw=1)
    bars.set_title("deviation from the specification per joint")
    bars.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _urdf_text(robot):
    """The URDF text of a shipped robot's name or a URDF path."""
    from body_scheme_sim.robots import robot_files

    return pathlib.Path(robot_files(robot, require_markers=False)[0]).read_text()


def _simulated(choice, steps, seed, perception="rendered"):
    """A learner taught by a babbling session in the simulator (:class:`~body_scheme_apps.robot_option.RobotChoice`),
    and the robot's nominal tree."""
    from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
    from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS, record_session

    nominal = choice.tree
    with tqdm(total=steps, desc="babbling in the simulator", unit="step", disable=not sys.stderr.isatty()) as bar:
        session = record_session(choice.robot, n_steps=steps, seed=seed, sigma_trans=RENDERED_SIGMA_TRANS,
                                 sigma_rot=RENDERED_SIGMA_ROT, perception=perception, camera=choice.camera,
                                 markers_path=choice.markers_path, package_path=choice.package_path,
                                 progress=lambda done: bar.update(done - bar.n))
    # The noise priors of the tracker on rendered images (as live_demo): its errors are heavy-tailed, and the
    # default "auto" prior, replaced by the first robust estimate, makes the thresholds too tight for them.
    config = BodySchemeConfig(sigma_trans=RENDERED_SIGMA_TRANS, sigma_rot=RENDERED_SIGMA_ROT)
    learner = BodySchemeLearner(nominal.marker_ids, nominal.n_actions, config, action_lower=nominal.action_lower,
                                action_upper=nominal.action_upper)
    pairs = zip(session.actions, session.observations, strict=True)
    for actions, observations in tqdm(pairs, total=len(session.actions), desc="learning", unit="step",
                                      disable=not sys.stderr.isatty()):
        learner.update(actions, observations)
    return learner, nominal, seldom_taken(session, nominal)


def seldom_taken(session, nominal):
    """Lines naming the markers that the camera had in view (``session.visible_truth``: in the image, facing it,
    large enough, not hidden) but the tracker took in fewer than :data:`SELDOM_TAKEN` of those pictures, with the
    session's refusals by kind; none if every marker was taken. A marker the learner never gets leaves its part
    unconnected: the Panda's base marker, seen square-on and small, was refused as ambiguous in nearly every
    picture (docs/your-robot.md)."""
    if session.visible_truth is None:  # a session that does not know what the camera had in view
        return []
    in_view, taken = session.visible_truth.sum(axis=0), session.visible.sum(axis=0)
    lines = [f"marker {marker_id} on {nominal.marker(marker_id).link}: in view in {in_view[k]} of {session.n_steps} "
             f"pictures, taken by the tracker in {taken[k]}" for k, marker_id in enumerate(session.marker_ids)
             if in_view[k] and taken[k] < SELDOM_TAKEN * in_view[k]]
    if lines and session.tracker_rejected:
        refused = ", ".join(f"{kind} {count}" for kind, count in sorted(session.tracker_rejected.items()))
        lines.append(f"the tracker refused (all markers): {refused}; a bigger marker, a closer camera or a marker "
                     f"tilted further from the line of sight helps (docs/your-robot.md)")
    return lines


@command
def main(argv=None):
    """Console entry point; exit code 1 with a one-line error for unreadable input."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.calibrate", description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--state", help="learner state file (scheme_node ~/save or checkpoint)")
    source.add_argument("--simulate", metavar="ROBOT", help="learn from the simulator first: a shipped robot's name "
                                                             "or a URDF path")
    parser.add_argument("--joint-names", help="comma-separated joint names in action order (default: the nominal "
                                              "URDF's, else joint_0, joint_1, ...)")
    parser.add_argument("--urdf", help="nominal URDF of the robot (with --markers): write the calibration report")
    parser.add_argument("--markers", help="nominal marker placement YAML (with --simulate: the markers to simulate; "
                                          "default: beside the URDF, else planned into --out)")
    parser.add_argument("--prefix", default="", help="prefix of link names (joints keep the robot's)")
    parser.add_argument("--steps", type=int, default=600, help="--simulate: babbling steps (default: %(default)s)")
    add_camera_arguments(parser, prefix="--simulate: ")
    parser.add_argument("--perception", choices=("rendered", "noise"), default="rendered",
                        help="--simulate: our tracker on rendered images, or noise at its accuracy "
                             "(default: %(default)s)")
    parser.add_argument("--repeat-state", help="a second session's learner state of the same robot: write "
                                               "repeatability.json (the two learned bodies' difference per joint)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output directory")
    args = parser.parse_args(argv)
    try:
        if args.simulate:
            choice = resolve_robot(args.simulate, args.markers, args.camera, args.package_path,
                                   pathlib.Path(args.out) / "markers.yaml", args.seed)
            learner, nominal, sightings = _simulated(choice, args.steps, args.seed, args.perception)
            for line in sightings:
                print(line)
            urdf_text = _urdf_text(choice.robot)
        else:
            learner = load_state(args.state)
            nominal = urdf_text = None
            if args.urdf or args.markers:
                if not (args.urdf and args.markers):
                    parser.error("--urdf and --markers go together")
                urdf_text = pathlib.Path(args.urdf).read_bytes().decode("utf-8", errors="replace")
                nominal = tree_from_urdf(urdf_text, load_markers_yaml(args.markers))
        names = (args.joint_names.split(",") if args.joint_names else
                 list(nominal.action_joint_names) if nominal is not None else
                 [f"joint_{k}" for k in range(learner.n_actions)])
        repeat = load_state(args.repeat_state) if args.repeat_state else None
        report = calibrate(learner, names, args.out, nominal, args.prefix, repeat, urdf_text)
    except (OSError, BodySchemeError) as error:
        print(f"calibrate: {error}", file=sys.stderr)
        return 1
    print(f"wrote {pathlib.Path(args.out) / 'learned.urdf'} and the accuracy report (accuracy.*)")
    print((pathlib.Path(args.out) / "accuracy.txt").read_text(), end="")
    if report is not None:
        print(format_report(report))
        print(f"max: axis {report['max_axis_deg']:.3f} deg, origin {report['max_origin_mm']:.2f} mm, marker "
              f"{report['max_marker_mm']:.2f} mm; wrote report.txt, report.json, report.png in {args.out}")
    if nominal is not None:
        print(verdict(learner, nominal, report, args.out))
    return 0


def verdict(learner, nominal, report, out):
    """One paragraph a user reads first: whether the learned body scheme is a true one of the robot (its edges
    model the right joints with no extra actions), which edges are not joints (GPs), the worst joint, and where the
    files are."""
    scheme = learner.body_scheme
    edges = "no body scheme" if scheme is None else f"{len(scheme.models)} edges"
    if is_true_tree(nominal, scheme):
        lines = [f"verdict: a true body scheme of the robot ({edges}, phase {learner.phase})"]
    else:
        lines = [f"verdict: NOT a true body scheme of the robot ({edges}, phase {learner.phase}): more commands, or "
                 f"markers the camera sees together more often (docs/your-robot.md)"]
    exported = [] if scheme is None else learned_tree(scheme, list(nominal.action_joint_names),
                                                      *learner.trained_range()).joints
    not_joints = [j for j in exported if j.type == "fixed" and j.model != "static"]
    if not_joints:
        lines.append(f"not joints: {len(not_joints)} of {len(scheme.models)} edges are no URDF joint "
                     f"({', '.join(f'{j.parent}->{j.child} ({j.model})' for j in not_joints)}): learned.urdf fixes "
                     f"them at mid-range and the report leaves them out. A GP edge: the observations of its part "
                     f"depend on the posture in a way no rigid joint explains (a tracker whose error changes with the "
                     f"viewing angle, or a joint that is not rigid)")
    rows = [] if report is None else report["joints"]
    if rows:
        axis = max(rows, key=lambda r: r["axis_deg"])
        text = f"worst joint: {axis['nominal_joint']} (axis {axis['axis_deg']:.2f} deg off)"
        placed = [r for r in rows if r["origin_mm"] is not None]  # a prismatic joint's axis has no origin
        if placed:
            origin = max(placed, key=lambda r: r["origin_mm"])
            text += f", {origin['nominal_joint']} (origin {origin['origin_mm']:.2f} mm off)"
        lines.append(text)
    lines.append(f"files: {pathlib.Path(out) / 'learned.urdf'} (drop-in URDF), accuracy.txt"
                 + (", report.txt / report.png" if report is not None else "") + f" in {out}")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
